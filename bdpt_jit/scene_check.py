"""What this version of ``bdpt`` renders, checked before any kernel is traced: a scene outside
that scope is refused with an error naming the plugin, never rendered wrongly."""

import re

import mitsuba as mi
import numpy as np

from .cameras import CAMERAS

SUPPORTED_VARIANTS = ('llvm_ad_rgb', 'cuda_ad_rgb', 'llvm_rgb', 'cuda_rgb')
SUPPORTED_EMITTERS = ('area', 'point', 'spot', 'directional', 'constant', 'envmap')
SUPPORTED_SENSORS = tuple(CAMERAS)     # a camera model registered in cameras.py is supported


class UnsupportedSceneError(ValueError):
    """The scene uses a plugin or feature that ``bdpt`` does not render (yet)."""


def check_variant():
    v = mi.variant()
    if v not in SUPPORTED_VARIANTS:
        raise UnsupportedSceneError(
            f"bdpt: Mitsuba variant '{v}' is not supported; use one of "
            f"{', '.join(SUPPORTED_VARIANTS)} (mi.set_variant(...) before loading the scene)")


# Mitsuba class names -> the plugin names users write in scene files
PLUGIN_NAMES = {
    'AreaLight': 'area', 'PointLight': 'point', 'SpotLight': 'spot', 'DirectionalEmitter': 'directional',
    'ConstantBackgroundEmitter': 'constant', 'EnvironmentMapEmitter': 'envmap', 'SunSkyEmitter': 'sunsky',
    'ProjectiveLight': 'projector', 'Projector': 'projector', 'DirectionalArea': 'directionalarea',
    'SunskyEmitter': 'sunsky',
    'PerspectiveCamera': 'perspective', 'ThinLensCamera': 'thinlens', 'OrthographicCamera': 'orthographic',
    'TelecentricLensCamera': 'telecentric', 'RadianceMeter': 'radiancemeter', 'IrradianceMeter': 'irradiancemeter',
    'DistantSensor': 'distant', 'Batch': 'batch',
}


def _plugin_name(obj) -> str:
    name = str(obj.class_name() if hasattr(obj, 'class_name') else type(obj).__name__)
    return PLUGIN_NAMES.get(name, name)


def check_scene(scene: mi.Scene, sensor: mi.Sensor):
    check_variant()
    s_name = _plugin_name(sensor)
    if s_name not in SUPPORTED_SENSORS:
        raise UnsupportedSceneError(
            f"bdpt: sensor plugin '{s_name}' is not supported yet (supported: {', '.join(SUPPORTED_SENSORS)})")
    if sensor.get_medium() is not None:
        raise UnsupportedSceneError("bdpt: participating media are not supported (the sensor has a medium)")
    for em in scene.emitters():
        e_name = _plugin_name(em)
        if e_name not in SUPPORTED_EMITTERS:
            raise UnsupportedSceneError(
                f"bdpt: emitter plugin '{e_name}' is not supported yet (supported: {', '.join(SUPPORTED_EMITTERS)})")
        keys = set(mi.traverse(em).keys())
        if any(k.startswith('radiance.') and k != 'radiance.value' for k in keys):
            raise UnsupportedSceneError(
                "bdpt: area emitters with a textured (spatially varying) radiance are not supported yet")
        if em.get_medium() is not None:
            raise UnsupportedSceneError("bdpt: participating media are not supported (an emitter has a medium)")
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            raise UnsupportedSceneError(
                f"bdpt: participating media are not supported (shape '{shape.id()}' has a medium)")


def scene_has_delta_bsdf(scene: mi.Scene) -> bool:
    """True if any BSDF of the scene has a delta lobe (then the delta handling is traced)."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta):
            return True
    return False


def scene_perturbs_normals(scene: mi.Scene) -> bool:
    """True if a BSDF of the scene perturbs the shading frame from the surface tangents
    (normal or bump map): light vertices then also store the tangents."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None and any(name in str(bsdf) for name in ('NormalMap', 'BumpMap')):
            return True
    return False


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
    """Which optional fields of a stored light vertex (light_path.FIELDS) the scene reads:
    - geometric_normal: a shape whose shading normals differ from its face normals;
    - tangent: an anisotropic BSDF, or one this analysis does not know (kept conservatively);
    - uv (with shape and triangle): a textured BSDF, a mesh attribute, or an unknown class;
    - surface_tangents: normal or bump maps;
    - depth: a delta or non-smooth BSDF (then not every vertex is stored, and a vertex's level
      does not give its depth)."""

    def __init__(self, scene: mi.Scene):
        bsdfs = [s.bsdf() for s in scene.shapes() if s.bsdf() is not None]
        self.geometric_normal = not all(_flat_faces(s) for s in scene.shapes())
        uv_free = all(_uv_free(b) for b in bsdfs)
        self.uv = not uv_free
        self.tangent = not uv_free or any(mi.has_flag(b.flags(), mi.BSDFFlags.Anisotropic) for b in bsdfs)
        self.surface_tangents = scene_perturbs_normals(scene)
        self.depth = not all(mi.has_flag(b.flags(), mi.BSDFFlags.Smooth) and
                             not mi.has_flag(b.flags(), mi.BSDFFlags.Delta) for b in bsdfs)
