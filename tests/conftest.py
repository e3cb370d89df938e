import contextlib
import os
import sys

import drjit as dr
import mitsuba as mi
import pytest

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


# renders of this many samples or more keep the whole pool: where the other worker compiles or
# waits, a second thread nearly halves them (1.8x), and side by side two threads each lose only
# 10% (docs/performance.md); the suite's small renders (16 x 16 pixels, up to 256 spp) take one
LARGE_RENDER = 1 << 18


def render_samples(scene, sensor=0, spp=0):
    """Samples of ``mi.render(scene, sensor=sensor, spp=spp)``: pixels times spp (0 where
    unknown)."""
    try:
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        size = sensor.film().crop_size()
        return int(size[0]) * int(size[1]) * int(spp or sensor.sampler().sample_count())
    except Exception:
        return 0


@contextlib.contextmanager
def threads(n):
    """Dr.Jit's pool at ``n`` threads inside, restored after. Only where no OpenEXR file is read
    or written: Mitsuba 3.9.1 waits forever on one with fewer than two threads
    (bdpt_jit.MIN_THREADS). The queue is synchronised on both sides: resizing the pool under
    launched kernels crashed the process."""
    before = dr.thread_count()
    dr.sync_thread()
    dr.set_thread_count(n)
    try:
        yield
    finally:
        dr.sync_thread()
        dr.set_thread_count(before)


def _with_threads(render, n):
    """``mi.render`` on ``n`` threads unless the render is large (a render reads or writes no
    OpenEXR file)."""
    def wrapped(scene, *args, **kwargs):
        sensor = args[1] if len(args) > 1 else kwargs.get('sensor', 0)
        spp = args[5] if len(args) > 5 else kwargs.get('spp', 0)
        if render_samples(scene, sensor, spp) >= LARGE_RENDER:
            return render(scene, *args, **kwargs)
        with threads(n):
            return render(scene, *args, **kwargs)
    wrapped.__wrapped__ = render
    return wrapped


def _on_share(fn, n):
    """``fn`` on ``n`` threads: for derivative passes, which launch kernels and read no file."""
    def wrapped(*args, **kwargs):
        with threads(n):
            return fn(*args, **kwargs)
    wrapped.__wrapped__ = fn
    return wrapped


_N = render_threads()
if _N is not None:
    mi.render = _with_threads(mi.render, _N)
    for _name in ('forward_to', 'forward_from', 'backward', 'backward_to', 'backward_from'):
        setattr(dr, _name, _on_share(getattr(dr, _name), _N))


# test files that never read or write an OpenEXR file (no scene, no Bitmap): their every test
# runs on the worker's share of the CPUs, not only its renders (many small kernels)
ONE_SHARE_FILES = {'test_mis_partition.py'}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    if _N is None or os.path.basename(str(item.fspath)) not in ONE_SHARE_FILES:
        yield
        return
    with threads(_N):
        yield


# The order in which pytest-xdist hands the test files to its workers (``--dist loadfile
# --no-loadscope-reorder``, scripts/test.sh): the longest first, so that the two workers end
# together (longest-processing-time-first scheduling). xdist's own order, by the number of tests
# in a file, gave the few-test, long files (test_beams.py: one 45-s test) to whichever worker
# was free near the end while the other waited. Files not listed (under 30 s each) follow, in
# collection order. By their cold seconds in one run (docs/performance.md, thirty-third session:
# a file's figure depends on what the other worker compiled before it).
HEAVY_FILES = ('test_gradients.py', 'test_media_agreement.py', 'test_lights.py', 'test_coverage.py',
               'test_media_render.py', 'test_variants.py', 'test_mis_partition.py', 'test_stability.py',
               'test_moments.py', 'test_light_cache.py', 'test_beams.py', 'test_specialisation.py',
               'test_compare.py', 'test_cluster.py', 'test_agreement.py', 'test_media_phase.py', 'test_fuzz.py',
               'test_offsets.py', 'test_cli.py')


def pytest_collection_modifyitems(config, items):
    rank = {name: k for k, name in enumerate(HEAVY_FILES)}
    items.sort(key=lambda item: rank.get(os.path.basename(str(item.fspath)), len(HEAVY_FILES)))
