"""The files the command writes: the multi-layer EXR and the PNG beside it, both written
atomically, and the check of the output path before anything is rendered."""

import os
import tempfile

from .errors import CLIError


def output_paths(scene_path, output):
    """(EXR path, PNG path) for ``-o`` (default: the scene's name in the working directory),
    refused if they cannot be written."""
    out = output or os.path.splitext(os.path.basename(scene_path))[0] + '.exr'
    return out, check_output(out)


def check_output(out):
    """Refuse an output path that cannot be written, before any rendering; returns the PNG's."""
    if not out.lower().endswith('.exr'):
        raise CLIError(f"output must be an .exr file (the PNG is written beside it): {out}")
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        raise CLIError(f"output folder does not exist: {folder}")
    png = os.path.splitext(out)[0] + '.png'
    for path in (out, png):
        if os.path.isdir(path):
            raise CLIError(f"output path is a folder: {path}")
    try:                                            # os.access says yes to root even on read-only mounts
        fd, probe = tempfile.mkstemp(prefix='.bdpt-jit-probe.', dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise CLIError(f"output folder is not writable: {folder} ({e.strerror})") from None
    return png


def atomic_write(path, write_fn):
    """Write through a temporary file in the same folder, then rename: an interrupted render
    never leaves a truncated file under the final name."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)                # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def film_channel_names(film):
    """The names of the film's own channels where it has a layout of its own (``specfilm``: its
    bands' names, as Mitsuba writes them); None for RGB and luminance films."""
    import mitsuba as mi
    if not film.flags() & mi.FilmFlags.Special:
        return None
    b = film.bitmap()
    return [b.struct_()[i].name for i in range(b.channel_count())]


def exr_channels(rgb, layers=None, aov_names=(), colour_names=None):
    """Channel dict for OpenEXR: the image as R, G, B (Y for a monochrome variant's one
    channel; ``colour_names`` for a film of its own channels), then its AOV channels under their
    names (``dd.T``, ...); each strategy layer as ``<name>.weighted.R/G/B`` and
    ``<name>.unweighted.R/G/B``."""
    import numpy as np
    ch = {}
    rgb = np.asarray(rgb, dtype=np.float32)
    n_colour = rgb.shape[2] - len(aov_names)
    names = colour_names or (['Y'] if n_colour == 1 else ['R', 'G', 'B'])
    for c, cname in enumerate(list(names) + list(aov_names)):
        ch[cname] = np.ascontiguousarray(rgb[:, :, c])
    for name, kinds in (layers or {}).items():
        for kind in ('weighted', 'unweighted'):
            a = np.asarray(kinds[kind], dtype=np.float32)
            for c, cname in enumerate('RGB'):
                ch[f'{name}.{kind}.{cname}'] = np.ascontiguousarray(a[:, :, c])
    return ch


def write_exr(path, rgb, header_extra, layers=None, aov_names=(), extra_channels=None, colour_names=None):
    """ZIP-compressed scanline EXR; ``header_extra`` values are written as strings;
    ``extra_channels``: more named channels (--denoise: ``denoised.R``, ``albedo.R``, ...)."""
    import OpenEXR
    header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}
    header.update({k: str(v) for k, v in header_extra.items()})
    channels = exr_channels(rgb, layers, aov_names, colour_names)
    channels.update(extra_channels or {})
    atomic_write(path, lambda tmp: OpenEXR.File(header, channels).write(tmp))


def write_png(path, rgb):
    """Tone mapping: clamp to [0, 1], sRGB transfer curve, 8 bits (a film of other than one or
    three channels, a specfilm's bands: their mean, in gray)."""
    import numpy as np
    import mitsuba as mi
    a = np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    if a.shape[2] not in (1, 3):
        a = a.mean(axis=2, keepdims=True)
    a = np.ascontiguousarray(a)
    fmt = mi.Bitmap.PixelFormat.Y if a.shape[2] == 1 else mi.Bitmap.PixelFormat.RGB
    png = mi.Bitmap(a, fmt).convert(fmt, mi.Struct.Type.UInt8, srgb_gamma=True)
    atomic_write(path, lambda tmp: png.write(tmp))
