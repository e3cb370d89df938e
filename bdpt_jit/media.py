"""Participating media: the building blocks every strategy will call once media are wired into
the walk (docs/media.md lists what is left): which medium a ray is in, the transmittance of an
edge through index-matched (``null``) boundaries, distance sampling with the majorant, and the
medium vertex with its phase function. Nothing here is traced for a scene without media: the
kernels call this module only where ``MediaInfo.any`` (a Python value) says the scene has one.

Measures. A medium vertex lies in a volume: its densities are per unit volume, ``pdf_w`` (the
phase function's, per unit solid angle) times the distance density ``pdf_l`` (per unit length)
over d^2, with no cosine (``MediumVertex.cos`` is 1). A surface reached by a ray through a
medium has the probability ``pdf_l`` of getting there (no unit): T, or its proxy below.

Distance densities (``DistanceSample.pdf_fwd``/``pdf_rev``, ``EdgeTransmittance.pdf_l``):

- homogeneous media, exact: sigma_t T per unit length at a medium vertex, T at a surface; the
  reverse density (the same edge sampled from its other end) takes sigma_t at the start. In
  chromatic media a channel c is chosen per sample (uniformly) and the densities are the mean
  over channels, sum_c p_c / n, so the weight f / mean_c p_c is bounded by n / (the channel's
  share) and no channel makes fireflies: the one-sample spectral MIS of Mitsuba 0.6's
  homogeneous medium (``strategy=balance``, its default) and of Miller, Georgiev and Jarosz,
  "A null-scattering path integral formulation of light transport" (SIGGRAPH 2019, sec. 5).
- heterogeneous media: delta tracking with the medium's majorant m (Mitsuba's, gray for
  ``heterogeneous``): tentative collisions at rate m, each real with the probability
  mean_c sigma_t,c / m and null otherwise (volpath's choice, the balance over channels of the
  null-scattering formulation); a real collision weighs prod(sigma_n,c / mean sigma_n) /
  mean sigma_t, a pass-through prod(sigma_n,c / mean sigma_n): exact f / p per channel, so
  the throughput is unbiased. The *marginal* density of a vertex, sigma_t T, has no closed form
  (T is a ratio-tracking estimate), and an estimate of it in the MIS would differ between the
  strategies that weigh the same path. The MIS therefore uses a deterministic proxy:
  mean_c sigma_t,c(x) T_maj at a medium vertex and T_maj at a surface, with
  T_maj = exp(-m * (length inside the medium's bounding box)). Any deterministic function of the
  path, computed the same way by every strategy, keeps the weights a partition of unity, so the
  estimator stays unbiased; the proxy is zero exactly where the true density is (sigma_t = 0),
  so no strategy that can sample a path gets weight 0 from it. Only the variance depends on how
  close the proxy is to sigma_t T (exact where sigma_t = m). T_maj is floored at TMAJ_FLOOR
  (1e-6) in the densities: exp(-m L) is 0 in float32 beyond m L ~ 104 (and its square in the
  power heuristic leaves the float range sooner), and a strategy whose density came out 0 that
  way lost its share of a path whose ratio-tracked transmittance was far above T_maj (a grid
  with empty voxels under a large majorant: images 1-3% off before the floor). Any floor keeps
  the proxy deterministic, so the weights still sum to one. Mitsuba 0.6 instead integrates tau
  by Simpson quadrature (``method=simpson``).

Both kinds in one edge multiply (the channel choice applies in the homogeneous parts only).
"""

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .jitmath import safe_div, finite_or_zero
from .rays import spawn, spawn_to

MAX_CROSSINGS = 64        # null interfaces one segment may cross (beyond: treated as blocked)
TMAJ_FLOOR = 1e-6         # the MIS proxy T_maj's least value (module docstring: float32 underflow)
PHASE_RADIANCE = mi.PhaseFunctionContext(None, mi.TransportMode.Radiance)
PHASE_IMPORTANCE = mi.PhaseFunctionContext(None, mi.TransportMode.Importance)


@dataclass(frozen=True)
class MediaInfo:
    """What the scene's media need, as plain Python values (trace-time constants):
    any (a medium anywhere), heterogeneous (one is not homogeneous: ratio and delta tracking
    traced), chromatic (a homogeneous medium's sigma_t differs between channels: a channel is
    chosen per distance sample), gray (every medium's sigma_t is the same in all channels, so a
    point a distance-sampled ray passes has survived with the probability T: merging inside
    media by beams, beams.py), partial_null (a shape's BSDF has a Null lobe beside others:
    ``thindielectric``, ``mask``; walks and edges pass such a surface with its Null lobe's
    probability, MediumTracer), varying_albedo (a homogeneous medium's albedo is a volume),
    any_null (a shape's BSDF has a Null lobe: with no medium, the tracer still walks and
    connects through such surfaces, context.media_setup), exclude_null (every partly null BSDF
    is thin-glass-like: asked to leave Null out it samples its delta lobes alone, so a walk that
    stops there samples them so, transport._sample), null_emitters (an emitter's BSDF is ``null``
    alone: walks and edges meet it, scene_check.null_emitter_shape). Built by
    scene_check.media_info."""

    any: bool = False
    heterogeneous: bool = False
    chromatic: bool = False
    gray: bool = False
    partial_null: bool = False
    varying_albedo: bool = False
    any_null: bool = False
    exclude_null: bool = False
    null_emitters: bool = False


