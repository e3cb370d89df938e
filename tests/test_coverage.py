"""Plugins of Mitsuba 3.9 that bdpt renders beyond the first scope (issue 14), each against
Mitsuba's own integrators, and the plugins it refuses, each with a message that says why.

- cameras no light path reaches (cameras.UnreachableCamera): orthographic, radiancemeter,
  distant, irradiancemeter; bdpt combines hits, direct and connections there, lt is refused;
- area lights with a textured radiance (bitmap, checkerboard), whose positions Mitsuba samples
  by the texture (endpoints.EmitterTable.pdf_pos_a);
- sunsky (an infinite emitter) through a window; projector (delta position, textured frustum);
  directionalarea (a surface emitting along its normal: only light subpaths reach its light, so
  the reference is ptracer, and `path`, like technique pt, renders it black);
- refusals: the aov integrator wrapping bdpt, textured emitters on meshes and cylinders, timed_sunsky, batch;
- docs/coverage.md lists every plugin Mitsuba ships.

Agreement as in test_lights.py: K batches, Welch per pixel and per 4x4 block (helpers.agreement);
references cached under tests/.refcache. Uniform weights are heavy-tailed wherever BSDF sampling
alone must find a small bright light (design.md), so they run at more samples, and not with the
sun (0.27 degrees wide) in view of BSDF sampling: the sky alone there."""

import os
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from bdpt_jit.scene_check import UnsupportedSceneError, check_scene
from helpers import REPO, agreement, cached_reference, render_batches, scene_fingerprint
from stability_cases import cornell, diffuse, film, rgb

T = mi.ScalarTransform4f
RES = 16
BATCHES = 16
REF_SEED = 50_000           # first seed of this file's reference batches


def reference(name, build, integrator, spp, batches=BATCHES, seed0=REF_SEED):
    """Reference batches of Mitsuba's ``integrator`` (a dict) on the scene ``build()``, cached."""
    scene = mi.load_dict(build())
    key = ('coverage', name, scene_fingerprint(scene), tuple(sorted(integrator.items())), spp, batches, seed0)
    return cached_reference(key, lambda: render_batches(scene, integrator, spp, batches, seed0=seed0))


