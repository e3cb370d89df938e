import os
import sys

import mitsuba as mi

mi.set_variant('llvm_ad_rgb')

import bdpt_jit  # noqa: E402,F401  (registers the plugin)

sys.path.insert(0, os.path.dirname(__file__))
