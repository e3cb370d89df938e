"""Every emitter kind: agreement with Mitsuba, a white furnace, and stiff light configurations.

References as in test_agreement.py. Mitsuba's `path` cannot hit point, spot or directional
lights, so it misses every caustic they cast through glass or off a mirror; where such caustics
exist (sun-room.xml) bdpt and lt are compared with `ptracer` in the pixels light tracing can
render, and pt (which shares path's blind spot) with `path` at equal samples."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (agreement, assert_finite, cornell_scene, file_reference, load_scene, no_delta_mask, reference,
                     render_batches)
from stability_cases import cornell, lowpoly_sphere_mesh

RES = 32
BATCHES = 16
REF_SEED = 20_000           # first seed of the references' batches


@pytest.mark.parametrize('max_depth,technique,mis', [
    (2, 'bdpt', 'power'),
    (3, 'bdpt', 'power'),
    (5, 'bdpt', 'power'),
    (5, 'bdpt', 'uniform'),
    (4, 'pt', 'power'),
    (4, 'lt', 'power'),
])
def test_all_lights_agree_with_path(max_depth, technique, mis):
    """area + point + spot + directional + envmap together; no delta surfaces, so `path` is a
    valid reference in every pixel (lt: where no environment is seen directly)."""
    name = 'all-lights.xml'
    scene = load_scene(name, RES, max_depth)
    ref = file_reference(name, RES, max_depth, 'path', 1024, BATCHES, REF_SEED)
    # uniform weights render the glossy sphere's reflection of the small lights heavy-tailed:
    # one pixel 25% low at 16 x 256 spp, within the test at 16 x 1024
    spp = {'pt': 1024, 'lt': 64}.get(technique, 1024 if mis == 'uniform' else 64)
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique, 'mis': mis},
                          spp, BATCHES)
    mask = no_delta_mask(scene) if technique == 'lt' else None
    ok, msg = agreement(mine, ref, mask=mask)
    assert ok, f'{technique}/{mis} max_depth={max_depth}: {msg}'


@pytest.mark.parametrize('max_depth,technique,mis', [
    (3, 'bdpt', 'power'),
    (5, 'bdpt', 'power'),
    (5, 'bdpt', 'uniform'),
    (5, 'lt', 'power'),
    (5, 'pt', 'power'),
])
def test_sun_room(max_depth, technique, mis):
    """The paper's Figure 7 setup: sun and sky through a ceiling opening, glass and mirror."""
    name = 'sun-room.xml'
    scene = load_scene(name, RES, max_depth)
    if technique == 'pt':
        ref, mask, spp = file_reference(name, RES, max_depth, 'path', 1024, BATCHES, REF_SEED), None, 1024
    else:
        ref, mask = file_reference(name, RES, max_depth, 'ptracer', 1024, BATCHES, REF_SEED), no_delta_mask(scene)
        # lt is ptracer's estimator: splats from vertices close to the camera make it
        # heavy-tailed, so it is compared at the reference's sample count
        spp = 1024 if technique == 'lt' else 256 if mis == 'uniform' else 64
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique, 'mis': mis},
                          spp, BATCHES)
    ok, msg = agreement(mine, ref, mask=mask)
    assert ok, f'{technique}/{mis} max_depth={max_depth}: {msg}'


def test_path_misses_the_sun_caustics_that_bdpt_renders():
    """Where the sun's light reaches the floor only through the glass sphere, bdpt agrees with
    ptracer while `path` is darker: a reference check, not a bdpt assertion alone."""
    name, md = 'sun-room.xml', 5
    scene = load_scene(name, RES, md)
    mask = no_delta_mask(scene)
    pt_ref = file_reference(name, RES, md, 'ptracer', 1024, BATCHES, REF_SEED).mean(axis=0)[mask].mean()
    path_ref = file_reference(name, RES, md, 'path', 1024, BATCHES, REF_SEED).mean(axis=0)[mask].mean()
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': md}, 64, BATCHES).mean(axis=0)[mask].mean()
    assert path_ref < pt_ref * 0.995                  # path misses the caustics
    assert abs(mine - pt_ref) < abs(path_ref - pt_ref) / 3


