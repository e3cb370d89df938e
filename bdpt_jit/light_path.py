"""Light subpaths: emission from an area emitter, importance transport through the scene,
the light image (t=1: every light vertex connected to the camera and splatted), and the
storage of the vertices that camera subpaths connect to (s>=2).

Storage is a set of global arrays, level-major (index = level * N + path), so the same code
runs with symbolic loops (one kernel) and with evaluated loops (as Dr.Jit's AD needs). When
``max_depth`` bounds the subpath, the storage is sized exactly; without a bound the loop pauses
the lanes whose storage is full, the storage grows, and the loop resumes: no vertex is ever
dropped, so every strategy the MIS weights count is really available."""

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .connect import (CTX_IMPORTANCE, adjoint_correction, adjoint_eval, eval_light_vertex, reverse_pdf_w,
                      sample_bsdf, smooth_mask)
from .endpoints import direction_sample_at, safe_div
from .roulette import roulette


# Every field a light vertex can need, in storage order. A scene stores only those its BSDFs
# and shapes read (record_type): scatter and gather cost per word on the CPU (measured: storing
# 35-word records took ~140 ms of a 720 ms render; 25 words +20% samples/s).
FIELDS = {
    'p': mi.Point3f,          # position
    'n': mi.Normal3f,         # geometric normal         (absent: the shading normal, see below)
    'n_s': mi.Normal3f,       # shading normal
    's': mi.Vector3f,         # shading tangent          (absent: any tangent, isotropic BSDFs)
    'uv': mi.Point2f,         # surface parametrisation  (textures)
    'wi': mi.Vector3f,        # direction towards y_{j-1}: local (with s), else world
    'shape': mi.ShapePtr,     # its shape                (mesh attributes)
    'bsdf': mi.BSDFPtr,       # its BSDF
    'prim_index': mi.UInt32,  # triangle                 (mesh attributes)
    'dp_du': mi.Vector3f,     # surface tangents         (normal and bump maps)
    'dp_dv': mi.Vector3f,
    'beta': mi.Color3f,       # Le / p up to y_j, importance transport
    'd_vcm': mi.Float,        # MIS quantities (mis.py)
    'd_vc': mi.Float,
    'depth': mi.UInt32,       # j: edges from y0         (absent: level + 1, every vertex stored)
}


_COMPONENTS = {mi.Point3f: 3, mi.Normal3f: 3, mi.Vector3f: 3, mi.Color3f: 3, mi.Point2f: 2,
               mi.Float: 1, mi.UInt32: 1, mi.ShapePtr: 1, mi.BSDFPtr: 1}


