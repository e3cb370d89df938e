"""What this version of ``bdpt`` renders, checked before any kernel is traced: a scene outside
that scope is refused with an error naming the plugin, never rendered wrongly."""

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from .cameras import CAMERAS

SUPPORTED_VARIANTS = tuple(f'{backend}{ad}_{colour}' for colour in ('rgb', 'mono', 'spectral')
                           for backend in ('llvm', 'cuda') for ad in ('_ad', ''))
SUPPORTED_EMITTERS = ('area', 'point', 'spot', 'directional', 'constant', 'envmap', 'sunsky', 'projector',
                      'directionalarea')
SUPPORTED_SENSORS = tuple(CAMERAS)     # a camera model registered in cameras.py is supported


class UnsupportedSceneError(ValueError):
    """The scene uses a plugin or feature that ``bdpt`` does not render (yet). ``alternative``:
    the Mitsuba integrator that renders it (the command suggests it), None: any."""

    def __init__(self, message, alternative=None):
        super().__init__(message)
        self.alternative = alternative


def check_variant():
    v = mi.variant()
    if v is not None and 'polarized' in v:
        raise UnsupportedSceneError(
            f"bdpt: Mitsuba variant '{v}' is not supported: polarized transport needs Mueller matrices "
            "and reference frames carried along both subpaths and matched at every connection; use the "
            f"same variant without polarization ({v.replace('_polarized', '')})")
    if v not in SUPPORTED_VARIANTS:
        raise UnsupportedSceneError(
            f"bdpt: Mitsuba variant '{v}' is not supported; use one of "
            f"{', '.join(SUPPORTED_VARIANTS)} (mi.set_variant(...) before loading the scene)")


# Mitsuba class names -> the plugin names users write in scene files
PLUGIN_NAMES = {
    'AreaLight': 'area', 'PointLight': 'point', 'SpotLight': 'spot', 'DirectionalEmitter': 'directional',
    'ConstantBackgroundEmitter': 'constant', 'EnvironmentMapEmitter': 'envmap', 'SunSkyEmitter': 'sunsky',
    'ProjectiveLight': 'projector', 'Projector': 'projector', 'DirectionalArea': 'directionalarea',
    'SunskyEmitter': 'sunsky', 'TimedSunskyEmitter': 'timed_sunsky',
    'PerspectiveCamera': 'perspective', 'ThinLensCamera': 'thinlens', 'OrthographicCamera': 'orthographic',
    'TelecentricLensCamera': 'telecentric', 'RadianceMeter': 'radiancemeter', 'IrradianceMeter': 'irradiancemeter',
    'DistantSensor': 'distant', 'DistantSensorImpl': 'distant', 'Batch': 'batch', 'BatchSensor': 'batch',
    'HomogeneousMedium': 'homogeneous', 'HeterogeneousMedium': 'heterogeneous',
    'Rectangle': 'rectangle', 'Disk': 'disk', 'Sphere': 'sphere', 'Cylinder': 'cylinder', 'Cube': 'cube',
    'OBJMesh': 'obj', 'PLYMesh': 'ply', 'SerializedMesh': 'serialized', 'BlenderMesh': 'blender',
    'MergeShape': 'merge', 'Mesh': 'mesh',
}

# Why a plugin that Mitsuba 3.9 has is refused (docs/coverage.md lists them all)
REFUSED_REASONS = {
    'batch': "it renders several sensors side by side into one film, each needing its own camera model: "
             "render each sensor on its own",
    'timed_sunsky': "Mitsuba 3.9.1 cannot evaluate it inside a symbolic loop (its own path and ptracer "
                    "fail on it too: 'jit_var_schedule(): not permitted'); sunsky with a fixed sun renders",
}

# Radiance textures that read more of the surface point than its uv and position: the start of a
# light subpath is Mitsuba's PositionSample3f (position, normal, uv), which has no triangle index
RADIANCE_TEXTURES_REFUSED = {'MeshAttribute': 'mesh_attribute'}

# Shapes an area light with a textured radiance may have. Mitsuba samples such a light through
# the texture and the shape's uv map (``eval_parameterization``), which must be one-to-one onto
# the surface: true of rectangles, disks and spheres. A mesh's uv map often is not (a cube's
# faces share their uvs: Mitsuba then samples one face, and its own path and ptracer are wrong
# as well), and a transformed cylinder's ``eval_parameterization`` returns points up to ~1e-5 of
# its size off the surface, where light subpaths start and intersect the cylinder again.
TEXTURED_EMITTER_SHAPES = {'Rectangle': 'rectangle', 'Disk': 'disk', 'Sphere': 'sphere'}
UV_CHECK_MAX_TRIANGLES = 2_000_000
UV_CHECK_GRID = 256
UV_TOLERANCE = 1e-4          # uvs this far outside [0, 1] still count (a sphere mesh's 1.00001)


