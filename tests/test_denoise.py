"""Denoising (``bdpt_jit.denoise``, ``bdpt-jit render --denoise``) and FLIP in the comparison
report: the denoised Cornell box is much closer to a converged reference than the noisy render,
in relative MSE and in FLIP, with its exposure kept; the feature pass records the surface seen
through glass, not the glass; the EXR holds the raw, denoised, albedo and normal layers with
the denoiser named in its header, and the PNG is the denoised image; the report's FLIP is
flip_evaluator's own value; a missing package or a variant the denoiser cannot serve is one
line, and the raw image is still written."""

import os
import subprocess
import sys

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

from bdpt_jit import cli
from bdpt_jit.denoise import DenoiseError, backends, denoise, denoise_with_settings, feature_images
from bdpt_jit.passes import RenderHooks

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORNELL = os.path.join(REPO, 'scenes', 'cornell-box.xml')
RES = 96                        # OIDN needs some pixels to work with: at 64x64 its gain is smaller
SPP = 16
EPS_REL = 0.1                   # relMSE's eps as benchmarks/compare_lib.py has it
VARIANT = ['--variant', 'llvm_ad_rgb']


def read_exr(path):
    f = OpenEXR.File(str(path), separate_channels=True)
    return {name: c.pixels for name, c in f.channels().items()}, f.header()


def stack(ch, prefix, names='RGB'):
    return np.stack([ch[prefix + c] for c in names], axis=-1).astype(np.float64)


def srgb8(x):
    """Clamp to [0, 1], sRGB transfer curve, 8 bits (docs/cli.md's PNG)."""
    x = np.clip(x, 0.0, 1.0)
    return np.round(255 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055))


def rel_mse(img, ref):
    eps = (EPS_REL * ref.mean()) ** 2
    return float((((img - ref) ** 2) / (ref ** 2 + eps)).mean())


# ----------------------------------------------------------------------------- Cornell box
@pytest.fixture(scope='module')
def cornell(tmp_path_factory):
    """bdpt-jit render --denoise of the Cornell box at 16 spp (in this process)."""
    out = tmp_path_factory.mktemp('denoise') / 'cornell.exr'
    rc = cli.main(['render', CORNELL, '-D', f'res={RES}', '--spp', str(SPP), '--denoise', '-q',
                   '-o', str(out), *VARIANT])
    assert rc == 0
    ch, header = read_exr(out)
    return out, ch, header


@pytest.fixture(scope='module')
def reference():
    """Mitsuba's path at 4 x 256 spp, and the variance of that mean from its batches.

    Statistics: the noisy 16-spp bdpt render has relMSE ~0.02 here (0.3 per sample); path's
    per-sample relMSE is ~0.9, so 1024 spp leave ~9e-4 in the reference, a fifth of the denoised
    image's ~4e-3 (the test checks a quarter from the batches' variance). The reference's error
    r is independent of both images' and adds to both measured errors: (a + r) / (b + r) > a / b
    for a < b, so it can only make the denoised image's ratio look worse, and the ratio test is
    conservative; 1024 spp keep it cheap (~4 s on 2 cores)."""
    scene = mi.load_file(CORNELL, res=str(RES), integrator='path')
    batches = np.stack([np.array(mi.render(scene, spp=256, seed=7000 + b), dtype=np.float64)[:, :, :3]
                        for b in range(4)])
    mean = batches.mean(axis=0)
    var_of_mean = batches.var(axis=0, ddof=1) / len(batches)
    return mean, var_of_mean


def flip_ldr(img, ref):
    """FLIP (LDR mode) of img against ref, both exposed so that ref's 98th percentile is white."""
    import flip_evaluator
    scale = 1.0 / np.quantile(ref.mean(axis=2), 0.98)
    ldr = lambda x: (srgb8(x * scale) / 255).astype(np.float32)  # noqa: E731
    return flip_evaluator.evaluate(ldr(ref), ldr(img), 'LDR')[1]


