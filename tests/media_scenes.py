"""Scenes with participating media for issue 23, their analytic values, and the reference harness.

Every builder returns a Mitsuba scene dict (``mi.load_dict`` it): small (16x16 or 32x32, box
filter, so a pixel's value is the mean of the radiance over its footprint), built only from
plain values, ``mi.ScalarTransform4f`` and, for grids, ``mi.VolumeGrid`` made from a numpy array
(no binary files). The dicts are variant-independent: colours are ``rgb`` values in [0, 1], a
coefficient above 1 is such a colour times the medium's ``scale``. No builder sets an
integrator: max_depth belongs to the integrator given to the render.

Conventions of Mitsuba 3.9.1 the scenes rely on (each checked in tests/test_media_scenes.py):

- A camera inside a medium needs the sensor's ``medium`` (a ``ref`` to a top-level medium object
  of the dict); shapes with the same ``ref`` as ``interior`` share the very same medium.
- ``volpath``'s max_depth counts surface bounces and *real* medium collisions; null collisions
  (delta tracking) and crossings of ``null`` BSDFs are not counted (volpath.cpp: depth + 1 on a
  medium scatter, and on a surface only when the sampled lobe is not Null). max_depth 1: emitters
  seen directly (through media); 2: single scattering or direct lighting.
- An emitter does not infer the medium around it: a light inside fog declares it (``medium`` of
  a point light, ``interior``/``exterior`` of an area light's shape). The walls of a foggy room
  declare the fog on both sides, so that every integrator reads the same medium everywhere.
- ``gridvolume`` takes an in-memory grid: ``'grid': mi.VolumeGrid(a)`` with ``a`` of shape
  (z, y, x, channels) float32; the grid fills the unit cube, placed by its ``to_world``.
"""

import math

import mitsuba as mi
import numpy as np

import stability_cases
from stability_cases import T, diffuse, rgb, sensor

REF_SEED = 10_000           # first seed of the references' batches (as test_agreement.py)
FLOAT_FLOOR = 1e-5          # helpers.agreement's relative resolution here: float32 rounding is no bias


# ------------------------------------------------------------------------------- pieces
def homogeneous(sigma_t, albedo, g=0.0, scale=1.0):
    """A homogeneous medium. ``sigma_t``, ``albedo``: a float or an RGB triple (sigma_t's entries
    above 1 are normalised and the maximum moved into ``scale``); ``g``: Henyey-Greenstein
    parameter (0: isotropic phase function)."""
    m = {'type': 'homogeneous', 'albedo': rgb(albedo)}
    if np.ndim(sigma_t) == 0:
        s = max(float(sigma_t), 1.0)
        m['sigma_t'] = rgb(float(sigma_t) / s)
    else:
        s = max(max(float(v) for v in sigma_t), 1.0)
        m['sigma_t'] = rgb([float(v) / s for v in sigma_t])
    m['scale'] = s * float(scale)
    if g != 0.0:
        m['phase'] = {'type': 'hg', 'g': float(g)}
    return m


def density_grid(kind, n=8):
    """Density grids in [0, 1] (shape (n, n, n, 1), float32) for heterogeneous media:
    ``'blob'``: a smooth bump falling to exactly 0 in the corners (empty voxels), ``'single'``: one
    voxel of value 1, ``'octants'``: 2x2x2 voxels of values 0, 1, 0.25, 0.5, 1, 0, 0.75, 0.1
    (two empty), ``'constant'``: all 1."""
    if kind == 'single':
        return np.ones((1, 1, 1, 1), np.float32)
    if kind == 'octants':
        v = np.array([0.0, 1.0, 0.25, 0.5, 1.0, 0.0, 0.75, 0.1], np.float32)
        return v.reshape(2, 2, 2, 1)
    if kind == 'constant':
        return np.ones((n, n, n, 1), np.float32)
    c = (np.arange(n) + 0.5) / n - 0.5
    z, y, x = np.meshgrid(c, c, c, indexing='ij')
    r2 = (x * x + y * y + z * z) / 0.25
    return np.clip(1.0 - r2, 0.0, 1.0).astype(np.float32)[..., None]


def heterogeneous(grid, scale, albedo, g=0.0, centre=(0, 0, 0), half=1.0, nearest=False):
    """A heterogeneous medium: sigma_t = scale * ``grid`` (density_grid), filling the cube of
    half-width ``half`` about ``centre``; ``nearest``: piecewise-constant voxels (else trilinear)."""
    vol = {'type': 'gridvolume', 'grid': mi.VolumeGrid(np.ascontiguousarray(grid, np.float32)),
           'to_world': T().translate([c - half for c in centre]).scale(2.0 * half)}
    if nearest:
        vol['filter_type'] = 'nearest'
    m = {'type': 'heterogeneous', 'sigma_t': vol, 'albedo': rgb(albedo), 'scale': float(scale)}
    if g != 0.0:
        m['phase'] = {'type': 'hg', 'g': float(g)}
    return m


def ref(name):
    return {'type': 'ref', 'id': name}


def null_sphere(radius=1.0, centre=(0, 0, 0), medium='medium'):
    """A sphere with a null BSDF holding the top-level medium ``medium``."""
    return {'type': 'sphere', 'radius': float(radius), 'center': [float(c) for c in centre],
            'bsdf': {'type': 'null'}, 'interior': ref(medium)}


def null_cube(half=1.0, centre=(0, 0, 0), medium='medium'):
    return {'type': 'cube', 'to_world': T().translate(list(map(float, centre))).scale(float(half)),
            'bsdf': {'type': 'null'}, 'interior': ref(medium)}


def constant_sky(value=1.0):
    return {'type': 'constant', 'radiance': rgb(value)}


def scene(**objects):
    return {'type': 'scene', **objects}


def _camera(res, origin, target, fov, medium=None, up=(0, 1, 0), near_clip=1e-3, far_clip=1e4):
    """A perspective camera (stability_cases.sensor) in the top-level medium ``medium`` (an id).
    Mitsuba clips camera rays at ``far_clip``: a scene larger than it needs a larger one."""
    s = sensor(origin, target, up=up, fov=fov, res=res, near_clip=near_clip, far_clip=far_clip)
    if medium is not None:
        s['medium'] = ref(medium)
    return s


