"""A fuzzer for ``bdpt``: random small scenes from a seeded generator (random boxes, spheres,
rectangles and disks, mirrored transforms now and then; BSDFs among diffuse, roughplastic,
roughconductor, conductor, dielectric and plastic; emitters among area, point, spot,
directional and constant; a random camera and film shape).

Every scene must render finite and non-negative under every technique and weighting. Where
Mitsuba's `path` converges -- no delta surface (conductor, dielectric, plastic: caustics of
delta lights, and heavy tails elsewhere) and roughness alpha >= 0.2 -- the power-weighted
image must also agree with `path` by the project's statistical test.

A failing scene is written as Python source to ``tests/fuzz_failures/seed_<N>.py`` (ignored by
git) and replayed with

    .venv/bin/python tests/test_fuzz.py replay tests/fuzz_failures/seed_<N>.py

or ``replay(path)`` from Python; every saved file is also replayed by
``test_replay_saved_failures``, so a fixed case stays fixed until its file is removed.

CI runs ``FAST_SEEDS`` (finiteness only); the slow part runs ``SLOW_SEEDS`` with agreement.
``BDPT_FUZZ_SEEDS=a:b`` (environment) runs seeds a..b-1 instead, both parts.
"""

import glob
import math
import os
import sys

import mitsuba as mi
import numpy as np
import pytest

if __name__ == '__main__':          # `python tests/test_fuzz.py replay FILE`
    mi.set_variant('llvm_ad_rgb')
    import bdpt_jit  # noqa: F401
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import stability_cases as sc   # noqa: E402
from helpers import render_batches   # noqa: E402

T = mi.ScalarTransform4f
FAILURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'fuzz_failures')
COMBOS = [('bdpt', 'power'), ('bdpt', 'uniform'), ('pt', 'power'), ('pt', 'uniform'), ('lt', 'power')]
DELTA_BSDFS = ('conductor', 'dielectric', 'plastic')


def _seeds(default):
    env = os.environ.get('BDPT_FUZZ_SEEDS')
    if env:
        a, b = (int(x) for x in env.split(':'))
        return list(range(a, b))
    return default


FAST_SEEDS = _seeds(list(range(6)))
SLOW_SEEDS = _seeds(list(range(100, 160)))


# ============================================================================ the generator
def _rgb(rng, lo, hi):
    return sc.rgb([float(x) for x in rng.uniform(lo, hi, 3)])


def random_bsdf(rng):
    kind = rng.choice(['diffuse', 'diffuse', 'roughplastic', 'roughconductor', 'conductor', 'dielectric', 'plastic'])
    if kind == 'diffuse':
        b = {'type': 'diffuse', 'reflectance': _rgb(rng, 0.05, 0.95)}
    elif kind == 'roughplastic':
        b = {'type': 'roughplastic', 'alpha': float(rng.uniform(0.05, 0.6)), 'diffuse_reflectance': _rgb(rng, 0.05, 0.9)}
    elif kind == 'roughconductor':
        b = {'type': 'roughconductor', 'alpha': float(rng.uniform(0.05, 0.6)),
             'material': str(rng.choice(['Au', 'Cu', 'Al', 'none']))}
    elif kind == 'conductor':
        b = {'type': 'conductor', 'material': str(rng.choice(['Ag', 'none']))}
    elif kind == 'dielectric':
        b = {'type': 'dielectric', 'int_ior': float(rng.uniform(1.2, 1.9))}
    else:
        b = {'type': 'plastic', 'diffuse_reflectance': _rgb(rng, 0.05, 0.9)}
    if kind in ('diffuse', 'roughconductor') and rng.random() < 0.25:
        b = {'type': 'twosided', 'bsdf': b}
    return b


def random_transform(rng, center_box=1.5, size=(0.2, 0.8), uniform=False):
    t = rng.uniform(-center_box, center_box, 3)
    t[1] = abs(t[1]) * 0.6
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    s = rng.uniform(*size, 3)
    if uniform:                                        # Mitsuba's sphere takes no other
        s[:] = s[0]
    elif rng.random() < 0.12:
        s[rng.integers(3)] *= -1                       # a mirrored (negative-determinant) transform
    return T().translate(t.tolist()).rotate(axis.tolist(), float(rng.uniform(0, 360))).scale(s.tolist())


