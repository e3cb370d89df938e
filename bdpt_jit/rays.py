"""Every ray that leaves a surface: its origin offset from the surface by a bound on the
floating-point error of the point it leaves, and, for shadow rays, a far end that stops the
same way short of the target. No other epsilon is used anywhere.

Why: Mitsuba's ``spawn_ray``/``spawn_ray_to`` offset by (1 + max|p|) * 8.9e-5 and shorten
shadow rays by 8.9e-4 of their length, whatever the size of the geometry: at a scale of 1e-3
that offset is 4% of a unit box (its image moved +1.6%), far from the origin it is large
against the geometry (+16% at 1e4). pbrt-v4 offsets by a bound of the intersection's error
along the normal (``OffsetRayOrigin``); Waechter and Binder ("A Fast and Robust Method for
Avoiding Self-Intersection", Ray Tracing Gems, 2019) in units in the last place of the
position. Here the bound follows the magnitude of the numbers the point was computed from:

    err = ERR_ULPS * 2^-24 * max(max_i |p_i|, M_shape)

M_shape the largest coordinate magnitude of the shape's bounding box (a triangle's hit point is
interpolated from its vertices, whose rounding it inherits; this also covers points near the
origin of a large shape). Measured on the Cornell box at scales 1e-4 to 1e5 and moved by 1e3
and 1e4: hit points lie within 3 * 2^-24 * max|p| of their plane; ERR_ULPS = 8 leaves a margin
for the offset's own rounding. The offset has a cost of its own (occluders closer than it are
missed): the box moved by 1e4 renders +0.04% with 4, +0.1% with 8, +0.25% with 16. The offset is err * |n|_1 along the geometric normal, to the side
the ray leaves on, so every component moves by at least err. Scale-free: at any scale and
placement the offset is the same fraction of float32's spacing there.

Triangle meshes far from the origin against their size (magnitude > PROJECT_RATIO x their
extent) get a tighter bound: Mitsuba interpolates a hit point from the three vertices
(about 3 units of 2^-24 max|p| off their plane, measured), and ``project_to_triangle`` moves it
back onto the plane of its triangle (p - n ((p - p0) . n): p - p0 and the dot product are
exact or small, one rounding remains): within 1.3 units of the plane on a mesh sphere at the
origin, moved by 1e3, 1e4 and 3e4. Their hit points' offset is MESH_ULPS = 3 units (the origin
then lies at least 2.3 units on its side of the plane, over 400k rays each), which matters because an
offset has a cost of its own proportional to it: a concave surface (a closed sphere seen from
inside) has a cap around each vertex that no ray from the offset origin reaches (n . (y - p) <
offset): -0.2% with 8 units on a unit sphere moved by 1e4, about -0.1% with 3. Points that
Mitsuba samples on a mesh (emitter sampling) are not projected and keep the general bound.

Cylinders: Mitsuba 3.9 takes a cylinder's hit point as o + t d with t from a quadratic solved in
single precision, and does not move it back onto the surface; its error grows with the square of
the distance the ray travelled (measured on a cylinder of radius 1.5: 1.5e-6 from 3 units away,
5.4e-5 from 24, 3.5e-3 from 200), far beyond the bound above, so that rays leaving such a point
hit the cylinder again (a camera 24 units away saw half of a diffuse cylinder's light: the
rays into half of each hemisphere started under the surface). ``project_to_surface`` moves
such hits back onto the cylinder, as pbrt refines its quadrics' hits (its object space: unit
radius about z; scaled to radius 1 there and mapped back), after which the general bound holds."""

import drjit as dr
import mitsuba as mi
import numpy as np

