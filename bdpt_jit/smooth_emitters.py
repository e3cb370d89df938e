"""Area emitters on smooth-shaded meshes: their positions sampled with the triangle's own normal.

Mitsuba 3.9.1's mesh ``sample_position`` returns the interpolated shading normal as the
position's normal, and its area emitter's ``sample_direction`` converts the density to solid
angle with it. But emitted power leaves a surface element by the cosine to its geometric
normal, and a ray leaving the point crosses its triangle's plane, not the shading normal's: on a
smooth-shaded sphere of 224 triangles light subpaths started about the shading normal made
bdpt and lt 1.1% bright against a render from emitter hits alone (48 triangles: 2%; Mitsuba's
``path`` 0.1-0.3%, its emitter sampling weighed down by MIS). Radiance itself stays Mitsuba's:
an area emitter emits towards the side of the shading normal (``eval`` reads ``si.wi`` in the
shading frame), as camera rays that hit it see.

For these meshes (untextured area emitters whose vertex normals differ from their faces'
normals) bdpt samples the position itself, uniformly by area as Mitsuba does (a triangle by
its area, then a uniform point on it): the point, its triangle's normal and its shading normal
(both negated where the mesh flips its normals, as Mitsuba's hits are). Light subpaths leave
cosine-distributed about the triangle's normal, or (UNIFORM_SHARE of them) in a uniform
direction: radiance leaves also behind the triangle, in the directions that the shading normal
faces and the triangle does not (on a closed mesh of 48 triangles whose normals face inwards,
what the camera sees from outside is only that), emitter sampling converts the area density
with the triangle's normal, and every emission density the MIS reads at such an emitter's points uses the
triangle's normal (endpoints.py, direct.py, camera_path.py). Textured radiance keeps Mitsuba's
sampling (it draws positions through the texture). Meshes whose vertex positions are being
differentiated keep Mitsuba's (its position samples carry their derivatives)."""

import drjit as dr
import mitsuba as mi
import numpy as np

from .emitter_tables import emitter_kinds

# a vertex normal farther than this from a face's normal (1 - cos) makes a mesh smooth-shaded
SMOOTH_TOL = 1e-6
# the share of light subpaths that leave such a mesh in a uniform direction (emission_direction)
UNIFORM_SHARE = 0.1


def _emitter_meshes(scene):
    """Emitter registry id -> its shape, for the emissive meshes of ``scene`` (as scene.shapes()
    gives them: ``emitter.get_shape()`` returns a Shape without the Mesh interface)."""
    out = {}
    for shape in scene.shapes():
        if shape.is_emitter() and shape.is_mesh():
            out[int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(shape.emitter()))[0])] = shape
    return out


def _smooth_mesh(emitter, shape):
    """The mesh ``shape`` of an untextured area ``emitter`` if it is smooth-shaded and not
    differentiated (module docstring), else None."""
    if (shape is None or not shape.has_vertex_normals()
            or emitter_kinds(emitter.flags()) != {'area'}
            or mi.has_flag(emitter.flags(), mi.EmitterFlags.SpatiallyVarying)):
        return None
    params = mi.traverse(shape)
    if 'vertex_positions' in params.keys() and dr.grad_enabled(params['vertex_positions']):
        return None
    return shape