def uv_map_is_one_to_one(mesh) -> bool:
    """A mesh's uv map is one-to-one (no two triangles overlap in uv space, all uvs in
    [0, 1]^2 up to UV_TOLERANCE), checked on a UV_CHECK_GRID^2 grid of points in uv space: each
    triangle, shrunk a little towards its centre (shared edges are not overlap), is laid in
    uv space at a height of its own, and a ray down through each point counts the triangles
    above it (Mitsuba's ray tracing: meshes of up to UV_CHECK_MAX_TRIANGLES). Mitsuba samples a
    textured area light on a mesh through this map (``eval_parameterization``); where it is
    one-to-one, Mitsuba's sampling and densities agree (a textured quad mesh: bdpt, lt and pt
    within 1.6 sigma of ptracer)."""
    params = mi.traverse(mesh)            # (an emitter's get_shape() gives the Shape interface)
    keys = set(params.keys())
    uv_key = next((k for k in keys if k.endswith('vertex_texcoords')), None)
    face_key = next((k for k in keys if k.endswith('faces')), None)
    if uv_key is None or face_key is None:
        return False
    faces = np.array(params[face_key], dtype=np.int64).reshape(-1, 3)
    if len(faces) > UV_CHECK_MAX_TRIANGLES:
        return False
    uv = np.array(params[uv_key], dtype=np.float64).reshape(-1, 2)
    if uv.size == 0 or uv.min() < -UV_TOLERANCE or uv.max() > 1 + UV_TOLERANCE:
        return False
    return _most_triangles_over_a_point(uv[faces]) <= 1


def _most_triangles_over_a_point(tri):
    """The largest number of the uv triangles ``tri`` (F x 3 x 2) over one point of the grid
    (uv_map_is_one_to_one)."""
    f = len(tri)
    centre = tri.mean(axis=1, keepdims=True)
    tri = centre + (tri - centre) * (1.0 - 1e-4)
    height = (np.arange(f, dtype=np.float64) + 1.0) / (f + 1.0)        # one level a triangle, in (0, 1)
    pos = np.concatenate([tri, np.broadcast_to(height[:, None, None], (f, 3, 1))], axis=2).reshape(-1, 3)
    flat = mi.Mesh('uv check', 3 * f, f)
    p = mi.traverse(flat)
    p['vertex_positions'] = mi.Float(pos.astype(np.float32).ravel())
    p['faces'] = mi.UInt32(np.arange(3 * f, dtype=np.uint32))
    p.update()
    scene = mi.load_dict({'type': 'scene', 'uv': flat})
    g = UV_CHECK_GRID
    u, v = np.meshgrid((np.arange(g) + 0.5) / g, (np.arange(g) + 0.5) / g)
    ray = mi.Ray3f(mi.Point3f(u.ravel(), v.ravel(), np.full(g * g, 2.0)), mi.Vector3f(0.0, 0.0, -1.0))
    count = np.zeros(g * g, np.int64)
    step = 0.5 / (f + 1.0)
    for _ in range(2):                   # (two triangles over a point settle it)
        si = scene.ray_intersect(ray)
        hit = np.array(si.is_valid())
        count += hit
        ray = mi.Ray3f(mi.Point3f(ray.o.x, ray.o.y, dr.select(si.is_valid(), si.p.z - step, -1.0)), ray.d)
    return int(count.max())


def _plugin_name(obj) -> str:
    name = str(obj.class_name() if hasattr(obj, 'class_name') else type(obj).__name__)
    return PLUGIN_NAMES.get(name, name)


def describe_medium(medium) -> str:
    """A medium (or any other plugin object: an emitter) as a message names it: its id (if any)
    and its plugin."""
    plugin = _plugin_name(medium)
    ident = str(medium.id()) if hasattr(medium, 'id') else ''
    return f"'{ident}' ({plugin})" if ident else f"'{plugin}'"


