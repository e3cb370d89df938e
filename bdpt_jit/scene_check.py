"""What this version of ``bdpt`` renders, checked before any kernel is traced: a scene outside
that scope is refused with an error naming the plugin, never rendered wrongly."""

import mitsuba as mi

SUPPORTED_VARIANTS = ('llvm_ad_rgb', 'cuda_ad_rgb', 'llvm_rgb', 'cuda_rgb')
SUPPORTED_EMITTERS = ('area', 'point', 'spot', 'directional', 'constant', 'envmap')
SUPPORTED_SENSORS = ('perspective', 'thinlens')


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
