"""Subpaths through participating media: the vertex a walk reaches by distance sampling (a
surface or a real collision in a medium), the step that samples it, and the transmittance
and distance densities of the edges every strategy builds. Used only where the scene has a
medium (``ctx.media``, a Python value): the kernels of other scenes are traced without any
of it (tests/test_media_render.py compares their kernel hashes).

A vertex of such a scene is a ``PathVertex``: per lane a surface vertex (vertex.Vertex) or a
medium vertex (media.MediumVertex), with the medium the walk reached it in. Its surface part
holds, in medium lanes, a point with a zero normal and no shape: every ray it spawns then
leaves without an offset, it has no emitter and no BSDF, and its cosine is 1 (``cos``). The
densities and measures are media.py's; where they enter the MIS: mis.MIS.distance (the
walk's edges) and the strategies (camera_path.py, light_path.py), each density of a vertex
sampled across an edge times that edge's distance density ``pdf_l``."""

import drjit as dr
import mitsuba as mi
import numpy as np

from .emitter_tables import sphere_placements, sphere_positions, sphere_shapes
from .media import DensityFactor, MediumVertex, medium_after, medium_array, medium_at_sensor, surface_stop
from .rays import spawn
from .vertex import Vertex


def _point_si(mei):
    """A SurfaceInteraction3f at the collision ``mei`` for the surface part of a medium lane:
    its point, no normal, no shape, the frame along wi (world wi = to_world((0, 0, 1)))."""
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(mei.p))
    si.p, si.t, si.time = mei.p, mei.t, mei.time
    if mi.is_spectral:
        si.wavelengths = mei.wavelengths
    si.sh_frame = mi.Frame3f(mei.wi)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    return si


class MediumHit:
    """Where a distance-sampled step ends, one field a line."""
    DRJIT_STRUCT = {
        'si': mi.SurfaceInteraction3f,   # the surface reached (where not collided; invalid: the ray escaped)
        'mei': mi.MediumInteraction3f,   # the real collision (where collided)
        'collided': mi.Bool,             # a medium vertex
        'medium': mi.MediumPtr,          # the medium the step ended in (the collision's, or the surface's incoming side)
    }

    def __init__(self, si=None, mei=None, collided=None, medium=None):
        self.si, self.mei, self.collided, self.medium = si, mei, collided, medium

    def is_valid(self):
        """A vertex was reached: a collision or a surface (not: the ray left the scene)."""
        return self.collided | self.si.is_valid()

    @property
    def p(self):
        return dr.select(self.collided, self.mei.p, self.si.p)

    def cos(self, d):
        """|cos| at the vertex reached along ``d``: 1 at a collision."""
        return dr.select(self.collided, 1.0, dr.abs(dr.dot(self.si.n, d)))

    def interaction(self):
        """The surface interaction a vertex of this hit holds (``_point_si`` in medium lanes)."""
        return dr.select(self.collided, _point_si(self.mei), self.si)