def _check_textured_area_light(shape):
    """An area emitter with a textured radiance on ``shape``: Mitsuba samples its positions
    through the shape's uv map (``eval_parameterization``), which bdpt relies on only where it
    is exact and one-to-one (TEXTURED_EMITTER_SHAPES, uv_map_is_one_to_one), and not on a
    rotated sphere: Mitsuba 3.9.1's sphere traces the ray that finds the point of a uv along
    the unrotated direction, so it returns another point than the texture chose (bdpt and lt
    1% bright under a rotated checkerboard sphere, where the two differ)."""
    name = str(shape.class_name())
    if name not in TEXTURED_EMITTER_SHAPES and not (shape.is_mesh() and uv_map_is_one_to_one(shape)):
        raise UnsupportedSceneError(
            f"bdpt: an area emitter with a textured radiance on the shape '{shape.id()}' "
            f"({_plugin_name(shape)}) is not supported: Mitsuba samples a textured emitter through "
            "the shape's uv map, which bdpt relies on only for "
            f"{', '.join(TEXTURED_EMITTER_SHAPES.values())} and meshes whose uv map is one-to-one "
            "(this one's triangles overlap in uv space, leave [0, 1]^2 or have no uvs; a cylinder's "
            "is not exact); give the emitter a uniform radiance or a one-to-one uv map")
    if name == 'Sphere':
        m = np.array(mi.traverse(shape)['to_world'].matrix, dtype=np.float64).reshape(4, 4)[:3, :3]
        if not np.allclose(m / np.linalg.norm(m[:, 0]), np.eye(3), atol=1e-5):
            raise UnsupportedSceneError(
                f"bdpt: an area emitter with a textured radiance on the rotated sphere '{shape.id()}' is not "
                "supported: Mitsuba 3.9.1's sphere finds the point of a texture's uv along the unrotated "
                "direction (eval_parameterization), so its textured position samples are not the points the "
                "texture chose; place the sphere by a translation and a uniform scale only, or give the "
                "emitter a uniform radiance")


