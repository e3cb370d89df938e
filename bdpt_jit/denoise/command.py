"""``bdpt-jit render --denoise``: the denoiser checked before the render, then the feature pass
and the denoiser run on the image the render reached (a ``--time`` budget's, an interrupted
render's), the EXR layers and header keys. A denoiser that cannot run leaves the raw image to be
written and keeps its one-line error (``error``) for the command to print."""

import math
import time

import numpy as np

from . import backends, denoise_with_settings, feature_images
from .backends import DenoiseError
from .features import DEFAULT_MAX_DEPTH

FEATURE_SPP_MAX = 64            # the feature pass traces the render's spp, up to this many


def feature_spp(spp):
    """Samples per pixel of the feature pass for a render that reached ``spp``."""
    return int(min(max(math.ceil(spp), 1), FEATURE_SPP_MAX))


class DenoiseStep:
    """One command's denoising. ``error``: why it could not run (None if it ran or has not)."""

    def __init__(self, variant, quality='high'):
        self.quality = quality
        self.error = None
        self.backend = None
        self.stats = {}
        try:
            self.backend = backends.choose(variant)
        except DenoiseError as e:
            self.error = str(e)

    def run(self, scene, colour, spp, seed):
        """(extra EXR channels, the image for the PNG): the denoised image and its features, or
        the raw image (and no channels) where the denoiser cannot run."""
        if self.error is not None:
            self.stats = {'denoise.error': self.error}
            return {}, colour
        sensor = scene.sensors()[0]
        t0 = time.perf_counter()
        spp_f = feature_spp(spp)
        try:
            albedo, normal = feature_images(scene, sensor, spp=spp_f, seed=seed)
        except Exception as e:                  # the render is kept whatever goes wrong here
            self.error = f"the feature pass failed: {backends.first_line(e)}"
            self.stats = {'denoise.error': self.error}
            return {}, colour
        t1 = time.perf_counter()
        try:
            den, settings = denoise_with_settings(colour, albedo, normal, backend=self.backend,
                                                  quality=self.quality,
                                                  to_sensor=sensor.world_transform().inverse())
        except DenoiseError as e:
            self.error = str(e)
            self.stats = {'denoise.error': self.error}
            return exr_layers(None, albedo, normal), colour
        t2 = time.perf_counter()
        self.stats = {f'denoise.{k}': v for k, v in settings.items()}
        self.stats.update({'denoise.feature_spp': spp_f, 'denoise.feature_max_depth': DEFAULT_MAX_DEPTH,
                           'denoise.normal_space': 'world', 'denoise.layers': 'denoised albedo normal',
                           'denoise.feature_time_s': f'{t1 - t0:.3f}', 'denoise.time_s': f'{t2 - t1:.3f}'})
        return exr_layers(den, albedo, normal), den


def exr_layers(denoised, albedo, normal):
    """EXR channels: ``denoised.R/G/B`` (``denoised.Y`` in a monochrome variant), ``albedo.R/G/B``
    (or ``albedo.Y``), ``normal.X/Y/Z``; float32, finite."""
    ch = {}
    for name, img, xyz in (('denoised', denoised, False), ('albedo', albedo, False), ('normal', normal, True)):
        if img is None:
            continue
        a = np.nan_to_num(np.asarray(img, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        a = a[:, :, None] if a.ndim == 2 else a
        names = 'XYZ' if xyz else ('Y' if a.shape[2] == 1 else 'RGB')
        for c, cname in enumerate(names):
            ch[f'{name}.{cname}'] = np.ascontiguousarray(a[:, :, c])
    return ch


def summary_text(stats):
    """The summary's line on denoising, from the header keys (None without --denoise)."""
    if 'denoise.error' in stats:
        return f"not denoised: {stats['denoise.error']}"
    if 'denoise.denoiser' not in stats:
        return None
    g = stats.get
    text = (f"{g('denoise.denoiser')} on {g('denoise.device')}, {g('denoise.filter')}, hdr, quality "
            f"{g('denoise.quality', 'n/a')}; features {g('denoise.features')} at {g('denoise.feature_spp')} spp "
            f"(feature pass {float(g('denoise.feature_time_s')):.2f} s, denoiser {float(g('denoise.time_s')):.2f} s)")
    if 'denoise.fallback' in stats:
        text += f"; {stats['denoise.fallback']}"
    return text
