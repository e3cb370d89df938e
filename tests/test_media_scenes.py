"""The scenes with media of tests/media_scenes.py and their analytic values, checked with Mitsuba's
own `volpath` and `volpathmis` (no bdpt here: tests/test_media_agreement.py compares bdpt with
these). They establish that the scenes say what their docstrings say and that the analytic
values are right, before any bdpt render is compared with them.

Statistics: 16 independent batches (fixed seeds) per render; against an analytic value
media_scenes.assert_value (image mean within 4 standard errors, 4x4 blocks and pixels by one-sample
t-tests Sidak-corrected at 0.01); volpath against volpathmis helpers.agreement (Welch, pixels and
4x4 blocks, Sidak at 0.01) with a relative resolution of 1e-5 (media_scenes.FLOAT_FLOOR: the sky
seen through empty voxels is 0.2 exactly in one integrator and 0.2 - 1e-7 in the other). 16x16
pixels.

They render only Mitsuba's integrators, so they are in the slow set (`-m slow`), to run when
media_scenes.py or Mitsuba changes: CI holds bdpt to the same analytic values, and the references
(tests/references) stay those these checks passed with. The checks of this project's own files
(the benchmark scenes, the quadrature's convergence, the sensor's medium) stay in CI."""

import math

import mitsuba as mi
import numpy as np
import pytest

import media_scenes as ms
from helpers import agreement, render_batches

K = 16
VALIDATION = pytest.mark.slow       # (the module docstring)


def volpath(max_depth=-1, which='volpath', **params):
    return {'type': which, 'max_depth': max_depth, **params}


def test_sensor_medium_is_the_spheres_medium():
    """The sensor's ``medium`` given as a ``ref`` is the very object the sphere holds (one medium:
    a camera inside it starts in it), and a point light's ``medium`` is kept."""
    sc = ms.load('absorbing_sphere')
    assert sc.sensors()[0].get_medium() is not None
    assert sc.sensors()[0].get_medium() == sc.shapes()[0].interior_medium()
    room = ms.load('fog_room', light='point')
    fog = room.sensors()[0].get_medium()
    assert all(e.get_medium() == fog for e in room.emitters())
    assert all(s.interior_medium() == fog and s.exterior_medium() == fog for s in room.shapes())


ABSORBING = [
    # (sigma_t, radius, translate): every pixel exp(-sigma_t radius)
    (1.0, 1.0, (0.0, 0.0, 0.0)),
    (1e3, 1.0, (0.0, 0.0, 0.0)),          # exp(-1000) = 0 exactly
    (1e-4, 1e4, (0.0, 0.0, 0.0)),         # a thin medium in a large sphere: exp(-1)
    (1e3, 1e-3, (0.0, 0.0, 0.0)),         # the scene scaled by 1e-3: exp(-1)
    (1.0, 1.0, (1e4, -1e4, 1e4)),         # moved by 1e4: exp(-1)
]


@VALIDATION
@pytest.mark.parametrize('which', ['volpath', 'volpathmis'])
@pytest.mark.parametrize('sigma_t,radius,translate', ABSORBING)
def test_absorbing_sphere_is_exp_minus_optical_depth(which, sigma_t, radius, translate):
    """(a) Camera at the centre of the absorbing null sphere. Catches: the sensor's medium
    ignored (1), the medium not left at the null boundary (0)."""
    b = render_batches(ms.load('absorbing_sphere', sigma_t=sigma_t, radius=radius, translate=translate),
                       volpath(-1, which), 16, K)
    ms.assert_value(b, ms.absorbing_sphere_value(sigma_t, radius), f'{which} sigma_t {sigma_t} radius {radius}')


@VALIDATION
def test_absorbing_sphere_thin_is_finite():
    """(h) sigma_t 1e-4 over a radius of 1: exp(-1e-4), indistinguishable from 1 at this sample
    count; held to its value within 2e-4."""
    b = render_batches(ms.load('absorbing_sphere', sigma_t=1e-4), volpath(), 16, K)
    ms.assert_value(b, math.exp(-1e-4), 'thin', rtol=2e-4)


@VALIDATION
@pytest.mark.parametrize('grid', ['octants', 'single'])
def test_absorbing_grid_matches_quadrature(grid):
    """(a, h) A heterogeneous absorbing cube with the camera at its centre, piecewise-constant
    voxels: two empty octants ('octants') and a single voxel ('single'), against the pixel
    quadrature of exp(-sigma v d). Catches: a grid read in another axis order (the four octants
    seen have different densities), an empty voxel treated as dense."""
    b = render_batches(ms.load('absorbing_cube', grid=grid), volpath(), 16, K)
    ms.assert_value(b, ms.absorbing_cube_expected(grid)[..., None], f'absorbing cube {grid}')


def test_absorbing_cube_quadrature_converged():
    """The pixel quadrature with 8 x 8 nodes against 16 x 16 (the cube's edges cross pixels,
    where the integrand's slope jumps), and the single-scattering one likewise."""
    a, b = ms.absorbing_cube_expected('octants', n=8), ms.absorbing_cube_expected('octants', n=16)
    assert np.abs(a - b).max() < 2e-4
    (a, mask), (b, _) = ms.single_scatter_expected(n=8), ms.single_scatter_expected(n=12)
    assert np.abs(a - b)[mask].max() < 1e-6 * a.max()


