"""Keeps the set of Mitsuba objects fixed while a render traces its kernels.

Dr.Jit 1.5.0 aborts the process ("invalid redefinition of function 'func_...'" from LLVM, then
SIGABRT) when one kernel holds the same callable body once as a single-target call and once as a
multi-target call: its table of a kernel's functions (``globals_map`` in drjit-core's eval.cpp)
keys a callable by its hash *and* by that kind, and both entries are then defined under the one
name ``func_<hash>``. A Mitsuba virtual call (``MediumPtr.get_majorant``, ``BSDFPtr.eval``, ...)
is single-target when its domain holds one live instance and multi-target when it holds more. So
a render whose trace records a virtual call, then sees an instance of that domain created or
freed, then records the same call again, aborts when the kernel is compiled (with an empty kernel
cache; a cached kernel is never compiled). Reproduced in a few lines: two homogeneous media, a
``get_majorant`` call through pointers to the first, the second deleted, the same call again,
``dr.eval`` (``docs/design.md``, "Traced kernels and the garbage collector").

Nothing in this package creates or frees such an object while tracing. Python's cyclic garbage
collector may: it runs at any allocation, in any thread, and frees whatever an earlier scene left
in a reference cycle (seen in the test suite, where an earlier test's scene with one medium was
collected during a render of a scene with one other medium). ``held`` therefore switches the
automatic collector off for the duration of a render (its trace and its kernels' evaluation) and
restores it after; objects freed by reference counting are unaffected, and cyclic garbage is
collected at the next collection after the render. (Not for longer: Dr.Jit's AD graph is freed
with the variables that hold it, and garbage kept across renders leaves stale edges in later
traversals.)
"""

import functools
import gc
from contextlib import contextmanager


@contextmanager
def collector_paused():
    """No automatic cyclic garbage collection inside the block (re-entrant: the state on entry
    is restored on exit)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def held(method):
    """Decorates an integrator method that traces and evaluates kernels: ``collector_paused``
    around the whole call."""
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with collector_paused():
            return method(*args, **kwargs)
    return wrapper
