"""Invariants that a correct renderer keeps exactly or in expectation: finite pixels, an exact
zero without emitters, and a light image (t=1 strategies) whose brightness does not depend on
resolution, samples per pixel or a crop window."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import assert_finite, cornell_scene, render_batches, scene_path


@pytest.mark.parametrize('technique', ['bdpt', 'pt', 'lt'])
@pytest.mark.parametrize('max_depth', [0, 1, 3, -1])
def test_no_emitters_renders_exact_zero(technique, max_depth):
    scene = cornell_scene(16, light=False)
    img = np.array(mi.render(scene, integrator=mi.load_dict(
        {'type': 'bdpt', 'technique': technique, 'max_depth': max_depth}), spp=4))
    assert np.all(img == 0.0)


def test_max_depth_zero_is_black_like_path():
    scene = cornell_scene(16)
    mine = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 0}), spp=4))
    ref = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'path', 'max_depth': 0}), spp=4))
    assert np.all(mine == 0.0) and np.all(ref == 0.0)


@pytest.mark.parametrize('scene_name', ['cornell-box.xml', 'paper-fig6.xml', 'caustic.xml'])
@pytest.mark.parametrize('technique,mis', [('bdpt', 'power'), ('bdpt', 'uniform'), ('pt', 'balance'), ('lt', 'power')])
def test_every_pixel_finite(scene_name, technique, mis):
    scene = mi.load_file(scene_path(scene_name), res=24, max_depth=-1)
    img = mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'technique': technique, 'mis': mis}), spp=8)
    a = assert_finite(img)
    assert a.min() >= 0.0


def light_image_mean(scene, spp, batches, region):
    """Mean of the light-tracing image (technique lt) over ``region`` (in crop pixels)."""
    b = render_batches(scene, {'type': 'bdpt', 'technique': 'lt', 'max_depth': 3}, spp, batches)
    y0, y1, x0, x1 = region
    per_batch = b[:, y0:y1, x0:x1, :].mean(axis=(1, 2, 3))
    return per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(batches)


def assert_same(a, b, what):
    (m1, s1), (m2, s2) = a, b
    z = abs(m1 - m2) / np.sqrt(s1 ** 2 + s2 ** 2)
    assert z < 4, f'{what}: {m1:.5g} +- {s1:.2g} vs {m2:.5g} +- {s2:.2g} ({z:.1f} sigma)'


def test_light_image_independent_of_resolution():
    # same field of view: the whole image's mean brightness
    a = light_image_mean(cornell_scene(16), 64, 8, (0, 16, 0, 16))
    b = light_image_mean(cornell_scene(48), 8, 8, (0, 48, 0, 48))
    assert_same(a, b, 'resolution 16 vs 48')


def test_light_image_independent_of_spp():
    a = light_image_mean(cornell_scene(24), 8, 8, (0, 24, 0, 24))
    b = light_image_mean(cornell_scene(24), 64, 8, (0, 24, 0, 24))
    assert_same(a, b, 'spp 8 vs 64')


def test_light_image_independent_of_crop_window():
    full = render_batches(cornell_scene(32), {'type': 'bdpt', 'technique': 'lt', 'max_depth': 3}, 64, 8)
    crop = render_batches(cornell_scene(32, crop=(8, 4, 16, 20)), {'type': 'bdpt', 'technique': 'lt', 'max_depth': 3}, 64, 8)
    assert crop.shape[1:3] == (20, 16)
    f = full[:, 4:24, 8:24, :].mean(axis=(1, 2, 3))
    c = crop.mean(axis=(1, 2, 3))
    assert_same((f.mean(), f.std(ddof=1) / np.sqrt(8)), (c.mean(), c.std(ddof=1) / np.sqrt(8)), 'crop window')


def test_non_square_film_matches_path():
    scene = cornell_scene(40, height=24)
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': 3}, 32, 8).mean(axis=(1, 2, 3))
    ref = render_batches(scene, {'type': 'path', 'max_depth': 3}, 256, 8, seed0=99).mean(axis=(1, 2, 3))
    assert_same((mine.mean(), mine.std(ddof=1) / np.sqrt(8)), (ref.mean(), ref.std(ddof=1) / np.sqrt(8)), 'non-square film')


def test_strategy_layers_sum_to_the_image():
    scene = mi.load_file(scene_path('paper-fig6.xml'), res=16, max_depth=4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'strategy_images': True})
    img = np.array(mi.render(scene, integrator=integ, spp=8))[:, :, :3]
    layers = integ.strategy_images
    assert set(layers) >= {'s0_t2', 's1_t1', 's2_t2', 's4_t1', 'other'}
    total = sum(v['weighted'] for v in layers.values())
    np.testing.assert_allclose(total, img, rtol=1e-4, atol=1e-5 * img.max())
    # a path of k edges has k+1 strategies: none beyond max_depth was counted
    assert not layers['other']['weighted'].any()
    for name, v in layers.items():
        assert np.all(np.isfinite(v['unweighted'])) and np.all(v['weighted'] <= v['unweighted'] + 1e-6)


def test_ray_statistics_are_exact_where_they_can_be():
    """pt with max_depth 1: one primary ray per sample, nothing else."""
    scene = cornell_scene(8)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 1, 'technique': 'pt', 'statistics': True})
    mi.render(scene, integrator=integ, spp=3)
    r = integ.last_render_info['rays']
    assert r['camera_rays'] == 8 * 8 * 3 and r['light_rays'] == 0 and r['shadow_rays'] == 0
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 2, 'technique': 'lt', 'statistics': True})
    mi.render(scene, integrator=integ, spp=2)
    r = integ.last_render_info['rays']
    assert r['camera_rays'] == 0 and r['light_rays'] == 8 * 8 * 2       # one emission ray each
    assert 0 < r['shadow_rays_blocked'] < r['shadow_rays']


def uniform_view(rfilter, width=16, height=12):
    """A camera facing an emitter of radiance 1 that fills its whole view (and 2 pixels more on
    each side, no more: light subpaths start on it): every pixel is 1."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 40,
                   'film': {'type': 'hdrfilm', 'width': width, 'height': height,
                            'rfilter': {'type': rfilter}},
                   'to_world': T().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0])},
        'light': {'type': 'rectangle',
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [1.0, 1.0, 1.0]}},
                  'to_world': T().translate([0, 0, 1]).rotate([0, 1, 0], 180).scale([0.47, 0.37, 1])}})