def check(name, build, ref_integrator, ref_spp, integrator, spp):
    scene = mi.load_dict(build())
    ref = reference(name, build, ref_integrator, ref_spp)
    mine = render_batches(scene, integrator, spp, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'{name} {integrator}: {msg}'


def assert_refused(scene, match):
    """check_scene refuses ``scene`` with a message matching ``match``, or (``match`` None or
    False) accepts it."""
    if match:
        with pytest.raises(UnsupportedSceneError, match=match):
            check_scene(scene, scene.sensors()[0])
    else:
        check_scene(scene, scene.sensors()[0])


def cause_chain(e):
    """The messages of an exception and of everything it was raised from."""
    out = []
    while e is not None:
        out.append(str(e))
        e = e.__cause__ or e.__context__
    return '\n'.join(out)


# ---------------------------------------------------------------------------- scenes
def ortho_box():
    """The Cornell box through an orthographic camera tilted up, so that it sees the light."""
    d = cornell(RES)
    for k in ('fov', 'fov_axis', 'focus_distance'):
        d['sensor'].pop(k, None)
    d['sensor'].update(type='orthographic', to_world=T().look_at(origin=[0, -0.6, 3.9], target=[0, 0.2, 0],
                                                                 up=[0, 1, 0]).scale([1.05, 1.05, 1]))
    return d


def meter_box(kind):
    """The Cornell box measured by a 1x1 sensor: a radiance meter looking at the back wall, a
    distant sensor aimed at a patch of the box, an irradiance meter on a patch of the floor."""
    d = cornell(1)
    if kind == 'radiancemeter':
        d['sensor'] = {'type': 'radiancemeter', 'origin': [0.0, -0.2, 3.0], 'direction': [0.13, 0.7, -3.0],
                       'film': film(1)}
    elif kind == 'distant':
        d['sensor'] = {'type': 'distant', 'direction': [0.0, -0.3, -1.0], 'film': film(1),
                       'target': {'type': 'rectangle', 'to_world': T().translate([0.3, -0.4, 0.0]).scale(0.3)}}
    else:
        d.pop('sensor')
        d['meter'] = {'type': 'rectangle', 'to_world': T().translate([-0.3, -0.99, 0.4]).rotate([1, 0, 0], -90).scale(0.1),
                      'sensor': {'type': 'irradiancemeter', 'film': film(1)}}
    return d


def texture_image():
    """8x8 radiance far from uniform (Mitsuba samples it by its luminance): ramps, a dark
    quarter and one texel 40 times brighter than the rest."""
    img = np.zeros((8, 8, 3), np.float32)
    yy, xx = np.mgrid[0:8, 0:8]
    img[..., 0] = 0.5 + 3.0 * xx / 8
    img[..., 1] = 0.5 + 3.0 * yy / 8
    img[..., 2] = 1.0
    img[:4, :4] = 0.0
    img[6, 1] = [40.0, 30.0, 20.0]
    return img


def radiance_texture(kind):
    if kind == 'bitmap':
        return {'type': 'bitmap', 'bitmap': mi.Bitmap(texture_image()), 'raw': True}
    if kind == 'tiled':     # repeated 2 x 3 times and shifted: Mitsuba's sample_position ignores to_uv
        return {'type': 'bitmap', 'bitmap': mi.Bitmap(texture_image()), 'raw': True,
                'to_uv': mi.ScalarTransform3f().scale([2.0, 3.0]).translate([0.1, 0.2])}
    return {'type': 'checkerboard', 'color0': {'type': 'uniform', 'value': 12.0},
            'color1': {'type': 'uniform', 'value': 0.5}, 'to_uv': mi.ScalarTransform3f().scale([3, 3])}


def textured_box(texture='bitmap', shape='rectangle'):
    """The Cornell box lit only by a textured area light: a panel in front of the back wall
    (seen by the camera), or a sphere or disk in the box."""
    d = cornell(RES, light=False)
    emitter = {'type': 'area', 'radiance': radiance_texture(texture)}
    if shape == 'rectangle':
        d['lamp'] = {'type': 'rectangle', 'to_world': T().translate([0.0, 0.1, -0.98]).scale(0.55)}
    elif shape == 'sphere':
        d['lamp'] = {'type': 'sphere', 'center': [0.2, 0.3, -0.2], 'radius': 0.25}
    else:
        d['lamp'] = {'type': shape, 'to_world': T().translate([0.2, 0.3, -0.2]).rotate([1, 0, 0], 30).scale(0.2)}
    d['lamp'].update(bsdf=diffuse(0.0), emitter=emitter)
    return d


def textured_quad_mesh_box(texture='bitmap'):
    """The Cornell box lit by a textured quad *mesh* in front of the back wall, its uv map
    one-to-one (scene_check.uv_map_is_one_to_one)."""
    d = cornell(RES, light=False)
    V = np.array([[-0.55, -0.45, -0.98], [0.55, -0.45, -0.98], [0.55, 0.65, -0.98], [-0.55, 0.65, -0.98]], np.float32)
    UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    props = mi.Properties()
    props['emitter'] = mi.load_dict({'type': 'area', 'radiance': radiance_texture(texture)})
    props['bsdf'] = mi.load_dict(diffuse(0.0))
    mesh = mi.Mesh('lamp_mesh', 4, 2, props=props, has_vertex_normals=False, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p['vertex_positions'] = dr.ravel(mi.Point3f(V[:, 0], V[:, 1], V[:, 2]))
    p['vertex_texcoords'] = dr.ravel(mi.Point2f(UV[:, 0], UV[:, 1]))
    p['faces'] = dr.ravel(mi.Vector3u(F[:, 0], F[:, 1], F[:, 2]))
    p.update()
    d['lamp'] = mesh
    return d


def window_room(sun_scale=0.2):
    """A closed room [-1, 1]^3 (y up) with a square window in the ceiling, a box on the floor,
    lit by Mitsuba's sunsky (z up in its frame, rotated to y up): the sun falls through the
    window onto the box and the floor; everything else is lit by the sky."""
    w = 0.35
    d = {'type': 'scene',
         'sensor': {'type': 'perspective', 'fov': 80, 'film': film(RES),
                    'to_world': T().look_at(origin=[0, 0.6, 0.95], target=[0, -1, -0.3], up=[0, 1, 0])},
         'floor': {'type': 'rectangle', 'to_world': T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
                   'bsdf': diffuse([0.7, 0.6, 0.5])},
         'back': {'type': 'rectangle', 'to_world': T().translate([0, 0, -1]), 'bsdf': diffuse(0.6)},
         'front': {'type': 'rectangle', 'to_world': T().translate([0, 0, 1]).rotate([0, 1, 0], 180), 'bsdf': diffuse(0.6)},
         'left': {'type': 'rectangle', 'to_world': T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
                  'bsdf': diffuse([0.6, 0.2, 0.2])},
         'right': {'type': 'rectangle', 'to_world': T().translate([1, 0, 0]).rotate([0, 1, 0], -90),
                   'bsdf': diffuse([0.2, 0.6, 0.2])},
         'block': {'type': 'cube', 'to_world': T().translate([0.3, -0.75, -0.2]).scale(0.25), 'bsdf': diffuse(0.7)},
         'sky': {'type': 'sunsky', 'to_world': T().rotate([1, 0, 0], -90), 'sun_direction': [-0.15, 1.0, 0.25],
                 'sky_scale': 10.0, 'sun_scale': float(sun_scale)}}
    for name, (cx, cz, sx, sz) in {'c1': (0, (1 + w) / 2, 1, (1 - w) / 2), 'c2': (0, -(1 + w) / 2, 1, (1 - w) / 2),
                                   'c3': ((1 + w) / 2, 0, (1 - w) / 2, w), 'c4': (-(1 + w) / 2, 0, (1 - w) / 2, w)}.items():
        d[name] = {'type': 'rectangle', 'to_world': T().translate([cx, 1, cz]).rotate([1, 0, 0], 90).scale([sx, sz, 1]),
                   'bsdf': diffuse(0.6)}
    return d


def projector_box(textured=True):
    """The Cornell box lit by a projector aimed at the back corner; textured: a 10x6 image with
    a bright block and a dark band (not square: the frustum's aspect is the texture's)."""
    d = cornell(RES, light=False)
    e = {'type': 'projector', 'fov': 40, 'scale': 2.0,
         'to_world': T().look_at(origin=[0.6, 0.8, 0.6], target=[-0.2, -0.6, -0.5], up=[0, 1, 0])}
    if textured:
        img = np.zeros((6, 10, 3), np.float32)
        img[...] = [1.0, 0.7, 0.3]
        img[1:4, 2:5] = [8.0, 2.0, 1.0]
        img[:, 8:] = 0.0
        e['irradiance'] = {'type': 'bitmap', 'bitmap': mi.Bitmap(img), 'raw': True}
    d['projector'] = e
    return d


def directionalarea_box():
    """The Cornell box lit only by a 0.6 x 0.6 panel under the ceiling emitting straight down."""
    d = cornell(RES, light=False)
    d['panel'] = {'type': 'rectangle', 'to_world': T().translate([0.1, 0.95, -0.1]).rotate([1, 0, 0], 90).scale(0.3),
                  'bsdf': diffuse(0.5), 'emitter': {'type': 'directionalarea', 'radiance': rgb([6.0, 5.0, 4.0])}}
    return d


# ---------------------------------------------------------------------------- cameras
@pytest.mark.parametrize('max_depth,technique,mis,spp', [
    (1, 'bdpt', 'power', 64),            # the light seen directly: s=0 alone (no s=1,t=1 to compete)
    (3, 'bdpt', 'power', 256),
    (3, 'pt', 'power', 1024),
    (3, 'bdpt', 'uniform', 2048),
])
def test_orthographic_cornell_box(max_depth, technique, mis, spp):
    """A delta-direction camera: no light-tracing strategy, the weights of the others sum to one."""
    check('ortho-box', ortho_box, {'type': 'path', 'max_depth': max_depth}, 4096,
          {'type': 'bdpt', 'max_depth': max_depth, 'technique': technique, 'mis': mis}, spp)


def test_orthographic_renders_no_light_strategies():
    """bdpt through an orthographic camera traces no splat, and lt is refused with the reason."""
    scene = mi.load_dict(ortho_box())
    integrator = mi.load_dict({'type': 'bdpt', 'max_depth': 3})
    mi.render(scene, integrator=integrator, spp=1)
    traced = integrator.last_render_info['strategies']
    assert not any('t=1' in s for s in traced) and any('s>=2' in s for s in traced), traced
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'technique': 'lt'}), spp=1)
    assert "technique 'lt' cannot render through the sensor 'orthographic'" in cause_chain(info.value)


@pytest.mark.parametrize('kind', ['radiancemeter', 'distant', 'irradiancemeter'])
@pytest.mark.parametrize('technique,mis', [('bdpt', 'power'), ('bdpt', 'uniform'), ('pt', 'power')])
def test_meters_agree_with_path(kind, technique, mis):
    """1x1 sensors: one delta ray, parallel rays at a target, irradiance over a shape."""
    check(f'meter-{kind}', lambda: meter_box(kind), {'type': 'path', 'max_depth': 4}, 4096,
          {'type': 'bdpt', 'max_depth': 4, 'technique': technique, 'mis': mis}, 1024)