def _arrays(shape):
    """(positions (V, 3), normals (V, 3), faces (F, 3)) of a mesh, float64 and int64."""
    pos = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    nrm = np.array(shape.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
    faces = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    return pos, nrm, faces


def _is_smooth(pos, nrm, faces):
    """Whether some vertex normal differs from the normal of a face it belongs to."""
    n_face = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    n_face /= np.maximum(np.linalg.norm(n_face, axis=1, keepdims=True), 1e-300)
    n_vert = nrm[faces] / np.maximum(np.linalg.norm(nrm[faces], axis=2, keepdims=True), 1e-300)
    return bool(np.any(1.0 - np.einsum('fk,fjk->fj', n_face, n_vert) > SMOOTH_TOL))


class SmoothEmitters:
    """Tables of the smooth-shaded emitter meshes (module docstring), concatenated, one field a
    line; ``present`` False (and nothing else built) where the scene has none."""

    def __init__(self, scene, emitters, ids, size):
        self.present = False
        meshes = _emitter_meshes(scene)
        slot = [-1] * size                # per emitter id: the mesh's rank among these, or -1
        keys, tris, normals, signs = [], [], [], []
        for e, i in zip(emitters, ids):
            shape = _smooth_mesh(e, meshes.get(i))
            if shape is None:
                continue
            pos, nrm, faces = _arrays(shape)
            if not _is_smooth(pos, nrm, faces):
                continue
            area = 0.5 * np.linalg.norm(np.cross(pos[faces[:, 1]] - pos[faces[:, 0]],
                                                 pos[faces[:, 2]] - pos[faces[:, 0]]), axis=1)
            rank = len(signs)
            slot[i] = rank
            # the mesh's cumulative area share, offset by its rank: one increasing array for all
            keys.append(rank + np.cumsum(area) / max(area.sum(), 1e-300))
            keys[-1][-1] = rank + 1.0
            tris.append(pos[faces].reshape(-1, 9))
            normals.append(nrm[faces].reshape(-1, 9))
            signs.append(-1.0 if shape.has_flipped_normals() else 1.0)
        if not signs:
            return
        self.present = True
        self.slot = mi.Int32(slot)                            # emitter id -> rank, -1: not smooth
        self.sign = mi.Float(signs)                           # rank -> -1 where normals are flipped
        key = np.concatenate(keys)
        self.key = mi.Float64(key)                            # face -> rank + its cumulative share
        self.first = mi.UInt32(np.searchsorted(key, np.arange(len(signs)), side='right'))   # rank -> first face
        tri = np.concatenate(tris).T.astype(np.float32)
        self.corners = [mi.Point3f(tri[3 * k], tri[3 * k + 1], tri[3 * k + 2]) for k in range(3)]   # face -> p0, p1, p2
        nrm = np.concatenate(normals).T.astype(np.float32)
        self.vertex_normals = [mi.Vector3f(nrm[3 * k], nrm[3 * k + 1], nrm[3 * k + 2]) for k in range(3)]
        self.face_count = len(key)

    def rank(self, emitter, active=True):
        """Per lane: the rank of ``emitter`` among the smooth meshes, and whether it is one."""
        r = dr.gather(mi.Int32, self.slot, dr.reinterpret_array(mi.UInt32, emitter), active)
        return mi.UInt32(dr.maximum(r, 0)), active & (r >= 0)

    def sample(self, emitter, u, active):
        """A uniform point on the smooth mesh of ``emitter`` (lanes ``smooth``, returned):
        (smooth, point, triangle normal, shading normal, barycentric uv)."""
        rank, smooth = self.rank(emitter, active)
        target = mi.Float64(rank) + mi.Float64(dr.clip(u.y, 0.0, 1.0 - 2.0 ** -24))
        face = dr.binary_search(0, self.face_count - 1,
                                lambda i: dr.gather(mi.Float64, self.key, i, smooth) <= target)
        hi = dr.gather(mi.Float64, self.key, face, smooth)
        first = dr.gather(mi.UInt32, self.first, rank, smooth)
        lo = dr.select(face > first, dr.gather(mi.Float64, self.key, face - 1, smooth & (face > first)),
                       mi.Float64(rank))
        u_y = mi.Float(dr.clip((target - lo) / dr.maximum(hi - lo, 1e-300), 0.0, 1.0 - 2.0 ** -24))
        b = mi.warp.square_to_uniform_triangle(mi.Point2f(u.x, u_y))
        p0, p1, p2 = (dr.gather(mi.Point3f, c, face, smooth) for c in self.corners)
        e0, e1 = p1 - p0, p2 - p0
        p = dr.fma(e0, b.x, dr.fma(e1, b.y, p0))
        sign = dr.gather(mi.Float, self.sign, rank, smooth)
        n_geo = dr.normalize(dr.cross(e0, e1)) * sign
        n0, n1, n2 = (dr.gather(mi.Vector3f, c, face, smooth) for c in self.vertex_normals)
        n_sh = dr.normalize(dr.fma(n0, 1.0 - b.x - b.y, dr.fma(n1, b.x, n2 * b.y))) * sign
        return smooth, p, n_geo, n_sh, b


def emission_direction(n_geo, u):
    """A direction leaving a smooth-shaded emitter mesh at a point of triangle normal ``n_geo``:
    uniform with probability UNIFORM_SHARE, else cosine-distributed about ``n_geo`` (``u.x``
    chooses and is reused). Returns (direction, its density per unit solid angle)."""
    uniform = u.x < UNIFORM_SHARE
    u_x = dr.select(uniform, u.x / UNIFORM_SHARE, (u.x - UNIFORM_SHARE) / (1.0 - UNIFORM_SHARE))
    u2 = mi.Point2f(dr.clip(u_x, 0.0, 1.0 - 2.0 ** -24), u.y)
    d = dr.select(uniform, mi.warp.square_to_uniform_sphere(u2),
                  mi.Frame3f(n_geo).to_world(mi.warp.square_to_cosine_hemisphere(u2)))
    return d, emission_pdf_w(n_geo, d)


def emission_pdf_w(n_geo, d):
    """The density per unit solid angle of emission_direction choosing ``d``."""
    return ((1.0 - UNIFORM_SHARE) * dr.maximum(dr.dot(n_geo, d), 0.0) * (1.0 / dr.pi)
            + UNIFORM_SHARE * (0.25 / dr.pi))
