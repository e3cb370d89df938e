"""The ``bdpt`` integrator plugin: bidirectional path tracing with every (s,t) strategy."""

import time as _time

import drjit as dr
import mitsuba as mi

from . import params as P
from .camera_path import CameraTracer
from .endpoints import Camera, EmitterTable
from .film import FilmAccumulator, StrategyLayers
from .stats import RayStats
from .connect import DiffuseTable
from .light_path import LightStore, LightTracer, record_type
from .mis import MIS
from .scene_check import VertexNeeds, check_scene, check_variant, scene_has_delta_bsdf, scene_perturbs_normals

UNBOUNDED = 0x3FFFFFFF          # max_depth = -1
BYTES_PER_LIGHT_VERTEX = 128    # light_path.FIELDS: at most 32 words
BYTES_PER_SAMPLE = 1200         # camera and light loop state, film positions
MEMORY_BUDGET = 1 << 30         # automatic samples_per_pass keeps the storage near this


def _diffuse_table(scene):
    table = DiffuseTable(scene)
    return table if table.any else None


def _caused_by_interrupt(exc):
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


class Context:
    """What the kernels are specialised to: the scene, the settings, and which strategies
    are possible. Plain Python values here become trace-time constants. (A plain class on
    purpose: Dr.Jit traverses dataclasses, and one referenced inside a loop becomes loop state.)

    Fields: scene, sensor, camera (endpoints.Camera), emitters (endpoints.EmitterTable),
    mis (mis.MIS), time, max_depth_edges, unbounded, rr_depth, hide_emitters, has_delta,
    exact_adjoint (BSDFs that perturb their shading frame: connect.adjoint_eval), record (the
    light-vertex record type, light_path.record_type), diffuse (connect.DiffuseTable or None),
    use_s0, use_s1, use_connect, splat_y0, splat_t1, splat_scale, n_opaque (the pass size as
    an opaque UInt32), layers (film.StrategyLayers or None), inv_spp."""

    def __init__(self, **fields):
        self.splat_scale = 1.0
        self.inv_spp = 1.0
        self.n_opaque = None
        self.layers = None
        self.stats = None
        self.__dict__.update(fields)

    @property
    def needs_light_pass(self):
        return self.splat_y0 or self.splat_t1 or self.use_connect

    @property
    def needs_camera_pass(self):
        return self.use_s0 or self.use_env or self.use_s1 or self.use_connect

    def strategies(self):
        out = []
        if self.use_s0:
            out.append('s=0 (camera subpath hits an emitter)')
        if self.use_env:
            out.append('s=0 (camera subpath leaves the scene: environment)')
        if self.use_s1:
            out.append('s=1 (emitter sampling)')
        if self.splat_y0:
            out.append('s=1,t=1 (emitter seen by the camera through light tracing)')
        if self.splat_t1:
            out.append('t=1 (light subpath vertices splatted to the camera)')
        if self.use_connect:
            out.append('s>=2,t>=2 (subpath connections)')
        return out


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
        self.strategy_images = None     # after a render with strategy_images: the layers (dict)
        self.progress = None            # optional callable(samples_done, samples_total), per pass
        self.last_render_info = {}

    # ------------------------------------------------------------------ setup
    def make_context(self, scene, sensor) -> Context:
        check_scene(scene, sensor)
        unbounded = self.max_depth < 0
        edges = UNBOUNDED if unbounded else self.max_depth
        tech = self.technique
        has_emitters = len(scene.emitters()) > 0
        has_area = any(mi.has_flag(e.flags(), mi.EmitterFlags.Surface) for e in scene.emitters())
        film = sensor.film()
        return Context(
            scene=scene, sensor=sensor, camera=Camera(sensor), emitters=EmitterTable(scene),
            mis=MIS(self.mis_kind, tech), time=sensor.shutter_open(),
            max_depth_edges=edges, unbounded=unbounded, rr_depth=self.rr_depth,
            hide_emitters=self.hide_emitters, has_delta=scene_has_delta_bsdf(scene),
            exact_adjoint=scene_perturbs_normals(scene), record=record_type(VertexNeeds(scene)),
            diffuse=_diffuse_table(scene),
            use_s0=has_area and tech in ('bdpt', 'pt') and edges >= 1,
            use_env=scene.environment() is not None and tech in ('bdpt', 'pt') and edges >= 1,
            use_s1=has_emitters and tech in ('bdpt', 'pt') and edges >= 2,
            use_connect=has_emitters and tech == 'bdpt' and edges >= 3,
            splat_y0=has_area and tech in ('bdpt', 'lt') and edges >= 1 and not self.hide_emitters,
            splat_t1=has_emitters and tech in ('bdpt', 'lt') and edges >= 2,
        )

    def light_capacity(self, ctx: Context) -> int:
        if not ctx.use_connect:
            return 0
        if ctx.unbounded:
            return 8
        return ctx.max_depth_edges - 2

    def plan_passes(self, ctx, spp, n_pixels):
        """Split spp x pixels samples into passes of whole pixels; returns
        [(spp_in_pass, pixel_start, pixel_count)]."""
        per_sample = BYTES_PER_SAMPLE + BYTES_PER_LIGHT_VERTEX * self.light_capacity(ctx)
        budget = self.samples_per_pass or max(MEMORY_BUDGET // per_sample, 1)
        if budget >= n_pixels:
            spp_pass = max(1, min(spp, budget // n_pixels))
            passes, done = [], 0
            while done < spp:
                k = min(spp_pass, spp - done)
                passes.append((k, 0, n_pixels))
                done += k
            return passes
        passes = []
        for _ in range(spp):
            for start in range(0, n_pixels, budget):
                passes.append((1, start, min(budget, n_pixels - start)))
        return passes

    # ------------------------------------------------------------------ render
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        ctx = self.make_context(scene, sensor)
        film = sensor.film()
        acc = FilmAccumulator(film)
        if spp == 0:
            spp = sensor.sampler().sample_count()
        crop = film.crop_size()
        n_pixels = int(crop[0]) * int(crop[1])
        # opaque: literals would be baked into the kernels and recompile them for every spp
        ctx.splat_scale = dr.opaque(mi.Float, acc.splat_scale(spp))
        ctx.inv_spp = dr.opaque(mi.Float, 1.0 / spp)
        if self.settings['statistics']:
            ctx.stats = RayStats()
        if self.settings['strategy_images']:
            ctx.layers = StrategyLayers(film, max_length=min(ctx.max_depth_edges, 8))
        passes = self.plan_passes(ctx, spp, n_pixels)
        t0 = _time.perf_counter()
        levels_used = 0
        samples_done, interrupted = 0, False
        for i, (spp_pass, pixel_start, pixel_count) in enumerate(passes):
            try:
                self.render_pass(ctx, scene, sensor, acc, seed, i, spp_pass, pixel_start, pixel_count)
                levels_used = max(levels_used, ctx.levels_used)
                samples_done += spp_pass * pixel_count
                if self.progress is not None:
                    self.progress(samples_done, spp * n_pixels)
            except (KeyboardInterrupt, RuntimeError) as e:
                # Ctrl-C while Dr.Jit traces a loop arrives as a RuntimeError caused by it
                if samples_done == 0 or not _caused_by_interrupt(e):
                    raise
                interrupted = True          # keep what the finished passes rendered
                break
        # Each light path splatted 1/spp; if the render stopped early, fewer light paths were
        # traced than that scale assumes (camera samples are normalised per pixel anyway).
        light_scale = spp * n_pixels / samples_done if samples_done else 1.0
        image = acc.develop(light_scale)
        dr.eval(image)
        self.strategy_images = ctx.layers.images(light_scale) if ctx.layers is not None else None
        self.last_render_info = {
            'strategies': ctx.strategies(),
            'passes': len(passes),
            'spp': spp,
            'samples': samples_done,
            'interrupted': interrupted,
            'delta_handling': ctx.has_delta,
            'light_pass': ctx.needs_light_pass,
            'camera_pass': ctx.needs_camera_pass,
            'light_vertex_levels': self.light_capacity(ctx),
            'light_vertex_levels_used': levels_used,
            'light_vertex_fields': list(ctx.record.DRJIT_STRUCT),
            'time_s': _time.perf_counter() - t0,
        }
        if ctx.stats is not None:
            self.last_render_info['rays'] = ctx.stats.summary()
        return image

    def render_pass(self, ctx, scene, sensor, acc, seed, i, spp_pass, pixel_start, pixel_count):
        """Pass ``i``: spp_pass samples in each of pixel_count crop pixels from pixel_start."""
        n = spp_pass * pixel_count
        ctx.n_opaque = dr.opaque(mi.UInt32, n)
        ctx.levels_used = 0
        sampler = sensor.sampler().clone()
        sampler.set_sample_count(spp_pass)
        # an opaque seed: a literal would be baked into the kernels and recompile them per seed
        sampler.seed(dr.opaque(mi.UInt32, (seed * 1000003 + i * 7919) & 0xFFFFFFFF), n)
        store = None
        if ctx.needs_light_pass:
            cap = self.light_capacity(ctx)
            if cap > 0:
                store = LightStore(n=n, capacity=cap, record=ctx.record)
                store.allocate()
            LightTracer(ctx).trace(sampler, n, acc, store)
            if store is not None:
                ctx.levels_used = store.capacity
        if ctx.needs_camera_pass:
            CameraTracer(ctx).trace(sampler, n, spp_pass, pixel_start, acc, store)
        dr.eval(acc.cam.tensor(), acc.lt.tensor())
        if ctx.layers is not None:
            dr.eval(ctx.layers.buf)
        if ctx.stats is not None:
            ctx.stats.end_pass()

    def sample(self, *args, **kwargs):
        raise NotImplementedError('bdpt renders whole images: call mi.render(scene) with it')

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
