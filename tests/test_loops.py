"""The walks' loops are recorded once (bdpt_jit/loops.py): a loop that learns its constant state
gives the loop's values, learns again where a constant starts to vary (discarding the
recording's side effects), and the renders keep their images and kernels."""

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from bdpt_jit import loops, transport
from helpers import scene_path


def toy_loop(label, step, buf, n=8):
    """Three iterations of x += step, y += 2 (x a literal 0 before the loop, so with step 0 it
    is constant), each adding 1 to every entry of ``buf`` (a side effect)."""
    x, y, i = dr.zeros(mi.Float, n), dr.arange(mi.Float, n), dr.zeros(mi.UInt32, n)

    def body(objects, state):
        i, x, y = state
        dr.scatter_add(buf, mi.Float(1.0), dr.arange(mi.UInt32, n))
        return objects, (i + 1, x + step, y + 2.0)

    _, (_, x, y) = loops.while_once(label, (), (i, x, y), lambda o, s: s[0] < 3, body)
    dr.eval(x, y, buf)
    return x.numpy(), y.numpy()


def test_a_constant_leaf_that_starts_to_vary_is_learnt_again():
    buf = dr.zeros(mi.Float, 8)
    x, y = toy_loop('test_toy_a', 0.0, buf)
    assert np.all(x == 0) and np.all(y == np.arange(8) + 6) and np.all(buf.numpy() == 3)
    key = next(k for k in loops._CONSTANT if k[0] == 'test_toy_a')
    assert (1,) in loops._CONSTANT[key]         # x learnt constant, kept out of the loop state
    # the same signature, but now x changes: the recording stops, is discarded, x is loop state
    x, y = toy_loop('test_toy_a', 1.5, buf)
    assert np.all(x == 4.5) and np.all(y == np.arange(8) + 6)
    assert np.all(buf.numpy() == 6)             # the stopped recording's side effects are gone
    assert (1,) not in loops._CONSTANT[key]
    x, _ = toy_loop('test_toy_a', 0.0, buf)     # constant again: learnt again
    assert np.all(x == 0) and np.all(buf.numpy() == 9) and (1,) in loops._CONSTANT[key]


def test_learning_again_leaves_no_frames_behind(monkeypatch):
    """A loop learnt again (while_once catches _Relearn and records once more) keeps nothing of
    the exception: its traceback holds the frames of the render that called the loop (its light
    store, its context) in a reference cycle that only Python's garbage collector frees. Left
    behind, a render's first recording kept that memory until a collection, and the next render
    allocated fresh memory: technique auto's second timing of a trial took up to 2.5 times its
    first (docs/light-cache.md, thirty-third session). Planted: the exception kept, frames found."""
    import gc
    monkeypatch.setattr(loops, '_CONSTANT', {})        # every loop learnt afresh
    scene = mi.load_file(scene_path('cornell-box.xml'), res=8, max_depth=3)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 3})
    relearnt = []
    record = loops._record

    def counted(key, *args):
        try:
            return record(key, *args)
        except RuntimeError:
            relearnt.append(key[0])
            raise
    monkeypatch.setattr(loops, '_record', counted)
    gc.collect()
    was = gc.get_debug()
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        integ.render(scene, scene.sensors()[0], seed=0, spp=1)
        gc.collect()
        frames = [o.f_code.co_name for o in gc.garbage if type(o).__name__ == 'frame']
    finally:
        gc.set_debug(was)
        gc.garbage.clear()
    assert relearnt, 'no loop was learnt again: the test needs one'
    assert not frames, frames


def test_a_state_the_loop_cannot_walk_is_loop_state_whole():
    buf = dr.zeros(mi.Float, 4)
    state = ([dr.zeros(mi.Float, 4)], dr.zeros(mi.UInt32, 4))     # a list: not walked

    def body(objects, s):
        dr.scatter_add(buf, mi.Float(1.0), dr.arange(mi.UInt32, 4))
        return objects, ([s[0][0] + 1.0], s[1] + 1)

    _, (xs, i) = loops.while_once('test_toy_b', (), state, lambda o, s: s[1] < 2, body)
    dr.eval(xs[0], buf)
    assert np.all(xs[0].numpy() == 2) and np.all(buf.numpy() == 2)
    assert not any(k[0] == 'test_toy_b' for k in loops._CONSTANT)


def test_structs_keep_their_types():
    """The body gets the state's own types back (a Mitsuba struct, its Point3f), with a
    constant struct field (a literal direction) kept out of the loop state."""
    n = 4
    ray = dr.zeros(mi.Ray3f, n)
    ray.d = mi.Vector3f(0, 0, 1)

    def body(objects, s):
        r, count = s
        assert isinstance(r, mi.Ray3f) and isinstance(r.o, mi.Point3f)
        r = mi.Ray3f(r)
        r.o = r.o + r.d
        return objects, (r, count + 1)

    for _ in range(2):                      # the second with the constants learnt
        _, (r, count) = loops.while_once('test_toy_c', (), (ray, dr.zeros(mi.UInt32, n)), lambda o, s: s[1] < 3, body)
        dr.eval(r.o, count)
        assert np.all(r.o.z.numpy() == 3) and np.all(r.o.x.numpy() == 0) and np.all(count.numpy() == 3)
    key = next(k for k in loops._CONSTANT if k[0] == 'test_toy_c')
    assert (0, 'd', 2) in loops._CONSTANT[key] and (0, 'o', 2) not in loops._CONSTANT[key]


