"""What the kernels of one render are specialised to. Plain Python values here become
trace-time constants; Dr.Jit values (the opaque scales) are kernel inputs, so changing them
does not recompile anything.

A plain class on purpose: Dr.Jit traverses dataclasses, and one referenced inside a loop
becomes loop state. Per-pass values (the pass size, the light-vertex storage) are not here:
they live in store.LightStore and are passed to the tracers."""

import drjit as dr
import mitsuba as mi

from .cameras import camera_for
from .connect import DiffuseTable
from .endpoints import EmitterTable
from .film import FilmAccumulator, StrategyLayers
from .gradients import ADSampling, check_parameters
from .mis import MIS
from .params import ParameterError, aov_channel_names, parse_aovs
from .passes import UNBOUNDED
from .rays import RayOffsets
from .sampling import Sampling
from .scene_check import (UnsupportedSceneError, VertexNeeds, check_infinite_emitters, describe_medium,
                          has_instances, media_info,
                          scene_has_delta_bsdf, scene_media, scene_refracts, scene_perturbs_normals,
                          scene_non_reciprocal)
from .stats import MediumStats, RayStats
from .store import record_type
from .strategies import StrategySet


def diffuse_table(scene):
    """connect.DiffuseTable of the scene where it covers every BSDF (a table beside Mitsuba's
    calls for other BSDFs is slower than the calls alone: its docstring), else None (also
    where it cannot see them all: instanced shapes' BSDFs are not in scene.shapes())."""
    if has_instances(scene) or not mi.is_rgb:
        return None                 # (its reflectances are RGB: spectral and mono use the BSDFs)
    if any(str(s.bsdf().class_name()) != 'SmoothDiffuse' for s in scene.shapes() if s.bsdf() is not None):
        return None                 # (before the table reads each BSDF's parameters: 0.1-0.3 ms a render)
    table = DiffuseTable(scene)
    return table if table.everything else None


# a vertex's emitter-sampling (or splat) evaluation and its scatter's BSDF sample in one call
# where the scene allows it (Context.fuse_draw); False: two calls (for tests)
FUSE_DRAW = True


class _NoSplats:
    """A camera seen as one that no light path reaches (for StrategySet)."""
    reachable = False

    def __init__(self, camera):
        self.plugin = getattr(camera, 'plugin', 'camera')


