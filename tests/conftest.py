import os
import sys

import drjit as dr
import mitsuba as mi

mi.set_variant('llvm_ad_rgb')

import bdpt_jit  # noqa: E402,F401  (registers the plugin)

sys.path.insert(0, os.path.dirname(__file__))


def render_threads():
    """Dr.Jit threads a render of this test process runs on: its share of the CPUs when
    pytest-xdist runs several workers, else None (Dr.Jit's own pool). Dr.Jit's pool threads
    wait for work by spinning, so two workers of two threads on two CPUs spend much of the
    machine waiting: two processes rendering small images side by side made 2.2x the renders
    a second with one thread each (docs/performance.md, thirty-second session)."""
    workers = int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)
    share = max(1, cpus // workers)
    return share if workers > 1 and share < dr.thread_count() else None


def _with_threads(render, n):
    """``mi.render`` on ``n`` threads, the pool restored after it: only around renders, since
    Mitsuba 3.9.1 waits forever on any OpenEXR file (scene loading, Bitmap) with fewer than two
    (bdpt_jit.MIN_THREADS), and a render reads or writes none. Dr.Jit's queue is synchronised
    on both sides: resizing the pool under launched kernels crashed the process."""
    def wrapped(*args, **kwargs):
        before = dr.thread_count()
        dr.sync_thread()            # (resizing the pool under queued kernels crashes)
        dr.set_thread_count(n)
        try:
            return render(*args, **kwargs)
        finally:
            dr.sync_thread()
            dr.set_thread_count(before)
    wrapped.__wrapped__ = render
    return wrapped


_N = render_threads()
if _N is not None:
    mi.render = _with_threads(mi.render, _N)
