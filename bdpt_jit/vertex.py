"""A subpath vertex and what every strategy asks of it: its value towards a direction in either
transport mode with both densities, the cosine there, the rays it spawns, and the one
visibility test between two points, which returns a transmittance.

A vertex today is a point on a surface: the hit (``si``: position, geometric normal, shading
frame, incident direction, shape), its scatterer (the BSDF) and the bound on its position's
floating-point error (rays.RayOffsets), from which every ray it spawns is offset. A vertex kind
without a surface (a medium vertex) would answer ``cos`` with 1 and evaluate a phase function:
the strategies reach vertices only through these operations."""

import drjit as dr
import mitsuba as mi

from .connect import (CTX_IMPORTANCE, CTX_RADIANCE, adjoint_correction, eval_camera_vertex, eval_light_vertex,
                      reverse_pdf_w, smooth_mask)
from .rays import offset_origin, spawn, spawn_to, spawn_to_emitter

RADIANCE = 'radiance'           # a camera subpath's vertex: it transports radiance
IMPORTANCE = 'importance'       # a light subpath's vertex: it transports importance
MAX_EMITTER_SKIPS = 16          # emitter shapes a hidden-emitter ray passes (past_emitter_shapes)


def bsdf_context(mode):
    """Mitsuba's BSDF context of a transport mode (RADIANCE or IMPORTANCE)."""
    return CTX_RADIANCE if mode == RADIANCE else CTX_IMPORTANCE


def _without_null(transport_mode):
    c = mi.BSDFContext(transport_mode)
    c.type_mask = int(mi.BSDFFlags.All) & ~int(mi.BSDFFlags.Null)      # every lobe kind but Null
    return c


CTX_RADIANCE_NO_NULL = _without_null(mi.TransportMode.Radiance)
CTX_IMPORTANCE_NO_NULL = _without_null(mi.TransportMode.Importance)


def context_without_null(mode):
    """The BSDF context of ``mode`` that leaves Null lobes out (media.MediaInfo.exclude_null)."""
    return CTX_RADIANCE_NO_NULL if mode == RADIANCE else CTX_IMPORTANCE_NO_NULL


