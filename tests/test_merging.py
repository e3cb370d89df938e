"""Vertex merging (techniques vcm and vm; merge.py, mis.py).

- The merging estimate and the radius schedule against an analytic value: a point light above
  a diffuse plane, seen from above by an orthographic camera, with ``vm``. The expected image is
  the irradiance blurred by the merging disc of each pass, which numerical quadrature gives; a
  wrong normalisation (1/(pi r^2 N)), a wrong kernel, a lost or doubly counted grid cell, or a
  radius schedule other than r_i = r_1 i^((alpha-1)/2) moves the image mean by more than the
  stated bound, and the bound also separates the blurred value from the sharp one.
- ``vcm`` and ``vm`` inside a closed emitting sphere, where merging has no bias of its own: the
  closed form, with merges carrying much of the weight (a broken partition fails here);
  test_mis_partition checks the weights themselves on random paths.
- ``vcm`` against ``bdpt`` (per pixel and per 4x4 block, helpers.agreement) on a diffuse Cornell
  box, where no path needs merging, at a small radius.
- A caustic seen through glass: the same plane under a sheet of delta transmission (a
  ``dielectric`` of matched index: it refracts straight on, reflects nothing, transmits all),
  the point light above the sheet, the camera looking through it. Every path of 4 edges is
  light - sheet - plane - sheet - camera, which no connection and no emitter hit can sample (a
  point light, a delta vertex next to the diffuse one on both sides): only merging renders it,
  and its expected image is again the blurred irradiance, for vcm and vm, so the bias falls with
  the passes as the radius schedule predicts.
- The same plane under a ``thindielectric`` sheet, whose transmission is a Null lobe: shadow
  rays and connections pass it with its transmittance (taken from Mitsuba's thindielectric),
  so bdpt and pt render the sharp irradiance through it.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import agreement, assert_finite, cornell_scene, reference, render_batches

H = 1.0              # light height above the plane
INTENSITY = 10.0     # point light intensity (W/sr)
RHO = 0.5            # plane albedo
HALF = 0.5           # the camera sees [-HALF, HALF]^2
PLANE = 10.0         # the plane spans [-PLANE, PLANE]^2 (its edges stay far from every disc)
RES = 32


SHEET = 0.5         # height of the thin dielectric sheet (between the plane and the light)


SHEETS = {'matched': {'type': 'dielectric', 'int_ior': 1.0, 'ext_ior': 1.0},    # delta transmission, all of it
          'thin': {'type': 'thindielectric'}}                                   # a Null lobe beside a delta reflection


def plane_scene(sheet=None):
    """The plane under the point light, seen from above; ``sheet`` ('matched', 'thin') a sheet of
    that BSDF between them (SHEETS)."""
    T = mi.ScalarTransform4f
    extra = {}
    if sheet:
        extra['sheet'] = {'type': 'rectangle', 'to_world': T().translate([0, 0, SHEET]).scale([PLANE, PLANE, 1.0]),
                          'bsdf': SHEETS[sheet]}
    return mi.load_dict({
        'type': 'scene', **extra,
        'plane': {'type': 'rectangle', 'to_world': T().scale([PLANE, PLANE, 1.0]),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [RHO] * 3}}},
        'light': {'type': 'point', 'position': [0.0, 0.0, H],
                  'intensity': {'type': 'rgb', 'value': [INTENSITY] * 3}},
        'sensor': {'type': 'orthographic',
                   'to_world': T().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]).scale([HALF, HALF, 1.0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'},
                            'pixel_format': 'rgb'},
                   'sampler': {'type': 'independent'}},
    })


def irradiance(x, y):
    return INTENSITY * H / (H * H + x * x + y * y) ** 1.5


def sheet_transmittance(cos_theta):
    """Mitsuba's thindielectric transmittance (Fresnel with the inter-reflections), read from
    the BSDF itself: its transmission lobe is chosen with that probability, weight 1."""
    c = mi.Float(np.asarray(cos_theta, np.float64).ravel())
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(c))
    si.wi = mi.Vector3f(dr.safe_sqrt(1 - c * c), 0, c)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    bs, _ = mi.load_dict({'type': 'thindielectric'}).sample(mi.BSDFContext(), si, mi.Float(1 - 1e-6),
                                                            mi.Point2f(0.5, 0.5))
    return np.array(bs.pdf, np.float64).reshape(np.shape(cos_theta))


def through_sheet(x, y):
    """Irradiance of the plane under the sheet (the light crosses it once)."""
    cos = H / np.sqrt(H * H + x * x + y * y)
    table_c = np.linspace(0.0, 1.0, 2001)
    return irradiance(x, y) * np.interp(cos, table_c, sheet_transmittance(table_c))


def expected_mean(radii, field=irradiance):
    """rho/pi times the irradiance averaged over the seen square and over the disc of each
    pass's radius, averaged over the passes (midpoint quadrature, converged to ~1e-5)."""
    g = (np.arange(64) + 0.5) / 64 * 2 * HALF - HALF            # the square (symmetric)
    X, Y = np.meshgrid(g, g, indexing='ij')
    # the unit disc: 24 rings of equal area x 48 angles
    rr = np.sqrt((np.arange(24) + 0.5) / 24)
    th = (np.arange(48) + 0.5) / 48 * 2 * np.pi
    dx, dy = (rr[:, None] * np.cos(th)).ravel(), (rr[:, None] * np.sin(th)).ravel()
    vals = []
    for r in radii:
        e = field(X[..., None] + r * dx, Y[..., None] + r * dy).mean()
        vals.append(e)
    return RHO / np.pi * float(np.mean(vals))


