"""``python -m bdpt_jit.cli``: the same as the ``bdpt-jit`` command."""

import sys

from . import main

sys.exit(main())
