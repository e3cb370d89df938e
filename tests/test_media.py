"""The medium building blocks (bdpt_jit/media.py) in isolation, against analytic values:
transmittance through null boundaries, ratio tracking, delta tracking and its densities
(chromatic included), the phase vertex, stiff values, and that a scene without media traces
the same kernels. No renders: media are not wired into the strategies yet (docs/media.md).

Statistical bounds: a mean of N independent estimates is compared with its analytic value
within Z = 5 of its standard errors (estimated from the samples); a KS statistic against 1.95 /
sqrt(N) (alpha = 0.001)."""

import gc
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from bdpt_jit import media, media_path
from bdpt_jit.rays import RayOffsets, spawn_to
from bdpt_jit.scene_check import media_info
from bdpt_jit.stats import MediumStats

Z = 5.0
_KEEP = []
KS_001 = 1.95


def _sphere(radius, medium, centre=(0, 0, 0), exterior=None):
    d = {'type': 'sphere', 'radius': radius, 'center': list(centre), 'bsdf': {'type': 'null'},
         'interior': medium}
    if exterior is not None:
        d['exterior'] = exterior
    return d


def _homogeneous(sigma_t, albedo=0.5, g=None):
    m = {'type': 'homogeneous', 'albedo': albedo}
    if np.ndim(sigma_t) == 0:
        m['sigma_t'] = float(sigma_t)
    else:        # an RGB sigma_t above 1: a reflectance-range colour times a scale
        s = float(max(sigma_t))
        m['sigma_t'] = {'type': 'rgb', 'value': [float(v) / s for v in sigma_t]}
        m['scale'] = s
    if g is not None:
        m['phase'] = {'type': 'hg', 'g': float(g)}
    return m


def _tracer(scene, stats=None):
    offsets = RayOffsets(scene)
    dr.make_opaque(offsets.table, offsets.rel)       # (as Context.evaluate_tables does)
    return media.MediumTracer(scene, offsets, media_info(scene), stats)


def _sampler(n, seed=0):
    s = mi.load_dict({'type': 'independent'})
    s.seed(seed, n)
    s.schedule_state()
    dr.eval()
    return s


def _edge(tracer, p, q, medium, n, medium_end=None, sampler=None):
    """The EdgeTransmittance from the point ``p`` (in ``medium``) to ``q``, both on no surface."""
    zero = dr.zeros(mi.Vector3f, n)
    p = mi.Point3f(p) + zero
    q = mi.Point3f(q) + zero
    ray = spawn_to((p, zero, 0.0), (q, zero, 0.0), 0.0)
    end = (q, zero, dr.zeros(mi.Float, n))
    return tracer.edge(ray, end, media.medium_array(medium, n), sampler or _sampler(n), dr.full(mi.Bool, True, n),
                       medium_end)


def _np(x):
    return np.array(x, dtype=np.float64)


def _assert_mean(samples, expected, what):
    samples = np.asarray(samples, dtype=np.float64)
    m, se = samples.mean(), samples.std(ddof=1) / np.sqrt(len(samples))
    assert abs(m - expected) <= Z * se + 1e-7, f"{what}: mean {m:.6g} vs {expected:.6g} (se {se:.3g})"


# ---------------------------------------------------------------------- transmittance
def test_homogeneous_null_sphere_is_exact():
    """Catches: T from the ray's parameter range rather than the distance inside the medium, the
    medium not changed at the null boundary (T of the whole segment, exp(-2)), an offset
    stopping the walk at the boundary (T = 0)."""
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(1.0, _homogeneous(1.0))})
    inner = scene.shapes()[0].interior_medium()
    t = _tracer(scene)
    out = _edge(t, (0, 0, 0), (0, 0, 3), inner, 4)          # centre outwards, beyond the sphere
    np.testing.assert_allclose(_np(out.tr), np.exp(-1.0), rtol=2e-6)
    assert np.all(_np(out.ok)) and np.all(_np(dr.reinterpret_array(mi.UInt32, out.medium)) == 0)
    inside = _edge(t, (0, 0, 0), (0.3, 0.4, 0.0), inner, 4)   # ends inside: exp(-0.5)
    np.testing.assert_allclose(_np(inside.tr), np.exp(-0.5), rtol=2e-6)
    ray = mi.Ray3f(dr.zeros(mi.Point3f, 4), mi.Vector3f(0.6, 0.0, 0.8) + dr.zeros(mi.Vector3f, 4))
    to_inf = t.edge(ray, None, media.medium_array(inner, 4), _sampler(4), dr.full(mi.Bool, True, 4))
    np.testing.assert_allclose(_np(to_inf.tr), np.exp(-1.0), rtol=2e-6)   # towards an environment


