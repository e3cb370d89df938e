"""The ``bdpt`` integrator plugin: bidirectional path tracing with every (s,t) strategy.

A render flows through the modules in this order: the settings (params.py) and the scene
(scene_check.py) make a Context (context.py: the camera model, the emitter table, the
strategy set, the MIS weights); the render is cut into passes (passes.py); each pass traces
the light subpaths (light_path.py: splats to the light image, vertices into store.py) and
then the camera subpaths (camera_path.py: hits, emitter sampling, connections), both
evaluating vertices with connect.py and weighting with mis.py; the film (film.py) develops
the camera image plus the light image."""

import math
import time as _time

import drjit as dr
import mitsuba as mi

from . import params as P
from .camera_path import CameraTracer
from .context import Context
from .film import FilmAccumulator
from .light_cache import PILOT_PASS, PILOT_PATHS, LightCache, counts as cache_counts, pilot
from .light_path import LightTracer
from .beams import BeamGather, BeamGrid, beam_cap
from .merge import MergeSchedule, Merger, PhotonGrid
from .passes import (BYTES_PER_LIGHT_VERTEX, BYTES_PER_SAMPLE, PassState, RenderHooks, caused_by_interrupt,
                     count_passes, light_capacity, pass_sampler, pixel_sampler, plan_passes)
from .gradients import check_parameters, geometry_keys
from .jit_guard import held
from .scene_check import check_scene, check_variant, describe_medium
from .store import LightStore

LATTICE_PASS = 1 << 25          # pass_seed index of a lattice pilot's camera samples (lattice_pass_state)
AD_BYTES_FACTOR = 8             # a differentiable pass holds its AD graph: passes this much smaller


class AutoRender:
    """What the segments of a technique-auto render share (BDPTIntegrator.render_auto), one
    field a line."""

    def __init__(self, scene, sensor, seed, spp, n_pixels, evaluate):
        self.scene = scene              # the scene rendered
        self.sensor = sensor            # its sensor
        self.seed = seed                # the caller's seed (segment k: plus k auto.SEGMENT_SEED)
        self.spp = spp                  # the caller's samples per pixel, all segments together
        self.n_pixels = n_pixels        # the crop's pixels
        self.evaluate = evaluate        # mi.render's evaluate


