"""Which (s,t) strategies exist for a scene and the settings: decided here once, read by the
kernels (what they trace), by mis.py (which densities a weight sums) and by
``last_render_info``.

A path of k edges has k + 2 strategies (s light vertices, t camera vertices, s + t = k + 1).
They fall into families, each offered by some techniques:

| family | strategies | bdpt | pt | lt | vcm | vm |
|---|---|---|---|---|---|---|
| hits | s=0: the camera subpath hits an emitter (or leaves the scene: environment) | yes | yes | | yes | (1) |
| direct | s=1, t>=2: emitter sampling from a camera vertex | yes | yes | | yes | |
| connections | s>=2, t>=2: a light vertex connected to a camera vertex | yes | | | yes | |
| splats | t=1: a light vertex connected to the camera, splatted to the light image | yes | | yes | yes | |
| merges | a camera vertex merged with the light vertices of every light subpath of the pass within the radius (merge.py) | | | | yes | (1) |

(1) ``vm`` is progressive photon mapping (``ppm``): no MIS, a partition instead. The camera
subpath scatters through delta vertices only; it merges at its first non-delta vertex and ends
there, and it counts an emitter it hits only when every vertex before was delta (or none).

The splats need a camera that a light vertex can be connected to (cameras.CameraModel
``reachable``); without one (orthographic, radiancemeter, distant, irradiancemeter) bdpt
combines hits, direct and connections, and ``lt`` is refused (it would have no strategy). Which of them a render traces also depends on the scene (its emitter kinds)
and on ``max_depth``: a strategy whose shortest path is longer than max_depth is not traced.
"""

TECHNIQUES = ('bdpt', 'pt', 'lt', 'vcm', 'vm')


class StrategySet:
    """The families a technique combines (``hits``, ``direct``, ``connections``, ``splats``:
    what the MIS weights count) and what the kernels trace for one scene (``trace_*``)."""

    def __init__(self, technique='bdpt', max_depth_edges=0x3FFFFFFF, has_area=True, has_emitters=True,
                 has_env=False, camera_reachable=True, hide_emitters=False):
        if technique not in TECHNIQUES:
            raise ValueError(f"technique must be one of {', '.join(TECHNIQUES)}, got {technique!r}")
        if technique == 'lt' and not camera_reachable:
            raise ValueError("technique 'lt' needs a camera that light paths can reach; this one "
                             "(a delta direction or position) has no light-tracing strategy: use bdpt or pt")
        self.technique = technique
        self.camera_reachable = camera_reachable
        # ---- families of the estimator (mis.py)
        self.hits = technique in ('bdpt', 'pt', 'vcm', 'vm')
        self.direct = technique in ('bdpt', 'pt', 'vcm')
        self.connections = technique in ('bdpt', 'vcm')
        self.splats = technique in ('bdpt', 'lt', 'vcm') and camera_reachable
        self.merges = technique in ('vcm', 'vm')
        self.ppm = technique == 'vm'        # merges and hits as a partition, without MIS
        # ---- what the kernels trace for this scene and max_depth (edges)
        edges = max_depth_edges
        self.trace_s0 = self.hits and has_area and edges >= 1
        self.trace_env = self.hits and has_env and edges >= 1
        self.trace_s1 = self.direct and has_emitters and edges >= 2
        self.trace_connect = self.connections and has_emitters and edges >= 3
        self.trace_splat_y0 = self.splats and has_area and edges >= 1 and not hide_emitters
        self.trace_splat = self.splats and has_emitters and edges >= 2
        self.trace_merge = self.merges and has_emitters and edges >= 2

    @classmethod
    def for_scene(cls, technique, max_depth_edges, emitters, camera, hide_emitters):
        """``emitters``: endpoints.EmitterTable; ``camera``: cameras.CameraModel."""
        scene = emitters.scene
        if technique == 'lt' and not camera.reachable:
            from .scene_check import UnsupportedSceneError
            raise UnsupportedSceneError(
                f"bdpt: technique 'lt' cannot render through the sensor '{camera.plugin}': light tracing "
                "never reaches it (a delta direction or position: no light path can be connected to it); "
                "use technique 'bdpt' or 'pt'")
        return cls(technique, max_depth_edges, has_area=emitters.has_area, has_emitters=emitters.count > 0,
                   has_env=scene.environment() is not None, camera_reachable=camera.reachable,
                   hide_emitters=hide_emitters)

    @property
    def light_pass(self):
        """Light subpaths are traced (splats or connections)."""
        return self.trace_splat_y0 or self.trace_splat or self.trace_connect or self.trace_merge

    @property
    def camera_pass(self):
        """Camera subpaths are traced (hits, emitter sampling or connections)."""
        return self.trace_s0 or self.trace_env or self.trace_s1 or self.trace_connect or self.trace_merge

    # The names reports use, in the order the kernels run them.
    DESCRIPTIONS = (
        ('trace_s0', 's=0 (camera subpath hits an emitter)'),
        ('trace_env', 's=0 (camera subpath leaves the scene: environment)'),
        ('trace_s1', 's=1 (emitter sampling)'),
        ('trace_splat_y0', 's=1,t=1 (emitter seen by the camera through light tracing)'),
        ('trace_splat', 't=1 (light subpath vertices splatted to the camera)'),
        ('trace_connect', 's>=2,t>=2 (subpath connections)'),
        ('trace_merge', 'merges (camera vertices merged with light vertices within the radius)'),
    )

    def traced(self):
        """What this render traces, named for reports."""
        return [text for flag, text in self.DESCRIPTIONS if getattr(self, flag)]

    @classmethod
    def every_strategy(cls):
        """Every strategy a render can trace, named as ``traced`` names them."""
        return [text for _, text in cls.DESCRIPTIONS]