def _check_directional_transform(emitter):
    """A ``directional`` emitter whose to_world scales its z axis: Mitsuba 3.9.1's
    ``sample_direction`` returns ``to_world * (0, 0, 1)`` unnormalised as the direction, so its
    own path multiplies the irradiance by the scale (twice as bright under a uniform scale of
    2), while light subpaths leave along the normalised direction (bdpt 31% and lt 50% below
    path there): no single image to agree with. Refused, naming the fix."""
    m = np.array(emitter.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    scale = float(np.linalg.norm(m[:3, 2]))
    if abs(scale - 1.0) > 1e-4:
        raise UnsupportedSceneError(
            f"bdpt: the directional emitter '{emitter.id()}' has a to_world that scales its direction by "
            f"{scale:.6g}: Mitsuba's directional emitter then reads its direction unnormalised (its own path "
            "renders the irradiance times that scale); give it a rotation only, or its 'direction' parameter")


def _transform_faults(shape):
    """Why the to_world of a disk or cylinder ``shape`` places an emitter off the surface its rays
    hit, or None. Mitsuba samples their positions through ``to_world`` and intersects through
    its stored inverse (disk) or a radius and length read from it (cylinder): a transform whose
    inverse does not invert it (``rotate`` about an axis that is not a unit vector: Mitsuba
    3.9.1 does not normalise it) put a disk light's points 1e-4 of its size off the disk, half
    of them behind it (bdpt and lt 52% dark); a cylinder with a shear or with unequal x and y
    scales (which Mitsuba warns of) has no consistent area (its own path 26% bright)."""
    t = mi.traverse(shape)['to_world']
    m = np.array(t.matrix, dtype=np.float64).reshape(4, 4)
    it = np.array(t.inverse_transpose, dtype=np.float64).reshape(4, 4)
    if not np.allclose(m @ it.T, np.eye(4), atol=1e-4):
        return ("its to_world's stored inverse does not invert it (a rotation about an axis that is not a unit "
                "vector? Mitsuba 3.9.1's rotate does not normalise the axis), so the points Mitsuba samples on "
                "it lie off the surface its rays hit; normalise the rotation axis")
    if str(shape.class_name()) == 'Cylinder':
        c = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
        norms = np.linalg.norm(m[:3, :2], axis=0)
        if abs(norms[0] - norms[1]) > 1e-4 * norms.max() or not np.allclose(c.T @ c, np.eye(3), atol=1e-4):
            return ("its to_world shears it or scales its x and y axes unequally, which Mitsuba's cylinder does "
                    "not support (it warns; its area and its sampled points then disagree with what rays hit); "
                    "use a rotation, a scale equal in x and y, and a translation")
    return None


def _check_emitter_placement(shape):
    """Refuses an area emitter on a disk or cylinder placed where Mitsuba's sampled points are
    not on the surface its rays hit (_transform_faults)."""
    if str(shape.class_name()) not in ('Disk', 'Cylinder'):
        return
    why = _transform_faults(shape)
    if why is not None:
        raise UnsupportedSceneError(
            f"bdpt: the area emitter on the {str(shape.class_name()).lower()} '{shape.id()}' is not supported: {why}")


def check_scene(scene: mi.Scene, sensor: mi.Sensor):
    check_variant()
    s_name = _plugin_name(sensor)
    if s_name not in SUPPORTED_SENSORS:
        why = f": {REFUSED_REASONS[s_name]}" if s_name in REFUSED_REASONS else " yet"
        raise UnsupportedSceneError(
            f"bdpt: sensor plugin '{s_name}' is not supported{why} (supported: {', '.join(SUPPORTED_SENSORS)})")
    for em in scene.emitters():
        e_name = _plugin_name(em)
        if e_name not in SUPPORTED_EMITTERS:
            why = f": {REFUSED_REASONS[e_name]}" if e_name in REFUSED_REASONS else " yet"
            raise UnsupportedSceneError(
                f"bdpt: emitter plugin '{e_name}' is not supported{why} (supported: {', '.join(SUPPORTED_EMITTERS)})")
        if e_name == 'directional':
            _check_directional_transform(em)
        if mi.has_flag(em.flags(), mi.EmitterFlags.Surface):
            text = str(em)
            shape = em.get_shape()
            if mi.has_flag(em.flags(), mi.EmitterFlags.SpatiallyVarying) and e_name == 'area':
                _check_textured_area_light(shape)
            _check_emitter_placement(shape)
            if e_name == 'directionalarea':
                try:       # its emitted radiance comes from the texture's sample_spectrum
                    em.sample_wavelengths(dr.zeros(mi.SurfaceInteraction3f, 1), mi.Float(0.5), True)
                except Exception as e:
                    raise UnsupportedSceneError(
                        "bdpt: the directionalarea emitter's radiance texture cannot be sampled by Mitsuba "
                        f"({e}); Mitsuba's ptracer fails on it too: use a bitmap or a uniform radiance") from None
            for cls, name in RADIANCE_TEXTURES_REFUSED.items():
                if cls + '[' in text:
                    raise UnsupportedSceneError(
                        f"bdpt: the {e_name} emitter's radiance from the texture '{name}' is not supported: a "
                        "light subpath starts at Mitsuba's position sample (position, normal, uv), which "
                        "carries no triangle to read a mesh attribute at (bitmap and checkerboard "
                        "radiance are supported)")
    _check_film(sensor)
    _check_instanced_media(scene, sensor)
    _check_monochrome_bsdfs(scene)


FILTER_NAMES = {'BoxFilter': 'box', 'GaussianFilter': 'gaussian', 'TentFilter': 'tent',
                'MitchellNetravaliFilter': 'mitchell', 'CatmullRomFilter': 'catmullrom', 'LanczosSincFilter': 'lanczos'}


def _check_film(sensor):
    """A film with ``sample_border`` and a filter wider than a pixel: Mitsuba's ``path`` then
    also traces camera rays through a border of pixels around the crop, so an edge pixel averages
    its whole filter footprint. Light-image splats cannot land there (``sample_direction`` drops
    points outside the crop), and bdpt's passes cover the crop's pixels: its edge pixels would be
    the footprint cut at the crop (1.5% off on average over a 16 x 16 Cornell box)."""
    film = sensor.film()
    border = int(film.rfilter().border_size())
    if film.sample_border() and border > 0:
        raise UnsupportedSceneError(
            f"bdpt: the film's 'sample_border' is true with the reconstruction filter "
            f"'{FILTER_NAMES.get(str(film.rfilter().class_name()), film.rfilter().class_name())}' ({border} pixel(s) of border): Mitsuba's path then samples "
            "beyond the crop, where light-image splats cannot reach, and bdpt's edge pixels would differ "
            "from it. Set sample_border to false (edge pixels as path renders them without it) or use the "
            "'box' filter, for which the border is empty")


# BSDF classes that Mitsuba 3.9.1 cannot evaluate in monochrome variants, and why
MONO_REFUSED_BSDFS = {
    'Hair': "Mitsuba 3.9.1's hair computes its absorption with srgb_model_eval, which fails in "
            "monochrome variants (its own path fails too)",
}


def _check_monochrome_bsdfs(scene):
    """Refuse, naming the shape, a BSDF that cannot be evaluated in a monochrome variant,
    before any kernel is traced (else: an error from deep inside the render)."""
    if not mi.is_monochromatic:
        return
    for shape in scene.shapes():
        text = str(shape.bsdf()) if shape.bsdf() is not None else ''
        for cls, why in MONO_REFUSED_BSDFS.items():
            if cls + '[' in text:
                where = f"the shape '{shape.id()}'" if shape.id() else f"a {_plugin_name(shape)} shape"
                raise UnsupportedSceneError(
                    f"bdpt: the BSDF of {where} ({cls.lower()}) cannot be rendered in the "
                    f"variant '{mi.variant()}': {why}; use an RGB or spectral variant")


def _check_instanced_media(scene, sensor):
    """Refuse a medium the analysis cannot see: shapes inside instanced shape groups are not in
    ``scene.shapes()``, so a medium on one of them would be rendered as vacuum. A scene with
    instances and a medium among its objects that no visible shape, emitter or sensor uses is
    refused (the medium may be an instanced shape's)."""
    if not has_instances(scene):
        return
    seen = {int(dr.reinterpret_array(mi.UInt32, mi.MediumPtr(m))[0]) for m in scene_media(scene, sensor)}
    params = mi.traverse(scene)
    for key in params.keys():
        node = params.properties[key][2]
        if isinstance(node, mi.Medium) and int(dr.reinterpret_array(mi.UInt32, mi.MediumPtr(node))[0]) not in seen:
            raise UnsupportedSceneError(
                f"bdpt: the medium {describe_medium(node)} is not on any shape bdpt can see: media on shapes "
                "inside instanced shape groups are not supported (bdpt would render them as vacuum); put the "
                "medium's shape outside the shape group", alternative='volpath')


def check_infinite_emitters(scene, outside):
    """Refuse an infinite emitter (environment, constant, sun and sky, directional) beyond a
    medium that fills space: where the medium outside every shape (media_path.outside_medium)
    is homogeneous it has no end, and no light from infinity crosses it (Mitsuba's volpath
    attenuates such light over twice the scene's radius from each point, a convention that a
    light subpath, leaving from the emitter, cannot follow)."""
    if outside is None or not outside.is_homogeneous():
        return
    for em in scene.emitters():
        if mi.has_flag(em.flags(), mi.EmitterFlags.Infinite):
            raise UnsupportedSceneError(
                f"bdpt: the emitter {describe_medium(em)} lies at infinity, beyond the homogeneous medium "
                f"{describe_medium(outside)} that fills the space outside every shape (the sensor's medium, "
                "or the shapes' exterior, with no shape bounding it): no light from infinity crosses an "
                "unbounded medium. Bound the medium with a shape (e.g. a cube with a null BSDF and the "
                "medium as its interior) or remove the emitter", alternative='volpath')


def has_instances(scene: mi.Scene) -> bool:
    """True if the scene instances shape groups: their shapes and BSDFs are not in
    ``scene.shapes()``, so every analysis below answers conservatively (delta handling, exact
    adjoint, every stored field), and the diffuse table is not used (context.diffuse_table)."""
    return any(str(s.class_name()) == 'Instance' for s in scene.shapes())


def scene_has_lobe(scene: mi.Scene, *lobes) -> bool:
    """True if any BSDF of the scene has one of the ``lobes`` (mi.BSDFFlags), or the scene has
    instances (whose BSDFs this test cannot see)."""
    if has_instances(scene):
        return True
    mask = 0
    for lobe in lobes:
        mask |= int(lobe)
    return any(int(s.bsdf().flags()) & mask for s in scene.shapes() if s.bsdf() is not None)


def scene_has_delta_bsdf(scene: mi.Scene) -> bool:
    """True if any BSDF of the scene has a delta lobe (then the delta handling is traced)."""
    return scene_has_lobe(scene, mi.BSDFFlags.Delta)


def scene_refracts(scene: mi.Scene) -> bool:
    """True if any BSDF of the scene has a delta or glossy transmission lobe (a dielectric: the
    camera subpaths' roulette then follows the refractions, transport.scatter)."""
    return scene_has_lobe(scene, mi.BSDFFlags.DeltaTransmission, mi.BSDFFlags.GlossyTransmission)


def scene_perturbs_normals(scene: mi.Scene) -> bool:
    """True if a BSDF of the scene perturbs the shading frame from the surface tangents
    (normal or bump map): light vertices then also store the tangents."""
    if has_instances(scene):
        return True
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None and any(name in str(bsdf) for name in ('NormalMap', 'BumpMap')):
            return True
    return False


# BSDF classes (as Mitsuba 3.9.1 names and prints them, nested ones included) whose
# importance-mode value is their radiance-mode value with the directions swapped (the adjoint,
# Veach's eq. 5.17), checked with _non_reciprocal; and the texture and spectrum names that
# printing them shows. Anything else is probed.
RECIPROCAL_CLASSES = {
    'SmoothDiffuse', 'RoughConductor', 'SmoothConductor', 'SmoothDielectric', 'RoughDielectric',
    'ThinDielectric', 'SmoothPlastic', 'RoughPlastic', 'TwoSided', 'TwoSidedBRDF', 'BlendBSDF', 'Null',
    'Mask', 'MaskBSDF', 'NormalMap', 'BumpMap', 'Principled', 'PolarizedPlastic', 'SpecularDiffusePolarized',
    'LinearPolarizer', 'CircularPolarizer', 'LinearRetarder', 'brdf', 'nested_bsdf',
    'Checkerboard', 'MeshAttribute', 'Transform', 'ContinuousDistribution', 'IrregularContinuousDistribution',
}


def _known_reciprocal(bsdf) -> bool:
    """Every class ``bsdf`` prints (nested BSDFs, textures, spectra) is in RECIPROCAL_CLASSES or
    a texture or spectrum. Mitsuba prints principled BSDFs as 'Principled BSDF :' and
    principledthin as 'The Thin Principled BSDF :' (not reciprocal: its thin transmission)."""
    text = str(bsdf)
    names = set(re.findall(r'([A-Za-z_]\w*)\[', text)) | {str(bsdf.class_name())}
    names |= set(re.findall(r'([A-Za-z][\w ]*) BSDF :', text))
    return all(n in RECIPROCAL_CLASSES or n.endswith(('Spectrum', 'Texture')) for n in names)


def _vectors(x):
    """mi.Vector3f of a numpy array of directions (n x 3)."""
    return mi.Vector3f(*[mi.Float(x[:, c].astype(np.float32)) for c in range(3)])


def _probe_surface(wi):
    """A SurfaceInteraction3f per direction of ``wi`` (n x 3, local): the BSDF probes' surface
    (_null_excludable, _non_reciprocal), its frame the identity, its uv spread over [0, 1)^2,
    visible wavelengths in spectral variants."""
    n = len(wi)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi, si.n = _vectors(wi), mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    k = np.arange(n)
    si.uv = mi.Point2f(mi.Float((k * 0.618034 % 1).astype(np.float32)), mi.Float((k * 0.754878 % 1).astype(np.float32)))
    if mi.is_spectral:
        si.wavelengths = mi.Spectrum(450, 520, 590, 660)
    return si


def _probe_pairs(n=48):
    """Directions on a spiral over the whole sphere and every ordered pair of them not within
    0.05 of tangent at either end: (wi, wo) as numpy arrays (pairs x 3)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = k * np.pi * (3 - np.sqrt(5))
    d = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing='ij')
    keep = (i != j) & (np.abs(d[i, 2]) > 0.05) & (np.abs(d[j, 2]) > 0.05)
    return d[i[keep]], d[j[keep]]


def _non_reciprocal(bsdf) -> bool:
    """Whether ``bsdf``'s importance-mode value f*(a -> b) |cos b| differs from its radiance-mode
    value with the directions swapped, f(b -> a) |cos a| |cos b| / |cos a|, by more than 1e-3
    of their size at any probe pair (_probe_pairs; uv varied over the pairs). Mitsuba 3.9.1's
    ``hair`` (its azimuthal offset is read from wi) and ``principledthin`` (its thin
    transmission) are not reciprocal."""
    from .connect import CTX_IMPORTANCE, CTX_RADIANCE
    a, b = _probe_pairs()
    f_imp = np.atleast_2d(np.array(bsdf.eval(CTX_IMPORTANCE, _probe_surface(a), _vectors(b))))
    f_rad = np.atleast_2d(np.array(bsdf.eval(CTX_RADIANCE, _probe_surface(b), _vectors(a)))) * np.abs(b[:, 2] / a[:, 2])
    diff = np.abs(f_imp - f_rad)
    return bool((diff > 1e-3 * (np.abs(f_imp) + np.abs(f_rad)) + 1e-6).any())


def scene_non_reciprocal(scene: mi.Scene) -> bool:
    """True if a BSDF of the scene is not reciprocal (_non_reciprocal): only BSDFs with classes
    outside RECIPROCAL_CLASSES are probed."""
    bsdfs = _distinct([s.bsdf() for s in scene.shapes() if s.bsdf() is not None])
    return any(_non_reciprocal(b) for b in bsdfs if not _known_reciprocal(b))


# BSDF and spectrum classes (as Mitsuba 3.9 prints them) whose values depend neither on the
# surface's uv nor on its tangent unless Mitsuba flags them Anisotropic: a BSDF built only from
# these needs neither stored (a texture, mesh attribute, normal map or unknown plugin does)
UV_FREE_CLASSES = {
    'SmoothDiffuse', 'RoughConductor', 'SmoothConductor', 'SmoothDielectric', 'RoughDielectric',
    'ThinDielectric', 'SmoothPlastic', 'RoughPlastic', 'TwoSided', 'TwoSidedBRDF', 'BlendBSDF', 'Null',
    'UniformSpectrum', 'SRGBReflectanceSpectrum', 'brdf', 'nested_bsdf',
}


def _uv_free(bsdf) -> bool:
    names = set(re.findall(r'([A-Za-z_]\w*)\[', str(bsdf))) | {str(bsdf.class_name())}
    return names <= UV_FREE_CLASSES


def _flat_faces(shape) -> bool:
    """True if the shading normal of ``shape`` is its geometric normal, up to sign and rounding:
    disks and spheres, meshes without vertex normals, meshes whose vertex normals are the face
    normals (rectangles, cubes, faceted models)."""
    name = str(shape.class_name())
    if name in ('Disk', 'Sphere'):
        return True
    if not shape.is_mesh():
        return False
    if not shape.has_vertex_normals():
        return True
    pos = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
    nrm = np.array(shape.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
    faces = np.array(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
    if faces.size == 0:
        return True
    e1 = pos[faces[:, 1]] - pos[faces[:, 0]]
    e2 = pos[faces[:, 2]] - pos[faces[:, 0]]
    fn = np.cross(e1, e2)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    for k in range(3):
        vn = nrm[faces[:, k]]
        vn = vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
        if np.any(np.abs(np.abs(np.sum(vn * fn, axis=1)) - 1.0) > 1e-6):
            return False
    return True


class VertexNeeds:
    """Which optional fields of a stored light vertex (store.FIELDS) the scene reads:
    - geometric_normal: a shape whose shading normals differ from its face normals;
    - tangent: an anisotropic BSDF, or one this analysis does not know (kept conservatively);
    - uv (with shape and triangle): a textured BSDF, a mesh attribute, or an unknown class;
    - surface_tangents: normal or bump maps;
    - depth: a delta or non-smooth BSDF (then not every vertex is stored, and a vertex's level
      does not give its depth)."""

    def __init__(self, scene: mi.Scene):
        if has_instances(scene):       # shapes and BSDFs this analysis cannot see: every field
            self.geometric_normal = self.uv = self.tangent = self.surface_tangents = self.depth = True
            return
        bsdfs = [s.bsdf() for s in scene.shapes() if s.bsdf() is not None]
        self.geometric_normal = not all(_flat_faces(s) for s in scene.shapes())
        uv_free = all(_uv_free(b) for b in bsdfs)
        self.uv = not uv_free
        self.tangent = not uv_free or any(mi.has_flag(b.flags(), mi.BSDFFlags.Anisotropic) for b in bsdfs)
        self.surface_tangents = scene_perturbs_normals(scene)
        self.depth = not all(mi.has_flag(b.flags(), mi.BSDFFlags.Smooth) and
                             not mi.has_flag(b.flags(), mi.BSDFFlags.Delta) for b in bsdfs)


def scene_media(scene: mi.Scene, sensor: mi.Sensor = None) -> list:
    """Every medium of the scene (shape interiors and exteriors, emitters, the sensor), each once."""
    found = {}
    objs = [m for s in scene.shapes() for m in (s.interior_medium(), s.exterior_medium())]
    objs += [e.get_medium() for e in scene.emitters()]
    objs += [s.get_medium() for s in ([sensor] if sensor is not None else scene.sensors())]
    for m in objs:
        if m is not None:
            found[int(dr.reinterpret_array(mi.UInt32, mi.MediumPtr(m))[0])] = m
    return list(found.values())


def _chromatic(medium) -> bool:
    """A homogeneous medium whose sigma_t differs between the channels of the variant (in
    spectral variants: at four wavelengths across the visible range)."""
    mei = dr.zeros(mi.MediumInteraction3f, 1)
    if mi.is_spectral:
        mei.wavelengths = mi.Spectrum(400.0, 500.0, 600.0, 700.0)
    sigma_t = np.array(medium.get_scattering_coefficients(mei, True)[2]).ravel()
    return bool(np.ptp(sigma_t) > 0)


def _gray(medium) -> bool:
    """Whether the medium's sigma_t is the same in every channel everywhere (then distance
    sampling's survival probability is the transmittance itself, which beam merging needs:
    beams.py). Homogeneous: ``_chromatic``; heterogeneous: its sigma_t volume's values (a grid's
    channels, a constant's value), False where they cannot be read."""
    if mi.is_monochromatic:
        return True
    if medium.is_homogeneous():
        return not _chromatic(medium)
    try:
        params = mi.traverse(medium)
        keys = [k for k in params.keys() if k.startswith('sigma_t.')]
    except Exception:       # (a medium plugin without traversable parameters)
        return False
    for k in keys:
        a = np.array(params[k], dtype=np.float64)
        a = a.reshape(-1, a.shape[-1]) if (k.endswith('.data') and a.ndim > 1) else a.reshape(1, -1)
        if a.shape[1] > 1 and np.ptp(a, axis=1).max() > 0:
            return False
    return bool(keys)