ERR_ULPS = 8
ERR_REL = ERR_ULPS * 2.0 ** -24
MESH_ULPS = 3            # triangle meshes of the scene's list, hit points projected (above)
MESH_REL = MESH_ULPS * 2.0 ** -24
# A mesh is projected only where its magnitude is large against its own size: the projection
# costs ~10% of a render (two virtual calls and gathers a hit: SmallVCM box 0.91 vs 1.03 M
# samples/s), and near the origin the general bound is already tiny against the geometry
# (at this ratio the offset is 8 * 2^-24 * 16 = 8e-6 of the mesh's size).
PROJECT_RATIO = 16.0
# Far end of a shadow ray, relative to its length, in scenes with shapes that Mitsuba intersects
# by solving a quadratic in single precision (spheres, cylinders, curves): their hit distance is
# far less accurate than their hit point. Measured: shadow rays towards a sphere light (r 0.07
# at distance 2.5) test as blocked by the light itself on 19% of the lanes when they stop
# 1e-6 short, 0.6% at 1e-5 relative, 0.2% at 1e-4, none from 3e-4 (Mitsuba stops 8.9e-4 short).
QUADRIC_REL = 2.0 ** -11
QUADRIC_SHAPES = ('Sphere', 'Cylinder', 'BSplineCurve', 'LinearCurve', 'SDFGrid', 'Ellipsoids')
# Hit points of SDF grids (a cubic solved per voxel) lie further off their surface than the
# general bound allows: an instanced grid 24 units from the camera (Mitsuba's test scene
# various_shapes) rendered 3% dark with it, right with 4 times it (and with 100 times). A hit
# inside an instance is on a shape of unknown kind: it takes it too.
COARSE_REL = 4 * ERR_REL
CULLED_SHAPES = ('BSplineCurve', 'LinearCurve')
COARSE_SHAPES = ('SDFGrid',)


def shape_bbox(shape):
    """The shape's bounding box. Mitsuba 3.9.1 merges shapes that share a BSDF and have no id
    into one mesh, and where it merges ``rectangle`` shapes the mesh's box is left invalid (and
    so the scene's, or the scene's lacks them): such a mesh's box is found from its vertices."""
    bb = shape.bbox()
    if bb.valid() or not shape.is_mesh() or shape.vertex_count() == 0:
        return bb
    v = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    v = v[np.isfinite(v).all(axis=1)]
    if len(v) == 0:
        return bb
    return mi.ScalarBoundingBox3f(mi.ScalarPoint3f(v.min(axis=0)), mi.ScalarPoint3f(v.max(axis=0)))


def scene_bbox(scene):
    """The scene's bounding box from its shapes' (``shape_bbox``), not ``scene.bbox()``, which a
    merged mesh leaves invalid or too small. Invalid only for a scene without geometry."""
    out = mi.ScalarBoundingBox3f()
    for shape in scene.shapes():
        b = shape_bbox(shape)
        if b.valid():
            out.expand(b)
    return out


