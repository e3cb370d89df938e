"""Error against run time: `bdpt` (and its vertex-merging techniques `vcm` and `vm`) against Mitsuba's
`path` and `ptracer`, and against Mitsuba 0.6's `bdpt` and `path` where a built Mitsuba 0.6 is given (the measurement part of `benchmarks/compare.py`;
`compare_report.py` writes the report, `mitsuba06.py` builds and runs Mitsuba 0.6).

For each scene: a cached reference with its own remaining error, then every contestant over a range
of time budgets (renders timed after a warm-up, medians over repeats, errors averaged over
independent renders), an equal-sample point, ray counts, and the kernels compiled on the way.
Mitsuba 0.6's contestants render a converted copy of the scene, whose pixels differ from the Mitsuba 3
scene's by a few percent in places: their errors are measured against a reference of their own (a
long render of 0.6's `bdpt`), over the same pixels.
"""

import dataclasses
import hashlib
import json
import os
import re
import statistics
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

mi.set_variant('llvm_ad_rgb')
import bdpt_jit  # noqa: E402,F401  (registers the 'bdpt' integrator)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mitsuba06  # noqa: E402
import raycount  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SCENE_DIR = REPO / 'scenes'
REF_VERSION = 2                 # bump when the reference construction changes (invalidates the cache)
QUOTABLE = 0.1                  # a figure is quoted only where the reference's expected error is below this fraction of it
EPS_REL = 0.1                   # relMSE denominator: ref^2 + (EPS_REL * mean of the reference over the region)^2
FLIP_WHITE_QUANTILE = 0.98      # FLIP's LDR exposure: this quantile of the reference's luminance maps to white

# seeds: contestants count up from 1; references, their pilots and the ray counts use disjoint ranges
SEED_REF, SEED_PILOT, SEED_COUNT, SEED_REF06 = 1_000_000, 2_000_000, 3_000_000, 4_000_000
SEED_FEATURES = 5_000_000
FEATURE_SPP = 64                # the denoiser's feature pass (--denoise): one per scene, shared by the contestants


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    key: str
    file: str
    title: str
    tests: str
    reference: str          # 'mixed': path + ptracer over the whole image; 'light': ptracer, region = pixels it can render
    max_depth: int
    crop: tuple             # (x0, y0, x1, y1) as fractions of the image
    focus: bool = False     # a scene where bdpt is expected to beat path at equal time (stated in the summary)
    vcm_target: str = ''    # issue 15's equal-time target for `vcm`: 'caustic' (specular-diffuse-specular paths:
                            # relMSE <= 0.25 of path's), 'plain' (none: within 1.2x of bdpt's), '' (none stated)
    ref_scale: int = 1      # the reference's batches take this many times the mode's ref_spp (hard scenes)
    user: bool = False      # given with --scene-file (`file` is then an absolute path)

    @property
    def path(self):
        return SCENE_DIR / self.file        # an absolute `file` stays as it is


SCENES = [
    SceneSpec('fig6', 'paper-fig6.xml', "The paper's Figure 6 scene",
              'Cornell box with a glossy floor, a mirror, a textured diffuse and a glass sphere, an area light '
              '(the paper\'s Table 1)', 'mixed', 8, (0.45, 0.5, 0.95, 1.0)),
    SceneSpec('fig7', 'sun-room.xml', "The paper's Figure 7 scene",
              'Cornell-type room lit by a directional sun through a ceiling opening and a dim sky; textured, mirror '
              'and glass spheres (the paper\'s Table 2)', 'light', 6, (0.3, 0.45, 0.8, 0.95), ref_scale=4),
    SceneSpec('fig7-caustic', 'sun-room-caustic.xml', "The paper's Figure 7 scene, caustic detail",
              'close-up of the sun\'s caustic under the glass sphere of the Figure 7 scene (the paper\'s Table 3)',
              'light', 6, (0.3, 0.3, 0.9, 0.9), focus=True, ref_scale=12, vcm_target='caustic'),
    SceneSpec('veach-mis', 'veach-mis.xml', 'Veach-style MIS scene',
              'glossy plates of four roughnesses reflecting spherical lights of four sizes', 'mixed', 8,
              (0.0, 0.5, 0.5, 1.0), vcm_target='plain'),
    SceneSpec('indirect-room', 'indirect-room.xml', 'Indirectly lit room',
              'the visible room is lit only through a narrow slit from a light facing away in the next room',
              'mixed', 8, (0.0, 0.4, 0.5, 0.9), focus=True, vcm_target='plain'),
    SceneSpec('caustic', 'caustic.xml', 'Caustic from a small light',
              'a small spherical area light focused by a glass sphere onto a diffuse floor', 'mixed', 8,
              (0.05, 0.45, 0.55, 0.95), focus=True, ref_scale=3, vcm_target='caustic'),
    SceneSpec('torus-glass', 'torus-in-glass.xml', 'Torus in glass',
              'a diffuse torus embedded in a block of smooth acrylic (IOR 1.49) over a diffuse floor, lit by a small '
              'spherical area light: the torus is lit and seen only through the glass, and the floor is lit through '
              'it (light -> glass -> diffuse -> glass -> camera: no connection or light-tracing strategy reaches '
              'these paths; vertex merging does)', 'mixed', 10, (0.2, 0.25, 0.8, 0.85), ref_scale=8,
              vcm_target='caustic'),
    SceneSpec('cornell-box', 'cornell-box.xml', 'Cornell box',
              'the classic diffuse Cornell box under a rectangular area light: no specular surface, so no '
              'specular-diffuse-specular path (vertex merging adds only cost here)', 'mixed', 8,
              (0.25, 0.5, 0.75, 1.0), vcm_target='plain'),
]


