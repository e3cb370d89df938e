"""Camera subpaths: the strategies that end on the camera side, each weighted by mis.py.
- s=0: the camera subpath hits an emitter;
- s=1: emitter sampling from a camera vertex (Mitsuba's ``sample_emitter_direction``, small
  sphere emitters by bdpt's own cap sampling: endpoints.EmitterTable.sample_direct);
- s>=2, t>=2: connection of a camera vertex to each stored light vertex, with a shadow ray;
- merges (techniques vcm, vm): the camera vertex merged with the light vertices of the pass
  within the merging radius (merge.py).
No connection or merge is made at a delta vertex (a BSDF without a smooth component). With
technique vm (progressive photon mapping) the subpath goes on only through delta lobes: it
merges at its first vertex with a smooth component and ends where it samples a smooth lobe, so
an emitter it hits was reached through delta vertices only.

Each strategy is a function of its own: Dr.Jit's loops carry every variable assigned in their
body as loop state, so the loops below assign only what really carries over between
iterations, and the temporaries of each strategy stay inside its function."""

import drjit as dr
import mitsuba as mi

from . import gradients
from .connect import CTX_RADIANCE, eval_camera_vertex, eval_light_vertex, reverse_pdf_w, smooth_mask
from .endpoints import AreaKinds
from .jitmath import pdf_w_to_a, safe_div
from .rays import spawn, spawn_to, spawn_to_emitter
from .roulette import roulette