class PathVertex:
    """A vertex of a subpath in a scene with media, one field a line (module docstring)."""
    DRJIT_STRUCT = {
        'surf': Vertex,                  # the surface vertex (medium lanes: a point, no normal, no BSDF)
        'mei': mi.MediumInteraction3f,   # the collision (medium lanes): medium, sigma_s/n/t, wi (world)
        'in_medium': mi.Bool,            # a medium vertex
        'medium': mi.MediumPtr,          # the medium the walk reached the vertex in
    }

    def __init__(self, surf=None, mei=None, in_medium=None, medium=None):
        self.surf, self.mei, self.in_medium, self.medium = surf, mei, in_medium, medium

    @classmethod
    def at(cls, ctx, hit, ray=None):
        """The vertex at the MediumHit ``hit`` (``ray``: the ray that found it, for the BSDF lookup)."""
        si = hit.interaction()
        return cls(Vertex.at(ctx, si, ray), hit.mei, mi.Bool(hit.collided), hit.medium)

    # the operations of vertex.Vertex
    si = property(lambda self: self.surf.si)
    bsdf = property(lambda self: self.surf.bsdf)
    err = property(lambda self: self.surf.err)
    p = property(lambda self: self.surf.si.p)

    def _phase(self):
        return MediumVertex(self.mei)

    def cos(self, w):
        """|cos| towards ``w``: the surface's, 1 at a medium vertex."""
        return dr.select(self.in_medium, 1.0, self.surf.cos(w))

    def smooth(self, table=None):
        """Lanes with a smooth component: every medium vertex, the surface's otherwise."""
        return self.in_medium | self.surf.smooth(table)

    def eval(self, ctx, wo_world, mode, active):
        """As vertex.Vertex.eval: the BSDF's value and densities, or the phase function's."""
        m = self.in_medium
        f_s, fwd_s, rev_s, ok_s = self.surf.eval(ctx, wo_world, mode, active & ~m)
        f_m, fwd_m, rev_m, ok_m = self._phase().eval(ctx, wo_world, mode, active & m)
        return (dr.select(m, f_m, f_s), dr.select(m, fwd_m, fwd_s), dr.select(m, rev_m, rev_s),
                dr.select(m, ok_m, ok_s))

    def spawn(self, d):
        return self.surf.spawn(d)             # (medium lanes: no normal, so no offset)

    def spawn_to(self, ctx, q, n_q, err_q):
        return self.surf.spawn_to(ctx, q, n_q, err_q)

    def spawn_to_emitter(self, ctx, ds):
        return self.surf.spawn_to_emitter(ctx, ds)

    # what media add
    def medium_towards(self, d):
        """The medium a ray leaving the vertex in direction ``d`` travels in."""
        return dr.select(self.in_medium, self.medium, medium_after(self.surf.si, d, self.medium))

    def density_factor(self, info):
        """The vertex's media.DensityFactor: sigma_t at a medium vertex, (1, 1) at a surface
        (at a partly null one, (1, the probability that a walk stops there): media.surface_stop)."""
        f = DensityFactor.at(info, self.mei.medium, self.mei.sigma_t, self.in_medium)
        if info.partial_null:
            f.sig_het = f.sig_het * surface_stop(self.surf.bsdf, self.surf.si, ~self.in_medium)
        return f

    def merge_factor(self, mis, info, offered=True):
        """A merge at this vertex relative to a surface merge (mis.MIS.merge_factor)."""
        return mis.merge_factor(self.in_medium, offered, self.density_factor(info).sigma())

    def end(self):
        """The (point, normal, error) a shadow ray towards this vertex ends at (rays.spawn_to)."""
        return self.surf.si.p, self.surf.si.n, self.surf.err


def sample_direction(ctx, mode, sampler, v, active, surface_sample):
    """The next direction at the PathVertex ``v``: ``surface_sample`` (transport's BSDF
    sampling, same arguments and results) in surface lanes, the phase function in medium lanes
    with the same two samples. Returns (pdf_fwd_w, factor, wo_world, pdf_rev_w, active,
    is_delta or None, the samples, the relative index of refraction or None)."""
    m = v.in_medium
    pdf_fwd, factor, wo, pdf_rev, ok, is_delta, u, eta = surface_sample(ctx, mode, sampler, v.surf, active & ~m)
    ph = v._phase().sample(mode, u[0], u[1], active & m)
    if is_delta is not None:
        is_delta = is_delta & ~m
    if eta is not None:
        eta = dr.select(m, 1.0, eta)
    return (dr.select(m, ph.pdf_w, pdf_fwd), mi.Spectrum(dr.select(m, ph.weight, factor)), dr.select(m, ph.wo, wo),
            dr.select(m, ph.pdf_rev_w, pdf_rev), dr.select(m, ph.active, ok), is_delta, u, eta)


def sample_step(ctx, sampler, ray, medium, start, beta, active):
    """Distance sampling along ``ray`` from a point in ``medium`` whose DensityFactor is
    ``start`` (media.MediumTracer.sample_distance): (the vertex reached, a MediumHit; the
    throughput ``beta`` times the step's weight; the step's forward and reverse distance
    densities, mis.MIS.distance's arguments)."""
    ds = ctx.media.sample_distance(ray, None, medium, sampler, start, active)
    # vacuum everywhere (null lobes only): a literal, so that no medium-vertex branch is traced
    collided = ds.collided & active if ctx.media.info.any else mi.Bool(False)
    hit = MediumHit(ds.si, ds.mei, collided, ds.medium)
    return hit, mi.Spectrum(dr.select(active, beta * ds.weight, beta)), ds.pdf_fwd, ds.pdf_rev


