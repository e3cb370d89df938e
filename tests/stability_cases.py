"""Scene builders for the numerical-stability suite (tests/test_stability.py, tests/test_fuzz.py),
and the Cornell box every test builds (``cornell``; loaded: helpers.cornell_scene).

Every builder returns a Mitsuba scene *dict* (``mi.load_dict`` it), small (8x8 to 32x32, box
filter) so that a case renders in well under a second once its kernels are compiled. The dicts
hold only plain values and ``mi.ScalarTransform4f``, so the fuzzer can write them to a file and
replay them (``dict_to_py`` / ``dict_from_py``).
"""

import math

import mitsuba as mi
import numpy as np

T = mi.ScalarTransform4f

WHITE = {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.8, 0.8, 0.8]}}


def rgb(v):
    return {'type': 'rgb', 'value': [float(x) for x in v] if isinstance(v, (list, tuple)) else float(v)}


def diffuse(v=0.8):
    return {'type': 'diffuse', 'reflectance': rgb(v)}


def film(width, height=None, crop=None):
    f = {'type': 'hdrfilm', 'width': int(width), 'height': int(height or width), 'pixel_format': 'rgb',
         'rfilter': {'type': 'box'}}
    if crop is not None:
        ox, oy, cw, ch = crop
        f.update(crop_offset_x=ox, crop_offset_y=oy, crop_width=cw, crop_height=ch)
    return f


def sensor(origin, target, up=(0, 1, 0), fov=40.0, res=16, height=None, crop=None, near_clip=1e-3,
           far_clip=1e4, kind='perspective', spp=4, **extra):
    s = {'type': kind, 'fov': float(fov), 'near_clip': float(near_clip), 'far_clip': float(far_clip),
         'to_world': T().look_at(origin=list(map(float, origin)), target=list(map(float, target)),
                                 up=list(map(float, up))),
         'film': film(res, height, crop),
         'sampler': {'type': 'independent', 'sample_count': spp}}
    s.update(extra)
    return s


# ---------------------------------------------------------------------------- Cornell box
def cornell(res=16, height=None, crop=None, light=True, closed=False, albedo=None, radiance_scale=1.0,
            camera=None):
    """Mitsuba's Cornell box (``mi.cornell_box()``: walls at +-1, camera at z=3.9 looking at -z),
    box filter, ``res`` x ``height`` (default square) pixels, ``crop``: (offset x, offset y,
    width, height). ``light=False``: no emitter. ``radiance_scale`` scales the light's radiance.
    ``camera``: sensor properties updated (e.g. ``{'type': 'thinlens', ...}``). ``closed``: a
    front wall at z=+1 facing inwards, and the camera moved inside (at z=0.9, wide angle).
    ``albedo``: every BSDF becomes a white diffuse of that albedo."""
    d = mi.cornell_box()
    d.pop('integrator', None)
    d['sensor']['film'] = film(res, height, crop)
    d['sensor']['sampler'] = {'type': 'independent', 'sample_count': 4}
    if not light:
        d.pop('light')
    elif radiance_scale != 1.0:
        v = d['light']['emitter']['radiance']['value']
        d['light']['emitter']['radiance']['value'] = [float(x) * radiance_scale for x in v]
    if albedo is not None:
        for k in ('white', 'red', 'green'):
            d[k] = diffuse(albedo)
    if closed:
        # front wall at z = +1, normal towards -z (into the box)
        d['front'] = {'type': 'rectangle', 'to_world': T().translate([0, 0, 1]).rotate([0, 1, 0], 180),
                      'bsdf': {'type': 'ref', 'id': 'white'}}
        d['sensor'].update(fov=100.0, to_world=T().look_at(origin=[0, 0, 0.9], target=[0, 0, -1], up=[0, 1, 0]))
    if camera is not None:
        d['sensor'].update(camera)
    return d