def has_medium(medium):
    """Lanes whose MediumPtr is not null (null: vacuum)."""
    return dr.reinterpret_array(mi.UInt32, medium) != 0


def medium_after(si, d, current):
    """The medium a ray in direction ``d`` enters at the hit ``si``: the shape's interior or
    exterior where the shape is a medium transition (``si.target_medium``), else the medium the
    ray was in (a surface that declares no medium lies inside ``current``, as volpath reads it)."""
    return dr.select(si.is_valid() & si.is_medium_transition(), si.target_medium(d), current)


def medium_array(medium, width):
    """A MediumPtr array of ``width`` lanes all pointing to ``medium`` (None: vacuum)."""
    if medium is None:
        return dr.zeros(mi.MediumPtr, width)
    return dr.select(dr.full(mi.Bool, True, width), mi.MediumPtr(medium), dr.zeros(mi.MediumPtr, width))


def medium_at_sensor(sensor, width=1):
    """The medium around the camera (``sensor.get_medium()``, None: vacuum), per lane."""
    return medium_array(sensor.get_medium(), width)


def medium_at_emitter(emitter, n, d, active=True):
    """The medium a light subpath starts in from emitter ``emitter`` (an EmitterPtr) leaving in
    direction ``d`` at a point of normal ``n``: for an area emitter whose shape is a medium
    transition, its exterior or interior by the side of ``d``; else ``emitter.get_medium()``
    (a point light inside a medium sphere reports None unless given one)."""
    own = emitter.get_medium()
    shape = emitter.get_shape()
    on_shape = dr.reinterpret_array(mi.UInt32, shape) != 0
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(n))
    si.shape, si.n, si.t = shape, n, 1.0
    return dr.select(active & on_shape & si.is_medium_transition(), si.target_medium(d), own)


# every lobe flag but Null: a BSDF with the Null flag and none of these passes all light unchanged
_LOBES = int(mi.BSDFFlags.Reflection | mi.BSDFFlags.Transmission) & ~int(mi.BSDFFlags.Null)


def is_null(bsdf, si, null_emitters=True):
    """Lanes whose hit ``si`` is an index-matched boundary: a BSDF whose only lobe is Null (the
    ``null`` plugin). A BSDF with a Null lobe beside others (``thindielectric``, whose straight
    transmission is flagged Null; ``mask`` of opacity below 1) is ``partly_null``: a walk passes it
    with that lobe's probability, counting no bounce, else stops there as a surface vertex
    (MediumTracer._partial_step; a vertex that then draws the Null lobe again ends,
    transport.scatter), and an edge passes it weighted by that lobe's transmission, as volpath's
    shadow rays do. An emitter of such a BSDF on a shape that is no medium transition is met
    instead (scene_check.null_emitter_shape), where ``null_emitters`` (MediaInfo's: False where
    the scene has none, and the shape's virtual calls are left out)."""
    flags = bsdf.flags()
    out = si.is_valid() & mi.has_flag(flags, mi.BSDFFlags.Null) & ((flags & _LOBES) == 0)
    if not null_emitters:
        return out
    shape = si.shape
    return out & ~(shape.is_emitter() & ~shape.is_medium_transition())


def partly_null(bsdf, si, active):
    """Lanes of ``active`` whose hit ``si`` is a BSDF with a Null lobe beside others (is_null),
    and the Spectrum that lobe passes there (``eval_null_transmission``: 1 - R of a thin
    dielectric, 1 - opacity of a mask); 0 elsewhere."""
    flags = bsdf.flags()
    part = active & si.is_valid() & mi.has_flag(flags, mi.BSDFFlags.Null) & ((flags & _LOBES) != 0)
    return part, dr.select(part, bsdf.eval_null_transmission(si, part), 0.0)


def surface_stop(bsdf, si, active):
    """The probability that a walk reaching the surface ``si`` stops there (1 - the mean of its
    Null lobe's transmission, partly_null; 1 on any other surface): a surface's DensityFactor."""
    _, passed = partly_null(bsdf, si, active)
    return dr.select(active, 1.0 - mean(passed), 1.0)


def channel_of(s, c):
    """Component ``c`` (a UInt32 per lane) of the Spectrum ``s``."""
    out = s[0]
    for i in range(1, dr.size_v(mi.Spectrum)):
        out = dr.select(c == i, s[i], out)
    return out


