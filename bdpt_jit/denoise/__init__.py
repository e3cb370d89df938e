"""Denoising a render: Intel Open Image Denoise on the CPU variants, OptiX on the CUDA ones.

    import mitsuba as mi
    mi.set_variant('llvm_ad_rgb')
    import bdpt_jit
    from bdpt_jit.denoise import denoise, feature_images
    scene = mi.load_file('scenes/cornell-box.xml', res='128')
    image = mi.render(scene, spp=16)
    albedo, normal = feature_images(scene, spp=16)         # the feature pass (features.py)
    clean = denoise(image, albedo, normal)                  # numpy, the shape of the colour

``denoise`` takes linear HDR colour, (H, W, 3), or (H, W, 1) / (H, W) from a monochrome
variant, and optional albedo ((H, W, 3) or (H, W, 1), in [0, 1]) and normal ((H, W, 3), world
space) images; channels after the colour (alpha, AOVs) are refused: slice them off.
``denoise_with_settings`` also returns what ran (denoiser, device, filter, settings).

Which denoiser (backends.py): ``backend='auto'`` gives OIDN's ``RT`` filter on the CPU in
``llvm_*`` variants and ``mi.OptixDenoiser`` in ``cuda_*`` ones (OIDN on its CUDA device where
OptiX cannot start); ``'oidn-cpu'``, ``'optix'`` and ``'oidn-cuda'`` ask for one. A missing
package or a variant a denoiser cannot serve raises ``DenoiseError`` with one line saying what
to install (``pip install -e '.[denoise]'``) or what is supported.

Colour values that are not finite or are negative are set to 0 before denoising (the count is
in the settings, ``replaced_pixels``), and so is anything non-finite the denoiser returns."""

import numpy as np

from . import backends
from .backends import INSTALL_HINT, QUALITIES, DenoiseError
from .features import DEFAULT_MAX_DEPTH, feature_images

__all__ = ['denoise', 'denoise_with_settings', 'feature_images', 'DenoiseError', 'INSTALL_HINT',
           'DEFAULT_MAX_DEPTH', 'QUALITIES']


def denoise(image, albedo=None, normal=None, *, backend='auto', quality='high', to_sensor=None):
    """The denoised image (numpy float32, the shape of ``image``). ``to_sensor``: OptiX only,
    the world-to-sensor transform for world-space normals (``sensor.world_transform().inverse()``)."""
    return denoise_with_settings(image, albedo, normal, backend=backend, quality=quality,
                                 to_sensor=to_sensor)[0]


def denoise_with_settings(image, albedo=None, normal=None, *, backend='auto', quality='high', to_sensor=None):
    """(denoised image, settings dict: denoiser, device, filter, hdr, quality, features, ...)."""
    import mitsuba as mi
    if quality not in QUALITIES:
        raise DenoiseError(f"denoise quality must be one of {', '.join(QUALITIES)}, not {quality!r}")
    chosen = backends.choose(mi.variant(), backend)
    colour, shape, n_bad = _colour(image)
    alb = _feature(albedo, 'albedo', colour.shape[:2], (1, 3), 0.0, 1.0)
    nrm = _feature(normal, 'normal', colour.shape[:2], (3,), -1.0, 1.0)
    if nrm is not None and alb is None:
        raise DenoiseError("a normal image needs an albedo image too (Open Image Denoise and OptiX take "
                           "normals only with albedo)")
    out, settings = _run(chosen, colour, alb, nrm, quality, to_sensor)
    out = np.nan_to_num(np.asarray(out, dtype=np.float32)[:, :, :3], nan=0.0, posinf=0.0, neginf=0.0)
    out = np.maximum(out, 0.0)
    if shape[-1] == 1 or len(shape) == 2:       # monochrome: the three equal channels, averaged
        out = out.mean(axis=2, keepdims=True)
    settings.update(features=' '.join(n for n, a in (('albedo', alb), ('normal', nrm)) if a is not None) or 'none',
                    replaced_pixels=str(n_bad))
    return out.reshape(shape).astype(np.float32), settings


def _run(chosen, colour, alb, nrm, quality, to_sensor):
    """The chosen backend; on CUDA, OIDN's CUDA device where OptiX could not run."""
    if chosen == 'oidn-cpu':
        return backends.run_oidn_cpu(colour, alb, nrm, quality)
    if chosen == 'oidn-cuda':
        return backends.run_oidn_cuda(colour, alb, nrm, quality)
    try:
        return backends.run_optix(colour, alb, nrm, to_sensor)
    except DenoiseError as optix_error:
        try:
            out, settings = backends.run_oidn_cuda(colour, alb, nrm, quality)
        except DenoiseError as oidn_error:
            raise DenoiseError(f"{optix_error}; and {oidn_error}") from None
        settings['fallback'] = f'OptiX unavailable ({optix_error})'
        return out, settings


def _colour(image):
    """(float32 (H, W, 3) colour, the input's shape, count of values set to 0)."""
    a = np.asarray(image, dtype=np.float32)
    shape = a.shape
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3) or min(a.shape[:2]) == 0:
        raise DenoiseError(f"the image to denoise must be (H, W, 3), (H, W, 1) or (H, W), not {shape} "
                           f"(slice alpha and AOV channels off)")
    bad = ~np.isfinite(a) | (a < 0)
    a = np.where(bad, 0.0, a).astype(np.float32)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return np.ascontiguousarray(a), shape, int(bad.any(axis=2).sum())


def _feature(x, name, hw, channels, lo, hi):
    """A feature image as float32 (H, W, 3), finite and clipped to [lo, hi]; None stays None."""
    if x is None:
        return None
    a = np.asarray(x, dtype=np.float32)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[:2] != tuple(hw) or a.shape[2] not in channels:
        raise DenoiseError(f"the {name} image must be {hw[0]}x{hw[1]} with {' or '.join(map(str, channels))} "
                           f"channels, not {np.asarray(x).shape}")
    a = np.clip(np.nan_to_num(a, nan=0.0, posinf=hi, neginf=lo), lo, hi)
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return np.ascontiguousarray(a, dtype=np.float32)
