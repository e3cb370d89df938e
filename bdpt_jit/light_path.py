"""Light subpaths: emission from any emitter kind (endpoints.EmitterTable), importance
transport through the scene, the light image (t=1: every light vertex connected to the camera
and splatted; s=1,t=1: the emitter vertex itself), and the vertices that camera subpaths
connect to (s>=2), written to the light-vertex store (store.LightStore)."""

import drjit as dr
import mitsuba as mi

from . import media_path, transport
from .film import NearestPixel
from .jitmath import pdf_w_to_a, safe_div
from .media import medium_at_sensor
from .rays import spawn_to
from .transport import Subpath
from .vertex import IMPORTANCE, Vertex, past_emitter_shapes, visibility, visible


class LightTracer:
    """Traces the light subpaths of one pass (``ps``: passes.PassState) in the shared context."""

    def __init__(self, ctx, ps):
        self.ctx, self.ps = ctx, ps
        self.mis = ps.mis_light if ps.mis_light is not None else ps.mis
        # spectral variants: the wavelengths' sampling weight. It enters the splats (t=1) only:
        # the camera subpath of the same sample carries it already, and a connection multiplies
        # both throughputs
        self.wl_weight = ps.spectral[1] if ps.spectral is not None else 1.0
        self.sampler = ps.light_sampler     # the pass's sampler (the light vertex cache: its own)
        self.n = ps.n_light                 # light subpaths: one per camera sample, or n_L (cache)
        self.splat_scale = ps.splat_scale if ps.splat_scale is not None else ctx.splat_scale
        self.splats = not ps.pilot          # a pilot pass (light_cache.pilot) only stores vertices
        # per-pixel counts (pixel_counts.py): the crop pixel a splat lands in
        self.pixels = NearestPixel(ctx.sensor.film()) if ctx.pixel_counts is not None else None

    # ------------------------------------------------------------------ emission
    def start(self):
        """Emission and the first hit y1: (y1, the Subpath there). The sample's wavelengths
        (spectral variants) are the pass state's: its camera subpath carries the same ones."""
        c, ps = self.ctx, self.ps
        sampler = self.sampler
        active = dr.full(mi.Bool, True, self.n)
        u_sel, u_pos, u_dir = sampler.next_1d(), sampler.next_2d(), sampler.next_2d()
        wl = ps.spectral[0] if ps.spectral is not None else None
        e = c.sampling.sample_emission(u_sel, u_pos, u_dir, active, wl)
        active = e.active

        # ---------------- s=1, t=1: the emitter vertex y0 seen by the camera ----------------
        u_cam = sampler.next_2d()
        if self.splats and c.strategies.trace_splat_y0 and e.kinds.area is not False:      # only surfaces can be seen directly
            self.strategy_s1_t1(u_cam, e, e.active_y0 & e.kinds.area)

        active &= c.max_depth_edges >= 2
        if c.media is None:
            si = c.sampling.intersect(e.ray, active)
            beta, si = c.sampling.first_hit(e, si, u_dir, active)
            y1 = si
        else:       # distance sampling from the emitter's medium (media_path.MediumHit)
            si, beta, pdf_fwd_l, pdf_rev_l = media_path.sample_step(
                c, sampler, e.ray, c.emitter_media.medium(e.emitter, e.ps.p, e.ps.n, e.d, active),
                media_path.surface_start(self.n), e.beta, active)
            y1 = si.interaction()
        if c.stats is not None:
            c.stats.ray('light', active, si.is_valid())
        active &= si.is_valid()
        pdf_direct = c.emitters.pdf_direct_first_hit(e, y1, active)
        cos_hit = dr.abs(dr.dot(si.n, e.ray.d)) if c.media is None else si.cos(e.ray.d)
        dist2 = c.emitters.first_edge_dist2(e, y1)
        st = self.mis.light_start(e.pdf_emit_w, e.cos_e, e.kinds.delta, pdf_direct, dist2, cos_hit)
        if c.media is not None:
            st = self.mis.distance(st, pdf_fwd_l, pdf_rev_l)
        # (media: the roulette's reference before the first step, camera_path.CameraTracer.first_hit)
        beta_start = dr.max(beta) if c.media is None else dr.max(e.beta)
        return si, Subpath(beta, beta_start, st, dr.full(mi.UInt32, 1, self.n), active)

    # ------------------------------------------------------------------ strategies
    def add_layer(self, s, t, film_pos, weighted, unweighted, active):
        """A splat's sample in the strategy layers (parameter strategy_images) and the moment
        estimation's film (moments.py)."""
        c = self.ctx
        if c.layers is not None:
            c.layers.add(s, t, film_pos, weighted, unweighted, active)
        if c.moments is not None:
            c.moments.add(s, t, film_pos, weighted, unweighted, active)

    def strategy_s1_t1(self, u, e, active):
        """s=1, t=1: the emitter vertex y0 connected to the camera."""
        c = self.ctx
        si_e, ps = e.si_e, e.ps
        ds, sensor_w = c.sensor.sample_direction(si_e, u, active)
        ok = active & (ds.pdf > 0) & c.camera.between_clip_planes(ds)
        cos_g = dr.dot(ps.n, ds.d)                            # emitter normal towards camera
        si_to_cam = mi.SurfaceInteraction3f(si_e)
        si_to_cam.wi = si_e.to_local(ds.d)
        le = e.emitter.eval(si_to_cam, ok)
        front = cos_g > 0
        if c.emitters.smooth is not None:   # (smooth-shaded meshes also emit behind their triangles)
            front |= c.emitters.smooth.rank(e.emitter, ok)[1]
        ok &= front & (dr.max(le) > 0)
        ray = spawn_to((ps.p, ps.n, e.err), (c.camera.near_point(ds), mi.Normal3f(0.0), 0.0), ps.time,
                       c.offsets.far_rel, si_e.wavelengths)
        et = self.camera_edge(ray, ds, ((ps.p, ps.n, e.err), c.emitter_media.medium(e.emitter, ps.p, ps.n, ds.d, ok)),
                              None, ok) if c.media is not None else None
        tr = visibility(c, t1_shadow_ray(c, ray, ds, (ps.p, ps.n, e.err), si_e), ok) if et is None else et.tr
        ok &= visible(tr)
        pdf_light_a = e.pdf_light_a
        pdf_cam_a = pdf_w_to_a(c.camera.pdf_w(-ds.d), cos_g, dr.square(ds.dist))  # We |cos| / d^2
        if et is not None:      # media: the camera subpath reaches y0 (a surface) with the edge's T
            pdf_cam_a = pdf_cam_a * et.pdf_l_near
        self.pixel_counts_at(ds.uv, ok)
        w = self.mis.weight_s1t1(pdf_cam_a, pdf_light_a)
        value = le * tr * dr.abs(cos_g) * (sensor_w * safe_div(1.0, pdf_light_a)) * self.splat_scale
        if not isinstance(self.wl_weight, float):
            value = value * self.wl_weight
        self.ps.film.put_splat(ds.uv, value * w, ok, si_e.wavelengths)
        self.add_layer(1, 1, ds.uv + c.camera.crop_offset, value * w, value, ok)

    def pixel_counts_at(self, uv, active):
        """Per-pixel counts (pixel_counts.py): the weight formed next is a splat's at film position
        ``uv``, whose pixel's counts it takes."""
        c = self.ctx
        if self.pixels is not None:         # (the pixel add_layer's position lands in)
            pixel, inside = self.pixels.index(uv + c.camera.crop_offset, active)
            self.mis.eval_counts = c.pixel_counts.counts(pixel, self.ps.vpp, self.ps.n_lt, inside)

    def strategy_t1(self, v, sub, active, scatters):
        """t=1 (s >= 2): the light vertex ``v`` connected to the camera and splatted to the
        light image (``scatters``: the lanes that scatter at ``v`` next: Vertex.eval_and_draw)."""
        c = self.ctx
        si = v.si
        ds, sensor_w = c.sensor.sample_direction(si, self.sampler.next_2d(), active)
        ok = active & (ds.pdf > 0) & c.camera.between_clip_planes(ds)
        if c.fuse_draw and not c.exact_adjoint:     # with the scatter's BSDF sample
            f, _, valid = v.eval_and_draw(c, ds.d, IMPORTANCE, self.sampler, scatters | ok)
            pdf_rev_w = v.pdf_rev_w(c, ds.d, IMPORTANCE, ok & valid)
        else:
            f, _, pdf_rev_w, valid = v.eval(c, ds.d, IMPORTANCE, ok)
        ok &= valid & (dr.max(f) > 0)
        ray = v.spawn_to(c, c.camera.near_point(ds), mi.Normal3f(0.0), 0.0)
        et = self.camera_edge(ray, ds, (v.end(), v.medium_towards(ds.d)), v, ok) if c.media is not None else None
        if c.see_through_emitters:      # camera rays pass emitters' shapes: never end on one
            ok &= ~si.shape.is_emitter()
            tr = visibility(c, past_emitter_shapes(c, t1_shadow_ray(c, ray, ds, (si.p, si.n, v.err), si), ok), ok)
        else:
            tr = visibility(c, t1_shadow_ray(c, ray, ds, (si.p, si.n, v.err), si), ok) if et is None else et.tr
        ok &= visible(tr)
        if et is None:
            pdf_cam_a = pdf_w_to_a(c.camera.pdf_w(-ds.d), dr.dot(si.n, ds.d), dr.square(ds.dist))
        else:       # media: the camera subpath reaches y with the edge's distance density there
            pdf_cam_a = pdf_w_to_a(c.camera.pdf_w(-ds.d), v.cos(ds.d), dr.square(ds.dist)) * et.pdf_l_near
        merge_y = v.merge_factor(self.mis, c.media.info) if et is not None and self.mis.merge_everywhere else None
        self.pixel_counts_at(ds.uv, ok)
        w = self.mis.weight_t1(sub.mis.d_vcm, sub.mis.d_vc, pdf_cam_a, pdf_rev_w, merge_y)
        value = sub.beta * f * tr * sensor_w * self.splat_scale
        if not isinstance(self.wl_weight, float):
            value = value * self.wl_weight
        self.ps.film.put_splat(ds.uv, value * w, ok, si.wavelengths)
        self.add_layer(sub.depth + 1, 1, ds.uv + c.camera.crop_offset, value * w, value, ok)

    def camera_edge(self, ray, ds, y, v, active):
        """The edge between the camera point ``ds`` and the light subpath's vertex y through media
        (``ray``: the shadow ray from y; ``y``: (y's (p, n, err), its medium towards the camera);
        ``v``: y as a media_path.PathVertex, or None: the emitter point): media_path.EdgeTerms,
        its near end y. In a scene with media it is walked from the camera, as the camera
        subpaths' first segments (and Mitsuba's volpath's camera rays) see it: in the sensor's
        medium, changing at medium transitions; a y on a medium transition, or on the emitter,
        takes the medium the walk arrives in, any other y must be in it, else the edge is not
        made. Where the media are declared consistently a walk from y finds the same edge; where
        not (a sensor in a fog it does not declare: bdpt was 5% dark against volpath there, lt
        black; a light across a boundary), the splats follow the camera subpaths. It is walked
        from y, as before, without media (Null lobes only) and in consistently declared scenes
        with shapes whose hits are inexact (curves, SDF grids, shapes in instances), where a walk
        from the camera can meet y's own surface first (a hair fibre's far side: lt 1.6% dark;
        a quadric inside an instance); the walk from y passes it."""
        c = self.ctx
        n = dr.width(ds.p)
        y_end, medium_y = y
        cam = (c.camera.near_point(ds), mi.Normal3f(0.0), mi.Float(0.0))
        near = v.density_factor(c.media.info) if v is not None else media_path.surface_start(n)
        inexact = c.offsets.coarse or c.offsets.one_sided
        if not c.media.info.any or (inexact and c.emitter_media.consistent):
            return media_path.edge_terms(c, self.sampler, ray, cam, (medium_y, medium_at_sensor(c.sensor, n)),
                                         (near, media_path.surface_start(n)), active)
        check = False if v is None else v.in_medium | ~v.surf.si.is_medium_transition()
        back = spawn_to(cam, y_end, ray.time, c.offsets.far_rel, ray.wavelengths)
        et = c.media.edge(back, y_end, medium_at_sensor(c.sensor, n), self.sampler, active, medium_y, check=check)
        if c.stats is not None:
            c.stats.shadow(active, ~et.ok)
        return media_path.EdgeTerms(et.tr, et.pdf_l(media_path.surface_start(n)), et.pdf_l(near))

    # ------------------------------------------------------------------ walk
    mode = IMPORTANCE
    label = 'bdpt_light_subpath'
    segments = False            # (transport.walk: no beams on this side)

    def trace(self):
        """Trace the pass's light subpaths; splat the t=1 strategies; fill the pass's store.
        With a growable storage (max_depth -1) lanes whose storage is full pause, the storage
        grows, and the walk resumes."""
        c, store = self.ctx, self.ps.store
        si, sub = self.start()
        ray = dr.zeros(mi.Ray3f, self.n)                # (the walk's ray: not read on this side)
        self.idx = dr.arange(mi.UInt32, self.n)
        count = dr.zeros(mi.UInt32, self.n)
        while True:
            self.cap_eff = store.capacity if store is not None and c.unbounded else 0xFFFFFFFF
            si, sub, (count,) = transport.walk(c, self.mis, self.sampler, self, si, ray, sub, (count,))
            if store is None:
                break
            store.count = count
            if not c.unbounded or not dr.any(sub.active):
                break
            store.grow()             # lanes paused on a full storage resume with more levels

    def go_on(self, sub, carry):
        return sub.active & (carry[0] < self.cap_eff)

    def vertex(self, si, ray):
        if self.ctx.media is None:
            return Vertex.at(self.ctx, si)
        return media_path.PathVertex.at(self.ctx, si)

    def at_vertex(self, v, ray, sub, carry):
        """At light vertex y_depth: store it (s >= 2, t >= 2) and splat it (t=1)."""
        c, store = self.ctx, self.ps.store
        (count,) = carry
        max_edges = c.max_depth_edges
        smooth = v.smooth(c.diffuse)
        if store is not None:
            # a stored vertex is followed by an edge and a camera vertex (connections) or by a
            # camera vertex at the same place (merges)
            store_edges = 1 if c.strategies.trace_merge else 2
            do_store = sub.active & smooth & (sub.depth + store_edges <= max_edges)
            store.record.store(store.v, store.record.make(v, sub), store.slot(count, self.idx), do_store)
            count = count + dr.select(do_store, 1, 0)
        scatters = sub.active & (sub.depth + 2 <= max_edges)
        if self.splats and c.strategies.trace_splat:
            self.strategy_t1(v, sub, sub.active & smooth & (sub.depth + 1 <= max_edges), scatters)
        sub.active = scatters
        if c.media is not None and self.mis.mis_merges:
            return sub, (count,), v.merge_factor(self.mis, c.media.info)
        return sub, (count,), True

    def after_step(self, ray, si, v, sub, carry, was_delta):
        return carry


def t1_shadow_ray(ctx, ray, ds, end, si):
    """The shadow ray of a t=1 connection: ``ray`` (from the vertex ``end`` = (p, n, err) to the
    camera's point ``ds.p``), or in a scene with curves the same segment traced from the camera,
    as camera rays and the other connections see the scene. Mitsuba culls the faces of curves
    that a ray meets from inside, and a B-spline strand's ends are open, so visibility there
    depends on the direction (rays.CULLED_SHAPES): traced from the vertex, lt was a tenth of pt
    on an open tube. Elsewhere the vertex end leaves its surface by its error bound and the
    far stop (rays.RayOffsets.far_rel) lies at the camera: traced from the camera, a vertex on
    a quadric inside an instance was hidden by its own surface (-0.5%)."""
    if not ctx.offsets.one_sided:
        return ray
    return spawn_to((ctx.camera.near_point(ds), mi.Normal3f(0.0), 0.0), end, si.time, ctx.offsets.far_rel,
                    si.wavelengths)