def furnace_scene(res=16):
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 50,
                   'to_world': mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': res, 'height': res, 'pixel_format': 'rgb',
                            'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent', 'sample_count': 16}},
        'env': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': 0.8}},
        'white': {'type': 'sphere', 'center': [-0.7, 0, 0], 'radius': 0.6,
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 1.0}}},
        'glass': {'type': 'sphere', 'center': [0.7, 0.1, 0.5], 'radius': 0.5,
                  'bsdf': {'type': 'dielectric', 'int_ior': 1.5}},
        'plate': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, -0.8, 0]).rotate([1, 0, 0], -90).scale(1.5),
                  'bsdf': {'type': 'twosided', 'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 1.0}}}},
    })


@pytest.mark.parametrize('technique,mis', [('bdpt', 'power'), ('bdpt', 'uniform'), ('pt', 'power')])
def test_white_furnace(technique, mis):
    """A constant environment Le around white diffuse (albedo 1) and smooth dielectric objects:
    every pixel is Le, with max_depth -1 (Russian roulette on, light storage grown as needed)."""
    scene = furnace_scene()
    b = render_batches(scene, {'type': 'bdpt', 'max_depth': -1, 'technique': technique, 'mis': mis}, 64, 8)
    per_batch = b.mean(axis=(1, 2, 3))
    mean, sigma = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    assert abs(mean - 0.8) <= 4 * sigma, f'{mean} vs 0.8 (sigma {sigma})'
    px = b.mean(axis=0)[:, :, 0]
    px_sigma = b.std(axis=0, ddof=1)[:, :, 0] / np.sqrt(b.shape[0])
    from scipy import stats
    p = 2 * stats.t.sf(np.abs(px - 0.8) / np.maximum(px_sigma, 1e-9), b.shape[0] - 1)
    exact = px_sigma < 1e-7                           # pixels seeing only the environment
    assert np.all(np.abs(px[exact] - 0.8) < 1e-5)
    assert p[~exact].min() >= 1 - 0.99 ** (1 / max((~exact).sum(), 1)), f'min p {p[~exact].min()}'


def box_with(emitter, res=16):
    d = cornell(res, light=False)
    d['extra'] = emitter
    return mi.load_dict(d)


@pytest.mark.parametrize('case', ['point_near_wall', 'spot_away', 'envmap_one_texel'])
@pytest.mark.parametrize('technique', ['bdpt', 'pt', 'lt'])
def test_stiff_lights_render_finite(case, technique, tmp_path):
    if case == 'point_near_wall':          # 1e-4 from the back wall (z = -1)
        scene = box_with({'type': 'point', 'position': [0.1, 0.2, -1 + 1e-4], 'intensity': {'type': 'rgb', 'value': 1.0}})
    elif case == 'spot_away':              # points out of the open front, at nothing
        scene = box_with({'type': 'spot', 'cutoff_angle': 10,
                          'to_world': mi.ScalarTransform4f().look_at(origin=[0, 0, 0.5], target=[0, 0, 10], up=[0, 1, 0])})
    else:
        env = np.zeros((16, 32, 3), np.float32)
        env[5, 7] = 1e4
        path = str(tmp_path / 'env.exr')
        mi.Bitmap(env).write(path)
        scene = box_with({'type': 'envmap', 'filename': path})
    img = mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': technique}), spp=16)
    a = assert_finite(img)
    assert a.min() >= -1e-6
    if case == 'spot_away':                # no light reaches anything the camera sees
        assert np.all(a == 0)


def thinlens_box():
    return cornell_scene(RES, camera={'type': 'thinlens', 'aperture_radius': 0.1, 'focus_distance': 3.0})