class BDPTIntegrator(mi.SamplingIntegrator):
    __doc__ = None  # set below from the parameter table

    def __init__(self, props=None):
        check_variant()
        self.settings = P.parse_properties(props if props is not None else {})
        # The base class would read Mitsuba's own (deprecated) 'samples_per_pass' and warn;
        # every parameter is read from the table above instead.
        super().__init__(mi.Properties())
        s = self.settings
        self.max_depth = s['max_depth']
        self.rr_depth = s['rr_depth']
        self.technique = s['technique']
        self.mis_kind = s['mis']
        self.hide_emitters = s['hide_emitters']
        self.samples_per_pass = s['samples_per_pass']
        self.aov_channels = P.aov_channel_names(P.parse_aovs(s['aovs']))   # the film's extra channels
        self.strategy_images = None     # after a render with strategy_images: the layers (dict)
        self.hooks = RenderHooks()      # progress and stopping between passes (passes.RenderHooks)
        self.merge_iteration = 0        # vcm, vm: iterations (samples per pixel) so far, over every render (merge.py)
        self.last_merge_radius = None   # the last pass's merging radius (world units)
        self.last_beam_paths = None     # and the light subpaths an iteration its beams gathered from
        self.last_render_info = {}
        self.cache_run = None           # the light vertex cache's (V / n_L of the pilot, c) for this render
        self.moment_counts = None       # technique auto's pilot: the candidates' (n_c, n_lt) (moments.py)
        self.moment_film = None         # its moments.MomentFilm after a render
        self.pixel_counts = None        # technique auto's per-pixel candidate: pixel_counts.PixelCounts
        self.last_chosen = None         # technique auto: the integrator of its last decision (renders on without choosing)
        self.trial_stride = 1           # technique auto's timed trial of a large crop: camera samples every k-th row (auto.trial_stride)
        self.trial_row = 0              # from this row (0 .. k - 1)

    # ------------------------------------------------------------------ setup
    def make_context(self, scene, sensor, spp=1) -> Context:
        check_scene(scene, sensor)
        settings = self.settings
        if settings['technique'] == 'auto':       # its candidates are bdpt's configurations
            settings = {**settings, 'technique': 'bdpt'}
        ctx = Context(scene, sensor, settings, spp)
        if self.moment_counts is not None:        # technique auto's pilot (moments.py)
            from .moments import instrument
            self.moment_film = instrument(ctx, self.moment_counts)
        if self.pixel_counts is not None:         # technique auto's per-pixel candidate
            self.per_pixel(ctx, sensor)
        return ctx

    def per_pixel(self, ctx, sensor):
        """Context ``ctx`` made to render with self.pixel_counts (pixel_counts.py): its weights
        moments.FamilyMIS's under the render's heuristic, dotted with each lane's pixel's counts,
        its stored records carrying the families."""
        from .moments import FamilyMIS, family_record
        crop = sensor.film().crop_size()
        if ctx.light_cache is None or ctx.ad or self.pixel_counts.pixels != int(crop[0]) * int(crop[1]):
            raise ValueError('bdpt: per-pixel counts need the light vertex cache (light_paths), no '
                             'derivatives and a map of the crop\'s pixels')
        ctx.mis = FamilyMIS(ctx.strategies, kind=self.settings['mis'], merge_everywhere=ctx.mis.merge_everywhere)
        ctx.record = family_record(ctx.record)
        ctx.pixel_counts = self.pixel_counts

    def light_capacity(self, ctx: Context) -> int:
        return light_capacity(ctx.strategies, ctx.max_depth_edges, ctx.unbounded)

    def bytes_per_sample(self, ctx: Context) -> int:
        ratio = ctx.light_cache.ratio if ctx.light_cache is not None else 1.0   # light subpaths a sample
        return BYTES_PER_SAMPLE + int(BYTES_PER_LIGHT_VERTEX * self.light_capacity(ctx) * ratio)

    def start_cache(self, ctx, seed, light_paths):
        """The light vertex cache's pilot (light_cache.pilot; at most the render's ``light_paths``)
        and the connections c it implies (parameter connections -1: the pilot's vertices per light
        subpath, rounded, at least 1)."""
        if ctx.light_cache is None:
            self.cache_run = None
            return
        vpp = pilot(self, ctx, seed, light_paths) if ctx.strategies.trace_connect else 0.0
        c = ctx.light_cache.connections
        self.cache_run = (vpp, c if c > 0 else max(1, int(round(vpp))))

    # ------------------------------------------------------------------ render
    @held
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not develop:
            raise NotImplementedError(
                "bdpt: render(develop=False) is not supported: bdpt develops the camera image and "
                "the light image together (call it with develop=True)")
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if spp == 0:
            spp = sensor.sampler().sample_count()
        if self.technique == 'auto':
            return self.render_auto(scene, sensor, seed, spp, evaluate)
        ctx = self.make_context(scene, sensor, spp)
        acc = FilmAccumulator(sensor.film(), ctx.aov_names)
        crop = sensor.film().crop_size()
        n_pixels = int(crop[0]) * int(crop[1])
        if ctx.light_cache is not None:
            paths = max(256, int(ctx.light_cache.ratio * spp * n_pixels))
            if self.trial_stride > 1:   # (a trial's kernels count k times, auto.lattice_weight: its pilot's too)
                paths = max(256, min(paths, PILOT_PATHS) // self.trial_stride)
            self.start_cache(ctx, seed, paths)
        t0 = _time.perf_counter()
        samples_done, interrupted, levels_used = self.run_passes(ctx, acc, seed, spp, n_pixels)
        # Each light path splatted 1/spp; if the render stopped early, fewer light paths were
        # traced than that scale assumes (camera samples are normalised per pixel anyway).
        light_scale = spp * n_pixels / samples_done if samples_done else 1.0
        image = acc.develop(light_scale)
        if evaluate:
            dr.eval(image)
        self.strategy_images = ctx.layers.images(light_scale) if ctx.layers is not None else None
        self.last_render_info = self.render_info(ctx, spp, n_pixels, samples_done, interrupted, levels_used)
        self.last_render_info['time_s'] = _time.perf_counter() - t0
        return image

    def render_auto(self, scene, sensor, seed, spp, evaluate):
        """technique 'auto' (auto.py): a pilot's moment estimates and timed trials choose a
        configuration, which renders. A long render (a --time one too) decides again as it goes
        (auto.segment_spp): each segment renders with the configuration chosen before it, from
        pilots that share no sample with it, and the image is the segments' images combined
        with auto.segment_weights."""
        from . import auto
        governs = [auto.horizon(spp, 0)]        # the spp the next decision governs
        make = self.auto_factory(governs)
        t0 = _time.perf_counter()
        ctx = self.make_context(scene, sensor, spp)
        crop = sensor.film().crop_size()
        n_pixels = int(crop[0]) * int(crop[1])
        vpp, vpp_merging = self.auto_vertices(make, ctx, seed, n_pixels)
        best, trials = auto.choose(make, ctx, scene, sensor, seed, vpp, vpp_merging)
        cut = [make.cut_short]                  # (each decision: a timing left out at the caller's decision_over)
        self.hooks.decided()
        decided_s, render_s, segments = _time.perf_counter() - t0, 0.0, []
        job = AutoRender(scene, sensor, seed, spp, n_pixels, evaluate)
        took = [decided_s]                      # each decision's seconds
        while True:
            done = sum(seg['spp'] for seg in segments)
            own = [seg for seg in segments if seg['trial'] is best]       # wall seconds per spp with best
            per_spp = sum(seg['seconds'] for seg in own) / sum(seg['spp'] for seg in own) if own else None
            n = auto.segment_spp(best, render_s, decided_s, spp - int(round(done)), len(segments) + 1, per_spp)
            t1 = _time.perf_counter()
            segments.append(self.auto_segment(make(best.settings, best.pixel_counts), best, job, len(segments), n, done))
            segments[-1]['seconds'] = _time.perf_counter() - t1
            render_s += segments[-1]['seconds']
            if done + n >= spp or segments[-1]['info']['interrupted']:     # all rendered, or stopped
                break
            if self.hooks.stop():               # the stop rule, as between passes
                segments[-1]['info']['interrupted'] = True
                break
            t1 = _time.perf_counter()
            rendered = int(round(sum(seg['spp'] for seg in segments)))
            governs[0] = auto.horizon(spp - rendered, rendered)
            make.cut_short = False
            best = auto.rechoose(make, trials, scene, sensor, seed, len(segments))
            cut.append(make.cut_short)
            self.hooks.decided()
            took.append(_time.perf_counter() - t1)
            decided_s += took[-1]
        image = self.combine_segments(segments, spp, n_pixels)
        self.last_render_info['auto'] = {'chosen': best.name, 'pilot_spp': auto.pilot_spp(sensor), 'trial_spp': auto.trial_spp(sensor),
                                         'trial_s': decided_s, 'vertices_per_light_path': vpp, 'vertices_per_merging_light_path': vpp_merging,
                                         'decisions_cut': sum(cut),
                                         # (relmse_1spp: the v the segment's weight used; a per-pixel candidate
                                         # is built again at each decision, so 'candidates' may list a later one)
                                         'decisions': [{'chosen': seg['trial'].name, 'seconds': t, 'spp': seg['spp'],
                                                        'relmse_1spp': seg['trial'].rel_var, 'weight': seg['weight']}
                                                       for seg, t in zip(segments, took)],
                                         'candidates': [tr.report() for tr in trials],
                                         'cost_model': auto.cost_fit(trials)}
        return image

    def auto_factory(self, governs):
        """technique auto's ``make(settings, pixel_counts=None)``: an integrator of the candidate
        configuration ``settings``, this one's other settings kept, its merges' iteration count
        that of the samples per pixel the decision governs (``governs[0]``, updated by the
        caller); ``make.decision_over``: the render's hook (auto.out_of_time)."""
        from . import auto
        base = {k: v for k, v in self.settings.items() if v is not None}

        def make(settings, pixel_counts=None):
            integ = BDPTIntegrator({**base, 'technique': 'bdpt', **settings})
            integ.pixel_counts = pixel_counts
            # pilots and trials at the radius of the iterations the decision governs (merge.py:
            # it shrinks with them; auto.pilot_iteration), not at the next one's (a segment's
            # integrator is given the render's own count: auto_segment)
            integ.merge_iteration = auto.pilot_iteration(self.merge_iteration, governs[0], self.settings['radius_alpha'])
            return integ
        make.decision_over = self.hooks.decision_ends
        make.cut_short = False                  # (auto.out_of_time)
        return make

    def auto_vertices(self, make, ctx, seed, n_pixels):
        """technique auto's stored vertices per light subpath (light_cache.pilot, at least 256
        light subpaths): (the plain caches', the merging caches' or None where none is offered),
        each from a cache of its own kind, as its renders measure it (start_cache; with the
        render's seed, the same light subpaths). A merging cache's light subpaths also store the
        vertices only a merge can use (the caustic at 16 x 16, max_depth 4: 1.18 against 0.97
        with one seed; the Cornell box 2.05 against 1.45), and its connections draw among all of
        them (n_c = c / V, auto.candidates)."""
        from . import auto
        if not ctx.strategies.trace_connect or mi.is_spectral:     # (no caches in spectral variants)
            return 0.0, None
        kinds = [{}] + ([{'technique': 'vcm', 'merge_everywhere': True}] if auto.offers_merging(ctx) else [])
        out = []
        for kind in kinds:
            integ = make({**kind, 'light_paths': 1.0, 'connections': 1})
            out.append(pilot(integ, integ.make_context(ctx.scene, ctx.sensor), seed, max(256, n_pixels)))
        return out[0], (out[1] if len(out) > 1 else None)

    def auto_segment(self, chosen, trial, job, k, spp, spp_before):
        """Segment ``k`` of the auto render ``job`` (an AutoRender): ``spp`` samples per pixel of
        the ``chosen`` integrator (``trial``'s configuration), seeded with seed + k
        auto.SEGMENT_SEED (segment 0: the caller's seed), its progress reported after the
        ``spp_before`` of earlier segments."""
        from .auto import SEGMENT_SEED
        offset, total = int(round(spp_before * job.n_pixels)), job.spp * job.n_pixels
        chosen.hooks = RenderHooks(on_pass=lambda done, _: self.hooks.passed(offset + done, total),
                                   should_stop=self.hooks.stop)
        chosen.merge_iteration = self.merge_iteration
        seed = job.seed + k * SEGMENT_SEED if k else job.seed
        image = chosen.render(job.scene, job.sensor, seed, spp, True, job.evaluate)
        self.merge_iteration = chosen.merge_iteration
        self.last_chosen = chosen
        info = dict(chosen.last_render_info)
        return {'trial': trial, 'image': image, 'layers': chosen.strategy_images, 'info': info,
                'spp': info['samples'] / job.n_pixels}

    def combine_segments(self, segments, spp, n_pixels):
        """The image of an auto render's segments (auto.segment_weights), its strategy layers
        (weighted: combined alike, so they still sum to the image; unweighted: those of the
        segments that rendered the last segment's configuration, in proportion to their samples,
        as the strategies traced are that configuration's) and last_render_info (the last
        segment's, with the samples, passes and ray counts of all)."""
        from .auto import segment_weights
        weights = segment_weights([(seg['trial'], seg['spp']) for seg in segments])
        for seg, w in zip(segments, weights):
            seg['weight'] = w
        image = segments[0]['image']
        if len(segments) > 1:
            image = sum((seg['image'] * w for seg, w in zip(segments[1:], weights[1:])), image * weights[0])
            dr.eval(image)
        layers = None
        if all(seg['layers'] is not None for seg in segments):
            same = [seg for seg in segments if seg['trial'] is segments[-1]['trial']]
            n_same = sum(seg['spp'] for seg in same)
            layers = {name: {'weighted': sum(seg['layers'][name]['weighted'] * w for seg, w in zip(segments, weights)),
                             'unweighted': sum(seg['layers'][name]['unweighted'] * (seg['spp'] / n_same) for seg in same)}
                      for name in segments[-1]['layers']}
        self.strategy_images = layers
        info = dict(segments[-1]['info'])
        info.update(spp=spp, samples=sum(seg['info']['samples'] for seg in segments),
                    passes=sum(seg['info']['passes'] for seg in segments),
                    interrupted=any(seg['info']['interrupted'] for seg in segments))
        if all('rays' in seg['info'] for seg in segments):
            info['rays'] = {key: sum(seg['info']['rays'][key] for seg in segments) for key in info['rays']}
        self.last_render_info = info
        return image

    def run_passes(self, ctx, acc, seed, spp, n_pixels):
        """Render the passes in turn until done or stopped (RenderHooks.should_stop, Ctrl-C);
        returns (samples done, interrupted, light-vertex levels used)."""
        total = spp * n_pixels
        samples_done, levels_used = 0, 0
        plan = plan_passes(spp, n_pixels, self.bytes_per_sample(ctx), self.samples_per_pass)
        for i, (spp_pass, pixel_start, pixel_count) in enumerate(plan):
            if samples_done > 0 and self.hooks.stop():
                return samples_done, True, levels_used
            if ctx.moments is not None:      # technique auto's pilot (moments.py): its halves
                cam = camera_lattice(lattice_step(ctx), pixel_start, pixel_count)[1]
                ctx.moments.begin_pass(spp_pass * pixel_count, spp_pass, samples_done // n_pixels, spp_pass * cam)
            try:
                levels = self.render_pass(ctx, acc, seed, i, spp_pass, pixel_start, pixel_count)
            except (KeyboardInterrupt, RuntimeError) as e:
                if samples_done == 0 or not caused_by_interrupt(e):
                    raise
                return samples_done, True, levels_used      # keep the finished passes
            levels_used = max(levels_used, levels)
            samples_done += spp_pass * pixel_count
            self.hooks.passed(samples_done, total)
        return samples_done, False, levels_used

    def render_pass(self, ctx, acc, seed, i, spp_pass, pixel_start, pixel_count):
        """Pass ``i``: spp_pass samples in each of pixel_count crop pixels from pixel_start.
        Returns the light-vertex levels it used."""
        ps = self.pass_state(ctx, acc, seed, i, spp_pass, pixel_start, pixel_count)
        if self.trial_stride > 1 and ps.n == 0:     # (a trial's pass without a row of its lattice)
            return 0
        if ctx.strategies.light_pass:
            cap = self.light_capacity(ctx)
            ps.store = LightStore(n=ps.n_light, capacity=cap, record=ctx.record) if cap > 0 else None
            LightTracer(ctx, ps).trace()
            # Evaluate what the light subpaths leave to the camera pass (the sampler's state, the
            # stored vertices' counts): left symbolic, the camera kernel would trace every light
            # subpath again to recompute them (SmallVCM box: 2838 operations and 683 ms, against
            # 1742 and 549 ms with them read from memory)
            if ctx.strategies.camera_pass:
                ps.sampler.schedule_state()
                if ps.store is not None:
                    dr.schedule(ps.store.count)
                dr.eval()
            if ctx.light_cache is not None and ctx.strategies.trace_connect and ps.store is not None:
                c = self.cache_run[1] if ctx.pixel_counts is None else max(ctx.pixel_counts.c_max, 1)
                ps.cache = LightCache(ps.store, c)
        if ctx.strategies.trace_merge:
            ps.merger = Merger(ctx, PhotonGrid(ctx.scene, ps.store, ps.schedule, surface_only=ctx.beams), ps.mis)
            if ctx.beams:
                ps.beams = BeamGather(ctx, BeamGrid(ctx.scene, ps.store, ps.schedule), ps.mis)
            self.last_merge_radius = ps.schedule.r_last
            self.last_beam_paths = ps.schedule.beam_paths if ctx.beams else None
        if ctx.strategies.camera_pass and ps.n > 0:    # (auto's lattice pilot: a pass may hold no kept pixel)
            CameraTracer(ctx, ps).trace()
        elif (acc.has_alpha or acc.n_aov) and ps.n > 0:
            CameraTracer(ctx, ps).trace_first_hits()
        dr.eval(acc.cam.tensor(), acc.lt.tensor())
        if ctx.layers is not None:
            dr.eval(ctx.layers.buf)
        if ctx.moments is not None:
            dr.eval(ctx.moments.buf)
        if ctx.stats is not None:
            ctx.stats.end_pass()
        if ctx.medium_stats is not None:
            ctx.medium_stats.end_pass()
        return ps.store.capacity if ps.store is not None else 0

    def pass_state(self, ctx, acc, seed, i, spp_pass, pixel_start, pixel_count):
        """The passes.PassState of pass ``i``: its sampler, wavelengths and merging schedule
        (which advances the merge iteration count)."""
        k = self.camera_stride(ctx)
        trial = self.trial_stride > 1       # (technique auto's timed trial of a large crop: camera_stride)
        run = int(ctx.sensor.film().crop_size()[0]) if trial else 1      # (its rows)
        row = self.trial_row if trial else 0
        v0, n_cam = camera_lattice(k, pixel_start, pixel_count, run, row)
        n = spp_pass * n_cam
        index = i if k == 1 else LATTICE_PASS + i
        sampler = pass_sampler(ctx, spp_pass, seed, index, max(n, 1))
        u_wl, spectral = None, None
        if mi.is_spectral:
            # one set of wavelengths per sample, for its light and its camera subpath (Mitsuba's
            # emitters would draw their own in sample_ray): the sensor's, as its sample_ray does
            u_wl = sampler.next_1d()
            if ctx.strategies.trace_merge:
                # merging pairs a camera vertex with light vertices of other samples of its
                # iteration (merge.MergeSchedule: sample j of every pixel): they share sample j of
                # the first pixel's wavelengths, so a light vertex's throughput is for the camera
                # vertex's wavelengths
                u_wl = dr.gather(mi.Float, u_wl, dr.arange(mi.UInt32, n) % dr.opaque(mi.UInt32, spp_pass))
            spectral = ctx.sensor.sample_wavelengths(dr.zeros(mi.SurfaceInteraction3f, n), u_wl, True)
        # light subpaths: one per sample of each crop pixel of the pass, or the cache's n_L (whole ones
        # per iteration)
        pixels = max(n_cam, 1) if trial else pixel_count     # the pixels whose samples have light subpaths
        n_light = ctx.light_cache.light_paths(spp_pass, pixels) if ctx.light_cache is not None \
            else spp_pass * pixels
        schedule, eta, radius = None, None, None
        if ctx.strategies.trace_merge:
            s = self.settings
            # a trial's light subpaths are 1/k of the render's: its radius sqrt(k) times the
            # render's keeps pi r^2 N, the light vertices a merge finds (and its weights' eta),
            # with 1/k of the render's cap on the beams' N
            radius_rel = s['radius'] * (math.sqrt(k) if trial else 1.0)
            beams = -(-beam_cap(ctx.strategies, s['beam_paths']) // (k if trial else 1))     # (0: all)
            schedule = MergeSchedule(ctx.scene, radius_rel, s['radius_alpha'], self.merge_iteration + 1,
                                     spp_pass, n_light // spp_pass, beams)
            self.merge_iteration += spp_pass
            # (max: a lattice pass without camera samples, whose terms are unused)
            eta, radius = merge_terms(schedule, max(n, 1), ctx.media is not None)
        ps = PassState(sampler, n, spp_pass, v0, acc, ctx.mis.for_pass(eta, radius=radius, **beam_terms(ctx, schedule)))
        ps.spectral, ps.u_wl, ps.schedule = spectral, u_wl, schedule
        ps.pixel_sampler = pixel_sampler(ctx, spp_pass, seed, index, max(n, 1))
        if trial:
            ps.pixel_stride, ps.pixel_run, ps.pixel_offset = k, run, row * run
        elif k > 1:
            self.lattice_pass_state(ctx, ps, seed, i, k, n_light)
        if ctx.light_cache is not None:
            self.cache_pass_state(ctx, ps, seed, i, n_light, (eta, radius))
        if trial and n_cam > 0:     # its splats stand for the light subpaths of every pixel of the pass
            scale = ps.splat_scale if ps.splat_scale is not None else ctx.splat_scale
            ps.splat_scale = scale * dr.opaque(mi.Float, pixel_count / n_cam)
        return ps

    def camera_stride(self, ctx):
        """k: the passes trace camera samples in every k-th crop pixel or row only. technique
        auto's timed trial of a large crop (``trial_stride``, auto.trial_stride): in every k-th
        row (whole rows: its camera rays as coherent as the render's), with light subpaths for
        those samples only and its merges at sqrt(k) times the radius (pass_state), so that
        each sample's work, and so the time a sample per pixel of the crop takes, is the
        render's; its pilot (``lattice_step``): in every k-th pixel, with every light subpath of
        the render; 1 elsewhere."""
        return self.trial_stride if self.trial_stride > 1 else lattice_step(ctx)

    def lattice_pass_state(self, ctx, ps, seed, i, k, n_light):
        """technique auto's pilot of a large crop (``lattice_step`` k > 1): camera samples in
        every k-th crop pixel only (the ones its moment film keeps), every light subpath of the
        classic estimator (one per sample of every crop pixel, their own sampler seeded as the
        pass's would be), so that the kept pixels' estimates and the counts in the MIS are the
        classic estimator's; camera sample j connects to light subpath j."""
        ps.pixel_stride = k
        ps.n_light = n_light
        ps.light_sampler = pass_sampler(ctx, ps.spp_pass, seed, i, n_light)
        if ps.schedule is not None:     # merges: the light subpaths' own etas (and radii in media)
            eta, radius = merge_terms(ps.schedule, n_light, ctx.media is not None)
            ps.mis_light = ctx.mis.for_pass(eta, radius=radius, **beam_terms(ctx, ps.schedule))

    def cache_pass_state(self, ctx, ps, seed, i, n_light, merging):
        """The light vertex cache's share of pass ``i`` (light_cache.py): n_L light subpaths with
        their own sampler, the splats' scale 1/spp times n / n_L, the MIS counts (merges: the
        camera samples' (``merging``: their eta and, with media, radius), and the light subpaths'
        of their iterations in ``mis_light``)."""
        ps.n_light = n_light
        ps.light_sampler = pass_sampler(ctx, ps.spp_pass, seed, PILOT_PASS + 1 + i, n_light)
        ps.splat_scale = ctx.splat_scale * dr.opaque(mi.Float, ps.n / n_light)
        vpp, c = self.cache_run
        counts = cache_counts(vpp, c, n_light, ps.n, ctx.strategies.trace_connect)
        if ctx.pixel_counts is not None:    # the counts per lane, at its pixel (CameraTracer, LightTracer)
            ps.vpp, ps.n_lt, counts = vpp, counts[1], None
        eta, radius = merging
        ps.mis = ctx.mis.for_pass(eta, counts, radius, **beam_terms(ctx, ps.schedule))
        eta_light, radius_light = merge_terms(ps.schedule, n_light, ctx.media is not None)
        ps.mis_light = ctx.mis.for_pass(eta_light, counts, radius_light, **beam_terms(ctx, ps.schedule))

    def render_info(self, ctx, spp, n_pixels, samples_done, interrupted, levels_used):
        info = {
            'strategies': ctx.strategies.traced(),
            'passes': count_passes(spp, n_pixels, self.bytes_per_sample(ctx), self.samples_per_pass),
            'spp': spp,
            'samples': samples_done,
            'interrupted': interrupted,
            'delta_handling': ctx.has_delta,
            'light_pass': ctx.strategies.light_pass,
            'camera_pass': ctx.strategies.camera_pass,
            'light_vertex_levels': self.light_capacity(ctx),
            'light_vertex_levels_used': levels_used,
            'light_vertex_fields': list(ctx.record.DRJIT_STRUCT) if ctx.record_built else [],
        }
        if ctx.stats is not None:
            info['rays'] = ctx.stats.summary()
        if ctx.media is not None and not ctx.media.info.any:
            info['null_lobes'] = 'passed on walks and edges (media.MediumTracer; the scene has no medium)'
        elif ctx.media is not None:
            info['media'] = {'heterogeneous': ctx.media.info.heterogeneous, 'chromatic': ctx.media.info.chromatic,
                             'merging': None if not ctx.strategies.trace_merge else ('beams' if ctx.beams else 'points'),
                             'outside': _described(ctx.emitter_media.outside),
                             'sensor': _described(ctx.sensor.get_medium()),
                             'around_sensor': _described(ctx.emitter_media.around_sensor),
                             'declared_consistently': ctx.emitter_media.consistent,
                             **(ctx.medium_stats.summary() if ctx.medium_stats is not None else {})}
        if ctx.light_cache is not None:
            vpp, c = self.cache_run
            info['light_cache'] = {'light_paths_per_sample': ctx.light_cache.ratio, 'connections': c,
                                   'pilot_vertices_per_path': vpp}
        if ctx.strategies.trace_merge:
            info['merge_iteration'] = self.merge_iteration
            info['merge_radius'] = self.last_merge_radius
            if ctx.beams:
                info['media']['beam_paths'] = self.last_beam_paths
        return info

    # ------------------------------------------------------------------ derivatives
    @held
    def render_forward(self, scene, params=None, sensor=0, seed=0, spp=0):
        """Forward-mode derivative of the image (the gradients set on ``params`` pushed to the
        image), pass by pass: what ``mi.render`` calls for ``dr.forward``. See gradients.py."""
        grad = None
        for img in self.differentiable_passes(scene, params, sensor, seed, spp):
            dr.forward_to(img)
            g = dr.grad(img)
            grad = g if grad is None else grad + g
            dr.eval(grad)
        return grad

    @held
    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Reverse-mode derivative: ``grad_in`` (the image's adjoint) propagated to the scene
        parameters, pass by pass, so that memory is bounded by the pass size, not by spp."""
        for img in self.differentiable_passes(scene, params, sensor, seed, spp):
            dr.backward_from(img * grad_in)
            dr.eval()                   # the gradients accumulated so far: no graph kept across passes

    def differentiable_passes(self, scene, params, sensor, seed, spp):
        """Yields, pass by pass, a differentiable image of that pass's share of the render
        (film.FilmAccumulator.pass_image), traced with evaluated loops (Dr.Jit 1.5.0's AD
        through symbolic loops is unreliable) and detached sampling (gradients.py)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        check_parameters(params, scene)
        if spp == 0:
            spp = sensor.sampler().sample_count()
        check_scene(scene, sensor)
        if self.technique == 'auto':
            raise NotImplementedError("bdpt: technique 'auto' renders trial images first and has no "
                                      "derivatives; differentiate with a technique of its own")
        if self.technique in ('vcm', 'vm'):
            raise NotImplementedError(
                f"bdpt: technique '{self.technique}' (vertex merging) is not differentiable here: the "
                "merging kernel's derivatives (with respect to positions inside the radius) are not "
                "implemented; differentiate with technique 'bdpt', 'pt' or 'lt'")
        geometry = tuple(geometry_keys(params))
        if geometry and self.technique == 'lt':
            raise NotImplementedError(
                "bdpt: gradients with respect to geometry need camera subpaths: with technique 'lt' every "
                "path reaches the image through a splat whose pixel moves with the geometry (a boundary "
                "term); use technique 'bdpt' or 'pt'")
        ctx = Context(scene, sensor, self.settings, spp, ad=True, ad_geometry=geometry)
        crop = sensor.film().crop_size()
        n_pixels = int(crop[0]) * int(crop[1])
        # the AD graph of a sample holds every vertex's values: passes 8 times smaller
        plan = plan_passes(spp, n_pixels, AD_BYTES_FACTOR * self.bytes_per_sample(ctx), self.samples_per_pass)
        with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False), \
                dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
            for i, (spp_pass, pixel_start, pixel_count) in enumerate(plan):
                if pixel_count != n_pixels:
                    raise NotImplementedError(
                        "bdpt: derivatives need passes of whole images: raise samples_per_pass to at "
                        f"least the crop's {n_pixels} pixels")
                acc = FilmAccumulator(sensor.film(), ctx.aov_names)
                self.render_pass(ctx, acc, seed, i, spp_pass, pixel_start, pixel_count)
                yield acc.pass_image(spp_pass / spp)

    def aov_names(self):
        """The AOV channels this integrator adds to the film (parameter ``aovs``), as Mitsuba's
        integrators report theirs."""
        return list(self.aov_channels)

    def sample(self, *args, **kwargs):
        # Mitsuba calls a nested integrator's sample() (the aov integrator wrapping bdpt does)
        raise NotImplementedError(
            "bdpt cannot run inside another integrator (such as Mitsuba's 'aov', which calls the nested "
            "integrator's per-sample sample()): bdpt renders whole images, its light-tracing strategies "
            "splat into other pixels and are added as a light image. bdpt renders the same AOV channels "
            "itself: give it the parameter aovs (e.g. <string name=\"aovs\" value=\"dd:depth,nn:sh_normal\"/> "
            "inside <integrator type=\"bdpt\">, or mi.load_dict({'type': 'bdpt', 'aovs': 'dd:depth,nn:sh_normal'})); "
            "or: Render the AOV channels with the aov integrator alone and the image with bdpt.")

    def to_string(self):
        return (f"BDPTIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"mis={self.mis_kind}, technique={self.technique}, hide_emitters={self.hide_emitters}]")


BDPTIntegrator.__doc__ = f"""
Bidirectional path tracer (``bdpt``)
------------------------------------

Veach's bidirectional path tracing with every (s,t) connection strategy, combined by multiple
importance sampling whose weights are computed with Georgiev's recursion (seed paper eqs.
20-22). Path tracing (``technique=pt``) and light tracing (``technique=lt``) are subsets of
the same estimator.

{P.markdown_table()}

Example (XML)::

    <integrator type="bdpt">
        <integer name="max_depth" value="8"/>
        <string name="mis" value="power"/>
    </integrator>

Example (Python)::

    import mitsuba as mi
    mi.set_variant('llvm_ad_rgb')
    import bdpt_jit
    scene = mi.load_file('scenes/cornell-box.xml')
    image = mi.render(scene, integrator=mi.load_dict({{'type': 'bdpt', 'max_depth': 8}}))
"""


def _described(medium):
    """scene_check.describe_medium, None for vacuum."""
    return describe_medium(medium) if medium is not None else None


def lattice_step(ctx):
    """k: technique auto's pilot (moments.py) of a crop larger than moments.MAX_PIXELS traces its
    camera samples in every k-th crop pixel only, the ones its moment film keeps
    (``Integrator.lattice_pass_state``); 1 everywhere else, and in spectral variants (where a
    sample's light and camera subpaths share their wavelengths)."""
    m = ctx.moments
    return m.step if m is not None and m.step > 1 and not mi.is_spectral else 1


def camera_lattice(k, pixel_start, pixel_count, run=1, first=0):
    """(v0, count): the lattice pixels v0 .. v0 + count - 1 among crop pixels [pixel_start,
    pixel_start + pixel_count), of the lattice of run ``first`` of every k runs of ``run``
    pixels (camera_path.camera_pixels; k: BDPTIntegrator.camera_stride; run 1: every k-th pixel)."""
    def below(x):           # lattice pixels before crop pixel x
        return x // (run * k) * run + min(max(x % (run * k) - first * run, 0), run)
    v0 = below(pixel_start)
    return v0, below(pixel_start + pixel_count) - v0


def beam_terms(ctx, schedule):
    """mis.MIS.for_pass's arguments on merges inside media: whether they are beams and the
    share of an iteration's light subpaths that the beams gather from (merge.MergeSchedule)."""
    share = schedule.beam_share if ctx.beams and schedule is not None else 1.0
    return {'beams': ctx.beams, 'beam_share': share}


def merge_terms(schedule, n, media):
    """(eta, radius) of lanes 0 .. n-1 of a pass (camera samples or light subpaths, a pixel's
    samples consecutive) under its merge.MergeSchedule: each one's eta = pi r^2 N of its
    iteration and, with media (``media``), its ball's radius; (None, None) without merging."""
    if schedule is None:
        return None, None
    lanes = dr.arange(mi.UInt32, n)
    return schedule.eta(lanes), (schedule.radius(schedule.group(lanes)) if media else None)