def transformed(d, scale=1.0, translate=(0.0, 0.0, 0.0)):
    """The scene ``d`` (shapes with ``to_world``, point lights with ``position``, one sensor
    built by look_at) moved by x -> scale * x + translate. Radiance is unchanged, so the exact
    image is the same at every scale. The camera keeps a rigid frame (Mitsuba refuses scale in
    a camera transform): its origin is moved, and its clip planes scaled."""
    M = T().translate(list(map(float, translate))) @ T().scale(float(scale))
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            v = dict(v)
            if k == 'sensor':
                m = np.array(v['to_world'].matrix, dtype=np.float64).reshape(4, 4)
                o = m[:3, 3] * scale + np.array(translate)
                fwd = m[:3, 2]
                up = m[:3, 1]
                v['to_world'] = T().look_at(origin=o.tolist(), target=(o + fwd).tolist(), up=up.tolist())
                v['near_clip'] = float(v.get('near_clip', 1e-3)) * scale
                v['far_clip'] = float(v.get('far_clip', 100.0)) * scale
            elif 'to_world' in v:
                v['to_world'] = M @ v['to_world']
            elif 'position' in v:
                p = np.array(v['position'], dtype=np.float64) * scale + np.array(translate)
                v['position'] = p.tolist()
        out[k] = v
    return out


# ---------------------------------------------------------------------------- sphere lights
def sphere_light(radius, height=250.0, res=16, visible=False):
    """A sphere emitter of ``radius`` whose centre is ``height`` above a diffuse floor (with a
    diffuse box and a rough-plastic sphere on it), at constant power: radiance
    L = height^2 / (pi radius^2), so that the floor's irradiance below the light is ~1 whatever
    the radius (the same power as a point light of intensity height^2 at the centre:
    ``sphere_light_point_equivalent``). The light is out of the camera's view unless
    ``visible``. radius 1e-4 at height 1.5: (r/d)^2 = 4.4e-9 < 2^-24, so the cone that
    Mitsuba's emitter sampling draws in has cos(theta_max) = 1 in single precision."""
    L = height ** 2 / (math.pi * radius ** 2)
    cam = sensor([0, 3, 4], [0, 0, 0], res=res, fov=45, far_clip=1e4) if visible else \
        sensor([0, 1.0, 4.5], [0, 0.2, 0], res=res, fov=30, far_clip=1e4)
    return {
        'type': 'scene',
        'sensor': cam,
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(5), 'bsdf': diffuse(0.7)},
        'box': {'type': 'cube', 'to_world': T().translate([-0.8, 0.5, 0]).scale(0.5), 'bsdf': diffuse([0.7, 0.3, 0.2])},
        'ball': {'type': 'sphere', 'center': [0.9, 0.6, 0.3], 'radius': 0.6,
                 'bsdf': {'type': 'roughplastic', 'alpha': 0.3, 'diffuse_reflectance': rgb([0.2, 0.4, 0.7])}},
        'light': {'type': 'sphere', 'center': [0.3, float(height), 0.2], 'radius': float(radius),
                  'emitter': {'type': 'area', 'radiance': rgb(L)}},
    }


def sphere_light_point_equivalent(radius, height=250.0, res=16):
    """``sphere_light`` with the sphere replaced by a point light of the same power at its
    centre (intensity height^2): the same image up to O((radius / distance)^2), and one that
    Mitsuba's `path` renders without the sphere's cone sampling."""
    d = sphere_light(radius, height, res)
    light = d.pop('light')
    d['light'] = {'type': 'point', 'position': light['center'], 'intensity': rgb(height ** 2)}
    return d


# ---------------------------------------------------------------------------- point lights
def point_near_wall(dist=1e-6, res=16):
    """A point light ``dist`` in front of the Cornell box's back wall (z = -1)."""
    d = cornell(res, light=False)
    d['light'] = {'type': 'point', 'position': [0.1, 0.2, -1.0 + dist], 'intensity': rgb(1.0)}
    return d


def point_in_closed_box(res=16, albedo=None):
    """A point light inside the closed Cornell box, the camera inside too (Mitsuba 0.6's
    single 80,000x firefly)."""
    d = cornell(res, light=False, closed=True, albedo=albedo)
    d['light'] = {'type': 'point', 'position': [0.0, 0.6, -0.2], 'intensity': rgb(2.0)}
    return d


def point_at_pinhole(res=16):
    """A point light exactly at the camera's pinhole (0, 0, 3.9)."""
    d = cornell(res, light=False)
    d['light'] = {'type': 'point', 'position': [0.0, 0.0, 3.9], 'intensity': rgb(10.0)}
    return d


