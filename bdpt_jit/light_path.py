"""Light subpaths: emission from any emitter kind (endpoints.EmitterTable), importance
transport through the scene, the light image (t=1: every light vertex connected to the camera
and splatted; s=1,t=1: the emitter vertex itself), and the vertices that camera subpaths
connect to (s>=2), written to the light-vertex store (store.LightStore)."""

import drjit as dr
import mitsuba as mi

from . import gradients
from .connect import CTX_IMPORTANCE, adjoint_correction, adjoint_eval, eval_light_vertex, reverse_pdf_w, smooth_mask
from .jitmath import pdf_w_to_a, safe_div, sel
from .rays import spawn, spawn_to
from .roulette import roulette


class LightTracer:
    """Traces light subpaths; owned by the integrator, which passes in the shared context."""

    def __init__(self, ctx):
        self.ctx = ctx
        self.wl_weight = 1.0        # spectral variants: the wavelengths' sampling weight (start)

    # ------------------------------------------------------------------ emission
    def start(self, sampler, n, film, spectral=None):
        """``spectral``: (wavelengths, their sampling weight) of each sample in spectral variants
        (the camera subpath of the same sample carries the same ones), else None."""
        c = self.ctx
        active = dr.full(mi.Bool, True, n)
        u_sel, u_pos, u_dir = sampler.next_1d(), sampler.next_2d(), sampler.next_2d()
        wl = spectral[0] if spectral is not None else None
        e = gradients.sample_emission(c, c.time, u_sel, u_pos, u_dir, active, wl)
        # the wavelengths' sampling weight enters the splats (t=1) only: the camera subpath of
        # the same sample carries it already, and a connection multiplies both throughputs
        self.wl_weight = spectral[1] if spectral is not None else 1.0
        active = e.active

        # ---------------- s=1, t=1: the emitter vertex y0 seen by the camera ----------------
        u_cam = sampler.next_2d()
        if c.strategies.trace_splat_y0 and e.kinds.area is not False:      # only surfaces can be seen directly
            self.splat_emitter_vertex(u_cam, e, film, active & e.kinds.area,
                                      spectral[1] if spectral is not None else 1.0)

        d_vc = c.mis.light_init(e.pdf_emit_w, e.cos_e, e.kinds.delta)
        d_vm = c.mis.vm_init_light(d_vc)            # (vc_factor 0 without merges: unused then)
        active &= c.max_depth_edges >= 2
        si = gradients.intersect(c, e.ray, active)
        if c.ad:
            beta = e.beta * gradients.emission_ratio(c, e, si, u_dir, c.time, active & si.is_valid())
            # wi from the emitter point (a material point); an infinite emitter's y0 is a direction
            si.wi = sel(e.kinds.infinite, si.wi, si.to_local(dr.normalize(e.y0_p - si.p)))
        else:
            beta = e.beta
        if c.stats is not None:
            c.stats.ray('light', active, si.is_valid())
        active &= si.is_valid()
        pdf_direct = c.emitters.pdf_direct_first_hit(e, si, active)
        cos_hit = dr.abs(dr.dot(si.n, e.ray.d))
        dist2 = c.emitters.first_edge_dist2(e, si)
        d_vcm, d_vc = c.mis.light_first_hit(d_vc, e.pdf_emit_w, pdf_direct, dist2, cos_hit)
        d_vm = c.mis.vm_on_hit(d_vm, cos_hit) if c.mis.mis_merges else dr.zeros(mi.Float, n)
        depth = dr.full(mi.UInt32, 1, n)
        return active, si, beta, d_vcm, d_vc, d_vm, depth

    def splat_emitter_vertex(self, u, e, film, active, wl_weight=1.0):
        """s=1, t=1: the emitter vertex y0 connected to the camera (``wl_weight``: the
        wavelengths' sampling weight in spectral variants)."""
        c = self.ctx
        si_e, ps, emitter = e.si_e, e.ps, e.emitter
        ds, sensor_w = c.sensor.sample_direction(si_e, u, active)
        ok = active & (ds.pdf > 0)
        cos_g = dr.dot(ps.n, ds.d)                            # emitter normal towards camera
        si_to_cam = mi.SurfaceInteraction3f(si_e)
        si_to_cam.wi = si_e.to_local(ds.d)
        le = emitter.eval(si_to_cam, ok)
        ok &= (cos_g > 0) & (dr.max(le) > 0)
        blocked = c.scene.ray_test(spawn_to(ps.p, ps.n, e.err, ds.p, mi.Normal3f(0.0), 0.0, ps.time, c.offsets.far_rel,
                                            si_e.wavelengths), ok)
        if c.stats is not None:
            c.stats.shadow(ok, blocked)
        ok &= ~blocked
        pdf_light_a = e.pdf_light_a
        pdf_cam_a = pdf_w_to_a(c.camera.pdf_w(-ds.d), cos_g, dr.square(ds.dist))  # We |cos| / d^2
        w = c.mis.weight_s1t1(pdf_cam_a, pdf_light_a)
        value = le * dr.abs(cos_g) * (sensor_w * safe_div(1.0, pdf_light_a)) * c.splat_scale
        if not isinstance(wl_weight, float):
            value = value * wl_weight
        film.put_splat(ds.uv, value * w, ok, si_e.wavelengths)
        if c.layers is not None:
            c.layers.add(1, 1, ds.uv + c.camera.crop_offset, value * w, value, ok)

    # ------------------------------------------------------------------ walk
    def trace(self, sampler, n, film, store, spectral=None):
        """Trace N light subpaths; splat t=1 strategies; fill ``store`` (or None)."""
        c = self.ctx
        active, si, beta, d_vcm, d_vc, d_vm, depth = self.start(sampler, n, film, spectral)
        beta_start = dr.max(beta)
        idx = dr.arange(mi.UInt32, n)
        count = dr.zeros(mi.UInt32, n)
        # a merge's terms waiting for the next vertex (mis.MIS.pending; none behind y0)
        pend = (dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)) if c.mis.pending else (mi.Float(0.0), mi.Float(0.0))
        while True:
            active, si, beta, d_vcm, d_vc, d_vm, pend, depth, count = self.walk(
                sampler, idx, film, store, active, si, beta, beta_start, d_vcm, d_vc, d_vm, pend, depth, count)
            if store is None:
                break
            store.count = count
            if not c.unbounded or not dr.any(active):
                break
            store.grow()             # lanes paused on a full storage resume with more levels

    def splat_vertex(self, sampler, si, err, bsdf, depth, beta, d_vcm, d_vc, film, active):
        """t=1: the light vertex ``si`` connected to the camera and splatted to the light image."""
        c = self.ctx
        ds, sensor_w = c.sensor.sample_direction(si, sampler.next_2d(), active)
        ok = active & (ds.pdf > 0)
        f, pdf_fwd_w, pdf_rev_w, valid = eval_light_vertex(si, bsdf, ds.d, ok, c.exact_adjoint, c.diffuse)
        ok &= valid & (dr.max(f) > 0)
        blocked = c.scene.ray_test(spawn_to(si.p, si.n, err, ds.p, mi.Normal3f(0.0), 0.0, si.time, c.offsets.far_rel,
                                            si.wavelengths), ok)
        if c.stats is not None:
            c.stats.shadow(ok, blocked)
        ok &= ~blocked
        pdf_cam_a = pdf_w_to_a(c.camera.pdf_w(-ds.d), dr.dot(si.n, ds.d), dr.square(ds.dist))
        w = c.mis.weight_t1(d_vcm, d_vc, pdf_cam_a, pdf_rev_w)
        value = beta * f * sensor_w * c.splat_scale
        if not isinstance(self.wl_weight, float):
            value = value * self.wl_weight
        film.put_splat(ds.uv, value * w, ok, si.wavelengths)
        if c.layers is not None:
            c.layers.add(depth + 1, 1, ds.uv + c.camera.crop_offset, value * w, value, ok)

    def advance(self, sampler, si, err, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, pend, active):
        """Scatter at ``si`` and find the next vertex. In a differentiable pass the next vertex
        is a material point and the edge's derivative enters the throughput (gradients.py)."""
        c = self.ctx
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        ray, beta, d_vcm, d_vc, d_vm, pend, active, is_delta = self.scatter(
            sampler, u1, u2, si, err, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, pend, active)
        si_next, beta, dist2 = gradients.next_vertex(c, False, si, bsdf, ray, (u1, u2), is_delta, beta, active)
        return ray, si_next, beta, d_vcm, d_vc, d_vm, pend, active, dist2

    def scatter(self, sampler, u1, u2, si, err, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, pend, active):
        """Sample the next direction in importance mode (the adjoint BSDF; lobe and direction
        samples ``u1``, ``u2``); update throughput, MIS quantities and the roulette. Returns the
        next ray, the updated state and the delta mask (None without delta lobes). ``pend``: the
        previous vertex's merge terms (mis.MIS.pending), counted here if this vertex is delta."""
        c = self.ctx
        beta_in = beta
        bs, bsdf_w = gradients.sample_bsdf(c, bsdf, CTX_IMPORTANCE, si, u1, u2, active)
        wo_world = si.to_world(bs.wo)
        corr, ok = adjoint_correction(si, bs.wo, wo_world, active)
        active = active & ok & (bs.pdf > 0) & (dr.max(bsdf_w) > 0)
        is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) if c.has_delta else None
        if c.exact_adjoint:
            # BSDFs with their own shading frame (normal/bump maps): the exact adjoint value
            # over the sampling density for smooth samples, Veach's factor for delta ones
            smooth_sample = active & ~is_delta if c.has_delta else active
            f_adj, pdf_rev_adj, _ = adjoint_eval(si, bsdf, bs.wo, wo_world, smooth_sample)
            beta = beta * dr.select(smooth_sample, f_adj * safe_div(1.0, bs.pdf), bsdf_w * corr)
            pdf_rev_w = dr.select(smooth_sample, pdf_rev_adj, 0.0)
        elif c.has_delta:
            beta = beta * (bsdf_w * corr)
            pdf_rev_w = dr.select(is_delta, 0.0,
                                  reverse_pdf_w(bsdf, CTX_IMPORTANCE, si, bs.wo, active & ~is_delta, c.diffuse))
        else:
            beta = beta * (bsdf_w * corr)         # no delta lobe in the scene: none traced
            pdf_rev_w = reverse_pdf_w(bsdf, CTX_IMPORTANCE, si, bs.wo, active, c.diffuse)
        if c.ad:   # the factor without derivatives: the edge's derivative comes with edge_ratio
            beta = mi.Spectrum(beta_in * dr.detach(beta * safe_div(1.0, dr.detach(beta_in))))
        cos_out = dr.abs(dr.dot(si.n, wo_world))
        here = not c.mis.pending                  # a merge here: deferred to the next vertex (mis.py)
        if c.mis.pending:
            d_vc, d_vm = c.mis.absorb_pending(d_vc, d_vm, pend[0], pend[1], is_delta)
            pend = c.mis.pending_after_scatter(cos_out, bs.pdf, is_delta)
        if c.mis.mis_merges:
            d_vm = c.mis.vm_on_scatter(d_vm, d_vcm, cos_out, bs.pdf, pdf_rev_w, is_delta, here)
        d_vcm, d_vc = c.mis.on_scatter(d_vcm, d_vc, cos_out, bs.pdf, pdf_rev_w, is_delta, merge_here=here)
        if c.mis.camera_chains and is_delta is not None:
            active &= ~is_delta       # delta chains are crossed from the camera side only (mis.py)
        # Russian roulette (as Mitsuba's path: from rr_depth on, survival <= 0.95)
        beta, active = roulette(beta, beta_start, depth, c.rr_depth, active, sampler.next_1d())
        ray = spawn(si.p, si.n, err, wo_world, si.time, si.wavelengths)
        return (dr.detach(ray) if c.ad else ray), beta, d_vcm, d_vc, d_vm, pend, active, is_delta

    @dr.syntax
    def walk(self, sampler, idx, film, store, active, si, beta, beta_start, d_vcm, d_vc, d_vm, pend, depth, count):
        c = self.ctx
        max_edges = c.max_depth_edges
        store_on = store is not None
        # Read the store before the loop: its array is excluded from the loop state so that
        # the scatters land in it, not in a copy
        st_v = store.v if store_on else None
        slot_of = store.slot if store_on else None
        make_record = store.record.make if store_on else None
        store_record = store.record.store if store_on else None
        pausing = store_on and c.unbounded     # bounded storage is sized to never fill
        # a stored vertex is followed by an edge and a camera vertex (connections) or by a camera
        # vertex at the same place (merges)
        store_edges = 1 if c.strategies.trace_merge else 2
        cap_eff = store.capacity if pausing else 0xFFFFFFFF
        while dr.hint(active & (count < cap_eff), label='bdpt_light_subpath', exclude=[st_v]):
            bsdf = si.bsdf()
            smooth = smooth_mask(bsdf, c.diffuse)
            err = c.offsets.error(si.p, si.shape)

            # ---------------- store y_depth for connections (s >= 2, t >= 2) ----------------
            if dr.hint(store_on, mode='scalar'):
                do_store = active & smooth & (depth + store_edges <= max_edges)
                store_record(st_v, make_record(si, err, bsdf, beta, d_vcm, d_vc, depth, d_vm), slot_of(count, idx),
                             do_store)
                count[do_store] += 1

            # ---------------- t = 1: connect y_depth to the camera ----------------
            if dr.hint(c.strategies.trace_splat, mode='scalar'):
                self.splat_vertex(sampler, si, err, bsdf, depth, beta, d_vcm, d_vc, film,
                                  active & smooth & (depth + 1 <= max_edges))

            # ---------------- continue the walk ----------------
            active &= depth + 2 <= max_edges
            ray, si, beta, d_vcm, d_vc, d_vm, pend, active, dist2 = self.advance(
                sampler, si, err, bsdf, depth, beta, beta_start, d_vcm, d_vc, d_vm, pend, active)
            if dr.hint(c.stats is not None, mode='scalar'):
                c.stats.ray('light', active, si.is_valid())
            active &= si.is_valid()
            d_vcm, d_vc = c.mis.on_hit(d_vcm, d_vc, dist2, dr.abs(dr.dot(si.n, ray.d)))
            if dr.hint(c.mis.mis_merges, mode='scalar'):
                d_vm = c.mis.vm_on_hit(d_vm, dr.abs(dr.dot(si.n, ray.d)))
            if dr.hint(c.mis.pending, mode='scalar'):
                pend = (c.mis.vm_on_hit(pend[0], dr.abs(dr.dot(si.n, ray.d))),
                        c.mis.vm_on_hit(pend[1], dr.abs(dr.dot(si.n, ray.d))))
            depth += 1
        return active, si, beta, d_vcm, d_vc, d_vm, pend, depth, count