def scene_radius(scene):
    b = scene.bbox()
    return float(dr.norm(b.max - b.min)) * 0.5


def test_stored_slots_are_the_valid_slots_in_order():
    """store.LightStore.stored_slots, over which the photon grid and the light vertex cache are
    built: every slot level * n + i with level < count[i], in increasing order, and no other
    (a slot left out loses its vertex's merges and draws; an empty one merges garbage)."""
    from bdpt_jit.store import LightStore
    count = [0, 3, 1, 2, 0, 3]
    store = LightStore(len(count), 3)
    store.count = mi.UInt32(count)
    want = sorted(level * len(count) + i for i, k in enumerate(count) for level in range(k))
    assert store.stored_slots().numpy().tolist() == want
    store.count = dr.zeros(mi.UInt32, len(count))
    assert dr.width(store.stored_slots()) == 0


@pytest.mark.parametrize('alpha', [pytest.param(1.0, marks=pytest.mark.slow), 0.75])
def test_vm_matches_the_blurred_irradiance(alpha):
    """Image mean of ``vm`` (max_depth 2: light -> plane -> camera) with ``spp`` iterations (one
    pass: iteration j is sample j of every pixel, merge.MergeSchedule), over K renders by fresh
    integrators (each runs iterations 1..spp): within 4
    standard errors of the blurred analytic mean for the schedule ``alpha``, while the sharp
    value (no blur) and the other schedule's value lie far outside."""
    scene = plane_scene()
    r1 = 0.5
    rel = r1 / scene_radius(scene)
    spp, K = 64, 8
    means = []
    for k in range(K):
        integ = mi.load_dict({'type': 'bdpt', 'technique': 'vm', 'max_depth': 2, 'radius': rel,
                              'radius_alpha': alpha})
        img = assert_finite(mi.render(scene, integrator=integ, spp=spp, seed=100 + k))
        assert integ.last_render_info['merge_iteration'] == spp
        means.append(float(np.mean(img)))
    means = np.array(means)
    m, se = means.mean(), means.std(ddof=1) / np.sqrt(K)
    radii = [r1 * i ** (0.5 * (alpha - 1.0)) for i in range(1, spp + 1)]
    want = expected_mean(radii)
    other = expected_mean([r1 * i ** (0.5 * ((1.75 - alpha) - 1.0)) for i in range(1, spp + 1)])
    sharp = expected_mean([0.0])
    msg = f'vm mean {m:.5f} +- {se:.5f}, expected {want:.5f} (sharp {sharp:.5f}, other schedule {other:.5f})'
    assert abs(m - want) < 4 * se, msg
    assert abs(sharp - want) > 8 * se and abs(other - want) > 6 * se, 'the test cannot tell: ' + msg


