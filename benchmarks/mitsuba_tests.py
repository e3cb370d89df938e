"""bdpt on Mitsuba 3's own render-test scenes (the ``tests/scenes`` of mitsuba-data, public:
github.com/mitsuba-renderer/mitsuba-data), each against the reference image and variance that
Mitsuba's test suite compares its integrators with (32000 spp, scalar variants).

    python benchmarks/mitsuba_tests.py --data /path/to/mitsuba-data [--spp 32] [--batches 8] [--only homo_]

Each scene ``<name>_<integrator>.xml`` is loaded as Mitsuba's test loads it (its integrator:
path, direct, volpath, volpathmis, ptracer) and rendered by bdpt (technique ``--technique``)
at the scene's max_depth (``direct``: 2), ``--batches`` renders of ``--spp`` with seeds of their
own. Printed per scene: the seconds, whether every pixel is finite, the image mean over the
reference's, and the share of pixels and of 4x4 blocks whose z score exceeds 5 and 4: z = (mean -
ref) / se, se^2 the batches' variance of the mean, at least Mitsuba's own floor (the reference's
per-sample variance, at least 1e-4, over the samples rendered: its test_renders.py's z test), plus
the reference's variance over its 32000 samples. A scene bdpt refuses prints its one-line reason.
Not a test (the data is not in this repository, and the machine has no network in CI): the
figures are in docs/mitsuba-tests.md."""

import argparse
import glob
import os
import re
import sys
import time

import mitsuba as mi
import numpy as np

REF_SPP = 32000          # the references' samples per pixel (mitsuba-data's test_renders.py)


def texts(path):
    """The scene file's text and those of the files it includes."""
    out = [open(path).read()]
    for inc in re.findall(r'<include\s+filename="([^"]+)"', out[0]):
        p = os.path.join(os.path.dirname(path), inc)
        if os.path.exists(p):
            out += texts(p)
    return out


def max_depth(path, integrator):
    """The scene's max_depth (a default resolved; ``direct``: 2, as it renders; none: -1)."""
    if integrator == 'direct':
        return 2
    text = '\n'.join(texts(path))
    m = re.search(r'name="max_depth"\s+value="([^"]+)"', text)
    if not m:
        return -1
    value = m.group(1)
    if value.startswith('$'):
        value = re.search(r'<default\s+name="%s"\s+value="([^"]+)"' % value[1:], text).group(1)
    return int(value)


def reference(path, stem):
    """The reference image and per-sample variance (H x W x C float64), or None."""
    colour = 'rgb' if 'rgb' in mi.variant() else ('mono' if 'mono' in mi.variant() else 'spectral')
    ref = os.path.join(os.path.dirname(path), 'refs', f'{stem}_ref_{colour}.exr')
    if not os.path.exists(ref):
        return None
    out = [np.array(mi.Bitmap(f), dtype=np.float64) for f in (ref, ref.replace('.exr', '_var.exr'))]
    out[1] = np.maximum(out[1], 0.0)        # (a second moment less the squared mean: can round below 0)
    return [a[..., None] if a.ndim == 2 else a for a in out]


def luminance(rgb):
    """Y of linear sRGB (Rec. 709 weights), keeping a channel axis of one."""
    return (rgb @ np.array([0.2126, 0.7152, 0.0722]))[..., None]


def blocks(a, b=4):
    """4x4 block means of the images ``a`` (... x H x W x C)."""
    h, w = a.shape[-3] // b * b, a.shape[-2] // b * b
    return a[..., :h, :w, :].reshape(*a.shape[:-3], h // b, b, w // b, b, a.shape[-1]).mean((-4, -2))


def z_scores(images, ref, var, spp):
    """(pixels' z, blocks' z) of the batches ``images`` against ``ref`` (module docstring)."""
    k = len(images)
    floor = np.maximum(var, 1e-4) / (k * spp)
    se2 = np.maximum(images.var(0, ddof=1) / k, floor) + var / REF_SPP
    z = (images.mean(0) - ref) / np.sqrt(se2 + 1e-30)
    bi = blocks(images)
    bse2 = np.maximum(bi.var(0, ddof=1) / k, blocks(floor[None])[0] / 16) + blocks(var[None])[0] / (16 * REF_SPP)
    return z, (bi.mean(0) - blocks(ref[None])[0]) / np.sqrt(bse2 + 1e-30)


def run(path, args):
    """One scene's line."""
    stem, integrator = os.path.splitext(os.path.basename(path))[0].rsplit('_', 1)
    refs = reference(path, stem)
    if refs is None:
        return f'{stem}: no reference'
    depth = max_depth(path, integrator)
    t0 = time.time()
    try:
        scene = mi.load_file(path, integrator=integrator)
        it = mi.load_dict({'type': 'bdpt', 'technique': args.technique, 'max_depth': depth})
        images = np.stack([np.array(mi.render(scene, integrator=it, spp=args.spp, seed=k), dtype=np.float64)
                           for k in range(args.batches)])
    except Exception as e:          # (mi.render chains the plugin's own error)
        cause = e.__cause__ or e
        return f'{stem} [{integrator}, max_depth {depth}]: {type(cause).__name__}: {str(cause).splitlines()[0][:300]}'
    ref, var = refs
    if images.shape[-1] == 1 and ref.shape[-1] == 3:    # mono: the references are RGB, compared by luminance
        ref, var = luminance(ref), luminance(np.sqrt(var)) ** 2     # (var: the bound with full correlation)
    images = images[..., :ref.shape[-1]]
    z, bz = z_scores(images, ref, var, args.spp)
    return (f'{stem} [{integrator}, max_depth {depth}] {time.time() - t0:.1f} s, finite {np.isfinite(images).all()}, '
            f'mean / ref {images.mean() / max(ref.mean(), 1e-12):.4f}, pixels |z| > 5 {np.mean(np.abs(z) > 5):.4f}, '
            f'blocks |z| > 4 {np.mean(np.abs(bz) > 4):.3f} (max {np.abs(bz).max():.1f})')


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--data', required=True, help='a checkout of mitsuba-data (its tests/scenes)')
    ap.add_argument('--variant', default='llvm_ad_rgb')
    ap.add_argument('--technique', default='bdpt')
    ap.add_argument('--spp', type=int, default=32)
    ap.add_argument('--batches', type=int, default=8)
    ap.add_argument('--only', default=None, help='scenes whose file name holds this')
    args = ap.parse_args()
    scenes = sorted(glob.glob(os.path.join(args.data, 'tests', 'scenes', '*', '*_*.xml')))
    if not scenes:
        sys.exit(f'no scenes under {os.path.join(args.data, "tests", "scenes")}: --data must be a mitsuba-data checkout')
    mi.set_variant(args.variant)
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import bdpt_jit  # noqa: F401  (registers the plugin)
    for path in scenes:
        if args.only is None or args.only in os.path.basename(path):
            print(run(path, args), flush=True)


if __name__ == '__main__':
    main()
