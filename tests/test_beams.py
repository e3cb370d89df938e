"""Merging inside media by beams (bdpt_jit/beams.py): the grid walk finds each light vertex
within r of a camera segment once (and merge.py's ball query each one within r of a point, its
estimate normalised per unit volume in a medium, per unit area on a surface), the strategy's
MIS factor reaches the kernels, and the choice between beams and balls follows the scene's
media. The estimate's value is checked by
the renders of tests/test_media_render.py (vm and vcm against volpath, the white furnace),
its weights by tests/test_mis_partition.py (beams: 1 / sigma_t of the vertex)."""

from types import SimpleNamespace

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from test_media_render import BATCHES, SCENES, bdpt, render_batches, volpath_reference

from bdpt_jit.beams import BeamGather, BeamGrid, Segment
from bdpt_jit.merge import Merger, MergeSchedule, PhotonGrid, scene_radius
from bdpt_jit.store import LightStore, make_record_type

SPP_PASS = 2        # iterations in the pass: sample / light subpath idx belongs to idx % 2


def random_store(rng, n, levels=2):
    """A store of ``n`` light subpaths with up to ``levels`` vertices each, uniform in [-1, 1]^3
    (80% of them medium vertices). Returns (the store, its vertices as numpy: p, path, valid)."""
    record = make_record_type(['p', 'beta', 'd_vcm', 'd_vc', 'medium', 'in_medium'])
    store = LightStore(n=n, capacity=levels, record=record)
    count = rng.integers(0, levels + 1, size=n)
    ps, paths, valid = [], [], []
    for level in range(levels):
        p = rng.uniform(-1, 1, size=(n, 3))
        med = rng.uniform(size=n) < 0.8
        rec = record()
        rec.p = mi.Point3f(*[mi.Float(p[:, i]) for i in range(3)])
        rec.beta, rec.d_vcm, rec.d_vc = mi.Spectrum(1.0), mi.Float(0.0), mi.Float(0.0)
        rec.medium = dr.zeros(mi.MediumPtr, n)
        rec.in_medium = mi.UInt32(med.astype(np.uint32))
        idx = dr.arange(mi.UInt32, n)
        record.store(store.v, rec, store.slot(mi.UInt32(level), idx), mi.Bool(level < count))
        ps.append(p)
        paths.append(np.arange(n))
        valid.append(med & (level < count))
    store.count = mi.UInt32(count.astype(np.uint32))
    dr.eval(store.v, store.count)
    return store, (np.concatenate(ps), np.concatenate(paths), np.concatenate(valid))


def test_the_beams_cap_is_the_parameter_or_automatic():
    """beams.beam_cap: the parameter beam_paths where set (0: all), else BEAM_PATHS in vcm and
    all (0) in vm, whose beams alone sample what they sample."""
    from bdpt_jit.beams import BEAM_PATHS, beam_cap
    from bdpt_jit.strategies import StrategySet
    assert beam_cap(StrategySet('vcm'), None) == BEAM_PATHS
    assert beam_cap(StrategySet('vm'), None) == 0
    assert beam_cap(StrategySet('vm'), 85) == 85 and beam_cap(StrategySet('vcm'), 0) == 0


def test_stored_slots_split_into_medium_and_surface_vertices():
    """LightStore.stored_slots(in_medium=...): the beam grid's vertices (inside media) and the
    photon grid's where media merge by beams (on surfaces) are the stored vertices of each kind,
    in increasing order, and together every stored vertex once."""
    rng = np.random.default_rng(7)
    n = 500
    store, (p, path, medium_stored) = random_store(rng, n, levels=3)
    every = np.array(store.stored_slots())
    med = np.array(store.stored_slots(in_medium=True))
    surf = np.array(store.stored_slots(in_medium=False))
    expected_med = np.nonzero(medium_stored)[0]          # (numpy's order: level-major, as the slots)
    assert np.array_equal(med, expected_med)
    assert np.all(np.diff(surf) > 0) and np.all(np.diff(med) > 0)
    assert np.array_equal(np.sort(np.concatenate([med, surf])), every)
    assert 0 < len(surf) < len(every)


def counting(self, k, interval, seg, group_r2, active, tap=None):
    """BeamGather.merge_one replaced by 1 for every entry the walk counts."""
    ok = self.candidate(k, interval, seg, group_r2, active)[0]
    return dr.select(ok, mi.Spectrum(1.0), 0.0), ()


@pytest.mark.parametrize('n,radius_rel,cap', [(40000, 0.04, None), (3000, 0.03, None), (60, 0.2, None),
                                              (40000, 0.04, 7001)])