def test_vm_refuses_what_it_cannot_render():
    """Merging has no (s,t) layers; the radius must be positive and alpha in (0, 1]: each
    refused with the parameter named."""
    for bad in ({'radius': 0.0}, {'radius': -1.0}, {'radius_alpha': 0.0}, {'radius_alpha': 1.5},
                {'radius': 'big'}):
        with pytest.raises(Exception, match=f"parameter '{list(bad)[0]}'"):   # (Mitsuba wraps it)
            mi.load_dict({'type': 'bdpt', 'technique': 'vcm', **bad})
    with pytest.raises(Exception, match="parameter 'strategy_images'"):
        mi.load_dict({'type': 'bdpt', 'technique': 'vcm', 'strategy_images': True})


def test_vcm_agrees_with_bdpt_on_a_diffuse_box():
    """No path of a diffuse Cornell box needs merging; with merges at every vertex
    (merge_everywhere) and a small radius, vcm's bias (the blur of the merges, weighted by their
    MIS weights) is below the noise of this test, so its image must agree with bdpt's per pixel
    and per block (merges carry little weight at this radius: the partition is tested sharply by
    test_closed_sphere)."""
    load = lambda: cornell_scene(16)                                     # noqa: E731
    ref = reference(('cornell16', 'merging'), load, {'type': 'bdpt', 'max_depth': 5}, 64, 8, 900)
    scene = load()
    got = render_batches(scene, {'type': 'bdpt', 'max_depth': 5, 'technique': 'vcm', 'radius': 0.004,
                                 'merge_everywhere': True}, 64, 8, seed0=0)
    ok, msg = agreement(got, ref)
    assert ok, msg


def test_vcm_without_specular_surfaces_is_bdpt():
    """By default a camera vertex merges only behind a delta vertex (mis.py): in a scene without
    one there is no merge, and vcm renders bdpt's pixels (same seed, same kernels); with
    merge_everywhere it does not (the merges change the pixels)."""
    scene = cornell_scene(16)
    bdpt = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 5}), spp=4, seed=3))
    vcm = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': 'vcm'})
    # (up to float32 rounding: light tracing's splats are atomic adds whose order varies)
    np.testing.assert_allclose(np.array(mi.render(scene, integrator=vcm, spp=4, seed=3)), bdpt, rtol=1e-5, atol=1e-7)
    assert 'merge_iteration' not in vcm.last_render_info
    everywhere = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': 'vcm', 'merge_everywhere': True})
    assert not np.allclose(np.array(mi.render(scene, integrator=everywhere, spp=4, seed=3)), bdpt, rtol=1e-5, atol=1e-7)


def enclosure_scene(rho):
    """The closed emitting sphere (test_analytic.sphere_mesh, a fine mesh) seen from inside at
    32x32: the radiance is Le sum rho^k everywhere."""
    from test_analytic import sphere_mesh
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 60,
                   'to_world': mi.ScalarTransform4f().look_at(origin=[0, 0, 0.3], target=[0, 0, -1], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': 32, 'height': 32, 'pixel_format': 'rgb',
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'sphere': sphere_mesh(rho, n_theta=24, n_phi=48),
    })


@pytest.mark.parametrize('technique,mis,radius', [('vcm', 'power', 0.05), ('vcm', 'balance', 0.05),
                                                  ('vm', 'power', 0.1)])