def media_info(scene: mi.Scene, sensor: mi.Sensor = None):
    """media.MediaInfo of the scene: whether it has media, a heterogeneous one (ratio and delta
    tracking traced), a chromatic homogeneous one (a channel chosen per distance sample), and
    whether every medium is gray (beam merging: beams.py), whether a BSDF is partly null."""
    from .media import MediaInfo
    media = scene_media(scene, sensor)
    return MediaInfo(any=bool(media),
                     heterogeneous=any(not m.is_homogeneous() for m in media),
                     chromatic=any(m.is_homogeneous() and _chromatic(m) for m in media),
                     gray=all(_gray(m) for m in media),
                     partial_null=any(_partial_null(s.bsdf()) for s in scene.shapes()),
                     any_null=any(_any_null(s.bsdf()) and not null_emitter_shape(s) for s in scene.shapes()),
                     null_emitters=any(null_emitter_shape(s) for s in scene.shapes()),
                     exclude_null=_null_excludable(_distinct([s.bsdf() for s in scene.shapes() if _partial_null(s.bsdf())])),
                     varying_albedo=any(m.is_homogeneous() and _varying_albedo(m) for m in media))


def _varying_albedo(medium) -> bool:
    """A medium whose albedo is a volume other than a constant (a ``gridvolume``)."""
    return any(k.startswith('albedo.') and not k.startswith('albedo.value') for k in mi.traverse(medium).keys())