class Context:
    """Fields (all set here, none added later):

    scene, sensor      the Mitsuba scene and the sensor rendered
    camera             cameras.CameraModel of the sensor
    emitters           endpoints.EmitterTable: emitter choice and emission densities
    offsets            rays.RayOffsets: the error bounds every spawned ray is offset by
    strategies         strategies.StrategySet: what exists and what is traced
    mis                mis.MIS: the weights, for the heuristic and the strategy set
    time               the sensor's shutter-open time (every ray's time)
    max_depth_edges    longest path in edges (passes.UNBOUNDED for max_depth = -1)
    unbounded          max_depth = -1: the light-vertex storage grows as needed
    rr_depth           edges from which Russian roulette may end a subpath
    hide_emitters      directly visible emitters hidden
    see_through_emitters  the first camera edge and t=1 shadow rays pass emitters' shapes
    has_delta          the scene has a BSDF with a delta lobe (delta handling traced)
    refracts           the scene has a BSDF with a transmission lobe that refracts (scene_refracts)
    exact_adjoint      light vertices take connect.adjoint_eval: a BSDF perturbs its shading
                       frame, or one is not reciprocal (scene_check._non_reciprocal: hair,
                       principledthin) and the technique combines strategies, which must all
                       estimate path's integrand vertex by vertex. lt alone keeps Mitsuba's
                       importance-mode value (ptracer's estimator), the one hair's own sampling
                       covers: with the swapped value lt was 1.1% dark on hair curves
    defensive          technique lt with the exact adjoint: light subpaths mix uniform directions
                       into the BSDF's (transport._defensive)
    record             the light-vertex record type (store.record_type)
    diffuse            connect.DiffuseTable, or None unless every BSDF is a constant diffuse
    fuse_draw          a camera vertex's emitter-sampling evaluation and its scatter's BSDF sample
                       made in one BSDF call (vertex.Vertex.eval_and_draw)
    inv_spp            1 / spp, opaque: camera-sample contributions to the strategy layers
    splat_scale        the light image's scale per splat (film.FilmAccumulator.splat_scale), opaque
    layers             film.StrategyLayers, or None (parameter strategy_images)
    moments            moments.MomentFilm, or None: technique auto's pilot (moments.instrument)
    stats              stats.RayStats, or None (parameter statistics)
    ad                 a differentiable pass (gradients.py): detached sampling, values with derivatives
    ad_geometry        the gradient-enabled shape parameters of a differentiable pass (their keys)
    sampling           sampling.Sampling, or gradients.ADSampling in a differentiable pass
    aovs, aov_names    the AOVs asked for (params.parse_aovs) and their film channels
    light_cache        light_cache.CacheSettings, or None: the classic estimator (parameter light_paths)
    media              media.MediumTracer of a scene with participating media, or None (none of
                       the medium code is traced then)
    emitter_media      media_path.EmitterMedia (the medium each emitter lies in), or None
    medium_stats       stats.MediumStats (parameter statistics, a scene with media), or None
    """

    def __init__(self, scene, sensor, settings, spp, ad=False, ad_geometry=()):
        self.scene, self.sensor = scene, sensor
        self.camera = camera_for(sensor)
        self.offsets = RayOffsets(scene)
        # lt and vm: light subpaths alone carry their paths (endpoints.EmitterTable._env_direction)
        self.emitters = EmitterTable(scene, self.offsets, env_defensive=settings['technique'] in ('lt', 'vm'))
        self.unbounded = settings['max_depth'] < 0
        self.max_depth_edges = UNBOUNDED if self.unbounded else settings['max_depth']
        self.hide_emitters = settings['hide_emitters']
        self.has_delta = scene_has_delta_bsdf(scene)
        self.refracts = scene_refracts(scene)
        technique = self.strategy_setup(settings, ad, ad_geometry)
        self.time = sensor.shutter_open()
        self.rr_depth = settings['rr_depth']
        self.exact_adjoint = (scene_perturbs_normals(scene)
                              or (technique not in ('lt', 'pt') and scene_non_reciprocal(scene)))
        self.defensive = technique == 'lt' and self.exact_adjoint and not ad     # transport._defensive
        self.media, self.emitter_media, self.medium_stats = self.media_setup(scene, sensor, settings, technique)
        # hide_emitters: camera rays pass emitters' shapes, as Mitsuba's `path`'s do (in scenes
        # without media: there the first edge is sampled by distance, and the shapes stay)
        self.see_through_emitters = (self.hide_emitters and self.media is None
                                     and any(shape.is_emitter() for shape in scene.shapes()))
        # merges inside media by beams (beams.py: gray media only), else by balls (merge.py)
        self.beams = (self.media is not None and self.media.info.any and self.strategies.trace_merge
                      and self.media.info.gray
                      and settings.get('media_merging', 'beams') == 'beams')
        self._record = None     # the stored light vertices' type: built when a store asks (record)
        # the table's reflectances are constants: derivatives go through Mitsuba's BSDFs
        self.diffuse = None if ad else diffuse_table(scene)
        if ad:      # likewise the sphere lights' table (direct.py): Mitsuba's sampling has the derivatives
            self.emitters.all_spheres, self.emitters.sph_le = False, None
        # (the table makes no call to fuse; media and differentiable passes sample elsewhere)
        self.fuse_draw = FUSE_DRAW and self.diffuse is None and not ad and self.media is None
        # opaque: literals would be baked into the kernels and recompile them for every spp
        self.inv_spp = dr.opaque(mi.Float, 1.0 / spp)
        self.splat_scale = dr.opaque(mi.Float, FilmAccumulator.splat_scale(spp))
        self.output_setup(settings)
        self.moments = None         # moments.MomentFilm of technique auto's pilot (moments.instrument)
        self.pixel_counts = None    # pixel_counts.PixelCounts of auto's per-pixel candidate (BDPTIntegrator.per_pixel)
        self.stats = RayStats() if settings['statistics'] else None
        self.sampling = ADSampling(self) if ad else Sampling(self)
        self.light_cache = self.cache_settings(settings)
        self.evaluate_tables()

    def strategy_setup(self, settings, ad, ad_geometry):
        """The strategies the scene and technique sample (StrategySet) and their weights (MIS);
        returns the technique they follow (vcm without a delta BSDF: bdpt)."""
        self.ad = ad
        self.ad_geometry = tuple(ad_geometry)
        merge_everywhere = bool(settings.get('merge_everywhere', False))
        technique = settings['technique']
        if technique == 'vcm' and not merge_everywhere and not self.has_delta:
            technique = 'bdpt'      # merges only behind delta vertices, and the scene has none (mis.py)
        self.strategies = StrategySet.for_scene(technique, self.max_depth_edges, self.emitters,
                                                self.camera, self.hide_emitters)
        if ad_geometry:
            # derivatives with respect to geometry: light-tracing splats land where their vertex
            # projects, and moving geometry moves them across pixels (a boundary term bdpt does
            # not have): their strategies leave the partition of unity (gradients.py)
            self.strategies = StrategySet.for_scene(technique, self.max_depth_edges, self.emitters,
                                                    _NoSplats(self.camera), self.hide_emitters)
        # geometry next to mirrors and glass: chains differentiated from the camera side only
        self.mis = MIS(settings['mis'], self.strategies, detached=ad,
                       camera_chains=bool(ad_geometry) and self.has_delta, merge_everywhere=merge_everywhere)
        return technique

    def output_setup(self, settings):
        """What a pass writes besides the image: AOVs and strategy layers, checked against the
        variant."""
        self.aovs = parse_aovs(settings.get('aovs', ''))
        self.aov_names = aov_channel_names(self.aovs)
        if self.aovs and mi.is_spectral:
            raise ParameterError(f"bdpt: parameter 'aovs' needs an RGB or monochrome variant, not "
                                 f"'{mi.variant()}'")
        if settings['strategy_images'] and not mi.is_rgb:
            raise ParameterError(f"bdpt: parameter 'strategy_images' needs an RGB variant (the layers are "
                                 f"RGB images), not '{mi.variant()}'")
        self.layers = (StrategyLayers(self.sensor.film(), max_length=min(self.max_depth_edges, 8))
                       if settings['strategy_images'] else None)

    @property
    def record(self):
        """The stored light vertices' record type (store.record_type), with the optional fields
        this scene reads (VertexNeeds): built on first use, so that path tracing, which stores
        none, does not read the meshes' buffers for it on every render call."""
        if self._record is None:
            self._record = record_type(VertexNeeds(self.scene), merging=self.mis.mis_merges,
                                       media=self.media is not None)
        return self._record

    @record.setter
    def record(self, value):
        self._record = value

    @property
    def record_built(self):
        """Whether a store asked for the record type (light vertices were stored)."""
        return self._record is not None

    def media_setup(self, scene, sensor, settings, technique):
        """(media.MediumTracer, media_path.EmitterMedia, stats.MediumStats or None) of a scene
        with participating media; (None, None, None) without: no medium code is traced. Refuses
        what is not built with media yet, naming the parameter and the medium."""
        info = media_info(scene, sensor)
        if not info.any and not (info.any_null and not self.ad):
            return None, None, None
        from .media import MediumTracer
        from .media_path import EmitterMedia, around_sensor, outside_medium, sensor_walk
        # a surface with a Null lobe and no medium: the tracer passes it on walks and edges with
        # its Null lobe's probability and transmission (media.MediumTracer), so that a shadow ray
        # through a mask or thin glass is not blocked (Mitsuba's path blocks it: a point light
        # behind a mask lit nothing); vacuum everywhere, so no distance is sampled
        if not info.any:
            emitter_media = EmitterMedia(scene, self.offsets, placements=self.emitters.sphere_placements)
            return MediumTracer(scene, self.offsets, info, None), emitter_media, None
        first = describe_medium(scene_media(scene, sensor)[0])
        if self.ad:
            raise UnsupportedSceneError(
                f"bdpt: gradients with participating media are not available yet (the scene has the medium "
                f"{first}): render it without derivatives, or differentiate with Mitsuba's prbvolpath",
                alternative='prbvolpath')
        if not self.ad:
            # a gradient-enabled parameter (the primal render of mi.render with params): refused
            # now, before any kernel runs, as the backward pass would refuse it (gradients.py);
            # its primal kernels also met a Dr.Jit 1.5 code-generation failure ("invalid
            # redefinition of function" in a virtual call) after some process histories
            check_parameters(mi.traverse(scene), scene)
        stats = MediumStats() if settings['statistics'] else None
        walk = sensor_walk(scene, self.offsets, sensor)
        outside = outside_medium(scene, self.offsets, sensor, walk)
        check_infinite_emitters(scene, outside)
        around = around_sensor(scene, self.offsets, sensor, outside)
        emitter_media = EmitterMedia(scene, self.offsets, outside, around, not walk.inconsistent,
                                     self.emitters.sphere_placements)
        return MediumTracer(scene, self.offsets, info, stats), emitter_media, stats

    def cache_settings(self, settings):
        """light_cache.CacheSettings of the parameters light_paths and connections, or None."""
        ratio = float(settings.get('light_paths', -1.0))
        if ratio == -1.0:
            return None
        if self.ad:
            raise ParameterError("bdpt: parameter 'light_paths' (the light vertex cache) has no derivatives "
                                 "here: differentiate with light_paths -1")
        if mi.is_spectral:
            raise ParameterError(f"bdpt: parameter 'light_paths' needs an RGB or monochrome variant, not "
                                 f"'{mi.variant()}' (a cached vertex would meet camera vertices of other "
                                 "wavelengths)")
        from .light_cache import CacheSettings
        return CacheSettings(ratio, int(settings.get('connections', -1)))

    def evaluate_tables(self):
        """Evaluate the tables' arrays now: left lazy, the first pass's kernels would compute
        them inline and differ from every later pass's, and compile twice (measured: the three
        main kernels of a 4-pass render compiled again for pass 2)."""
        arrays = []
        for obj in (self.emitters, self.offsets, self.diffuse, self.camera):
            for v in (vars(obj).values() if obj is not None else ()):
                if v is not None and dr.is_jit_v(v):
                    arrays.append(v)
        if arrays:
            dr.make_opaque(*arrays)