def test_closed_sphere(technique, mis, radius):
    """Inside a closed diffuse enclosure that emits Le everywhere the radiance is Le sum rho^k
    (test_analytic), and the density of light vertices on its surface is uniform: a merge within
    a ball of radius r sees the surface's area pi r^2 (exact for a sphere, Archimedes; +1e-3 at
    r = 0.1 for this fine mesh), so ``vm`` has no bias here at any radius. ``vcm`` has one of
    its own: a merge's MIS weight is evaluated at the camera vertex for a light vertex up to r
    away, so the weights of nearby paths only sum to one as r -> 0 (measured at 16x16: +0.15%
    at r = 0.1, none visible at 0.05 within 0.014%). At r = 0.05 merges still carry much of the
    weight (eta = pi r^2 N ~ 8): leaving the merging term out of the connections' recursion
    (mis.on_scatter) moves the mean by +7% (over 100 sigma), a lost d_vm update or a wrong
    normalisation likewise."""
    from test_analytic import LE
    rho, max_depth = 0.8, 4
    scene = enclosure_scene(rho)
    # (a diffuse enclosure: vcm merges only with merge_everywhere, and would otherwise be bdpt)
    everywhere = {'merge_everywhere': True} if technique == 'vcm' else {}
    b = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique, 'mis': mis,
                               'radius': radius / scene_radius(scene), 'radius_alpha': 1.0, **everywhere},
                       spp=16, batches=16)
    expected = LE * sum(rho ** k for k in range(max_depth))
    per_batch = b.mean(axis=(1, 2, 3))
    mean, sigma = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    assert abs(mean - expected) <= 4 * sigma, f'{mean} vs {expected} (sigma {sigma})'


@pytest.mark.parametrize('technique', ['vcm', pytest.param('vm', marks=pytest.mark.slow)])
def test_caustic_through_glass_matches_the_blurred_irradiance(technique):
    """The plane seen through a sheet of delta transmission, lit by the point light through it,
    at max_depth 4 (light - sheet - plane - sheet - camera; bdpt renders black here). vcm and vm,
    radius_alpha 0.5 (a fast schedule, so that the fall is measurable in a short test): the
    image mean after 16 and after 64 passes each within 4 standard errors of the blurred
    analytic value for that many passes (the bias falls as the schedule predicts: the two
    expected values differ by more than 6 standard errors)."""
    scene = plane_scene(sheet='matched')
    r1, K = 0.8, 8
    rel = r1 / scene_radius(scene)
    got, want, se = {}, {}, {}
    for spp in (16, 64):
        means = []
        for k in range(K):
            # 16 iterations in 16 passes, 64 in one pass: the schedule is the same
            per_pass = {'samples_per_pass': RES * RES} if spp == 16 else {}
            integ = mi.load_dict({'type': 'bdpt', 'technique': technique, 'max_depth': 4, 'radius': rel,
                                  'radius_alpha': 0.5, **per_pass})
            img = assert_finite(mi.render(scene, integrator=integ, spp=spp, seed=300 + k))
            assert integ.last_render_info['merge_iteration'] == spp
            assert integ.last_render_info['passes'] == (spp if per_pass else 1)
            means.append(float(np.mean(img)))
        got[spp], se[spp] = np.mean(means), np.std(means, ddof=1) / np.sqrt(K)
        radii = [r1 * i ** -0.25 for i in range(1, spp + 1)]
        want[spp] = expected_mean(radii)
        msg = f'{technique}, {spp} passes: {got[spp]:.5f} +- {se[spp]:.5f}, expected {want[spp]:.5f}'
        assert abs(got[spp] - want[spp]) < 4 * se[spp], msg
    assert abs(want[64] - want[16]) > 6 * max(se.values()), f'the test cannot tell: {want}, {se}'
    bdpt = mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 4}), spp=4)
    assert float(np.max(np.array(bdpt))) == 0.0      # no connection samples these paths