def test_homogeneous_scene_traces_no_tracking(monkeypatch):
    """A scene with homogeneous media only (MediaInfo.heterogeneous False) traces neither ratio
    nor delta tracking: transmittance and distance sampling run with both, and the majorant's
    transmittance, replaced by functions that raise."""
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(1.0, _homogeneous([0.5, 1.0, 2.0]))})
    t = _tracer(scene)
    assert not t.info.heterogeneous and t.info.chromatic

    def refuse(*args, **kwargs):
        raise AssertionError('tracking traced in a homogeneous-only scene')
    monkeypatch.setattr(media.MediumTracer, 'ratio_track', refuse)
    monkeypatch.setattr(media.MediumTracer, 'delta_track', refuse)
    monkeypatch.setattr(media, 'majorant_transmittance', refuse)
    inner = scene.shapes()[0].interior_medium()
    out = _edge(t, (0, 0, 0), (0, 0, 3), inner, 4)
    np.testing.assert_allclose(_np(out.tr), np.exp(-np.array([0.5, 1.0, 2.0]))[:, None] + np.zeros(4), rtol=2e-6)
    _, ds = _distance(scene, inner, 64)
    assert np.all(np.isfinite(_np(ds.weight)))


def test_nested_and_serial_media_multiply():
    """Nested (a sphere of sigma_t 2 inside one of 0.5, by interior/exterior) and two media in
    series: T is the product. Catches: the exterior medium of the inner sphere ignored (vacuum
    between the boundaries: exp(-2)), or the first medium kept after the boundary."""
    a, b = _homogeneous(0.5), _homogeneous(2.0)
    # nested: the inner sphere's exterior is the outer sphere's interior (the same object)
    ma = mi.load_dict(a)
    nested = mi.load_dict({'type': 'scene', 'outer': _sphere(2.0, ma),
                           'inner': _sphere(1.0, mi.load_dict(b), exterior=ma)})
    inner_medium = [s for s in nested.shapes() if abs(s.bbox().extents()[0] - 2.0) < 1e-3][0].interior_medium()
    out = _edge(_tracer(nested), (0, 0, 0), (0, 0, 3), inner_medium, 4)
    np.testing.assert_allclose(_np(out.tr), np.exp(-2.0 * 1.0 - 0.5 * 1.0), rtol=4e-6)
    serial = mi.load_dict({'type': 'scene', 's1': _sphere(0.5, a, centre=(0, 0, 1)),
                           's2': _sphere(0.25, b, centre=(0, 0, 3))})
    out = _edge(_tracer(serial), (0, 0, -1), (0, 0, 5), None, 4)
    np.testing.assert_allclose(_np(out.tr), np.exp(-0.5 * 1.0 - 2.0 * 0.5), rtol=4e-6)


def test_opaque_surface_blocks_and_inconsistency_is_counted():
    """0 through a diffuse wall inside the medium; an end that claims another medium than the
    one the walk arrives in is not made (T exactly 0) and counted once per lane."""
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(2.0, _homogeneous(1.0)),
                          'wall': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, 0, 1])}})
    inner = [s for s in scene.shapes() if s.interior_medium() is not None][0].interior_medium()
    stats = MediumStats()
    t = _tracer(scene, stats)
    out = _edge(t, (0, 0, 0), (0, 0, 3), inner, 4)
    assert np.all(_np(out.tr) == 0.0) and not np.any(_np(out.ok))
    out = _edge(t, (0, 0, 0), (0, 0.5, 0.5), inner, 8, medium_end=media.medium_array(None, 8))
    assert np.all(_np(out.tr) == 0.0) and not np.any(_np(out.ok))
    stats.end_pass()
    assert stats.summary()['medium_inconsistencies'] == 8
    out = _edge(t, (0, 0, 0), (0, 0.5, 0.5), inner, 8, medium_end=media.medium_array(inner, 8))
    np.testing.assert_allclose(_np(out.tr), np.exp(-np.sqrt(0.5)), rtol=4e-6)