def _placed(p, scale, translate):
    return [float(scale * a + b) for a, b in zip(p, translate)]


# ------------------------------------------------------------------ (a) absorbing sphere
def absorbing_sphere(sigma_t=1.0, radius=1.0, translate=(0.0, 0.0, 0.0), res=16):
    """(a) The camera at the centre of a null sphere of ``radius`` filled with a purely absorbing
    homogeneous medium (albedo 0) of ``sigma_t``, under a constant emitter of 1: every camera
    ray leaves the medium after exactly ``radius``, so every pixel is exp(-sigma_t radius)
    (``absorbing_sphere_value``) at any max_depth >= 1 (a collision ends the path). The camera's
    near clip is 1e-7 radius (Mitsuba starts camera rays at the near plane). ``translate`` moves
    the sphere and the camera together (stiff placements: radius 1e-3 and sigma_t 1e3 is the
    scene scaled by 1e-3; translate 1e4 far from the origin)."""
    c = [float(v) for v in translate]
    return scene(
        sensor=_camera(res, c, [c[0], c[1], c[2] - 1.0], 60.0, medium='medium', near_clip=1e-7 * radius,
                       far_clip=1e4 * max(radius, 1.0)),
        medium=homogeneous(sigma_t, 0.0),
        sphere=null_sphere(radius, c),
        sky=constant_sky(1.0))


def absorbing_sphere_value(sigma_t=1.0, radius=1.0, **_):
    return math.exp(-sigma_t * radius)


def absorbing_cube(grid='octants', sigma=1.0, half=1.0, res=16):
    """(a, heterogeneous; h: empty and single voxels) The camera at the centre of a null cube of
    half-width ``half`` holding a purely absorbing heterogeneous medium with piecewise-constant
    voxels (``density_grid(grid)`` times ``sigma``), under a constant emitter of 1. From the
    centre a ray stays in one octant, so with the 2x2x2 'octants' grid (two of them empty) or the
    1-voxel 'single' grid its transmittance is exp(-sigma v d), v the octant's density and d the
    distance to the cube's face (``absorbing_cube_expected``: a pixel quadrature of it). The
    camera looks along -z with a 100 degree field of view (the back face and parts of the four
    side faces): the octants' boundaries x = 0 and y = 0 fall on pixel edges (``res`` even), so
    v is constant over each pixel; of the four octants seen, one is empty."""
    return scene(
        sensor=_camera(res, [0, 0, 0], [0, 0, -1.0], 100.0, medium='medium', near_clip=1e-7 * half),
        medium=heterogeneous(density_grid(grid), sigma, 0.0, half=half, nearest=True),
        cube=null_cube(half),
        sky=constant_sky(1.0))


def absorbing_cube_expected(grid='octants', sigma=1.0, half=1.0, res=16, n=8):
    """The pixel values of ``absorbing_cube`` (H, W) by Gauss-Legendre quadrature over each
    pixel (n x n nodes) of exp(-sigma v d) in double precision."""
    g = density_grid(grid)[..., 0].astype(np.float64)

    def radiance(o, d):
        dist = np.min(half / np.maximum(np.abs(d), 1e-300), axis=1)
        if g.shape[0] == 1:
            v = np.full(len(d), g[0, 0, 0])
        else:       # the grid is indexed [z, y, x]
            ix, iy, iz = ((d > 0).astype(int)[:, k] for k in range(3))
            v = g[iz, iy, ix]
        return np.exp(-sigma * v * dist)
    return pixel_quadrature(mi.load_dict(absorbing_cube(grid, sigma, half, res)), radiance, n)


# ---------------------------------------------------------------------------- (b) furnaces
def furnace(kind='homogeneous', g=0.0, inside=False, sigma_t=1.0, radius=1.0, grid='blob', res=16):
    """(b) A furnace: a null sphere of ``radius`` holding a medium of albedo 1 under a constant
    emitter of 1. No energy is lost, so every pixel sees exactly 1 at max_depth -1 (every path
    ends in the emitter; finite depths see less). ``kind``: 'homogeneous' (``sigma_t``) or
    'heterogeneous' (``density_grid(grid)`` times ``sigma_t``, trilinear; the grid fills the
    sphere's bounding cube); ``g``: HG parameter; ``inside``: the camera at the centre (the
    sensor in the medium), else at 3 radii looking at it (the sphere fills the middle of the
    image, the sky the corners)."""
    if kind == 'homogeneous':
        med = homogeneous(sigma_t, 1.0, g)
    else:
        med = heterogeneous(density_grid(grid), sigma_t, 1.0, g, half=radius)
    far = 1e4 * max(radius, 1.0)
    if inside:
        cam = _camera(res, [0, 0, 0], [0, 0, -1], 60.0, medium='medium', near_clip=1e-7 * radius, far_clip=far)
    else:
        cam = _camera(res, [0, 0, 3.0 * radius], [0, 0, 0], 45.0, near_clip=1e-3 * radius, far_clip=far)
    return scene(sensor=cam, medium=med, sphere=null_sphere(radius), sky=constant_sky(1.0))


FURNACE_VALUE = 1.0

# the furnaces the tests render: (kind, g, inside, sigma_t, radius, grid)
FURNACES = [
    ('homogeneous', 0.0, False, 1.0, 1.0, 'blob'),
    ('homogeneous', 0.0, True, 1.0, 1.0, 'blob'),
    ('homogeneous', 0.7, False, 1.0, 1.0, 'blob'),
    ('homogeneous', 0.7, True, 1.0, 1.0, 'blob'),
    ('heterogeneous', 0.0, False, 1.0, 1.0, 'blob'),
    ('heterogeneous', 0.0, True, 1.0, 1.0, 'blob'),
    ('heterogeneous', 0.7, False, 1.0, 1.0, 'blob'),
    ('heterogeneous', 0.7, True, 1.0, 1.0, 'blob'),
]
STIFF_FURNACES = [        # (h)
    ('homogeneous', 0.99, False, 1.0, 1.0, 'blob'),
    ('homogeneous', -0.99, False, 1.0, 1.0, 'blob'),
    ('homogeneous', 0.0, True, 1e-4, 1e4, 'blob'),       # thin and large
    ('homogeneous', 0.0, False, 1e-4, 1e4, 'blob'),
    ('homogeneous', 0.0, False, 1e3, 3e-3, 'blob'),      # dense and small: optical radius 3
    ('heterogeneous', 0.0, False, 2.0, 1.0, 'single'),
    ('heterogeneous', 0.0, True, 2.0, 1.0, 'octants'),
]