def test_thin_glass_reflects_with_the_probability_of_its_reflectance():
    """A thin pane in front of a black wall, under a sky of 1, seen head-on: a pixel is R, the
    pane's reflectance. A walk that reaches the pane stops with probability R (1 - its Null
    lobe's transmission) and then samples its reflection alone (media.MediaInfo.exclude_null):
    one sample is 1 with probability R, else 0, so a pixel of N samples has variance
    R (1 - R) / N. Sampling the whole BSDF at the stop (Null again with probability 1 - R,
    ending the lane) reflects with probability R^2 and weight 1 / R: 14 times the variance."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        'type': 'scene', 'sky': {'type': 'constant', 'radiance': 1.0},
        'pane': {'type': 'rectangle', 'bsdf': {'type': 'thindielectric'}},
        'wall': {'type': 'rectangle', 'to_world': T().translate([0, 0, -1]).scale(3), 'bsdf': {'type': 'diffuse', 'reflectance': 0.0}},
        'sensor': {'type': 'orthographic', 'to_world': T().look_at(origin=[0, 0, 2], target=[0, 0, 0], up=[0, 1, 0]).scale([0.5, 0.5, 1.0]),
                   'film': {'type': 'hdrfilm', 'width': 16, 'height': 16, 'rfilter': {'type': 'box'}, 'pixel_format': 'rgb'}}})
    r = 1.0 - float(sheet_transmittance(np.array([1.0]))[0])
    spp = 64
    img = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'pt'}),
                             spp=spp, seed=5))[..., 0].ravel()
    assert abs(img.mean() - r) < 4 * np.sqrt(r * (1 - r) / spp / img.size), (img.mean(), r)
    assert 0.7 < img.var(ddof=1) / (r * (1 - r) / spp) < 1.4, (img.var(ddof=1), r * (1 - r) / spp)


@pytest.mark.parametrize('technique', ['pt', 'bdpt'])
def test_a_thin_sheet_passes_shadow_rays(technique):
    """The plane seen through a thindielectric sheet, lit by the point light through it: the
    sheet's transmission is a Null lobe, which shadow rays and connections pass with its
    transmittance, so pt and bdpt render the sharp irradiance times the sheet's transmittance
    on the light's side and on the camera's (before, as in Mitsuba's path, they rendered
    black). max_depth 2: passing a Null lobe is no bounce (as volpath counts), and the paths
    the sheet reflects back to the plane have 3 edges or more. The image mean within 4 standard
    errors of the quadrature."""
    scene = plane_scene(sheet='thin')
    t_cam = float(sheet_transmittance(np.array([1.0]))[0])       # the camera looks straight down
    b = render_batches(scene, {'type': 'bdpt', 'max_depth': 2, 'technique': technique}, 16, 8)
    per_batch = b.mean(axis=(1, 2, 3))
    got, se = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    want = t_cam * expected_mean([0.0], through_sheet)
    assert abs(got - want) < 4 * se + 1e-5 * want, f'{technique}: {got:.5f} +- {se:.5f}, expected {want:.5f}'


@pytest.mark.slow
def test_vm_converges_to_bdpt_on_a_diffuse_box():
    """vm alone renders what bdpt renders, slowly: a Cornell box (max_depth 4, 32x32, 1024 light
    subpaths a pass, radius 0.02, alpha 0.75) over 16 x 512 passes against bdpt: the image mean
    within 4 standard errors plus 0.5% (the remaining blur), every 4x4 block within 4 standard
    errors plus 3% (blocks at the box's edges and corners are blurred most)."""
    scene = cornell_scene(32)
    ref = render_batches(scene, {'type': 'bdpt', 'max_depth': 4}, 512, 8, seed0=50)
    got = render_batches(scene, {'type': 'bdpt', 'max_depth': 4, 'technique': 'vm', 'radius': 0.02}, 512, 16)
    m_got, m_ref = got.mean(axis=(1, 2, 3)), ref.mean(axis=(1, 2, 3))
    se = np.sqrt(m_got.var(ddof=1) / len(m_got) + m_ref.var(ddof=1) / len(m_ref))
    assert abs(m_got.mean() - m_ref.mean()) < 4 * se + 0.005 * m_ref.mean(), (m_got.mean(), m_ref.mean(), se)

    def blocks(x):
        K, H, W, C = x.shape
        return x.reshape(K, H // 4, 4, W // 4, 4, C).mean(axis=(2, 4))
    a, b = blocks(got), blocks(ref)
    diff = np.abs(a.mean(0) - b.mean(0))
    se_b = np.sqrt(a.var(0, ddof=1) / a.shape[0] + b.var(0, ddof=1) / b.shape[0])
    bad = diff > 4 * se_b + 0.03 * b.mean(0)
    assert not bad.any(), f'{bad.sum()} blocks off, worst {(diff / np.maximum(b.mean(0), 1e-9)).max():.3f}'


def test_a_bucket_shared_by_neighbouring_cells_is_read_once():
    """merge.Merger.ranges over the 2 x 2 x 2 cells around a point: where several of the cells
    hash to one bucket (here all eight: a table of one bucket holding 5 entries), its entries
    are visited once, not once per cell (which would count those light vertices up to 8 times)."""
    from bdpt_jit.merge import MergeSchedule, Merger, PhotonGrid
    scene = plane_scene()
    grid = PhotonGrid.__new__(PhotonGrid)
    grid.origin = mi.Point3f(0.0)
    grid.mask = dr.opaque(mi.UInt32, 0)                      # one bucket
    grid.schedule = MergeSchedule(scene, 0.01, 0.75, 1, 1, 16)
    grid.start = mi.UInt32([0, 5])                            # bucket 0: entries 0..4
    starts, totals = Merger(None, grid, None).ranges(mi.Point3f([0.3, 1.7], [0.2, -0.4], [0.0, 0.0]), mi.UInt32(0))
    assert np.array(totals[8]).tolist() == [5, 5]
    assert np.array(starts[0]).tolist() == [0, 0]


def test_radius_schedule_is_knaus_and_zwickers():
    """merge.MergeSchedule: iteration i (from 1, over every render) merges within
    r_i = r_1 i^((alpha-1)/2) and weights with eta_i = pi r_i^2 N; checked exactly (float32)
    for the iterations of a pass that starts at iteration 5. A schedule whose exponent is off
    (doubled: (alpha - 1) instead of (alpha - 1) / 2) is 30% off at i = 5 here."""
    from bdpt_jit.merge import MergeSchedule, scene_radius
    scene = plane_scene()
    alpha, first, spp_pass, pixels = 0.6, 5, 4, 7
    s = MergeSchedule(scene, 0.01, alpha, first, spp_pass, pixels)
    r1 = 0.01 * scene_radius(scene)
    i = np.arange(first, first + spp_pass, dtype=np.float64)
    want = r1 * i ** ((alpha - 1) / 2)
    got = np.array(s.radius(mi.UInt32(np.arange(spp_pass))), np.float64)
    assert np.allclose(got, want, rtol=1e-6), (got, want)
    idx = mi.UInt32(np.arange(spp_pass * pixels))
    eta = np.array(s.eta(idx), np.float64)
    assert np.allclose(eta, np.pi * np.tile(want, pixels) ** 2 * pixels, rtol=1e-5)
    assert s.r_last == pytest.approx(want[-1], rel=1e-6)


def test_the_merge_kernel_uses_its_own_iterations_radius():
    """merge.Merger.gather: a camera vertex of iteration i gathers within r_i, the radius its
    MIS weights take (eta_i = pi r_i^2 N), and normalises by pi r_i^2 N. Two iterations in one
    pass (alpha 0.25: r_2 = 0.77 r_1), one light vertex each, at 0.88 r_1 from its camera vertex:
    iteration 1 finds its vertex with exactly R/pi beta_y / (pi r_1^2 N); iteration 2 does not
    (0.88 r_1 > r_2). A kernel that took the next iteration's radius (or the previous one's)
    fails one of the two, and a normalisation by another radius is 30% or more off."""
    from bdpt_jit.merge import MergeSchedule, Merger, PhotonGrid
    from bdpt_jit.mis import MISState
    from bdpt_jit.store import LightStore, StoredVertex
    from bdpt_jit.transport import Subpath
    from bdpt_jit.vertex import Vertex
    scene = plane_scene()
    integ = mi.load_dict({'type': 'bdpt', 'technique': 'vm'})
    ctx = integ.make_context(scene, scene.sensors()[0])
    sched = MergeSchedule(scene, 0.01, 0.25, 1, 2, 1)             # iterations 1 and 2, N = 1
    r = np.array(sched.radius(mi.UInt32([0, 1])), np.float64)
    assert r[1] < 0.8 * r[0]
    z = np.array([[0.1, -0.2, 0.0], [0.3, 0.1, 0.0]])              # the camera vertices (on the plane)
    y = z + np.array([0.88 * r[0], 0.0, 0.0])                     # each iteration's light vertex

    def hit(pts):
        o = mi.Point3f(*[mi.Float(pts[:, k] + (1.0 if k == 2 else 0.0)) for k in range(3)])
        si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(0, 0, -1)))
        assert np.all(np.array(si.is_valid()))
        return si
    beta_y = 0.37
    si_y = hit(y)
    si_y.wi = mi.Vector3f(0, 0, 1)                                # the light came from straight above
    light = Subpath(beta=mi.Color3f(beta_y), mis=MISState(mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)),
                    depth=mi.UInt32(1), active=mi.Bool(True))
    store = LightStore(n=2, capacity=1, record=StoredVertex)
    StoredVertex.store(store.v, StoredVertex.make(Vertex(si_y, si_y.bsdf(), mi.Float(0.0)), light),
                       store.slot(mi.UInt32(0), dr.arange(mi.UInt32, 2)), mi.Bool(True))
    store.count = mi.UInt32([1, 1])
    merger = Merger(ctx, PhotonGrid(scene, store, sched), ctx.mis.for_pass())
    si_z = hit(z)
    si_z.wi = mi.Vector3f(0, 0, 1)                                # seen from straight above
    cam = Subpath(beta=mi.Color3f(1.0), mis=MISState(mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)),
                  depth=mi.UInt32(1), active=mi.Bool(True))
    got = np.array(merger.gather(dr.arange(mi.UInt32, 2), Vertex.at(ctx, si_z), cam, mi.Bool(True)))[0]
    want = RHO / np.pi * beta_y / (np.pi * r[0] ** 2 * 1)
    assert got[0] == pytest.approx(want, rel=1e-4), (got, want)
    assert got[1] == 0.0, got