@pytest.mark.parametrize('max_depth,technique,mis', [
    (1, 'bdpt', 'power'),       # the light seen through the lens: s=0 against s=1,t=1
    (3, 'bdpt', 'power'),
    # (CI time: the lens enters t=1, which lt covers, the first camera ray, which pt and bdpt cover,
    # and the MIS weights, which bdpt with the power heuristic checks)
    pytest.param(4, 'bdpt', 'uniform', marks=pytest.mark.slow),
    (3, 'pt', 'power'),
    (3, 'lt', 'power'),
    (3, 'lt', 'uniform'),
])
def test_thinlens_cornell_box(max_depth, technique, mis):
    """A thin-lens view (defocused) of the Cornell box: light-image splats through sampled lens
    points; no delta surfaces, so `path` is a reference everywhere."""
    scene = thinlens_box()
    ref = reference(('thinlens-box', RES), thinlens_box, {'type': 'path', 'max_depth': max_depth},
                    1024, BATCHES, 30_000)
    spp = 1024 if technique == 'pt' or mis == 'uniform' else 64
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique, 'mis': mis}, spp, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'{technique}/{mis} max_depth={max_depth}: {msg}'


def against_path(key, build, max_depth, technique, spp, seed0, mask=None):
    """bdpt (``technique``, ``spp`` a batch) on the scene ``build()`` against Mitsuba's path (a
    reference of 1024 spp a batch from seed ``seed0``, cached under ``key``), pixel by pixel and
    in blocks, in the pixels ``mask(scene)`` where given: (passed, message)."""
    ref = reference(key, build, {'type': 'path', 'max_depth': max_depth}, 1024, BATCHES, seed0)
    scene = build()
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique}, spp, BATCHES)
    return agreement(mine, ref, mask=None if mask is None else mask(scene))


def box_behind_a_wall(camera):
    """The Cornell box closed by a front wall at z = +1 facing in, seen from outside (z = 3.9)
    through it: near_clip 2.95 clips the wall away (2.9 from the camera on its axis, further
    off it), as scenes clip a room's wall to look in."""
    d = cornell(16, closed=True, camera={'type': camera, 'fov': 39.3, 'near_clip': 2.95,
                                         'aperture_radius': 0.1, 'focus_distance': 3.9})
    if camera == 'perspective':
        d['sensor'].pop('aperture_radius'), d['sensor'].pop('focus_distance')
    d['sensor']['to_world'] = mi.ScalarTransform4f().look_at(origin=[0, 0, 3.9], target=[0, 0, 0], up=[0, 1, 0])
    return mi.load_dict(d)


@pytest.mark.parametrize('camera', ['perspective', 'thinlens'])
@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_near_clip_beyond_a_wall(camera, technique):
    """Camera rays start on the near-clip plane, so t=1 connections end there
    (cameras.Perspective.near_point): ended at the lens point, the wall hid every light vertex
    (lt black, bdpt 74% dark); ended near_clip (not near_clip / cos) from it, the pixels more
    than 10 degrees off the axis would still be behind the wall. Splats of points the clip
    planes cut away are left out (cameras.Perspective.between_clip_planes; Mitsuba's thinlens
    does not: lt 1.1% bright with it, where the clip cuts the edges of the side walls)."""
    ok, msg = against_path(('box-behind-a-wall', camera), lambda: box_behind_a_wall(camera), 3, technique, 64, 50_000)
    assert ok, f'{camera} {technique}: {msg}'


def box_past_the_far_plane(camera):
    """The Cornell box seen from z = 3.9 with far_clip 4.5: its back wall (4.9 away on the
    axis) and the back of its floor, ceiling and side walls lie beyond the far-clip plane."""
    d = cornell(16, camera={'type': camera, 'fov': 39.3, 'far_clip': 4.5, 'aperture_radius': 0.1,
                            'focus_distance': 3.9})
    if camera == 'perspective':
        d['sensor'].pop('aperture_radius'), d['sensor'].pop('focus_distance')
    d['sensor']['to_world'] = mi.ScalarTransform4f().look_at(origin=[0, 0, 3.9], target=[0, 0, 0], up=[0, 1, 0])
    return mi.load_dict(d)