def next_vertex(ctx, mis, sampler, v, ray, sub):
    """The walk's next vertex from the PathVertex ``v`` along ``ray``: (the MediumHit, the
    Subpath with the step's weight and distance densities, the squared edge length between
    the two vertices)."""
    hit, sub.beta, pdf_fwd_l, pdf_rev_l = sample_step(ctx, sampler, ray, v.medium_towards(ray.d),
                                                      v.density_factor(ctx.media.info), sub.beta, sub.active)
    sub.mis = mis.distance(sub.mis, pdf_fwd_l, pdf_rev_l)
    return hit, sub, dr.squared_norm(hit.p - v.p)


def surface_start(width):
    """The DensityFactor of a subpath's start (a lens point or an emitter point: no medium vertex)."""
    return DensityFactor.surface(width)


def sensor_medium(ctx, width):
    """The medium around the camera, per lane."""
    return medium_at_sensor(ctx.sensor, width)


class EdgeTerms:
    """What a strategy takes from the edge between its two vertices, one field a line."""

    def __init__(self, tr, pdf_l_far, pdf_l_near):
        self.tr = tr                    # transmittance (Spectrum; 0 where the edge is not made)
        self.pdf_l_far = pdf_l_far      # the edge's distance density at its far end (sampled from the near one)
        self.pdf_l_near = pdf_l_near    # ... at its near end (sampled from the far one)


def edge_terms(ctx, sampler, ray, ends, media, factors, active):
    """The shadow or connection ray ``ray`` from the near end to the far one through media:
    ``ends`` (near point for nothing, far (q, n_q, err_q)) as media.MediumTracer.edge takes its
    ``end``; ``media`` = (the near end's medium towards the far one, the far end's medium
    towards the near one, None: not checked); ``factors`` = the DensityFactors of (near, far).
    Counts the shadow ray in the statistics. Returns EdgeTerms."""
    et = ctx.media.edge(ray, ends, media[0], sampler, active, media[1])
    if ctx.stats is not None:
        ctx.stats.shadow(active, ~et.ok)
    return EdgeTerms(et.tr, et.pdf_l(factors[1]), et.pdf_l(factors[0]))


def connection_edge(ctx, sampler, ray, z, y, d, active):
    """edge_terms of the connection ray ``ray`` from the PathVertex ``z`` to the PathVertex
    ``y`` in the unit direction ``d``: each end's medium towards the other, their densities."""
    info = ctx.media.info
    return edge_terms(ctx, sampler, ray, y.end(), (z.medium_towards(d), y.medium_towards(-d)),
                      (z.density_factor(info), y.density_factor(info)), active)


