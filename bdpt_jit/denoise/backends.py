"""The denoisers behind ``bdpt_jit.denoise.denoise``: which one a variant gets, and each call.

- CPU variants (``llvm_*``): Intel Open Image Denoise's ``RT`` filter on its CPU device
  (package ``pyoidn``), HDR colour, albedo and normal, ``cleanAux`` off (the features are
  prefiltered by OIDN), quality ``high``.
- CUDA variants (``cuda_*``): Mitsuba's ``mi.OptixDenoiser`` (OptiX's HDR model, albedo and
  normals in the sensor's frame); where OptiX cannot be started, OIDN's ``RT`` filter on its CUDA
  device. Neither has run on this project's machines (no GPU): the code follows the two APIs'
  documentation, and the header and summary say which one ran.

Every backend takes float32 (H, W, 3) colour and features and returns (H, W, 3)."""

import numpy as np

INSTALL_HINT = "pip install -e '.[denoise]'"
QUALITIES = ('high', 'balanced', 'fast')


class DenoiseError(Exception):
    """The denoiser cannot run: a missing package, a variant it cannot serve, a bad input.
    The message is one line that says what to do."""


def variant_kind(variant):
    """'cpu' or 'cuda' for a variant the denoisers serve; DenoiseError for the others."""
    if variant is None:
        raise DenoiseError("denoising needs a Mitsuba variant: call mi.set_variant(...) first")
    if 'polarized' in variant:
        raise DenoiseError(f"denoising does not support the polarized variant '{variant}'; use "
                           f"{variant.replace('_polarized', '')}")
    if variant.startswith('llvm_'):
        return 'cpu'
    if variant.startswith('cuda_'):
        return 'cuda'
    raise DenoiseError(f"denoising needs a JIT variant (llvm_* on the CPU: Open Image Denoise; cuda_*: "
                       f"OptiX), not '{variant}' (the feature pass is a Dr.Jit kernel)")


def import_pyoidn():
    """pyoidn, or DenoiseError saying how to install it."""
    try:
        import pyoidn
    except ImportError:
        raise DenoiseError(f"denoising needs the package pyoidn (Intel Open Image Denoise), which is not "
                           f"installed: {INSTALL_HINT}") from None
    return pyoidn


def oidn_version(pyoidn):
    return getattr(getattr(pyoidn, 'version', None), 'oidn_version', 'unknown')


def choose(variant, backend='auto'):
    """The backend for ``variant``: 'oidn-cpu', 'optix' or 'oidn-cuda' (``backend`` 'auto'
    picks by variant; naming one checks that the variant can run it). Raises DenoiseError."""
    kind = variant_kind(variant)
    if backend == 'auto':
        backend = 'oidn-cpu' if kind == 'cpu' else 'optix'
    if backend not in ('oidn-cpu', 'optix', 'oidn-cuda'):
        raise DenoiseError(f"unknown denoiser {backend!r}: 'auto', 'oidn-cpu', 'optix' or 'oidn-cuda'")
    if backend == 'oidn-cpu':
        import_pyoidn()
    elif kind != 'cuda':
        raise DenoiseError(f"the {backend} denoiser needs a cuda_* variant, not '{variant}' "
                           f"(on llvm_* variants: oidn-cpu)")
    elif backend == 'oidn-cuda':
        import_pyoidn()
    return backend


def run_oidn_cpu(colour, albedo, normal, quality):
    """OIDN's RT filter on the CPU device, HDR. Returns (image, settings)."""
    pyoidn = import_pyoidn()
    try:
        out = pyoidn.denoise(colour, albedo, normal, hdr=True, clean_aux=False, quality=quality)
    except (RuntimeError, ValueError, TypeError) as e:
        raise DenoiseError(f"Open Image Denoise failed: {e}") from None
    return out, {'denoiser': f'Intel Open Image Denoise {oidn_version(pyoidn)} (pyoidn)', 'device': 'cpu',
                 'filter': 'RT', 'hdr': 'true', 'clean_aux': 'false', 'quality': quality}


def run_optix(colour, albedo, normal, to_sensor):
    """mi.OptixDenoiser (needs a cuda_* variant with OptiX). Normals are turned into the sensor's
    frame by ``to_sensor`` (a world-to-sensor mi.Transform4f), as the denoiser asks. Returns
    (image, settings); raises DenoiseError where OptiX cannot run."""
    import mitsuba as mi
    h, w = colour.shape[:2]
    try:
        den = mi.OptixDenoiser(mi.ScalarVector2u(w, h), albedo=albedo is not None, normals=normal is not None)
        kw = {}
        if albedo is not None:
            kw['albedo'] = mi.TensorXf(albedo)
        if normal is not None:
            kw['normals'] = mi.TensorXf(normal)
            if to_sensor is not None:
                kw['to_sensor'] = to_sensor
        out = np.array(den(mi.TensorXf(colour), **kw), dtype=np.float32)
    except Exception as e:          # no OptiX in the driver, a Mitsuba built without it, ...
        raise DenoiseError(f"the OptiX denoiser could not run: {first_line(e)}") from None
    return out[:, :, :3], {'denoiser': f'OptiX (mi.OptixDenoiser, Mitsuba {mi.__version__})', 'device': 'cuda',
                           'filter': 'OptiX HDR model', 'hdr': 'true',
                           'normals': 'sensor frame' if to_sensor is not None else 'as given'}


def run_oidn_cuda(colour, albedo, normal, quality):
    """OIDN's RT filter on its CUDA device, the images copied to and from device buffers.
    Returns (image, settings)."""
    pyoidn = import_pyoidn()
    if not pyoidn.Device.is_cuda_available(0):
        raise DenoiseError("Open Image Denoise has no CUDA device here (pyoidn's CUDA backend found no GPU)")
    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CUDA)
    buffers = []
    try:
        device.commit()
        _oidn_check(device, 'CUDA device')
        flt = pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT)
        h, w = colour.shape[:2]
        out = np.empty_like(colour)
        images = [('color', colour), ('albedo', albedo), ('normal', normal), ('output', out)]
        for name, arr in images:
            if arr is None:
                continue
            buf = pyoidn.Buffer(device, arr.nbytes)
            buffers.append((name, buf, arr))
            if name != 'output':
                buf.write(0, arr.nbytes, arr)
            flt.set_image(name, buf, pyoidn.OIDN_FORMAT_FLOAT3, w, h)
        flt.set_bool('hdr', True)
        flt.set_quality({'high': pyoidn.OIDN_QUALITY_HIGH, 'balanced': pyoidn.OIDN_QUALITY_BALANCED,
                         'fast': pyoidn.OIDN_QUALITY_FAST}[quality])
        flt.commit()
        flt.execute()
        device.wait()
        _oidn_check(device, 'RT filter on CUDA')
        buffers[-1][1].read(0, out.nbytes, out)
        flt.release()
    finally:
        for _, buf, _ in buffers:
            buf.release()
        device.release()
    return out, {'denoiser': f'Intel Open Image Denoise {oidn_version(pyoidn)} (pyoidn)', 'device': 'cuda',
                 'filter': 'RT', 'hdr': 'true', 'clean_aux': 'false', 'quality': quality}


def first_line(e):
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _oidn_check(device, what):
    err = device.get_error()
    if err:
        raise DenoiseError(f"Open Image Denoise ({what}) failed: {err}")
