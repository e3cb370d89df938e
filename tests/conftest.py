import gc
import os
import sys

import mitsuba as mi
import pytest

mi.set_variant('llvm_ad_rgb')

import bdpt_jit  # noqa: E402,F401  (registers the plugin)

sys.path.insert(0, os.path.dirname(__file__))


@pytest.fixture(autouse=True, scope='module')
def _no_collection_inside_a_module():
    """Python's cyclic garbage collector is off while a test module runs and collects between
    modules: a collection in the middle of a kernel's trace (in any thread, Mitsuba's own
    integrators' references included) may free an earlier test's Mitsuba object and abort the
    process in Dr.Jit 1.5.0 (bdpt_jit/jit_guard.py, which does the same for bdpt's renders)."""
    was = gc.isenabled()
    gc.disable()
    yield
    if was:
        gc.enable()
    gc.collect()