def test_which_medium_at_the_ends():
    """The sensor's medium, an area emitter's side by the direction it emits into (interior
    inwards, exterior outwards), and a surface that is no medium transition keeping the medium
    the ray was in."""
    fog = _homogeneous(1.0)
    scene = mi.load_dict({'type': 'scene',
                          'sph': {**_sphere(1.0, fog), 'emitter': {'type': 'area'}},
                          'wall': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, 0, 0.5])},
                          'cam': {'type': 'perspective', 'medium': _homogeneous(3.0)}})
    sphere = [s for s in scene.shapes() if s.interior_medium() is not None][0]
    ids = lambda m: _np(dr.reinterpret_array(mi.UInt32, m))
    own = lambda m: int(ids(mi.MediumPtr(m))[0])
    assert np.all(ids(media.medium_at_sensor(scene.sensors()[0], 2)) == own(scene.sensors()[0].get_medium()))
    em = dr.zeros(mi.EmitterPtr, 2)
    em = dr.select(dr.full(mi.Bool, True, 2), mi.EmitterPtr(sphere.emitter()), em)
    n = mi.Vector3f(0, 0, 1)
    assert np.all(ids(media.medium_at_emitter(em, n, mi.Vector3f(0, 0, -1))) == own(sphere.interior_medium()))
    assert np.all(ids(media.medium_at_emitter(em, n, mi.Vector3f(0, 0, 1))) == 0)
    ray = mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, 1))
    si = scene.ray_intersect(ray)                       # the wall, inside the sphere
    inner = media.medium_array(sphere.interior_medium(), 1)
    assert ids(media.medium_after(si, ray.d, inner))[0] == own(sphere.interior_medium())
    assert not media.is_null(si.bsdf(ray), si)[0]


def _grid_box(rows, scale):
    """A null cube [-1, 1]^3 holding a heterogeneous medium whose density grid has the given
    rows along y (each a list of voxels along x; nearest filter), times ``scale``."""
    data = np.array(rows, np.float32)[None, :, :, None]          # (z, y, x, channels)
    medium = {'type': 'heterogeneous', 'albedo': 0.8, 'scale': scale,
              'sigma_t': {'type': 'gridvolume', 'grid': mi.VolumeGrid(data), 'filter_type': 'nearest',
                          'to_world': mi.ScalarTransform4f().translate([-1, -1, -1]).scale(2)}}
    return mi.load_dict({'type': 'scene', 'box': {'type': 'cube', 'bsdf': {'type': 'null'}, 'interior': medium}})


@pytest.mark.parametrize('y, tau', [(-0.5, 0.25 * 2.0 * 2.0),           # constant 0.25 of the majorant 1 (x 2)
                                    (0.5, 0.25 * 2.0 * 1.0 + 1.0 * 2.0 * 1.0)])   # two voxels: 0.5 and 2 over 1 each
def test_ratio_tracking_matches_optical_depth(y, tau):
    """Ratio tracking along x from outside the box to outside it (through both null faces):
    the mean of 2^15 estimates is exp(-tau) within 5 standard errors. Row y = -0.5 has density
    0.25 below the grid's majorant 1 (not 0.5, where sigma_t / m = 1 - sigma_t / m); row y = 0.5
    has 0.25 over x < 0 and 1 over x > 0 (tau by hand: 0.25 * 2 * 1 + 1 * 2 * 1). Catches: a
    factor sigma_t / m instead of 1 - sigma_t / m,
    the bounding-box clip left out (the clamped grid outside the box counted: tau + 2 * 0.5),
    the walk not continuing from each tentative collision."""
    n = 1 << 15
    scene = _grid_box([[0.25, 0.25], [0.25, 1.0]], 2.0)
    t = _tracer(scene)
    assert t.info.heterogeneous
    out = _edge(t, (-3, y, 0.2), (3, y, 0.2), None, n)
    tr = _np(out.tr[0])
    _assert_mean(tr, np.exp(-tau), f'ratio tracking, y={y}')
    np.testing.assert_allclose(_np(out.tmaj), np.exp(-2.0 * 2.0), rtol=1e-5)   # majorant 2 over length 2


