"""Light subpath endpoints: where light subpaths start (every emitter kind bdpt renders), how
emitters are sampled from a camera vertex (s=1) and every emission density the MIS needs. Every
rule that depends on the emitter kind is here; the camera's side is cameras.py. Mitsuba does not expose the
emission densities (``Emitter.pdf_position`` raises, and no emitter gives the pdf of the
direction ``sample_ray`` chooses), so they are computed here, per emitter kind, in one place:

| kind (flags) | position density | direction density |
|---|---|---|
| area (Surface) | Mitsuba's ``sample_position``: uniform by area, or by the radiance texture (bitmap, checkerboard: SpatiallyVarying) | cos / pi about the normal |
| directionalarea (Surface, DeltaDirection) | its shape's ``sample_position`` (uniform by area, textured or not) | discrete (1): along the normal |
| point, spot, projector (DeltaPosition) | discrete (1) | uniform sphere; uniform cone within the spot's cutoff, or around the projector's frustum |
| directional (DeltaDirection, Infinite) | 1 / (pi R^2) on a disk facing the light | discrete (1) |
| constant, envmap, sunsky (Infinite) | 1 / (pi R^2) on a disk facing the direction | the emitter's ``pdf_direction`` |

R is the radius of the scene's bounding sphere (slightly enlarged). For infinite emitters the
'vertex' y0 is a direction, so its densities are per unit solid angle and the first edge has
no distance factor; delta emitters cannot be hit (no s=0) nor sampled by BSDF sampling.
A directionalarea emitter (a surface emitting only along its normal) is delta too: no camera
ray can hit it and emitter sampling cannot reach it (Mitsuba's ``sample_direction`` for it returns
nothing), so only the strategies with s >= 2 render its light (connections and splats).
All selection probabilities are Mitsuba's own (``scene.sample_emitter``, proportional to each
emitter's ``sampling_weight``)."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .jitmath import INV_PI, neg, pdf_w_to_a, safe_div, sel
from .rays import RayOffsets, no_wavelengths, offset_origin, scene_bbox

from .direct import SMALL_SPHERE, DirectSampling  # noqa: F401  (SMALL_SPHERE: re-exported)
from .smooth_emitters import SmoothEmitters, emission_direction, emission_pdf_w
from .emitter_tables import (emitter_kinds, inverse_areas, projector_cone, remapped_textures,  # noqa: F401
                             sphere_placements, sphere_positions, sphere_radiance, sphere_shapes, sphere_table,
                             spot_cones)     # (projector_cone: re-exported)


def _or(a, b):
    """Mask union that keeps Python constants (a kind absent from the scene is False)."""
    if a is False:
        return b
    if b is False:
        return a
    if a is True or b is True:
        return True
    return a | b


class Kinds:
    """Per-lane emitter kind masks. Kinds the scene does not have are the Python constant
    False, so code for them is not traced.

    area       a surface emitting diffusely (Surface, not DeltaDirection)
    dir_area   a surface emitting along its normal only (directionalarea)
    delta_pos  point, spot, projector
    delta_dir  a direction at infinity (directional)
    infinite   at infinity (directional, constant, envmap, sunsky); env: infinite, not delta
    delta      no camera ray can hit it (delta_pos, delta_dir, dir_area)"""

    def __init__(self, table, emitter):
        flags = emitter.flags() if table.mixed else None
        F = mi.EmitterFlags

        def has(kind, test):
            if not getattr(table, 'has_' + kind):
                return False
            if not table.mixed:
                return True
            return test()
        surface = lambda: mi.has_flag(flags, F.Surface)              # noqa: E731
        ddir = lambda: mi.has_flag(flags, F.DeltaDirection)          # noqa: E731
        self.area = has('area', lambda: surface() & ~ddir())
        self.dir_area = has('dir_area', lambda: surface() & ddir())
        self.delta_pos = has('delta_pos', lambda: mi.has_flag(flags, F.DeltaPosition))
        self.delta_dir = has('delta_dir', lambda: ddir() & ~surface())
        self.infinite = has('infinite', lambda: mi.has_flag(flags, F.Infinite))   # directional included
        self.env = self.infinite if self.delta_dir is False else (
            False if self.delta_dir is True else self.infinite & ~self.delta_dir)
        self.delta = _or(_or(self.delta_pos, self.delta_dir), self.dir_area)
        self.surface = _or(self.area, self.dir_area)     # on a shape: rays leave with an offset


class AreaKinds:
    """Kinds of an emitter that a camera ray hit: always an area emitter."""
    area, delta_pos, delta_dir, infinite, env, delta = True, False, False, False, False, False
    dir_area, surface = False, True


ENV_DEFENSIVE = 0.1     # EmitterTable.env_defensive: the share of uniform directions from environments


class EmitterTable(DirectSampling):
    """Emitter choice and the emission densities of every emitter kind."""

    def __init__(self, scene: mi.Scene, offsets: RayOffsets = None, env_defensive=False):
        self.scene = scene
        # light subpaths leave environment emitters in uniform directions too (_env_direction)
        self.env_defensive = env_defensive
        self.offsets = offsets if offsets is not None else RayOffsets(scene)
        emitters = scene.emitters()
        weights = [float(e.sampling_weight()) for e in emitters]
        self.total_weight = sum(weights) or 1.0
        self.count = len(emitters)
        kinds = set()
        for e in emitters:
            kinds |= emitter_kinds(e.flags())
        self.has_area = 'area' in kinds
        self.has_dir_area = 'dir_area' in kinds
        self.has_delta_pos = 'delta_pos' in kinds
        self.has_delta_dir = 'delta_dir' in kinds
        self.has_infinite = 'infinite' in kinds
        self.mixed = len(kinds) > 1
        # area emitters whose radiance is a texture: Mitsuba samples their positions by the texture
        self.has_textured_area = any('area' in emitter_kinds(e.flags()) and
                                     mi.has_flag(e.flags(), mi.EmitterFlags.SpatiallyVarying) for e in emitters)
        # the disk of infinite emitters: covers the scene's bounding sphere
        bs = scene_bbox(scene).bounding_sphere()
        r = float(bs.radius) if math.isfinite(float(bs.radius)) and float(bs.radius) > 0 else 1.0
        self.center = mi.Point3f(bs.center)
        self.radius = r * 1.01 + 1e-4
        self.pdf_disk = 1.0 / (math.pi * self.radius ** 2)
        # per-emitter tables, indexed by the emitter's registry id (emitter_tables.py)
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0]) for e in emitters]
        size = max(ids + [0]) + 1
        self.cone_cos, self.cone_axis = spot_cones(emitters, ids, size)
        spheres = sphere_shapes(emitters, ids)
        self.sph_r, self.sph_c = sphere_table(emitters, ids, size, spheres)
        self.has_sphere = bool(np.any(np.array(self.sph_r) > 0))
        # every emitter a sphere of constant radiance (direct.py): its cone sampled here from any
        # point outside it, its radiance read from this table
        self.sph_le = sphere_radiance(emitters, ids, size) if self.has_sphere else None
        self.all_spheres = self.sph_le is not None
        self.inv_area = inverse_areas(emitters, ids, size)
        self.sphere_placements = sphere_placements(spheres, size)
        self.uniform_starts = remapped_textures(emitters, ids, size) if self.has_textured_area else None
        smooth = SmoothEmitters(scene, emitters, ids, size) if self.has_area else None
        self.smooth = smooth if smooth is not None and smooth.present else None     # (smooth_emitters.py)

    def kinds(self, emitter):
        return Kinds(self, emitter)

    def sample_position(self, emitter, time, u, active):
        """The emitter's ``sample_position``, on spheres the point on the sphere rays hit
        (sphere_positions); uniform over the shape where its texture's sampling ignores a
        ``to_uv`` (remapped_textures); on smooth-shaded meshes bdpt's own, its normal the
        triangle's (smooth_emitters.py). Returns (ps, weight, shading normal)."""
        mitsubas = active        # the lanes Mitsuba's sample_position serves (not replaced below)
        if self.uniform_starts is not None:
            uniform = active & self._uniform_start(emitter)
            mitsubas = mitsubas & ~uniform
        if self.smooth is not None:
            smooth = self.smooth.rank(emitter, active)[1]
            mitsubas = mitsubas & ~smooth
        ps, w = emitter.sample_position(time, u, mitsubas)
        if self.uniform_starts is not None:
            ps = dr.select(uniform, emitter.get_shape().sample_position(time, u, uniform), ps)
        ps = sphere_positions(ps, dr.reinterpret_array(mi.UInt32, emitter), self.sphere_placements, active)
        n_sh = mi.Vector3f(ps.n)
        if self.smooth is not None:
            _, p, n_geo, n_sh_smooth, b = self.smooth.sample(emitter, u, smooth)
            ps.p, ps.n, ps.uv = dr.select(smooth, p, ps.p), dr.select(smooth, n_geo, ps.n), dr.select(smooth, b, ps.uv)
            ps.pdf = dr.select(smooth, self.uniform_pdf_a(emitter), ps.pdf)
            ps.time = dr.select(smooth, time, ps.time)
            n_sh = dr.select(smooth, n_sh_smooth, n_sh)
        return ps, w, n_sh

    def _uniform_start(self, emitter):
        """Whether light subpaths start uniformly over ``emitter``'s shape (remapped_textures)."""
        return dr.gather(mi.Bool, self.uniform_starts, dr.reinterpret_array(mi.UInt32, emitter))

    def pdf_select(self, emitter):
        """Probability of choosing ``emitter`` (an EmitterPtr)."""
        return emitter.sampling_weight() / self.total_weight

    def uniform_pdf_a(self, emitter):
        """1 / the area of the emitter's shape (0 for emitters without one): the density of
        Mitsuba's shape ``sample_position``, uniform by area for every shape."""
        return dr.gather(mi.Float, self.inv_area, dr.reinterpret_array(mi.UInt32, emitter))

    def pdf_pos_a(self, emitter, ps):
        """Area emitters: density per unit area of the emission position ``ps`` (a
        PositionSample3f or DirectionSample3f on the emitter, uv set) as Mitsuba's
        ``sample_position`` samples it: uniform over the shape, or, for a textured radiance, the
        texture's ``pdf_position(uv)`` over |dp/du x dp/dv|. Mitsuba exposes that density only
        inside the area light's ``pdf_direction``: seen from the point one unit along the
        normal it is exactly the density per unit area."""
        uniform = self.uniform_pdf_a(emitter)
        if not self.has_textured_area:
            return uniform
        flags = emitter.flags()
        F = mi.EmitterFlags
        textured = (mi.has_flag(flags, F.Surface) & mi.has_flag(flags, F.SpatiallyVarying)
                    & ~mi.has_flag(flags, F.DeltaDirection))
        if self.uniform_starts is not None:
            textured &= ~self._uniform_start(emitter)
        n = dr.normalize(mi.Vector3f(ps.n))
        it = dr.zeros(mi.Interaction3f, dr.width(n))
        it.p, it.time = ps.p + n, ps.time
        ds = dr.zeros(mi.DirectionSample3f, dr.width(n))
        ds.p, ds.n, ds.uv, ds.time = ps.p, n, ps.uv, ps.time
        ds.d, ds.dist, ds.emitter = -n, mi.Float(1.0), emitter
        return dr.select(textured, emitter.pdf_direction(it, ds, textured), uniform)

    @staticmethod
    def pdf_dir_w(cos_e):
        """Area emitters: cosine-weighted about the (shading) normal, as Mitsuba samples it."""
        return dr.abs(cos_e) * INV_PI

    def cone(self, emitter):
        idx = dr.reinterpret_array(mi.UInt32, emitter)
        return dr.gather(mi.Float, self.cone_cos, idx), dr.gather(mi.Vector3f, self.cone_axis, idx)

    def cone_pdf_w(self, emitter, d_out):
        """Point and spot lights: density of the emitted direction ``d_out``."""
        cos_cut, axis = self.cone(emitter)
        inside = dr.dot(axis, d_out) >= cos_cut
        return dr.select(inside, mi.warp.square_to_uniform_cone_pdf(mi.Vector3f(0, 0, 1), cos_cut), 0.0)

    # ------------------------------------------------------------------ light subpath start
    def sample_emission(self, time, u_sel, u_pos, u_dir, active, wavelengths=None):
        """Start a light subpath: choose an emitter, a position and a direction. Returns an
        Emission with the ray, the throughput after emission and the densities. ``wavelengths``:
        the sample's (spectral variants: the camera subpath's, integrator.BDPTIntegrator.pass_state)."""
        wl = wavelengths if wavelengths is not None else no_wavelengths()
        idx, _, _ = self.scene.sample_emitter(u_sel, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), idx, active)
        k = self.kinds(emitter)
        e = Emission()
        e.emitter, e.kinds = emitter, k
        p_sel = self.pdf_select(emitter)
        e.p_sel = p_sel
        finite = neg(k.infinite)
        # ---- position (area, point, spot)
        ps, _, n_sh = self.sample_position(emitter, time, u_pos, active & finite)
        e.ps = ps
        si_e = mi.SurfaceInteraction3f(ps, wl)
        if self.smooth is not None:     # emission reads the side of the shading normal
            si_e.sh_frame = mi.Frame3f(n_sh)
        e.si_e = si_e
        st = EmissionStart(ps, si_e, wl)               # what each emitter kind's block below overwrites
        for kind, start in ((k.area, self._start_area), (k.dir_area, self._start_dir_area),
                            (k.delta_pos, self._start_delta_pos), (k.infinite, self._start_infinite)):
            if kind is not False:
                start(emitter, kind, st, time, u_pos, u_dir, active)
        e.d, e.origin, e.n_e, e.cos_e = st.d, st.origin, st.n_e, st.cos_e
        e.pdf_emit_w = p_sel * st.p_pos * st.p_dir
        e.pdf_light_a = p_sel * st.p_pos                     # y0's density (s=1, t=1)
        e.beta = mi.Spectrum(st.value * safe_div(1.0, e.pdf_emit_w))
        e.active = active & (e.pdf_emit_w > 0) & (dr.max(st.value) > 0)
        # y0 itself (the strategy s=1, t=1), whatever its emitted direction carries: on a
        # smooth-shaded mesh a direction about the triangle's normal may leave on the shading
        # normal's dark side (smooth_emitters.py), and y0 is seen by the camera all the same
        e.active_y0 = active & (e.pdf_light_a > 0)
        # area emitters: the ray leaves a surface; points and infinite emitters' disks: no offset
        e.err = sel(k.surface, self.offsets.error(ps.p, emitter.get_shape(), hit=False), mi.Float(0.0)) \
            if k.surface is not False else mi.Float(0.0)
        n_off = sel(k.surface, mi.Normal3f(ps.n), mi.Normal3f(0.0)) if k.surface is not False else mi.Normal3f(0.0)
        e.ray = mi.Ray3f(offset_origin(st.origin, n_off, e.err, st.d), st.d, dr.largest(mi.Float), time, wl)
        return e

    # Each of the four blocks below overwrites, in the lanes of its emitter kind (`kind`), the fields
    # of an EmissionStart: the emitted value, the position and direction densities, the direction,
    # the ray's origin, the cosine at the emitter and the emitter's normal.

    def _start_area(self, emitter, kind, st, time, u_pos, u_dir, active):
        """Area emitters: cosine-weighted direction around the sampled point's normal."""
        ps, si_e = st.ps, st.si_e
        local = mi.warp.square_to_cosine_hemisphere(u_dir)
        if self.smooth is None:
            si_e.wi = local                                  # area emitters read si.wi (and si.uv)
            d_area, p_dir, cos_e = si_e.to_world(local), self.pdf_dir_w(local.z), local.z
        else:           # smooth-shaded meshes: smooth_emitters.emission_direction about the triangle's
            smooth = self.smooth.rank(emitter, active & kind)[1]        # normal ps.n
            d_s, p_s = emission_direction(ps.n, u_dir)
            d_area = dr.select(smooth, d_s, mi.Frame3f(ps.n).to_world(local))
            p_dir = dr.select(smooth, p_s, self.pdf_dir_w(local.z))
            cos_e = dr.abs(dr.dot(ps.n, d_area))
            si_e.wi = si_e.to_local(d_area)                  # the radiance by the shading frame
        le = emitter.eval(si_e, active & kind)
        st.value = sel(kind, le * cos_e, st.value)
        st.p_pos = sel(kind, ps.pdf, st.p_pos)               # by area, or by the radiance texture
        st.p_dir = sel(kind, p_dir, st.p_dir)
        st.d = sel(kind, d_area, st.d)
        st.cos_e = sel(kind, dr.abs(dr.dot(ps.n, d_area)), st.cos_e)

    def _start_dir_area(self, emitter, kind, st, time, u_pos, u_dir, active):
        """directionalarea: along the normal only (Mitsuba's sample_ray); the radiance at the point is
        what its sample_wavelengths returns (its eval is 0: no direction given can be the normal)."""
        ps = st.ps
        _, le_n = emitter.sample_wavelengths(st.si_e, mi.Float(0.5), active & kind)
        st.value = sel(kind, le_n, st.value)
        st.p_pos = sel(kind, ps.pdf, st.p_pos)
        st.p_dir = sel(kind, mi.Float(1.0), st.p_dir)
        st.d = sel(kind, mi.Vector3f(ps.n), st.d)

    def _start_delta_pos(self, emitter, kind, st, time, u_pos, u_dir, active):
        """Point and spot lights: a direction uniform in the emitter's cone."""
        cos_cut, axis = self.cone(emitter)
        d_cone = mi.Frame3f(axis).to_world(mi.warp.square_to_uniform_cone(u_dir, cos_cut))
        it = dr.zeros(mi.Interaction3f)
        it.p = st.ps.p + d_cone                              # at distance 1: weight = intensity
        it.time, it.wavelengths = time, st.wl
        _, intensity = emitter.sample_direction(it, u_dir, active & kind)
        st.value = sel(kind, intensity, st.value)
        st.p_dir = sel(kind, mi.warp.square_to_uniform_cone_pdf(mi.Vector3f(0, 0, 1), cos_cut), st.p_dir)
        st.d = sel(kind, d_cone, st.d)
        st.n_e = sel(kind, d_cone, st.n_e)

    def _start_infinite(self, emitter, kind, st, time, u_pos, u_dir, active):
        """Infinite emitters: a direction from the emitter (_env_direction where env_defensive),
        an origin on the disk of the scene's bounding sphere facing it."""
        it = dr.zeros(mi.Interaction3f)
        it.p = self.center
        it.time, it.wavelengths = time, st.wl
        if self.env_defensive:
            to_light, value, p_dir = self._env_direction(emitter, kind, it, u_dir, active)
        else:
            ds_inf, w_inf = emitter.sample_direction(it, u_dir, active & kind)
            to_light, value, p_dir = ds_inf.d, w_inf * ds_inf.pdf, ds_inf.pdf   # (to_light: towards the emitter)
        disk = mi.warp.square_to_uniform_disk_concentric(u_pos) * self.radius
        o_inf = self.center + to_light * self.radius + mi.Frame3f(to_light).to_world(mi.Vector3f(disk.x, disk.y, 0))
        st.value = sel(kind, value, st.value)              # radiance (irradiance if delta)
        st.p_pos = sel(kind, mi.Float(self.pdf_disk), st.p_pos)
        st.p_dir = sel(kind, p_dir, st.p_dir)              # 1 for directional
        st.d = sel(kind, -to_light, st.d)
        st.origin = sel(kind, o_inf, st.origin)
        st.n_e = sel(kind, -to_light, st.n_e)

    def _env_direction(self, emitter, kind, it, u_dir, active):
        """The direction towards an infinite emitter where light subpaths alone render what they
        carry (techniques lt and vm: no MIS weight reads their densities): environment emitters
        give a uniform direction with probability ENV_DEFENSIVE, else one of their own, the
        mixture's density the direction density. Mitsuba's `envmap` with `mis_compensation`
        samples no direction darker than its mean: lt was 6.3% dark on a plane under one
        (ptracer 6.1%), vm 6.9%. Directional emitters (a delta direction) are sampled as they
        are. Returns (direction, emitted value, direction density)."""
        env = kind & self.kinds(emitter).env
        uniform = env & (u_dir.x < ENV_DEFENSIVE)
        u_x = dr.select(uniform, u_dir.x / ENV_DEFENSIVE, (u_dir.x - ENV_DEFENSIVE) / (1.0 - ENV_DEFENSIVE))
        u_own = mi.Point2f(dr.select(env, u_x, u_dir.x), u_dir.y)
        ds, w = emitter.sample_direction(it, u_own, active & kind)
        ds.d = dr.select(uniform, mi.warp.square_to_uniform_sphere(u_own), ds.d)
        pdf_own = emitter.pdf_direction(it, ds, active & env)
        si = dr.zeros(mi.SurfaceInteraction3f)       # (eval: Mitsuba's eval_direction reads ds.uv)
        si.wi, si.time, si.wavelengths = -ds.d, it.time, it.wavelengths
        le = emitter.eval(si, active & env)
        p_dir = (1.0 - ENV_DEFENSIVE) * pdf_own + ENV_DEFENSIVE * mi.warp.square_to_uniform_sphere_pdf(ds.d)
        return ds.d, dr.select(env, le, w * ds.pdf), dr.select(env, p_dir, ds.pdf)

    def pdf_direct_first_hit(self, e, si1, active):
        """Density of emitter sampling choosing y0 when seen from the first hit y1: per unit
        area at y0 (area), per unit solid angle (environment), discrete (delta emitters)."""
        k = e.kinds
        out = e.p_sel * 1.0
        if k.area is not False or k.env is not False:
            ds = mi.DirectionSample3f(e.ps)
            to_y0 = e.origin - si1.p
            dist = dr.norm(to_y0)
            ds.d = sel(k.infinite, -e.d, to_y0 / dr.maximum(dist, 1e-30))
            ds.dist = dist
            ds.n = e.n_e
            ds.emitter = e.emitter
            ds.delta = mi.Bool(False)
            pdf_w = self.pdf_direct_w(si1, ds, active & neg(k.delta))
            out = sel(k.area, self.per_area(pdf_w, ds), out)
            out = sel(k.env, pdf_w, out)
        if k.dir_area is not False:
            out = sel(k.dir_area, 0.0, out)                  # emitter sampling never reaches it
        return out

    @staticmethod
    def first_edge_dist2(e, si1):
        """Squared length of the first edge y0 -> y1 as the area density of y1 needs it: 1 for
        infinite emitters, whose y0 is a direction (solid-angle measure)."""
        d2 = dr.squared_norm(si1.p - e.origin)        # between the vertices, not from the offset origin
        if e.kinds.infinite is False:
            return d2
        return dr.select(e.kinds.infinite, 1.0, d2)

    # ------------------------------------------------------------------ camera side
    def pdf_direct_a(self, ref_it, ds, active):
        """Area emitters: density per unit area at the emitter point ``ds`` of emitter sampling
        from ``ref_it``, emitter choice included."""
        return self.per_area(self.pdf_direct_w(ref_it, ds, active), ds)

    @staticmethod
    def per_area(pdf_w, ds):
        """A density per unit solid angle at the reference point, per unit area at ``ds.p``."""
        return pdf_w_to_a(pdf_w, dr.dot(ds.n, ds.d), dr.square(ds.dist))

    def error_at(self, ds):
        """The error bound of an emitter sample's point for a shadow ray's far end (rays.py):
        area emitters' points lie on their shape; a point light or a direction has none."""
        k = self.kinds(ds.emitter)
        if k.surface is False:
            return mi.Float(0.0)
        return sel(k.surface, self.offsets.error(ds.p, ds.emitter.get_shape(), hit=False), mi.Float(0.0))

    @staticmethod
    def direct_terms(ds, k):
        """For emitter sampling's weight (mis.weight_s1): the density per unit solid angle at the
        camera vertex (a point light's discrete density times d^2, the solid-angle form of its
        'area' density) and |cos| at the emitter point (1 for points and infinite emitters,
        which have no surface normal)."""
        cos_e = sel(k.area, dr.abs(dr.dot(ds.n, ds.d)), mi.Float(1.0))
        pdf_direct_w = sel(k.delta_pos, ds.pdf * dr.square(ds.dist), ds.pdf)
        return pdf_direct_w, cos_e

    def pdf_emit_w_env(self, env, ref_it, d, active):
        """Emission density of the environment emitter ``env`` in the direction ``-d`` (``d``:
        towards the environment): its choice, the disk facing the scene and its direction
        density. Returns (DirectionSample3f towards it, pdf_emit_w)."""
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = d
        ds.dist = mi.Float(dr.inf)
        ds.emitter = mi.EmitterPtr(env)
        p_sel = self.pdf_select(mi.EmitterPtr(env))
        return ds, p_sel * self.pdf_disk * env.pdf_direction(ref_it, ds, active)

    def pdf_emit_w_at(self, emitter, ds, d_out, k=None):
        """Emission density (choice, position, direction ``d_out`` leaving the emitter) of the
        emitter point / direction ``ds``: what a light subpath would have used to start there."""
        if k is None:
            k = self.kinds(emitter)
        p_sel = self.pdf_select(emitter)
        out = mi.Float(0.0)
        if k.area is not False:
            p_dir = self.pdf_dir_w(dr.dot(ds.n, d_out))
            if self.smooth is not None:     # (ds.n: the triangle's normal there)
                p_dir = dr.select(self.smooth.rank(emitter)[1], emission_pdf_w(ds.n, d_out), p_dir)
            out = sel(k.area, self.pdf_pos_a(emitter, ds) * p_dir, out)
        if k.dir_area is not False:
            out = sel(k.dir_area, self.uniform_pdf_a(emitter), out)   # direction: discrete
        if k.delta_pos is not False:
            out = sel(k.delta_pos, self.cone_pdf_w(emitter, d_out), out)
        if k.delta_dir is not False:
            out = sel(k.delta_dir, mi.Float(self.pdf_disk), out)
        if k.env is not False:
            # (mi.DirectionSample3f(ds) would take the PositionSample3f overload and leave
            # d, dist and emitter empty: build it field by field)
            ds_env = dr.zeros(mi.DirectionSample3f, dr.width(d_out))
            ds_env.p, ds_env.n, ds_env.time, ds_env.pdf = ds.p, ds.n, ds.time, ds.pdf
            ds_env.d, ds_env.dist, ds_env.emitter = -d_out, ds.dist, emitter   # towards the emitter
            it = dr.zeros(mi.Interaction3f, dr.width(d_out))
            out = sel(k.env, self.pdf_disk * emitter.pdf_direction(it, ds_env, k.env), out)
        return p_sel * out


class EmissionStart:
    """What sample_emission's per-kind blocks fill in: their defaults are those of lanes of no kind."""

    def __init__(self, ps, si_e, wl):
        self.ps, self.si_e, self.wl = ps, si_e, wl
        self.value = mi.Spectrum(0.0)
        self.p_pos = mi.Float(1.0)
        self.p_dir = mi.Float(0.0)
        self.d = mi.Vector3f(0, 0, 1)
        self.origin = mi.Point3f(ps.p)
        self.cos_e = mi.Float(1.0)
        self.n_e = mi.Vector3f(ps.n)


class Emission:
    """A light subpath's start (see EmitterTable.sample_emission)."""
    emitter = kinds = p_sel = ps = si_e = d = origin = n_e = cos_e = err = None
    pdf_emit_w = pdf_light_a = beta = active = active_y0 = ray = None