@pytest.mark.parametrize('rfilter,technique', [('gaussian', 'lt'), ('gaussian', 'bdpt'), ('tent', 'lt'),
                                               ('lanczos', 'lt')])
def test_edge_pixels_with_a_wide_filter(rfilter, technique):
    """Splats come only from inside the film, so with a filter wider than a pixel the light
    image's edge pixels lack the filter's mass beyond the edge (Mitsuba's ptracer renders them
    0.84 with the Gaussian filter): film.splat_gain makes them path's pixels, which average the
    samples inside. The outer two rings of pixels and the rest, each against the exact 1."""
    b = render_batches(uniform_view(rfilter), {'type': 'bdpt', 'technique': technique, 'max_depth': 1}, 256, 8)
    edge = np.ones(b.shape[1:3], bool)
    edge[2:-2, 2:-2] = False
    for what, mask in (('edge', edge), ('inside', ~edge)):
        per_batch = b[:, mask, :].mean(axis=(1, 2))
        m, se = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
        assert abs(m - 1.0) < 4 * se + 1e-4, f'{what} pixels: {m:.5f} +- {se:.2g}, exactly 1 expected'


def test_splat_coverage_of_the_tent_filter():
    """A tent of radius 1 centred on an end pixel has 1/8 of its mass beyond the end."""
    from bdpt_jit.film import splat_coverage
    cov = splat_coverage(mi.load_dict({'type': 'tent'}), 6)
    assert np.allclose(cov, [0.875, 1, 1, 1, 1, 0.875], atol=1e-5), cov