class RayOffsets:
    """The per-shape magnitudes of a scene and the functions that spawn rays with them."""

    def __init__(self, scene: mi.Scene):
        mags, meshes = {}, set()
        for shape in scene.shapes():
            bb = shape_bbox(shape)
            m = max(float(np.max(np.abs(np.array(bb.min)))), float(np.max(np.abs(np.array(bb.max)))))
            idx = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])
            mags[idx] = m if np.isfinite(m) else 0.0
            extent = float(np.max(np.array(bb.max) - np.array(bb.min)))
            if shape.is_mesh() and np.isfinite(m) and m > PROJECT_RATIO * extent:
                meshes.add(idx)
        self.size = max(list(mags) + [0]) + 1
        table = np.zeros(self.size, np.float32)
        rel = np.full(self.size, ERR_REL, np.float32)
        for i, m in mags.items():
            table[i] = m
        for i in meshes:
            rel[i] = MESH_REL
        coarse = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0]) for sh in scene.shapes()
                  if str(sh.class_name()) in COARSE_SHAPES}
        if any(str(sh.class_name()) == 'Instance' for sh in scene.shapes()):
            coarse |= set(range(1, self.size)) - set(mags)      # the shapes inside instances (their own ids)
        for i in coarse:
            rel[i] = COARSE_REL
        self.per_shape = bool(meshes or coarse)         # else every hit takes ERR_REL
        self.coarse = bool(coarse)               # SDF grids or shapes in instances: their hits are inexact
        self.table = mi.Float(table)
        self.rel = mi.Float(rel)
        self.any_mesh = bool(meshes)             # any mesh projected: else the kernels leave it out
        self.cylinders = self._cylinder_tables(scene)     # any cylinder: else the kernels leave it out
        every = all_shapes(scene)       # (those inside instances too)
        quadric = any(str(s.class_name()) in QUADRIC_SHAPES for s in every)
        self.far_rel = QUADRIC_REL if quadric else ERR_REL
        self.curve_ends = self._curve_end_table(every)    # any B-spline curve: else left out
        # Mitsuba culls the faces of curves that rays meet from inside: visibility between two
        # points then depends on the direction it is traced in (light_path.t1_shadow_ray)
        self.one_sided = any(str(s.class_name()) in CULLED_SHAPES for s in every)

    def _cylinder_tables(self, scene):
        """Per shape index, the rows of the to_object and to_world matrices of the scene's
        cylinders (``project_to_surface``); False where there are none."""
        cyl = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0]): _matrix(mi.traverse(sh)['to_world'])
               for sh in scene.shapes() if str(sh.class_name()) == 'Cylinder'}
        if not cyl:
            return False
        fwd, inv = np.zeros((3, 4, self.size), np.float32), np.zeros((3, 4, self.size), np.float32)
        flag = np.zeros(self.size, np.uint32)
        for i, m in cyl.items():
            fwd[:, :, i], inv[:, :, i], flag[i] = m[:3], np.linalg.inv(m)[:3], 1
        self.cyl_flag = mi.UInt32(flag)
        self.cyl_fwd = [mi.Vector4f(*row) for row in fwd]
        self.cyl_inv = [mi.Vector4f(*row) for row in inv]
        return True

    def _curve_end_table(self, shapes):
        """Per shape index, the largest segment parameter that the last segment of a
        ``bsplinecurve`` among ``shapes`` may hold (``clamp_curve_ends``); 0 elsewhere. False
        without such curves."""
        ends = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0]): _last_segment_end(sh.primitive_count())
                for sh in shapes if str(sh.class_name()) == 'BSplineCurve'}
        if not ends:
            return False
        self.curve_size = max(ends) + 1        # (curves inside instances may lie past self.size)
        table = np.zeros(self.curve_size, np.float32)
        last = np.zeros(self.curve_size, np.uint32)
        for i, (v_max, n) in ends.items():
            table[i], last[i] = v_max, n - 1
        self.curve_v_max, self.curve_last = mi.Float(table), mi.UInt32(last)
        return True

    def clamp_curve_ends(self, pi, active):
        """``pi`` with the segment parameter of hits at the far end of a ``bsplinecurve``'s
        last segment kept below the value whose global parameter (v + N - 1) / N rounds to 1:
        Mitsuba 3.9.1 then floors v N to N unclipped (bsplinecurve.cpp ``partials``), reads its
        segment table one past the end and control points at whatever that holds (a segfault
        at random: one render in ten of 60 strands at 48 x 48, 256 spp; Mitsuba's own ``path``
        reads there too). The hit point is o + t d, unchanged; its frame moves by less than
        the float spacing of the curve's parameter. In place."""
        if not self.curve_ends:
            return pi
        idx = dr.reinterpret_array(mi.UInt32, pi.shape)
        known = (idx < self.curve_size) & (idx > 0)
        at_end = active & pi.is_valid() & known & (pi.prim_index == dr.gather(mi.UInt32, self.curve_last, idx, known))
        v_max = dr.gather(mi.Float, self.curve_v_max, idx, at_end)
        pi.prim_uv = mi.Point2f(dr.select(at_end & (v_max > 0), dr.minimum(pi.prim_uv.x, v_max), pi.prim_uv.x),
                                pi.prim_uv.y)
        return pi

    def intersect(self, scene, ray, active, flags=None):
        """scene.ray_intersect (with ``flags``: Mitsuba's (ray, flags, coherent, active) form),
        its hits at the end of a B-spline curve clamped first (``clamp_curve_ends``)."""
        if not self.curve_ends:
            if flags is None:
                return scene.ray_intersect(ray, active)
            return scene.ray_intersect(ray, flags, False, active)
        pi = self.clamp_curve_ends(scene.ray_intersect_preliminary(ray, False, active), active)
        return pi.compute_surface_interaction(ray, mi.RayFlags.All if flags is None else flags, active)

    def _known(self, shape):
        idx = dr.reinterpret_array(mi.UInt32, shape)
        return idx, (idx < self.size) & (idx > 0)

    def shape_magnitude(self, shape):
        """M_shape of a ShapePtr (0 for a shape not in the scene's list, e.g. inside an
        instance: the position's own magnitude then bounds the error)."""
        idx, known = self._known(shape)
        return dr.gather(mi.Float, self.table, idx, known)

    def error(self, p, shape=None, hit=True):
        """The bound ``err`` of a point ``p`` on ``shape`` (None: a point not on a surface
        interpolated from a shape: its own magnitude). ``hit``: a ray's hit point, projected onto
        its triangle on the meshes that project (sampling.Sampling.intersect); False: a position Mitsuba
        sampled on the shape (emitter sampling), which keeps the general bound (on the sphere mesh
        moved by 1e4 such points lie up to 2.2 units off their triangle's plane)."""
        m = dr.max(dr.abs(p))
        if shape is None:
            return ERR_REL * m
        m = dr.maximum(m, self.shape_magnitude(shape))
        if not self.per_shape or not hit:
            return ERR_REL * m
        idx, known = self._known(shape)
        rel = dr.select(known, dr.gather(mi.Float, self.rel, idx, known), COARSE_REL)
        return rel * m

    def project_to_surface(self, si, active):
        """``si.p`` of a hit moved onto its surface where Mitsuba's is inexact: a triangle
        mesh's far from the origin (``project_to_triangle``), a cylinder's (module docstring).
        In place."""
        si = self.project_to_triangle(si, active)
        if not self.cylinders:
            return si
        idx, known = self._known(si.shape)
        cyl = active & si.is_valid() & known & (dr.gather(mi.UInt32, self.cyl_flag, idx, known) != 0)
        p = dr.detach(si.p)
        rows = [dr.gather(mi.Vector4f, t, idx, cyl) for t in self.cyl_inv]
        local = [dr.fma(r.x, p.x, dr.fma(r.y, p.y, dr.fma(r.z, p.z, r.w))) for r in rows]
        scale = dr.rsqrt(dr.maximum(dr.fma(local[0], local[0], local[1] * local[1]), 1e-30))
        local = [local[0] * scale, local[1] * scale, local[2]]
        rows = [dr.gather(mi.Vector4f, t, idx, cyl) for t in self.cyl_fwd]
        q = mi.Point3f(*[dr.fma(r.x, local[0], dr.fma(r.y, local[1], dr.fma(r.z, local[2], r.w))) for r in rows])
        si.p = dr.select(cyl, si.p + (q - p), si.p)
        return si

    def project_to_triangle(self, si, active):
        """``si.p`` of a hit on a triangle mesh of the scene's list moved onto the plane of its
        triangle (the bound MESH_REL assumes it; module docstring). In place; the correction
        carries no derivative (in a differentiable pass p keeps those of the traced hit)."""
        if not self.any_mesh:
            return si
        idx, known = self._known(si.shape)
        mesh = active & si.is_valid() & known & (dr.gather(mi.Float, self.rel, idx, known) == MESH_REL)
        meshp = mi.MeshPtr(si.shape)
        fi = meshp.face_indices(si.prim_index, mesh)
        p0 = dr.detach(meshp.vertex_position(fi.x, mesh))   # (a differentiated mesh: its positions track)
        n = dr.detach(si.n)
        h = dr.dot(dr.detach(si.p) - p0, n)
        si.p = dr.select(mesh, si.p - n * h, si.p)
        return si