class Vertex:
    """One vertex, one field a line (a Dr.Jit struct: it can be stored, selected, carried)."""
    DRJIT_STRUCT = {
        'si': mi.SurfaceInteraction3f,    # the hit: p, geometric normal n, sh_frame, wi (local), shape
        'bsdf': mi.BSDFPtr,               # the scatterer
        'err': mi.Float,                  # bound on the position's error (rays.RayOffsets.error)
    }

    def __init__(self, si=None, bsdf=None, err=None):
        self.si, self.bsdf, self.err = si, bsdf, err
        self.drawn = None       # (not a struct field) the scatter's BSDF sample, if eval_and_draw drew it

    @classmethod
    def at(cls, ctx, si, ray=None):
        """The vertex at the hit ``si`` (``ray``: the ray that found it, for the BSDF lookup)."""
        return cls(si, si.bsdf(ray) if ray is not None else si.bsdf(), ctx.offsets.error(si.p, si.shape))

    @property
    def p(self):
        return self.si.p

    def cos(self, w):
        """|cos| between the geometric normal and the unit direction ``w``."""
        return dr.abs(dr.dot(self.si.n, w))

    def smooth(self, table=None):
        """Lanes whose scatterer has a smooth (connectable) component."""
        return smooth_mask(self.bsdf, table)

    def eval(self, ctx, wo_world, mode, active):
        """The vertex's value towards ``wo_world`` (radiance mode: f |cos_s|; importance mode:
        the adjoint with its change of measure, connect.eval_light_vertex), the forward density
        of ``wo_world`` and the reverse density of the incident direction, per unit solid angle.
        Returns (value, pdf_fwd_w, pdf_rev_w, valid)."""
        if mode == RADIANCE:
            f, pdf_fwd_w, pdf_rev_w = eval_camera_vertex(self.si, self.bsdf, wo_world, active, ctx.diffuse)
            return f, pdf_fwd_w, pdf_rev_w, active
        return eval_light_vertex(self.si, self.bsdf, wo_world, active, ctx.exact_adjoint, ctx.diffuse)

    def eval_and_draw(self, ctx, wo_world, mode, sampler, active):
        """``eval``'s value towards ``wo_world``, its forward density and validity, and in the
        same BSDF call (Mitsuba's ``eval_pdf_sample``, as its ``path`` makes it) the BSDF sample
        of the scatter at this vertex, kept in ``drawn`` for transport.scatter, in the lanes
        ``active`` (those that scatter). One call instead of two: 6% of a minimal path tracer's
        time on scenes/veach-mis.xml. The scatter's samples are drawn from ``sampler`` now, in
        the order the scatter would draw them. Not for BSDFs that need the exact adjoint
        (importance mode there: connect.adjoint_eval)."""
        u1, u2 = sampler.next_1d(), sampler.next_2d()
        wo_local = self.si.to_local(wo_world)
        f, pdf_fwd_w, bs, bsdf_w = self.bsdf.eval_pdf_sample(bsdf_context(mode), self.si, wo_local, u1, u2, active)
        self.drawn = (bs, bsdf_w, (u1, u2))
        if mode == RADIANCE:
            return f, pdf_fwd_w, active
        corr, valid = adjoint_correction(self.si, wo_local, wo_world, active)
        return f * corr, pdf_fwd_w, valid

    def pdf_rev_w(self, ctx, wo_world, mode, active):
        """The density of the incident direction given ``wo_world`` (``eval``'s pdf_rev_w)."""
        return reverse_pdf_w(self.bsdf, bsdf_context(mode), self.si, self.si.to_local(wo_world), active, ctx.diffuse)

    def spawn(self, d):
        """An extension ray in the unit direction ``d``."""
        si = self.si
        return spawn(si.p, si.n, self.err, d, si.time, si.wavelengths)

    def spawn_to(self, ctx, q, n_q, err_q):
        """A shadow ray to the point ``q`` (``n_q``, ``err_q``: its surface, or zero and 0 for a
        point on none)."""
        si = self.si
        return spawn_to((si.p, si.n, self.err), (q, n_q, err_q), si.time, ctx.offsets.far_rel, si.wavelengths)

    def spawn_to_emitter(self, ctx, ds):
        """A shadow ray to the emitter sample ``ds`` (rays.spawn_to_emitter)."""
        si = self.si
        return spawn_to_emitter((si.p, si.n, self.err), ds, ctx.emitters.error_at(ds), si.time,
                                ctx.offsets.far_rel, si.wavelengths, ctx.emitters.kinds(ds.emitter).infinite)


def visibility(ctx, ray, active):
    """The transmittance along the shadow ray ``ray`` (a Spectrum: 1 where nothing blocks it,
    0 where something does or the lane is not ``active``), counted in the statistics (blocked
    shadow rays)."""
    blocked = ctx.scene.ray_test(ray, active)
    if ctx.stats is not None:
        ctx.stats.shadow(active, blocked)
    return mi.Spectrum(dr.select(active & ~blocked, 1.0, 0.0))


def past_emitter_shapes(ctx, ray, active):
    """``ray`` started past the area emitters' shapes it meets first (hide_emitters: camera rays
    see through them, as Mitsuba's `path` skips them, its skip_area_emitters; a t=1 shadow ray,
    the same segment from the other end, passes them too). Its far end stays where it was."""
    far = ray.o + ray.d * dr.select(ray.maxt < dr.largest(mi.Float), ray.maxt, 0.0)

    def body(ray, skips, live):
        pi = ctx.scene.ray_intersect_preliminary(ray, False, live)
        live &= pi.is_valid() & pi.shape.is_emitter()
        si = ctx.sampling.resolve(pi, ray, live)
        o = offset_origin(si.p, si.n, ctx.offsets.error(si.p, si.shape), ray.d)
        maxt = dr.select(ray.maxt < dr.largest(mi.Float), dr.dot(far - o, ray.d), ray.maxt)
        ray.o = dr.select(live, o, ray.o)
        ray.maxt = dr.select(live, maxt, ray.maxt)
        live &= maxt > 0
        return ray, skips + 1, live

    ray, _, _ = dr.while_loop((mi.Ray3f(ray), mi.UInt32(0), mi.Bool(active)),
                              lambda ray, skips, live: live & (skips < MAX_EMITTER_SKIPS), body,
                              label='bdpt_past_emitters')
    return ray


def visible(tr):
    """The lanes a transmittance lets through."""
    return dr.max(tr) > 0