# ----------------------------------------------------------------------- pixel quadrature
def pixel_rays(scene_obj, n):
    """Camera rays of every pixel at n x n Gauss-Legendre nodes of its footprint: origins and unit
    directions (H, W, n*n, 3) float64, and the nodes' weights (n*n,), summing to 1 (a box filter
    averages the radiance over the footprint)."""
    sensor_ = scene_obj.sensors()[0]
    w, h = sensor_.film().crop_size()
    x, wx = np.polynomial.legendre.leggauss(n)
    x, wx = (x + 1) / 2, wx / 2
    iy, ix, sy, sx = np.meshgrid(np.arange(h), np.arange(w), np.arange(n), np.arange(n), indexing='ij')
    u = (ix + x[sx]) / w
    v = (iy + x[sy]) / h
    ray, _ = sensor_.sample_ray(0.0, 0.5, mi.Point2f(u.ravel(), v.ravel()), mi.Point2f(0.5))
    o = np.array(ray.o, np.float64).T.reshape(h, w, n * n, 3)
    d = np.array(ray.d, np.float64).T.reshape(h, w, n * n, 3)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return o, d, np.outer(wx, wx).ravel()


def pixel_quadrature(scene_obj, radiance, n=8):
    """Pixel values (H, W[, C]) of the radiance function ``radiance(o, d)`` (arrays (N, 3) of
    origins and unit directions -> (N,) or (N, C)) averaged over each pixel by Gauss-Legendre
    quadrature (pixel_rays)."""
    o, d, w = pixel_rays(scene_obj, n)
    h, wd = o.shape[:2]
    L = np.asarray(radiance(o.reshape(-1, 3), d.reshape(-1, 3)), np.float64)
    L = L.reshape(h, wd, n * n, *L.shape[1:])
    return np.tensordot(w, np.moveaxis(L, 2, 0), axes=1)


def sphere_chord(o, d, centre, radius):
    """Where the rays o + t d (unit d) are inside the sphere: (t_in, t_out), t_in clipped at 0,
    and a mask of the rays that cross it ahead."""
    oc = o - np.asarray(centre, np.float64)
    b = np.einsum('ij,ij->i', oc, d)
    c = np.einsum('ij,ij->i', oc, oc) - radius * radius
    disc = b * b - c
    root = np.sqrt(np.maximum(disc, 0.0))
    t_in, t_out = np.maximum(-b - root, 0.0), -b + root
    return t_in, t_out, (disc > 0) & (t_out > 0)


def hg(cos_theta, g):
    """The Henyey-Greenstein phase function of the scattering angle's cosine (light's direction
    of travel before and after), per steradian."""
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos_theta) ** 1.5)


# ---------------------------------------------------------------- (c) single scattering
SS_LIGHT = (1.5, 1.0, 0.5)


def single_scatter(sigma_t=1.0, albedo=0.5, g=0.0, radius=1.0, intensity=10.0, res=16):
    """(c) Single scattering: a null sphere of ``radius`` at the origin holding a homogeneous
    medium (``sigma_t``, ``albedo``, HG ``g``), a point light of ``intensity`` outside it at
    SS_LIGHT, the camera outside at (0, 0, 3) looking at the centre, nothing else (no emitter
    seen, no surface but the null boundary). At max_depth 2 (Mitsuba's volpath: one real
    collision, then emitter sampling) a pixel is the single-scattering integral along each camera
    ray (``single_scatter_expected``); max_depth 1 renders 0."""
    return scene(
        sensor=_camera(res, [0, 0, 3.0], [0, 0, 0], 45.0),
        medium=homogeneous(sigma_t, albedo, g),
        sphere=null_sphere(radius),
        light={'type': 'point', 'position': list(SS_LIGHT), 'intensity': rgb(intensity)})


def single_scatter_radiance(o, d, sigma_t, albedo, g, radius, intensity, n_t=64):
    """Single-scattered radiance along the rays (o, unit d) of ``single_scatter``: the integral
    over t in the sphere of T(t_in, t) sigma_s p(theta) I T(x, light) / |x - light|^2, by
    Gauss-Legendre quadrature in t (n_t nodes) in double precision. T(x, light) is the
    transmittance over the chord from x towards the light (the light is outside the sphere)."""
    t_in, t_out, hit = sphere_chord(o, d, (0, 0, 0), radius)
    x, w = np.polynomial.legendre.leggauss(n_t)
    span = np.where(hit, t_out - t_in, 0.0)
    t = t_in[:, None] + span[:, None] * (x[None, :] + 1) / 2
    p = o[:, None, :] + t[..., None] * d[:, None, :]
    to_l = np.asarray(SS_LIGHT, np.float64) - p
    dist = np.linalg.norm(to_l, axis=-1)
    lhat = to_l / dist[..., None]
    b = np.einsum('ijk,ijk->ij', p, lhat)
    exit_l = -b + np.sqrt(np.maximum(b * b - (np.einsum('ijk,ijk->ij', p, p) - radius * radius), 0.0))
    cos_theta = np.einsum('ijk,ik->ij', lhat, d)       # light travels along -lhat, then along -d
    f = (np.exp(-sigma_t * (t - t_in[:, None])) * albedo * sigma_t * hg(cos_theta, g)
         * intensity * np.exp(-sigma_t * exit_l) / dist ** 2)
    return (f @ w) * span / 2


