"""Emitter sampling from a camera vertex (s=1) and its density, for every emitter kind: Mitsuba's
``scene.sample_emitter_direction`` and ``pdf_emitter_direction``, except for sphere emitters
that look small from the reference point, whose visible cone bdpt samples itself. A part of
endpoints.EmitterTable (a base class of it), kept in a module of its own for length."""

import drjit as dr
import mitsuba as mi

from .jitmath import finite_or_zero, safe_div

# (r/d)^2 below which a sphere emitter's visible cone is sampled here (small_sphere); above it
# Mitsuba's cone sampling is exact to ~1e-5 in float32
SMALL_SPHERE = 1e-2
# where every emitter is a sphere of constant radiance (EmitterTable.all_spheres): (r/d)^2 below
# which the cone is sampled here, from any point outside the sphere (Mitsuba samples points
# inside or on it by area)
OUTSIDE = 1.0 - 1e-4


class DirectSampling:
    """Needs, from EmitterTable: scene, has_sphere, sph_r, sph_c, all_spheres, sph_le, pdf_select.

    Where every emitter of the scene is a sphere of constant radiance (``all_spheres``), the
    cone is sampled here from every point outside the sphere, small-looking or not, and the
    radiance read from the table: no virtual call to an emitter in emitter sampling or its
    density but for points inside a sphere (6% of pt's kernel time on scenes/veach-mis.xml,
    four sphere lights: Mitsuba's ``sample_direction`` and ``eval_direction`` in every lane;
    the first stays for the points inside a sphere, masked: in a branch that packets without one
    skip it gained nothing measurable)."""

    def small_sphere(self, emitter, ref_p):
        """Lanes whose emitter is a sphere of radius r seen from ``ref_p`` at a distance d with
        (r/d)^2 < SMALL_SPHERE (< OUTSIDE where ``all_spheres``), and there the cone's
        1 - cos(theta_max) (+ centre, radius, sin^2(theta_max) = (r/d)^2).

        Mitsuba samples a sphere's visible cone with cos(theta_max) = sqrt(1 - (r/d)^2) in
        float32: once (r/d)^2 is a few ulps of 1 its sample weight is biased (+11% at
        r/d = 7e-4, +49% at 4e-4), below 2^-24 its density is +inf and its weight 0. There the
        cone is sampled from 1 - cos(theta_max) = (r/d)^2 / (1 + cos(theta_max)), which keeps
        its precision (sample_direct, pdf_direct_w)."""
        idx = dr.reinterpret_array(mi.UInt32, emitter)
        r = dr.gather(mi.Float, self.sph_r, idx)
        centre = dr.gather(mi.Point3f, self.sph_c, idx)
        d2 = dr.squared_norm(ref_p - centre)
        small = (r > 0) & (dr.square(r) < (OUTSIDE if self.all_spheres else SMALL_SPHERE) * d2)
        # (elsewhere a value that keeps the cone's arithmetic finite in the lanes it does not serve)
        sin2_max = dr.select(small, dr.square(r) * safe_div(1.0, d2), SMALL_SPHERE)
        one_minus_cos_max = sin2_max / (1.0 + dr.safe_sqrt(1.0 - sin2_max))
        return small, centre, r, sin2_max, one_minus_cos_max

    @staticmethod
    def _cone_pdf_w(one_minus_cos_max):
        """Uniform density on the visible cone, per unit solid angle at the reference point."""
        return safe_div(1.0, 2.0 * dr.pi * one_minus_cos_max)

    @staticmethod
    def _cone_point(ref_p, centre, r, sin2_max, one_minus_cos_max, u2):
        """The point of the sphere (and its normal) seen from ``ref_p`` in the direction drawn
        uniformly in solid angle from the visible cone (pbrt-v4's Sphere::Sample: the angle
        alpha at the centre from theta), 1 - cos(theta) and sin^2(theta) formed without
        cancellation."""
        x = u2.x * one_minus_cos_max                        # 1 - cos(theta)
        cos_t = 1.0 - x
        sin2_t = x * (2.0 - x)
        cos_a = sin2_t * dr.rsqrt(sin2_max) + cos_t * dr.safe_sqrt(1.0 - sin2_t * safe_div(1.0, sin2_max))
        sin_a = dr.safe_sqrt(1.0 - dr.square(cos_a))
        s_phi, c_phi = dr.sincos(2.0 * dr.pi * u2.y)
        frame = mi.Frame3f(dr.normalize(centre - ref_p))
        n = frame.to_world(mi.Vector3f(-sin_a * c_phi, -sin_a * s_phi, -cos_a))
        return dr.fma(n, r, centre), n

    def sample_direct(self, ref_it, u, active):
        """Emitter sampling from ``ref_it``: Mitsuba's ``scene.sample_emitter_direction``
        (emitter chosen by ``scene.sample_emitter``, then the emitter's own sample_direction),
        except small-looking sphere emitters (small_sphere). Returns (ds, Le / pdf)."""
        if not self.has_sphere:
            return self.scene.sample_emitter_direction(ref_it, u, False, active)
        index, sel_w, u_x = self.scene.sample_emitter(u.x, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), index, active)
        u2 = mi.Point2f(u_x, u.y)
        small, centre, r, sin2_max, omc = self.small_sphere(emitter, ref_it.p)
        small &= active
        ds, spec = emitter.sample_direction(ref_it, u2, active & ~small)
        p, n = self._cone_point(ref_it.p, centre, r, sin2_max, omc, u2)
        to_p = p - ref_it.p
        dist = dr.norm(to_p)
        ds_s = dr.zeros(mi.DirectionSample3f, dr.width(u))
        ds_s.p, ds_s.n, ds_s.d, ds_s.dist, ds_s.time = p, n, to_p * safe_div(1.0, dist), dist, ref_it.time
        ds_s.emitter, ds_s.delta = emitter, mi.Bool(False)
        ds_s.pdf = self._cone_pdf_w(omc)
        if self.all_spheres:    # (the cone's point faces ref_it: the emitting side)
            le = dr.gather(mi.Spectrum, self.sph_le, dr.reinterpret_array(mi.UInt32, emitter), small)
        else:
            le = emitter.eval_direction(ref_it, ds_s, small)
        spec_s = le * safe_div(1.0, ds_s.pdf)
        ds = dr.select(small, ds_s, ds)
        spec = dr.select(small, spec_s, spec)
        ds.pdf *= self.scene.pdf_emitter(index, active)
        return ds, spec * sel_w

    def pdf_direct_w(self, ref_it, ds, active):
        """Density per unit solid angle at ``ref_it`` of sample_direct choosing the emitter
        point or direction ``ds``, emitter choice included; 0 where a density is not finite
        (finite_or_zero)."""
        if not self.has_sphere:
            return finite_or_zero(self.scene.pdf_emitter_direction(ref_it, ds, active))
        small, _, _, _, omc = self.small_sphere(ds.emitter, ref_it.p)
        pdf_w = self.scene.pdf_emitter_direction(ref_it, ds, active & ~small)
        cone = self._cone_pdf_w(omc) * self.pdf_select(ds.emitter)
        return finite_or_zero(dr.select(small, cone, pdf_w))