def mean(s):
    """The mean over the channels of a Spectrum. (Not dr.mean, which divides by the array's
    whole size and so puts the wavefront's width in the kernel as a literal: a new kernel for
    every sample count.)"""
    return dr.sum(s, axis=0) * (1.0 / len(s))


def interaction_at(medium, ray, active, t=0.0, coefficients=True):
    """A MediumInteraction3f of ``medium`` at distance ``t`` along ``ray`` (wi = -ray.d, the
    direction towards where the ray came from, as Mitsuba's), with its scattering coefficients
    filled in (one virtual call) unless ``coefficients`` is False."""
    mei = dr.zeros(mi.MediumInteraction3f, dr.width(ray.o))
    mei.p, mei.wi, mei.medium, mei.sh_frame = ray(t), -ray.d, medium, mi.Frame3f(-ray.d)
    mei.t, mei.time = t, ray.time
    if mi.is_spectral:
        mei.wavelengths = ray.wavelengths
    if coefficients:
        sigma_s, sigma_n, sigma_t = medium.get_scattering_coefficients(mei, active)
        mei.sigma_s, mei.sigma_n, mei.sigma_t = sigma_s, sigma_n, sigma_t
    return mei


class DensityFactor:
    """The factor a vertex's medium contributes to a distance density, split by kind (one
    field a line): a homogeneous medium's sigma_t stays per channel inside the channel mean, a
    heterogeneous medium's mean sigma_t multiplies outside it (module docstring)."""
    DRJIT_STRUCT = {
        'sig_hom': mi.Spectrum,   # per-channel factor inside the mean (sigma_t, or 1)
        'sig_het': mi.Float,      # scalar factor outside it (mean sigma_t, or 1)
    }

    def __init__(self, sig_hom=None, sig_het=None):
        self.sig_hom, self.sig_het = sig_hom, sig_het

    def sigma(self):
        """The factor as one number (gray media: sigma_t at a medium vertex, 1 at a surface)."""
        return mean(self.sig_hom) * self.sig_het

    @staticmethod
    def surface(width):
        """A surface end: T alone (probability of reaching it)."""
        return DensityFactor(dr.full(mi.Spectrum, 1.0, width), dr.full(mi.Float, 1.0, width))

    @staticmethod
    def at(info, medium, sigma_t, vertex):
        """The factor at a vertex: ``vertex`` (a mask) a medium vertex of ``medium`` whose
        sigma_t is ``sigma_t``; elsewhere a surface (1, 1)."""
        n = dr.width(sigma_t)
        hom = vertex
        if info.heterogeneous:
            het = vertex & ~medium.is_homogeneous()
            hom = vertex & ~het
            sig_het = dr.select(het, mean(sigma_t), 1.0)
        else:
            sig_het = dr.full(mi.Float, 1.0, n)
        return DensityFactor(dr.select(hom, sigma_t, 1.0), sig_het)


def pdf_l(tr_hom, tmaj, factor):
    """The distance density of an edge (per unit length at a medium vertex, a probability at a
    surface) from its homogeneous per-channel transmittance ``tr_hom``, the majorant
    transmittance ``tmaj`` of its heterogeneous parts (floored: TMAJ_FLOOR), and the end's
    DensityFactor."""
    return finite_or_zero(mean(tr_hom * factor.sig_hom) * factor.sig_het * dr.maximum(tmaj, TMAJ_FLOOR))



def majorant_transmittance(medium, ray, length, active):
    """T_maj = exp(-m L) of a heterogeneous medium along ``ray`` over [0, ``length``], L the
    part inside the medium's bounding box (the MIS proxy of the module docstring; deterministic,
    so every strategy computes the same value for the same edge)."""
    hit, lo, hi = medium.intersect_aabb(ray)
    lo, hi = dr.maximum(lo, 0.0), dr.minimum(hi, length)
    inside = dr.select(active & hit & (hi > lo), hi - lo, 0.0)
    m = medium.get_majorant(interaction_at(medium, ray, active, coefficients=False), active)[0]
    return dr.select(inside > 0, dr.exp(-m * inside), 1.0)


def _copy_ray(ray, maxt):
    """A new ray (own arrays: the tracking loops update it) along ``ray``, bounded at ``maxt``."""
    return mi.Ray3f(mi.Point3f(ray.o), mi.Vector3f(ray.d), mi.Float(maxt), mi.Float(ray.time), ray.wavelengths)


def homogeneous_tr(sigma_t, t):
    """exp(-sigma_t t) per channel; 1 where sigma_t is 0 (also for t infinite)."""
    return mi.Spectrum(dr.select(sigma_t > 0, dr.exp(-sigma_t * t), 1.0))