def point_in_opaque_box(res=16):
    """A point light shut inside a closed box, the camera outside: no light can arrive."""
    return {
        'type': 'scene',
        'sensor': sensor([0, 1, 4], [0, 0, 0], res=res),
        'box': {'type': 'cube', 'bsdf': diffuse(0.8)},
        'floor': {'type': 'rectangle', 'to_world': T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(4),
                  'bsdf': diffuse(0.8)},
        'light': {'type': 'point', 'position': [0.1, 0.2, 0.0], 'intensity': rgb(100.0)},
    }


def emitters_facing_away(res=16):
    """An area light above the Cornell box facing up into the void, and a spot light in front of
    it shining away from the box: no light reaches anything the camera sees (and the area light's
    back faces the scene)."""
    d = cornell(res, light=False)
    d['away_area'] = {'type': 'rectangle', 'to_world': T().translate([0, 1.5, 0]).rotate([1, 0, 0], -90).scale(0.5),
                      'emitter': {'type': 'area', 'radiance': rgb(10.0)}}
    d['away_spot'] = {'type': 'spot', 'cutoff_angle': 15.0, 'intensity': rgb(50.0),
                      'to_world': T().look_at(origin=[0, 0, 1.5], target=[0, 0, 10], up=[0, 1, 0])}
    return d


# ---------------------------------------------------------------------------- grazing angles
GRAZE_DEG = 0.1      # 89.9 degrees from the normal


def grazing(light='directional', res=16, elevation_deg=GRAZE_DEG):
    """A diffuse floor (y = 0) seen by a camera whose central ray is ``elevation_deg`` above the
    floor (89.9 degrees from its normal), lit at the same angle by a ``light``: directional, an
    area light far along the floor, or a spot."""
    e = math.radians(elevation_deg)
    D = 4.0
    h = D * math.tan(e)
    d = {
        'type': 'scene',
        'sensor': sensor([0, h, 0], [0, 0, D], res=res, fov=4.0, near_clip=1e-4),
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(200), 'bsdf': diffuse(0.7)},
        'post': {'type': 'cube', 'to_world': T().translate([0.15, 0.05, D + 1]).scale(0.05), 'bsdf': diffuse(0.5)},
    }
    if light == 'directional':
        d['light'] = {'type': 'directional', 'direction': [0.0, -math.sin(e), -math.cos(e)],
                      'irradiance': rgb(500.0)}
    elif light == 'area':
        dist = 100.0
        c = [0.0, dist * math.tan(e), D + dist]
        d['light'] = {'type': 'rectangle', 'to_world': T().look_at(origin=c, target=[0, 0, D], up=[0, 1, 0]).scale(0.5),
                      'emitter': {'type': 'area', 'radiance': rgb(5e4)}}
    elif light == 'spot':
        d['light'] = {'type': 'spot', 'cutoff_angle': 20.0, 'intensity': rgb(5e3),
                      'to_world': T().look_at(origin=[0, 20 * math.tan(e), D + 20], target=[0, 0, D], up=[0, 1, 0])}
    else:
        raise ValueError(light)
    return d


def camera_in_floor_plane(res=8):
    """The camera exactly in the floor's plane (y = 0) looking along it: the central rays are
    parallel to the floor (|cos| = 0 where they meet its edge)."""
    return {
        'type': 'scene',
        'sensor': sensor([0, 0, 0], [0, 0, 5], res=res, fov=10.0),
        'floor': {'type': 'rectangle', 'to_world': T().translate([0, 0, 5]).rotate([1, 0, 0], -90).scale(3),
                  'bsdf': diffuse(0.7)},
        'wall': {'type': 'rectangle', 'to_world': T().translate([0, 0, 8]).rotate([0, 1, 0], 180).scale(3),
                 'bsdf': diffuse(0.7)},
        'light': {'type': 'rectangle', 'to_world': T().translate([0, 2, 5]).rotate([1, 0, 0], 90).scale(0.5),
                  'emitter': {'type': 'area', 'radiance': rgb(10.0)}},
    }