FURNACES = ms.FURNACES + ms.STIFF_FURNACES


@VALIDATION
@pytest.mark.parametrize('kind,g,inside,sigma_t,radius,grid', FURNACES)
def test_furnace_renders_the_emitters_radiance(kind, g, inside, sigma_t, radius, grid):
    """(b) Albedo 1 in a null sphere under a constant emitter of 1, max_depth -1 (no Russian
    roulette: rr_depth 1e5): every pixel 1. Catches: a lost or doubled scattering weight, a
    phase function that does not integrate to 1, null collisions counted as events that scatter."""
    b = render_batches(ms.load('furnace', kind=kind, g=g, inside=inside, sigma_t=sigma_t, radius=radius, grid=grid),
                       volpath(-1, rr_depth=100000), 16, K)
    ms.assert_value(b, ms.FURNACE_VALUE, f'furnace {kind} g {g} inside {inside} sigma_t {sigma_t} {grid}')


@VALIDATION
def test_furnace_at_finite_depth_is_darker():
    """The furnace holds only at unbounded depth: at max_depth 2 the image mean is well below 1
    (a test that would pass with a wrong depth convention is no furnace test)."""
    b = render_batches(ms.load('furnace', inside=True), volpath(2), 16, 4)
    assert b.mean() < 0.9


@VALIDATION
@pytest.mark.parametrize('which', ['volpath', 'volpathmis'])
@pytest.mark.parametrize('sigma_t,albedo,g', [(1.0, 0.5, 0.0), (1.0, 0.5, 0.7), (3.0, 0.9, -0.5)])
def test_single_scattering_matches_quadrature(which, sigma_t, albedo, g):
    """(c) At max_depth 2 volpath renders single scattering only (one real collision, then the
    point light by emitter sampling: Mitsuba counts medium collisions as bounces, null
    boundaries not), equal to the 1D quadrature along each camera ray, in the pixels off the
    sphere's silhouette. Catches (in the quadrature): the HG sign convention (per pixel g = +0.7
    and -0.7 differ by up to 30% here), the transmittance towards the light left out."""
    val, mask = ms.single_scatter_expected(sigma_t, albedo, g)
    b = render_batches(ms.load('single_scatter', sigma_t=sigma_t, albedo=albedo, g=g), volpath(2, which), 64, K)
    ms.assert_value(b, val, f'{which} single scattering sigma_t {sigma_t} g {g}', mask=mask)


@VALIDATION
def test_single_scattering_depth_convention():
    """max_depth 1 renders exactly 0 (the point light is never seen), max_depth 3 more than
    single scattering (double scattering adds): the quadrature is the max_depth 2 image."""
    sc = ms.load('single_scatter')
    assert np.all(render_batches(sc, volpath(1), 4, 2) == 0.0)
    val, mask = ms.single_scatter_expected()
    assert render_batches(sc, volpath(3), 64, 2).mean(axis=0)[mask].sum() > 1.1 * 3 * val[mask].sum()


AGREEMENT = [
    # (scene, params, max_depth, spp per batch): volpath and volpathmis, 16 batches each
    ('fog_room', {}, 5, 64),
    ('fog_room', {'light': 'point', 'g': 0.5}, 5, 64),        # both share the point light's 1/d^2
    ('fog_room', {'light': 'sphere', 'g': 0.5}, 5, 64),
    ('grid_box', {}, 5, 64),
    ('glass_media', {}, 6, 128),
    ('volumetric_caustic', {'light_radius': 0.15}, 6, 128),
]


@VALIDATION
@pytest.mark.parametrize('name,params,max_depth,spp', AGREEMENT)
def test_volpath_and_volpathmis_agree(name, params, max_depth, spp):
    """(d)-(g) Mitsuba's two volumetric path tracers agree block by block: the references bdpt is
    compared with (cached: media_scenes.media_reference) are two estimators of one image."""
    a = ms.media_reference(name, max_depth, 'volpath', spp, K, params=params)
    b = ms.media_reference(name, max_depth, 'volpathmis', spp, K, params=params)
    ok, msg = agreement(a, b, alpha=0.01, floor=ms.FLOAT_FLOOR)
    assert ok, f'{name} {params} max_depth {max_depth}: {msg}'


@pytest.mark.parametrize('file,glass', [('volumetric-caustic.xml', True), ('fog.xml', False)])
def test_benchmark_scene_files_are_the_dicts(file, glass):
    """scenes/media/*.xml (benchmarks/bench_media.py) are media_scenes.volumetric_caustic written
    out: mi.load_file loads them, and volpath with one seed renders the dict's image up to the
    float rounding of their transforms (a path that diverges on a rare event: measured max 4e-4
    on a mean of 0.075)."""
    from helpers import scene_path
    a = mi.load_file(scene_path('media/' + file), res=16)
    b = ms.load('volumetric_caustic', glass=glass, res=16)
    x, y = (np.array(mi.render(s, integrator=mi.load_dict(volpath(8)), spp=64, seed=3)) for s in (a, b))
    assert abs(x.mean() / y.mean() - 1) < 1e-3
    assert np.mean(np.abs(x - y) > 1e-3 * y.max()) < 0.01
    assert a.sensors()[0].get_medium() is not None and len(a.shapes()) == len(b.shapes())