def test_each_light_vertex_within_r_of_a_segment_counts_once(monkeypatch, n, radius_rel, cap):
    """Random segments (inside and outside the vertices' box, ending or infinite) against random
    light vertices of two iterations: the walk's count for each segment lies between the brute
    force's count of vertices clearly within r of it (margins of 1e-4 r and 1e-4 along it, for
    float32) and of those loosely within: never a vertex twice (cells of 2 r, n = 40000; wider
    cells where vertices are sparse, n = 3000; a radius near the cells, n = 60). With a ``cap``
    on the light subpaths of an iteration that beams gather from (merge.MergeSchedule,
    parameter beam_paths): only the vertices of its first ``cap``, and the estimate over
    N_b = cap (planted: the grid given every vertex, or N the iteration's light subpaths, fails)."""
    rng = np.random.default_rng(n)
    scene = mi.load_dict({'type': 'scene', 'box': {'type': 'cube'}})
    store, (p, path, valid) = random_store(rng, n)
    schedule = MergeSchedule(scene, radius_rel, 1.0, 1, SPP_PASS, n // SPP_PASS, beam_cap=cap)
    paths = min(n // SPP_PASS, cap or n)
    if cap is not None:
        assert schedule.beam_paths == cap
        valid = valid & (path < cap * SPP_PASS)
    r = radius_rel * scene_radius(scene)
    grid = BeamGrid(scene, store, schedule)
    monkeypatch.setattr(BeamGather, 'merge_one', counting)
    gather = BeamGather(SimpleNamespace(moments=None), grid, None)

    m = 400
    o = rng.uniform(-1.6, 1.6, size=(m, 3))
    d = rng.normal(size=(m, 3))
    d[: m // 8, 1:] = 0.0                           # some along an axis (the walk's flat axes)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_end = np.where(rng.uniform(size=m) < 0.2, np.inf, rng.uniform(0, 3, size=m))
    F = lambda a: mi.Float(a.astype(np.float32))       # noqa: E731
    ray = mi.Ray3f(mi.Point3f(*[F(o[:, i]) for i in range(3)]), mi.Vector3f(*[F(d[:, i]) for i in range(3)]))
    seg = Segment(None, ray, None, F(t_end), SimpleNamespace(beta=mi.Spectrum(1.0)), True)
    got = np.array(gather.gather(dr.arange(mi.UInt32, m), seg, dr.full(mi.Bool, True, m)).x)
    got = got * np.pi * r * r * paths               # the estimate's 1 / (pi r^2 N) taken out

    lo, hi = [], []
    for j in range(m):
        mine = valid & (path % SPP_PASS == j % SPP_PASS)
        s = (p - o[j]) @ d[j]
        dist2 = np.sum((p - o[j] - s[:, None] * d[j]) ** 2, axis=1)
        lo.append(np.sum(mine & (s > 1e-4) & (s < t_end[j] - 1e-4) & (dist2 < r * r * (1 - 1e-4))))
        hi.append(np.sum(mine & (s > -1e-4) & (s < t_end[j] + 1e-4) & (dist2 < r * r * (1 + 1e-4))))
    lo, hi = np.array(lo), np.array(hi)
    assert hi.sum() > 100, 'too few vertices near the segments for the test to mean anything'
    assert np.all(np.abs(got - np.round(got)) < 1e-3), got
    got = np.round(got)
    bad = np.nonzero((got < lo) | (got > hi))[0]
    assert bad.size == 0, f'segments {bad[:5]}: counted {got[bad[:5]]}, brute force {lo[bad[:5]]}..{hi[bad[:5]]}'


def counting_balls(self, k, v, sub, active, inv_factor=None, tap=None):
    """Merger.merge_one replaced by 1 for every entry the query finds."""
    return dr.select(active, mi.Spectrum(1.0), 0.0), ()


@pytest.mark.parametrize('in_medium', [True, False])
def test_a_ball_merge_counts_each_light_vertex_within_r_once(monkeypatch, in_medium):
    """merge.py's query (the photon grid, the ball around a camera vertex) at random points
    against the stored vertices of two iterations (both kinds: the merge's own test of kinds is
    left to it): each vertex of the query's iteration within r counts once (brute force, with
    margins of 1e-4 r for float32), and the estimate is that count over the density's
    measure, 4/3 pi r^3 N inside a medium, pi r^2 N on a surface, exactly (planted: a 1%
    error in either, or a grid cell lost, fails)."""
    rng = np.random.default_rng(5)
    n, radius_rel = 30000, 0.05
    scene = mi.load_dict({'type': 'scene', 'box': {'type': 'cube'}})
    store, _ = random_store(rng, n)
    slot = store.stored_slots()
    first = dr.gather(mi.Vector4f, store.v, slot * store.record.packets())
    p = np.stack([np.array(first.x), np.array(first.y), np.array(first.z)], axis=1)
    iteration = (np.array(slot) % n) % SPP_PASS
    schedule = MergeSchedule(scene, radius_rel, 1.0, 1, SPP_PASS, n // SPP_PASS)
    r = radius_rel * scene_radius(scene)
    monkeypatch.setattr(Merger, 'merge_one', counting_balls)
    merger = Merger(SimpleNamespace(media=SimpleNamespace(info=None), moments=None),
                    PhotonGrid(scene, store, schedule), SimpleNamespace(mis_merges=False))
    m = 600
    q = rng.uniform(-1.1, 1.1, size=(m, 3))
    F = lambda a: mi.Float(a.astype(np.float32))       # noqa: E731
    v = SimpleNamespace(si=SimpleNamespace(p=mi.Point3f(*[F(q[:, i]) for i in range(3)])),
                        in_medium=dr.full(mi.Bool, in_medium, m))
    got = np.array(merger.gather(dr.arange(mi.UInt32, m), v, SimpleNamespace(beta=mi.Spectrum(1.0)),
                                 dr.full(mi.Bool, True, m)).x)
    measure = (4.0 / 3.0 * np.pi * r ** 3 if in_medium else np.pi * r * r) * (n // SPP_PASS)
    dist2 = np.sum((p[None, :, :] - q[:, None, :]) ** 2, axis=2)
    mine = iteration[None, :] == (np.arange(m) % SPP_PASS)[:, None]
    lo = np.sum(mine & (dist2 < r * r * (1 - 1e-4)), axis=1)
    hi = np.sum(mine & (dist2 < r * r * (1 + 1e-4)), axis=1)
    assert hi.sum() > 300, 'too few vertices near the queries for the test to mean anything'
    count = got * measure
    assert np.all(np.abs(count - np.round(count)) < 1e-3 * np.maximum(count, 1)), count[:8]
    count = np.round(count)
    bad = np.nonzero((count < lo) | (count > hi))[0]
    assert bad.size == 0, f'queries {bad[:5]}: counted {count[bad[:5]]}, brute force {lo[bad[:5]]}..{hi[bad[:5]]}'


def test_beams_where_media_are_gray_and_balls_where_chromatic():
    """last_render_info['media']['merging']: beams in gray fog, balls where a
    medium's sigma_t differs between channels (the juice in the glass), and with
    media_merging = points; None for a technique that does not merge."""
    cases = [('fog-area', 'vcm', {}, 'beams'), ('fog-area', 'vcm', {'media_merging': 'points'}, 'points'),
             ('glass-juice', 'vcm', {}, 'points'), ('fog-area', 'bdpt', {}, None)]
    for name, technique, extra, expected in cases:
        integ = mi.load_dict({'type': 'bdpt', 'technique': technique, 'max_depth': 4, 'merge_everywhere': True,
                              **extra})
        mi.render(mi.load_dict(SCENES[name]()), integrator=integ, spp=1)
        assert integ.last_render_info['media']['merging'] == expected, (name, technique, extra)


def test_gray_heterogeneous_grids_are_told_apart():
    """scene_check._gray on heterogeneous media: a one-channel grid and an RGB grid with equal
    channels are gray, an RGB grid with unequal ones is not."""
    from bdpt_jit.scene_check import _gray
    g = np.ones((2, 2, 2, 3), dtype=np.float32)
    chroma = g.copy()
    chroma[1, 1, 1, 2] = 0.5
    for data, expected in [(np.ones((2, 2, 2, 1), dtype=np.float32), True), (g, True), (chroma, False)]:
        medium = mi.load_dict({'type': 'heterogeneous',
                               'sigma_t': {'type': 'gridvolume', 'grid': mi.VolumeGrid(data)}})
        assert _gray(medium) == expected, data.shape


@pytest.mark.parametrize('merging,spp', [('beams', 4096), pytest.param('points', 16384, marks=pytest.mark.slow)])
def test_merging_inside_media_image_mean(merging, spp):
    """vm in the fog room, beams (4096 samples a pixel, ~25 s) and balls (16384, ~100 s, slow):
    the image mean within 4 combined standard errors of volpath's (merges inside the medium make
    ~90% of vm's image here). Planted, a 1% error of the estimate's normalisation moved it by 4.2
    of them with balls (4/3 pi r^3 N) and by 9.9 with beams at 16384 (pi r^2 N;
    test_media_render.py's test_merging_agrees_with_volpath catches a 5% one)."""
    integ = {**bdpt('vm', 6), 'radius': 0.05, 'samples_per_pass': 1 << 16, 'media_merging': merging}
    mine = render_batches(mi.load_dict(SCENES['fog-area']()), integ, spp, BATCHES).mean(axis=(1, 2, 3))
    ref = volpath_reference('fog-area', 6).mean(axis=(1, 2, 3))
    se = np.hypot(mine.std(ddof=1), ref.std(ddof=1)) / np.sqrt(BATCHES)
    assert abs(mine.mean() - ref.mean()) <= 4 * se, f'vm {mine.mean():.6f} vs volpath {ref.mean():.6f} +- {se:.6f}'
