"""One step of a subpath's random walk, for both directions: scatter at a vertex (the BSDF
sampled in radiance mode for camera subpaths, in importance mode, the adjoint, for light
subpaths), Russian roulette, the next vertex, and the MIS events of both (mis.MIS.scatter,
mis.MIS.hit). The two tracers (camera_path.py, light_path.py) differ only in the strategies
they evaluate at each vertex; the walk between vertices is this module."""

import drjit as dr
import mitsuba as mi

from . import media_path
from .connect import adjoint_correction, adjoint_eval, reverse_pdf_w, smooth_mask
from .jitmath import safe_div
from .loops import while_once
from .mis import MISState
from .roulette import roulette
from .vertex import IMPORTANCE, RADIANCE, bsdf_context, context_without_null
from .media import _LOBES

PENDING_HITS = True     # False: camera walks carry whole interactions (for side-by-side measurements)
DEFENSIVE = 0.1         # technique lt with the exact adjoint: the share of uniform directions (_defensive)


class Subpath:
    """The state a subpath's walk carries from vertex to vertex, one field a line."""
    DRJIT_STRUCT = {
        'beta': mi.Spectrum,      # throughput up to the current vertex: We / p (camera), Le / p (light)
        'beta_start': mi.Float,   # max component of the throughput at the start (the roulette's reference)
        'mis': MISState,          # the running MIS quantities (mis.py)
        'depth': mi.UInt32,       # edges from the subpath's start to the current vertex
        'active': mi.Bool,        # the walk goes on
    }

    def __init__(self, beta=None, beta_start=None, mis=None, depth=None, active=None):
        self.beta, self.beta_start, self.mis = beta, beta_start, mis
        self.depth, self.active = depth, active


class PendingHit:
    """The next vertex of a walk before its surface interaction is computed, one field a line:
    what a primal camera walk without media carries from one step to the next instead of a whole
    SurfaceInteraction3f (30 varying words against 11; each word of loop state costs pt's
    kernel ~0.1% on scenes/veach-mis.xml). The interaction is computed from it at the next step
    (``resolve``), where the hit's MIS event, which needs the hit's position and normal, is
    taken too (``arrive`` takes the rest of it at once)."""
    DRJIT_STRUCT = {
        'pi': mi.PreliminaryIntersection3f,   # the ray's hit: distance, primitive, shape
        'origin': mi.Point3f,                 # the vertex the ray left (the lens point before the first hit)
    }

    def __init__(self, pi=None, origin=None):
        self.pi = pi
        self.origin = origin if origin is None or isinstance(origin, mi.Point3f) else mi.Point3f(origin)

    def is_valid(self):
        return self.pi.is_valid()


def resolve(ctx, mis, mode, hit, ray, sub):
    """The PendingHit ``hit`` of ``ray`` made a vertex: its SurfaceInteraction3f (as
    scene.ray_intersect computes it, in ``sub``'s active lanes) and ``sub`` with the hit's MIS
    event (the edge's change of measure from ``hit.origin``)."""
    si = ctx.sampling.resolve(hit.pi, ray, sub.active)
    st = mis.hit(sub.mis, dr.squared_norm(si.p - hit.origin), dr.abs(dr.dot(si.n, ray.d)), mode == RADIANCE)
    return si, Subpath(sub.beta, sub.beta_start, st, sub.depth, sub.active)


def _reverse_pdf(ctx, mode, v, bs, wo_world, active, is_delta):
    """(throughput factor of an importance-mode sample where the exact adjoint replaces it, or
    None; the reverse density of the incident direction) at vertex ``v``."""
    si, bsdf = v.si, v.bsdf
    bsdf_ctx = bsdf_context(mode)
    if mode != RADIANCE and ctx.exact_adjoint:
        # BSDFs with their own shading frame (normal/bump maps): the exact adjoint value over
        # the sampling density for smooth samples (Veach's factor for delta ones: the caller's)
        smooth_sample = active & ~is_delta if ctx.has_delta else active
        f_adj, pdf_rev_adj, _ = adjoint_eval(si, bsdf, bs.wo, wo_world, smooth_sample)
        return (smooth_sample, f_adj * safe_div(1.0, bs.pdf)), dr.select(smooth_sample, pdf_rev_adj, 0.0)
    if ctx.has_delta:
        return None, dr.select(is_delta, 0.0,
                               reverse_pdf_w(bsdf, bsdf_ctx, si, bs.wo, active & ~is_delta, ctx.diffuse))
    return None, reverse_pdf_w(bsdf, bsdf_ctx, si, bs.wo, active, ctx.diffuse)