def random_scene(seed):
    """The scene dict of fuzz case ``seed`` (plain values: it can be written and replayed)."""
    rng = np.random.default_rng(seed)
    d = {'type': 'scene'}
    # camera
    dist = rng.uniform(3.0, 6.0)
    az, el = rng.uniform(0, 2 * math.pi), rng.uniform(math.radians(-10), math.radians(70))
    origin = [dist * math.cos(el) * math.sin(az), 0.3 + dist * math.sin(el), dist * math.cos(el) * math.cos(az)]
    target = rng.uniform(-0.5, 0.5, 3).tolist()
    w, h = [(8, 8), (10, 6), (6, 10), (8, 8)][rng.integers(4)]
    d['sensor'] = sc.sensor(origin, target, fov=float(rng.uniform(25, 70)), res=w, height=h)
    if rng.random() < 0.2:
        d['sensor'].update(type='thinlens', aperture_radius=float(rng.uniform(0.01, 0.2)), focus_distance=float(dist))
    # geometry
    if rng.random() < 0.7:
        d['floor'] = {'type': 'rectangle', 'to_world': T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(4),
                      'bsdf': random_bsdf(rng)}
    for i in range(int(rng.integers(2, 6))):
        kind = str(rng.choice(['cube', 'sphere', 'rectangle', 'disk']))
        shape = {'type': kind, 'bsdf': random_bsdf(rng), 'to_world': random_transform(rng, uniform=kind == 'sphere')}
        d[f'shape{i}'] = shape
    # emitters
    kinds = ['area_rect', 'area_sphere', 'point', 'spot', 'directional', 'constant']
    n_em = int(rng.integers(1, 3))
    for i, kind in enumerate(rng.choice(kinds, size=n_em, replace=False)):
        pos = [float(rng.uniform(-2, 2)), float(rng.uniform(1.5, 3.5)), float(rng.uniform(-2, 2))]
        if kind == 'area_rect':
            size = float(rng.uniform(0.15, 0.8))
            d[f'light{i}'] = {'type': 'rectangle',
                              'to_world': T().look_at(origin=pos, target=rng.uniform(-1, 1, 3).tolist(), up=[0.3, 1, 0.2]).scale(size),
                              'emitter': {'type': 'area', 'radiance': _rgb(rng, 1.0, 10.0 / size)}}
        elif kind == 'area_sphere':
            r = float(rng.uniform(0.05, 0.5))
            d[f'light{i}'] = {'type': 'sphere', 'center': pos, 'radius': r,
                              'emitter': {'type': 'area', 'radiance': _rgb(rng, 1.0, 3.0 / r)}}
        elif kind == 'point':
            d[f'light{i}'] = {'type': 'point', 'position': pos, 'intensity': _rgb(rng, 2.0, 20.0)}
        elif kind == 'spot':
            d[f'light{i}'] = {'type': 'spot', 'cutoff_angle': float(rng.uniform(15, 60)), 'intensity': _rgb(rng, 5.0, 50.0),
                              'to_world': T().look_at(origin=pos, target=rng.uniform(-1, 1, 3).tolist(), up=[0.3, 1, 0.2])}
        elif kind == 'directional':
            v = rng.normal(size=3)
            v[1] = -abs(v[1]) - 0.2
            d[f'light{i}'] = {'type': 'directional', 'direction': (v / np.linalg.norm(v)).tolist(), 'irradiance': _rgb(rng, 0.5, 4.0)}
        else:
            d[f'light{i}'] = {'type': 'constant', 'radiance': _rgb(rng, 0.1, 1.0)}
    return d


def _bsdfs(d):
    out = []
    def walk(x):
        if isinstance(x, dict):
            if 'type' in x and x['type'] in ('diffuse', 'roughplastic', 'roughconductor', 'conductor', 'dielectric',
                                               'plastic', 'twosided'):
                out.append(x)
            for v in x.values():
                walk(v)
    walk(d)
    return out


def path_converges(d):
    """`path` is a reference here: no delta surface, and no lobe sharper than alpha = 0.2."""
    for b in _bsdfs(d):
        if b['type'] in DELTA_BSDFS:
            return False
        if 'alpha' in b and b['alpha'] < 0.2:
            return False
    return True


# ============================================================================ checks, saving, replay
def save_failure(seed, d, what):
    os.makedirs(FAILURES, exist_ok=True)
    path = os.path.join(FAILURES, f'seed_{seed}.py')
    text = sc.dict_to_py(d)
    header = ''.join(f'# {line}\n' for line in str(what).splitlines())
    with open(path, 'w') as f:
        f.write(f'# fuzz seed {seed}: {header[2:]}' + text)
    rel = os.path.relpath(path, os.path.dirname(FAILURES) + '/..')
    return f'scene saved to {rel}; replay: .venv/bin/python tests/test_fuzz.py replay {rel}'


