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

from . import media_path, transport
from .beams import Segment
from .endpoints import AreaKinds
from .jitmath import pdf_w_to_a, safe_div
from .media import medium_at_sensor
from .mis import EmitterDensities, MISState
from .transport import Subpath
from .vertex import IMPORTANCE, RADIANCE, Vertex, past_emitter_shapes, visibility, visible


def _cos(v, d):
    """The cosine at vertex ``v`` towards ``d`` for a change of measure (jitmath.pdf_w_to_a
    takes its absolute value): 1 at a medium vertex (media_path.PathVertex)."""
    return dr.dot(v.si.n, d) if isinstance(v, Vertex) else v.cos(d)


SPARSE_IF = True    # False: the sparse strategies computed in every lane (for side-by-side measurements)


def where(ctx, mask, value, label):
    """``value()`` (a Spectrum, computed for the lanes in ``mask``; its side effects there
    only) in ``mask``, 0 elsewhere: a symbolic branch, so that a packet of lanes none of which is
    in ``mask`` skips it (LLVM: a branch around the block). For strategies that few lanes take:
    s=0 (emitters hit) on veach-mis' small spheres cost pt 3% of its time computed in every
    lane, 7% on the caustic. Primal passes only (a differentiable pass computes it in every
    lane: its derivatives through Dr.Jit's branch are not tested)."""
    if not SPARSE_IF or ctx.ad:
        return value()
    return dr.if_stmt((), mask, value, lambda: mi.Spectrum(0.0), label=label, mode='symbolic')