class EdgeTransmittance:
    """What the transmittance walk of one edge returns, one field a line."""
    DRJIT_STRUCT = {
        'tr': mi.Spectrum,        # transmittance: exact in homogeneous parts, ratio tracking in heterogeneous ones
        'tr_hom': mi.Spectrum,    # the homogeneous parts' exact per-channel T (for pdf_l)
        'tmaj': mi.Float,         # majorant transmittance of the heterogeneous parts (the MIS proxy, for pdf_l)
        'medium': mi.MediumPtr,   # the medium the walk ended in (at the far end)
        'ok': mi.Bool,            # the edge is made: no opaque surface, the ends agree on the medium
    }

    def __init__(self, tr=None, tr_hom=None, tmaj=None, medium=None, ok=None):
        self.tr, self.tr_hom, self.tmaj, self.medium, self.ok = tr, tr_hom, tmaj, medium, ok

    def pdf_l(self, factor):
        """The edge's distance density towards an end whose DensityFactor is ``factor``."""
        return pdf_l(self.tr_hom, self.tmaj, factor)


class DistanceSample:
    """A distance sampled from a ray in a medium (MediumTracer.sample_distance), one field a line."""
    DRJIT_STRUCT = {
        'mei': mi.MediumInteraction3f,    # the real collision (where ``collided``); t from the ray's origin
        'si': mi.SurfaceInteraction3f,    # the surface reached (where not ``collided``; invalid: the ray escaped)
        'collided': mi.Bool,              # a real collision in a medium (a medium vertex)
        'weight': mi.Spectrum,            # T / pdf_l at a collision (no sigma_s: the vertex's value has it), T / P at the surface
        'pdf_fwd': mi.Float,              # sigma_t T per unit length at a collision, T at the surface (proxies: module docstring)
        'pdf_rev': mi.Float,              # the same seen from the end: sigma_t(start) T if the ray left a medium vertex, else T
        'medium': mi.MediumPtr,           # the medium at the end (the collision's, or the one the surface was reached in)
        'ok': mi.Bool,                    # a collision or a surface was found (not: escaped, or too many crossings)
    }

    def __init__(self, mei=None, si=None, collided=None, weight=None, pdf_fwd=None, pdf_rev=None,
                 medium=None, ok=None):
        self.mei, self.si, self.collided, self.weight = mei, si, collided, weight
        self.pdf_fwd, self.pdf_rev, self.medium, self.ok = pdf_fwd, pdf_rev, medium, ok