def single_scatter_expected(sigma_t=1.0, albedo=0.5, g=0.0, radius=1.0, intensity=10.0, res=16, n=8):
    """(values (H, W), mask (H, W)) of ``single_scatter`` at max_depth 2: the pixel quadrature
    (n x n nodes) of single_scatter_radiance. The mask holds the pixels whose footprint (a
    16 x 16 probe grid, dilated by one pixel) lies wholly inside or wholly outside the sphere's
    silhouette, where the integrand is smooth and the quadrature exact to ~1e-6; pixels on the
    silhouette are left out."""
    sc = mi.load_dict(single_scatter(sigma_t, albedo, g, radius, intensity, res))
    val = pixel_quadrature(sc, lambda o, d: single_scatter_radiance(o, d, sigma_t, albedo, g, radius, intensity), n)
    return val, off_silhouette(sc, (0, 0, 0), radius)


def off_silhouette(scene_obj, centre, radius):
    """(H, W) mask of the pixels whose footprint (16 x 16 probes, dilated by one pixel) lies
    wholly inside or wholly outside the silhouette of the sphere (``centre``, ``radius``)."""
    o, d, _ = pixel_rays(scene_obj, 16)
    hit = sphere_chord(o.reshape(-1, 3), d.reshape(-1, 3), centre, radius)[2].reshape(o.shape[:3])
    mixed = hit.any(axis=2) & ~hit.all(axis=2)
    dil = mixed.copy()
    dil[1:] |= mixed[:-1]; dil[:-1] |= mixed[1:]; dil[:, 1:] |= mixed[:, :-1]; dil[:, :-1] |= mixed[:, 1:]
    return ~dil


# ------------------------------------------------------------------------------ rooms
WALLS = {   # name: (transform of the unit rectangle [-1, 1]^2 (normal +z) onto a wall facing inwards, albedo)
    'floor': (T().translate([0, -1, 0]).rotate([1, 0, 0], -90), 0.7),
    'ceiling': (T().translate([0, 1, 0]).rotate([1, 0, 0], 90), 0.7),
    'back': (T().translate([0, 0, -1]), 0.7),
    'front': (T().translate([0, 0, 1]).rotate([0, 1, 0], 180), 0.7),
    'left': (T().translate([-1, 0, 0]).rotate([0, 1, 0], 90), [0.7, 0.2, 0.2]),
    'right': (T().translate([1, 0, 0]).rotate([0, 1, 0], -90), [0.2, 0.7, 0.2]),
}


def in_medium(shape, medium):
    """``shape`` with ``medium`` (a top-level id) on both sides: a surface inside fog."""
    return dict(shape, interior=ref(medium), exterior=ref(medium))


def closed_room(medium='fog'):
    """The six diffuse walls of the box [-1, 1]^3 facing inwards (red left, green right), each
    with ``medium`` on both sides (None: no medium declared). Each wall reaches 1% past the
    box's edges: walls that only meet there let rays slip through the seams."""
    out = {}
    for name, (tf, albedo) in WALLS.items():
        w = {'type': 'rectangle', 'to_world': tf @ T().scale([1.01, 1.01, 1.0]), 'bsdf': diffuse(albedo)}
        out[name] = in_medium(w, medium) if medium else w
    return out


def _strands_file():
    """A text file of 12 B-spline strands (4 control points each, radius 0.03), written once to
    the temporary directory under a fixed name (the references' keys hold the scene's
    description, which names the file)."""
    import os
    import tempfile
    path = os.path.join(tempfile.gettempdir(), 'bdpt_media_scenes_strands.txt')
    lines = []
    for k in range(12):
        x = -0.6 + 0.1 * k
        lines += [f'{x:.2f} -0.9 -0.4 0.03', f'{x + 0.02:.2f} -0.3 -0.35 0.03', f'{x - 0.02:.2f} 0.2 -0.45 0.03',
                  f'{x:.2f} 0.5 -0.4 0.03', '']
    text = '\n'.join(lines)
    if not os.path.exists(path) or open(path).read() != text:
        tmp = f'{path}.{os.getpid()}.tmp'
        with open(tmp, 'w') as f:
            f.write(text)
        os.replace(tmp, path)
    return path


def fog_room(sigma_t=0.5, albedo=0.8, g=0.0, light='area', res=16, sensor_medium=True, extra=None):
    """(d) Fog filling a closed room: the box [-1, 1]^3 of diffuse walls (closed_room), filled
    with a homogeneous fog (``sigma_t``, ``albedo``, HG ``g``), the camera inside it at
    (0, 0, 0.9) looking at -z (the sensor in the fog); ``light``: 'area' (a 0.3 x 0.3 square
    under the ceiling facing down, radiance 10, in the fog on both sides), 'sphere' (radius 0.05
    at (0.3, 0.6, -0.2), radiance 64, the fog outside) or 'point' (intensity 0.5 there, its
    ``medium`` the fog). Nothing specular. Values: references only (volpath, volpathmis).

    Two estimators have infinite variance here, so no t-test can use them: light tracing with
    the camera in a medium (a light vertex at distance d from the camera contributes ~ 1/d^2,
    whose square is not integrable over the volume around the camera; uniform MIS weights keep
    that strategy), and emitter sampling of the 'point' light from medium vertices (1/d^2 at the
    light: volpath's own estimator). Compare the 'point' variant only between volpath and
    volpathmis, which share it.

    ``sensor_medium`` False: the sensor does not declare the fog it is in (a scene declared
    inconsistently). volpath's camera rays then see no fog before their first wall, where they
    enter it; light subpaths' splats must follow them (light_path.camera_edge).

    ``extra``: 'instance' adds a diffuse sphere (radius 0.25) as an instance of a shape group,
    'curves' a dozen diffuse B-spline strands (radius 0.03) standing on the floor, each declaring
    no medium (they lie in the fog): shapes whose hits are inexact (rays.RayOffsets.coarse,
    one_sided), where a splat's edge is walked from the light vertex (LightTracer.camera_edge)."""
    objs = dict(closed_room('fog'))
    if extra == 'instance':
        objs['group'] = {'type': 'shapegroup', 'ball': {'type': 'sphere', 'radius': 0.25,
                                                        'bsdf': diffuse([0.8, 0.5, 0.3])}}
        objs['inst'] = {'type': 'instance', 'shapegroup': ref('group'), 'to_world': T().translate([0.2, -0.5, -0.3])}
    elif extra == 'curves':
        objs['hair'] = {'type': 'bsplinecurve', 'filename': _strands_file(), 'bsdf': diffuse([0.8, 0.5, 0.3])}
    if light == 'area':
        objs['light'] = in_medium({'type': 'rectangle', 'to_world': T().translate([0, 0.98, 0]).rotate([1, 0, 0], 90)
                                   .scale(0.15), 'bsdf': diffuse(0.0),
                                   'emitter': {'type': 'area', 'radiance': rgb(10.0)}}, 'fog')
    elif light == 'sphere':
        objs['light'] = {'type': 'sphere', 'center': [0.3, 0.6, -0.2], 'radius': 0.05, 'exterior': ref('fog'),
                         'emitter': {'type': 'area', 'radiance': rgb(64.0)}}
    else:
        objs['light'] = {'type': 'point', 'position': [0.3, 0.6, -0.2], 'intensity': rgb(0.5), 'medium': ref('fog')}
    return scene(sensor=_camera(res, [0, 0, 0.9], [0, 0, -1], 75.0, medium='fog' if sensor_medium else None),
                 fog=homogeneous(sigma_t, albedo, g), **objs)