# ---------------------------------------------------------------------------- textured area lights
@pytest.mark.parametrize('texture,shape,technique,mis,spp', [
    ('bitmap', 'rectangle', 'bdpt', 'power', 256),
    ('bitmap', 'rectangle', 'lt', 'power', 1024),      # lt: heavy-tailed in dim pixels at 256
    ('bitmap', 'rectangle', 'pt', 'power', 1024),
    ('bitmap', 'rectangle', 'bdpt', 'uniform', 2048),
    ('checker', 'rectangle', 'bdpt', 'power', 256),
    ('checker', 'rectangle', 'lt', 'power', 1024),
    ('checker', 'sphere', 'bdpt', 'power', 256),
    ('bitmap', 'disk', 'bdpt', 'power', 256),
    ('tiled', 'rectangle', 'lt', 'power', 1024),
    ('tiled', 'rectangle', 'bdpt', 'power', 256),
])
def test_textured_area_light(texture, shape, technique, mis, spp):
    """Emission at the sampled point's uv; positions at Mitsuba's texture-driven density (the
    bitmap's: a uniform-area density in the weights is +2.8% here, in the throughput +190%).
    A texture with a ``to_uv`` ('tiled', as the checkerboard): Mitsuba's sample_position
    ignores it, so bright texels of the tiling fell where its density is 0 and lt was 2.9% dark;
    light subpaths start uniformly on such emitters (emitter_tables.remapped_textures)."""
    check(f'textured-{texture}-{shape}', lambda: textured_box(texture, shape), {'type': 'path', 'max_depth': 3}, 4096,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique, 'mis': mis}, spp)


@pytest.mark.parametrize('technique', ['bdpt', 'lt', 'pt'])
def test_textured_light_on_a_mesh_with_a_one_to_one_uv_map(technique):
    """A textured quad mesh (uv map one-to-one): allowed, and against ptracer (Mitsuba samples
    it through its uv map, as it does rectangles)."""
    check('textured_quad_mesh', textured_quad_mesh_box, {'type': 'ptracer', 'max_depth': 3}, 1024,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique}, 1024 if technique == 'pt' else 256)