def user_scene(text):
    """A scene given on the command line: KEY=PATH[,max_depth=N][,reference=mixed|light][,ref_scale=N]
    [,focus=1][,title=TEXT]. The scene file must take a `res` parameter or `resx` and `resy` (Mitsuba 3
    `$name` parameters); max_depth defaults to the file's own `max_depth` default. Raises ValueError."""
    key, sep, rest = text.partition('=')
    key = key.strip()
    if not sep or not key or not re.fullmatch(r'[A-Za-z0-9_.-]+', key):
        raise ValueError(f'{text!r}: expected KEY=PATH[,name=value...] with a key of letters, digits, -, _ or .')
    file, *opts = rest.split(',')
    path = Path(file).expanduser().resolve()
    if not path.is_file():
        raise ValueError(f'{key}: no scene file {path}')
    kw = {}
    for opt in opts:
        name, sep, value = opt.partition('=')
        name = name.strip()
        if not sep or name not in ('max_depth', 'reference', 'ref_scale', 'focus', 'title'):
            raise ValueError(f'{key}: unknown option {opt!r} (max_depth, reference, ref_scale, focus, title)')
        kw[name] = value.strip()
    names = scene_parameters(path)
    if 'res' not in names and not {'resx', 'resy'} <= names:
        raise ValueError(f'{key}: {path} takes neither a $res parameter nor $resx and $resy: the comparison '
                         f'cannot set its resolution')
    if 'max_depth' not in kw:
        m = re.search(r'<default\s+name="max_depth"\s+value="(-?\d+)"', path.read_text())
        if not m:
            raise ValueError(f'{key}: {path} has no max_depth default: add max_depth=N')
        kw['max_depth'] = m.group(1)
    if kw.get('reference', 'mixed') not in ('mixed', 'light'):
        raise ValueError(f"{key}: reference must be 'mixed' (path and ptracer) or 'light' (ptracer)")
    return SceneSpec(key, str(path), kw.get('title', f'{key} ({path.parent.name}/{path.name}, given with --scene-file)'),
                     f'a scene given with --scene-file ({path})', kw.get('reference', 'mixed'), int(kw['max_depth']),
                     (0.25, 0.25, 0.75, 0.75), focus=kw.get('focus', '0') not in ('0', 'false', 'no', ''),
                     ref_scale=int(kw.get('ref_scale', 1)), user=True)


def scene_parameters(path):
    """The `$name` parameters a Mitsuba 3 scene file uses (mi.load_file refuses others)."""
    names = set()
    for e in ET.parse(path).getroot().iter():         # comments left out
        for v in e.attrib.values():
            names.update(re.findall(r'\$([A-Za-z_][A-Za-z0-9_]*)', v))
    return names


@dataclasses.dataclass(frozen=True)
class Contestant:
    key: str
    label: str
    props: dict
    replica: bool = False   # rays counted by the replica in raycount.py (Mitsuba's integrators count none)
    renderer: str = 'mitsuba3'     # or 'mitsuba06': rendered by a built Mitsuba 0.6 (props['type'] is its integrator)
    progressive: bool = False      # a fresh integrator for every render: `vcm` and `vm` shrink their merging radius
                                   # over every pass of one integrator object, so a reused one would carry the radius
                                   # of earlier renders into the next (renders would not be independent draws)
    budgeted: bool = False         # at a budget, one render stopped once the budget has passed (``render_budgeted``),
                                   # as `bdpt-jit render --time` renders: technique auto, whose time is not linear
                                   # in its spp (each render decides afresh, and may choose otherwise)


CONTESTANTS = [
    Contestant('bdpt', 'bdpt power', {'type': 'bdpt', 'mis': 'power'}),
    Contestant('bdpt-balance', 'bdpt balance', {'type': 'bdpt', 'mis': 'balance'}),
    Contestant('bdpt-uniform', 'bdpt uniform', {'type': 'bdpt', 'mis': 'uniform'}),
    Contestant('bdpt-pt', 'bdpt pt', {'type': 'bdpt', 'technique': 'pt'}),
    Contestant('bdpt-lt', 'bdpt lt', {'type': 'bdpt', 'technique': 'lt'}),
    # vertex connection and merging (issue 15), radius and radius_alpha at the integrator's defaults
    Contestant('vcm', 'bdpt vcm', {'type': 'bdpt', 'technique': 'vcm'}, progressive=True),
    # Georgiev et al.'s set of merges (every non-specular camera vertex) instead of the default (behind a
    # specular vertex only)
    Contestant('vcm-all', 'bdpt vcm everywhere', {'type': 'bdpt', 'technique': 'vcm', 'merge_everywhere': True},
               progressive=True),
    Contestant('vm', 'bdpt vm', {'type': 'bdpt', 'technique': 'vm'}, progressive=True),
    # issue 22's efficiency-aware choice: each render chooses again (its pilot and trials in its time)
    Contestant('auto', 'bdpt auto', {'type': 'bdpt', 'technique': 'auto'}, progressive=True, budgeted=True),
    Contestant('path', 'Mitsuba path', {'type': 'path'}, replica=True),
    Contestant('ptracer', 'Mitsuba ptracer', {'type': 'ptracer'}, replica=True),
]
# Mitsuba 0.6's `bdpt` and `path`, as the seed paper's tables have them: added where a built Mitsuba 0.6
# is found (benchmarks/mitsuba06.py), each with the scene's max depth and rrDepth 5. They count no rays.
MITSUBA06_CONTESTANTS = [
    Contestant('mitsuba06-bdpt', 'mitsuba06 bdpt', {'type': 'bdpt'}, renderer='mitsuba06'),
    Contestant('mitsuba06-path', 'mitsuba06 path', {'type': 'path'}, renderer='mitsuba06'),
]
ALL_CONTESTANTS = CONTESTANTS + MITSUBA06_CONTESTANTS
BASELINE = 'path'
BUDGET_PASS_SPP = 4                 # a budgeted contestant's passes (Runner.render_budgeted): its hook's steps
REQUIRED = ('bdpt', BASELINE)       # the summary and the equal-sample point are relative to these