@pytest.mark.parametrize('camera', ['perspective', 'thinlens'])
def test_far_clip_cuts_light_tracing_s_splats(camera):
    """Splats of points beyond the far-clip plane are left out (between_clip_planes: Mitsuba
    3.9.1's thinlens computes the test and drops it); lt against path, which sees nothing there."""
    ok, msg = against_path(('box-past-the-far-plane', camera), lambda: box_past_the_far_plane(camera), 3, 'lt',
                           64, 55_000)
    assert ok, f'{camera}: {msg}'


def plane_under_a_compensated_envmap():
    """A plane and a rough plastic ball under an `envmap` with `mis_compensation` (a sun-like
    spot and a sky varying along the azimuth), seen from above."""
    h, w = 32, 64
    sky = np.full((h, w, 3), 0.5, np.float32) * (1 + 0.8 * np.sin(np.arange(w) / w * 2 * np.pi))[None, :, None]
    sky[4:8, 10:14] = 200.0
    T = mi.ScalarTransform4f
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 50, 'to_world': T().look_at(origin=[0, 2, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': 16, 'height': 16, 'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3), 'bsdf': {'type': 'diffuse'}},
        'ball': {'type': 'sphere', 'center': [0, 0.5, 0], 'radius': 0.5, 'bsdf': {'type': 'roughplastic', 'alpha': 0.2}},
        'env': {'type': 'envmap', 'bitmap': mi.Bitmap(sky), 'mis_compensation': True}})


def test_light_tracing_under_an_envmap_with_mis_compensation():
    """Mitsuba's envmap with mis_compensation samples no direction darker than its mean, so
    light subpaths must leave it in uniform directions too where nothing else renders their
    paths (technique lt; endpoints.EmitterTable._env_direction): lt was 6.3% dark here
    (ptracer is 6.1%), p 6e-12 per pixel. Where the environment is seen directly lt renders
    nothing (no_delta_mask leaves those pixels out)."""
    ok, msg = against_path(('compensated-envmap', 16), plane_under_a_compensated_envmap, 4, 'lt', 256, 60_000,
                           mask=no_delta_mask)
    assert ok, msg