def uv_sphere(rings, segments, fold=False):
    """A UV sphere mesh (rings x segments quads, two triangles each) with uvs in [0, 1]^2 and a
    seam (and 1 + 1e-5 at the far edge, as Mitsuba's test mesh sphere.obj has); ``fold``: the
    upper half's u mirrored onto the lower half's (two triangles over each point)."""
    th, ph = np.meshgrid(np.linspace(0, np.pi, rings + 1), np.linspace(0, 2 * np.pi, segments + 1), indexing='ij')
    pos = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    u = ph / (2 * np.pi) * (1 + 1e-5)
    v = th / np.pi
    if fold:
        u = np.where(u > 0.5, 1.0 - u, u)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    i = np.arange(rings)[:, None] * (segments + 1) + np.arange(segments)[None, :]
    a, b, c, d = i, i + 1, i + segments + 1, i + segments + 2
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    mesh = mi.Mesh('uv sphere', len(pos), len(faces), has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p['vertex_positions'] = mi.Float(pos.astype(np.float32).ravel())
    p['vertex_texcoords'] = mi.Float(uv.astype(np.float32).ravel())
    p['faces'] = mi.UInt32(faces.astype(np.uint32).ravel())
    p.update()
    return mesh


def test_uv_check_of_a_large_sphere_mesh():
    """scene_check.uv_map_is_one_to_one on a UV sphere of 32768 triangles (Mitsuba's test scene
    various_emitters has a textured light on such a mesh, refused before: over 20000 triangles,
    and its uvs reach 1.00001): one-to-one; with its upper half's u folded onto the lower half,
    not."""
    from bdpt_jit.scene_check import uv_map_is_one_to_one
    assert uv_map_is_one_to_one(uv_sphere(128, 128))
    assert not uv_map_is_one_to_one(uv_sphere(128, 128, fold=True))


@pytest.mark.parametrize('shape', ['cube', 'cylinder'])
def test_textured_emitter_refused_on_meshes_and_cylinders(shape):
    """A cube's faces share their uvs (not one-to-one), a cylinder's uv map is not exact."""
    scene = mi.load_dict(textured_box('checker', shape))
    with pytest.raises(UnsupportedSceneError, match=f"textured radiance on the shape .*\\({shape}\\)"):
        check_scene(scene, scene.sensors()[0])


def test_textured_emitter_refused_on_a_rotated_sphere():
    """Mitsuba 3.9.1's sphere finds the point of a uv along the unrotated direction: a textured
    sphere light whose to_world rotates it is refused (bdpt and lt were 1% bright under one
    rotated by 110 degrees, against path); translated and scaled it renders
    (test_textured_area_light)."""
    d = textured_box('checker', 'sphere')
    d['lamp'] = {**d['lamp'], 'to_world': T().translate([0.2, 0.3, -0.2]).rotate([0.6, 0.0, 0.8], 110).scale(0.25)}
    del d['lamp']['center'], d['lamp']['radius']
    scene = mi.load_dict(d)
    with pytest.raises(UnsupportedSceneError, match="textured radiance on the rotated sphere"):
        check_scene(scene, scene.sensors()[0])
    del d['lamp']['to_world']
    d['lamp'].update(center=[0.2, 0.3, -0.2], radius=0.25)
    scene = mi.load_dict(d)
    check_scene(scene, scene.sensors()[0])


def narrow_gaussian_box(stddev):
    """The Cornell box through a Gaussian filter of standard deviation ``stddev``: 0.2, whose
    weights sum to between 0.6 and 1.0 over the pixel grid; 0.1, of radius 0.4 (no neighbour)."""
    d = cornell(RES)
    d['sensor']['film'] = {'type': 'hdrfilm', 'width': RES, 'height': RES,
                           'rfilter': {'type': 'gaussian', 'stddev': stddev}}
    return d


@pytest.mark.parametrize('stddev', [0.1, 0.2])
@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_a_narrow_gaussian_filter(technique, stddev):
    """The light image weighs splats by the filter unnormalised and divides each pixel by the
    filter's mass over the crop (film.py), which makes its pixel path's for any filter. With
    each splat normalised over its footprint, as Mitsuba's ptracer splats, it was so only
    where the filter's weights sum to one over the grid: under the Gaussian of 0.2 lt and bdpt
    failed path's pixels (p 1e-34; lt's pixel across the light's edge 2.9 times path's). The
    Gaussian of 0.1 lies within its pixel, and still needs the division (film.splat_gain: lt
    was 94% dark with it left to the box filter alone)."""
    check(f'narrow-gaussian-{stddev}' if stddev != 0.2 else 'narrow-gaussian', lambda: narrow_gaussian_box(stddev),
          {'type': 'path', 'max_depth': 4}, 1024, {'type': 'bdpt', 'max_depth': 4, 'technique': technique}, 64)


def test_a_film_sampling_its_border_is_refused_where_the_border_is_not_empty():
    """With sample_border, Mitsuba's path traces camera rays through a border around the crop
    (the filter's radius), so an edge pixel averages its whole footprint; bdpt's light image cannot
    splat there (bdpt and lt were 1.5% bright over a 16 x 16 Cornell box with the Gaussian filter).
    Refused naming the parameter and filter; a box filter's border is empty and renders."""
    d = cornell(8)
    for rfilter, refused in (('gaussian', True), ('tent', True), ('box', False)):
        d['sensor']['film'] = {'type': 'hdrfilm', 'width': 8, 'height': 8, 'sample_border': True,
                               'rfilter': {'type': rfilter}}
        scene = mi.load_dict(d)
        assert_refused(scene, refused and f"'sample_border' is true with the reconstruction filter '{rfilter}'")


def test_a_directional_emitter_whose_transform_scales_its_direction_is_refused():
    """Mitsuba's directional emitter takes to_world * (0, 0, 1) unnormalised as its direction:
    its path renders a scaled one brighter by the scale, light subpaths leave along the unit
    direction (bdpt 31% and lt 50% below path under a uniform scale of 2). Refused naming the
    emitter; a rotation alone renders."""
    look = T().look_at(origin=[0, 0, 3], target=[0.2, -0.3, 0], up=[0, 1, 0])
    for scale, refused in ((2.0, True), ([1.0, 1.0, 0.5], True), (1.0, False)):
        d = cornell(8)
        d['sun'] = {'type': 'directional', 'to_world': look @ T().scale(scale), 'id': 'sun',
                    'irradiance': {'type': 'rgb', 'value': [2.0, 2.0, 2.0]}}
        scene = mi.load_dict(d)
        assert_refused(scene, refused and "directional emitter 'sun' has a to_world that scales")


def test_disk_and_cylinder_lights_off_the_surface_their_rays_hit_are_refused():
    """Mitsuba samples a disk's or cylinder's points through to_world and intersects it
    through the transform's stored inverse (disk) or a radius read from it (cylinder). With a
    rotation about an axis that is not a unit vector (Mitsuba's rotate does not normalise it)
    the inverse does not invert the transform: a disk light's sampled points lay 1e-4 of its
    size off the disk its rays hit, half behind it (bdpt and lt 52% dark); a cylinder scaled
    unequally in x and y has no consistent area (Mitsuba's path 26% bright). Refused naming the
    shape; with a unit axis, and a disk scaled unequally, they render (an ellipse is exact)."""
    T = mi.ScalarTransform4f
    unit = list(np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9]))
    cases = [('disk', T().rotate([0.3, 0.2, 0.9], 40).scale(0.2), 'stored inverse does not invert it'),
             ('cylinder', T().rotate([0.3, 0.2, 0.9], 40).scale(0.2), 'stored inverse does not invert it'),
             ('cylinder', T().rotate(unit, 40).scale([0.35, 0.12, 0.2]), 'scales its x and y axes unequally'),
             ('disk', T().rotate(unit, 40).scale([0.35, 0.12, 0.2]), None),
             ('cylinder', T().rotate(unit, 40).scale([0.15, 0.15, 0.4]), None)]
    for shape, placement, refused in cases:
        d = cornell(8)
        d.pop('light')
        d['lamp'] = {'type': shape, 'to_world': T().translate([0.1, 0.6, -0.1]) @ placement,
                     'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [6.0, 5.0, 4.0]}}}
        scene = mi.load_dict(d)
        assert_refused(scene, refused and f"the area emitter on the {shape} 'lamp'.*{refused}")


# ---------------------------------------------------------------------------- null lobes
def null_emitters(mirror=False, leaf=False):
    """The Cornell box with its light's BSDF ``null`` and a second emitter of BSDF ``null`` in
    view (a panel turned towards the camera); ``mirror``: a mirror ball that shows the light;
    ``leaf``: a leaf of opacity 0.4 (a ``mask``: partly null surfaces, media.MediumTracer)."""
    d = cornell(RES)
    d['light']['bsdf'] = {'type': 'null'}
    d['panel'] = {'type': 'rectangle', 'to_world': T().translate([0.3, 0.0, 0.2]).rotate([0, 1, 0], 20).scale(0.2),
                  'emitter': {'type': 'area', 'radiance': rgb([3.0, 2.0, 1.0])}, 'bsdf': {'type': 'null'}}
    if mirror:
        d['ball'] = {'type': 'sphere', 'center': [0.3, -0.5, 0.2], 'radius': 0.35, 'bsdf': {'type': 'conductor'}}
    if leaf:
        d['leaf'] = {'type': 'rectangle', 'to_world': T().translate([-0.3, 0.3, 0.3]).rotate([1, 0, 0], 60).scale(0.3),
                     'bsdf': {'type': 'mask', 'opacity': 0.4, 'bsdf': {'type': 'twosided', 'bsdf': diffuse(0.8)}}}
    return d


@pytest.mark.parametrize('case', ['pt', 'bdpt-mirror', 'pt-leaf'])
def test_emitters_whose_bsdf_is_null(case):
    """An emitter whose BSDF is ``null`` is met by walks as a surface with a delta lobe that goes
    straight on (scene_check.null_emitter_shape), as Mitsuba's path meets it: passed as an
    invisible surface, no camera subpath collected its emission (pt 68% dark, bdpt 2.5% dark
    where a mirror shows the light). With a mask in the scene (partly null surfaces, walked by
    media.MediumTracer) the reference is volpath at unbounded depth, where its convention (a
    null surface counts no bounce) and path's agree."""
    technique, _, extra = case.partition('-')
    ref_integrator = {'type': 'volpath', 'max_depth': -1} if extra == 'leaf' else {'type': 'path', 'max_depth': 4}
    check(f'null-emitters-{extra}', lambda: null_emitters(mirror=extra == 'mirror', leaf=extra == 'leaf'),
          ref_integrator, 1024, {**ref_integrator, 'type': 'bdpt', 'technique': technique}, 64)


def leaf_over_floor(opacity, light='point', material=0.0):
    """A floor lit by a light above a leaf: a rectangle whose BSDF is a ``mask`` of ``opacity``
    over a two-sided diffuse of reflectance ``material`` (None: no leaf; 'null': a null BSDF).
    The camera sees the floor, not the leaf."""
    d = {'type': 'scene',
         'sensor': {'type': 'perspective', 'fov': 20, 'film': film(RES),
                    'to_world': T().look_at(origin=[3, 0.3, 0], target=[0, 0, 0], up=[0, 1, 0])},
         'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(0.6), 'bsdf': diffuse(0.5)}}
    if light == 'point':
        d['light'] = {'type': 'point', 'position': [0, 2, 0], 'intensity': 5.0}
    else:
        d['light'] = {'type': 'rectangle', 'to_world': T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(0.2),
                      'emitter': {'type': 'area', 'radiance': 30.0}}
    if opacity is not None:
        bsdf = {'type': 'null'} if opacity == 'null' else {
            'type': 'mask', 'opacity': opacity, 'material': {'type': 'twosided', 'bsdf': diffuse(material)}}
        d['leaf'] = {'type': 'rectangle', 'to_world': T().translate([0, 1, 0]).rotate([1, 0, 0], -90).scale(2.5),
                     'bsdf': bsdf}
    return d


# (CI time: bdpt under the point light in the slow set: its s=1 shadow rays are pt's, checked
# under the point light, and its connections start from any light as under the area light)
@pytest.mark.parametrize('technique,light', [('pt', 'point'), ('pt', 'area'), ('bdpt', 'area'),
                                             pytest.param('bdpt', 'point', marks=pytest.mark.slow)])
def test_shadow_rays_pass_null_lobes(technique, light):
    """A black leaf of opacity 0.4 passes 0.6 of the light to every floor point, and a null
    sheet all of it: each floor pixel is 0.6 times (1 times) the same renderer's without the
    leaf. Mitsuba's path blocks shadow rays at such surfaces: under a point light it renders the
    floor black, and bdpt's pt did (media.MediumTracer now passes them, context.media_setup)."""
    integ = {'type': 'bdpt', 'max_depth': -1, 'technique': technique}
    spp = 64 if technique == 'pt' else 16
    free = render_batches(mi.load_dict(leaf_over_floor(None, light)), integ, spp, BATCHES, seed0=7)
    for opacity, share in ((0.4, 0.6), ('null', 1.0)):
        mine = render_batches(mi.load_dict(leaf_over_floor(opacity, light)), integ, spp, BATCHES)
        ok, msg = agreement(mine, share * free)
        assert ok, f'{opacity} over the {light} light, {technique}: {msg}'


def test_a_leaf_s_checkered_opacity_against_volpath():
    """The leaf fully opaque in one square of two (a checkerboard opacity, as foliage's alpha
    maps), reflecting 0.3: against Mitsuba's volpath, which passes its shadow rays through
    null lobes (its path does not)."""
    checker = {'type': 'checkerboard', 'color0': 0.0, 'color1': 1.0, 'to_uv': mi.ScalarTransform3f().scale([8, 8])}
    check('leaf-checker', lambda: leaf_over_floor(checker, 'point', 0.3), {'type': 'volpath', 'max_depth': -1}, 1024,
          {'type': 'bdpt', 'max_depth': -1, 'technique': 'pt'}, 64)


# ---------------------------------------------------------------------------- merged shapes
def sky_into_a_box(distinct=False):
    """A box open at the top under a sky (the camera inside), its five walls rectangles of equal
    BSDFs: Mitsuba 3.9.1 merges them into one mesh and leaves its bounding box, and the scene's,
    invalid. ``distinct``: reflectances 1e-6 apart, so that nothing merges (the reference)."""
    walls = {'floor': T().translate([0, -1, 0]).rotate([1, 0, 0], -90), 'back': T().translate([0, 0, -1]),
             'front': T().translate([0, 0, 1]).rotate([0, 1, 0], 180),
             'left': T().translate([-1, 0, 0]).rotate([0, 1, 0], 90), 'right': T().translate([1, 0, 0]).rotate([0, 1, 0], -90)}
    d = {'type': 'scene', 'sky': {'type': 'constant', 'radiance': 1.0},
         'sensor': {'type': 'perspective', 'fov': 70, 'film': film(RES),
                    'to_world': T().look_at(origin=[0, 0, 0.9], target=[0, -0.2, -1], up=[0, 1, 0])}}
    for i, (name, to_world) in enumerate(walls.items()):
        r = 0.7 * (1 + 1e-6 * i) if distinct else 0.7
        d[name] = {'type': 'rectangle', 'to_world': to_world, 'bsdf': {'type': 'twosided', 'bsdf': diffuse(r)}}
    return d


@pytest.mark.parametrize('technique', ['lt', 'pt', 'bdpt'])
def test_an_environment_over_merged_rectangles(technique):
    """Light subpaths from an environment start on a disk around the scene's bounding sphere:
    from the invalid box of merged rectangles it was NaN, so lt rendered nothing of the sky and
    bdpt too little (rays.scene_bbox takes the box from the shapes, a mesh's from its vertices;
    the merge radius and the grids read it too). Mitsuba's environment samples lie at twice
    that sphere's radius, 2e-4 from the vertex there, so emitter sampling's shadow rays passed
    the walls: pt 1.7% too bright, as Mitsuba's path (rays.spawn_to_emitter now sends them to
    infinity). Against path on the same box unmerged, with the sky hidden (lt renders no
    directly seen environment)."""
    merged = mi.load_dict(sky_into_a_box())
    assert len(merged.shapes()) == 1 and not merged.bbox().valid()       # what Mitsuba does
    assert len(mi.load_dict(sky_into_a_box(True)).shapes()) == 5
    ref = reference('sky-into-a-box', lambda: sky_into_a_box(True), {'type': 'path', 'max_depth': 3,
                                                                      'hide_emitters': True}, 1024)
    mine = render_batches(merged, {'type': 'bdpt', 'max_depth': 3, 'technique': technique, 'hide_emitters': True},
                          512 if technique == 'lt' else 256, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'{technique}: {msg}'


# ---------------------------------------------------------------------------- sunsky
@pytest.mark.parametrize('sun,technique,mis,spp', [
    (True, 'bdpt', 'power', 256),
    (True, 'lt', 'power', 1024),
    (True, 'pt', 'power', 256),
    (False, 'bdpt', 'uniform', 1024),
])
def test_sunsky_through_a_window(sun, technique, mis, spp):
    """sunsky is an infinite emitter with sample_direction and pdf_direction: the environment
    code path (a disk facing the direction, Mitsuba's direction density) renders it."""
    scale = 0.2 if sun else 0.0
    check(f'window-room-{scale}', lambda: window_room(scale), {'type': 'path', 'max_depth': 3}, 4096,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique, 'mis': mis}, spp)


def test_timed_sunsky_refused_with_the_reason():
    d = window_room()
    d['sky'] = {'type': 'timed_sunsky', 'to_world': T().rotate([1, 0, 0], -90)}
    scene = mi.load_dict(d)
    with pytest.raises(UnsupportedSceneError, match="'timed_sunsky' is not supported: Mitsuba 3.9.1 cannot"):
        check_scene(scene, scene.sensors()[0])


# ---------------------------------------------------------------------------- projector
@pytest.mark.parametrize('textured,technique,mis,spp', [
    (True, 'bdpt', 'power', 256),
    (True, 'lt', 'power', 256),
    (True, 'pt', 'power', 1024),
    (True, 'bdpt', 'uniform', 256),
    (False, 'bdpt', 'power', 256),
])
def test_projector(textured, technique, mis, spp):
    """Light subpaths leave the projector uniformly in a cone around its frustum (a 5% error in
    that density: lt -4.6%, caught here)."""
    check(f'projector-{textured}', lambda: projector_box(textured), {'type': 'path', 'max_depth': 3}, 4096,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique, 'mis': mis}, spp)


def test_projector_cone_holds_its_frustum():
    """The cone of endpoints.projector_cone holds every direction Mitsuba's projector emits, for
    a wide, non-square, rotated and scaled one."""
    from bdpt_jit.endpoints import projector_cone
    img = np.ones((3, 12, 3), np.float32)
    e = mi.load_dict({'type': 'projector', 'fov': 100, 'irradiance': {'type': 'bitmap', 'bitmap': mi.Bitmap(img)},
                      'to_world': T().rotate([0.3, 1, 0.2], 70).scale([1.5, 0.7, 1.0])})
    cos_cut, axis = projector_cone(e)
    n = 1 << 14
    rng = np.random.default_rng(3)
    u = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    ray, w = e.sample_ray(0.0, 0.5, u, u, True)
    d = np.array(ray.d, dtype=np.float64)
    cos = (np.array(axis) @ d) / np.linalg.norm(d, axis=0)
    assert cos.min() >= cos_cut
    assert cos.min() < cos_cut + 0.02          # and not much wider than the frustum's corners


# ---------------------------------------------------------------------------- directionalarea
@pytest.mark.parametrize('technique,mis', [('bdpt', 'power'), ('lt', 'power'), ('bdpt', 'uniform')])
def test_directionalarea_agrees_with_ptracer(technique, mis):
    """Only the strategies with s >= 2 see this light (its s=0 and s=1 densities are 0: taking
    emitter sampling's density for its first hit as nonzero is -34% with uniform weights)."""
    check('directionalarea', directionalarea_box, {'type': 'ptracer', 'max_depth': 4}, 1024,
          {'type': 'bdpt', 'max_depth': 4, 'technique': technique, 'mis': mis}, 256)


def test_directionalarea_is_black_to_path_tracing():
    """No camera-side strategy can reach it: technique pt renders it black, as Mitsuba's path."""
    scene = mi.load_dict(directionalarea_box())
    pt = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'technique': 'pt', 'max_depth': 4}), spp=16))
    path = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'path', 'max_depth': 4}), spp=16))
    assert np.all(pt == 0) and np.all(path == 0)