class CameraTracer:
    def __init__(self, ctx):
        self.ctx = ctx

    def primary(self, sampler, n, spp_pass, pixel_start, u_wavelength=None):
        """Camera rays for N samples: spp_pass consecutive samples per pixel of the crop,
        starting at crop pixel ``pixel_start`` (``u_wavelength``: see trace)."""
        c = self.ctx
        idx = dr.arange(mi.UInt32, n)
        pixel = idx // dr.opaque(mi.UInt32, spp_pass) + dr.opaque(mi.UInt32, pixel_start)
        crop_w = int(c.camera.crop_size.x)
        pos = mi.Point2f(mi.Float(pixel % crop_w), mi.Float(pixel // crop_w)) + sampler.next_2d()
        adjusted = pos / c.camera.crop_size
        u_wl = sampler.next_1d() if u_wavelength is None else u_wavelength
        ray, ray_w = c.camera.sample_ray(c.time, u_wl, adjusted, sampler.next_2d())
        return pos + c.camera.crop_offset, ray, mi.Spectrum(ray_w)

    def aov_values(self, si, ray):
        """The AOV channels (parameter ``aovs``) of each camera ray's first hit, as Mitsuba's aov
        integrator computes them; 0 where the ray leaves the scene."""
        valid = si.is_valid()
        out = []
        for _, kind in self.ctx.aovs:
            if kind == 'depth':
                vals = [si.t]
            elif kind == 'position':
                vals = [si.p.x, si.p.y, si.p.z]
            elif kind == 'uv':
                vals = [si.uv.x, si.uv.y]
            elif kind == 'geo_normal':
                vals = [si.n.x, si.n.y, si.n.z]
            elif kind == 'sh_normal':
                vals = [si.sh_frame.n.x, si.sh_frame.n.y, si.sh_frame.n.z]
            else:                                     # albedo
                a = si.bsdf(ray).eval_diffuse_reflectance(si, valid)
                vals = [a[i if dr.size_v(a) == 3 else 0] for i in range(3)]
            out += [dr.select(valid, v, 0.0) for v in vals]
        return out

    # ------------------------------------------------------------------ strategies
    def strategy_s0(self, si, ray, prev, depth, beta, d_vcm, d_vc, active, film_pos=None):
        """s=0: the camera subpath hits an emitter at ``si``."""
        c = self.ctx
        emitter = si.emitter(c.scene)
        hit_em = active & (emitter != None)            # noqa: E711 (pointer test)
        if c.hide_emitters:
            hit_em &= depth > 1
        le = emitter.eval(si, hit_em)
        ds = mi.DirectionSample3f(c.scene, si, prev)
        pdf_y0_a = c.emitters.pdf_select(emitter) * c.emitters.pdf_pos_a(emitter, ds)
        pdf_direct_a = dr.select(depth == 1, pdf_y0_a,
                                 c.emitters.pdf_direct_a(prev, ds, hit_em & (depth > 1)))
        pdf_emit_w = c.emitters.pdf_emit_w_at(emitter, ds, -ray.d, AreaKinds)
        w = c.mis.weight_s0(d_vcm, d_vc, pdf_direct_a, pdf_emit_w)
        if c.layers is not None:
            c.layers.add(0, depth + 1, film_pos, beta * le * (w * c.inv_spp), beta * le * c.inv_spp, hit_em)
        return dr.select(hit_em, beta * le * w, 0.0)

    def strategy_env(self, ray, prev, depth, beta, d_vcm, d_vc, escaped, film_pos=None):
        """s=0 for infinite emitters: the camera subpath leaves the scene (``depth``: edges
        including the escaping one; d_vcm, d_vc as before that edge: the environment's
        'vertex' is a direction, measured per unit solid angle)."""
        c = self.ctx
        env = c.scene.environment()
        if c.hide_emitters:
            escaped = escaped & (depth > 1)
        si_env = dr.zeros(mi.SurfaceInteraction3f)
        si_env.wi = -ray.d
        si_env.time, si_env.wavelengths = ray.time, ray.wavelengths
        le = env.eval(si_env, escaped)
        ds, pdf_emit_w = c.emitters.pdf_emit_w_env(env, prev, ray.d, escaped)
        pdf_direct_w = c.emitters.pdf_direct_w(prev, ds, escaped & (depth > 1))
        # seen directly: no other strategy can sample it (light tracing cannot hit the pinhole)
        w = dr.select(depth == 1, 1.0, c.mis.weight_s0(d_vcm, d_vc, pdf_direct_w, pdf_emit_w))
        if c.layers is not None:
            c.layers.add(0, depth + 1, film_pos, beta * le * (w * c.inv_spp), beta * le * c.inv_spp, escaped)
        return dr.select(escaped, beta * le * w, 0.0)

    def strategy_s1(self, si, bsdf, beta, d_vcm, d_vc, u, active, depth=None, film_pos=None, err=None,
                    merge_z=True):
        """s=1: emitter sampling from the camera vertex ``si`` (``merge_z``: whether a merge at
        ``si`` is a strategy, mis.MIS.merge_here_camera)."""
        c = self.ctx
        ds, em_w = gradients.sample_direct(c, si, u, active)
        # never `active &=` on a parameter: Dr.Jit's in-place operators would narrow the
        # caller's mask too (it then dropped the connections of failed emitter samples)
        active = active & (ds.pdf > 0) & (dr.max(em_w) > 0)
        err = c.offsets.error(si.p, si.shape) if err is None else err
        blocked = c.scene.ray_test(spawn_to_emitter(si.p, si.n, err, ds,
                                                    c.emitters.error_at(ds), si.time, c.offsets.far_rel,
                                                    si.wavelengths), active)
        if c.stats is not None:
            c.stats.shadow(active, blocked)
        active &= ~blocked
        f, pdf_bsdf_w, pdf_rev_w = eval_camera_vertex(si, bsdf, ds.d, active, c.diffuse)
        k = c.emitters.kinds(ds.emitter)
        pdf_emit_w = c.emitters.pdf_emit_w_at(ds.emitter, ds, -ds.d, k)
        pdf_direct_w, cos_e = c.emitters.direct_terms(ds, k)
        cos_z = dr.abs(dr.dot(si.n, ds.d))
        w = c.mis.weight_s1(d_vcm, d_vc, pdf_bsdf_w, pdf_direct_w, pdf_emit_w, cos_e, cos_z, pdf_rev_w,
                            emitter_is_delta=k.delta, merge_z=merge_z)
        if c.layers is not None:
            value = beta * f * em_w * c.inv_spp
            c.layers.add(1, depth + 1, film_pos, value * w, value, active)
        return dr.select(active, beta * f * em_w * w, 0.0)

    def connect_one(self, record, st_v, slot, si, bsdf, depth, beta, d_vcm, d_vc, active, film_pos=None,
                    level=None, err=None, merge_z=True):
        """s>=2, t>=2: camera vertex ``si`` connected to the stored light vertex ``slot`` (at
        ``level`` of the storage: needed by records that do not store the depth)."""
        c = self.ctx
        v = record.load(st_v, slot, active)
        v_depth = v.depth_at(level)
        ok = active & (v_depth + depth + 1 <= c.max_depth_edges)
        y = v.interaction(c.time, si.wavelengths)     # the sample's wavelengths (spectral)
        to_y = y.p - si.p
        dist2 = dr.squared_norm(to_y)
        d = to_y * dr.rsqrt(dr.select(dist2 > 0, dist2, 1.0))
        f_c, pdf_c_w, pdf_c_rev_w = eval_camera_vertex(si, bsdf, d, ok, c.diffuse)
        f_l, pdf_l_w, pdf_l_rev_w, ok_l = eval_light_vertex(y, v.bsdf, -d, ok, c.exact_adjoint, c.diffuse)
        contrib = beta * f_c * f_l * v.beta * safe_div(1.0, dist2)
        # The guard where the contribution is formed: vertices ~1e-19 apart give a subnormal
        # dist2 whose inverse overflows (and a NaN once the power weight, 0 there, multiplies it)
        ok &= ok_l & (dr.max(contrib) > 0) & (dr.max(contrib) < dr.inf)
        err = c.offsets.error(si.p, si.shape) if err is None else err
        blocked = c.scene.ray_test(spawn_to(si.p, si.n, err, y.p, y.n, v.err, si.time,
                                            c.offsets.far_rel, si.wavelengths), ok)
        if c.stats is not None:
            c.stats.shadow(ok, blocked)
        ok &= ~blocked
        w = c.mis.weight_connect(
            v.d_vcm, v.d_vc, d_vcm, d_vc,
            pdf_w_to_a(pdf_c_w, dr.dot(y.n, d), dist2),
            pdf_w_to_a(pdf_l_w, dr.dot(si.n, d), dist2),
            pdf_l_rev_w, pdf_c_rev_w, merge_z)
        if c.layers is not None:
            c.layers.add(v_depth + 1, depth + 1, film_pos, contrib * (w * c.inv_spp), contrib * c.inv_spp, ok)
        return dr.select(ok, contrib * w, 0.0)

    @dr.syntax
    def connect_all(self, store, idx, si, bsdf, depth, beta, d_vcm, d_vc, active, film_pos=None, err=None,
                    merge_z=True):
        """Sum of the connections of camera vertex ``si`` to the light subpath of its sample."""
        c = self.ctx
        n_light, record, st_v, slot_of = store.count, store.record, store.v, store.slot   # read before the loop
        # stored depths grow with j (depth_j >= j + 1): beyond j_end max_depth forbids all
        j_end = dr.minimum(n_light, mi.UInt32(c.max_depth_edges) - dr.minimum(depth + 1, c.max_depth_edges))
        L = mi.Spectrum(0.0)
        j = mi.UInt32(0)
        err = c.offsets.error(si.p, si.shape) if err is None else err   # once for all connections of si
        while dr.hint(active & (j < j_end), label='bdpt_connect'):
            L += self.connect_one(record, st_v, slot_of(j, idx), si, bsdf, depth, beta, d_vcm, d_vc,
                                  active, film_pos, level=j, err=err, merge_z=merge_z)
            j += 1
        return L

    def advance(self, sampler, si, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, active, err, merge_here=True):
        """Scatter at ``si`` and find the next vertex. In a differentiable pass the next vertex
        is a material point and the edge's derivative enters the throughput (gradients.py).
        Also returns whether ``si`` scattered through a delta lobe (False without delta lobes)."""
        c = self.ctx
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        ray, beta, d_vcm, d_vc, d_vm, active, is_delta = self.scatter(
            sampler, u1, u2, si, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, active, err, merge_here)
        si_next, beta, dist2 = gradients.next_vertex(c, True, si, bsdf, ray, (u1, u2), is_delta, beta, active)
        was_delta = is_delta if is_delta is not None else mi.Bool(False)
        return ray, si_next, beta, d_vcm, d_vc, d_vm, active, dist2, was_delta

    def scatter(self, sampler, u1, u2, si, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, active, err,
                merge_here=True):
        """Sample the next direction (lobe and direction samples ``u1``, ``u2``); update
        throughput, MIS quantities and the roulette. Returns the next ray, the updated state
        and the delta mask (None in scenes without delta lobes). ``merge_here``: whether a merge
        at ``si`` is a strategy (mis.MIS.merge_here_camera)."""
        c = self.ctx
        bs, bsdf_w = gradients.sample_bsdf(c, bsdf, CTX_RADIANCE, si, u1, u2, active)
        active = active & (bs.pdf > 0) & (dr.max(bsdf_w) > 0)
        beta = beta * bsdf_w
        wo_world = si.to_world(bs.wo)
        if c.has_delta:
            is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            pdf_rev_w = dr.select(is_delta, 0.0,
                                  reverse_pdf_w(bsdf, CTX_RADIANCE, si, bs.wo, active & ~is_delta, c.diffuse))
        else:
            is_delta = None                           # no delta lobe in the scene: not traced
            pdf_rev_w = reverse_pdf_w(bsdf, CTX_RADIANCE, si, bs.wo, active, c.diffuse)
        cos_out = dr.abs(dr.dot(si.n, wo_world))
        if c.mis.mis_merges:
            d_vm = c.mis.vm_on_scatter(d_vm, d_vcm, cos_out, bs.pdf, pdf_rev_w, is_delta, merge_here)
        d_vcm, d_vc = c.mis.on_scatter(d_vcm, d_vc, cos_out, bs.pdf, pdf_rev_w, is_delta, camera_side=True,
                                       merge_here=merge_here)
        if c.strategies.ppm:        # vm: only delta lobes go on (a smooth one was merged)
            active &= is_delta if is_delta is not None else False
        beta, active = roulette(beta, beta_start, depth, c.rr_depth, active, sampler.next_1d())
        ray = spawn(si.p, si.n, err, wo_world, si.time, si.wavelengths)
        return (dr.detach(ray) if c.ad else ray), beta, d_vcm, d_vc, d_vm, active, is_delta

    # ------------------------------------------------------------------ walk
    @dr.syntax
    def trace(self, sampler, n, spp_pass, pixel_start, film, store, u_wavelength=None, merger=None):
        """``u_wavelength``: the samples' wavelength samples in spectral variants (the light
        subpaths were given the wavelengths they choose), else None. ``merger``: merge.Merger
        of the pass (techniques vcm and vm), else None."""
        c = self.ctx
        mis = c.mis
        max_edges = c.max_depth_edges
        film_pos, ray, beta = self.primary(sampler, n, spp_pass, pixel_start, u_wavelength)
        wavelengths = ray.wavelengths
        beta_start = dr.max(beta)
        idx = dr.arange(mi.UInt32, n)

        si = gradients.intersect(c, ray, True, primary=True)     # in solid angle: no edge factor
        if c.stats is not None:
            c.stats.ray('camera', dr.full(mi.Bool, True, n), si.is_valid())
        L = mi.Spectrum(0.0)
        if c.strategies.trace_env:
            L += self.strategy_env(ray, dr.zeros(mi.Interaction3f, n), mi.UInt32(1), beta,
                                   mi.Float(0), mi.Float(0), ~si.is_valid() & (max_edges >= 1), film_pos)
        active = si.is_valid() & (max_edges >= 1)
        alpha = dr.select(si.is_valid(), 1.0, 0.0)
        aov_values = self.aov_values(si, ray) if c.aovs else ()
        pdf_cam_w = c.camera.pdf_w(ray.d)
        d_vcm, d_vc = mis.camera_init(pdf_cam_w)
        # the first edge's length as every other strategy measures it (from the lens point)
        dist2_cam = c.camera.first_edge_dist2(ray, si.p)
        d_vcm, d_vc = mis.on_hit(d_vcm, d_vc, dist2_cam, dr.abs(dr.dot(si.n, ray.d)))
        d_vm = dr.zeros(mi.Float, n)                  # [VCM (31)-(33)] no merge behind the camera
        depth = mi.UInt32(1)                          # edges from the camera to si
        prev = dr.zeros(mi.Interaction3f, n)          # previous camera vertex (depth > 1)
        prev_delta = dr.zeros(mi.Bool, n)             # it scattered through a delta lobe (the camera: no)

        while dr.hint(active, label='bdpt_camera_subpath'):
            bsdf = si.bsdf(ray)
            err = c.offsets.error(si.p, si.shape)     # the vertex's error bound, for all its rays (rays.py)

            # ---------------- s = 0: the camera subpath hits an emitter ----------------
            if dr.hint(c.strategies.trace_s0, mode='scalar'):
                L += self.strategy_s0(si, ray, prev, depth, beta, d_vcm, d_vc, active, film_pos)

            active &= depth + 1 <= max_edges          # every strategy below adds an edge
            smooth = active & smooth_mask(bsdf, c.diffuse)
            merge_here = mis.merge_here_camera(prev_delta)   # a merge at si is a strategy (mis.py)

            # ---------------- s = 1: emitter sampling ----------------
            if dr.hint(c.strategies.trace_s1, mode='scalar'):
                L += self.strategy_s1(si, bsdf, beta, d_vcm, d_vc, sampler.next_2d(), smooth, depth, film_pos, err,
                                      merge_here)

            # ---------------- s >= 2: connect to the light subpath ----------------
            if dr.hint(c.strategies.trace_connect, mode='scalar'):
                L += self.connect_all(store, idx, si, bsdf, depth, beta, d_vcm, d_vc, smooth, film_pos, err,
                                      merge_here)

            # ---------------- merges with the light vertices within the radius ----------------
            if dr.hint(c.strategies.trace_merge, mode='scalar'):
                L += merger.gather(idx, si, bsdf, depth, beta, d_vcm, d_vm, smooth & merge_here)

            # ---------------- continue the walk ----------------
            prev = mi.Interaction3f(si)
            ray, si, beta, d_vcm, d_vc, d_vm, active, dist2, prev_delta = self.advance(
                sampler, si, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, active, err, merge_here)
            if dr.hint(c.stats is not None, mode='scalar'):
                c.stats.ray('camera', active, si.is_valid())
            if dr.hint(c.strategies.trace_env, mode='scalar'):
                L += self.strategy_env(ray, prev, depth + 1, beta, d_vcm, d_vc,
                                       active & ~si.is_valid(), film_pos)
            active &= si.is_valid()
            d_vcm, d_vc = mis.on_hit(d_vcm, d_vc, dist2, dr.abs(dr.dot(si.n, ray.d)))
            if dr.hint(mis.mis_merges, mode='scalar'):
                d_vm = mis.vm_on_hit(d_vm, dr.abs(dr.dot(si.n, ray.d)))
            depth += 1

        film.put_camera(film_pos, L, alpha, mi.Bool(True), wavelengths, aov_values)