def count_bodies():
    """Patch dr.while_loop to count the body recordings per loop label: (the counts, undo)."""
    orig, counts = dr.while_loop, {}

    def counting(state, cond, body, label=None, **kw):
        def counted(*s):
            counts[label] = counts.get(label, 0) + 1
            return body(*s)
        return orig(state, cond, counted, label=label, **kw)
    dr.while_loop = counting
    return counts, lambda: setattr(dr, 'while_loop', orig)


CASES = [('caustic.xml', 'pt'), ('caustic.xml', 'lt'), ('caustic.xml', 'bdpt'), ('caustic.xml', 'vcm'),
         ('media/fog.xml', 'bdpt')]


@pytest.mark.parametrize('name,technique', CASES)
def test_walks_recorded_once_same_image(name, technique):
    """The images with the loops recorded once equal dr.while_loop's to rounding (same seed);
    after the first render each walk's body is recorded once."""
    scene = mi.load_file(scene_path(name), res=16, max_depth=5)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': technique})
    images = {}
    for once in (False, True):
        loops.ONCE = once
        try:
            images[once] = np.array(mi.render(scene, integrator=integ, spp=4, seed=5))
        finally:
            loops.ONCE = True
    np.testing.assert_allclose(images[True], images[False], rtol=1e-4, atol=1e-5 * images[False].max())
    counts, undo = count_bodies()
    try:
        np.array(mi.render(scene, integrator=integ, spp=4, seed=6))
    finally:
        undo()
    walks = {k: v for k, v in counts.items() if k in ('bdpt_camera_subpath', 'bdpt_light_subpath')}
    assert walks and all(v == 1 for v in walks.values()), counts


@pytest.mark.parametrize('name,technique,aovs', [('cornell-box.xml', 'pt', 'dd:depth,nn:sh_normal'),
                                                  ('caustic.xml', 'vcm', ''), ('veach-mis.xml', 'bdpt', '')])
def test_pending_hits_same_image(name, technique, aovs):
    """Camera walks that carry their next hit as a transport.PendingHit (its interaction and MIS
    event computed at the next step) render the image, AOVs included, of walks that carry whole
    interactions (same seed; a pending hit whose MIS event were dropped or taken from the wrong
    point would change the weights)."""
    scene = mi.load_file(scene_path(name), res=16, max_depth=5)
    props = {'type': 'bdpt', 'max_depth': 5, 'technique': technique}
    if aovs:
        props['aovs'] = aovs
    images = {}
    for pending in (False, True):
        transport.PENDING_HITS = pending
        try:
            images[pending] = np.array(mi.render(scene, integrator=mi.load_dict(props), spp=4, seed=5))
        finally:
            transport.PENDING_HITS = True
    assert np.all(np.isfinite(images[True]))
    np.testing.assert_allclose(images[True], images[False], rtol=1e-5, atol=1e-6 * images[False].max())


def loop_sizes(scene, integ, capfd):
    """{label: state variables} of the walks as Dr.Jit creates them in a render (after a warm-up
    render), from its log."""
    np.array(mi.render(scene, integrator=integ, spp=1, seed=0))
    capfd.readouterr()
    level = dr.log_level()
    dr.set_log_level(dr.LogLevel.InfoSym)
    try:
        np.array(mi.render(scene, integrator=integ, spp=1, seed=1))
    finally:
        dr.set_log_level(level)
    log = capfd.readouterr()         # (Dr.Jit's log reaches Python's stdout under pytest)
    found = re.findall(r'created a loop \("(\w+)"\) with (\d+)/\d+ state variables', log.out + log.err)
    return {label: int(n) for label, n in found if label.endswith('_subpath')}


@pytest.mark.parametrize('technique', ['pt', 'bdpt', 'vcm'])
def test_walks_carry_no_more_state_than_dr_jits_second_recording(technique, capfd):
    """The walks recorded once carry no more state variables than Dr.Jit leaves in them when it
    records a loop again to remove the unchanged ones (a learner that kept those in the state
    would carry ~16 more a walk: the time, the derivatives that ray_intersect leaves at zero,
    the merging quantities where nothing merges)."""
    scene = mi.load_file(scene_path('caustic.xml'), res=16, max_depth=5)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': technique})
    sizes = {}
    for once in (False, True):
        loops.ONCE = once
        try:
            sizes[once] = loop_sizes(scene, integ, capfd)
        finally:
            loops.ONCE = True
    assert sizes[True] and sizes[True].keys() == sizes[False].keys(), sizes
    assert all(sizes[True][k] <= sizes[False][k] for k in sizes[True]), sizes