def test_directionalarea_texture_without_spectrum_sampling_refused():
    d = directionalarea_box()
    d['panel']['emitter']['radiance'] = radiance_texture('checker')
    scene = mi.load_dict(d)
    with pytest.raises(UnsupportedSceneError, match="directionalarea emitter's radiance texture cannot be sampled"):
        check_scene(scene, scene.sensors()[0])


# ---------------------------------------------------------------------------- shapes
def instanced_box():
    """The Cornell box with two instances of one shape group (a sphere and a small cube)."""
    d = cornell(RES)
    d['group'] = {'type': 'shapegroup',
                  'ball': {'type': 'sphere', 'radius': 0.25, 'bsdf': diffuse([0.7, 0.7, 0.3])},
                  'cube': {'type': 'cube', 'to_world': T().translate([0.0, -0.35, 0.0]).scale(0.1), 'bsdf': diffuse(0.5)}}
    for name, x in (('left', -0.45), ('right', 0.4)):
        d[name] = {'type': 'instance', 'shapegroup': {'type': 'ref', 'id': 'group'},
                   'to_world': T().translate([x, -0.5, 0.1 * x])}
    return d


@pytest.mark.parametrize('technique', ['bdpt', 'lt'])
def test_instances_agree_with_path(technique):
    """Instanced shapes (they failed before: a virtual call on shapes reached the instance's
    pdf_position, which raises)."""
    check('instances', instanced_box, {'type': 'path', 'max_depth': 3}, 4096,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique}, 256)