def _distinct(bsdfs) -> list:
    """``bsdfs`` with each BSDF once (shapes share them)."""
    found = {}
    for b in bsdfs:
        found.setdefault(int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0]), b)
    return list(found.values())


def _null_excludable(bsdfs) -> bool:
    """Whether every one of ``bsdfs`` (partly null) samples only delta lobes and never its Null
    lobe when asked to leave Null out (vertex.context_without_null): ``thindielectric`` does, a
    ``mask`` does not (it then samples Null alone). Probed with 64 incident directions and
    lobe samples on both sides; False for an empty list (nothing to exclude)."""
    from .vertex import IMPORTANCE, RADIANCE, context_without_null
    if not bsdfs:
        return False
    k = np.arange(64)
    cos = (k % 8 + 0.5) / 8 * np.where(k < 32, 1.0, -1.0)
    si = _probe_surface(np.stack([np.sqrt(1 - cos * cos), np.zeros_like(cos), cos], axis=1))
    u1, u2 = mi.Float(((k // 8 % 4 + 0.5) / 4).astype(np.float32)), mi.Point2f(0.3, 0.7)
    for bsdf in bsdfs:
        for mode in (RADIANCE, IMPORTANCE):
            bs, w = bsdf.sample(context_without_null(mode), si, u1, u2)
            null = np.array(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null))
            delta = np.array(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
            if null.any() or not (delta | (np.array(dr.max(w)) == 0)).all():
                return False
    return True


def _any_null(bsdf) -> bool:
    """A BSDF with a Null lobe (``null``, ``mask``, ``thindielectric``, ...)."""
    return bsdf is not None and bool(int(bsdf.flags()) & int(mi.BSDFFlags.Null))


def null_emitter_shape(shape) -> bool:
    """An emitter whose BSDF is ``null`` alone, on a shape that is no medium transition. Walks
    and edges do not pass it as an invisible surface (media.is_null) but meet it as a surface
    vertex with a delta lobe that goes straight on, as Mitsuba's path does (a bounce): its
    emission is then the camera subpath's s=0 as at any emitter. Passed whole, it was seen by no
    camera subpath: technique pt rendered neither the emitter in view nor in a mirror (68% and
    59% dark on the Cornell box with its light's BSDF null) and bdpt not in a mirror (2.5%)."""
    bsdf = shape.bsdf()
    return (shape.is_emitter() and not shape.is_medium_transition() and bsdf is not None
            and not (int(bsdf.flags()) & _lobes()))


def _lobes() -> int:
    from .media import _LOBES
    return _LOBES


def _partial_null(bsdf) -> bool:
    """A BSDF with a Null lobe beside others (media.is_null: not an index-matched boundary)."""
    from .media import _LOBES
    flags = int(bsdf.flags()) if bsdf is not None else 0
    return bool(flags & int(mi.BSDFFlags.Null)) and bool(flags & _LOBES)