def test_denoised_cornell_box_beats_the_noisy_render(cornell, reference):
    """relMSE below a third of the noisy image's, FLIP below it, every pixel finite, the image
    mean within 2% of the reference's and of the noisy image's."""
    _, ch, _ = cornell
    ref, ref_var = reference
    raw, den = stack(ch, ''), stack(ch, 'denoised.')
    assert np.isfinite(raw).all() and np.isfinite(den).all() and (den >= 0).all()
    eps = (EPS_REL * ref.mean()) ** 2
    ref_rel = float((ref_var / (ref ** 2 + eps)).mean())
    rel_raw, rel_den = rel_mse(raw, ref), rel_mse(den, ref)
    assert ref_rel < 0.25 * rel_den, (ref_rel, rel_den)            # the reference is good enough to judge
    assert rel_den < rel_raw / 3, (rel_den, rel_raw)
    assert flip_ldr(den, ref) < flip_ldr(raw, ref)
    assert abs(den.mean() / ref.mean() - 1) < 0.02, (den.mean(), ref.mean())
    assert abs(den.mean() / raw.mean() - 1) < 0.02, (den.mean(), raw.mean())


def test_exr_layers_header_and_png(cornell):
    """Raw, denoised, albedo and normal layers; the header names the denoiser and its settings;
    the PNG is the denoised image's; the features are the box's (red left wall, white floor
    facing up)."""
    out, ch, header = cornell
    assert sorted(ch) == sorted(['R', 'G', 'B'] + [f'denoised.{c}' for c in 'RGB']
                                + [f'albedo.{c}' for c in 'RGB'] + [f'normal.{c}' for c in 'XYZ'])
    raw, den = stack(ch, ''), stack(ch, 'denoised.')
    assert np.abs(den - raw).mean() > 0.01 * raw.mean()             # not a copy of the raw image
    assert header['bdpt.denoise.denoiser'].startswith('Intel Open Image Denoise 2.')
    for key, value in (('device', 'cpu'), ('filter', 'RT'), ('hdr', 'true'), ('quality', 'high'),
                       ('features', 'albedo normal'), ('clean_aux', 'false'), ('feature_spp', str(SPP)),
                       ('normal_space', 'world')):
        assert header[f'bdpt.denoise.{key}'] == value, key
    png = np.array(mi.Bitmap(str(out)[:-4] + '.png'), dtype=np.float64)
    assert png.shape == (RES, RES, 3)
    assert np.abs(png - srgb8(den)).max() <= 1
    assert np.abs(png - srgb8(raw)).max() > 8                       # and not the raw image's
    albedo, normal = stack(ch, 'albedo.'), stack(ch, 'normal.', 'XYZ')
    left_wall, floor = (RES // 2, RES // 32), (RES - 6, RES // 2)   # (row, column)
    np.testing.assert_allclose(albedo[left_wall], [0.63, 0.065, 0.05], rtol=0.01)
    np.testing.assert_allclose(albedo[floor], [0.73, 0.73, 0.73], rtol=0.01)
    np.testing.assert_allclose(normal[floor], [0, 1, 0], atol=1e-3)
    np.testing.assert_allclose(normal[left_wall], [1, 0, 0], atol=1e-3)


def test_report_flip_is_flip_evaluators_own(cornell, reference):
    """benchmarks/compare_lib.flip_error (the report's FLIP column) is flip_evaluator's mean FLIP
    of the same LDR pair: both images times the stated exposure (the reference's 98th percentile
    to white), clamped, sRGB-encoded; over a region, the mean of flip_evaluator's error map there."""
    import flip_evaluator
    sys.path.insert(0, os.path.join(REPO, 'benchmarks'))
    import compare_lib as lib
    import compare_report as report
    _, ch, _ = cornell
    ref = reference[0]
    raw = stack(ch, '')
    whole = lib.Reference(ref, np.zeros_like(ref), np.ones(ref.shape[:2], bool), np.zeros(ref.shape[:2]), {})
    scale = 1.0 / np.quantile(ref.mean(axis=2), 0.98)
    assert lib.flip_exposure(whole) == pytest.approx(scale, rel=1e-12)

    def ldr(x):
        x = np.clip(x * scale, 0.0, 1.0)
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)
    emap, own, _ = flip_evaluator.evaluate(ldr(ref), ldr(raw), 'LDR', applyMagma=False)
    assert own > 0.01                                             # a noisy image: a real difference
    assert lib.flip_error(raw, whole) == pytest.approx(own, rel=1e-5)
    assert report.flip_cell({'flip': lib.flip_error(raw, whole)}) == report.fmt(own)
    half = np.zeros(ref.shape[:2], bool)
    half[:, :RES // 2] = True
    region = lib.Reference(ref, np.zeros_like(ref), half, np.zeros(ref.shape[:2]), {})
    scale = 1.0 / np.quantile(ref.mean(axis=2)[half], 0.98)
    emap, _, _ = flip_evaluator.evaluate(ldr(ref), ldr(raw), 'LDR', applyMagma=False)
    assert lib.flip_error(raw, region) == pytest.approx(float(emap[:, :, 0][half].mean()), rel=1e-5)


# ----------------------------------------------------------------------------- the feature pass
def glass_slab_scene():
    """A camera looking down at a diffuse floor through a tilted slab of smooth glass that fills
    the view, under a white sky (what a ray reflected off the glass would see)."""
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 30,
                   'to_world': mi.ScalarTransform4f().look_at(origin=[0, 4, 0], target=[0, 0, 0], up=[0, 0, 1]),
                   'film': {'type': 'hdrfilm', 'width': 16, 'height': 16, 'rfilter': {'type': 'box'}}},
        'floor': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(5),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.2, 0.5, 0.8]}}},
        'slab': {'type': 'cube',
                 'to_world': mi.ScalarTransform4f().translate([0, 1.5, 0]).rotate([0, 0, 1], 20).scale([2, 0.1, 2]),
                 'bsdf': {'type': 'dielectric', 'int_ior': 1.5}},
        'sky': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': 1.0}},
    })