def hair_curves():
    """Mitsuba's Cornell box without its boxes, and 60 strands of ``linearcurve`` (radius 0.012,
    wavy, floor to mid-height) of Mitsuba's ``hair`` BSDF: a scene light paths reach the fibres in,
    and whose image lt forms from the hair's importance-mode value. The control points are
    written once per process to a file of the temporary directory (removed at exit)."""
    import atexit
    import tempfile
    path = os.path.join(tempfile.gettempdir(), f'bdpt_coverage_curves_{os.getpid()}.txt')
    if not os.path.exists(path):
        rng = np.random.default_rng(3)
        lines = []
        for k in range(60):
            x0, z0 = rng.uniform(-0.6, 0.6, 2)
            lines += [f'{x0 + 0.1 * np.sin(3 * t + k):.5f} {-1 + 1.2 * t:.5f} {z0 + 0.1 * np.cos(2 * t + k):.5f} 0.012'
                      for t in np.linspace(0, 1, 6)] + ['']
        with open(path + '.tmp', 'w') as f:
            f.write('\n'.join(lines))
        os.replace(path + '.tmp', path)
        atexit.register(lambda: os.path.exists(path) and os.remove(path))
    d = cornell()
    d.pop('small-box')
    d.pop('large-box')
    d['hair'] = {'type': 'linearcurve', 'filename': path, 'bsdf': {'type': 'hair'}}
    return d


def test_hair_on_curves_agrees_with_path_in_lt():
    """Hair is not reciprocal (scene_check._non_reciprocal: its azimuthal offset is read from
    wi). On curves, the geometry it is made for, light tracing alone keeps Mitsuba's
    importance-mode value, offset read from the direction the light came from, and agrees with
    path (as ptracer's estimator). With the swapped radiance-mode value that the combinations
    take (context.exact_adjoint) lt was 1.1% dark at 48 x 48, 10% in 4x4 blocks: that value
    over the light side's density grows as 1/|cos| towards a fibre's silhouette."""
    check('hair_curves', hair_curves, {'type': 'path', 'max_depth': 5}, 1024,
          {'type': 'bdpt', 'max_depth': 5, 'technique': 'lt'}, 256)


def hair_boxes():
    """The Cornell box with both boxes of Mitsuba's ``hair`` BSDF, flat faces outside its
    model: there only the radiance-mode integrand is path's (lt and ptracer differ)."""
    d = cornell()
    for k in ('small-box', 'large-box'):
        d[k]['bsdf'] = {'type': 'hair'}
    return d