# ---------------------------------------------------------------------- distance sampling
def _distance(scene, medium, n, origin=(0, 0, 0), d=(0, 0, 1), seed=1, start=None, stats=None):
    t = _tracer(scene, stats)
    ray = mi.Ray3f(mi.Point3f(origin) + dr.zeros(mi.Point3f, n), mi.Vector3f(d) + dr.zeros(mi.Vector3f, n))
    start = start or media.DensityFactor.surface(n)
    return t, t.sample_distance(ray, None, media.medium_array(medium, n), _sampler(n, seed), start,
                                dr.full(mi.Bool, True, n))


def _edges_along_z(tracer, medium, m, length):
    """The connection side: m edges from the origin (in ``medium``) to points at the midpoints of
    m equal steps along +z up to ``length``; (their distances, MediumTracer.edge of them)."""
    ts = (np.arange(m) + 0.5) / m * length
    z = dr.zeros(mi.Vector3f, m)
    q = mi.Point3f(0, 0, 0) + z
    q.z = mi.Float(ts)
    ray = spawn_to((mi.Point3f(0, 0, 0) + z, z, 0.0), (q, z, 0.0), 0.0)
    edge = tracer.edge(ray, (q, z, dr.zeros(mi.Float, m)), media.medium_array(medium, m), _sampler(m),
                       dr.full(mi.Bool, True, m))
    return ts, edge


def _ks(samples, cdf, n):
    x = np.sort(samples)
    emp_hi = np.arange(1, len(x) + 1) / n
    emp_lo = np.arange(0, len(x)) / n
    f = cdf(x)
    return max(np.max(np.abs(emp_hi - f)), np.max(np.abs(f - emp_lo)))


def test_delta_tracking_homogeneous_distribution_and_densities():
    """sigma_t 2 in a null sphere of radius 1.5, rays from the centre: collision distances follow
    sigma_t exp(-sigma_t t) (KS over the sub-distribution, escapes counted as mass at 1.5), the
    weight is 1 / sigma_t at a collision and 1 at the surface, pdf_fwd equals the connection
    side's density (EdgeTransmittance.pdf_l) at the same point, and the distance density over
    [0, 1.5] plus the pass-through probability integrate to 1 (midpoint rule). sigma_t is not 1
    so that a density off by a factor sigma_t shows. Catches: sigma_t left out at a medium end
    (sum 1 - (1 - e^-3) / 2), sigma_t T used at the surface end (sum 1 + e^-3), the reverse
    density taking sigma_t at a surface start."""
    n, sigma, radius = 1 << 15, 2.0, 1.5
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(radius, _homogeneous(sigma))})
    inner = scene.shapes()[0].interior_medium()
    t, ds = _distance(scene, inner, n)
    coll = _np(ds.collided).astype(bool)
    tc = _np(ds.mei.t)[coll]
    assert _ks(tc, lambda x: 1 - np.exp(-sigma * x), n) < KS_001 / np.sqrt(n)
    _assert_mean(~coll, np.exp(-sigma * radius), 'pass-through probability')
    w = _np(ds.weight[0])
    np.testing.assert_allclose(w[coll], 1.0 / sigma, rtol=1e-5)
    np.testing.assert_allclose(w[~coll], 1.0, rtol=1e-5)
    np.testing.assert_allclose(_np(ds.pdf_fwd)[coll], sigma * np.exp(-sigma * tc), rtol=1e-5)
    np.testing.assert_allclose(_np(ds.pdf_fwd)[~coll], np.exp(-sigma * radius), rtol=1e-5)
    d_end = np.where(coll, _np(ds.mei.t), radius)
    np.testing.assert_allclose(_np(ds.pdf_rev), np.exp(-sigma * d_end), rtol=1e-5)   # surface start: T
    inner_n = media.medium_array(inner, n)
    vstart = media.DensityFactor.at(t.info, inner_n, dr.full(mi.Spectrum, sigma, n), dr.full(mi.Bool, True, n))
    _, dv = _distance(scene, inner, n, start=vstart)      # from a medium vertex: sigma_t T
    d_end = np.where(_np(dv.collided).astype(bool), _np(dv.mei.t), radius)
    np.testing.assert_allclose(_np(dv.pdf_rev), sigma * np.exp(-sigma * d_end), rtol=1e-5)
    # the connection side's density at the same points, and the partition of unity
    m = 4096
    ts, edge = _edges_along_z(t, inner, m, radius)
    sig = dr.full(mi.Spectrum, sigma, m)
    dens = _np(edge.pdf_l(media.DensityFactor.at(t.info, media.medium_array(inner, m), sig, dr.full(mi.Bool, True, m))))
    through = _edge(t, (0, 0, 0), (0, 0, radius + 1), inner, 1).pdf_l(media.DensityFactor.surface(1))
    total = dens.sum() * radius / m + _np(through)[0]
    assert abs(total - 1.0) < 2e-4, total