def grid_box(scale=4.0, albedo=0.8, g=0.3, grid='blob', sky=0.2, res=16):
    """(e) A heterogeneous grid in a null box under a small light and a sky: the cube
    [-0.6, 0.6]^3 with a null BSDF holds sigma_t = ``scale`` * density_grid(``grid``) (trilinear;
    'blob' is 0 in the corner voxels), ``albedo``, HG ``g``; a diffuse floor (albedo 0.5) at
    y = -0.65 under it (not touching it: a ray leaving the box through a face that coincides
    with the floor would pass the floor); a spherical light (radius 0.1, radiance 100) above at
    (0.5, 1.5, 0.5); a constant sky of ``sky``. The camera at (0, 1.6, 2.6) in vacuum, looking
    down at the box (the sky in the top five rows of 16). Pixels seeing the sky are beyond light
    tracing (media_lt_mask)."""
    return scene(
        sensor=_camera(res, [0, 1.6, 2.6], [0, -0.2, 0], 45.0),
        medium=heterogeneous(density_grid(grid), scale, albedo, g, half=0.6),
        box=null_cube(0.6),
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.65, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.5)},
        light={'type': 'sphere', 'center': [0.5, 1.5, 0.5], 'radius': 0.1,
               'emitter': {'type': 'area', 'radiance': rgb(100.0)}},
        sky=constant_sky(sky))


def glass_media(res=16):
    """(f) Glass spheres (dielectric, IOR 1.5, radius 0.35) filled with media, on a diffuse floor
    (y = -0.5) before a back wall (z = -1), under a square area light (side 1, radiance 6) at
    y = 1.5 facing down, no environment: the left sphere holds a chromatic scattering medium
    (sigma_t (1, 2, 4), albedo (0.9, 0.7, 0.5), HG g 0.5), the right one a chromatic absorbing
    medium (sigma_t (0.5, 2, 4), albedo 0). Camera at (0, 0.5, 2.5) in vacuum."""
    def glass(centre, medium):
        return {'type': 'sphere', 'center': centre, 'radius': 0.35, 'interior': ref(medium),
                'bsdf': {'type': 'dielectric', 'int_ior': 1.5, 'ext_ior': 1.0}}
    return scene(
        sensor=_camera(res, [0, 0.5, 2.5], [0, -0.1, 0], 40.0),
        scatter=homogeneous([1.0, 2.0, 4.0], [0.9, 0.7, 0.5], 0.5),
        absorb=homogeneous([0.5, 2.0, 4.0], 0.0),
        left=glass([-0.42, -0.15, 0.0], 'scatter'),
        right=glass([0.42, -0.15, 0.0], 'absorb'),
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.6)},
        wall={'type': 'rectangle', 'to_world': T().translate([0, 0, -1]).scale(3.0), 'bsdf': diffuse(0.5)},
        light={'type': 'rectangle', 'to_world': T().translate([0, 1.5, 0]).rotate([1, 0, 0], 90).scale(0.5),
               'bsdf': diffuse(0.0), 'emitter': {'type': 'area', 'radiance': rgb(6.0)}})


def volumetric_caustic(glass=True, light_radius=0.05, sigma_t=0.3, albedo=0.9, res=16):
    """(g) A volumetric caustic: the closed room of closed_room (diffuse walls in the fog), a
    thin homogeneous fog (``sigma_t``, ``albedo``, isotropic), a small spherical light of
    ``light_radius`` at (0, 0.8, 0) (radiance 0.1 / light_radius^2: its power does not depend on
    the radius; its exterior the fog) above a glass sphere (radius 0.35 at (0, 0.1, 0), IOR 1.5,
    the fog outside, vacuum inside) that focuses the light into a caustic cone in the fog
    (``glass`` False: the same room without the sphere). The camera in the fog at (0, 0, 0.95)
    looking at -z. The benchmark's scenes (scenes/media/*.xml are written from these dicts)."""
    objs = dict(closed_room('fog'))
    objs['light'] = {'type': 'sphere', 'center': [0, 0.8, 0], 'radius': float(light_radius),
                     'exterior': ref('fog'),
                     'emitter': {'type': 'area', 'radiance': rgb(0.1 / light_radius ** 2)}}
    if glass:
        objs['glass'] = {'type': 'sphere', 'center': [0, 0.1, 0], 'radius': 0.35, 'exterior': ref('fog'),
                         'bsdf': {'type': 'dielectric', 'int_ior': 1.5, 'ext_ior': 1.0}}
    return scene(sensor=_camera(res, [0, 0, 0.95], [0, 0, -1], 75.0, medium='fog'),
                 fog=homogeneous(sigma_t, albedo), **objs)