def test_hair_on_boxes_agrees_with_path_in_bdpt():
    """The exact adjoint at light vertices makes every strategy estimate path's integrand at a
    non-reciprocal BSDF: before, bdpt was 25% bright in blocks of hair-covered boxes (25
    standard errors at 48 x 48)."""
    check('hair_boxes', hair_boxes, {'type': 'path', 'max_depth': 5}, 1024,
          {'type': 'bdpt', 'max_depth': 5, 'technique': 'bdpt'}, 256)


def test_hair_refused_in_monochrome_variants():
    """Mitsuba 3.9.1's hair cannot be evaluated in a monochrome variant (its own path fails
    deep inside with "srgb_model_eval(): invoked for a non-spectral color type"): refused before
    any kernel, naming the shape and the variants that work (in a process of its own: the
    variant is switched)."""
    import subprocess
    import sys
    code = ("import sys, mitsuba as mi\nmi.set_variant('llvm_ad_mono')\nimport bdpt_jit\n"
            f"sys.path.insert(0, {os.path.join(REPO, 'tests')!r})\n"
            "from test_coverage import hair_boxes, cause_chain\n"
            "try:\n    mi.render(mi.load_dict(hair_boxes()), integrator=mi.load_dict({'type': 'bdpt'}), spp=1)\n"
            "except Exception as e:\n    print(cause_chain(e))\n")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=300).stdout
    assert re.search(r"bdpt: the BSDF of a \w+ shape \(hair\) cannot be rendered in the variant "
                     r"'llvm_ad_mono'.*use an RGB or spectral variant", out), out


def test_the_reciprocity_probe():
    """scene_check._non_reciprocal finds hair and principledthin's thin transmission, and no
    BSDF that is reciprocal (rough glass of alpha 0.001 included: float rounding stays below
    its bound); _known_reciprocal skips the probe for the classes known reciprocal only."""
    from bdpt_jit.scene_check import _known_reciprocal, _non_reciprocal
    found = {name: _non_reciprocal(mi.load_dict(d)) for name, d in {
        'hair': {'type': 'hair'},
        'principledthin': {'type': 'principledthin', 'spec_trans': 0.5},
        'blend with it': {'type': 'blendbsdf', 'weight': 0.3, 'a': {'type': 'diffuse'},
                          'b': {'type': 'principledthin', 'spec_trans': 0.5}},
        'principled': {'type': 'principled', 'spec_trans': 0.6, 'sheen': 0.3, 'clearcoat': 0.4, 'metallic': 0.3},
        'roughdielectric': {'type': 'roughdielectric', 'alpha': 0.001, 'int_ior': 2.4},
        'roughplastic': {'type': 'roughplastic', 'alpha': 0.02},
        'anisotropic conductor': {'type': 'roughconductor', 'alpha_u': 0.1, 'alpha_v': 0.4},
    }.items()}
    assert found == {'hair': True, 'principledthin': True, 'blend with it': True, 'principled': False,
                     'roughdielectric': False, 'roughplastic': False, 'anisotropic conductor': False}
    assert _known_reciprocal(mi.load_dict({'type': 'blendbsdf', 'weight': 0.5, 'a': {'type': 'principled'},
                                           'b': {'type': 'twosided', 'bsdf': {'type': 'roughplastic'}}}))
    assert not _known_reciprocal(mi.load_dict({'type': 'hair'}))
    assert not _known_reciprocal(mi.load_dict({'type': 'blendbsdf', 'weight': 0.5, 'a': {'type': 'principled'},
                                               'b': {'type': 'principledthin'}}))


def open_tube(tmp_dir):
    """A thick vertical ``bsplinecurve`` (radius 0.3, its ends open: Mitsuba culls the faces a
    ray meets from inside) standing 0.1 above a floor, black, a point light low beside it that
    lights the floor under it, and a camera above that sees the floor beyond the tube through
    its open top (camera rays enter there and leave through the far wall) and the floor under
    its foot only through its near wall."""
    path = os.path.join(tmp_dir, 'tube.txt')
    with open(path, 'w') as f:
        f.write('\n'.join(f'0 {y} 0 0.3' for y in (-0.3, 0.1, 0.5, 0.9, 1.3)) + '\n')
    return {'type': 'scene',
            'camera': {'type': 'perspective', 'fov': 40, 'to_world': T().look_at([1.5, 1.5, 0], [0, 0.3, 0], [0, 1, 0]),
                       'film': film(RES)},
            'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(1.2), 'bsdf': diffuse(0.5)},
            'tube': {'type': 'bsplinecurve', 'filename': path, 'bsdf': diffuse(0.0)},
            'light': {'type': 'point', 'position': [-1.0, 0.07, 0.0], 'intensity': rgb(5.0)}}


@pytest.mark.parametrize('technique', ['lt', 'bdpt'])
def test_an_open_tube_looks_the_same_to_every_technique(technique, tmp_path):
    """Visibility is not symmetric in Mitsuba (curves cull faces met from inside): t=1 shadow
    rays are traced from the camera (light_path.camera_to), as camera rays and every other
    strategy's. Traced from the vertex, lt was a tenth of pt here: the floor seen through the
    tube's open top was black, and the floor under its foot lit pixels that see the tube."""
    scene = mi.load_dict(open_tube(str(tmp_path)))
    ref = render_batches(scene, {'type': 'bdpt', 'technique': 'pt', 'max_depth': 3}, 64, BATCHES, seed0=REF_SEED)
    mine = render_batches(scene, {'type': 'bdpt', 'technique': technique, 'max_depth': 3}, 256, BATCHES)
    ok, msg = agreement(mine, ref)
    assert ok, f'open tube {technique}: {msg}'


def far_quadrics():
    """A cylinder and an instanced SDF grid (a torus) under a constant sky, seen from 24 units
    away as Mitsuba's test scene various_shapes sees them: Mitsuba's hit points on both lie off
    the surface by more than the general offset bound (rays.py: cylinders projected back onto
    the surface, SDF grids and shapes inside instances a wider bound)."""
    n = 16
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing='ij')
    sdf = np.hypot(np.hypot(X - 0.5, Y - 0.5) - 0.3, Z - 0.5) - 0.12       # a torus in the unit cube
    grid = mi.TensorXf(sdf.astype(np.float32).transpose(2, 1, 0)[..., None].copy())
    return {'type': 'scene',
            'sensor': {'type': 'perspective', 'fov': 14.0, 'film': film(RES, RES),
                       'to_world': T().look_at(origin=[-24, 0, 0], target=[0, 0, 0], up=[0, 0, 1])},
            'sky': {'type': 'constant', 'radiance': rgb(1.0)},
            'cylinder': {'type': 'cylinder', 'bsdf': diffuse([0.7, 0.5, 0.3]),
                         'to_world': T().translate([0, 0.9, -0.8]).rotate([1, 0, 0], -35).scale([0.8, 0.8, 1.6])},
            'group': {'type': 'shapegroup', 'torus': {'type': 'sdfgrid', 'grid': grid, 'bsdf': diffuse(0.6)}},
            'torus': {'type': 'instance', 'shapegroup': {'type': 'ref', 'id': 'group'},
                      'to_world': T().translate([0, -1.6, -0.2]).rotate([1, 0, 0], 60).scale(2.2).translate([-0.5, -0.5, -0.5])}}