def test_delta_tracking_across_nested_media():
    """Nested spheres (sigma_t 2 inside radius 1, 0.5 out to radius 2), rays from the centre:
    the pass-through probability is exp(-2.5); a collision's pdf_fwd equals the connection
    side's pdf_l to the same point (the walk's transmittance carried across the boundary); the
    density integrates to 1 with the pass-through over both media. Catches: the first medium's
    transmittance dropped at the null boundary (collisions beyond it with the density of a walk
    that started there), the medium not switched (sigma_t 2 out to radius 2)."""
    n, m = 1 << 15, 4096
    ma = mi.load_dict(_homogeneous(0.5))
    scene = mi.load_dict({'type': 'scene', 'outer': _sphere(2.0, ma),
                          'inner': _sphere(1.0, mi.load_dict(_homogeneous(2.0)), exterior=ma)})
    inner = [s for s in scene.shapes() if abs(s.bbox().extents()[0] - 2.0) < 1e-3][0].interior_medium()
    t, ds = _distance(scene, inner, n)
    coll = _np(ds.collided).astype(bool)
    _assert_mean(~coll, np.exp(-2.5), 'pass-through probability')
    d = _np(ds.mei.t)
    sig = np.where(d < 1.0, 2.0, 0.5)
    tr = np.where(d < 1.0, np.exp(-2.0 * d), np.exp(-2.0 - 0.5 * (d - 1.0)))
    np.testing.assert_allclose(_np(ds.pdf_fwd)[coll], (sig * tr)[coll], rtol=2e-5)
    # the connection side: edges from the centre to points along z, their density at a medium vertex
    ts, edge = _edges_along_z(t, inner, m, 2.0)
    sig_q = mi.Spectrum(mi.Float(np.where(ts < 1.0, 2.0, 0.5)))
    dens = _np(edge.pdf_l(media.DensityFactor.at(t.info, edge.medium, sig_q, dr.full(mi.Bool, True, m))))
    through = _edge(t, (0, 0, 0), (0, 0, 3), inner, 1).pdf_l(media.DensityFactor.surface(1))
    assert abs(dens.sum() * 2.0 / m + _np(through)[0] - 1.0) < 2e-4