def check_finite(d, spp=4, combos=COMBOS, depths=(5, -1)):
    """Renders under every combination; returns a list of failure descriptions."""
    scene = mi.load_dict(d)
    problems = []
    for technique, mis in combos:
        for md in depths:
            img = np.array(mi.render(scene, integrator=mi.load_dict(
                {'type': 'bdpt', 'technique': technique, 'mis': mis, 'max_depth': md}), spp=spp, seed=3))
            nonfinite = int(np.sum(~np.isfinite(img)))
            low = float(np.nanmin(img)) if img.size else 0.0
            if nonfinite or low < -1e-6:
                problems.append(f'{technique}/{mis} max_depth={md}: {nonfinite} non-finite, min {low:.3g}')
    return problems


def check_agreement(d, batches=16, spp=64, ref_spp=1024, max_depth=5):
    scene = mi.load_dict(d)
    ref = render_batches(scene, {'type': 'path', 'max_depth': max_depth}, ref_spp, batches, seed0=70_000)
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth}, spp, batches)
    ok, msg = sc.agree(mine, ref)
    return [] if ok else [f'bdpt/power max_depth={max_depth} vs path: {msg}']


def replay(path, agree=None):
    """Re-run a saved fuzz failure: finiteness under every combination, and agreement with path
    where it applies (``agree``: force it on or off). Returns the list of problems."""
    with open(path) as f:
        d = sc.dict_from_py(f.read())
    problems = check_finite(d)
    if agree or (agree is None and path_converges(d)):
        problems += check_agreement(d)
    return problems


FAST_CHECKS = [('bdpt', 'power', 5), ('bdpt', 'power', -1), ('pt', 'uniform', 5), ('lt', 'power', 5)]


def run_case(seed, agree):
    d = random_scene(seed)
    if agree:
        problems = check_finite(d)
    else:     # CI: fewer compilations per scene
        problems = sum((check_finite(d, combos=[(t, m)], depths=(md,)) for t, m, md in FAST_CHECKS), [])
    if not problems and agree and path_converges(d):
        problems = check_agreement(d)
    if problems:
        where = save_failure(seed, d, '\n'.join(problems))
        pytest.fail(f'fuzz seed {seed}: ' + '; '.join(problems) + f'\n{where}')


# ============================================================================ tests
def test_generator_is_deterministic_and_round_trips():
    """The same seed gives the same scene, and a scene written by save_failure reads back equal
    (so a saved failure replays what failed)."""
    a, b = random_scene(7), random_scene(7)
    assert sc.dict_to_py(a) == sc.dict_to_py(b)
    back = sc.dict_from_py(sc.dict_to_py(a))
    assert sc.dict_to_py(back) == sc.dict_to_py(a)
    img1 = np.array(mi.render(mi.load_dict(a), spp=4, seed=1, integrator=mi.load_dict({'type': 'path'})))
    img2 = np.array(mi.render(mi.load_dict(back), spp=4, seed=1, integrator=mi.load_dict({'type': 'path'})))
    assert np.array_equal(img1, img2)


@pytest.mark.parametrize('seed', FAST_SEEDS)
def test_fuzz_finite(seed):
    run_case(seed, agree=False)


@pytest.mark.slow
@pytest.mark.parametrize('seed', SLOW_SEEDS)
def test_fuzz_slow(seed):
    run_case(seed, agree=True)


def test_replay_saved_failures():
    """Every saved failure (tests/fuzz_failures/*.py, none in a clean checkout) replays clean."""
    problems = []
    for path in sorted(glob.glob(os.path.join(FAILURES, '*.py'))):
        problems += [f'{os.path.basename(path)}: {p}' for p in replay(path)]
    assert not problems, '; '.join(problems)


if __name__ == '__main__':
    if len(sys.argv) >= 3 and sys.argv[1] == 'replay':
        bad = 0
        for p in sys.argv[2:]:
            problems = replay(p)
            print(f'{p}: ' + ('ok' if not problems else '; '.join(problems)))
            bad += bool(problems)
        sys.exit(1 if bad else 0)
    print('usage: python tests/test_fuzz.py replay FILE...')
    sys.exit(2)