class CameraTracer:
    """Traces the camera subpaths of one pass (``ps``: passes.PassState) in the shared context."""

    def __init__(self, ctx, ps):
        self.ctx, self.ps = ctx, ps
        self.mis = ps.mis
        self.film_pos = None        # each sample's film position (set by trace: the strategy layers)
        self.lanes = None           # per-pixel counts: the lanes' PixelLanes (set by trace)

    def primary(self):
        """Camera rays for the pass's samples: spp_pass consecutive samples per pixel of the
        crop from crop pixel ``pixel_start``; the wavelength sample is the pass state's where
        the light subpaths were given the wavelengths it chooses (spectral variants)."""
        c, ps = self.ctx, self.ps
        sampler = ps.sampler
        pixel = camera_pixels(ps)
        crop_w = int(c.camera.crop_size.x)
        in_pixel = (ps.pixel_sampler or sampler).next_2d()
        pos = mi.Point2f(mi.Float(pixel % crop_w), mi.Float(pixel // crop_w)) + in_pixel
        adjusted = pos / c.camera.crop_size
        u_wl = sampler.next_1d() if ps.u_wl is None else ps.u_wl
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
    def add_layer(self, s, t, value, w, active):
        """The strategy layers (parameter strategy_images) and the moment estimation's film:
        ``value`` weighted by ``w`` and not."""
        c = self.ctx
        if c.layers is not None:
            c.layers.add(s, t, self.film_pos, value * (w * c.inv_spp), value * c.inv_spp, active)
        if c.moments is not None:       # the moment estimation's pilot (moments.py)
            c.moments.add(s, t, self.film_pos, value * (w * c.inv_spp), value * c.inv_spp, active)

    def strategy_s0(self, v, ray, prev, sub):
        """s=0: the camera subpath hits an emitter at ``v`` (``prev``: the vertex before)."""
        c = self.ctx
        emitter = v.si.emitter(c.scene)
        hit_em = sub.active & (emitter != None)            # noqa: E711 (pointer test)
        if c.hide_emitters:
            hit_em &= sub.depth > 1
        return where(c, hit_em, lambda: self._s0_value(v, ray, prev, sub, emitter, hit_em), 'bdpt_s0')

    def _s0_value(self, v, ray, prev, sub, emitter, hit_em):
        c = self.ctx
        si, depth = v.si, sub.depth
        le = emitter.eval(si, hit_em)
        ds = mi.DirectionSample3f(c.scene, si, prev)       # (its normal: the shading normal)
        pdf_y0_a = c.emitters.pdf_select(emitter) * c.emitters.pdf_pos_a(emitter, ds)
        if c.emitters.smooth is not None:   # smooth-shaded emitter meshes: every density by the triangle's normal
            ds.n = dr.select(c.emitters.smooth.rank(emitter, hit_em)[1], si.n, ds.n)
        pdf_direct_a = dr.select(depth == 1, pdf_y0_a,
                                 c.emitters.pdf_direct_a(prev, ds, hit_em & (depth > 1)))
        pdf_emit_w = c.emitters.pdf_emit_w_at(emitter, ds, -ray.d, AreaKinds)
        w = self.mis.weight_s0(sub.mis.d_vcm, sub.mis.d_vc, pdf_direct_a, pdf_emit_w, first_hit=depth == 1)
        self.add_layer(0, depth + 1, sub.beta * le, w, hit_em)
        return dr.select(hit_em, sub.beta * le * w, 0.0)

    def strategy_s0_env(self, ray, prev, depth, beta, st, escaped):
        """s=0 for infinite emitters: the camera subpath leaves the scene (``depth``: edges
        including the escaping one; ``st``: the MISState before that edge: the environment's
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
        w = dr.select(depth == 1, 1.0, self.mis.weight_s0(st.d_vcm, st.d_vc, pdf_direct_w, pdf_emit_w))
        self.add_layer(0, depth + 1, beta * le, w, escaped)
        return dr.select(escaped, beta * le * w, 0.0)

    def strategy_s1(self, v, sub, active, merge_z=True):
        """s=1: emitter sampling from the camera vertex ``v`` (``merge_z``: whether a merge at
        ``v`` is a strategy, mis.MIS.merge_here_camera)."""
        c = self.ctx
        si = v.si
        ds, em_w = c.sampling.sample_direct(si, self.ps.sampler.next_2d(), active)
        # never `active &=` on a parameter: Dr.Jit's in-place operators would narrow the
        # caller's mask too (it then dropped the connections of failed emitter samples)
        active = active & (ds.pdf > 0) & (dr.max(em_w) > 0)
        ray = v.spawn_to_emitter(c, ds)
        e = self.emitter_edge(v, ds, ray, active) if c.media is not None else None
        tr = visibility(c, ray, active) if e is None else e.tr
        active &= visible(tr)
        if c.fuse_draw:     # with the scatter's BSDF sample, for every lane that scatters
            f, pdf_bsdf_w, _ = v.eval_and_draw(c, ds.d, RADIANCE, self.ps.sampler, sub.active)
            pdf_rev_w = v.pdf_rev_w(c, ds.d, RADIANCE, active) if self.mis.reads_reverse else mi.Float(0.0)
        else:
            f, pdf_bsdf_w, pdf_rev_w, _ = v.eval(c, ds.d, RADIANCE, active)
        k = c.emitters.kinds(ds.emitter)
        pdf_emit_w = c.emitters.pdf_emit_w_at(ds.emitter, ds, -ds.d, k)
        pdf_direct_w, cos_e = c.emitters.direct_terms(ds, k)
        if e is not None:   # media: the s=0 strategy reaches the emitter point with T, the light subpath z with pdf_l
            pdf_bsdf_w, pdf_emit_w = pdf_bsdf_w * e.pdf_l_far, pdf_emit_w * e.pdf_l_near
        w = self.mis.weight_s1(sub.mis, pdf_bsdf_w, pdf_rev_w, v.cos(ds.d),
                               EmitterDensities(pdf_direct_w, pdf_emit_w, cos_e, k.delta), merge_z)
        value = sub.beta * f * tr * em_w
        self.add_layer(1, sub.depth + 1, value, w, active)
        return dr.select(active, value * w, 0.0)

    def strategy_st(self, slot, level, v, sub, active, merge_z=True, scale=None):
        """s>=2, t>=2: the camera vertex ``v`` connected to the stored light vertex ``slot``
        (at ``level`` of the storage: needed by records that do not store the depth).
        ``scale``: the estimator's factor of a vertex drawn from the light vertex cache
        (light_cache.LightCache.scale), or None (the sample's own light subpath)."""
        c, store = self.ctx, self.ps.store
        si = v.si
        rec = store.record.load(store.v, slot, active)
        v_depth = rec.depth_at(level)
        ok = active & (v_depth + sub.depth + 1 <= c.max_depth_edges)
        y = rec.vertex(c.time, si.wavelengths)        # the sample's wavelengths (spectral)
        to_y = y.p - si.p
        dist2 = dr.squared_norm(to_y)
        d = to_y * dr.rsqrt(dr.select(dist2 > 0, dist2, 1.0))
        f_c, pdf_c_w, pdf_c_rev_w, _ = v.eval(c, d, RADIANCE, ok)
        f_l, pdf_l_w, pdf_l_rev_w, ok_l = y.eval(c, -d, IMPORTANCE, ok)
        contrib = sub.beta * f_c * f_l * rec.beta * safe_div(1.0, dist2)
        # The guard where the contribution is formed: vertices ~1e-19 apart give a subnormal
        # dist2 whose inverse overflows (and a NaN once the power weight, 0 there, multiplies it)
        ok &= ok_l & (dr.max(contrib) > 0) & (dr.max(contrib) < dr.inf)
        ray = v.spawn_to(c, y.p, y.si.n, y.err)
        e = media_path.connection_edge(c, self.ps.sampler, ray, v, y, d, ok) if c.media is not None else None
        tr = visibility(c, ray, ok) if e is None else e.tr
        ok &= visible(tr)
        contrib = contrib * tr
        if scale is not None:
            contrib = contrib * scale
        pdf_cam_to_light_a = pdf_w_to_a(pdf_c_w, _cos(y, d), dist2)
        pdf_light_to_cam_a = pdf_w_to_a(pdf_l_w, _cos(v, d), dist2)
        if e is not None:   # media: each end sampled across the edge has its distance density
            pdf_cam_to_light_a, pdf_light_to_cam_a = pdf_cam_to_light_a * e.pdf_l_far, pdf_light_to_cam_a * e.pdf_l_near
        merge_y = None
        if e is not None and self.mis.merge_everywhere:     # media: a merge at y, relative to a surface's
            merge_y = y.merge_factor(self.mis, c.media.info)
        w = self.mis.weight_connect(rec, sub.mis, pdf_cam_to_light_a, pdf_light_to_cam_a,
                                    pdf_l_rev_w, pdf_c_rev_w, merge_z, merge_y)
        self.add_layer(v_depth + 1, sub.depth + 1, contrib, w, ok)
        return dr.select(ok, contrib * w, 0.0)

    def emitter_edge(self, v, ds, ray, active):
        """The shadow ray ``ray`` from camera vertex ``v`` to the emitter sample ``ds`` through
        media: media_path.EdgeTerms (far end: the emitter point, a surface)."""
        c = self.ctx
        end = (ds.p, ds.n, c.emitters.error_at(ds))
        media = (v.medium_towards(ds.d), c.emitter_media.medium(ds.emitter, ds.p, ds.n, -ds.d, active))
        factors = (v.density_factor(c.media.info), media_path.surface_start(dr.width(ds.p)))
        return media_path.edge_terms(c, self.ps.sampler, ray, end, media, factors, active)

    @dr.syntax
    def connect_all(self, idx, v, sub, active, merge_z=True):
        """Sum of the connections of camera vertex ``v`` to the light subpath of its sample."""
        c, store = self.ctx, self.ps.store
        n_light, slot_of = store.count, store.slot    # read before the loop
        if self.ps.n_light != self.ps.n:              # (auto's lattice pilot: camera sample j, light subpath j)
            n_light = dr.gather(mi.UInt32, n_light, idx)
        # heterogeneous media: ratio tracking on each connection draws samples, so the sampler
        # must be loop state (without this name in the loop the LLVM backend aborts)
        sampler = self.ps.sampler if c.media is not None and c.media.info.heterogeneous else None
        # stored depths grow with j (depth_j >= j + 1): beyond j_end max_depth forbids all
        j_end = dr.minimum(n_light, mi.UInt32(c.max_depth_edges) - dr.minimum(sub.depth + 1, c.max_depth_edges))
        L = mi.Spectrum(0.0)
        j = mi.UInt32(0)
        # (v, sub and the rest are read, not changed: out of the loop state, as Dr.Jit would
        # otherwise take them out by recording the loop again: loops.py)
        while dr.hint(active & (j < j_end), label='bdpt_connect', exclude=[v, sub, active, idx, j_end]):
            L += self.strategy_st(slot_of(j, idx), j, v, sub, active, merge_z)
            j += 1
            sampler = sampler       # (named in the loop: its state is loop state)
        return L

    @dr.syntax
    def connect_cache(self, v, sub, active, merge_z=True):
        """Sum of the connections of camera vertex ``v`` to c vertices drawn uniformly from the
        pass's light vertex cache (light_cache.py), each weighted by V / (c n_L)."""
        cache, sampler = self.ps.cache, self.ps.sampler     # (named: the sampler is loop state)
        c, scale = cache.c, cache.scale
        if self.lanes is not None:      # per-pixel counts: c(p) draws, each weighted V / (c(p) n_L)
            c, scale = self.lanes.c, cache.scale_for(self.lanes.c)
        L = mi.Spectrum(0.0)
        j = mi.UInt32(0)
        while dr.hint(active & (j < c), label='bdpt_connect_cache'):
            slot, level, ok = cache.draw((sampler.next_1d(), sampler.next_1d()), active)
            L += self.strategy_st(slot, level, v, sub, ok, merge_z, scale)
            j += 1
        return L

    # ------------------------------------------------------------------ walk
    def first_hit(self):
        """The camera rays and their first hits: (film positions, ray, hit, the environment
        seen directly, alpha, the AOV values, the Subpath at the hit). Where the walk carries
        its hits as transport.PendingHit (transport.deferred) the hit is one, and the Subpath's
        MIS state waits for its event (transport.resolve, at the walk's first step)."""
        c = self.ctx
        n, max_edges = self.ps.n, c.max_depth_edges
        film_pos, ray, beta = self.primary()
        beta_lens = beta
        beta_start = None
        if c.see_through_emitters:       # (hide_emitters: the first edge passes emitter shapes)
            si = c.sampling.intersect(past_emitter_shapes(c, ray, True), True, primary=True)
        elif transport.deferred(c, self.mode):
            si = transport.PendingHit(c.sampling.preliminary(ray, True), c.camera.lens_point(ray))
        elif c.media is None:
            si = c.sampling.intersect(ray, True, primary=True)     # in solid angle: no edge factor
        else:       # distance sampling from the camera's medium (media_path.MediumHit)
            # (the roulette's reference before the step: a collision's weight holds 1 / sigma_t, a
            # length, which the scatter's sigma_s takes back out; as a reference it would make
            # the survival probability depend on the scene's scale)
            beta_start = dr.max(beta)
            si, beta, pdf_fwd_l, pdf_rev_l = media_path.sample_step(
                c, self.ps.sampler, ray, medium_at_sensor(c.sensor, n), media_path.surface_start(n), beta,
                dr.full(mi.Bool, True, n))
        valid = si.is_valid()
        if c.stats is not None:
            c.stats.ray('camera', dr.full(mi.Bool, True, n), valid)
        self.film_pos = film_pos
        L = mi.Spectrum(0.0)
        if self.ps.beams is not None and self.mis.merge_offered(False) is True:
            L += self.first_beam(ray, si, beta_lens, film_pos)
        if c.strategies.trace_env:
            L += self.strategy_s0_env(ray, dr.zeros(mi.Interaction3f, n), mi.UInt32(1), beta,
                                      MISState(mi.Float(0), mi.Float(0)), ~valid & (max_edges >= 1))
        alpha = dr.select(valid, 1.0, 0.0)
        aov_values = self.aov_values(self.surface(si, ray), ray) if c.aovs else ()
        if isinstance(si, transport.PendingHit):
            st = self.mis.camera_before_hit(c.camera.pdf_w(ray.d), n)
        else:   # the first edge's length as every other strategy measures it (from the lens point)
            dist2_cam = c.camera.first_edge_dist2(ray, si.p)
            cos_hit = dr.abs(dr.dot(si.n, ray.d)) if c.media is None else si.cos(ray.d)
            st = self.mis.camera_start(c.camera.pdf_w(ray.d), dist2_cam, cos_hit)
        if c.media is not None:
            st = self.mis.distance(st, pdf_fwd_l, pdf_rev_l)
        sub = Subpath(beta, dr.max(beta) if beta_start is None else beta_start, st, mi.UInt32(1),
                      valid & (max_edges >= 1))
        return film_pos, ray, si, L, alpha, aov_values, sub

    def surface(self, hit, ray):
        """The surface interaction of the first hit ``hit`` of ``ray`` (for the AOVs)."""
        if isinstance(hit, transport.PendingHit):
            return self.ctx.sampling.resolve(hit.pi, ray, True)
        return hit if self.ctx.media is None else hit.si

    def first_beam(self, ray, hit, beta, film_pos):
        """Merges along the camera ray's segment through media (beams.py; where a merge at the
        first camera vertex is a strategy): ``beta``, the ray's weight, and the camera's MIS
        state before the first edge."""
        c, n = self.ctx, self.ps.n
        d_vcm, d_vc = self.mis.camera_init(c.camera.pdf_w(ray.d))
        zero = dr.zeros(mi.Float, n)
        st = MISState(d_vcm + zero, d_vc + zero, zero, zero, zero)
        sub = Subpath(beta, mi.Float(1.0), st, dr.zeros(mi.UInt32, n), dr.full(mi.Bool, True, n))
        seg = Segment(None, ray, medium_at_sensor(c.sensor, n), self.segment_end(ray, hit), sub, True)
        active = sub.active if self.lanes is None else sub.active & self.lanes.merge
        return self.ps.beams.gather(dr.arange(mi.UInt32, n), seg, active, film_pos)

    @staticmethod
    def segment_end(ray, hit):
        """Where the segment of ``ray`` that found the MediumHit ``hit`` ends (inf: nowhere)."""
        return dr.select(hit.is_valid(), dr.norm(hit.p - ray.o), dr.inf)

    segments = property(lambda self: self.ps.beams is not None)     # (transport.walk)

    def segment(self, v, ray, hit, scattered, carry, was_delta):
        """Merges along the segment from ``v`` to ``hit`` (beams.py), where a merge at a vertex
        behind ``v`` is a strategy; ``scattered``: the Subpath after the scatter at ``v``."""
        L, prev, prev_delta = carry
        offered = self.mis.merge_offered(was_delta)
        active = scattered.active if offered is True else scattered.active & offered
        if self.lanes is not None:
            active = active & self.lanes.merge
        seg = Segment(v, ray, v.medium_towards(ray.d), self.segment_end(ray, hit), scattered, False)
        # (in a branch, as the merges at vertices: behind delta vertices only, few packets gather)
        gathered = where(self.ctx, active, lambda: self.ps.beams.gather(self.idx, seg, active, self.film_pos),
                         'bdpt_beam_gather')
        return L + gathered, prev, prev_delta

    mode = RADIANCE
    label = 'bdpt_camera_subpath'

    def trace(self):
        """Trace the pass's camera subpaths, evaluate every camera-side strategy at each vertex
        and put the samples on the film."""
        ps = self.ps
        if self.ctx.pixel_counts is not None:   # (before any weight: the first hit's s=0 has one)
            self.lanes = PixelLanes(self.ctx.pixel_counts, ps)
            self.mis.eval_counts = self.lanes.counts
        film_pos, ray, si, L, alpha, aov_values, sub = self.first_hit()
        wavelengths = ray.wavelengths
        self.idx = dr.arange(mi.UInt32, ps.n)
        prev = dr.zeros(mi.Interaction3f, ps.n)          # previous camera vertex (depth > 1)
        prev_delta = dr.zeros(mi.Bool, ps.n)             # it scattered through a delta lobe (the camera: no)
        _, _, (L, _, _) = transport.walk(self.ctx, self.mis, ps.sampler, self, si, ray, sub, (L, prev, prev_delta))
        ps.film.put_camera(film_pos, L, alpha, mi.Bool(True), wavelengths, aov_values)

    def trace_first_hits(self):
        """Technique lt's camera samples: no radiance (its light image holds it all), only the
        film's alpha and AOVs at each sample's first hit, as ``path`` writes them."""
        film_pos, ray, _, _, alpha, aov_values, _ = self.first_hit()
        self.ps.film.put_camera(film_pos, mi.Spectrum(0.0), alpha, mi.Bool(True), ray.wavelengths, aov_values)

    def go_on(self, sub, carry):
        return sub.active

    def vertex(self, si, ray):
        if self.ctx.media is None:
            return Vertex.at(self.ctx, si, ray)
        return media_path.PathVertex.at(self.ctx, si, ray)

    def at_vertex(self, v, ray, sub, carry):
        """At camera vertex z: the hit (s=0), emitter sampling (s=1), the connections (s >= 2)
        and the merges. ``carry``: (radiance so far, the previous vertex, whether it was delta)."""
        c, ps, mis = self.ctx, self.ps, self.mis
        L, prev, prev_delta = carry
        if c.strategies.trace_s0:
            L = L + self.strategy_s0(v, ray, prev, sub)
        sub.active = sub.active & (sub.depth + 1 <= c.max_depth_edges)     # every strategy below adds an edge
        smooth = sub.active & v.smooth(c.diffuse)
        merge_here = mis.merge_here_camera(prev_delta)   # a merge at v is a strategy (mis.py)
        merge_mask = mis.merge_offered(prev_delta)       # and the camera gathers there
        if c.media is not None and mis.mis_merges:       # media: relative to a surface merge
            merge_here = v.merge_factor(mis, c.media.info, merge_here)
        if c.strategies.trace_s1:
            L = L + self.strategy_s1(v, sub, smooth, merge_here)
        if c.strategies.trace_connect and ps.cache is not None:
            L = L + self.connect_cache(v, sub, smooth, merge_here)
        elif c.strategies.trace_connect:
            L = L + self.connect_all(self.idx, v, sub, smooth, merge_here)
        if c.strategies.trace_merge:
            if ps.beams is not None:      # inside media the segments merge (beams.py, ``segment``)
                merge_mask = merge_mask & ~v.in_medium
            if self.lanes is not None:    # per-pixel counts: merges where the pixel's map has them
                merge_mask = merge_mask & self.lanes.merge
            # in a branch: where few lanes merge (the default merge set, behind delta vertices),
            # most packets skip the cells' lookup (on the sun room 0.29 s of the camera kernel
            # against 0.22 without the gather, 256 x 256 at 8 spp)
            gathers = smooth & merge_mask
            L = L + where(c, gathers, lambda: ps.merger.gather(self.idx, v, sub, gathers, self.film_pos, merge_here),
                          'bdpt_merge_gather')
        return sub, (L, prev, prev_delta), merge_here

    def after_step(self, ray, si, v, sub, carry, was_delta):
        """After the scatter at ``v``: the environment where the ray left the scene (s=0)."""
        L, _, _ = carry
        prev = mi.Interaction3f(v.si)
        if self.ctx.strategies.trace_env:
            escaped = sub.active & ~si.is_valid()
            L = L + where(self.ctx, escaped, lambda: self.strategy_s0_env(ray, prev, sub.depth + 1, sub.beta,
                                                                          sub.mis, escaped), 'bdpt_s0_env')
        return L, prev, was_delta


def camera_pixels(ps):
    """The crop pixel of each camera sample of pass ``ps``: spp_pass consecutive samples a pixel
    from pixel_start (every pixel_stride-th pixel in technique auto's pilot of a large crop:
    integrator.lattice_step; every pixel_stride-th row in its timed trials: the run j // run of
    ``pixel_run`` pixels starts at pixel (j // run) run stride + pixel_offset)."""
    pixel = dr.arange(mi.UInt32, ps.n) // dr.opaque(mi.UInt32, ps.spp_pass) + dr.opaque(mi.UInt32, ps.pixel_start)
    if ps.pixel_stride == 1:
        return pixel
    if ps.pixel_run == 1:
        return pixel * ps.pixel_stride
    run = dr.opaque(mi.UInt32, ps.pixel_run)
    return pixel // run * (run * ps.pixel_stride) + pixel % run + dr.opaque(mi.UInt32, ps.pixel_offset)


class PixelLanes:
    """The camera lanes' per-pixel counts (pixel_counts.py), one field a line."""

    def __init__(self, pixel_counts, ps):
        pixel = camera_pixels(ps)
        self.c = pixel_counts.c_at(pixel)                       # cached vertices each camera vertex draws
        self.merge = pixel_counts.merge_at(pixel)               # whether it merges
        self.counts = pixel_counts.counts(pixel, ps.vpp, ps.n_lt)   # (n_c, n_lt, n_m) of its MIS
