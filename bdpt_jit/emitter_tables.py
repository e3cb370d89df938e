"""Per-emitter tables that endpoints.EmitterTable reads in its kernels, built once per scene
from the scene's emitters and indexed by each emitter's registry id: the kinds of an emitter,
the cones of spot lights and projectors, the spheres that emitter sampling treats as seen
from outside (direct.py), and the inverse surface areas of area emitters' shapes."""

import math
import re

import drjit as dr
import mitsuba as mi
import numpy as np

from .connect import constant_value


def emitter_kinds(flags) -> set:
    """The kinds (Kinds' names) of one emitter, from its flags (Python ints)."""
    f = mi.EmitterFlags
    surface, ddir = mi.has_flag(flags, f.Surface), mi.has_flag(flags, f.DeltaDirection)
    kinds = set()
    if surface:
        kinds.add('dir_area' if ddir else 'area')
    if mi.has_flag(flags, f.DeltaPosition):
        kinds.add('delta_pos')
    if ddir and not surface:
        kinds.add('delta_dir')
    if mi.has_flag(flags, f.Infinite):
        kinds.add('infinite')
    return kinds


def spot_cones(emitters, ids, size):
    """(cos of the cutoff, unit axis) per emitter id: a spot light's cone, a projector's
    (projector_cone); the whole sphere (cos = -1) for every other emitter."""
    cos_cut, axis = [-1.0] * size, [[0.0, 0.0, 1.0] for _ in range(size)]
    for e, i in zip(emitters, ids):
        if e.class_name() == 'SpotLight':
            cos_cut[i], axis[i] = _spot_cone(e)
        elif e.class_name() == 'Projector':
            cos_cut[i], axis[i] = projector_cone(e)
    return mi.Float(cos_cut), mi.Vector3f([v[0] for v in axis], [v[1] for v in axis], [v[2] for v in axis])


def _spot_cone(emitter):
    """(cos of the half angle, unit axis) of a cone containing every direction a spot light
    lights. Mitsuba's spot evaluates the direction d by the local direction ``inverse() * d``
    (its stored inverse) against the cutoff angle: under a to_world that is a rotation (times a
    uniform scale) that is the circular cone of the cutoff around the image of +z; under a
    non-uniform scale (or a transform whose stored inverse is not its inverse) an elliptic one,
    which the cutoff's cone missed part of (lt 4.2% dark under a spot scaled 1.5 x 0.7). Then
    the cone bounds the images of 3600 directions of the cutoff's rim, widened by 1e-3 of its
    angle."""
    cos_c = math.cos(math.radians(float(dr.ravel(mi.traverse(emitter)['cutoff_angle']).numpy()[0])))
    inv = np.array(emitter.world_transform().inverse_transpose, dtype=np.float64).reshape(4, 4)[:3, :3].T
    to_world = np.linalg.inv(inv)             # what maps Mitsuba's local directions to the world's
    a = to_world[:, 2] / np.linalg.norm(to_world[:, 2])     # the spot shines along local +z
    rigid = to_world / np.linalg.norm(to_world[:, 0])
    if np.allclose(rigid.T @ rigid, np.eye(3), atol=1e-6):
        return cos_c, [float(x) for x in a]
    phi = np.linspace(0.0, 2 * math.pi, 3600, endpoint=False)
    sin_c = math.sqrt(max(0.0, 1.0 - cos_c * cos_c))
    rim = to_world @ np.stack([sin_c * np.cos(phi), sin_c * np.sin(phi), np.full_like(phi, cos_c)])
    angle = float(np.arccos(np.clip((a @ rim / np.linalg.norm(rim, axis=0)).min(), -1.0, 1.0)))
    return math.cos(min(math.pi, angle * (1.0 + 1e-3))), [float(x) for x in a]


def remapped_textures(emitters, ids, size):
    """A Bool per emitter id: an area emitter whose radiance texture maps the surface's uv through
    a ``to_uv`` transform other than the identity; None if there is none. Mitsuba's bitmap
    ``sample_position`` ignores ``to_uv``: it draws surface uvs by the texture's own layout, so a
    tiled or shifted texture is bright where those uvs have no density (technique lt 2.9% dark
    under one tiled 2 x 3), and light subpaths start uniformly on such emitters
    (EmitterTable.sample_position)."""
    flags = [False] * size
    for e, i in zip(emitters, ids):
        if 'area' not in emitter_kinds(e.flags()) or not mi.has_flag(e.flags(), mi.EmitterFlags.SpatiallyVarying):
            continue
        params = mi.traverse(e)
        for key in params.keys():
            if key.endswith('to_uv'):
                m = np.array(params[key].matrix, dtype=np.float64).reshape(3, 3)
                flags[i] = flags[i] or not np.allclose(m, np.eye(3), atol=1e-7)
    return mi.Bool(flags) if any(flags) else None