# ---------------------------------------------------------------------------- geometry
def corner(res=16, at_origin=True):
    """A 90-degree corner (three faces of a box meeting at one point) seen from close by, lit by
    a small area light: camera and light vertices nearly touch along the edges. With
    ``at_origin`` the corner is at (0,0,0), where single-precision coordinates are densest and
    distances between vertices on different faces can be tiny."""
    o = np.zeros(3) if at_origin else np.array([-1.0, -1.0, -1.0])
    def tr(*a):
        return (o + np.array(a, dtype=float)).tolist()
    return {
        'type': 'scene',
        'sensor': sensor(tr(0.6, 0.5, 0.7), tr(0, 0, 0), res=res, fov=30.0, near_clip=1e-4),
        # three unit squares on the planes x=0, y=0, z=0, normals pointing into the octant
        'wall_x': {'type': 'rectangle', 'to_world': T().translate(tr(0, 0.5, 0.5)).rotate([0, 1, 0], 90).scale(0.5),
                   'bsdf': diffuse([0.8, 0.3, 0.3])},
        'wall_y': {'type': 'rectangle', 'to_world': T().translate(tr(0.5, 0, 0.5)).rotate([1, 0, 0], -90).scale(0.5),
                   'bsdf': diffuse(0.8)},
        'wall_z': {'type': 'rectangle', 'to_world': T().translate(tr(0.5, 0.5, 0)).scale(0.5),
                   'bsdf': diffuse([0.3, 0.8, 0.3])},
        'light': {'type': 'rectangle',
                  'to_world': T().look_at(origin=tr(0.5, 0.9, 0.5), target=tr(0.3, 0, 0.3), up=[1, 0, 0]).scale(0.1),
                  'emitter': {'type': 'area', 'radiance': rgb(30.0)}},
    }


def lowpoly_sphere_mesh(n_theta=4, n_phi=6, radius=1.0, center=(0, 0, 0), bsdf=None, emitter=None, flip=False):
    """A UV sphere of few triangles with per-vertex normals (interpolated shading normals far
    from the geometric ones), as an ``mi.Mesh`` object (load_dict accepts it); ``emitter``: a
    dict of the emitter it carries; ``flip``: its normals flipped (Mitsuba's flip_normals)."""
    import drjit as dr
    from helpers import uv_sphere
    unit, F = uv_sphere(n_theta, n_phi)
    V = unit * radius + np.array(center, np.float64)
    N = unit
    # outward winding: flip faces whose geometric normal points inwards
    for k, (a, b, c) in enumerate(F):
        n = np.cross(V[b] - V[a], V[c] - V[a])
        if np.dot(n, (V[a] + V[b] + V[c]) / 3 - np.array(center)) < 0:
            F[k] = [a, c, b]
    props = mi.Properties()
    props['bsdf'] = mi.load_dict(bsdf or diffuse(0.8))
    if emitter is not None:
        props['emitter'] = mi.load_dict(emitter)
    props['flip_normals'] = flip
    mesh = mi.Mesh('lowpoly', len(V), len(F), props=props, has_vertex_normals=True)
    p = mi.traverse(mesh)
    p['vertex_positions'] = dr.ravel(mi.Point3f(*(V[:, i].astype(np.float32) for i in range(3))))
    p['vertex_normals'] = dr.ravel(mi.Normal3f(*(N[:, i].astype(np.float32) for i in range(3))))
    p['faces'] = dr.ravel(mi.Vector3u(*(F[:, i] for i in range(3))))
    p.update()
    return mesh


def lowpoly_sphere(res=16, bsdf=None):
    """An 8-sided low-polygon sphere with interpolated normals on a floor, lit by an area light."""
    return {
        'type': 'scene',
        'sensor': sensor([0, 1.5, 4], [0, 0, 0], res=res, fov=40),
        'ball': lowpoly_sphere_mesh(bsdf=bsdf),
        'floor': {'type': 'rectangle', 'to_world': T().translate([0, -1, 0]).rotate([1, 0, 0], -90).scale(4),
                  'bsdf': diffuse(0.6)},
        'light': {'type': 'rectangle', 'to_world': T().look_at(origin=[1.5, 3, 1], target=[0, 0, 0], up=[0, 1, 0]).scale(0.6),
                  'emitter': {'type': 'area', 'radiance': rgb(8.0)}},
    }