class MediumTracer:
    """Transmittance and distance sampling in the scene's media. A plain class (not a Dr.Jit
    struct or dataclass: referenced inside symbolic loops it must not become loop state).
    ``offsets``: rays.RayOffsets (rays leaving null interfaces); ``info``: MediaInfo;
    ``stats``: stats.MediumStats or None."""

    def __init__(self, scene, offsets, info, stats=None):
        self.scene, self.offsets, self.info, self.stats = scene, offsets, info, stats

    def _count(self, name, mask):
        if self.stats is not None:
            self.stats.count(name, mask)

    def _kinds(self, medium, active):
        """(homogeneous lanes, heterogeneous lanes or None) of ``medium`` among ``active``."""
        inm = active & has_medium(medium)
        if not self.info.heterogeneous:
            return inm, None
        hom = inm & medium.is_homogeneous()
        return hom, inm & ~hom

    def _cross(self, si, ray, end, medium):
        """(the ray on from the null hit ``si`` towards ``end`` = (q, n_q, err_q), the medium beyond)."""
        err = self.offsets.error(si.p, si.shape)
        on = spawn_to((si.p, si.n, err), end, ray.time, self.offsets.far_rel, ray.wavelengths)
        return on, medium_after(si, ray.d, medium)

    @dr.syntax
    def ratio_track(self, ray, length, medium, sampler, active):
        """Ratio tracking (Novak, Selle and Jarosz, "Residual ratio tracking for estimating
        attenuation in participating media", TOG 2014, sec. 3) in the heterogeneous ``medium``
        along ``ray`` over [0, ``length``]: tentative collisions at the majorant m (Mitsuba's
        ``sample_interaction``, which clips to the medium's box), each multiplying the estimate by
        sigma_n / m = 1 - sigma_t / m. Unbiased for each channel. Returns (T estimate, T_maj)."""
        r = _copy_ray(ray, length)
        tmaj = majorant_transmittance(medium, ray, length, active)
        tr = dr.full(mi.Spectrum, 1.0, dr.width(ray.o))
        going = mi.Bool(active)
        dr.make_opaque(tr)
        while going:
            mei = medium.sample_interaction(r, sampler.next_1d(going), mi.UInt32(0), going)
            tent = going & mei.is_valid()
            m = mei.combined_extinction[0]
            tr[tent] = mi.Spectrum(tr * safe_div(1.0, m) * mei.sigma_n)
            self._count('null_collisions', tent)
            r.o, r.maxt = dr.select(tent, mei.p, r.o), dr.select(tent, r.maxt - mei.t, r.maxt)
            going = tent & (dr.max(tr) > 0)
        return tr, tmaj

    def _segment_tr(self, ray, length, medium, sampler, active, tracking=True):
        """(T estimate, exact homogeneous T, T_maj) of ``medium`` along ``ray`` over [0, length]
        (``tracking`` False: the densities only, T_maj for the estimate in heterogeneous parts)."""
        if not self.info.any:           # vacuum everywhere (null lobes only): nothing to attenuate
            one = dr.full(mi.Spectrum, 1.0, dr.width(ray.o))
            return one, one, mi.Float(1.0)
        hom, het = self._kinds(medium, active)
        sigma_t = interaction_at(medium, ray, hom).sigma_t
        tr_hom = dr.select(hom, homogeneous_tr(sigma_t, length), 1.0)
        if het is None:
            return tr_hom, tr_hom, mi.Float(1.0)
        if not tracking:
            tmaj = majorant_transmittance(medium, ray, length, het)
            return dr.select(het, tmaj, tr_hom), tr_hom, dr.select(het, tmaj, 1.0)
        tr_het, tmaj = self.ratio_track(ray, length, medium, sampler, het)
        return dr.select(het, tr_het, tr_hom), tr_hom, dr.select(het, tmaj, 1.0)

    @dr.syntax
    def edge(self, ray, end, medium, sampler, active, medium_end=None, tracking=True, check=True):
        """The transmittance of the shadow ray ``ray`` (from a vertex in ``medium`` to the point
        ``end`` = (q, n_q, err_q), as rays.spawn_to takes it; None for a ray to infinity, towards
        an environment or directional emitter), crossing null interfaces (each
        a hit whose BSDF's only lobe is Null; the medium changes by medium_after), passing partly
        null surfaces weighted by their Null lobe's transmission (is_null) and stopping with 0 at
        any other surface. ``medium_end``: the medium the far end says it is in
        (None: not checked; ``check``: the lanes where it is); where the walk arrives in another,
        the edge is not made (T = 0) and counted as a medium inconsistency. ``tracking`` False: only the distance densities
        are needed (no ratio tracking; ``tr`` then holds T_maj in heterogeneous parts). Returns
        an EdgeTransmittance."""
        n = dr.width(ray.o)
        tr, tr_hom, tmaj = dr.full(mi.Spectrum, 1.0, n), dr.full(mi.Spectrum, 1.0, n), dr.full(mi.Float, 1.0, n)
        ok, going, crossings = mi.Bool(active), mi.Bool(active), dr.zeros(mi.UInt32, n)
        dr.make_opaque(tr, tr_hom, tmaj, crossings)     # (literals: Dr.Jit folds their updates, and re-recording fails)
        while going:
            si = self.offsets.project_to_surface(self.offsets.intersect(self.scene, ray, going), going)
            hit = going & si.is_valid()
            seg = self._segment_tr(ray, dr.select(hit, si.t, ray.maxt), medium, sampler, going, tracking)
            tr[going], tr_hom[going] = mi.Spectrum(tr * seg[0]), mi.Spectrum(tr_hom * seg[1])
            if self.info.heterogeneous:        # (homogeneous only: T_maj stays 1, a constant)
                tmaj[going] = tmaj * seg[2]
            bsdf = si.bsdf(ray)
            null = hit & is_null(bsdf, si, self.info.null_emitters)
            if self.info.partial_null:      # passed through the Null lobe, with its probability in the density
                part, passed = partly_null(bsdf, si, hit & ~null)
                tr[part], tr_hom[part] = mi.Spectrum(tr * passed), mi.Spectrum(tr_hom * mean(passed))
                null |= part & (dr.max(passed) > 0)
            crossings += 1
            ok[hit & ~null] = False
            ok[null & (crossings >= MAX_CROSSINGS)] = False
            going = null & (crossings < MAX_CROSSINGS)
            ray_on, medium_on = self._cross_any(si, ray, end, medium)
            ray, medium = dr.select(going, ray_on, ray), dr.select(going, medium_on, medium)
        if medium_end is not None:
            wrong = ok & check & (dr.reinterpret_array(mi.UInt32, medium) != dr.reinterpret_array(mi.UInt32, medium_end))
            self._count('medium_inconsistencies', wrong)
            ok &= ~wrong
        return EdgeTransmittance(dr.select(ok, tr, 0.0), tr_hom, tmaj, medium, ok)

    def transmittance(self, ray, end, medium, sampler, active, medium_end=None):
        """The transmittance (a Spectrum; 0 where the edge is not made) of ``edge``."""
        return self.edge(ray, end, medium, sampler, active, medium_end).tr

    # ------------------------------------------------------------------ distance sampling
    def _channel(self, sampler, active):
        """The channel that drives homogeneous distance sampling: uniform in chromatic media
        (one-sample spectral MIS), 0 otherwise (every channel's sigma_t is the same)."""
        if not self.info.chromatic:
            return mi.UInt32(0)
        k = dr.size_v(mi.Spectrum)
        return dr.minimum(mi.UInt32(sampler.next_1d(active) * k), k - 1)

    @dr.syntax
    def delta_track(self, ray, length, medium, sampler, active):
        """Delta tracking (Woodcock) in the heterogeneous ``medium`` along ``ray`` over
        [0, ``length``] with the spectral balance of the module docstring: a tentative collision
        is real with probability mean sigma_t / m. Returns (collided, the collision (t from
        ray.o), the null collisions' weight prod sigma_n,c / mean sigma_n, T_maj up to the end)."""
        r = _copy_ray(ray, length)
        w = dr.full(mi.Spectrum, 1.0, dr.width(ray.o))
        found = dr.zeros(mi.MediumInteraction3f, dr.width(ray.o))
        collided, t_acc, going = dr.zeros(mi.Bool, dr.width(w)), dr.zeros(mi.Float, dr.width(w)), mi.Bool(active)
        dr.make_opaque(w, found, collided, t_acc)
        while going:
            mei = medium.sample_interaction(r, sampler.next_1d(going), mi.UInt32(0), going)
            tent = going & mei.is_valid()
            p_real = safe_div(mean(mei.sigma_t), mei.combined_extinction[0])
            real = tent & (sampler.next_1d(tent) < p_real)
            null = tent & ~real
            w[null] = mi.Spectrum(w * safe_div(1.0, mean(mei.sigma_n)) * mei.sigma_n)
            step = mi.Float(mei.t)        # a copy: mei.t is a reference into mei, overwritten below
            t_acc[tent] = t_acc + step
            collided |= real
            mei.t = t_acc
            found = dr.select(real, mei, found)
            self._count('null_collisions', null)
            r.o, r.maxt = dr.select(null, mei.p, r.o), dr.select(null, r.maxt - step, r.maxt)
            going = null
        tmaj = majorant_transmittance(medium, ray, dr.select(collided, t_acc, length), active)
        return collided, found, w, tmaj

    def _collide(self, ray, length, medium, c, sampler, active):
        """One segment of distance sampling in ``medium`` (channel ``c`` in its homogeneous
        lanes): (collided, the collision, the segment's exact homogeneous T up to the end, its
        null weight, its T_maj, the collision's DensityFactor)."""
        if not self.info.any:           # vacuum everywhere (null lobes only): no collision
            n = dr.width(ray.o)
            one = dr.full(mi.Spectrum, 1.0, n)
            return (dr.zeros(mi.Bool, n), dr.zeros(mi.MediumInteraction3f, n), one, one, mi.Float(1.0),
                    DensityFactor.surface(n))
        hom, het = self._kinds(medium, active)
        mei = interaction_at(medium, ray, hom)
        sigma_c = channel_of(mei.sigma_t, c)
        t = dr.select(sigma_c > 0, -dr.log(1.0 - sampler.next_1d(hom)) * safe_div(1.0, sigma_c), dr.inf)
        collided = hom & (t < length)
        t_end = dr.select(collided, t, length)
        tr_hom = dr.select(hom, homogeneous_tr(mei.sigma_t, t_end), 1.0)
        mei.p, mei.t = ray(t_end), mi.Float(t_end)     # (homogeneous: the same sigma_t everywhere)
        if self.info.varying_albedo:        # its albedo a volume: sigma_s where the collision is
            sigma_s, sigma_n, sigma_t = medium.get_scattering_coefficients(mei, collided)
            mei.sigma_s, mei.sigma_n, mei.sigma_t = (dr.select(collided, a, b) for a, b in
                                                     ((sigma_s, mei.sigma_s), (sigma_n, mei.sigma_n), (sigma_t, mei.sigma_t)))
        w, tmaj = dr.full(mi.Spectrum, 1.0, dr.width(t)), mi.Float(1.0)
        factor = DensityFactor(dr.select(collided, mei.sigma_t, 1.0), dr.full(mi.Float, 1.0, dr.width(t)))
        if het is not None:
            coll_het, mei_het, w_het, tmaj_het = self.delta_track(ray, length, medium, sampler, het)
            coll_het &= het
            mei = dr.select(coll_het, mei_het, mei)
            collided |= coll_het
            w, tmaj = dr.select(het, w_het, w), dr.select(het, tmaj_het, tmaj)
            factor.sig_hom[coll_het] = 1.0
            factor.sig_het[coll_het] = mean(mei_het.sigma_t)
        return collided, mei, tr_hom, w, tmaj, factor

    @dr.syntax
    def sample_distance(self, ray, end, medium, sampler, start, active):
        """The next real collision or surface along ``ray`` (from a vertex in ``medium``;
        ``end``: the far end's (q, n_q, err_q) for rays.spawn_to after null crossings, or None for
        an extension ray), null collisions and null interfaces not counted as bounces.
        ``start``: the DensityFactor of the ray's origin (DensityFactor.at: a medium vertex's
        sigma_t, or DensityFactor.surface) for the reverse density. Returns a DistanceSample:
        weight = f / p per channel (module docstring), pdf_fwd / pdf_rev its distance densities."""
        n = dr.width(ray.o)
        origin = mi.Point3f(ray.o)
        c = self._channel(sampler, active)
        tr_hom, w, tmaj = dr.full(mi.Spectrum, 1.0, n), dr.full(mi.Spectrum, 1.0, n), dr.full(mi.Float, 1.0, n)
        found, si_end = dr.zeros(mi.MediumInteraction3f, n), dr.zeros(mi.SurfaceInteraction3f, n)
        factor = DensityFactor.surface(n)
        collided, ok, going, crossings = dr.zeros(mi.Bool, n), dr.zeros(mi.Bool, n), mi.Bool(active), dr.zeros(mi.UInt32, n)
        dr.make_opaque(tr_hom, w, tmaj, found, si_end, factor, collided, ok, crossings)
        while going:
            si = self.offsets.project_to_surface(self.offsets.intersect(self.scene, ray, going), going)
            hit = going & si.is_valid()
            coll, mei, seg_hom, seg_w, seg_maj, f = self._collide(ray, dr.select(hit, si.t, ray.maxt),
                                                                   medium, c, sampler, going)
            tr_hom[going] = mi.Spectrum(tr_hom * seg_hom)
            if self.info.heterogeneous:        # (homogeneous only: no null weight, T_maj 1)
                w[going], tmaj[going] = mi.Spectrum(w * seg_w), tmaj * seg_maj
            coll &= going
            collided |= coll
            found = dr.select(coll, mei, found)
            factor = dr.select(coll, f, factor)
            bsdf = si.bsdf(ray)
            null = hit & ~coll & is_null(bsdf, si, self.info.null_emitters)
            if self.info.partial_null:      # a partly null surface: passed with its Null lobe's probability
                null, factor = self._partial_step(sampler, (si, bsdf), hit & ~coll & ~null, null, (tr_hom, w, factor))
            crossings += 1
            si_end = dr.select(going & ~coll, si, si_end)
            ok[coll | (hit & ~null)] = True
            going = null & (crossings < MAX_CROSSINGS)
            ray_on, medium_on = self._cross_any(si, ray, end, medium)
            ray, medium = dr.select(going, ray_on, ray), dr.select(going, medium_on, medium)
        self._count('real_collisions', collided)
        found.t = dr.norm(found.p - origin)      # from the sample's origin (not the last segment's)
        return self._distance_result((found, si_end, collided), (tr_hom, w, tmaj), factor, start, medium, ok)

    @staticmethod
    def _partial_step(sampler, hit, active, null, state):
        """At the partly null surfaces among ``active`` (``hit``: the SurfaceInteraction3f and
        its BSDF): the walk passes with the probability c, the mean of the Null lobe's
        transmission (its densities take c; its weight the transmission over c), else stops there
        (the DensityFactor's stop probability 1 - c). ``state`` = (tr_hom, w, factor), updated in
        place. Returns (the lanes that pass or meet a null interface, the factor)."""
        tr_hom, w, factor = state
        part, passed = partly_null(hit[1], hit[0], active)
        c = mean(passed)
        cross = part & (sampler.next_1d(part) < c)
        tr_hom[cross] = mi.Spectrum(tr_hom * c)
        w[cross] = mi.Spectrum(w * passed * safe_div(1.0, c))
        stop = part & ~cross
        return null | cross, DensityFactor(factor.sig_hom, dr.select(stop, factor.sig_het * (1.0 - c), factor.sig_het))

    def _cross_any(self, si, ray, end, medium):
        """The ray on from a null hit: towards ``end`` (a shadow or connection ray) or in the same
        direction, unbounded (an extension ray: ``end`` None)."""
        if end is not None:
            return self._cross(si, ray, end, medium)
        err = self.offsets.error(si.p, si.shape)
        return spawn(si.p, si.n, err, ray.d, ray.time, ray.wavelengths), medium_after(si, ray.d, medium)

    def _distance_result(self, ends, parts, factor, start, medium, ok):
        """The DistanceSample from the walk's ends = (collision, surface, collided) and totals
        ``parts`` = (tr_hom, null weight, T_maj)."""
        (mei, si, collided), (tr_hom, w, tmaj) = ends, parts
        p_mix = mean(tr_hom * factor.sig_hom) * factor.sig_het      # the channel mixture's density (no T_maj)
        weight = finite_or_zero(tr_hom * w * safe_div(1.0, p_mix))
        pdf_fwd = pdf_l(tr_hom, tmaj, factor)
        pdf_rev = pdf_l(tr_hom, tmaj, start)
        return DistanceSample(mei, si, collided, weight, pdf_fwd, pdf_rev, medium, ok)


