"""Error against run time: `bdpt` against Mitsuba's `path` and `ptracer` (the measurement part of
`benchmarks/compare.py`; `compare_report.py` writes the report).

For each scene: a cached reference with its own remaining error, then every contestant over a range
of time budgets (renders timed after a warm-up, medians over repeats, errors averaged over
independent renders), an equal-sample point, ray counts, and the kernels compiled on the way.
"""

import dataclasses
import hashlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

mi.set_variant('llvm_ad_rgb')
import bdpt_jit  # noqa: E402,F401  (registers the 'bdpt' integrator)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import raycount  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SCENE_DIR = REPO / 'scenes'
REF_VERSION = 2                 # bump when the reference construction changes (invalidates the cache)
QUOTABLE = 0.1                  # a figure is quoted only where the reference's expected error is below this fraction of it
EPS_REL = 0.1                   # relMSE denominator: ref^2 + (EPS_REL * mean of the reference over the region)^2

# seeds: contestants count up from 1; references, their pilots and the ray counts use disjoint ranges
SEED_REF, SEED_PILOT, SEED_COUNT = 1_000_000, 2_000_000, 3_000_000


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
    ref_scale: int = 1      # the reference's batches take this many times the mode's ref_spp (hard scenes)


SCENES = [
    SceneSpec('fig6', 'paper-fig6.xml', "The paper's Figure 6 scene",
              'Cornell box with a glossy floor, a mirror, a textured diffuse and a glass sphere, an area light '
              '(the paper\'s Table 1)', 'mixed', 8, (0.45, 0.5, 0.95, 1.0)),
    SceneSpec('fig7', 'sun-room.xml', "The paper's Figure 7 scene",
              'Cornell-type room lit by a directional sun through a ceiling opening and a dim sky; textured, mirror '
              'and glass spheres (the paper\'s Table 2)', 'light', 6, (0.3, 0.45, 0.8, 0.95), ref_scale=4),
    SceneSpec('fig7-caustic', 'sun-room-caustic.xml', "The paper's Figure 7 scene, caustic detail",
              'close-up of the sun\'s caustic under the glass sphere of the Figure 7 scene (the paper\'s Table 3)',
              'light', 6, (0.3, 0.3, 0.9, 0.9), focus=True, ref_scale=12),
    SceneSpec('veach-mis', 'veach-mis.xml', 'Veach-style MIS scene',
              'glossy plates of four roughnesses reflecting spherical lights of four sizes', 'mixed', 8,
              (0.0, 0.5, 0.5, 1.0)),
    SceneSpec('indirect-room', 'indirect-room.xml', 'Indirectly lit room',
              'the visible room is lit only through a narrow slit from a light facing away in the next room',
              'mixed', 8, (0.0, 0.4, 0.5, 0.9), focus=True),
    SceneSpec('caustic', 'caustic.xml', 'Caustic from a small light',
              'a small spherical area light focused by a glass sphere onto a diffuse floor', 'mixed', 8,
              (0.05, 0.45, 0.55, 0.95), focus=True, ref_scale=3),
]


@dataclasses.dataclass(frozen=True)
class Contestant:
    key: str
    label: str
    props: dict
    replica: bool = False   # rays counted by the replica in raycount.py (Mitsuba's integrators count none)


CONTESTANTS = [
    Contestant('bdpt', 'bdpt power', {'type': 'bdpt', 'mis': 'power'}),
    Contestant('bdpt-balance', 'bdpt balance', {'type': 'bdpt', 'mis': 'balance'}),
    Contestant('bdpt-uniform', 'bdpt uniform', {'type': 'bdpt', 'mis': 'uniform'}),
    Contestant('bdpt-pt', 'bdpt pt', {'type': 'bdpt', 'technique': 'pt'}),
    Contestant('bdpt-lt', 'bdpt lt', {'type': 'bdpt', 'technique': 'lt'}),
    Contestant('path', 'Mitsuba path', {'type': 'path'}, replica=True),
    Contestant('ptracer', 'Mitsuba ptracer', {'type': 'ptracer'}, replica=True),
]
BASELINE = 'path'


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


