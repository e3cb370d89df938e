"""Subpath endpoints: where light subpaths start (emitters) and how camera subpaths are
weighted, with every density the MIS needs. Mitsuba does not expose the emission densities
(``Emitter.pdf_position`` raises, and no emitter gives the pdf of the direction ``sample_ray``
chooses), so they are computed here, per emitter type, in one place.

Scope (checked by ``scene_check``): area emitters on any shape, perspective cameras."""

import drjit as dr
import mitsuba as mi

INV_PI = 1.0 / dr.pi


def safe_div(a, b):
    """a / b, and 0 where b is 0 (a density or a squared distance that vanished)."""
    return dr.select(b != 0, a / dr.select(b != 0, b, 1.0), 0.0)


class EmitterTable:
    """Emitter choice (Mitsuba's own ``scene.sample_emitter``, proportional to each
    emitter's ``sampling_weight``) and the emission densities of area emitters."""

    def __init__(self, scene: mi.Scene):
        self.scene = scene
        weights = [float(e.sampling_weight()) for e in scene.emitters()]
        self.total_weight = sum(weights)
        self.count = len(weights)

    def pdf_select(self, emitter):
        """Probability of choosing ``emitter`` (an EmitterPtr)."""
        return emitter.sampling_weight() / self.total_weight

    @staticmethod
    def pdf_pos_a(emitter, ps):
        """Density per unit area of the emission position (Mitsuba's area emitters sample
        their shape's surface uniformly; spatially varying radiance is refused earlier)."""
        return emitter.get_shape().pdf_position(ps)

    @staticmethod
    def pdf_dir_w(cos_e):
        """Density per unit solid angle of the emitted direction: cosine-weighted around the
        emitter's (shading) normal, as Mitsuba's area emitter samples it."""
        return dr.abs(cos_e) * INV_PI

    def sample_emission(self, time, u_sel, u_pos, u_dir, active):
        """Start a light subpath. Returns (si_e, emitter, ray direction, beta after emission,
        Le * cos / (p_sel p_pos) for the s=1,t=1 splat is built by the caller from
        ``le_over_pdf_a``), and the densities."""
        idx, _, _ = self.scene.sample_emitter(u_sel, active)
        emitter = dr.gather(mi.EmitterPtr, self.scene.emitters_dr(), idx, active)
        ps, _ = emitter.sample_position(time, u_pos, active)
        p_sel = self.pdf_select(emitter)
        pdf_pos_a = self.pdf_pos_a(emitter, ps)
        pdf_light_a = p_sel * pdf_pos_a                          # y0's density, s=1,t=1
        local = mi.warp.square_to_cosine_hemisphere(u_dir)
        si_e = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f))
        si_e.wi = local                                          # area emitters read si.wi
        le = emitter.eval(si_e, active)
        d = si_e.to_world(local)
        cos_s = local.z                                          # shading cosine (emission)
        pdf_emit_w = pdf_light_a * self.pdf_dir_w(cos_s)         # y0 and its direction
        return ps, si_e, emitter, d, le, cos_s, p_sel, pdf_light_a, pdf_emit_w

    def pdf_direct_a(self, ref_it, ds, active):
        """Density per unit area at the emitter point ``ds`` of emitter sampling
        (``sample_emitter_direction``) from ``ref_it``, emitter choice included."""
        pdf_w = self.scene.pdf_emitter_direction(ref_it, ds, active)
        return pdf_w * dr.abs(dr.dot(ds.n, ds.d)) / dr.maximum(dr.square(ds.dist), 1e-30)

    def pdf_emit_w_at(self, emitter, ds, d_out):
        """Emission density (choice, position, direction ``d_out``) of a point ``ds`` on
        ``emitter``: what a light subpath would have used to start there."""
        return (self.pdf_select(emitter) * self.pdf_pos_a(emitter, ds)
                * self.pdf_dir_w(dr.dot(ds.n, d_out)))


def direction_sample_at(si_e: mi.SurfaceInteraction3f, ps: mi.PositionSample3f, ref_p, emitter):
    """A DirectionSample3f for the emitter point ``ps`` as seen from ``ref_p``."""
    ds = mi.DirectionSample3f(ps)
    d = ps.p - ref_p
    dist = dr.norm(d)
    ds.d = d / dr.maximum(dist, 1e-30)
    ds.dist = dist
    ds.emitter = emitter
    return ds


class Camera:
    """Perspective camera: importance We and its densities, normalised over the crop window
    (Mitsuba normalises the perspective sensor's importance over the crop rectangle)."""

    def __init__(self, sensor: mi.Sensor):
        self.sensor = sensor
        film = sensor.film()
        self.crop_offset = mi.ScalarPoint2f(film.crop_offset())
        self.crop_size = mi.ScalarVector2f(film.crop_size())
        # the pinhole (sample_ray's origins lie on the near-clip plane instead)
        self.position = mi.Point3f(sensor.world_transform() @ mi.ScalarPoint3f(0, 0, 0))

    def pdf_w(self, p_hit):
        """We(omega) of the direction from the camera to ``p_hit``: the camera's density per
        unit solid angle of that direction (pixel positions are uniform over the crop)."""
        it = dr.zeros(mi.Interaction3f)
        it.p = p_hit
        ds, w = self.sensor.sample_direction(it, mi.Point2f(0.5), True)
        return dr.select(ds.pdf > 0, w.x * dr.square(ds.dist), 0.0)