@dataclasses.dataclass
class Settings:
    mode: str
    res: int
    budgets: tuple          # wall-clock targets of the sweep (s); the last is the equal-time budget
    repeats: int            # timed renders per point (after one warm-up render)
    probe_spp: tuple        # first points of the sweep, which also calibrate each contestant's speed
    ref_spp: int            # spp of one reference batch
    ref_batches: int
    pilot_spp: int          # pilot batches: they choose the per-pixel weights of the combined reference
    pilot_batches: int
    count_spp: int          # spp of the ray-count renders (rays per sample, scaled to each table's spp)
    # Mitsuba 0.6's only where it is found; auto only where asked for (--contestants: each of its renders
    # compiles its candidates' kernels, a minute or more with a cold kernel cache)
    contestants: tuple = tuple(c.key for c in ALL_CONTESTANTS if c.key != 'auto')
    ref06_spp: int = 256    # Mitsuba 0.6's reference: ref06_batches renders of its bdpt at this spp
    ref06_batches: int = 8
    denoise: bool = False   # also denoise each contestant's equal-time image (--denoise)
    cluster: str = None     # references' batches on a Ray cluster (--cluster: bdpt_jit.cluster), else here


MODES = {
    'quick': Settings('quick', res=64, budgets=(0.2, 0.4, 0.8), repeats=3, probe_spp=(1, 8), ref_spp=1024,
                      ref_batches=16, pilot_spp=512, pilot_batches=4, count_spp=4),
    'full': Settings('full', res=96, budgets=(0.25, 0.5, 1.0, 2.0), repeats=4, probe_spp=(1, 8), ref_spp=1024,
                     ref_batches=16, pilot_spp=512, pilot_batches=4, count_spp=4),
    # Images of the size people render and budgets long enough for every error curve to reach its
    # -1 slope (error ~ 1/time). The references take the longest: per scene, 16 batches of 1024 spp
    # of Mitsuba 3's path and of its ptracer (times the scene's ref_scale) at 256x256, i.e. about
    # 2 x 16384 x 65536 = 2.1e9 samples (~15-30 min on 2 cores, hours for the caustic scenes with
    # their ref_scale), and 16 x 128 spp of Mitsuba 0.6's bdpt (~17 min for Veach's room on 2 cores).
    # Cached in benchmarks/cache/; --ref-spp, --ref-batches, --ref06-spp and --ref06-batches change
    # them (a figure is quoted only where the reference's error is below 0.1 of it: at 64 s, raise
    # --ref-spp for the scenes where bdpt wins by much).
    'realistic': Settings('realistic', res=256, budgets=(1.0, 4.0, 16.0, 64.0), repeats=1, probe_spp=(1, 4),
                          ref_spp=1024, ref_batches=16, pilot_spp=256, pilot_batches=4, count_spp=1,
                          contestants=('bdpt', 'vcm', 'vm', 'path', 'ptracer', 'mitsuba06-bdpt',
                                       'mitsuba06-path'),
                          ref06_spp=128, ref06_batches=16),
}


def contestants_of(keys):
    """Contestant objects for keys, in the order of ALL_CONTESTANTS."""
    return [c for c in ALL_CONTESTANTS if c.key in keys]


def unavailable(contestant):
    """Why this bdpt_jit cannot run a Mitsuba 3 contestant (its integrator refuses the parameters: `vcm` and
    `vm` before vertex merging landed), or None."""
    if contestant.renderer != 'mitsuba3':
        return None
    try:
        make_integrator(contestant, 8)
    except Exception as e:          # Mitsuba wraps the plugin's error, traceback and all: its last line says why
        lines = [line.strip() for line in str(e).splitlines() if line.strip()]
        return (lines[-1] if lines else type(e).__name__)[:300]
    return None


def contestant_settings(contestant):
    """The integrator parameters a contestant leaves at their defaults and the report names (the merging
    radius of `vcm` and `vm`), as {name: default}, from bdpt_jit's parameter table."""
    if contestant.props.get('type') != 'bdpt' or contestant.props.get('technique') not in ('vcm', 'vm'):
        return {}
    from bdpt_jit import params
    return {p.name: p.default for p in params.PARAMS
            if p.name in ('radius', 'radius_alpha') and p.name not in contestant.props}


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def to_np(img):
    a = np.array(img, dtype=np.float64)[:, :, :3]
    bad = ~np.isfinite(a)
    if bad.any():
        raise FloatingPointError(f'{bad.sum()} non-finite pixel values in a render')
    return a


def load_scene(spec, res):
    """The scene at res x res with Mitsuba's `path` as its integrator, passing only the parameters the
    file takes (`res`, or `resx` and `resy`; `max_depth`; `integrator`)."""
    scene = mi.load_file(str(spec.path), **scene_kwargs(spec, res))
    size = [int(v) for v in scene.sensors()[0].film().crop_size()]
    if size != [res, res]:
        raise ValueError(f'{spec.path}: its film is {size[0]}x{size[1]}, not {res}x{res}: the file must take '
                         f'a $res parameter, or $resx and $resy, for its width and height')
    return scene


def scene_kwargs(spec, res):
    """The parameters load_scene passes (those the file takes), as strings."""
    names = scene_parameters(spec.path)
    return {k: str(v) for k, v in (('res', res), ('resx', res), ('resy', res), ('max_depth', spec.max_depth),
                                   ('integrator', 'path')) if k in names}


def make_integrator(contestant, max_depth, **extra):
    return mi.load_dict(dict(contestant.props, max_depth=max_depth, **extra))


# ------------------------------------------------------------------------------------------ reference