def fog_box(glass=True, res=16):
    """(g') Bitterli's volumetric caustic, as its Mitsuba files declare its media: the box
    [-1, 1]^3 of closed_room's walls declaring no medium, its front face (z = 1) a ``null``
    rectangle with the fog (homogeneous, sigma_t 0.5, albedo 0.9) as interior, a glass sphere
    (radius 0.3 at (-0.2, -0.1, 0.1), IOR 1.5) with the fog as exterior and vacuum inside, and a
    square light (side 0.6, radiance 5, black) 2 cm under the ceiling facing down with the fog as
    exterior only (vacuum behind it, in the gap to the ceiling). The camera outside the box, in
    vacuum, at (0, 0, 3.5) looking at -z. volpath keeps a path's medium where it reflects off a
    wall that declares none; the light subpaths' vertices on the walls must be in the fog too,
    else their connections to the camera subpaths' are refused."""
    objs = {name: w for name, w in closed_room(None).items() if name != 'front'}
    objs['front'] = {'type': 'rectangle', 'to_world': T().translate([0, 0, 1]), 'bsdf': {'type': 'null'},
                     'interior': ref('fog')}
    objs['light'] = {'type': 'rectangle', 'to_world': T().translate([0, 0.98, 0]).rotate([1, 0, 0], 90).scale(0.3),
                     'bsdf': diffuse(0.0), 'exterior': ref('fog'),
                     'emitter': {'type': 'area', 'radiance': rgb(5.0)}}
    if glass:
        objs['glass'] = {'type': 'sphere', 'center': [-0.2, -0.1, 0.1], 'radius': 0.3, 'exterior': ref('fog'),
                         'bsdf': {'type': 'dielectric', 'int_ior': 1.5, 'ext_ior': 1.0}}
    return scene(sensor=_camera(res, [0, 0, 3.5], [0, 0, 0], 34.0), fog=homogeneous(0.5, 0.9), **objs)


def thin_glass(res=16):
    """(f') BSDFs with a Null lobe beside others in a scene with media (as Mitsuba's own test
    scenes, tests/scenes/participating_media, put them): a thin dielectric sphere (radius 0.5 at
    (0, 0, 0), IOR 1.5: it reflects ~8% and passes the rest straight on through its Null lobe)
    filled with a scattering medium (sigma_t 2, albedo 0.9), on a diffuse floor (y = -0.6) before
    a back wall (z = -1.2), and a card of ``mask`` (opacity 0.5 over a diffuse 0.8) half in front
    of the sphere; a square area light (side 0.8, radiance 8) at y = 1.4 facing down and a
    constant sky of 0.2. Camera at (0, 0.3, 2.6) in vacuum. volpath passes such surfaces on
    shadow rays weighted by their null transmission, and does not count a pass through the Null
    lobe as a bounce; bdpt's walks pass with that probability (media.MediumTracer)."""
    return scene(
        sensor=_camera(res, [0, 0.3, 2.6], [0, -0.1, 0], 45.0),
        medium=homogeneous(2.0, 0.9),
        glass={'type': 'sphere', 'center': [0, 0, 0], 'radius': 0.5, 'interior': ref('medium'),
               'bsdf': {'type': 'thindielectric', 'int_ior': 1.5, 'ext_ior': 1.0}},
        card={'type': 'rectangle', 'to_world': T().translate([0.45, 0.0, 0.8]).scale(0.35),
              'bsdf': {'type': 'mask', 'opacity': 0.5, 'bsdf': diffuse(0.8)}},
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.6, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.6)},
        wall={'type': 'rectangle', 'to_world': T().translate([0, 0, -1.2]).scale(3.0), 'bsdf': diffuse(0.5)},
        light={'type': 'rectangle', 'to_world': T().translate([0, 1.4, 0]).rotate([1, 0, 0], 90).scale(0.4),
               'bsdf': diffuse(0.0), 'emitter': {'type': 'area', 'radiance': rgb(8.0)}},
        sky=constant_sky(0.2))


def straddling_light(res=16):
    """(f'') An area light that declares no medium, half inside a fog sphere (a null boundary,
    radius 0.8 at the origin, sigma_t 1.5, albedo 0.8): a square (side 0.8, radiance 4) tilted
    towards the camera, centred on the sphere's surface at (0.8, 0, 0), so that some of its
    points emit into the fog and the rest into vacuum (media_path.EmitterMedia searches its
    medium per point). A diffuse floor (y = -0.9), a back wall (z = -1.5); no sky. The camera at
    (0, 0.4, 3) in vacuum."""
    return scene(
        sensor=_camera(res, [0, 0.4, 3.0], [0.2, -0.1, 0], 50.0),
        medium=homogeneous(1.5, 0.8),
        fog=null_sphere(0.8),
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.9, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.6)},
        wall={'type': 'rectangle', 'to_world': T().translate([0, 0, -1.5]).scale(3.0), 'bsdf': diffuse(0.5)},
        light={'type': 'rectangle', 'to_world': T().translate([0.8, 0.0, 0.0]).rotate([0, 1, 0], -30).scale(0.4),
               'bsdf': diffuse(0.0), 'emitter': {'type': 'area', 'radiance': rgb(4.0)}})


def open_fog(light='sphere', sky=0.0, res=16):
    """(f4) A fog that only the sensor carries (Mitsuba's simplest fog: the sensor's ``medium``,
    no shape bounding it, so that it fills all space, as volpath reads the scene): homogeneous,
    sigma_t 0.4, albedo 0.8; a diffuse floor (y = -0.5) and a diffuse sphere (radius 0.3 at the
    origin) that declare no medium (they lie in the fog); ``light``: 'sphere' (radius 0.1 at
    (0.4, 0.9, 0.2), radiance 40) or 'point' (intensity 2 there), neither declaring a medium
    (media_path.EmitterMedia finds the fog outside every shape: media_path.outside_medium);
    ``sky`` > 0 adds a constant sky beyond the unbounded fog, which bdpt refuses
    (scene_check.check_infinite_emitters). The camera at (0, 0.3, 2) in the fog."""
    objs = dict(
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.6)},
        ball={'type': 'sphere', 'center': [0, 0, 0], 'radius': 0.3, 'bsdf': diffuse(0.5)})
    if light == 'sphere':
        objs['light'] = {'type': 'sphere', 'center': [0.4, 0.9, 0.2], 'radius': 0.1,
                         'emitter': {'type': 'area', 'radiance': rgb(40.0)}}
    else:
        objs['light'] = {'type': 'point', 'position': [0.4, 0.9, 0.2], 'intensity': rgb(2.0)}
    if sky > 0:
        objs['sky'] = constant_sky(sky)
    return scene(sensor=_camera(res, [0, 0.3, 2.0], [0, -0.1, 0], 50.0, medium='fog'),
                 fog=homogeneous(0.4, 0.8), **objs)