def sample_kept(pdf_w, weight):
    """The lanes of a BSDF sample that a subpath continues from: density and weight > 0, which
    Mitsuba's NaN densities (its microfacet BSDFs' at u = 0 or a tangent wi) fail."""
    return (pdf_w > 0) & (dr.max(weight) > 0)


def _sample(ctx, mode, sampler, v, active, reverse=True, null_lobe=None):
    """The BSDF sampled at ``v`` (lobe and direction samples drawn here): (the direction's
    density per unit solid angle, the throughput factor, the outgoing direction in world space, the reverse density, active, the delta mask
    or None, the samples, the relative index of refraction crossed (None where the scene does
    not refract or the mode is importance: the roulette's, ``scatter``)). ``reverse``: whether
    the reverse density is needed (mis.MIS.reads_reverse); else 0, and no BSDF call for it.
    ``null_lobe``: a list that gets the lanes that sampled a Null lobe (scatter)."""
    si = v.si
    if getattr(v, 'drawn', None) is not None:      # drawn with the emitter sample's evaluation (Vertex.eval_and_draw)
        bs, bsdf_w, (u1, u2) = v.drawn
    else:
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        # at a stop on a partly null surface whose other lobes are delta (thin glass: media.py),
        # those lobes alone, so that its reflection is sampled with probability R, not R^2
        exclude = null_lobe is not None and ctx.media.info.exclude_null
        bsdf_ctx = context_without_null(mode) if exclude else bsdf_context(mode)
        bs, bsdf_w = ctx.sampling.sample_bsdf(v.bsdf, bsdf_ctx, si, u1, u2, active)
    if mode != RADIANCE and ctx.defensive:
        bs, bsdf_w = _defensive(ctx, sampler, v, bs, bsdf_w, active)
    wo_world = si.to_world(bs.wo)
    factor = bsdf_w
    if null_lobe is not None:
        null_lobe.append(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null))
    if mode != RADIANCE:       # the adjoint's shading-normal factor (connect.adjoint_correction)
        corr, ok = adjoint_correction(si, bs.wo, wo_world, active)
        active = active & ok
        factor = bsdf_w * corr
    active = active & sample_kept(bs.pdf, bsdf_w)
    is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) if ctx.has_delta else None
    exact, pdf_rev_w = _reverse_pdf(ctx, mode, v, bs, wo_world, active, is_delta) if reverse else (None, mi.Float(0.0))
    if exact is not None:
        factor = dr.select(exact[0], exact[1], factor)
    eta = dr.select(bs.eta > 0, bs.eta, 1.0) if (ctx.refracts and mode == RADIANCE) else None
    return bs.pdf, factor, wo_world, pdf_rev_w, active, is_delta, (u1, u2), eta


def _defensive(ctx, sampler, v, bs, bsdf_w, active):
    """A light subpath's sample at ``v`` for technique lt with the exact adjoint (normal and bump
    maps: connect.adjoint_eval): with probability DEFENSIVE a uniform direction instead of the
    BSDF's, and the smooth directions' density that of the mixture. The exact adjoint is not
    zero where Mitsuba's importance-mode sampler never goes (5.5% of its value on a normal-mapped
    diffuse surface), and light tracing alone has no other strategy for those paths: lt was
    0.46% dark on tests/stability_cases.normal_mapped. The throughput of smooth samples is then
    the exact adjoint over this density (_reverse_pdf); of delta ones Mitsuba's weight over
    1 - DEFENSIVE. A BSDF without a smooth lobe is sampled as it is. Returns (bs, bsdf_w)."""
    u, u2 = sampler.next_1d(), sampler.next_2d()
    is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    mixed = active & smooth_mask(v.bsdf, ctx.diffuse)      # (a BSDF of delta lobes only: as it is)
    uniform = mixed & (u < DEFENSIVE)
    bs.wo = dr.select(uniform, mi.warp.square_to_uniform_sphere(u2), bs.wo)
    smooth = uniform | ~is_delta
    pdf_smooth = v.bsdf.pdf(bsdf_context(IMPORTANCE), v.si, bs.wo, mixed & smooth)
    share = dr.select(mixed, 1.0 - DEFENSIVE, 1.0)
    bs.pdf = dr.select(mixed & smooth, share * pdf_smooth + DEFENSIVE * mi.warp.square_to_uniform_sphere_pdf(bs.wo),
                       share * bs.pdf)
    bs.sampled_type = dr.select(uniform, mi.UInt32(int(mi.BSDFFlags.GlossyReflection)), bs.sampled_type)
    # (a uniform lane's weight is the exact adjoint's, set by _reverse_pdf: 1 keeps it going)
    bsdf_w = dr.select(uniform, mi.Spectrum(1.0), dr.select(smooth, bsdf_w, bsdf_w * dr.rcp(share)))
    return bs, bsdf_w


