"""Cameras: what the strategies need to know of the sensor that starts every camera subpath.
A new camera is one subclass of ``CameraModel`` registered in ``CAMERAS`` (scene_check reads
the supported sensors from there), plus its agreement test.

The interface:
- ``pdf_w(d)``: the density We(omega) per unit solid angle of the first direction ``d``;
- ``lens_point(ray)``: where the first edge starts (its length enters the first vertex's area
  density: ``first_edge_dist2``);
- ``reachable``: whether a light vertex can be connected to the camera (t=1 strategies); a
  camera that no light path can reach (a delta direction, e.g. orthographic) sets it False
  and the MIS weights leave those strategies out (strategies.StrategySet);
- ``sample_ray(time, u_wavelength, film_sample, aperture_sample)``: the primary ray and its
  weight (Mitsuba's ``sample_ray``; ``sample_ray_differential`` for sensors that implement
  only that one).
Light-tracing splats take their value from ``sensor.sample_direction`` unchanged.

Cameras that light tracing does not reach (``UnreachableCamera``): orthographic (a delta
direction), radiancemeter (a delta ray), distant (a delta direction), irradiancemeter (a smooth
importance, but Mitsuba's ``sample_direction`` for it returns the constant pi, not an importance
a splat could use: its t=1 strategies are left out, a valid subset of the strategies)."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np


class CameraModel:
    plugin = None               # the name scene files use
    mitsuba_class = None        # Mitsuba's class name (sensor.class_name())
    reachable = True

    def __init__(self, sensor: mi.Sensor):
        self.sensor = sensor
        film = sensor.film()
        self.crop_offset = mi.ScalarPoint2f(film.crop_offset())
        self.crop_size = mi.ScalarVector2f(film.crop_size())

    def pdf_w(self, d):
        raise NotImplementedError

    def lens_point(self, ray):
        raise NotImplementedError

    def sample_ray(self, time, u_wavelength, film_sample, aperture_sample):
        return self.sensor.sample_ray(time, u_wavelength, film_sample, aperture_sample)

    def near_point(self, ds):
        """The end of a t=1 connection towards the camera's point ``ds.p`` (``ds.d``: the unit
        direction towards it): the point itself, where camera rays start there."""
        return ds.p

    def between_clip_planes(self, ds):
        """Whether the point a sensor.sample_direction ``ds`` was drawn for lies where camera
        rays reach (all of them, but for cameras with clip planes)."""
        return True

    def first_edge_dist2(self, ray, p):
        """Squared length of the first edge, from the lens point to the first vertex ``p``."""
        return dr.squared_norm(p - self.lens_point(ray))


class Perspective(CameraModel):
    """A pinhole. The film position is uniform over the crop window, so the direction from the
    pinhole has the density We(omega) = 1 / (A cos^3 theta) per unit solid angle, A the crop's
    area on the image plane at distance 1 and theta the angle to the optical axis. Mitsuba
    normalises the importance over the crop too."""
    plugin, mitsuba_class = 'perspective', 'PerspectiveCamera'

    def __init__(self, sensor: mi.Sensor):
        super().__init__(sensor)
        film = sensor.film()
        x_fov = float(dr.ravel(mi.traverse(sensor)['x_fov']).numpy()[0])
        w, h = (float(v) for v in film.size())
        cw, ch = (float(v) for v in film.crop_size())
        tan_x = math.tan(math.radians(x_fov) / 2)
        area = (2 * tan_x) * (2 * tan_x * h / w) * (cw * ch) / (w * h)
        self.inv_area = 1.0 / area
        m = np.array(sensor.world_transform().matrix).reshape(4, 4)
        axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
        self.axis = mi.Vector3f(*[float(x) for x in axis])
        self.near_clip = float(sensor.near_clip())
        self.far_clip = float(sensor.far_clip())
        # the pinhole (sample_ray's origins lie on the near-clip plane instead)
        self.position = mi.Point3f(*[float(x) for x in m[:3, 3]])

    def pdf_w(self, d):
        """We(omega) of the unit direction ``d`` leaving the pinhole (or lens point)."""
        c = dr.dot(d, self.axis)
        return dr.select(c > 0, self.inv_area * dr.rcp(dr.select(c > 0, c * c * c, 1.0)), 0.0)

    def to_near_plane(self, d):
        """The distance from the lens along the unit direction ``d`` leaving it to the near-clip
        plane: near_clip / cos(theta)."""
        c = dr.dot(d, self.axis)
        return self.near_clip * dr.rcp(dr.select(c > 0, c, 1.0))

    def lens_point(self, ray):
        """Mitsuba starts camera rays on the near-clip plane, near_clip / cos(theta) along the
        ray from the pinhole."""
        return ray.o - ray.d * self.to_near_plane(ray.d)

    def near_point(self, ds):
        """Where the segment from a point to the lens point ``ds.p`` crosses the near-clip
        plane. Camera rays start there, so nothing nearer the lens is seen (a scene may place
        its camera behind a wall and clip the wall away), and t=1 connections end there: ended
        at the lens, such a wall hid every light vertex from the camera (technique lt black,
        bdpt 74% dark: test_lights.py::test_near_clip_beyond_a_wall)."""
        return ds.p - ds.d * self.to_near_plane(-ds.d)

    def between_clip_planes(self, ds):
        """Whether the point ``ds`` was drawn for lies between the clip planes (its depth along
        the axis from the lens point ``ds.p``). Mitsuba 3.9.1's `thinlens` computes this in its
        sample_direction and leaves it out of the result in the JIT variants (its `perspective`
        applies it): without this, lt with a thin lens splatted points the camera rays clip
        away (1% bright where near_clip cut the edges of the Cornell box's walls)."""
        z = -dr.dot(ds.d, self.axis) * ds.dist
        return (z >= self.near_clip) & (z <= self.far_clip)


class ThinLens(Perspective):
    """A thin lens: the direction from the sampled lens point through the matching point of
    the focus plane has the pinhole's density We(omega); the lens point's own density is the
    same in every strategy (camera rays and splats sample it alike) and cancels in the MIS
    ratios. Rays start on the near-clip plane as the pinhole's do."""
    plugin, mitsuba_class = 'thinlens', 'ThinLensCamera'


class UnreachableCamera(CameraModel):
    """A camera that no light vertex is connected to (``reachable = False``): the strategies
    with t=1 do not exist for it, so the camera's density of its first direction enters no
    weight (mis.MIS.camera_init starts the camera subpath with zeros whatever ``pdf_w`` says:
    every remaining strategy samples the first edge the same way). ``pdf_w`` is a finite
    placeholder and the first edge starts at the ray's origin."""
    reachable = False

    def pdf_w(self, d):
        return dr.full(mi.Float, 1.0, dr.width(d))

    def lens_point(self, ray):
        return ray.o


class Orthographic(UnreachableCamera):
    """Parallel rays from the film rectangle on the near-clip plane: a delta direction."""
    plugin, mitsuba_class = 'orthographic', 'OrthographicCamera'


class RadianceMeter(UnreachableCamera):
    """One ray (delta position and direction); a 1x1 film."""
    plugin, mitsuba_class = 'radiancemeter', 'RadianceMeter'


class Distant(UnreachableCamera):
    """Parallel rays (a delta direction) aimed at the scene, a target point or a target shape;
    a 1x1 film."""
    plugin, mitsuba_class = 'distant', 'DistantSensorImpl'


class IrradianceMeter(UnreachableCamera):
    """Irradiance over a shape: cosine-weighted rays from points sampled uniformly on it
    (weight pi). Mitsuba implements only ``sample_ray_differential`` for it."""
    plugin, mitsuba_class = 'irradiancemeter', 'IrradianceMeter'

    def sample_ray(self, time, u_wavelength, film_sample, aperture_sample):
        ray, w = self.sensor.sample_ray_differential(time, u_wavelength, film_sample, aperture_sample)
        return mi.Ray3f(ray), w


CAMERAS = {cls.plugin: cls for cls in (Perspective, ThinLens, Orthographic, RadianceMeter, Distant,
                                       IrradianceMeter)}


def camera_for(sensor: mi.Sensor) -> CameraModel:
    name = str(sensor.class_name())
    for cls in CAMERAS.values():
        if cls.mitsuba_class == name:
            return cls(sensor)
    raise ValueError(f"bdpt: no camera model for sensor class {name!r}")
