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
    """Needs, from EmitterTable: scene, has_sphere, sph_r, sph_c, all_spheres, sph_le, pdf_select,
    smooth, uniform_pdf_a.

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
        except small-looking sphere emitters (small_sphere) and smooth-shaded emitter meshes
        (_smooth_direct). Returns (ds, Le / pdf)."""
        if not self.has_sphere and self.smooth is None:
            return self.scene.sample_emitter_direction(ref_it, u, False, active)
        index, sel_w, u_x = self.scene.sample_emitter(u.x, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), index, active)
        u2 = mi.Point2f(u_x, u.y)
        own = mi.Bool(False)
        if self.has_sphere:
            cone = self.small_sphere(emitter, ref_it.p)
            small = cone[0] & active
            own |= small
        if self.smooth is not None:
            smooth = self.smooth.rank(emitter, active)[1]
            own |= smooth
        ds, spec = emitter.sample_direction(ref_it, u2, active & ~own)
        if self.has_sphere:
            ds, spec = self._sphere_direct(ref_it, emitter, u2, small, cone[1:], ds, spec)
        if self.smooth is not None:
            ds, spec = self._smooth_direct(ref_it, emitter, u2, smooth, ds, spec)
        ds.pdf *= self.scene.pdf_emitter(index, active)
        return ds, spec * sel_w

    def _sphere_direct(self, ref_it, emitter, u2, small, cone, ds, spec):
        """(ds, Le / pdf) of emitter sampling on small-looking sphere emitters (lanes ``small``;
        ``cone``: small_sphere's centre, radius, sin^2 and 1 - cos of the cone); ``ds``,
        ``spec`` elsewhere."""
        centre, r, sin2_max, omc = cone
        p, n = self._cone_point(ref_it.p, centre, r, sin2_max, omc, u2)
        to_p = p - ref_it.p
        dist = dr.norm(to_p)
        ds_s = dr.zeros(mi.DirectionSample3f, dr.width(dist))
        ds_s.p, ds_s.n, ds_s.d, ds_s.dist, ds_s.time = p, n, to_p * safe_div(1.0, dist), dist, ref_it.time
        ds_s.emitter, ds_s.delta = emitter, mi.Bool(False)
        ds_s.pdf = self._cone_pdf_w(omc)
        if self.all_spheres:    # (the cone's point faces ref_it: the emitting side)
            le = dr.gather(mi.Spectrum, self.sph_le, dr.reinterpret_array(mi.UInt32, emitter), small)
        else:
            le = emitter.eval_direction(ref_it, ds_s, small)
        return dr.select(small, ds_s, ds), dr.select(small, le * safe_div(1.0, ds_s.pdf), spec)

    def _smooth_direct(self, ref_it, emitter, u2, smooth, ds, spec):
        """(ds, Le / pdf) of emitter sampling on smooth-shaded emitter meshes (lanes ``smooth``;
        smooth_emitters.py): a uniform point, its density per unit solid angle by its
        triangle's normal, its radiance by its shading normal; ``ds``, ``spec`` elsewhere."""
        _, p, n_geo, n_sh, b = self.smooth.sample(emitter, u2, smooth)
        to_p = p - ref_it.p
        dist = dr.norm(to_p)
        ds_m = dr.zeros(mi.DirectionSample3f, dr.width(dist))
        ds_m.p, ds_m.n, ds_m.uv, ds_m.time = p, n_geo, b, ref_it.time
        ds_m.d, ds_m.dist, ds_m.emitter, ds_m.delta = to_p * safe_div(1.0, dist), dist, emitter, mi.Bool(False)
        ds_m.pdf = self._smooth_pdf_w(ds_m)
        si = mi.SurfaceInteraction3f(ds_m, ref_it.wavelengths)
        si.sh_frame = mi.Frame3f(n_sh)
        si.wi = si.to_local(-ds_m.d)
        le = emitter.eval(si, smooth)
        return dr.select(smooth, ds_m, ds), dr.select(smooth, le * safe_div(1.0, ds_m.pdf), spec)

    def _smooth_pdf_w(self, ds):
        """The density per unit solid angle (emitter choice excluded) of a uniform point ``ds`` on
        a smooth-shaded emitter mesh, ``ds.n`` its triangle's normal: 1 / area by d^2 / |cos|."""
        return self.uniform_pdf_a(ds.emitter) * dr.square(ds.dist) * safe_div(1.0, dr.abs(dr.dot(ds.n, ds.d)))

    def pdf_direct_w(self, ref_it, ds, active):
        """Density per unit solid angle at ``ref_it`` of sample_direct choosing the emitter
        point or direction ``ds`` (on a smooth-shaded emitter mesh ``ds.n`` is its triangle's
        normal), emitter choice included; 0 where a density is not finite (finite_or_zero)."""
        if not self.has_sphere and self.smooth is None:
            return finite_or_zero(self.scene.pdf_emitter_direction(ref_it, ds, active))
        own = mi.Bool(False)
        if self.has_sphere:
            small, _, _, _, omc = self.small_sphere(ds.emitter, ref_it.p)
            own |= small
        if self.smooth is not None:
            smooth = self.smooth.rank(ds.emitter, active)[1]
            own |= smooth
        pdf_w = self.scene.pdf_emitter_direction(ref_it, ds, active & ~own)
        if self.has_sphere:
            pdf_w = dr.select(small, self._cone_pdf_w(omc) * self.pdf_select(ds.emitter), pdf_w)
        if self.smooth is not None:
            pdf_w = dr.select(smooth, self._smooth_pdf_w(ds) * self.pdf_select(ds.emitter), pdf_w)
        return finite_or_zero(pdf_w)