def scatter(ctx, mis, mode, sampler, v, sub, merge_here=True):
    """Sample the next direction at vertex ``v`` of subpath ``sub`` (``mis``: the pass's
    mis.MIS; ``merge_here``: camera side, whether a merge at ``v`` is a strategy). Updates the
    throughput, the MIS quantities and the roulette. Returns (the next ray, the new Subpath,
    the delta mask or None without delta lobes, the lobe and direction samples)."""
    null_lobe = None
    if ctx.media is None:
        # (a light subpath's always: with normal maps its exact adjoint comes with it, _reverse_pdf)
        pdf_fwd_w, factor, wo_world, pdf_rev_w, active, is_delta, u, eta = _sample(ctx, mode, sampler, v, sub.active,
                                                                                  mis.reads_reverse or mode != RADIANCE)
    else:       # a surface or a medium vertex (media_path.PathVertex)
        null_lobe = [] if ctx.media.info.partial_null else None
        surface_sample = _sample if null_lobe is None else \
            (lambda *args: _sample(*args, null_lobe=null_lobe))
        pdf_fwd_w, factor, wo_world, pdf_rev_w, active, is_delta, u, eta = media_path.sample_direction(
            ctx, mode, sampler, v, sub.active, surface_sample)
    if null_lobe:       # media: a walk that stopped at a partly null surface goes on through its other lobes
        # (its Null lobe: media.MediumTracer.sample_distance); a null emitter's vertex goes on
        # through its Null lobe (scene_check.null_emitter_shape)
        ends = null_lobe[0] & ~v.in_medium
        if ctx.media.info.null_emitters:
            ends &= (v.bsdf.flags() & _LOBES) != 0
        active = active & ~ends
    beta = sub.beta * factor
    camera_side = mode == RADIANCE
    if ctx.ad and not camera_side:   # the factor without derivatives: the edge's derivative comes with edge_ratio
        beta = mi.Spectrum(sub.beta * dr.detach(beta * safe_div(1.0, dr.detach(sub.beta))))
    st = mis.scatter(sub.mis, v.cos(wo_world), pdf_fwd_w, pdf_rev_w, is_delta, camera_side, merge_here)
    if camera_side and ctx.strategies.ppm:     # vm: only delta lobes go on (a smooth one was merged)
        active = active & (is_delta if is_delta is not None else False)
    if not camera_side and mis.camera_chains and is_delta is not None:
        active = active & ~is_delta      # delta chains are crossed from the camera side only (mis.py)
    # Russian roulette (as Mitsuba's path: from rr_depth on, survival <= 0.95, following the
    # radiance throughput times eta^2 of the refractions so far: a radiance entering glass of
    # index eta carries 1 / eta^2, which alone would end camera subpaths inside glass early)
    beta_start = sub.beta_start if eta is None else sub.beta_start * dr.detach(dr.rcp(dr.square(eta)))
    beta, active = roulette(beta, beta_start, sub.depth, ctx.rr_depth, active, sampler.next_1d())
    ray = v.spawn(wo_world)
    return (dr.detach(ray) if ctx.ad else ray), Subpath(beta, beta_start, st, sub.depth, active), is_delta, u