MODES = {
    'quick': Settings('quick', res=64, budgets=(0.2, 0.4, 0.8), repeats=3, probe_spp=(1, 8), ref_spp=1024,
                      ref_batches=16, pilot_spp=512, pilot_batches=4, count_spp=4),
    'full': Settings('full', res=96, budgets=(0.25, 0.5, 1.0, 2.0), repeats=4, probe_spp=(1, 8), ref_spp=1024,
                     ref_batches=16, pilot_spp=512, pilot_batches=4, count_spp=4),
}


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def to_np(img):
    a = np.array(img, dtype=np.float64)[:, :, :3]
    bad = ~np.isfinite(a)
    if bad.any():
        raise FloatingPointError(f'{bad.sum()} non-finite pixel values in a render')
    return a


def load_scene(spec, res):
    return mi.load_file(str(SCENE_DIR / spec.file), res=res, max_depth=spec.max_depth, integrator='path')


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


def render_batches(scene, integrator, spp, batches, seed0):
    """Mean and variance of the mean per pixel from independent batches (running sums)."""
    s1 = s2 = None
    for b in range(batches):
        a = to_np(mi.render(scene, integrator=integrator, spp=spp, seed=seed0 + b))
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
    text = (SCENE_DIR / spec.file).read_bytes()
    parts = (REF_VERSION, mi.__version__, dr.__version__, spec.file, hashlib.sha1(text).hexdigest(),
             spec.reference, spec.max_depth, s.res, s.ref_spp, s.ref_batches, s.pilot_spp, s.pilot_batches,
             spec.ref_scale)
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:16]


def render_reference_parts(spec, scene, s):
    """The renders a reference is combined from (cached as they are, combined on loading)."""
    parts = {}
    pt = mi.load_dict({'type': 'ptracer', 'max_depth': spec.max_depth})
    spp = s.ref_spp * spec.ref_scale
    parts['m_pt'], parts['v_pt'] = render_batches(scene, pt, spp, s.ref_batches, SEED_REF)
    parts['mask'] = footprint_mask(scene)
    if spec.reference == 'mixed':
        pa = mi.load_dict({'type': 'path', 'max_depth': spec.max_depth})
        parts['m_path'], parts['v_path'] = render_batches(scene, pa, spp, s.ref_batches, SEED_REF + 1000)
        _, parts['pv_pt'] = render_batches(scene, pt, s.pilot_spp, s.pilot_batches, SEED_PILOT)
        _, parts['pv_path'] = render_batches(scene, pa, s.pilot_spp, s.pilot_batches, SEED_PILOT + 1000)
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


# ------------------------------------------------------------------------------------------ contestants

def errors(img, ref):
    d2 = ((img - ref.mean) ** 2)[ref.region]
    return float(d2.mean()), float((d2 / (ref.mean[ref.region] ** 2 + ref.eps)).mean())


def kernel_summary(history):
    ks = [k for k in history if k.get('type') == dr.KernelType.JIT]
    return {'kernels': len(ks),
            'compiled': sum(1 for k in ks if not k.get('cache_hit')),
            'from_disk': sum(1 for k in ks if k.get('cache_disk')),
            'codegen_s': sum(k.get('codegen_time', 0.0) for k in ks) / 1e3,
            'backend_s': sum(k.get('backend_time', 0.0) for k in ks) / 1e3}