def normal_map_texture(n=32, seed=3):
    """A bumpy tangent-space normal map (RGB in [0, 1]) as a float32 array (n, n, 3): strong
    tilts up to ~60 degrees, including texels that lean towards grazing."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] / n
    nx = 0.9 * np.sin(2 * math.pi * 3 * x) + 0.3 * rng.standard_normal((n, n))
    ny = 0.9 * np.cos(2 * math.pi * 2 * y) + 0.3 * rng.standard_normal((n, n))
    nz = np.ones_like(nx) * 0.6
    v = np.stack([nx, ny, nz], -1)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return (v * 0.5 + 0.5).astype(np.float32)


def normal_map_file():
    """``normal_map_texture`` written to an EXR in the temporary directory (a file name keeps
    scene dicts reusable: a tensor in a dict is consumed by the first load), named by its
    content: the name enters the scene's description and so its reference's key
    (helpers.scene_fingerprint), which a per-process name changed in every run (a cold CI run
    rendered the reference of test_light_tracing_covers_the_exact_adjoint_of_normal_maps
    again). Written atomically once and left there, so no worker removes it under another."""
    import hashlib
    import os
    import tempfile
    data = normal_map_texture()
    digest = hashlib.sha1(data.tobytes()).hexdigest()[:12]
    path = os.path.join(tempfile.gettempdir(), f'bdpt_stability_normalmap_{digest}.exr')
    if not os.path.exists(path):
        tmp = path + f'.{os.getpid()}.tmp.exr'
        mi.Bitmap(data).write(tmp)
        os.replace(tmp, path)
    return path


def normal_mapped(res=16, inner=None):
    """A normal-mapped rectangle (floor) and sphere, lit by an area light."""
    inner = inner or {'type': 'roughplastic', 'alpha': 0.2, 'diffuse_reflectance': rgb([0.6, 0.5, 0.4])}
    path = normal_map_file()
    def nmap(b):
        return {'type': 'normalmap', 'normalmap': {'type': 'bitmap', 'filename': path, 'raw': True,
                                                    'filter_type': 'nearest'}, 'bsdf': b}
    return {
        'type': 'scene',
        'sensor': sensor([0, 2, 3], [0, 0, 0], res=res, fov=45),
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(2), 'bsdf': nmap(diffuse(0.7))},
        'ball': {'type': 'sphere', 'center': [0.3, 0.5, 0.0], 'radius': 0.5, 'bsdf': nmap(inner)},
        'light': {'type': 'rectangle', 'to_world': T().look_at(origin=[-1, 2.5, 1], target=[0, 0, 0], up=[0, 1, 0]).scale(0.5),
                  'emitter': {'type': 'area', 'radiance': rgb(10.0)}},
    }


def bump_mapped(res=16):
    """normal_mapped with bump maps (the normal-map image read as a height field, scale 0.3),
    one of them inside a twosided BSDF."""
    path = normal_map_file()
    def bump(b, scale=0.3):
        return {'type': 'bumpmap', 'scale': scale, 'texture': {'type': 'bitmap', 'filename': path, 'raw': True},
                'bsdf': b}
    d = normal_mapped(res)
    d['floor']['bsdf'] = {'type': 'twosided', 'bsdf': bump(diffuse(0.7))}
    d['ball']['bsdf'] = bump({'type': 'roughconductor', 'alpha': 0.25})
    return d


def negative_scale(res=16):
    """Shapes with a mirroring (negative-determinant) transform: a cube scaled by (-1, 1, 1), a
    sphere and a rectangle mirrored, the light itself mirrored."""
    return {
        'type': 'scene',
        'sensor': sensor([0, 2, 4], [0, 0, 0], res=res, fov=45),
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale([-3, 3, 3]), 'bsdf': diffuse(0.7)},
        'box': {'type': 'cube', 'to_world': T().translate([-0.7, 0.4, 0]).scale([-0.4, 0.4, 0.4]), 'bsdf': diffuse([0.7, 0.3, 0.2])},
        'ball': {'type': 'sphere', 'to_world': T().translate([0.7, 0.5, 0]).scale([0.5, -0.5, 0.5]),
                 'bsdf': {'type': 'roughconductor', 'alpha': 0.3}},
        'light': {'type': 'rectangle', 'to_world': T().translate([0, 2.5, 0]).rotate([1, 0, 0], 90).scale([0.5, -0.5, 0.5]),
                  'emitter': {'type': 'area', 'radiance': rgb(12.0)}},
    }


# ---------------------------------------------------------------------------- delta chains
def mirror_glass_mirror(res=16, light='area'):
    """Two facing mirrors with a glass sphere between them above a diffuse floor: paths of the
    form light - mirror - glass - glass - mirror - floor - camera, and the mirrors and glass seen
    directly. ``light``: a large area light (which `path` can find by BSDF sampling) or a point."""
    d = {
        'type': 'scene',
        'sensor': sensor([0, 2.0, 4.5], [0, 0.5, 0], res=res, fov=50),
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3), 'bsdf': diffuse(0.7)},
        'mirror_l': {'type': 'rectangle', 'to_world': T().translate([-1.5, 1, 0]).rotate([0, 1, 0], 90).scale(1.2),
                     'bsdf': {'type': 'conductor', 'material': 'none'}},
        'mirror_r': {'type': 'rectangle', 'to_world': T().translate([1.5, 1, 0]).rotate([0, 1, 0], -90).scale(1.2),
                     'bsdf': {'type': 'conductor', 'material': 'none'}},
        'glass': {'type': 'sphere', 'center': [0, 0.7, 0], 'radius': 0.6, 'bsdf': {'type': 'dielectric', 'int_ior': 1.5}},
    }
    if light == 'area':
        d['light'] = {'type': 'rectangle', 'to_world': T().translate([0, 3, 0]).rotate([1, 0, 0], 90).scale(2.0),
                      'emitter': {'type': 'area', 'radiance': rgb(2.0)}}
    else:
        d['light'] = {'type': 'point', 'position': [-1.0, 2.0, 0.5], 'intensity': rgb(10.0)}
    return d


def delta_only(res=16):
    """Only delta vertices between a point light and the pinhole: every surface is a mirror or
    glass, the light a point. No estimator can sample such paths (no vertex to connect at, no
    surface to hit the light from): the exact image is zero."""
    return {
        'type': 'scene',
        'sensor': sensor([0, 1.0, 4.0], [0, 0.5, 0], res=res, fov=50),
        'floor': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(3),
                  'bsdf': {'type': 'conductor', 'material': 'Au'}},
        'mirror': {'type': 'rectangle', 'to_world': T().translate([0, 1, -1.5]).scale(1.5),
                   'bsdf': {'type': 'conductor', 'material': 'none'}},
        'glass': {'type': 'sphere', 'center': [0, 0.7, 0], 'radius': 0.6, 'bsdf': {'type': 'dielectric', 'int_ior': 1.5}},
        'glass2': {'type': 'sphere', 'center': [-0.9, 0.3, 0.6], 'radius': 0.3, 'bsdf': {'type': 'thindielectric'}},
        'light': {'type': 'point', 'position': [0.5, 1.5, 1.0], 'intensity': rgb(10.0)},
    }


# ---------------------------------------------------------------------------- statistics
def agree(mine, ref, mask=None, rel=1e-4):
    """helpers.agreement, with the pixels where a t-test says nothing checked apart:
    - where the reference is exactly 0 in every batch (nothing there, or a surface seen exactly
      edge-on), ``mine`` must stay below ``rel`` x the image mean: single-precision geometry
      leaves a trace there (camera_in_floor_plane: 6e-7, the floor's plane tilted by float32
      rounding of its rotation, 4.4e-8 rad);
    - where both are noise-free (a deterministic direct light: grazing_directional), the
      means must agree to ``rel`` (helpers' exact branch allows 1e-6, below float32 summation
      error over 1024 samples)."""
    m = np.ones(mine.shape[1:3], bool) if mask is None else mask.copy()
    scale = max(float(np.abs(ref.mean())), 1e-12)
    zero_ref = np.all(ref == 0, axis=(0, 3))
    still = np.all(mine.var(axis=0) == 0, axis=-1) & np.all(ref.var(axis=0) == 0, axis=-1) & ~zero_ref
    bad = []
    z = m & zero_ref
    if z.any() and np.abs(mine.mean(axis=0)[z]).max() > rel * scale:
        bad.append(f'{int(z.sum())} pixels where the reference is exactly 0: max {np.abs(mine.mean(axis=0)[z]).max():.3g}')
    q = m & still
    if q.any():
        d = np.abs(mine.mean(axis=0)[q] - ref.mean(axis=0)[q]).max()
        if d > rel * scale:
            bad.append(f'{int(q.sum())} noise-free pixels differ by {d:.3g}')
    from helpers import agreement
    ok, msg = agreement(mine, ref, mask=m & ~zero_ref & ~still)
    if bad:
        ok = False
        msg = msg + '; ' + '; '.join(bad)
    return ok, msg


# ---------------------------------------------------------------------------- replay helpers
def dict_to_py(d):
    """Python source for a scene dict made of plain values, ScalarTransform4f and nested dicts
    (the fuzzer's scenes): ``dict_from_py`` reads it back."""
    def enc(v, ind):
        pad = ' ' * ind
        if isinstance(v, dict):
            items = ''.join(f"{pad}    {k!r}: {enc(x, ind + 4)},\n" for k, x in v.items())
            return '{\n' + items + pad + '}'
        if isinstance(v, mi.ScalarTransform4f):     # matrix and inverse transpose, bit for bit
            m = np.array(v.matrix, dtype=np.float64).reshape(4, 4).tolist()
            it = np.array(v.inverse_transpose, dtype=np.float64).reshape(4, 4).tolist()
            return f"T({m!r}, {it!r})"
        if isinstance(v, (list, tuple)):
            return '[' + ', '.join(enc(x, ind) for x in v) + ']'
        if isinstance(v, float):
            return repr(float(v))
        return repr(v)
    return ('# bdpt_jit stability fuzzer scene; replay: tests/test_fuzz.py::replay(path)\n'
            'SCENE = ' + enc(d, 0) + '\n')


def dict_from_py(text):
    def T(m, it=None):
        M = mi.ScalarMatrix4f(np.array(m, dtype=np.float32))
        if it is None:
            return mi.ScalarTransform4f(M)
        return mi.ScalarTransform4f(M, mi.ScalarMatrix4f(np.array(it, dtype=np.float32)))
    ns = {'T': T}
    exec(compile(text, '<scene>', 'exec'), ns)
    return ns['SCENE']


# ---------------------------------------------------------------------------- edge-value sampler
ONE_MINUS_EPS = float(np.nextafter(np.float32(1.0), np.float32(0.0)))   # 1 - 2^-24, largest float32 < 1
EDGE_SAMPLER = 'bdpt_stability_edge'


class EdgeSampler(mi.Sampler):
    """A sampler plugin whose every number is exactly 0 or 1 - 2^-24 (``pattern``: 'zero',
    'one', or 'mixed': each lane and dimension a hash-chosen one of the two). ``bdpt`` draws
    every random number of its kernels from the sensor's sampler (camera position and lens,
    emitter choice, emission position and direction, BSDF lobes and directions, splat lens
    samples, Russian roulette), so rendering with it feeds these values to every sampling
    routine that the kernels call, in the kernels themselves. The dimension counter advances
    while a kernel is traced, so in a loop every iteration sees the values of the first."""

    def __init__(self, props):
        super().__init__(props)
        self.pattern = props['pattern'] if 'pattern' in props else 'zero'
        self.w = 1
        self.dim = 0

    def clone(self):
        p = mi.Properties()
        p['pattern'] = self.pattern
        p['sample_count'] = self.sample_count()
        return EdgeSampler(p)

    def fork(self):
        return self.clone()

    def seed(self, seed, wavefront_size=1):
        self.w = int(wavefront_size)
        self.dim = 0

    def set_sample_count(self, count):
        pass

    def _value(self):
        import drjit as dr
        k = self.dim
        self.dim += 1
        if self.pattern == 'zero':
            return dr.full(mi.Float, 0.0, self.w)
        if self.pattern == 'one':
            return dr.full(mi.Float, ONE_MINUS_EPS, self.w)
        h = dr.arange(mi.UInt32, self.w) * 0x9E3779B1 ^ mi.UInt32((k * 0x85EBCA77 + 0x165667B1) & 0xFFFFFFFF)
        h = h ^ (h >> 15)
        h = h * 0x2C1B3C6D
        h = h ^ (h >> 12)
        return dr.select((h & 1) == 1, ONE_MINUS_EPS, 0.0)

    def next_1d(self, active=True):
        return self._value()

    def next_2d(self, active=True):
        return mi.Point2f(self._value(), self._value())

    def to_string(self):
        return f'EdgeSampler[pattern={self.pattern}]'


_registered = False


def register_edge_sampler():
    global _registered
    if not _registered:
        mi.register_sampler(EDGE_SAMPLER, lambda props: EdgeSampler(props))
        _registered = True


def with_edge_sampler(d, pattern):
    """The scene dict ``d`` with its sensor's sampler replaced by the edge-value sampler."""
    register_edge_sampler()
    d = dict(d)
    d['sensor'] = dict(d['sensor'])
    d['sensor']['sampler'] = {'type': EDGE_SAMPLER, 'pattern': pattern, 'sample_count': 4}
    return d