def footprint_mask(scene, probes=8):
    """Pixels whose whole footprint (probes x probes sub-pixel rays, dilated by one pixel) sees only
    surfaces without a delta lobe, and no environment: where light tracing renders every path."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    g = probes
    iy, ix, sy, sx = np.meshgrid(np.arange(h), np.arange(w), np.arange(g), np.arange(g), indexing='ij')
    u = (ix + (sx + 0.5) / g) / w
    v = (iy + (sy + 0.5) / g) / h
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u.ravel(), v.ravel()), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bad = ~si.is_valid() | (mi.has_flag(si.bsdf(ray).flags(), mi.BSDFFlags.Delta) & si.is_valid())
    bad = np.array(bad, dtype=bool).reshape(h, w, g * g).any(axis=2)
    dil = bad.copy()
    dil[1:] |= bad[:-1]
    dil[:-1] |= bad[1:]
    dil[:, 1:] |= bad[:, :-1]
    dil[:, :-1] |= bad[:, 1:]
    return ~dil


def render_batches(scene, integrator, spp, batches, seed0, images=None):
    """Mean and variance of the mean per pixel from independent batches (running sums); ``images``:
    the same batches rendered elsewhere (--cluster), in seed order."""
    s1 = s2 = None
    for b in range(batches):
        a = to_np(images[b] if images is not None else mi.render(scene, integrator=integrator, spp=spp, seed=seed0 + b))
        s1 = a if s1 is None else s1 + a
        s2 = a * a if s2 is None else s2 + a * a
    mean = s1 / batches
    var = np.maximum(s2 / batches - mean * mean, 0.0) * batches / (batches - 1)
    return mean, var / batches


def box(x, r):
    """Mean over a (2r+1)^2 window (edges replicated)."""
    p = np.pad(x, r, mode='edge')
    k = 2 * r + 1
    return sum(p[i:i + x.shape[0], j:j + x.shape[1]] for i in range(k) for j in range(k)) / k ** 2


@dataclasses.dataclass
class Reference:
    mean: np.ndarray        # (H, W, 3)
    var: np.ndarray         # (H, W, 3): variance of `mean` (its expected squared error per pixel)
    region: np.ndarray      # (H, W) bool: pixels over which errors are measured
    weight_pt: np.ndarray   # (H, W): weight of ptracer in the combination (1 - weight: path)
    meta: dict

    @property
    def eps(self):
        return (EPS_REL * float(self.mean[self.region].mean())) ** 2

    def expected_errors(self):
        """The reference's own expected MSE and relMSE over the region: what it adds to every
        contestant's measured error (contestant and reference are independent)."""
        v = self.var[self.region]
        return float(v.mean()), float((v / (self.mean[self.region] ** 2 + self.eps)).mean())


def reference_key(spec, s):
    text = spec.path.read_bytes()
    parts = (REF_VERSION, mi.__version__, dr.__version__, spec.file, hashlib.sha1(text).hexdigest(),
             spec.reference, spec.max_depth, s.res, s.ref_spp, s.ref_batches, s.pilot_spp, s.pilot_batches,
             spec.ref_scale)
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:16]


def reference_batches(spec, scene, s, props, spp, batches, seed0):
    """render_batches of the integrator ``props``; with --cluster each batch is one task on the cluster
    (the same mi.render call, so the same images as here)."""
    images = None
    if s.cluster:
        from bdpt_jit import cluster
        seeds = [seed0 + b for b in range(batches)]
        try:
            images = cluster.render_seeded(str(spec.path), scene_kwargs(spec, s.res), props, spp, seeds,
                                           cluster.Options(address=s.cluster))
        except cluster.ClusterError as e:
            sys.exit(f'compare.py: --cluster: {e}')
    return render_batches(scene, mi.load_dict(props), spp, batches, seed0, images)


def render_reference_parts(spec, scene, s):
    """The renders a reference is combined from (cached as they are, combined on loading)."""
    parts = {}
    pt = {'type': 'ptracer', 'max_depth': spec.max_depth}
    spp = s.ref_spp * spec.ref_scale
    parts['m_pt'], parts['v_pt'] = reference_batches(spec, scene, s, pt, spp, s.ref_batches, SEED_REF)
    parts['mask'] = footprint_mask(scene)
    if spec.reference == 'mixed':
        pa = {'type': 'path', 'max_depth': spec.max_depth}
        parts['m_path'], parts['v_path'] = reference_batches(spec, scene, s, pa, spp, s.ref_batches, SEED_REF + 1000)
        _, parts['pv_pt'] = reference_batches(spec, scene, s, pt, s.pilot_spp, s.pilot_batches, SEED_PILOT)
        _, parts['pv_path'] = reference_batches(spec, scene, s, pa, s.pilot_spp, s.pilot_batches, SEED_PILOT + 1000)
    meta = {'kind': spec.reference, 'spp_ptracer': spp * s.ref_batches, 'batches': s.ref_batches,
            'spp_path': spp * s.ref_batches if spec.reference == 'mixed' else 0,
            'pilot': f'{s.pilot_batches} x {s.pilot_spp} spp each', 'res': s.res, 'max_depth': spec.max_depth}
    return parts, meta