class VertexRecord:
    """One light vertex y_j as connections need it: the fields of its SurfaceInteraction3f that
    BSDFs read, its throughput and its MIS quantities. Subclasses name their fields in
    DRJIT_STRUCT (a subset of FIELDS, chosen by record_type)."""
    DRJIT_STRUCT = {}

    @classmethod
    def make(cls, si, bsdf, beta, d_vcm, d_vc, depth):
        v = cls()
        src = {'p': si.p, 'n': si.n, 'n_s': si.sh_frame.n, 's': si.sh_frame.s, 'uv': si.uv,
               'wi': si.wi if 's' in cls.DRJIT_STRUCT else si.to_world(si.wi),
               'shape': si.shape, 'bsdf': bsdf, 'prim_index': si.prim_index, 'dp_du': si.dp_du,
               'dp_dv': si.dp_dv, 'beta': beta, 'd_vcm': d_vcm, 'd_vc': d_vc, 'depth': depth}
        for k in cls.DRJIT_STRUCT:           # unused fields are never evaluated (lazy JIT)
            setattr(v, k, src[k])
        return v

    # ---------------------------------------------------------------- packed storage
    # A record is stored as consecutive float words, padded to whole packets of 4: one vertex
    # is written and read with a few 4-wide packet scatters/gathers (Dr.Jit's PacketOps)
    # instead of one scalar scatter/gather per word into separate arrays. Measured on the
    # SmallVCM box: storing light vertices took 256 of 1090 ms per render as separate
    # arrays; packets are ~4x faster to write and to read back.
    @classmethod
    def words(cls):
        return sum(_COMPONENTS[t] for t in cls.DRJIT_STRUCT.values())

    @classmethod
    def packets(cls):
        return (cls.words() + 3) // 4

    def pack(self):
        out = []
        for k, t in self.DRJIT_STRUCT.items():
            x = getattr(self, k)
            if t in (mi.ShapePtr, mi.BSDFPtr):
                out.append(dr.reinterpret_array(mi.Float, dr.reinterpret_array(mi.UInt32, x)))
            elif t is mi.UInt32:
                out.append(dr.reinterpret_array(mi.Float, x))
            elif t is mi.Float:
                out.append(x)
            else:
                out += [x[i] for i in range(_COMPONENTS[t])]
        return out

    @classmethod
    def unpack(cls, words):
        v = cls()
        i = 0
        for k, t in cls.DRJIT_STRUCT.items():
            m = _COMPONENTS[t]
            if t in (mi.ShapePtr, mi.BSDFPtr):
                x = dr.reinterpret_array(t, dr.reinterpret_array(mi.UInt32, words[i]))
            elif t is mi.UInt32:
                x = dr.reinterpret_array(mi.UInt32, words[i])
            elif t is mi.Float:
                x = words[i]
            else:
                x = t(*words[i:i + m])
            setattr(v, k, x)
            i += m
        return v

    @classmethod
    def allocate(cls, count):
        """Uninitialised storage for ``count`` records (every read is masked by the stored
        count; zeroing cost ~3% a pass)."""
        return dr.empty(mi.Float, max(count, 1) * cls.packets() * 4)

    @classmethod
    def store(cls, storage, record, slot, active):
        w = record.pack()
        w += [mi.Float(0.0)] * (cls.packets() * 4 - len(w))
        for q in range(cls.packets()):
            dr.scatter(storage, mi.Vector4f(*w[4 * q:4 * q + 4]), slot * cls.packets() + q, active)

    @classmethod
    def load(cls, storage, slot, active):
        w = []
        for q in range(cls.packets()):
            x = dr.gather(mi.Vector4f, storage, slot * cls.packets() + q, active)
            w += [x.x, x.y, x.z, x.w]
        return cls.unpack(w)

    def depth_at(self, level):
        """Edges from y0 to this vertex, stored at ``level`` (0-based)."""
        return self.depth if 'depth' in self.DRJIT_STRUCT else level + 1

    def interaction(self, time):
        """The SurfaceInteraction3f that the vertex's BSDF is evaluated at."""
        f = self.DRJIT_STRUCT
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(self.p))
        si.t = mi.Float(1.0)
        si.time = time
        si.p = self.p
        si.n = self.n if 'n' in f else self.n_s
        if 's' in f:
            si.sh_frame = mi.Frame3f(self.s, dr.cross(self.n_s, self.s), self.n_s)
            si.wi = self.wi
        else:
            # isotropic BSDFs: any tangent, with wi stored in world space and made local to it
            si.sh_frame = mi.Frame3f(self.n_s)
            si.wi = si.sh_frame.to_local(self.wi)
        if 'uv' in f:
            si.uv = self.uv
        if 'shape' in f:
            si.shape, si.prim_index = self.shape, self.prim_index
        if 'dp_du' in f:
            si.dp_du, si.dp_dv = self.dp_du, self.dp_dv
        return si


def make_record_type(fields):
    name = 'VertexRecord_' + '_'.join(fields)
    return type(name, (VertexRecord,), {'DRJIT_STRUCT': {k: FIELDS[k] for k in FIELDS if k in fields}})


# every field: what a scene the analysis knows nothing about gets
StoredVertex = make_record_type(list(FIELDS))


def record_type(needs):
    """The record for a scene: ``needs`` (scene_check.VertexNeeds) says which optional fields
    its BSDFs and shapes read."""
    fields = ['p', 'n_s', 'wi', 'bsdf', 'beta', 'd_vcm', 'd_vc']
    if needs.geometric_normal:
        fields.append('n')
    if needs.tangent:
        fields.append('s')
    if needs.uv:
        fields += ['uv', 'shape', 'prim_index']
    if needs.surface_tangents:
        fields += ['dp_du', 'dp_dv']
    if needs.depth:
        fields.append('depth')
    return make_record_type(fields)


@dataclass
class LightStore:
    """Vertices y_1, y_2, ... of N light subpaths at non-delta surfaces, level-major."""
    n: int                       # light subpaths (one per camera sample)
    capacity: int                # levels allocated
    record: type = StoredVertex  # a VertexRecord type (record_type)
    v: object = None             # packed records (VertexRecord.allocate) for n * capacity slots
    count: object = None         # mi.UInt32 per path: vertices stored

    def allocate(self):
        self.v = self.record.allocate(self.n * self.capacity)
        self.count = dr.zeros(mi.UInt32, self.n)

    def grow(self):
        """Double the levels, keeping what is stored (level-major: a plain prefix copy)."""
        old, count = self.v, self.count
        self.capacity *= 2
        self.allocate()
        self.count = count
        dr.scatter(self.v, old, dr.arange(mi.UInt32, dr.width(old)))
        dr.eval(self.v)