def open_smoke(bound=False, res=16):
    """(f5) A heterogeneous medium that only the sensor carries: density_grid('blob') times 2
    over [-1, 1]^3 (albedo 0.8), the camera inside it at (0, 0.2, 0.8), a diffuse floor (y =
    -0.5, reaching past the grid) and a constant sky of 0.5; ``bound``: the same medium also
    declared by a null cube on the grid's box, which changes nothing (the medium holds no
    density outside its grid). Mitsuba's volpath renders the two differently (0.09 and 0.23 for
    the image mean: with no bound its camera rays that leave the grid see little of the sky), so
    the unbounded scene is compared with volpath's render of the bounded one."""
    objs = dict(floor={'type': 'rectangle', 'to_world': T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(3.0),
                       'bsdf': diffuse(0.6)},
                sky=constant_sky(0.5))
    if bound:
        objs['box'] = null_cube(1.0, medium='smoke')
    return scene(sensor=_camera(res, [0, 0.2, 0.8], [0, -0.2, 0], 60.0, medium='smoke'),
                 smoke=heterogeneous(density_grid('blob'), 2.0, 0.8), **objs)


def albedo_grid(res=16):
    """(f''') A homogeneous medium whose albedo is a volume (Mitsuba allows a ``gridvolume``
    there, as its docs scene medium_homogeneous_sss_textured does): sigma_t 3 in a null cube
    [-0.6, 0.6]^3, its albedo 0.05 and 0.95 in alternate octants (nearest), HG g 0.3; a diffuse
    floor (y = -0.65), a spherical light (radius 0.1, radiance 100) at (0.5, 1.5, 0.5), a sky of
    0.2. The camera at (0, 1.6, 2.6) in vacuum. A collision's sigma_s is the albedo where it
    happens (before: where the ray left)."""
    cells = np.indices((2, 2, 2)).sum(axis=0) % 2
    med = homogeneous(3.0, 0.5, 0.3)
    med['albedo'] = {'type': 'gridvolume', 'filter_type': 'nearest',
                     'data': mi.TensorXf(np.where(cells == 1, 0.95, 0.05).astype(np.float32)[..., None]),
                     'to_world': T().translate([-0.6, -0.6, -0.6]).scale(1.2)}
    return scene(
        sensor=_camera(res, [0, 1.6, 2.6], [0, -0.2, 0], 45.0),
        medium=med, box=null_cube(0.6),
        floor={'type': 'rectangle', 'to_world': T().translate([0, -0.65, 0]).rotate([1, 0, 0], -90).scale(3.0),
               'bsdf': diffuse(0.5)},
        light={'type': 'sphere', 'center': [0.5, 1.5, 0.5], 'radius': 0.1,
               'emitter': {'type': 'area', 'radiance': rgb(100.0)}},
        sky=constant_sky(0.2))


# ------------------------------------------------------------------- the test harness
BUILDERS = {
    'absorbing_sphere': absorbing_sphere, 'absorbing_cube': absorbing_cube, 'furnace': furnace,
    'single_scatter': single_scatter, 'fog_room': fog_room, 'grid_box': grid_box,
    'glass_media': glass_media, 'volumetric_caustic': volumetric_caustic, 'thin_glass': thin_glass,
    'straddling_light': straddling_light, 'albedo_grid': albedo_grid, 'open_fog': open_fog,
    'open_smoke': open_smoke, 'fog_box': fog_box,
}


def load(name, **params):
    """The scene ``BUILDERS[name](**params)``, loaded."""
    return mi.load_dict(BUILDERS[name](**params))


def media_reference(name, max_depth, which='volpath', spp=256, batches=16, seed0=REF_SEED, params=None,
                    integrator_params=None):
    """Reference batches (K, H, W, 3) of Mitsuba's ``which`` ('volpath' or 'volpathmis') at
    ``max_depth`` on the scene ``BUILDERS[name](**params)``, ``batches`` batches of ``spp``
    samples from seed ``seed0``, cached under tests/.refcache (helpers.reference) by the scene's
    name and parameters, the variant, the integrator and its ``integrator_params`` (e.g.
    ``{'rr_depth': 10000}``), spp, batches and seeds, and by the loaded scene's digest
    (helpers.scene_fingerprint: its description and every parameter's value, grids included),
    so that an edit of this file elsewhere leaves the stored references in use."""
    from helpers import reference
    params = dict(params or {})
    key = ('media_scenes', name, tuple(sorted(params.items())), mi.variant())
    integ = {'type': which, 'max_depth': max_depth, **(integrator_params or {})}
    return reference(key, lambda: load(name, **params), integ, spp, batches, seed0)