def cone_sphere(emitter) -> bool:
    """Whether emitter sampling of ``emitter`` may sample its visible cone itself (direct.py): an
    untextured sphere area emitter. Not a textured sphere (Mitsuba samples it by the texture), nor
    one with flipped normals, which emits inwards, where the cone's points carry outward normals."""
    shape = emitter.get_shape()
    return (shape is not None and shape.class_name() == 'Sphere' and emitter_kinds(emitter.flags()) == {'area'}
            and not mi.has_flag(emitter.flags(), mi.EmitterFlags.SpatiallyVarying) and not shape.has_flipped_normals())


def _sphere_placement(shape):
    """(centre, radius) of a ``sphere`` shape, from its to_world (Mitsuba folds centre and
    radius into it)."""
    m = np.array(mi.traverse(shape)['to_world'].matrix, dtype=np.float64).reshape(4, 4)
    return [float(x) for x in m[:3, 3]], float(np.linalg.norm(m[:3, 0]))


def sphere_shapes(emitters, ids):
    """{emitter id: (sign, centre, radius)} of every sphere area emitter: sign +1, or -1 with
    flipped normals, and its placement (_sphere_placement: one mi.traverse a sphere, shared by
    the tables below and media_path.EmitterMedia)."""
    out = {}
    for e, i in zip(emitters, ids):
        shape = e.get_shape()
        if shape is not None and shape.class_name() == 'Sphere':
            out[i] = (-1.0 if shape.has_flipped_normals() else 1.0,) + tuple(_sphere_placement(shape))
    return out


def sphere_table(emitters, ids, size, spheres):
    """(radius, centre) per emitter id of the ``cone_sphere`` emitters, whose emitter sampling from
    points that see them small is done by bdpt (direct.py); radius 0 for every other emitter.
    ``spheres``: sphere_shapes."""
    sph_r, sph_c = [0.0] * size, [[0.0, 0.0, 0.0] for _ in range(size)]
    for e, i in zip(emitters, ids):
        if cone_sphere(e):
            _, sph_c[i], sph_r[i] = spheres[i]
    return mi.Float(sph_r), mi.Point3f([v[0] for v in sph_c], [v[1] for v in sph_c], [v[2] for v in sph_c])


def sphere_placements(spheres, size):
    """(sign, centre, radius) per emitter id of every sphere area emitter (``spheres``:
    sphere_shapes), for sphere_positions; sign 0 for every other emitter, +1 or -1 (flipped
    normals) for a sphere. None if there is none."""
    if not spheres:
        return None
    sign, centre, radius = [0.0] * size, [[0.0, 0.0, 0.0] for _ in range(size)], [0.0] * size
    for i, (sign_i, centre_i, radius_i) in spheres.items():
        sign[i], centre[i], radius[i] = sign_i, centre_i, radius_i
    return (mi.Float(sign), mi.Point3f([v[0] for v in centre], [v[1] for v in centre], [v[2] for v in centre]),
            mi.Float(radius))


def sphere_positions(ps, index, placements, active=True):
    """``ps`` (a PositionSample3f of the emitters with registry ids ``index``) with the points
    of sphere emitters put on the sphere that rays hit. Mitsuba 3.9.1's sphere
    ``sample_position`` draws a uniform unit direction ``local`` and returns the point
    ``to_world * local`` with the normal ``local`` (src/shapes/sphere.cpp), while its rays hit
    the sphere of centre ``to_world * 0`` and radius ``|to_world * x|``. Under a rotation the
    normal was not the point's (lt 29% dark, bdpt 24% under a rotated bulb; its ``ptracer``
    alike); under a transform that is not a rotation times a uniform scale (a rotation about an
    axis that is not a unit vector: Mitsuba's ``rotate`` does not normalise it) the points lay
    off that sphere, half of them inside it, where the light subpath's first ray met the sphere
    itself (lt 76% dark, bdpt 62%). The point is now centre + radius * local, the normal
    ``local`` (Mitsuba's, with its sign): uniform over the sphere the rays hit, at Mitsuba's
    density 1 / (4 pi radius^2). Where ``to_world`` is a rotation it is another point than
    Mitsuba's, of the same density; the uv stays Mitsuba's (textured spheres must not be
    rotated: scene_check). A differentiated ``to_world`` keeps the derivative of Mitsuba's
    point."""
    if placements is None:
        return ps
    sign = dr.gather(mi.Float, placements[0], index, active)
    centre = dr.gather(mi.Point3f, placements[1], index, active)
    radius = dr.gather(mi.Float, placements[2], index, active)
    ok = sign != 0
    local = mi.Vector3f(ps.n) * sign                      # Mitsuba's normal: local, negated if flipped
    p = dr.fma(local, radius, centre)
    if dr.grad_enabled(ps.p):       # (a differentiated to_world: Mitsuba's point's derivative)
        p = ps.p + dr.detach(p - ps.p)
    ps.p = dr.select(ok, p, ps.p)
    return ps