class LightTracer:
    """Traces light subpaths; owned by the integrator, which passes in the shared context."""

    def __init__(self, ctx):
        self.ctx = ctx

    # ------------------------------------------------------------------ emission
    def start(self, sampler, n, film):
        c = self.ctx
        active = dr.full(mi.Bool, True, n)
        e = c.emitters.sample_emission(c.time, sampler.next_1d(), sampler.next_2d(),
                                       sampler.next_2d(), active)
        active = e.active

        # ---------------- s=1, t=1: the emitter vertex y0 seen by the camera ----------------
        u_cam = sampler.next_2d()
        if c.splat_y0 and e.kinds.area is not False:      # only surfaces can be seen directly
            self.splat_emitter_vertex(u_cam, e, film, active & e.kinds.area)

        d_vc = c.mis.light_init(e.pdf_emit_w, e.cos_e, e.kinds.delta)
        active &= c.max_depth_edges >= 2
        si = c.scene.ray_intersect(e.ray, active)
        if c.stats is not None:
            c.stats.ray('light', active, si.is_valid())
        active &= si.is_valid()
        pdf_direct = c.emitters.pdf_direct_first_hit(e, si, active)
        cos_hit = dr.abs(dr.dot(si.n, e.ray.d))
        dist2 = dr.square(si.t) if e.kinds.infinite is False else \
            dr.select(e.kinds.infinite, 1.0, dr.square(si.t))  # infinite: solid-angle measure
        d_vcm, d_vc = c.mis.light_first_hit(d_vc, e.pdf_emit_w, pdf_direct, dist2, cos_hit)
        depth = dr.full(mi.UInt32, 1, n)
        return active, si, e.beta, d_vcm, d_vc, depth

    def splat_emitter_vertex(self, u, e, film, active):
        c = self.ctx
        si_e, ps, emitter = e.si_e, e.ps, e.emitter
        ds, sensor_w = c.sensor.sample_direction(si_e, u, active)
        ok = active & (ds.pdf > 0)
        cos_g = dr.dot(ps.n, ds.d)                            # emitter normal towards camera
        si_to_cam = mi.SurfaceInteraction3f(si_e)
        si_to_cam.wi = si_e.to_local(ds.d)
        le = emitter.eval(si_to_cam, ok)
        ok &= (cos_g > 0) & (dr.max(le) > 0)
        blocked = c.scene.ray_test(si_e.spawn_ray_to(ds.p), ok)
        if c.stats is not None:
            c.stats.shadow(ok, blocked)
        ok &= ~blocked
        pdf_light_a = e.pdf_light_a
        pdf_cam_a = c.camera.pdf_w(-ds.d) * dr.abs(cos_g) * safe_div(1.0, dr.square(ds.dist))  # We |cos| / d^2
        w = c.mis.weight_s1t1(pdf_cam_a, pdf_light_a)
        value = le * dr.abs(cos_g) * safe_div(sensor_w.x, pdf_light_a) * c.splat_scale
        film.put_splat(ds.uv, value * w, ok)
        if c.layers is not None:
            c.layers.add(1, 1, ds.uv + c.camera.crop_offset, value * w, value, ok)

    # ------------------------------------------------------------------ walk
    def trace(self, sampler, n, film, store):
        """Trace N light subpaths; splat t=1 strategies; fill ``store`` (or None)."""
        c = self.ctx
        active, si, beta, d_vcm, d_vc, depth = self.start(sampler, n, film)
        beta_start = dr.max(beta)
        idx = dr.arange(mi.UInt32, n)
        count = dr.zeros(mi.UInt32, n)
        while True:
            active, si, beta, d_vcm, d_vc, depth, count = self.walk(
                sampler, idx, film, store, active, si, beta, beta_start, d_vcm, d_vc, depth, count)
            if store is None:
                break
            store.count = count
            if not c.unbounded or not dr.any(active):
                break
            store.grow()             # lanes paused on a full storage resume with more levels

    @dr.syntax
    def walk(self, sampler, idx, film, store, active, si, beta, beta_start, d_vcm, d_vc, depth, count):
        c = self.ctx
        mis = c.mis
        store_on = store is not None
        capacity = store.capacity if store_on else 0
        max_edges = c.max_depth_edges
        # Read the store before the loop: a dataclass referenced in the loop body would become
        # loop state (Dr.Jit traverses dataclasses), and the scatter would land in a copy.
        st_v = store.v if store_on else None
        make_record = store.record.make if store_on else None
        store_record = store.record.store if store_on else None
        pausing = store_on and c.unbounded     # bounded storage is sized to never fill
        cap_eff = capacity if pausing else 0xFFFFFFFF
        while dr.hint(active & (count < cap_eff),
                      label='bdpt_light_subpath',
                      exclude=[st_v]):
            bsdf = si.bsdf()
            smooth = smooth_mask(bsdf, c.diffuse)

            # ---------------- store y_depth for connections (s >= 2, t >= 2) ----------------
            if dr.hint(store_on, mode='scalar'):
                do_store = active & smooth & (depth + 2 <= max_edges)
                slot = count * c.n_opaque + idx
                store_record(st_v, make_record(si, bsdf, beta, d_vcm, d_vc, depth), slot, do_store)
                count[do_store] += 1

            # ---------------- t = 1: connect y_depth to the camera ----------------
            if dr.hint(c.splat_t1, mode='scalar'):
                do_splat = active & smooth & (depth + 1 <= max_edges)
                ds, sensor_w = c.sensor.sample_direction(si, sampler.next_2d(), do_splat)
                do_splat &= ds.pdf > 0
                f, pdf_fwd_w, pdf_rev_w, ok = eval_light_vertex(si, bsdf, ds.d, do_splat, c.exact_adjoint, c.diffuse)
                do_splat &= ok & (dr.max(f) > 0)
                blocked = c.scene.ray_test(si.spawn_ray_to(ds.p), do_splat)
                if dr.hint(c.stats is not None, mode='scalar'):
                    c.stats.shadow(do_splat, blocked)
                do_splat &= ~blocked
                pdf_cam_a = c.camera.pdf_w(-ds.d) * dr.abs(dr.dot(si.n, ds.d)) * safe_div(1.0, dr.square(ds.dist))
                w = mis.weight_t1(d_vcm, d_vc, pdf_cam_a, pdf_rev_w)
                value = beta * f * sensor_w * c.splat_scale
                film.put_splat(ds.uv, value * w, do_splat)
                if dr.hint(c.layers is not None, mode='scalar'):
                    c.layers.add(depth + 1, 1, ds.uv + c.camera.crop_offset, value * w, value, do_splat)

            # ---------------- continue the walk ----------------
            active &= depth + 2 <= max_edges
            bs, bsdf_w = sample_bsdf(bsdf, CTX_IMPORTANCE, si, sampler.next_1d(), sampler.next_2d(), active, c.diffuse)
            wo_world = si.to_world(bs.wo)
            corr, ok = adjoint_correction(si, bs.wo, wo_world, active)
            active &= ok & (bs.pdf > 0) & (dr.max(bsdf_w) > 0)
            if dr.hint(c.exact_adjoint, mode='scalar'):
                # BSDFs with their own shading frame (normal/bump maps): the exact adjoint
                # value over the sampling density for smooth samples, Veach's factor for delta
                if dr.hint(c.has_delta, mode='scalar'):
                    is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                    smooth_sample = active & ~is_delta
                else:
                    is_delta = None
                    smooth_sample = active
                f_adj, pdf_rev_adj, _ = adjoint_eval(si, bsdf, bs.wo, wo_world, smooth_sample)
                beta *= dr.select(smooth_sample, f_adj * safe_div(1.0, bs.pdf), bsdf_w * corr)
                pdf_rev_w = dr.select(smooth_sample, pdf_rev_adj, 0.0)
            elif dr.hint(c.has_delta, mode='scalar'):
                beta *= bsdf_w * corr
                is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                pdf_rev_w = dr.select(is_delta, 0.0,
                                      reverse_pdf_w(bsdf, CTX_IMPORTANCE, si, bs.wo, active & ~is_delta, c.diffuse))
            else:
                beta *= bsdf_w * corr
                is_delta = None                       # no delta lobe in the scene: not traced
                pdf_rev_w = reverse_pdf_w(bsdf, CTX_IMPORTANCE, si, bs.wo, active, c.diffuse)
            cos_out = dr.abs(dr.dot(si.n, wo_world))
            d_vcm, d_vc = mis.on_scatter(d_vcm, d_vc, cos_out, bs.pdf, pdf_rev_w, is_delta)

            # Russian roulette (as Mitsuba's path: from rr_depth on, survival <= 0.95)
            beta, active = roulette(beta, beta_start, depth, c.rr_depth, active, sampler.next_1d())

            ray = si.spawn_ray(wo_world)
            si = c.scene.ray_intersect(ray, active)
            if dr.hint(c.stats is not None, mode='scalar'):
                c.stats.ray('light', active, si.is_valid())
            active &= si.is_valid()
            d_vcm, d_vc = mis.on_hit(d_vcm, d_vc, dr.square(si.t), dr.abs(dr.dot(si.n, ray.d)))
            depth += 1
        return active, si, beta, d_vcm, d_vc, depth, count