def combine(spec, parts, meta):
    """The reference from its parts. 'light': ptracer alone, over the pixels it can render (path misses
    the sun's caustics). 'mixed': per pixel, ptracer and path weighted by the inverse of their variances
    as independent pilot renders estimate them (over a window of pixels, so that a rare firefly in a
    neighbour counts: the pilots are short), so that the weights do not correlate with the estimates
    they combine; path alone where ptracer cannot render every path (footprint sees a delta surface or
    nothing)."""
    mask, m_pt, v_pt = parts['mask'], parts['m_pt'], parts['v_pt']
    if spec.reference == 'light':
        region = mask
        w = mask.astype(np.float64)
        m_path = v_path = np.zeros_like(m_pt)
    else:
        region = np.ones_like(mask)
        m_path, v_path = parts['m_path'], parts['v_path']
        r = max(1, mask.shape[0] // 16)
        meta = dict(meta, weight_window=2 * r + 1)
        a, b = box(parts['pv_pt'].mean(axis=2), r), box(parts['pv_path'].mean(axis=2), r)
        w = np.where(a + b > 0, b / np.maximum(a + b, 1e-300), 0.5)
        w = np.where(mask, w, 0.0)
    w3 = w[:, :, None]
    mean = w3 * m_pt + (1 - w3) * m_path
    var = w3 ** 2 * v_pt + (1 - w3) ** 2 * v_path
    meta = dict(meta, region_fraction=float(region.mean()), ptracer_weight_mean=float(w[region].mean()))
    return Reference(mean, var, region, w, meta)


def reference(spec, scene, s, cache_dir):
    path = Path(cache_dir) / f'ref-{spec.key}-{reference_key(spec, s)}.npz'
    if path.exists():
        z = np.load(path)
        meta = dict(json.loads(str(z['meta'])), cached=True)
        return combine(spec, {k: z[k] for k in z.files if k != 'meta'}, meta)
    spp = s.ref_spp * spec.ref_scale
    log(f"{spec.key}: rendering the reference ({s.ref_batches} batches of {spp} spp of ptracer"
        + (" and of path, and pilots)" if spec.reference == 'mixed' else ')'))
    t0 = time.perf_counter()
    parts, meta = render_reference_parts(spec, scene, s)
    meta['render_s'] = time.perf_counter() - t0
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f'.{os.getpid()}.tmp.npz')
    np.savez_compressed(tmp, meta=json.dumps(meta), **parts)
    os.replace(tmp, path)
    return combine(spec, parts, dict(meta, cached=False))


def scene06_file(spec, s, cache_dir):
    """The Mitsuba 0.6 form of the scene at the mode's resolution (written under cache_dir/mitsuba06/)."""
    dst = Path(cache_dir) / 'mitsuba06' / f'{spec.key}-{s.res}.xml'
    mitsuba06.convert_file(spec.path, dst, {'res': s.res, 'resx': s.res, 'resy': s.res}, spec.max_depth)
    return dst


def reference06(spec, m06, scene06, s, cache_dir, region):
    """Mitsuba 0.6's own reference: `ref06_batches` renders of its bdpt at `ref06_spp`, each with its own
    seed (mitsuba06.SEED_EDIT), over the same pixels as the Mitsuba 3 reference. Its own bdpt renders
    every path of the converted scene (the sun's caustics included); the report sets it beside the
    Mitsuba 3 reference (`agreement`)."""
    text = Path(scene06).read_bytes()
    parts = (REF_VERSION, m06.identity, hashlib.sha1(text).hexdigest(), s.res, s.ref06_spp, s.ref06_batches)
    path = Path(cache_dir) / f'ref06-{spec.key}-{hashlib.sha1(repr(parts).encode()).hexdigest()[:16]}.npz'
    meta = {'kind': 'mitsuba06 bdpt', 'spp': s.ref06_spp * s.ref06_batches, 'batches': s.ref06_batches,
            'res': s.res, 'max_depth': spec.max_depth}
    if path.exists():
        z = np.load(path)
        meta = dict(json.loads(str(z['meta'])), cached=True)
        mean, var = z['mean'], z['var']
    else:
        log(f'{spec.key}: rendering the Mitsuba 0.6 reference ({s.ref06_batches} batches of {s.ref06_spp} spp '
            f'of its bdpt)')
        t0 = time.perf_counter()
        s1 = s2 = None
        for b in range(s.ref06_batches):
            _, _, img = m06.render(scene06, 'bdpt', s.ref06_spp, seed=SEED_REF06 + b)
            a = to_np(img)
            s1 = a if s1 is None else s1 + a
            s2 = a * a if s2 is None else s2 + a * a
        n = s.ref06_batches
        mean = s1 / n
        var = np.maximum(s2 / n - mean * mean, 0.0) * n / (n - 1) / n
        meta['render_s'] = time.perf_counter() - t0
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f'.{os.getpid()}.tmp.npz')
        np.savez_compressed(tmp, meta=json.dumps(meta), mean=mean, var=var)
        os.replace(tmp, path)
        meta = dict(meta, cached=False)
    if mean.shape[:2] != region.shape:
        raise ValueError(f'{scene06}: Mitsuba 0.6 rendered {mean.shape[1]}x{mean.shape[0]} pixels, '
                         f'not {region.shape[1]}x{region.shape[0]}')
    return Reference(mean, var, region, np.zeros(region.shape), meta)


def agreement(ref, ref06):
    """How far the Mitsuba 0.6 reference is from the Mitsuba 3 one (relMSE over the region, with the Mitsuba 3
    reference's eps), and what their own errors alone would give: far above it, the converted scene differs."""
    r = ref.region
    denom = ref.mean[r] ** 2 + ref.eps
    return {'rel': float((((ref06.mean - ref.mean) ** 2)[r] / denom).mean()),
            'expected_rel': float(((ref.var + ref06.var)[r] / denom).mean()),
            'mean_ratio': float(ref06.mean[r].mean() / max(ref.mean[r].mean(), 1e-300))}


# ------------------------------------------------------------------------------------------ contestants

def errors(img, ref):
    d2 = ((img - ref.mean) ** 2)[ref.region]
    return float(d2.mean()), float((d2 / (ref.mean[ref.region] ** 2 + ref.eps)).mean())


def flip_exposure(ref):
    """The exposure FLIP's LDR images are made with: the scale that maps the 98th percentile of the
    reference's luminance (mean of its channels) over the measured region to white, as the crops have it."""
    lum = ref.mean.mean(axis=2)[ref.region]
    white = float(np.quantile(lum, FLIP_WHITE_QUANTILE)) if lum.size else 0.0
    return 1.0 / (white if white > 0 else max(float(lum.max()) if lum.size else 0.0, 1e-8))