def rotated_sphere_light(flipped):
    """A sphere light whose to_world rotates it: small, in the Cornell box without its ceiling
    light, or (``flipped``) a large one around the box, its normals flipped to emit inwards."""
    T = mi.ScalarTransform4f
    d = cornell(16)
    d.pop('light')
    if flipped:
        d.pop('back', None)
        d['shell'] = {'type': 'sphere', 'flip_normals': True, 'to_world': T().rotate([0.6, 0.8, 0.0], 70).scale(6.0),
                      'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [1.0, 0.8, 0.6]}}}
    else:
        d['bulb'] = {'type': 'sphere', 'to_world': T().translate([0.3, 0.5, 0.2]).rotate([1, 0, 0], 70).scale(0.03),
                     'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [30.0, 30.0, 30.0]}}}
    return mi.load_dict(d)


@pytest.mark.parametrize('flipped', [False, True])
@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_rotated_sphere_lights(flipped, technique):
    """Light subpaths leave a sphere light around the normal of their start point in the world:
    Mitsuba 3.9.1's sphere sample_position returns it in the sphere's own frame
    (emitter_tables.sphere_positions). Before, under the small rotated bulb lt was 29% dark and
    bdpt 24%; inside the flipped shell lt 56% dark and bdpt 0.8% bright."""
    ok, msg = against_path(('rotated-sphere-light', flipped), lambda: rotated_sphere_light(flipped), 4, technique,
                           256, 70_000)
    assert ok, f'flipped {flipped} {technique}: {msg}'


def sheared_sphere_light():
    """A sphere light in the Cornell box (without its ceiling light) placed by a rotation about
    an axis that is not a unit vector: Mitsuba 3.9.1's rotate does not normalise it, so to_world
    is not a rotation times a uniform scale (Mitsuba warns of the shear)."""
    T = mi.ScalarTransform4f
    d = cornell(16)
    d.pop('light')
    d['bulb'] = {'type': 'sphere', 'to_world': T().translate([0.1, 0.6, -0.1]).rotate([0.3, 0.2, 0.9], 40).scale(0.2),
                 'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [6.0, 5.0, 4.0]}}}
    return mi.load_dict(d)


@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_a_sphere_light_placed_by_a_transform_that_is_not_a_rotation(technique):
    """Mitsuba's sphere samples the point to_world * local while its rays hit the sphere of
    centre to_world * 0 and radius |to_world * x|: under a sheared to_world half the light
    subpaths started inside that sphere and met it first (lt 76% dark, bdpt 62%; path, which
    samples the sphere by its cone from outside, agrees with a render from hits alone). The
    point is put on the sphere rays hit (emitter_tables.sphere_positions)."""
    ok, msg = against_path(('sheared-sphere-light',), sheared_sphere_light, 4, technique, 256, 80_000)
    assert ok, f'{technique}: {msg}'


def scaled_spot():
    """A spot light in the Cornell box (without its ceiling light) pointing down, its to_world
    scaled 1.5 x 0.7 across its axis: it lights an elliptic cone."""
    T = mi.ScalarTransform4f
    d = cornell(16)
    d.pop('light')
    d['spot'] = {'type': 'spot', 'to_world': T().translate([0.0, 0.9, 0.0]).rotate([1, 0, 0], 90).scale([1.5, 0.7, 1.0]),
                 'cutoff_angle': 35, 'beam_width': 25, 'intensity': {'type': 'rgb', 'value': [5.0, 5.0, 5.0]}}
    return mi.load_dict(d)


def test_light_tracing_covers_the_elliptic_cone_of_a_scaled_spot():
    """Mitsuba's spot evaluates a direction by its local direction through the inverse of
    to_world: scaled unequally it lights an elliptic cone, which the cutoff's circular cone that
    light subpaths sampled did not cover (lt 4.2% dark, p 1e-27 in a block); the sampled cone
    now bounds the elliptic one (emitter_tables._spot_cone)."""
    ok, msg = against_path(('scaled-spot',), scaled_spot, 4, 'lt', 256, 90_000)
    assert ok, msg


def smooth_emitter_box(flip=False, hits_only=False):
    """The Cornell box (without its ceiling light) lit by a smooth-shaded sphere mesh of 48
    triangles (stability_cases.lowpoly_sphere_mesh, 4 x 8), emitting outwards, or (``flip``)
    inwards, where the camera sees from outside only the radiance its shading normals give the
    triangles' back sides. ``hits_only``: the emitter chosen by emitter sampling once in 10^4
    (a point light of intensity 0 takes the rest): Mitsuba's path then renders it from the
    hits of its BSDF samples, by the definition of the emitted radiance alone (its emitter
    sampling reads the shading normal as the area's)."""
    d = cornell(16)
    d.pop('light')
    emitter = {'type': 'area', 'radiance': {'type': 'rgb', 'value': [8.0, 8.0, 8.0]}}
    if hits_only:
        emitter['sampling_weight'] = 1e-4
        d['dark'] = {'type': 'point', 'position': [0.0, -5.0, 0.0], 'intensity': {'type': 'rgb', 'value': [0.0] * 3}}
    d['bulb'] = lowpoly_sphere_mesh(4, 8, radius=0.35, center=(0.1, 0.3, 0.0), emitter=emitter, flip=flip,
                                    bsdf={'type': 'twosided', 'bsdf': {'type': 'diffuse'}})
    return mi.load_dict(d)


@pytest.mark.parametrize('flip', [False, True])
@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_a_coarse_smooth_shaded_emitter_mesh(flip, technique):
    """Light subpaths leave a smooth-shaded emitter mesh by its triangles' normals, emitter
    sampling converts densities with them, and radiance that leaves behind a triangle (where
    the shading normal faces) is sampled too (smooth_emitters.py). Before, by the shading
    normal Mitsuba returns: bdpt and lt 2% bright; with flipped normals bdpt 91% dark, lt
    black. Against path rendering the emitter from hits alone (smooth_emitter_box)."""
    ref = reference(('smooth-emitter', flip), lambda: smooth_emitter_box(flip, hits_only=True),
                    {'type': 'path', 'max_depth': 4}, 2048, BATCHES, 100_000)
    mine = render_batches(smooth_emitter_box(flip), {'type': 'bdpt', 'max_depth': 4, 'technique': technique},
                          256, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'flip {flip} {technique}: {msg}'


def leaking_shell():
    """A point light inside a closed smooth-shaded shell of 48 triangles (two-sided diffuse) in
    the Cornell box without its ceiling light: every path that reaches the camera passes the
    shell where its shading normals and its triangles disagree about the side of a direction."""
    d = cornell(16)
    d.pop('light')
    d['shell'] = lowpoly_sphere_mesh(4, 8, radius=0.35, center=(0.1, 0.3, 0.0),
                                     bsdf={'type': 'twosided', 'bsdf': {'type': 'diffuse'}})
    d['inside'] = {'type': 'point', 'position': [0.1, 0.3, 0.0], 'intensity': {'type': 'rgb', 'value': [5.0] * 3}}
    return mi.load_dict(d)


@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_light_leaking_through_a_smooth_shaded_shell(technique):
    """Mitsuba's BSDFs evaluate in the shading frame, so its path renders light that passes a
    smooth-shaded surface; light vertices take those directions too (connect._cosines): with
    them refused, lt was black here and bdpt 93% dark (its camera-side strategies weighted by
    the light-side ones that could not sample them)."""
    ok, msg = against_path(('leaking-shell',), leaking_shell, 4, technique, 256, 110_000)
    assert ok, f'{technique}: {msg}'


def box_with_a_bulb():
    """The Cornell box (16 x 16) with a small sphere light in front of its back wall: the camera
    sees the bulb and the ceiling's light panel."""
    d = cornell(16)
    d['bulb'] = {'type': 'sphere', 'center': [0.3, 0.2, 0.4], 'radius': 0.15,
                 'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [3.0, 3.0, 3.0]}}}
    return mi.load_dict(d)


@pytest.mark.parametrize('technique', ['pt', 'bdpt', 'lt'])
def test_hide_emitters_sees_through_area_lights(technique):
    """hide_emitters: camera rays pass the shapes of area emitters, as Mitsuba's `path`'s do (its
    skip_area_emitters), so the bulb's and the panel's pixels show what lies behind them: pt
    through the camera's first edge (vertex.past_emitter_shapes), lt through its t=1 shadow rays,
    which pass those shapes too and never end on one. With the shapes kept, each technique was
    1.9% dark (p 1e-41)."""
    md = 4
    ref = reference(('box-with-a-bulb', 16), box_with_a_bulb, {'type': 'path', 'max_depth': md, 'hide_emitters': True},
                    1024, BATCHES, 50_000)
    mine = render_batches(box_with_a_bulb(), {'type': 'bdpt', 'max_depth': md, 'technique': technique,
                                              'hide_emitters': True}, 512 if technique == 'lt' else 256, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'{technique}: {msg}'


def test_hide_emitters_with_an_environment():
    """hide_emitters hides the directly seen environment as Mitsuba's `path` does (and the
    directly seen area light), while everything the environment lights stays."""
    name, md = 'all-lights.xml', 3
    scene = load_scene(name, RES, md)
    ref = file_reference(name, RES, md, 'path', 1024, BATCHES, 40_000, hide_emitters=True)
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': md, 'hide_emitters': True}, 64, BATCHES)
    # (the pixels that see the area light show what lies behind it: before camera rays passed
    # emitters' shapes, they were left out of this test, bdpt 0 there and `path` ~3e-4)
    visible = file_reference(name, RES, md, 'path', 1024, BATCHES, REF_SEED).mean(axis=0)
    on_light = (visible >= 4.0).any(axis=2)
    ok, msg = agreement(mine, ref)
    assert ok, msg
    sky = ~no_delta_mask(scene)            # pixels that see the environment (no delta surfaces here)
    assert (sky & ~on_light).any()