def test_delta_tracking_chromatic_one_sample_mis():
    """sigma_t (0.5, 1, 2): pdf_fwd is the channel mixture mean_c sigma_c exp(-sigma_c t) (and
    the pass-through mean_c exp(-sigma_c R)), the distances follow the mixture (KS), each
    channel's collision and pass-through probabilities are estimated without bias
    (E[w_c sigma_c 1{collided}] = 1 - exp(-sigma_c R), E[w_c 1{surface}] = exp(-sigma_c R)), and
    w_c sigma_c <= 3 (the balance over channels: no channel makes a firefly). Catches: the
    chosen channel's density instead of the mean (unbiased, but w_c sigma_c reaches
    0.25 e^{1.5 t}), a channel chosen with the wrong probability (biased means)."""
    n, radius = 1 << 16, 3.0
    sig = np.array([0.5, 1.0, 2.0])
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(radius, _homogeneous(sig))})
    inner = scene.shapes()[0].interior_medium()
    t, ds = _distance(scene, inner, n)
    assert t.info.chromatic
    coll = _np(ds.collided).astype(bool)
    tc = _np(ds.mei.t)
    mix = lambda x: np.mean(sig[:, None] * np.exp(-sig[:, None] * x[None, :]), axis=0)
    np.testing.assert_allclose(_np(ds.pdf_fwd)[coll], mix(tc[coll]), rtol=1e-5)
    np.testing.assert_allclose(_np(ds.pdf_fwd)[~coll], np.mean(np.exp(-sig * radius)), rtol=1e-5)
    spec = mi.Spectrum(*[float(v) for v in sig])
    vstart = media.DensityFactor.at(t.info, media.medium_array(inner, n), spec + dr.zeros(mi.Spectrum, n),
                                    dr.full(mi.Bool, True, n))
    _, dv = _distance(scene, inner, n, start=vstart)      # reverse density from a medium vertex
    d_end = np.where(_np(dv.collided).astype(bool), _np(dv.mei.t), radius)
    np.testing.assert_allclose(_np(dv.pdf_rev), mix(d_end), rtol=1e-5)
    cdf = lambda x: np.mean(1 - np.exp(-sig[:, None] * x[None, :]), axis=0)
    assert _ks(tc[coll], cdf, n) < KS_001 / np.sqrt(n)
    w = np.stack([_np(ds.weight[c]) for c in range(3)])
    for c in range(3):
        _assert_mean(np.where(coll, w[c] * sig[c], 0.0), 1 - np.exp(-sig[c] * radius), f'collision, channel {c}')
        _assert_mean(np.where(coll, 0.0, w[c]), np.exp(-sig[c] * radius), f'pass-through, channel {c}')
    assert np.all(np.isfinite(w)) and np.max(w * sig[:, None] * coll) <= 3.0 * (1 + 1e-5)


def test_delta_tracking_heterogeneous_is_unbiased():
    """The two-voxel grid (densities 0.5 and 2, majorant 2) along x: E[w 1{surface}] = exp(-2.5)
    and E[w sigma_t(x) 1{collided}] = 1 - exp(-2.5); a collision's pdf_fwd is the proxy
    sigma_t(x) T_maj (module docstring), 0 nowhere a collision happened. Catches: null
    collisions counted as real (collisions in the first voxel too often: biased), the null
    weight left out."""
    n = 1 << 16
    scene = _grid_box([[0.5, 0.5], [0.25, 1.0]], 2.0)
    stats = MediumStats()
    t, ds = _distance(scene, None, n, origin=(-3, 0.5, 0.2), d=(1, 0, 0), stats=stats)
    coll = _np(ds.collided).astype(bool)
    stats.end_pass()
    assert stats.summary()['real_collisions'] == coll.sum() and stats.summary()['null_collisions'] > 0
    x = _np(ds.mei.p.x)
    sigma = np.where(x < 0, 0.5, 2.0)
    w = _np(ds.weight[0])
    _assert_mean(np.where(coll, 0.0, w), np.exp(-2.5), 'pass-through')
    _assert_mean(np.where(coll, w * sigma, 0.0), 1 - np.exp(-2.5), 'collision')
    tmaj = np.exp(-2.0 * (x[coll] + 1.0))
    np.testing.assert_allclose(_np(ds.pdf_fwd)[coll], sigma[coll] * tmaj, rtol=1e-4)
    assert np.all(_np(ds.pdf_fwd)[coll] > 0)


# ---------------------------------------------------------------------- the phase vertex
def _vertex(g, n, sigma_t=1.0, albedo=0.5, wi=(0, 0, 1)):
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(1.0, _homogeneous(sigma_t, albedo, g))})
    medium = media.medium_array(scene.shapes()[0].interior_medium(), n)
    ray = mi.Ray3f(dr.zeros(mi.Point3f, n), -mi.Vector3f(wi) + dr.zeros(mi.Vector3f, n))
    v = media.MediumVertex(media.interaction_at(medium, ray, dr.full(mi.Bool, True, n)))
    _KEEP.append(scene)     # the MediumPtr lanes point into the scene: it must outlive them
    return v