def _matrix(transform):
    """A (width-1) Transform4f's matrix as a 4 x 4 float64 array."""
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def offset_origin(p, n, err, d):
    """``p`` moved off its surface (geometric normal ``n``, error bound ``err``) to the side of
    the direction ``d``: by err * |n|_1 along n, so each coordinate moves by at least err."""
    dist = err * (dr.abs(n.x) + dr.abs(n.y) + dr.abs(n.z))
    return dr.fma(mi.Vector3f(n), dr.mulsign(dist, dr.dot(n, d)), p)


def no_wavelengths():
    """The wavelengths of a ray in RGB and monochrome variants (none); spectral variants pass
    a sample's own."""
    return dr.zeros(mi.Color0f) if not mi.is_spectral else dr.zeros(mi.Spectrum)


def spawn(p, n, err, d, time, wavelengths=None):
    """An extension ray from the surface point ``p`` in the unit direction ``d``, carrying the
    path's ``wavelengths`` (spectral variants)."""
    wl = wavelengths if wavelengths is not None else no_wavelengths()
    return mi.Ray3f(offset_origin(p, n, err, d), d, dr.largest(mi.Float), time, wl)


def spawn_to(start, end, time, far_rel=ERR_REL, wavelengths=None):
    """A shadow ray from the surface point ``start`` = (p, n, err: position, geometric normal,
    error bound) to the point ``end`` = (q, n_q, err_q): both ends moved off their surfaces
    towards each other (``n_q`` zero and ``err_q`` 0 for a point on no surface: a pinhole, a
    point light), and the far end shortened by ``far_rel`` of the length (RayOffsets.far_rel:
    ERR_REL bounds the rounding of o + t d; QUADRIC_REL where the scene's quadric shapes make
    the hit distance itself inexact)."""
    (p, n, err), (q, n_q, err_q) = start, end
    to_q = q - p
    o = offset_origin(p, n, err, to_q)
    q_off = offset_origin(q, n_q, err_q, -to_q)
    d = q_off - o
    dist = dr.norm(d)
    d = d * dr.rcp(dr.select(dist > 0, dist, 1.0))
    wl = wavelengths if wavelengths is not None else no_wavelengths()
    return mi.Ray3f(o, d, dist * (1.0 - far_rel), time, wl)