def sphere_radiance(emitters, ids, size):
    """The radiance per emitter id where every emitter is a ``cone_sphere`` area light whose
    radiance is a constant (connect.constant_value): a table of mi.Spectrum, which emitter
    sampling reads instead of the emitter's ``eval_direction`` (direct.py, ``all_spheres``). None
    where any emitter is something else, and in spectral variants (a radiance there is a
    spectrum that the sample's wavelengths evaluate)."""
    if mi.is_spectral or not emitters:
        return None
    channels = 1 if mi.is_monochromatic else 3
    le = np.zeros((channels, size), np.float32)
    for e, i in zip(emitters, ids):
        v = constant_value(e, 'radiance.value', ('sampling_weight',)) \
            if cone_sphere(e) and e.class_name() == 'AreaLight' else None
        if v is None or v.size not in (1, channels):
            return None
        le[:, i] = np.broadcast_to(v, channels)
    return mi.Spectrum(le)         # (channels x emitter ids)


def inverse_areas(emitters, ids, size):
    """1 / area of each area emitter's shape per emitter id: Mitsuba's uniform position density
    (read from this table, not through a shape call: a virtual call on shapes reaches instances,
    whose pdf_position raises, in scenes that have any)."""
    inv_area = [0.0] * size
    for e, i in zip(emitters, ids):
        shape = e.get_shape()
        if shape is not None:
            area = float(dr.ravel(shape.surface_area()).numpy()[0])
            inv_area[i] = 1.0 / area if area > 0 else 0.0
    return mi.Float(inv_area)


def projector_cone(emitter):
    """(cos of the half angle, unit axis) of a circular cone around a ``projector``'s frustum:
    light subpaths sample their directions uniformly in it (directions outside the frustum get
    no intensity from Mitsuba's ``sample_direction``), and the densities use the same cone.
    The frustum is Mitsuba's: x_fov (from the emitter's description: Mitsuba exposes no
    accessor) and the texture's aspect, image plane at z = 1 of the emitter's to_world,
    half-extents tan(x_fov / 2) and that over the aspect. The corners' directions bound it (a
    circular cone containing the four edges contains their convex hull); the cone is widened
    by 1e-3 of its angle, and checked against the directions of Mitsuba's own ``sample_ray``."""
    from .scene_check import UnsupportedSceneError
    match = re.search(r'x_fov = ([0-9.eE+-]+)', str(emitter))
    if match is None:
        raise UnsupportedSceneError("bdpt: cannot read the field of view of the projector emitter "
                                    "(Mitsuba's description of it has no x_fov)")
    tan_x = math.tan(math.radians(float(match.group(1))) / 2)
    params = mi.traverse(emitter)
    aspect = 1.0
    if 'irradiance.data' in params.keys():
        h, w = np.array(params['irradiance.data']).shape[:2]
        aspect = w / h
    tan_y = tan_x / aspect
    m = np.array(emitter.world_transform().matrix, dtype=np.float64).reshape(4, 4)[:3, :3]
    axis = m @ np.array([0.0, 0.0, 1.0])
    axis /= np.linalg.norm(axis)
    cos_min = 1.0
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = m @ np.array([sx * tan_x, sy * tan_y, 1.0])
            cos_min = min(cos_min, float(np.dot(axis, c / np.linalg.norm(c))))
    angle = math.acos(max(-1.0, min(1.0, cos_min))) * (1 + 1e-3) + 1e-6
    if angle >= math.pi / 2:
        raise UnsupportedSceneError("bdpt: a projector emitter wider than a hemisphere is not supported")
    cos_cut = math.cos(angle)
    # Mitsuba's own emitted directions must lie in the cone (a check of the frustum read above)
    n = 4096
    rng = np.random.default_rng(0)
    u = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    ray, w = emitter.sample_ray(0.0, 0.5, u, u, True)
    d = np.array(ray.d, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=0, keepdims=True)          # (3, n)
    lit = np.broadcast_to(np.array(dr.max(w), dtype=np.float64).reshape(-1) > 0, (n,))
    if np.any((axis @ d)[lit] < cos_cut):
        raise UnsupportedSceneError("bdpt: the projector emitter's frustum could not be bounded "
                                    "(its emitted directions leave the cone computed from its field of view)")
    return cos_cut, [float(axis[0]), float(axis[1]), float(axis[2])]