@pytest.mark.parametrize('g', [0.0, 0.7, -0.99])
def test_phase_vertex_densities(g):
    """HG: eval's forward pdf equals the sampler's at the sampled directions, the value is
    sigma_s times the pdf, the reverse density equals the forward one (reciprocity), the pdf
    integrates to 1 over the sphere (midpoint rule in cos theta, 2^17 points, random phi), and
    the sampled mean cosine with the forward direction -wi is g. Catches: g's sign (mean cosine
    -g), wi taken as the propagation direction, a reverse density from swapped roles."""
    n = 1 << 14
    v = _vertex(g, n, albedo=0.5)
    s = _sampler(n, 3)
    ps = v.sample('radiance', s.next_1d(), s.next_2d(), dr.full(mi.Bool, True, n))
    f, pdf_fwd, pdf_rev, _ = v.eval(None, ps.wo, 'radiance', dr.full(mi.Bool, True, n))
    np.testing.assert_allclose(_np(pdf_fwd), _np(ps.pdf_w), rtol=2e-4)
    np.testing.assert_allclose(_np(pdf_rev), _np(pdf_fwd), rtol=2e-4)
    np.testing.assert_allclose(_np(ps.pdf_rev_w), _np(pdf_fwd), rtol=2e-4)
    np.testing.assert_allclose(_np(f[0]), 0.5 * _np(pdf_fwd), rtol=2e-4)
    np.testing.assert_allclose(_np(ps.weight[0]), 0.5, rtol=1e-4)
    assert _np(v.cos(ps.wo)).tolist() == [1.0] * n and all(_np(v.smooth()))
    cos_fwd = _np(dr.dot(ps.wo, -v.mei.wi))
    _assert_mean(cos_fwd, g, 'mean cosine')
    m = 1 << 17
    # nodes in cos theta: uniform for g = 0; for g != 0 uniform in ln(1 + g^2 + 2 g mu), which
    # spreads the peak of g = -0.99 (width ~1e-2 in mu) over many nodes (midpoint rule)
    x = (np.arange(m) + 0.5) / m
    if g == 0.0:
        mu, dmu = -1 + 2 * x, np.full(m, 2.0 / m)
    else:
        lo, hi = np.log((1 - abs(g)) ** 2), np.log((1 + abs(g)) ** 2)
        s_ = np.exp(lo + (hi - lo) * x)
        mu, dmu = (s_ - 1 - g * g) / (2 * g), s_ * (hi - lo) / m / (2 * abs(g))
    phi = np.random.default_rng(0).uniform(0, 2 * np.pi, m)
    st = np.sqrt(np.maximum(1 - mu * mu, 0))
    wo = mi.Vector3f(st * np.cos(phi), st * np.sin(phi), mu)
    _, pdf_q, _, _ = _vertex(g, m).eval(None, wo, 'radiance', dr.full(mi.Bool, True, m))
    pdf_q = _np(pdf_q)
    # HG in double precision (wi = +z, so the forward direction is mu = -1 for g > 0): the
    # quadrature itself integrates it to 1; Mitsuba's float32 1 + g^2 - 2 g cos loses
    # ~4 ulps / (1 + g^2 - 2 g cos) relative (0.3% at the peak of g = -0.99), the bound below
    denom = 1 + g * g + 2 * g * mu
    hg = (1 - g * g) / (4 * np.pi * denom ** 1.5)
    assert abs((hg * dmu).sum() * 2 * np.pi - 1.0) < 1e-6
    bound = 1.5 * 4 * 2.0 ** -24 * (1 + g * g + 2 * abs(g)) / denom + 2e-6
    assert np.all(np.abs(pdf_q - hg) <= bound * hg), np.max(np.abs(pdf_q - hg) / hg / bound)
    total = (pdf_q * dmu).sum() * 2 * np.pi
    assert abs(total - 1.0) <= (bound * hg * dmu).sum() * 2 * np.pi + 1e-6, total