def media_lt_mask(scene_obj, max_null=8):
    """Pixels light tracing (technique lt) can render in a scene with media: the footprint (8x8
    probes, dilated by one pixel) of each, followed through up to ``max_null`` null surfaces,
    ends on surfaces without a delta lobe, never in the environment (helpers.no_delta_mask, with
    null boundaries crossed). A pixel seeing the medium in front of the sky is left out too: its
    directly seen sky is beyond lt."""
    sensor_ = scene_obj.sensors()[0]
    w, h = sensor_.film().crop_size()
    g = 8
    iy, ix, sy, sx = np.meshgrid(np.arange(h), np.arange(w), np.arange(g), np.arange(g), indexing='ij')
    pos = mi.Point2f(((ix + (sx + 0.5) / g) / w).ravel(), ((iy + (sy + 0.5) / g) / h).ravel())
    ray, _ = sensor_.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    bad = np.zeros(ix.size, bool)
    pending = np.ones(ix.size, bool)
    for _ in range(max_null + 1):
        si = scene_obj.ray_intersect(ray)
        flags = si.bsdf(ray).flags()
        valid = np.array(si.is_valid(), bool)
        null = np.array(mi.has_flag(flags, mi.BSDFFlags.Null), bool) & valid
        delta = np.array(mi.has_flag(flags, mi.BSDFFlags.Delta), bool) & valid & ~null
        bad |= pending & (~valid | delta)
        pending &= null
        ray = si.spawn_ray(ray.d)
    bad |= pending
    bad = bad.reshape(h, w, g * g).any(axis=2)
    dil = bad.copy()
    dil[1:] |= bad[:-1]; dil[:-1] |= bad[1:]; dil[:, 1:] |= bad[:, :-1]; dil[:, :-1] |= bad[:, 1:]
    return ~dil


def assert_value(batches, expected, what, mask=None, z=4.0, alpha=0.01, rtol=1e-5):
    """Renders (K, H, W, C) against an analytic value (a scalar, (H, W) or (H, W, C)): the whole
    (masked) image's mean per channel within ``z`` standard errors (from the K batch means), and
    every 4x4 block and every pixel by a one-sample t-test, Sidak-corrected at ``alpha`` over the
    tested entries (with 16 batches, 16 blocks and 3 channels: |t| <= 4.9). ``rtol`` of the value
    is allowed on top of the statistical bounds, for float32. An image without any spread between
    batches (exp(-1000) = 0) is held to ``rtol`` in every entry; otherwise entries without spread
    (a sparse estimator, e.g. light tracing at a silhouette, that scored in no batch) are left to
    the image mean."""
    from scipy import stats
    b = np.asarray(batches, np.float64)
    K, H, W, C = b.shape
    e = np.asarray(expected, np.float64)
    e = np.broadcast_to(e[..., None] if e.ndim == 2 else e, (H, W, C))
    m = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
    exact = bool(np.all(b.std(axis=0)[m] == 0))     # a noise-free estimator: held to rtol everywhere
    diff = b - e[None]
    img = diff[:, m].mean(axis=1)                       # (K, C)
    se = img.std(axis=0, ddof=1) / math.sqrt(K)
    tol = rtol * np.abs(e[m]).mean() + 1e-7
    bad = np.abs(img.mean(axis=0)) > z * se + tol
    assert not bad.any(), f'{what}: image mean {b.mean(axis=0)[m].mean(axis=0)} vs {e[m].mean(axis=0)} (se {se})'
    hb, wb = H // 4 * 4, W // 4 * 4
    blk = diff[:, :hb, :wb].reshape(K, hb // 4, 4, wb // 4, 4, C).mean(axis=(2, 4))
    bm = m[:hb, :wb].reshape(hb // 4, 4, wb // 4, 4).all(axis=(1, 3))
    ev = np.abs(e[m]).mean()
    for name, x, mk in (('4x4 block', blk, bm), ('pixel', diff, m)):
        x = x[:, mk].reshape(K, -1)
        if not exact:       # entries without spread (a sparse estimator that scored in no batch) say
            x = x[:, x.std(axis=0) > 0]     # nothing of their own: the image mean covers them
        if x.shape[1] == 0:
            continue
        mean, s = x.mean(axis=0), x.std(axis=0, ddof=1) / math.sqrt(K)
        t = np.where(s > 0, np.maximum(np.abs(mean) - rtol * ev - 1e-7, 0) / np.maximum(s, 1e-300),
                     np.where(np.abs(mean) <= rtol * ev + 1e-7, 0.0, np.inf))
        p = 2 * stats.t.sf(t, K - 1)
        thr = 1 - (1 - alpha) ** (1 / p.size)
        i = p.argmin()
        assert p.min() >= thr, (f'{what}: {name} {np.unravel_index(i, p.shape)} mean diff {mean.ravel()[i]:.4g} '
                                f'(se {s.ravel()[i]:.3g}), p {p.min():.3g} < {thr:.3g}')


def furnace_lt_expected(inside=False, sigma_t=1.0, radius=1.0, res=16, n=8):
    """(values (H, W), mask (H, W)): what light tracing (technique lt) renders in a homogeneous
    ``furnace``, everything but the emitter seen directly through the medium, 1 - exp(-sigma_t
    chord) per camera ray (the chord inside the sphere; continuous at the silhouette), by pixel
    quadrature; the mask leaves out the pixels on the silhouette (off_silhouette), where light
    tracing's estimate is sparse (a thin rim that few light subpaths scatter in: measured on main
    5f11042, rim pixels 5-13 standard errors low or without any splat at 16 x 16 spp)."""
    sc = mi.load_dict(furnace('homogeneous', 0.0, inside, sigma_t, radius, res=res))

    def radiance(o, d):
        t_in, t_out, hit = sphere_chord(o, d, (0, 0, 0), radius)
        return np.where(hit, 1.0 - np.exp(-sigma_t * (t_out - t_in)), 0.0)
    return pixel_quadrature(sc, radiance, n), off_silhouette(sc, (0, 0, 0), radius)


def strategy_batches(scene_obj, integrator, spp, batches, seed0=0):
    """(images (K, H, W, 3), {layer: {'weighted': (K, H, W, 3), 'unweighted': ...}}) of
    ``batches`` renders of bdpt with ``strategy_images`` (integrator.strategy_images per render)."""
    integ = mi.load_dict({**integrator, 'strategy_images': True})
    imgs, layers = [], {}
    for b in range(batches):
        imgs.append(np.array(mi.render(scene_obj, integrator=integ, spp=spp, seed=seed0 + b), np.float64)[:, :, :3])
        for name, kinds in integ.strategy_images.items():
            for kind, a in kinds.items():
                layers.setdefault(name, {}).setdefault(kind, []).append(np.asarray(a, np.float64))
    return np.stack(imgs), {n: {k: np.stack(v) for k, v in kinds.items()} for n, kinds in layers.items()}