# ---------------------------------------------------------------------- the medium vertex
class PhaseSample:
    """A direction sampled by a medium vertex's phase function, one field a line."""
    DRJIT_STRUCT = {
        'wo': mi.Vector3f,        # the sampled direction (world space, unit)
        'weight': mi.Spectrum,    # sigma_s * phase / pdf_w (the vertex's value over its density)
        'pdf_w': mi.Float,        # forward density of wo per unit solid angle
        'pdf_rev_w': mi.Float,    # density of the incident direction wi given wo
        'active': mi.Bool,        # a valid sample
    }

    def __init__(self, wo=None, weight=None, pdf_w=None, pdf_rev_w=None, active=None):
        self.wo, self.weight, self.pdf_w, self.pdf_rev_w, self.active = wo, weight, pdf_w, pdf_rev_w, active


class MediumVertex:
    """A real collision in a medium as a subpath vertex: the same operations as vertex.Vertex
    (eval, cos, smooth, spawn, spawn_to), with the phase function for the BSDF and no surface.
    A sibling of Vertex rather than a field of it, so that the loop state of the kernels of
    scenes without media is unchanged (docs/media.md). One field a line."""
    DRJIT_STRUCT = {
        'mei': mi.MediumInteraction3f,   # p, wi (world, towards the previous vertex), medium, sigma_s/n/t, time, wavelengths
    }

    def __init__(self, mei=None):
        self.mei = mei

    @property
    def p(self):
        return self.mei.p

    def cos(self, w):
        """1: no surface, so no cosine in any area (here: volume) conversion."""
        return dr.full(mi.Float, 1.0, dr.width(w))

    def smooth(self, table=None):
        """Every lane: a phase function has no delta lobe, so a medium vertex always connects."""
        return dr.full(mi.Bool, True, dr.width(self.mei.p))

    def _phase(self, mode):
        ctx = PHASE_RADIANCE if mode == 'radiance' else PHASE_IMPORTANCE
        return self.mei.medium.phase_function(), ctx

    def eval(self, ctx, wo_world, mode, active):
        """sigma_s * phase(wi, wo) towards the unit direction ``wo_world``, the forward density
        of ``wo_world`` and the reverse density of wi given wo_world (per unit solid angle; the
        same in both transport modes: phase functions are reciprocal and need no adjoint
        correction). Returns (value, pdf_fwd_w, pdf_rev_w, valid), as Vertex.eval."""
        phase, pctx = self._phase(mode)
        value, pdf_fwd_w = phase.eval_pdf(pctx, self.mei, wo_world, active)
        rev = mi.MediumInteraction3f(self.mei)
        rev.wi, rev.sh_frame = wo_world, mi.Frame3f(wo_world)
        _, pdf_rev_w = phase.eval_pdf(pctx, rev, self.mei.wi, active)
        f = dr.select(active, self.mei.sigma_s * value, 0.0)
        return f, finite_or_zero(pdf_fwd_w), finite_or_zero(pdf_rev_w), active

    def sample(self, mode, u1, u2, active):
        """A direction from the phase function (Mitsuba's sampler): a PhaseSample."""
        phase, pctx = self._phase(mode)
        wo, w, pdf_w = phase.sample(pctx, self.mei, u1, u2, active)
        _, _, pdf_rev_w, _ = self.eval(None, wo, mode, active)
        ok = active & (pdf_w > 0)
        weight = dr.select(ok, finite_or_zero(self.mei.sigma_s * w), 0.0)
        return PhaseSample(wo, weight, finite_or_zero(pdf_w), pdf_rev_w, ok)

    def spawn(self, d):
        """An extension ray in the unit direction ``d``: from the point itself (no surface to
        leave, no offset)."""
        mei = self.mei
        return mi.Ray3f(mei.p, d, dr.largest(mi.Float), mei.time, _wavelengths(mei))

    def spawn_to(self, ctx, q, n_q, err_q):
        """A shadow ray to the point ``q`` (``n_q``, ``err_q`` as Vertex.spawn_to's): the near
        end not offset (normal zero), the far end as rays.spawn_to moves it."""
        mei = self.mei
        zero = dr.zeros(mi.Vector3f, dr.width(mei.p))
        return spawn_to((mei.p, zero, 0.0), (q, n_q, err_q), mei.time, ctx.offsets.far_rel, _wavelengths(mei))

    def density_factor(self, info, active):
        """The DensityFactor of this vertex (the distance densities of the edges at it)."""
        return DensityFactor.at(info, self.mei.medium, self.mei.sigma_t, active)


def _wavelengths(mei):
    return mei.wavelengths if mi.is_spectral else dr.zeros(mi.Color0f)