def advance(ctx, mis, mode, sampler, v, sub, merge_here=True):
    """Scatter at ``v`` and find the next vertex (in a differentiable pass a material point,
    the edge's derivative in the throughput: gradients.py). Returns (the ray, the next hit, the
    Subpath, the squared edge length between the two vertices, whether ``v`` scattered through
    a delta lobe, and with media the Subpath after the scatter, before the distance step (None
    without). The hit is not yet accounted for: ``arrive`` does that."""
    ray, sub, is_delta, u = scatter(ctx, mis, mode, sampler, v, sub, merge_here)
    scattered = None
    if deferred(ctx, mode):     # the interaction and the MIS event at the next step (PendingHit)
        si_next, dist2 = PendingHit(ctx.sampling.preliminary(ray, sub.active), v.p), None
    elif ctx.media is None:
        si_next, beta, dist2 = ctx.sampling.next_vertex(mode == RADIANCE, v, ray, u, is_delta, sub.beta, sub.active)
        sub.beta = beta
    else:       # distance sampling: a medium vertex or a surface (media_path.MediumHit)
        scattered = Subpath(sub.beta, sub.beta_start, sub.mis, sub.depth, sub.active)
        si_next, sub, dist2 = media_path.next_vertex(ctx, mis, sampler, v, ray, sub)
    if ctx.stats is not None:
        ctx.stats.ray('camera' if mode == RADIANCE else 'light', sub.active, si_next.is_valid())
    was_delta = is_delta if is_delta is not None else mi.Bool(False)
    return ray, si_next, sub, dist2, was_delta, scattered


def arrive(mis, mode, sub, si, ray, dist2):
    """The walk reaches the hit ``si`` of ``ray`` (a SurfaceInteraction3f, or a
    media_path.MediumHit in a scene with media; ``dist2``: the edge's squared length): lanes
    that left the scene end, the MIS quantities take the edge's change of measure, depth + 1."""
    active = sub.active & si.is_valid()
    if isinstance(si, PendingHit):      # the MIS event where the interaction is computed (resolve)
        return Subpath(sub.beta, sub.beta_start, sub.mis, sub.depth + 1, active)
    cos_hit = si.cos(ray.d) if isinstance(si, media_path.MediumHit) else dr.abs(dr.dot(si.n, ray.d))
    st = mis.hit(sub.mis, dist2, cos_hit, mode == RADIANCE)
    return Subpath(sub.beta, sub.beta_start, st, sub.depth + 1, active)


def deferred(ctx, mode):
    """Whether a walk carries its next vertex as a PendingHit: camera subpaths of primal
    passes without media (a light subpath's first hit is needed whole for its MIS start, and a
    differentiable pass's hits carry the edges' derivatives, gradients.py)."""
    return (PENDING_HITS and mode == RADIANCE and ctx.media is None and not ctx.ad
            and not ctx.see_through_emitters)


def walk(ctx, mis, sampler, tracer, si, ray, sub, carry):
    """The random walk of a subpath from its hit ``si`` (found by ``ray``), the same loop for
    both directions: at each vertex the tracer evaluates its strategies, then the walk scatters
    and finds the next vertex. ``tracer`` (a LightTracer or a CameraTracer) gives:

        mode                 RADIANCE (camera subpaths) or IMPORTANCE (light subpaths)
        label                the loop's name in the kernels
        go_on(sub, carry)    the lanes that go on
        vertex(si, ray)      the vertex.Vertex at a hit
        at_vertex(v, ray, sub, carry) -> (sub, carry, merge_here)   its strategies at v
        after_step(ray, si, v, sub, carry, was_delta) -> carry  what follows the step (before the hit counts)
        segment(v, ray, si, scattered, carry, was_delta) -> carry  with media, where ``segments``:
                             the step's segment (beams.py; ``scattered``: the Subpath before the step)

    ``carry``: the tracer's own loop state (a tuple of Dr.Jit values). ``si`` may be a
    PendingHit (``deferred``): the walk then carries its hits so. Returns (si, sub, carry)
    where the walk stopped. ``sampler``'s state is loop state. The loop is recorded once
    (loops.while_once)."""
    mode = tracer.mode

    def step(objects, state):
        si, ray, sub, carry = state
        if isinstance(si, PendingHit):
            si, sub = resolve(ctx, mis, mode, si, ray, sub)
        v = tracer.vertex(si, ray)
        sub, carry, merge_here = tracer.at_vertex(v, ray, sub, carry)
        ray, si, sub, dist2, was_delta, scattered = advance(ctx, mis, mode, sampler, v, sub, merge_here)
        if scattered is not None and tracer.segments:
            carry = tracer.segment(v, ray, si, scattered, carry, was_delta)
        carry = tracer.after_step(ray, si, v, sub, carry, was_delta)
        return objects, (si, ray, arrive(mis, mode, sub, si, ray, dist2), carry)

    def going(objects, state):
        return tracer.go_on(state[2], state[3])

    _, (si, _, sub, carry) = while_once(tracer.label, (sampler,), (si, ray, sub, carry), going, step,
                                        enabled=not ctx.ad)
    return si, sub, carry