@pytest.mark.parametrize('scene_file', ['caustic.xml', 'media/volumetric-caustic.xml'])
def test_merges_read_nothing_out_of_bounds(scene_file, capfd):
    """Dr.Jit's debug mode reports every gather outside its array: none from the merges' grids
    and gathers (merge.py, beams.py) with vcm merging everywhere, on surfaces and in a medium,
    at a radius that fills the cells. (Mitsuba's ImageBlock.put reports packet writes past its
    block in that mode for its own path and ptracer too: film.py's calls of it are left out.)
    Planted: the skip loop reading the entry after a query's last, fails."""
    import os
    scene = mi.load_file(os.path.join(os.path.dirname(__file__), '..', 'scenes', scene_file), res=16, max_depth=4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'vcm', 'merge_everywhere': True,
                          'radius': 0.1})
    was = dr.flag(dr.JitFlag.Debug)
    dr.set_flag(dr.JitFlag.Debug, True)
    try:
        dr.eval(mi.render(scene, integrator=integ, spp=4, seed=1))
        dr.sync_thread()
    finally:
        dr.set_flag(dr.JitFlag.Debug, was)
    err = capfd.readouterr().err
    bad = [line for line in err.splitlines() if 'out-of-bounds' in line and 'film.py' not in line]
    assert not bad, bad[:3]


