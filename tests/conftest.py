import os
import sys

import mitsuba as mi
import pytest

mi.set_variant('llvm_ad_rgb')

import bdpt_jit  # noqa: E402,F401  (registers the plugin)

sys.path.insert(0, os.path.dirname(__file__))


def pytest_collection_modifyitems(config, items):
    """With pytest-xdist (scripts/test.sh runs two workers: while one compiles a kernel on one
    core, the other runs), the tests of one local Ray instance stay on one worker."""
    for item in items:
        if os.path.basename(str(item.fspath)) == 'test_cluster.py':
            item.add_marker(pytest.mark.xdist_group('ray'))