# ---------------------------------------------------------------------- stiff values
@pytest.mark.parametrize('sigma_t', [1e-4, 1e3])
def test_stiff_extinction_finite(sigma_t):
    """sigma_t 1e-4 and 1e3: T exact (exp(-1e3) underflows to exactly 0), distance samples
    finite with non-negative densities, collisions inside the sphere."""
    n = 1024
    scene = mi.load_dict({'type': 'scene', 'sph': _sphere(1.0, _homogeneous(sigma_t))})
    inner = scene.shapes()[0].interior_medium()
    t = _tracer(scene)
    tr = _np(_edge(t, (0, 0, 0), (0, 0, 2), inner, 4).tr)
    np.testing.assert_allclose(tr, np.exp(-sigma_t), rtol=1e-5, atol=0)
    _, ds = _distance(scene, inner, n)
    for x in (ds.weight, ds.pdf_fwd, ds.pdf_rev, ds.mei.t):
        a = _np(x)
        assert np.all(np.isfinite(a[..., _np(ds.collided).astype(bool)])) and np.all(_np(ds.pdf_fwd) >= 0)
    assert np.all(_np(ds.mei.t)[_np(ds.collided).astype(bool)] <= 1.0 + 1e-5)


@pytest.mark.parametrize('g, albedo', [(0.99, 1.0), (-0.99, 0.0), (0.99, 0.0), (-0.99, 1.0)])
def test_stiff_phase_finite(g, albedo):
    """g = +-0.99 and albedo 0 and 1: eval and samples finite; albedo 0 gives value and weight 0."""
    n = 4096
    v = _vertex(g, n, albedo=albedo)
    s = _sampler(n, 5)
    ps = v.sample('importance', s.next_1d(), s.next_2d(), dr.full(mi.Bool, True, n))
    f, pdf_fwd, pdf_rev, _ = v.eval(None, ps.wo, 'importance', dr.full(mi.Bool, True, n))
    for x in (ps.weight, ps.pdf_w, ps.pdf_rev_w, f, pdf_fwd, pdf_rev):
        assert np.all(np.isfinite(_np(x)))
    np.testing.assert_allclose(_np(ps.weight), albedo, rtol=1e-4)
    if albedo == 0.0:
        assert np.all(_np(f) == 0.0)


# ---------------------------------------------------------------------- scenes without media
def _kernel_hashes(scene):
    # garbage first: a virtual call's kernel code depends on how many instances of its domain
    # are alive (one: a direct call; several: a dispatch), and an earlier test's scene left in
    # a reference cycle, collected between two measurements, changed the kernels of the second
    # (seen once in a full run; reproduced with a garbage scene of two other BSDFs)
    gc.collect()
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4})
    mi.render(scene, integrator=integ, spp=1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        mi.render(scene, integrator=integ, spp=1)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return [k['hash'] for k in hist if k['type'] == dr.KernelType.JIT]


def test_scene_without_media_traces_the_same_kernels(monkeypatch):
    """A Cornell box's kernels are the same before and after the media analysis and a
    MediumTracer were built for it, the analysis says it has none, and a render of it calls
    nothing of media.py (every function and method replaced by one that raises: once media are
    wired, their code must stay behind the Python flag MediaInfo.any). The hashes of whole
    renders on two trees: scripts/kernel_hashes.py."""
    from helpers import cornell_scene
    scene = cornell_scene(8)
    before = _kernel_hashes(scene)
    info = media_info(scene)
    assert (info.any, info.heterogeneous, info.chromatic) == (False, False, False)
    _tracer(scene)

    def refuse(*args, **kwargs):
        raise AssertionError('media code called for a scene without media')
    for name in ('medium_after', 'medium_at_sensor', 'medium_at_emitter', 'interaction_at', 'pdf_l',
                 'majorant_transmittance', 'homogeneous_tr', 'is_null'):
        monkeypatch.setattr(media, name, refuse)
    for name in ('sample_direction', 'sample_step', 'next_vertex', 'edge_terms', 'connection_edge',
                 'stored_vertex', 'enclosing_medium', 'surface_start', 'sensor_medium'):
        monkeypatch.setattr(media_path, name, refuse)
    for cls in (media.MediumTracer, media.MediumVertex, media.DensityFactor, media_path.PathVertex,
                media_path.MediumHit, media_path.EmitterMedia):
        for name, value in list(vars(cls).items()):
            if callable(value) and not name.startswith('__'):
                monkeypatch.setattr(cls, name, refuse)
    assert _kernel_hashes(scene) == before