@pytest.mark.parametrize('scene_file', ['caustic.xml', 'media/volumetric-caustic.xml'])
def test_a_query_merges_its_own_iteration_only_when_all_share_a_bucket(scene_file, monkeypatch):
    """The grids hash each entry's iteration with its cell, so a pass's iterations meet in a
    bucket only where hashes collide; merge.Merger.near and beams.BeamGather.candidate then keep
    the query's own (the iteration in the grids' copy of the positions). With one bucket for all
    (merge.BUCKETS tiny: every iteration's entries in it) the image is the one with the usual
    table, up to the order of the additions. Planted: the iteration test left out of either,
    fails (light vertices of the pass's other iterations merged too)."""
    import os
    from bdpt_jit import merge
    scene = mi.load_file(os.path.join(os.path.dirname(__file__), '..', 'scenes', scene_file), res=8, max_depth=4)
    images = []
    for buckets in (merge.BUCKETS, 1e-9):
        monkeypatch.setattr(merge, 'BUCKETS', buckets)
        integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'vcm', 'merge_everywhere': True,
                              'radius': 0.1})
        images.append(np.array(mi.render(scene, integrator=integ, spp=8, seed=3), np.float64))
    assert np.abs(images[0]).max() > 0
    np.testing.assert_allclose(images[1], images[0], rtol=1e-4, atol=1e-6 * np.abs(images[0]).max())