def ldr(img, scale):
    """An LDR image for FLIP: linear radiance times `scale`, clamped to [0, 1], sRGB-encoded (float32)."""
    x = np.clip(np.nan_to_num(img * scale, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def flip_error(img, ref):
    """Mean FLIP (NVIDIA's flip_evaluator, LDR mode, default 67 pixels per degree) of `img` against the
    reference, both tone-mapped by `ldr` with the reference's `flip_exposure`, averaged over the measured
    region (over the whole image: flip_evaluator's own mean)."""
    import flip_evaluator
    scale = flip_exposure(ref)
    emap, _, _ = flip_evaluator.evaluate(ldr(ref.mean, scale), ldr(img, scale), 'LDR', applyMagma=False)
    return float(np.asarray(emap, dtype=np.float64).reshape(ref.region.shape)[ref.region].mean())


def check_flip():
    """None, or why FLIP cannot be measured (flip_evaluator missing)."""
    try:
        import flip_evaluator  # noqa: F401
    except ImportError:
        return "FLIP needs the package flip-evaluator: pip install -e '.[bench]'"
    return None


def kernel_summary(history):
    ks = [k for k in history if k.get('type') == dr.KernelType.JIT]
    return {'kernels': len(ks),
            'compiled': sum(1 for k in ks if not k.get('cache_hit')),
            'from_disk': sum(1 for k in ks if k.get('cache_disk')),
            'codegen_s': sum(k.get('codegen_time', 0.0) for k in ks) / 1e3,
            'backend_s': sum(k.get('backend_time', 0.0) for k in ks) / 1e3}


class Runner:
    """Renders and times the contestants of one scene."""

    def __init__(self, spec, scene, ref, s, contestants, m06=None, scene06=None, ref06=None):
        self.spec, self.scene, self.ref, self.s = spec, scene, ref, s
        self.contestants = contestants
        self.by_key = {c.key: c for c in contestants}
        self.integrators = {c.key: make_integrator(c, spec.max_depth) for c in contestants
                            if c.renderer == 'mitsuba3' and not c.progressive}
        self.m06, self.scene06 = m06, scene06                 # Mitsuba 0.6 and the scene's 0.6 form
        self.refs = {c.key: ref06 if c.renderer == 'mitsuba06' else ref for c in contestants}
        self.seed = 0
        self.points = {c.key: [] for c in contestants}      # sweep points, in order
        self.compile = {c.key: [] for c in contestants}     # one record per warm-up render
        self.images = {}                                      # (key, spp) -> last image
        self.overhead06 = []                                  # 0.6: process start + scene loading (s), not timed
        self.choices = {}                                     # (key, spp) -> technique auto's decisions, each render

    def _render(self, key, spp, budget=None):
        """(seconds, image, spp rendered) of one render of ``key``: ``spp`` samples per pixel, or where
        the contestant is ``budgeted`` and a ``budget`` is given, as many as it renders in it."""
        self.seed += 1
        c = self.by_key[key]
        if c.budgeted and budget is not None:
            return self.render_budgeted(key, spp, budget)
        if c.renderer == 'mitsuba06':
            # its own render time (scene loading left out, as mi.load_file is for Mitsuba 3); the seed
            # makes each render independent (mitsuba06.SEED_EDIT)
            t, wall, img = self.m06.render(self.scene06, c.props['type'], spp, seed=self.seed)
            self.overhead06.append(wall - t)
            return t, to_np(img), spp
        # a progressive contestant gets a fresh integrator (its radius from the first pass), built untimed
        integ = make_integrator(c, self.spec.max_depth) if c.progressive else self.integrators[key]
        dr.sync_thread()
        t0 = time.perf_counter()
        img = mi.render(self.scene, integrator=integ, spp=spp, seed=self.seed)
        dr.eval(img)
        dr.sync_thread()
        t = time.perf_counter() - t0
        self.note_choice(key, spp, integ)
        return t, to_np(img), spp

    def note_choice(self, key, spp, integ):
        """technique auto's decisions in a render of ``key`` (its segments' choices joined by +)."""
        auto = (getattr(integ, 'last_render_info', None) or {}).get('auto')
        if auto:
            self.choices.setdefault((key, spp), []).append(
                ' + '.join(d['chosen'] for d in auto['decisions']) or auto['chosen'])

    def render_budgeted(self, key, spp, budget):
        """A budgeted contestant's render: 2^30 samples per pixel in passes of BUDGET_PASS_SPP,
        stopped by its should_stop hook once ``budget`` seconds have passed (the pass under way
        finishes, as the command's --time does), each pass waited for (Dr.Jit returns before a
        pass's kernels finish: without the wait every pass is queued before the hook sees the
        budget's end). Its spp: the samples it rendered over the pixels (a whole number where it
        stopped between passes; the mean of a point's renders is reported, rounded). Its choices
        are noted under ``spp`` (``stage``'s key for the budget) until ``stage`` moves them."""
        from bdpt_jit.passes import RenderHooks
        w, h = (int(v) for v in self.scene.sensors()[0].film().crop_size())
        integ = make_integrator(self.by_key[key], self.spec.max_depth, samples_per_pass=BUDGET_PASS_SPP * w * h)
        dr.sync_thread()
        t0 = time.perf_counter()
        integ.hooks = RenderHooks(on_pass=lambda done, total: dr.sync_thread(),
                                  should_stop=lambda: time.perf_counter() - t0 >= budget)
        img = mi.render(self.scene, integrator=integ, spp=1 << 30, seed=self.seed)
        dr.eval(img)
        dr.sync_thread()
        t = time.perf_counter() - t0
        self.note_choice(key, spp, integ)
        return t, to_np(img), integ.last_render_info['samples'] / (w * h)

    def stage(self, spp_of, budget=None):
        """One point per contestant: a warm-up render (its compile recorded from Dr.Jit's kernel
        history), then `repeats` timed renders, contestants interleaved so that a change in the
        machine's load spreads over all of them. Errors average every render (warm-up included:
        all are independent); the time is the median of the timed ones. A budgeted contestant
        renders ``budget`` seconds where one is given (``render_budgeted``): its spp is the mean of
        its renders', rounded."""
        out, spps = {}, {}
        # a budgeted point's renders are kept under the budget until their spp is known (``rekey``): under the
        # requested spp they could join an earlier point's of that spp
        spp_of = {key: ('budget', budget) if self.by_key[key].budgeted and budget is not None else spp
                  for key, spp in spp_of.items()}
        for key, spp in spp_of.items():
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history_clear()
            wall, img, done = self._render(key, spp, budget)
            hist = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            self.compile[key].append(dict(kernel_summary(hist), spp=done, warmup_s=wall))
            out[key] = {'spp': spp, 'times': [], 'errs': [self.measure(img, key)], 'warmup_s': wall}
            spps[key] = [done]
        for _ in range(self.s.repeats):
            for key, spp in spp_of.items():
                t, img, done = self._render(key, spp, budget)
                out[key]['times'].append(t)
                out[key]['errs'].append(self.measure(img, key))
                spps[key].append(done)
                self.images[(key, spp)] = img
        for key, p in out.items():
            if self.by_key[key].budgeted and budget is not None:
                self.rekey(key, p['spp'], int(round(float(np.mean(spps[key])))))
                p['spp'] = int(round(float(np.mean(spps[key]))))
            e = np.array(p.pop('errs'))
            n = len(e)
            p.update(time=statistics.median(p['times']), mse=float(e[:, 0].mean()), rel=float(e[:, 1].mean()),
                     mse_se=float(e[:, 0].std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0,
                     rel_se=float(e[:, 1].std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0, renders=n,
                     flip=float(e[:, 2].mean()), flip_se=float(e[:, 2].std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0)
        return out

    def rekey(self, key, old, new):
        """A budgeted point's image and choices, kept under its budget's key, moved to the spp it rendered."""
        for store in (self.images, self.choices):
            if (key, old) in store:
                store[(key, new)] = store.pop((key, old))

    def measure(self, img, key):
        """(MSE, relMSE, FLIP) of a contestant's render against its reference."""
        ref = self.refs[key]
        return (*errors(img, ref), flip_error(img, ref))

    @staticmethod
    def fit(points):
        """time = a + b spp through the point with the fewest samples (a: the per-render overhead) and
        the one with the most (the per-sample cost: timing noise matters least there)."""
        lo = min(points, key=lambda p: p['spp'])
        hi = max(points, key=lambda p: p['spp'])
        b = hi['time'] / hi['spp']                 # no overhead: an upper bound on the cost per sample
        if hi['spp'] > lo['spp'] and hi['time'] > lo['time']:
            b = max((hi['time'] - lo['time']) / (hi['spp'] - lo['spp']), 0.25 * b)
        a = min(max(lo['time'] - b * lo['spp'], 0.0), 0.9 * lo['time'])
        return a, max(b, 1e-9)

    def sweep(self):
        keys = [c.key for c in self.contestants]
        for spp in self.s.probe_spp:
            for key, p in self.stage({k: spp for k in keys}).items():
                self.points[key].append(dict(p, stage=f'probe {spp} spp'))
        for budget in self.s.budgets:
            spp_of = {}
            for key in keys:
                a, b = self.fit(self.points[key])
                spp_of[key] = max(int(round((budget - a) / b)), 1)
            for key, p in self.stage(spp_of, budget).items():
                self.points[key].append(dict(p, stage=f'budget {budget:g} s'))
            log(f'{self.spec.key}: budget {budget:g} s: ' + ', '.join(
                f"{k} {self.points[k][-1]['spp']} spp {self.points[k][-1]['time']:.2f} s" for k in keys))
        # the equal-time point: once more, with a refined fit, for whoever missed the budget by over 20%
        budget = self.s.budgets[-1]
        spp_of = {}
        for key in keys:
            if abs(self.points[key][-1]['time'] / budget - 1) > 0.2 and not self.by_key[key].budgeted:
                a, b = self.fit(self.points[key])
                spp = max(int(round((budget - a) / b)), 1)
                if spp != self.points[key][-1]['spp']:
                    spp_of[key] = spp
        if spp_of:
            for key, p in self.stage(spp_of).items():
                self.points[key].append(dict(p, stage=f'budget {budget:g} s, again'))
            log(f'{self.spec.key}: budget {budget:g} s again: ' + ', '.join(
                f"{k} {self.points[k][-1]['spp']} spp {self.points[k][-1]['time']:.2f} s" for k in spp_of))

    def equal_time(self):
        """Each contestant's point closest to the last budget (in log time)."""
        budget = self.s.budgets[-1]
        return {k: min(pts, key=lambda p: abs(np.log(p['time'] / budget))) for k, pts in self.points.items()}

    def equal_samples(self):
        """Every contestant at the spp `bdpt` (power) used at the equal-time budget."""
        spp = self.equal_time()['bdpt']['spp'] if 'bdpt' in self.points else self.s.probe_spp[-1]
        done, todo = {}, {}
        for key, pts in self.points.items():
            match = [p for p in pts if p['spp'] == spp]
            if match:
                done[key] = match[-1]
            else:
                todo[key] = spp
        if todo:
            done.update(self.stage(todo))
        return spp, done

    def count_rays(self):
        """Rays per sample of every contestant: bdpt's own statistics, the replica for Mitsuba's."""
        out = {}
        w, h = (int(v) for v in self.scene.sensors()[0].film().crop_size())
        spp = self.s.count_spp
        for i, c in enumerate(self.contestants):
            seed = SEED_COUNT + i
            if c.renderer == 'mitsuba06':
                out[c.key] = None           # Mitsuba 0.6 counts no rays, and no replica replays it
                continue
            if c.replica:
                r = raycount.count(c.key, self.scene, self.spec.max_depth, spp, seed=seed)
            else:
                integ = make_integrator(c, self.spec.max_depth, statistics=True)
                mi.render(self.scene, integrator=integ, spp=spp, seed=seed)
                r = dict((getattr(integ, 'last_render_info', None) or {}).get('rays') or {})
                if 'rays' not in r:             # a technique that counts no rays
                    log(f'{self.spec.key}: {c.key} counted no rays (statistics=true gave none)')
                    out[c.key] = None
                    continue
            n = w * h * spp
            out[c.key] = {'rays_per_sample': r['rays'] / n, 'zero_per_sample': r['zero_contribution_rays'] / n,
                          'detail_per_sample': {k: v / n for k, v in r.items() if k not in ('rays', 'samples')},
                          'counted_spp': spp, 'source': 'replica (raycount.py)' if c.replica else 'bdpt statistics'}
        return out


def denoised_errors(scene, runner, et):
    """--denoise: each contestant's equal-time image (its last timed render) denoised by bdpt_jit.denoise (Open
    Image Denoise on the CPU) with the albedo and normal of one feature pass of the scene, shared by all, and
    measured like the noisy image, which is measured again alone beside it. The denoiser's time is not in
    the budget (it is the same for every contestant and is reported)."""
    from bdpt_jit.denoise import denoise_with_settings, feature_images
    t0 = time.perf_counter()
    albedo, normal = feature_images(scene, spp=FEATURE_SPP, seed=SEED_FEATURES)
    feature_s = time.perf_counter() - t0
    points, settings = {}, {}
    for key, p in et.items():
        img = runner.images[(key, p['spp'])]
        t = time.perf_counter()
        den, settings = denoise_with_settings(img.astype(np.float32), albedo, normal)
        denoise_s = time.perf_counter() - t
        noisy, clean = runner.measure(img, key), runner.measure(den.astype(np.float64), key)
        points[key] = {'spp': p['spp'], 'time': p['time'], 'denoise_s': denoise_s,
                       'noisy': dict(zip(('mse', 'rel', 'flip'), noisy)),
                       'denoised': dict(zip(('mse', 'rel', 'flip'), clean))}
    return {'feature_spp': FEATURE_SPP, 'feature_s': feature_s, 'settings': settings, 'points': points}


def run_scene(spec, s, contestants, cache_dir, m06=None):
    """Measures one scene. `m06`: a mitsuba06.Mitsuba06, needed where `contestants` hold Mitsuba 0.6's."""
    t0 = time.perf_counter()
    scene = load_scene(spec, s.res)
    ref = reference(spec, scene, s, cache_dir)
    ref_mse, ref_rel = ref.expected_errors()
    how = 'cached' if ref.meta['cached'] else f"rendered in {ref.meta['render_s']:.0f} s"
    log(f'{spec.key}: reference {how}, its expected relMSE {ref_rel:.3g}')
    ref06 = scene06 = None
    ref06_info = None
    if any(c.renderer == 'mitsuba06' for c in contestants):
        if m06 is None:
            raise ValueError('Mitsuba 0.6 contestants without a Mitsuba 0.6 binary')
        scene06 = scene06_file(spec, s, cache_dir)
        ref06 = reference06(spec, m06, scene06, s, cache_dir, ref.region)
        mse06, rel06 = ref06.expected_errors()
        ref06_info = dict(ref06.meta, expected_mse=mse06, expected_rel=rel06, eps=ref06.eps,
                          agreement=agreement(ref, ref06), scene06=str(scene06))
        how = 'cached' if ref06.meta['cached'] else f"rendered in {ref06.meta['render_s']:.0f} s"
        log(f'{spec.key}: Mitsuba 0.6 reference {how}, its expected relMSE {rel06:.3g}; against the Mitsuba 3 '
            f"reference: relMSE {ref06_info['agreement']['rel']:.3g} "
            f"(their own errors: {ref06_info['agreement']['expected_rel']:.3g})")
    runner = Runner(spec, scene, ref, s, contestants, m06, scene06, ref06)
    runner.sweep()
    es_spp, es = runner.equal_samples()
    rays = runner.count_rays()
    et = runner.equal_time()
    crops = {'reference': ref.mean}
    for key, p in et.items():
        crops[key] = runner.images[(key, p['spp'])]
    result = {
        'spec': dataclasses.asdict(spec),
        'reference': dict(ref.meta, expected_mse=ref_mse, expected_rel=ref_rel, eps=ref.eps,
                          flip_exposure=flip_exposure(ref)),
        'reference06': ref06_info,          # Mitsuba 0.6's contestants are measured against this one
        'reference_of': {c.key: 'reference06' if c.renderer == 'mitsuba06' else 'reference' for c in contestants},
        'overhead06_s': statistics.median(runner.overhead06) if runner.overhead06 else None,
        'sweep': runner.points,
        'equal_time': {'budget_s': s.budgets[-1], 'points': et},
        'equal_samples': {'spp': es_spp, 'points': es},
        'rays': rays,
        'compile': runner.compile,
        # technique auto: per equal-time and sweep point, what each render chose (segments joined by ' + ')
        'auto_choices': [{'key': k, 'spp': spp, 'chose': v} for (k, spp), v in runner.choices.items()],
        'denoised': denoised_errors(scene, runner, et) if s.denoise else None,
        'seconds': time.perf_counter() - t0,
    }
    images = {'crops': crops, 'region': ref.region}
    return result, images


def machine_info():
    cpu = 'unknown CPU'
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    mem = None
    try:
        with open('/proc/meminfo') as f:
            for line in f:
                if line.startswith('MemTotal'):
                    mem = int(line.split()[1]) / 2 ** 20
    except OSError:
        pass
    import platform
    import subprocess
    try:
        commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=REPO, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = bool(subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no'], cwd=REPO,
                                    capture_output=True, text=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        commit, dirty = 'unknown', False
    return {'cpu': cpu, 'cores': os.cpu_count(), 'memory_gib': mem, 'os': platform.platform(),
            'python': platform.python_version(), 'mitsuba': mi.__version__, 'drjit': dr.__version__,
            'numpy': np.__version__, 'variant': mi.variant(), 'commit': commit, 'dirty': dirty,
            'load_average': os.getloadavg() if hasattr(os, 'getloadavg') else None}