def spawn_to_emitter(start, ds, err_q, time, far_rel=ERR_REL, wavelengths=None, infinite=False):
    """Shadow ray from ``start`` = (p, n, err), as spawn_to's, to an emitter sample ``ds``
    (DirectionSample3f): ``spawn_to`` its point, or an unbounded ray in its direction where the
    sample is at infinity (``infinite``: the lanes of environment and directional emitters, or
    ``ds.dist`` infinite). Mitsuba's infinite emitters
    put their samples at twice the radius of the scene's bounding sphere, which an invalid box
    (merged rectangles: scene_bbox) makes 2e-4 from the vertex: the ray then passed every wall."""
    p, n, err = start
    to = spawn_to(start, (ds.p, ds.n, err_q), time, far_rel, wavelengths)
    inf = ~dr.isfinite(ds.dist) | infinite
    o_inf = offset_origin(p, n, err, ds.d)
    return mi.Ray3f(dr.select(inf, o_inf, to.o), dr.select(inf, ds.d, to.d),
                    dr.select(inf, dr.largest(mi.Float), to.maxt), time, to.wavelengths)


def all_shapes(scene):
    """scene.shapes() and, in a scene with instances, the shapes inside its shape groups, which
    scene.shapes() does not list (found by mi.traverse: the objects its parameters belong to)."""
    shapes = list(scene.shapes())
    if not any(str(s.class_name()) == 'Instance' for s in shapes):
        return shapes
    seen = {int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes}
    params = mi.traverse(scene)
    for key in params.keys():
        node = params.properties[key][2]
        if isinstance(node, mi.Shape):
            i = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(node))[0])
            if i not in seen:
                seen.add(i)
                shapes.append(node)
    return shapes


def _last_segment_end(n):
    """(a float32 v in [0, 1], within two float spacings of n below 1, for which Mitsuba's
    B-spline computations keep the last of ``n`` segments: floor(((v + (n - 1)) / n) * n) =
    n - 1 in float32 (0 past n = 2^24), and n)."""
    f = np.float32
    v = min(f(1.0), f(np.nextafter(f(n), f(0.0)) - f(n - 1)))     # v + n - 1 below n
    while v > 0 and np.floor(f(f(f(v + f(n - 1)) / f(n)) * f(n))) >= n:
        v = np.nextafter(v, f(0.0))
    return max(float(v), 0.0), int(n)