@pytest.mark.parametrize('technique', ['bdpt', pytest.param('pt', marks=pytest.mark.slow)])
def test_far_quadrics_agree_with_path(technique):
    """A cylinder and an instanced SDF grid seen from afar (far_quadrics): bdpt rendered them
    3-50% dark before (rays from half of each cylinder point's hemisphere hit it again)."""
    check('far_quadrics', far_quadrics, {'type': 'path', 'max_depth': 3}, 1024,
          {'type': 'bdpt', 'max_depth': 3, 'technique': technique}, 256)


def ellipsoid_box():
    """Mitsuba's Cornell box without its boxes and with twelve ``ellipsoids`` (an analytic
    shape whose hit distance comes from a quadratic in single precision, as a sphere's)."""
    rng = np.random.default_rng(5)
    n = 12
    centres = np.c_[rng.uniform(-0.6, 0.6, n), rng.uniform(-0.8, 0.2, n), rng.uniform(-0.6, 0.4, n)]
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    d = cornell()
    d.pop('small-box')
    d.pop('large-box')
    d['ellipsoids'] = {'type': 'ellipsoids', 'centers': mi.TensorXf(centres.astype(np.float32)),
                       'scales': mi.TensorXf(rng.uniform(0.05, 0.2, (n, 3)).astype(np.float32)),
                       'quaternions': mi.TensorXf(quats.astype(np.float32)), 'bsdf': diffuse([0.3, 0.6, 0.8])}
    return d


def test_ellipsoids_agree_with_path():
    """Ellipsoids as surfaces, bdpt against path. Connections towards light vertices on them
    stop short by the quadric shapes' far stop (rays.QUADRIC_SHAPES; isolated by
    test_offsets.py::test_shadow_rays_to_points_on_quadrics): with the general one their own
    surface blocked 5% of them, and the ceiling of a 48 x 40 box was 3-5% dark in its top
    blocks (6 standard errors), a bias this 16 x 16 check is too coarse to see."""
    check('ellipsoid_box', ellipsoid_box, {'type': 'path', 'max_depth': 4}, 1024,
          {'type': 'bdpt', 'max_depth': 4, 'technique': 'bdpt'}, 256)


@pytest.mark.parametrize('sampler', ['stratified', 'ldsampler'])
def test_correlated_samplers_leave_the_image_unbiased(sampler):
    """Mitsuba 3.9.1's stratified and ldsampler correlate a sample's dimensions with each other,
    which biases every estimator that draws a path from them (Mitsuba's path at 4 spp: 2.2%
    dark under stratified): bdpt draws its paths from an independent sampler and takes only
    the pixel positions from the scene's (passes.pass_sampler, pixel_sampler). 64 batches of
    4 spp against the independent sampler's, pixel by pixel and in 4 x 4 blocks. Before, at
    this size: bdpt's pixels 22 (stratified) and 12 (ldsampler) standard errors from the
    independent sampler's, rms over 1500 batches; both failed here."""
    def scene(kind):
        d = cornell(16)
        d['sensor']['sampler'] = {'type': kind, 'sample_count': 4}
        return mi.load_dict(d)
    integ = {'type': 'bdpt', 'max_depth': 5}
    mine = render_batches(scene(sampler), integ, 4, 64)
    ref = render_batches(scene('independent'), integ, 4, 64, seed0=1000)
    ok, msg = agreement(mine, ref, alpha=0.01)
    assert ok, f'{sampler}: {msg}'


# ---------------------------------------------------------------------------- refusals
def test_aov_wrapper_refused_with_a_clear_message():
    """Mitsuba's aov integrator calls the nested integrator's per-sample sample(), which bdpt
    cannot serve (its light image splats across pixels): one message says so and how to get the
    AOVs; the aov integrator alone renders them."""
    scene = mi.load_dict(cornell(8))
    wrapped = mi.load_dict({'type': 'aov', 'aovs': 'dd:depth,nn:sh_normal', 'image': {'type': 'bdpt'}})
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=wrapped, spp=4)
    text = cause_chain(info.value)
    assert 'bdpt cannot run inside another integrator' in text
    assert 'Render the AOV channels with the aov integrator alone' in text
    aovs = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'aov', 'aovs': 'dd:depth,nn:sh_normal'}), spp=4))
    image = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt'}), spp=4))
    assert aovs.shape[:2] == image.shape[:2] and aovs.shape[2] == 4 and aovs[..., 0].max() > 3


def test_batch_sensor_refused_with_the_reason():
    d = cornell(8)
    s = d.pop('sensor')
    d['sensor'] = {'type': 'batch', 'a': s, 'b': dict(s), 'film': film(16, 8)}
    scene = mi.load_dict(d)
    with pytest.raises(UnsupportedSceneError, match="'batch' is not supported: it renders several sensors"):
        check_scene(scene, scene.sensors()[0])


# ---------------------------------------------------------------------------- the coverage table
def test_coverage_doc_lists_every_plugin():
    """docs/coverage.md names every plugin Mitsuba 3.9 ships (its plugin libraries), and marks
    the emitters and sensors scene_check supports as supported, the others as refused."""
    from bdpt_jit.scene_check import SUPPORTED_EMITTERS, SUPPORTED_SENSORS
    text = open(os.path.join(REPO, 'docs', 'coverage.md')).read()
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.split('|')]
        if len(cells) < 4 or not cells[1].startswith('`'):
            continue
        status = re.match(r'(supported|refused|not applicable|not tested)', cells[2])
        assert status, f'no status in: {line}'
        for name in re.findall(r'`([a-z0-9_]+)`', cells[1]):
            rows[name] = status.group(1)
    plugins = os.path.join(os.path.dirname(mi.__file__), 'plugins')
    shipped = {f[:-3] for f in os.listdir(plugins) if f.endswith('.so')}
    missing = sorted(shipped - set(rows))
    assert not missing, f'plugins missing from docs/coverage.md: {missing}'
    for name in SUPPORTED_EMITTERS + SUPPORTED_SENSORS:
        assert rows.get(name) == 'supported', name
    for name in ('timed_sunsky', 'batch'):
        assert rows.get(name) == 'refused', name
    for name in ('homogeneous', 'heterogeneous'):          # media are rendered (test_media_render.py)
        assert rows.get(name) == 'supported', name
