"""Emitter sampling from a camera vertex (s=1) and its density, for every emitter kind: Mitsuba's
``scene.sample_emitter_direction`` and ``pdf_emitter_direction``, except for sphere emitters
that look small from the reference point, whose visible cap bdpt samples by area itself. A
part of endpoints.EmitterTable (a base class of it), kept in a module of its own for length."""

import drjit as dr
import mitsuba as mi

from .jitmath import finite_or_zero, safe_div

# (r/d)^2 below which a sphere emitter's visible cap is sampled by area (small_sphere); above it
# Mitsuba's cone sampling is exact to ~1e-5 in float32
SMALL_SPHERE = 1e-2


class DirectSampling:
    """Needs, from EmitterTable: scene, has_sphere, sph_r, sph_c, pdf_select."""

    def small_sphere(self, emitter, ref_p):
        """Lanes whose emitter is a sphere of radius r seen from ``ref_p`` at a distance d with
        (r/d)^2 < SMALL_SPHERE, and there cos of the visible cap's rim, r/d (+ centre, radius).

        Mitsuba samples a sphere's visible cone with cos(theta_max) = sqrt(1 - (r/d)^2) in
        float32: once (r/d)^2 is a few ulps of 1 its sample weight is biased (+11% at
        r/d = 7e-4, +49% at 4e-4), below 2^-24 its density is +inf and its weight 0. There the
        visible cap is sampled uniformly by area instead (sample_direct, pdf_direct_w)."""
        idx = dr.reinterpret_array(mi.UInt32, emitter)
        r = dr.gather(mi.Float, self.sph_r, idx)
        centre = dr.gather(mi.Point3f, self.sph_c, idx)
        d2 = dr.squared_norm(ref_p - centre)
        small = (r > 0) & (dr.square(r) < SMALL_SPHERE * d2)
        z_min = r * dr.rsqrt(dr.select(small, d2, 1.0))
        return small, centre, r, z_min

    def _cap_pdf_w(self, r, z_min, cos_y, dist):
        """Uniform area density on the visible cap, 1 / (2 pi r^2 (1 - z_min)), per unit solid
        angle at the reference point."""
        pdf_a = safe_div(1.0, 2.0 * dr.pi * dr.square(r) * (1.0 - z_min))
        return pdf_a * safe_div(dr.square(dist), dr.abs(cos_y))

    def sample_direct(self, ref_it, u, active):
        """Emitter sampling from ``ref_it``: Mitsuba's ``scene.sample_emitter_direction``
        (emitter chosen by ``scene.sample_emitter``, then the emitter's own sample_direction),
        except small-looking sphere emitters (small_sphere). Returns (ds, Le / pdf)."""
        if not self.has_sphere:
            return self.scene.sample_emitter_direction(ref_it, u, False, active)
        index, sel_w, u_x = self.scene.sample_emitter(u.x, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), index, active)
        u2 = mi.Point2f(u_x, u.y)
        small, centre, r, z_min = self.small_sphere(emitter, ref_it.p)
        small &= active
        ds, spec = emitter.sample_direction(ref_it, u2, active & ~small)
        # uniform on the cap {n : dot(n, axis) >= z_min} facing the reference point
        axis = dr.normalize(ref_it.p - centre)
        z = dr.fma(-u2.x, 1.0 - z_min, 1.0)
        sin_z = dr.safe_sqrt(dr.fma(-z, z, 1.0))
        s_phi, c_phi = dr.sincos(2.0 * dr.pi * u2.y)
        n = mi.Frame3f(axis).to_world(mi.Vector3f(sin_z * c_phi, sin_z * s_phi, z))
        p = dr.fma(n, r, centre)
        to_p = p - ref_it.p
        dist = dr.norm(to_p)
        d = to_p * safe_div(1.0, dist)
        ds_s = dr.zeros(mi.DirectionSample3f, dr.width(u))
        ds_s.p, ds_s.n, ds_s.d, ds_s.dist, ds_s.time = p, n, d, dist, ref_it.time
        ds_s.emitter, ds_s.delta = emitter, mi.Bool(False)
        ds_s.pdf = self._cap_pdf_w(r, z_min, dr.dot(n, d), dist)
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
        small, _, r, z_min = self.small_sphere(ds.emitter, ref_it.p)
        pdf_w = self.scene.pdf_emitter_direction(ref_it, ds, active & ~small)
        cap = self._cap_pdf_w(r, z_min, dr.dot(ds.n, ds.d), ds.dist) * self.pdf_select(ds.emitter)
        return finite_or_zero(dr.select(small, cap, pdf_w))