class EmitterMedia:
    """The medium each emitter lies in, as the scene's geometry says: the emitter's own
    ``get_medium()`` where it has one; else, for an emitter with a position (area, point,
    spot), the medium of the nearest enclosing medium boundary (a shape that is a medium
    transition), found by rays from points of the emitter (``enclosing_medium``); infinite
    emitters lie outside every medium. Area emitters on a medium boundary emit into the side they
    face (``medium``). Mitsuba's point lights report no medium unless given one, yet lie inside
    the fog of a room; a light subpath started in vacuum there would disagree with every camera
    subpath about the medium, so every connection to it would be refused. An area emitter whose
    probe points (PROBES x PROBES over its surface) find different media straddles a boundary (a
    lamp half inside a glass of fog, as in Mitsuba's test scene ``homo_emitter_inside_medium``):
    its medium is searched for per point and direction in the kernels (``per_point``; None where
    no emitter needs it, and no kernel traces the search). Outside every shape lies the medium
    ``outside`` (``outside_medium``: vacuum unless the sensor's medium or the shapes' exteriors
    say otherwise): infinite emitters lie in it, and so does an emitter whose probe rays leave
    the scene without meeting a medium boundary (a point light in a fog that the sensor carries
    and no shape bounds: Mitsuba's volpath lights the fog with it, as bdpt now does)."""
    PROBES = 4

    def __init__(self, scene, offsets, outside=None, around=None, consistent=True, placements=None):
        self.scene, self.offsets = scene, offsets
        # the sphere emitters' placements (endpoints.EmitterTable.sphere_placements; None: found here)
        self.placements = placements if placements is not None else self.sphere_placements(scene)
        self.outside = outside                  # the medium outside every shape (None: vacuum)
        self.around_sensor = around             # the medium the shapes put around the sensor (around_sensor)
        self.consistent = consistent            # no inconsistent declaration seen (sensor_walk), no light across a boundary
        ids, varies = {}, {}
        probed = []                             # (key, emitter) of those found from probe points
        for em in scene.emitters():
            key = int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(em))[0])
            if em.get_medium() is not None:
                ids[key], varies[key] = _medium_id(em.get_medium()), 0
            elif mi.has_flag(em.flags(), mi.EmitterFlags.Infinite):
                ids[key], varies[key] = _medium_id(self.outside), 0
            else:
                probed.append((key, em))
        for (key, em), found in zip(probed, self.probe_media(probed)):
            ids[key] = found[0] if len(found) == 1 else 0
            varies[key] = int(len(found) > 1)
            shape = em.get_shape()
            # (a light across a boundary that is not its own shape's: its points' media differ)
            self.consistent &= not (varies[key] and (shape is None or not shape.is_medium_transition()))
        size = max(list(ids) + [0]) + 1
        self.table = mi.UInt32([ids.get(k, 0) for k in range(size)])
        self.per_point = mi.UInt32([varies.get(k, 0) for k in range(size)]) if any(varies.values()) else None

    @staticmethod
    def sphere_placements(scene):
        """emitter_tables.sphere_placements of the scene's emitters (where no EmitterTable gave them)."""
        emitters = scene.emitters()
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0]) for e in emitters]
        return sphere_placements(sphere_shapes(emitters, ids), max(ids + [0]) + 1)

    def probe_media(self, probed):
        """For each (registry id, emitter) of ``probed`` (emitters with a position and no medium
        of their own): the sorted medium ids (0: vacuum) its PROBES x PROBES probe points lie in,
        found by one walk for all of them (a walk an emitter cost 12 ms each: 0.5 s a render
        with 40 lights)."""
        if not probed:
            return []
        m, pp = len(probed), self.PROBES * self.PROBES
        k = dr.arange(mi.UInt32, m * pp)
        which, j = k // pp, k % pp
        # (the grid computed in the kernel: arrays made from numpy put their memory's alignment
        # in the kernels' code, whose hash then varied from render to render: outside_medium)
        u = (mi.Point2f(mi.Float(j % self.PROBES), mi.Float(j // self.PROBES)) + 0.5) / self.PROBES
        emitters = dr.gather(mi.EmitterPtr, mi.EmitterPtr([em for _, em in probed]), which)
        ps, _ = emitters.sample_position(0.0, u, True)
        ps = sphere_positions(ps, dr.reinterpret_array(mi.UInt32, emitters), self.placements)
        n = dr.select(dr.squared_norm(ps.n) > 0, mi.Vector3f(ps.n), mi.Vector3f(0.0, 0.0, 1.0))
        found = enclosing_medium(self.scene, self.offsets, mi.Point3f(ps.p), n, mi.Bool(True), self.outside)
        per_point = np.array(dr.reinterpret_array(mi.UInt32, found)).reshape(m, pp)
        return [sorted(set(int(i) for i in row)) for row in per_point]

    def medium(self, emitter, p, n, d, active=True):
        """The medium a ray from the point ``p`` of ``emitter`` (normal ``n``) in direction ``d``
        starts in."""
        own = dr.reinterpret_array(mi.MediumPtr, dr.gather(mi.UInt32, self.table,
                                                            dr.reinterpret_array(mi.UInt32, emitter)))
        shape = emitter.get_shape()
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(n))
        si.shape, si.n, si.t = shape, n, 1.0
        on_boundary = active & (dr.reinterpret_array(mi.UInt32, shape) != 0) & si.is_medium_transition()
        if self.per_point is not None:      # straddling emitters: the search from this point
            search = active & ~on_boundary & (dr.gather(mi.UInt32, self.per_point,
                                                        dr.reinterpret_array(mi.UInt32, emitter), active) != 0)
            own = dr.select(search, enclosing_medium(self.scene, self.offsets, p, d, search, self.outside), own)
        return dr.select(on_boundary, si.target_medium(d), own)


def _medium_id(medium):
    return 0 if medium is None else int(dr.reinterpret_array(mi.UInt32, mi.MediumPtr(medium))[0])


@dr.syntax
def enclosing_medium(scene, offsets, p, d, active, outside=None, max_hits=64):
    """The medium around the points ``p`` (per lane; null: vacuum): along the ray from each in
    direction ``d``, the first shape that is a medium transition tells by the side the ray meets
    it on (shapes that are not, opaque or not, lie inside one medium and are passed). A ray that
    leaves the scene finds the medium ``outside`` every shape (``outside_medium``; None:
    vacuum); one that meets ``max_hits`` other shapes first, vacuum."""
    ray = mi.Ray3f(p, dr.normalize(d))
    n = dr.width(p)
    found = dr.zeros(mi.MediumPtr, n)
    going, hits = mi.Bool(active), dr.zeros(mi.UInt32, n)
    left = dr.zeros(mi.Bool, n)
    while going:
        si = offsets.intersect(scene, ray, going)
        left |= going & ~si.is_valid()
        going &= si.is_valid()
        at = going & si.is_medium_transition()
        found = dr.select(at, si.target_medium(-ray.d), found)      # the side the ray came from
        hits += 1
        going &= ~at & (hits < max_hits)
        ray = dr.select(going, spawn(si.p, si.n, offsets.error(si.p, si.shape), ray.d, ray.time), ray)
    if outside is not None:
        found = dr.select(left, medium_array(outside, n), found)
    return found


OUTSIDE_RAYS = 64       # rays from the sensor that find the medium outside every shape (``outside_medium``)


def sensor_rays(n=OUTSIDE_RAYS):
    """OUTSIDE_RAYS directions over the sphere (a Fibonacci sphere; ``n`` lanes, those past
    OUTSIDE_RAYS unused), computed in the kernel (arrays made from numpy have their memory's
    alignment in the kernel's code: its hash varied from render to render)."""
    k = dr.minimum(dr.arange(mi.Float, n), OUTSIDE_RAYS - 1) + 0.5
    z = 1.0 - 2.0 * k / OUTSIDE_RAYS
    phi = dr.pi * (1.0 + 5.0 ** 0.5) * k
    rho = dr.sqrt(dr.maximum(0.0, 1.0 - z * z))
    return mi.Vector3f(rho * dr.cos(phi), rho * dr.sin(phi), z)


def medium_by_id(scene, sensor, ids):
    """The scene's medium whose id (``_medium_id``) most of ``ids`` hold (None: vacuum, or no id)."""
    if ids.size == 0:
        return None
    values, counts = np.unique(ids, return_counts=True)
    best = int(values[np.argmax(counts)])
    from .scene_check import scene_media
    return next((m for m in scene_media(scene, sensor) if _medium_id(m) == best), None)


CAMERA_PROBES = 16      # and a CAMERA_PROBES^2 grid of camera rays look for inconsistent declarations (``sensor_walk``)


class SensorWalk:
    """What rays from the sensor found, walking through every shape (``sensor_walk``), one field a line."""

    def __init__(self, medium, left, inconsistent):
        self.medium = medium                # the medium each ray ended in (numpy ids, ``_medium_id``)
        self.left = left                    # the rays that left the scene (numpy bool)
        self.inconsistent = inconsistent    # a ray met a medium transition whose side it came from declares another medium


def sensor_walk(scene, offsets, sensor, max_hits=256):
    """OUTSIDE_RAYS rays from the sensor's position in every direction and a grid of camera
    rays, each starting in the sensor's medium and taking at each medium transition it passes
    the side it goes into (shapes of any BSDF are passed: this follows the declarations, not the
    light), up to max_hits shapes. A SensorWalk of the first OUTSIDE_RAYS (outside_medium) and
    whether any ray met a transition that declares, on the side the ray came from, another
    medium than the one the ray was in: a sensor in a fog it does not declare, nested shapes
    that each declare a medium inside and none outside (light_path.camera_edge)."""
    n = OUTSIDE_RAYS + CAMERA_PROBES * CAMERA_PROBES
    k = dr.arange(mi.UInt32, n)
    c = dr.maximum(mi.Int32(k) - OUTSIDE_RAYS, 0)
    uv = mi.Point2f((mi.Float(c % CAMERA_PROBES) + 0.5) / CAMERA_PROBES, (mi.Float(c // CAMERA_PROBES) + 0.5) / CAMERA_PROBES)
    cam, _ = sensor.sample_ray(sensor.shutter_open(), 0.5, uv, mi.Point2f(0.5))
    around = k < OUTSIDE_RAYS
    d = sensor_rays(n)
    ray = mi.Ray3f(dr.select(around, mi.Point3f(sensor.world_transform().translation()), cam.o),
                   dr.select(around, d, cam.d))
    medium, left, bad = declaration_walk(scene, offsets, ray, medium_at_sensor(sensor, n), max_hits)
    ids = np.array(dr.reinterpret_array(mi.UInt32, medium))
    return SensorWalk(ids[:OUTSIDE_RAYS], np.array(left)[:OUTSIDE_RAYS], bool(np.any(np.array(bad))))


def declaration_walk(scene, offsets, ray, medium, max_hits=256):
    """Rays ``ray`` starting in ``medium`` (per lane), taking at each medium transition they pass
    the side they go into, through every shape (up to max_hits). Returns (the medium each ends
    in, the rays that left the scene, the rays that met a transition whose side they came from
    declares another medium than the one they were in)."""
    n = dr.width(ray.o)
    going, left, bad = dr.full(mi.Bool, True, n), dr.zeros(mi.Bool, n), dr.zeros(mi.Bool, n)
    for _ in range(max_hits):           # (a Python loop: once per render, on a few hundred rays)
        si = offsets.intersect(scene, ray, going)
        left |= going & ~si.is_valid()
        going &= si.is_valid()
        bad |= going & si.is_medium_transition() & (dr.reinterpret_array(mi.UInt32, si.target_medium(-ray.d))
                                                    != dr.reinterpret_array(mi.UInt32, medium))
        medium = dr.select(going, medium_after(si, ray.d, medium), medium)
        ray = dr.select(going, spawn(si.p, si.n, offsets.error(si.p, si.shape), ray.d, ray.time), ray)
        if not dr.any(going):
            break
    return medium, left, bad


def outside_medium(scene, offsets, sensor, walk=None):
    """The medium outside every shape (None: vacuum), as the scene's declarations say: the
    medium most of the sensor_walk's rays in every direction leave the scene in; vacuum where
    none leaves. A sensor in a fog that no shape bounds (Mitsuba's simplest fog: the sensor's
    ``medium``) finds that fog outside."""
    walk = walk or sensor_walk(scene, offsets, sensor)
    return medium_by_id(scene, sensor, walk.medium[walk.left])


def around_sensor(scene, offsets, sensor, outside):
    """The medium the shapes put around the sensor's position (None: vacuum): along each of
    OUTSIDE_RAYS directions the side of the first medium transition it meets that faces the
    sensor (``enclosing_medium``; a ray that leaves the scene finds ``outside``), the medium
    most of them find. A sensor that declares another (a camera in a fog it does not declare)
    renders as Mitsuba's volpath renders it, its rays in its own medium up to their first
    boundary (light_path.camera_edge), and last_render_info['media'] tells both."""
    origin = mi.Point3f(sensor.world_transform().translation())
    found = enclosing_medium(scene, offsets, dr.zeros(mi.Point3f, OUTSIDE_RAYS) + origin, sensor_rays(),
                             dr.full(mi.Bool, True, OUTSIDE_RAYS), outside)
    return medium_by_id(scene, sensor, np.array(dr.reinterpret_array(mi.UInt32, found)))


def stored_vertex(v, medium, in_medium):
    """A PathVertex from a stored light vertex: ``v`` its vertex.Vertex as store.VertexRecord
    rebuilds it, ``medium`` and ``in_medium`` (UInt32 0/1) its stored medium fields; a medium
    vertex's coefficients are evaluated again at its position."""
    m = in_medium != 0
    si = v.si
    mei = dr.zeros(mi.MediumInteraction3f, dr.width(si.p))
    mei.p, mei.t, mei.time = si.p, 1.0, si.time
    if mi.is_spectral:
        mei.wavelengths = si.wavelengths
    mei.wi = si.to_world(si.wi)
    mei.sh_frame = mi.Frame3f(mei.wi)
    mei.medium = dr.select(m, medium, dr.zeros(mi.MediumPtr, dr.width(si.p)))
    sigma_s, sigma_n, sigma_t = mei.medium.get_scattering_coefficients(mei, m)
    mei.sigma_s, mei.sigma_n, mei.sigma_t = sigma_s, sigma_n, sigma_t
    si_m = mi.SurfaceInteraction3f(si)
    si_m.n = dr.select(m, mi.Normal3f(0.0), si.n)
    si_m.shape = dr.select(m, dr.zeros(mi.ShapePtr, dr.width(si.p)), si.shape)
    bsdf = dr.select(m, dr.zeros(mi.BSDFPtr, dr.width(si.p)), v.bsdf)
    return PathVertex(Vertex(si_m, bsdf, v.err), mei, m, medium)