class Runner:
    """Renders and times the contestants of one scene."""

    def __init__(self, spec, scene, ref, s, contestants):
        self.spec, self.scene, self.ref, self.s = spec, scene, ref, s
        self.contestants = contestants
        self.integrators = {c.key: make_integrator(c, spec.max_depth) for c in contestants}
        self.seed = 0
        self.points = {c.key: [] for c in contestants}      # sweep points, in order
        self.compile = {c.key: [] for c in contestants}     # one record per warm-up render
        self.images = {}                                      # (key, spp) -> last image

    def _render(self, key, spp):
        self.seed += 1
        dr.sync_thread()
        t0 = time.perf_counter()
        img = mi.render(self.scene, integrator=self.integrators[key], spp=spp, seed=self.seed)
        dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t0, to_np(img)

    def stage(self, spp_of):
        """One point per contestant: a warm-up render (its compile recorded from Dr.Jit's kernel
        history), then `repeats` timed renders, contestants interleaved so that a change in the
        machine's load spreads over all of them. Errors average every render (warm-up included:
        all are independent); the time is the median of the timed ones."""
        out = {}
        for key, spp in spp_of.items():
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history_clear()
            wall, img = self._render(key, spp)
            hist = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            self.compile[key].append(dict(kernel_summary(hist), spp=spp, warmup_s=wall))
            out[key] = {'spp': spp, 'times': [], 'errs': [errors(img, self.ref)], 'warmup_s': wall}
        for _ in range(self.s.repeats):
            for key, spp in spp_of.items():
                t, img = self._render(key, spp)
                out[key]['times'].append(t)
                out[key]['errs'].append(errors(img, self.ref))
                self.images[(key, spp)] = img
        for key, p in out.items():
            e = np.array(p.pop('errs'))
            n = len(e)
            p.update(time=statistics.median(p['times']), mse=float(e[:, 0].mean()), rel=float(e[:, 1].mean()),
                     mse_se=float(e[:, 0].std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0,
                     rel_se=float(e[:, 1].std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0, renders=n)
        return out

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
            for key, p in self.stage(spp_of).items():
                self.points[key].append(dict(p, stage=f'budget {budget:g} s'))
            log(f'{self.spec.key}: budget {budget:g} s: ' + ', '.join(
                f"{k} {self.points[k][-1]['spp']} spp {self.points[k][-1]['time']:.2f} s" for k in keys))
        # the equal-time point: once more, with a refined fit, for whoever missed the budget by over 20%
        budget = self.s.budgets[-1]
        spp_of = {}
        for key in keys:
            if abs(self.points[key][-1]['time'] / budget - 1) > 0.2:
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
            if c.replica:
                r = raycount.count(c.key, self.scene, self.spec.max_depth, spp, seed=seed)
            else:
                integ = make_integrator(c, self.spec.max_depth, statistics=True)
                mi.render(self.scene, integrator=integ, spp=spp, seed=seed)
                r = dict(integ.last_render_info['rays'])
            n = w * h * spp
            out[c.key] = {'rays_per_sample': r['rays'] / n, 'zero_per_sample': r['zero_contribution_rays'] / n,
                          'detail_per_sample': {k: v / n for k, v in r.items() if k not in ('rays', 'samples')},
                          'counted_spp': spp, 'source': 'replica (raycount.py)' if c.replica else 'bdpt statistics'}
        return out


def run_scene(spec, s, contestants, cache_dir):
    t0 = time.perf_counter()
    scene = load_scene(spec, s.res)
    ref = reference(spec, scene, s, cache_dir)
    ref_mse, ref_rel = ref.expected_errors()
    how = 'cached' if ref.meta['cached'] else f"rendered in {ref.meta['render_s']:.0f} s"
    log(f'{spec.key}: reference {how}, its expected relMSE {ref_rel:.3g}')
    runner = Runner(spec, scene, ref, s, contestants)
    runner.sweep()
    es_spp, es = runner.equal_samples()
    rays = runner.count_rays()
    et = runner.equal_time()
    crops = {'reference': ref.mean}
    for key, p in et.items():
        crops[key] = runner.images[(key, p['spp'])]
    result = {
        'spec': dataclasses.asdict(spec),
        'reference': dict(ref.meta, expected_mse=ref_mse, expected_rel=ref_rel, eps=ref.eps),
        'sweep': runner.points,
        'equal_time': {'budget_s': s.budgets[-1], 'points': et},
        'equal_samples': {'spp': es_spp, 'points': es},
        'rays': rays,
        'compile': runner.compile,
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