def test_albedo_behind_glass_is_the_floor():
    """Every pixel sees the floor through the glass: its albedo (within 1%) and its normal, not
    the glass's (a dielectric has no diffuse reflectance; a walk that took the reflected rays
    would mix in the sky's 1; the slab's normal is tilted by 20 degrees)."""
    albedo, normal = feature_images(glass_slab_scene(), spp=4)
    assert albedo.shape == (16, 16, 3) and normal.shape == (16, 16, 3)
    np.testing.assert_allclose(albedo, np.broadcast_to([0.2, 0.5, 0.8], albedo.shape), rtol=0.01)
    np.testing.assert_allclose(normal, np.broadcast_to([0, 1, 0], normal.shape), atol=1e-3)


SPECTRAL_FEATURES = """
import sys
import mitsuba as mi
mi.set_variant('llvm_ad_spectral')
sys.path.insert(0, {tests!r})
from test_denoise import glass_slab_scene
from bdpt_jit.denoise import feature_images
albedo, normal = feature_images(glass_slab_scene(), spp=16)
print(*albedo.mean(axis=(0, 1)), *normal.mean(axis=(0, 1)))
"""


def test_spectral_albedo_is_the_srgb_reflectance():
    """In a spectral variant the floor's sRGB reflectance comes back as itself (it is converted
    under D65, the white of RGB emitters; converted alone, sRGB (0.2, 0.5, 0.8) would give
    (0.27, 0.47, 0.74)). The image mean, as each sample sees 4 wavelengths (noisy per pixel)."""
    r = subprocess.run([sys.executable, '-c', SPECTRAL_FEATURES.format(tests=os.path.dirname(__file__))],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr
    values = [float(v) for v in r.stdout.split()]
    np.testing.assert_allclose(values[:3], [0.2, 0.5, 0.8], rtol=0.01)
    np.testing.assert_allclose(values[3:], [0, 1, 0], atol=1e-3)


# ----------------------------------------------------------------------------- with the command's options
@pytest.mark.parametrize('budget', [['--spp', '8'], ['--time', '60', '--pass-spp', '1']], ids=['spp', 'time'])
def test_interrupted_render_is_denoised_and_strategy_layers_stay_raw(tmp_path, monkeypatch, budget):
    """Stopped after its first pass (as Ctrl-C or the budget stops it): the spp reached is
    denoised, the strategy layers still sum to the raw image."""
    monkeypatch.setattr(RenderHooks, 'stop', lambda self: True)
    out = tmp_path / 'cut.exr'
    rc = cli.main(['render', CORNELL, '-D', 'res=16', *budget, '--samples-per-pass', '256', '--max-depth', '5',
                   '--strategies', '--denoise', '-q', '-o', str(out), *VARIANT])
    assert rc == 130
    ch, header = read_exr(out)
    assert header['bdpt.interrupted'] == 'true' and header['bdpt.spp'] == '1'
    assert header['bdpt.denoise.feature_spp'] == '1'
    raw, den = stack(ch, ''), stack(ch, 'denoised.')
    total = sum(stack(ch, f'{n}.weighted.') for n in header['bdpt.layers'].split())
    np.testing.assert_allclose(total, raw, rtol=1e-4, atol=1e-5 * float(raw.max()))
    assert np.isfinite(den).all() and np.abs(den - raw).max() > 0


def run_cli(*args):
    return subprocess.run([sys.executable, '-m', 'bdpt_jit.cli', 'render', *args],
                          capture_output=True, text=True, timeout=120, cwd=REPO)


def test_monochrome_variant_denoises_one_channel(tmp_path):
    out = tmp_path / 'm.exr'
    r = run_cli(CORNELL, '-D', 'res=16', '--spp', '4', '--variant', 'llvm_ad_mono', '--denoise', '-q', '-o', str(out))
    assert r.returncode == 0, r.stderr
    ch, header = read_exr(out)
    assert sorted(ch) == ['Y', 'albedo.Y', 'denoised.Y', 'normal.X', 'normal.Y', 'normal.Z']
    assert np.isfinite(ch['denoised.Y']).all() and ch['denoised.Y'].mean() > 0
    # the red left wall's albedo as a monochrome variant sees it: its luminance
    np.testing.assert_allclose(ch['albedo.Y'][8, 1], 0.2126 * 0.63 + 0.7152 * 0.065 + 0.0722 * 0.05, rtol=0.01)


# ----------------------------------------------------------------------------- errors
def test_missing_package_is_one_line_and_the_raw_image_is_written(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, 'pyoidn', None)                # import pyoidn raises ImportError
    with pytest.raises(DenoiseError, match=r"pyoidn.*pip install -e '\.\[denoise\]'"):
        denoise(np.ones((4, 4, 3), np.float32))
    out = tmp_path / 'raw.exr'
    rc = cli.main(['render', CORNELL, '-D', 'res=16', '--spp', '2', '--denoise', '-q', '-o', str(out), *VARIANT])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('bdpt-jit: error: --denoise: ')
    assert "pip install -e '.[denoise]'" in err[0] and 'wrote the raw image' in err[0]
    ch, header = read_exr(out)
    assert sorted(ch) == ['B', 'G', 'R'] and 'pyoidn' in header['bdpt.denoise.error']
    png = np.array(mi.Bitmap(str(tmp_path / 'raw.png')), dtype=np.float64)
    assert np.abs(png - srgb8(stack(ch, ''))).max() <= 1


def test_unsupported_variant_says_what_is_supported(tmp_path):
    with pytest.raises(DenoiseError, match=r"needs a cuda_\* variant"):
        backends.choose('llvm_ad_rgb', 'optix')
    with pytest.raises(DenoiseError, match='polarized'):
        backends.choose('llvm_ad_rgb_polarized')
    assert backends.choose('llvm_ad_mono') == 'oidn-cpu' and backends.choose('cuda_ad_rgb') == 'optix'
    out = tmp_path / 's.exr'
    r = run_cli(CORNELL, '-D', 'res=8', '--spp', '1', '--variant', 'scalar_rgb', '--integrator', 'path',
                '--denoise', '-q', '-o', str(out))
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "not 'scalar_rgb'" in lines[0] and 'llvm_*' in lines[0], r.stderr
    assert 'Traceback' not in r.stderr
    ch, _ = read_exr(out)
    assert sorted(ch) == ['B', 'G', 'R'] and (tmp_path / 's.png').exists()


def test_bad_inputs_are_refused_and_bad_pixels_guarded():
    with pytest.raises(DenoiseError, match='needs an albedo'):
        denoise(np.ones((4, 4, 3), np.float32), normal=np.zeros((4, 4, 3), np.float32))
    with pytest.raises(DenoiseError, match='albedo image must be 4x4'):
        denoise(np.ones((4, 4, 3), np.float32), albedo=np.ones((5, 4, 3), np.float32))
    img = np.full((8, 8, 3), 0.5, np.float32)
    img[2, 3] = [np.nan, np.inf, -1.0]
    out, settings = denoise_with_settings(img)
    assert np.isfinite(out).all() and settings['replaced_pixels'] == '1' and settings['device'] == 'cpu'
    mono = denoise(img[:, :, 0])
    assert mono.shape == (8, 8) and np.isfinite(mono).all()
