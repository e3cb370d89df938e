"""The random decisions of a pass and the vertices they find: emission, BSDF and emitter
sampling, ray intersection, and the next vertex of a walk. A primal pass uses this class as it
is; a differentiable pass uses gradients.ADSampling, which makes the same decisions without
derivatives and attaches each edge's derivative (gradients.py). The Context holds the one a
render uses (``ctx.sampling``), so the tracers never ask which kind of pass they are in."""

import weakref

import drjit as dr
import mitsuba as mi

from . import connect


class Sampling:
    """Primal sampling for the Context ``ctx``. It holds the Context by a weak reference: the
    Context holds it, and a cycle would leave the Context, with the scene and its Dr.Jit arrays,
    to the cyclic garbage collector, which frees them at whatever allocation it runs, possibly
    while another scene's kernels are traced. With the cycle, later renders in the same process
    (Mitsuba's own ptracer among them) failed with virtual calls reaching base classes
    ("Texture::sample_spectrum(): not implemented", "Endpoint::eval_direction(): not
    implemented") in tests/test_coverage.py run alone; without it they pass."""

    def __init__(self, ctx):
        self.ctx = weakref.proxy(ctx)

    def intersect(self, ray, active, primary=False):
        """scene.ray_intersect; hits on triangle meshes moved onto their triangle's plane
        (rays.RayOffsets.project_to_triangle: the mesh error bound assumes it). ``primary``: a
        camera ray's first hit."""
        si = self.ctx.offsets.intersect(self.ctx.scene, ray, active)
        return self.ctx.offsets.project_to_surface(si, active)

    def preliminary(self, ray, active):
        """scene.ray_intersect_preliminary: the hit without its surface interaction
        (transport.PendingHit; ``resolve`` completes it)."""
        return self.ctx.scene.ray_intersect_preliminary(ray, False, active)

    def resolve(self, pi, ray, active):
        """The surface interaction of the preliminary hit ``pi`` of ``ray``: what ``intersect``
        returns for ``ray`` (Mitsuba's scene.ray_intersect is these two steps)."""
        pi = self.ctx.offsets.clamp_curve_ends(pi, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        return self.ctx.offsets.project_to_surface(si, active)

    def sample_bsdf(self, bsdf, mode, si, u1, u2, active):
        """connect.sample_bsdf (the diffuse table's lanes without a virtual call)."""
        return connect.sample_bsdf(bsdf, mode, si, u1, u2, active, self.ctx.diffuse)

    def sample_direct(self, si, u, active):
        """Emitter sampling from ``si`` (s=1): endpoints.EmitterTable.sample_direct."""
        return self.ctx.emitters.sample_direct(si, u, active)

    def sample_emission(self, u_sel, u_pos, u_dir, active, wavelengths=None):
        """A light subpath's start: endpoints.EmitterTable.sample_emission."""
        return self.ctx.emitters.sample_emission(self.ctx.time, u_sel, u_pos, u_dir, active, wavelengths)

    def first_hit(self, e, si, u_dir, active):
        """The throughput at the light subpath's first hit ``si`` of the emission ``e`` (and
        the hit, whose incident direction a differentiable pass recomputes)."""
        return e.beta, si

    def next_vertex(self, camera_side, v, ray, u, is_delta, beta, active):
        """The vertex that ``ray`` (sampled at vertex ``v`` with the samples ``u``) finds:
        returns it, the throughput and the squared length of the edge between the two vertices,
        not from the offset origin (rays.py: at grazing angles they differ by far more than
        rounding, and every density would follow t)."""
        si_next = self.intersect(ray, active)
        return si_next, beta, dr.squared_norm(si_next.p - v.si.p)
