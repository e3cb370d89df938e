"""The light vertex cache (light_cache.py, parameters ``light_paths`` and ``connections``) and
the sample counts in the MIS weights (mis.py, [Veach 9.2.2] n_i p_i).

- Partition of unity with counts: the brute force of tests/test_mis_partition.py with every
  strategy's density times its count (hits and emitter sampling 1, connections n_c = c n_L / V,
  light tracing n_lt = n_L / n, merges eta = pi r^2 N), random per path, against the recursive
  weights of mis.py with ``MIS.set_counts``.
- Renders: agreement with Mitsuba's references block by block for fixed configurations, every
  pixel finite, and each (s,t) strategy's unweighted layer against the classic estimator's
  (the same expectation: the cache changes which light vertices a camera vertex meets, not what
  a strategy estimates), which is what a wrong count factor in an estimator would break."""

import itertools

import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import test_mis_partition as tmp
from helpers import agreement, file_reference, load_scene, no_delta_mask, render_batches
from test_agreement import BATCHES, REF_SEED, RES
from test_analytic import LE, sphere_scene


def random_counts(rng):
    """(n_c, n_lt) per path: n_c = c n_L / V over c in 1..8, n_L / n in [1/8, 4], V / n_L in
    [0.5, 6] (stored vertices per light subpath)."""
    M = tmp.M
    c = rng.integers(1, 9, size=M).astype(float)
    ratio = 2.0 ** rng.uniform(-3, 2, size=M)
    per_path = rng.uniform(0.5, 6.0, size=M)
    return c / per_path, ratio          # c n_L / V = c / (V / n_L); n_L / n


@pytest.mark.parametrize('camera', ['pinhole', 'thinlens', 'delta'])
@pytest.mark.parametrize('emitter', tmp.KINDS)
@pytest.mark.parametrize('technique', ['bdpt', 'lt', 'vcm_all'])
@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
@pytest.mark.parametrize('k', [1, 4])
def test_partition_of_unity_with_counts(k, kind, technique, emitter, camera):
    """Random paths, random (n_L, c, merge density eta): the recursive weights equal the brute
    force h(n_s p_s) / sum_j h(n_j p_j) and sum to one wherever a strategy samples the path."""
    rng = np.random.default_rng(50_000 + 1000 * k + 31 * tmp.KINDS.index(emitter)
                                + 7 * ['power', 'balance', 'uniform'].index(kind))
    P = tmp.random_paths(rng, k, delta_prob=0.3, emitter=emitter)
    P['camera'] = camera
    if camera == 'delta' and technique == 'lt':
        return                               # refused (test_mis_partition)
    counts = random_counts(rng)
    w_rec = tmp.recursive(kind, technique, P, counts=counts)
    p_lens = 10.0 ** rng.uniform(-1, 3, size=tmp.M) if camera == 'thinlens' else None
    w_ref = tmp.brute_force(kind, technique, P, p_lens, counts=counts)
    assert np.all(np.isfinite(w_rec)) and np.all((w_rec >= 0) & (w_rec <= 1 + 1e-6))
    tech = 'vcm' if technique == 'vcm_all' else technique
    any_strategy = np.array([tmp.allowed(tech, k, s, P) for s in range(k + 1)]
                            + ([tmp.merge_allowed(k, i, P, technique == 'vcm_all') for i in range(1, k)]
                               if tech == 'vcm' else [])).any(axis=0)
    np.testing.assert_allclose(w_rec.sum(axis=0)[any_strategy], 1.0, rtol=1e-5)
    np.testing.assert_allclose(w_rec, w_ref, rtol=1e-5, atol=1e-7)


def test_counts_matter():
    """The counts change the weights (a check of the test: with the counts left out of the
    brute force, the recursive weights with counts disagree with it)."""
    rng = np.random.default_rng(3)
    P = tmp.random_paths(rng, 4, delta_prob=0.0)
    P['camera'] = 'pinhole'
    counts = random_counts(rng)
    w_rec = tmp.recursive('power', 'bdpt', P, counts=counts)
    assert not np.allclose(w_rec, tmp.brute_force('power', 'bdpt', P), rtol=1e-3)
    w_1pct = tmp.recursive('power', 'bdpt', P, counts=(counts[0] * 1.01, counts[1]))
    assert not np.allclose(w_1pct, tmp.brute_force('power', 'bdpt', P, counts=counts), rtol=1e-3)


@pytest.mark.parametrize('k', [2, 5])
@pytest.mark.parametrize('technique', ['bdpt', 'vcm_all'])
def test_partition_of_unity_with_counts_and_delta_vertices(k, technique):
    """Merges with counts: merge_everywhere with delta vertices (the pending terms)."""
    rng = np.random.default_rng(60_000 + k)
    P = tmp.random_paths(rng, k, delta_prob=0.5)
    P['camera'] = 'pinhole'
    counts = random_counts(rng)
    np.testing.assert_allclose(tmp.recursive('power', technique, P, counts=counts),
                               tmp.brute_force('power', technique, P, counts=counts), rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------- parameters
@pytest.mark.parametrize('params,needle', [
    ({'connections': -3}, "'connections' must be >= -1"),
    ({'light_paths': 1.0, 'connections': 0}, "'connections' must be -1 (automatic) or >= 1"),
    ({'light_paths': 0}, "'light_paths' must be -1 (the classic estimator) or > 0"),
    ({'light_paths': -0.5}, "'light_paths' must be -1"),
    ({'connections': 2}, "'connections' (2) needs the light vertex cache"),
    ({'light_paths': 1.0, 'technique': 'vm'}, "'light_paths' needs technique bdpt, lt or vcm"),
    ({'light_paths': 1.0, 'technique': 'pt'}, "'light_paths' needs technique bdpt, lt or vcm"),
])
def test_bad_parameters_name_the_parameter(params, needle):
    with pytest.raises(Exception) as e:
        mi.load_dict({'type': 'bdpt', **params})
    assert needle in str(e.value)


# ---------------------------------------------------------------------------- renders
# (light_paths, connections): n_L = 1/4 and 2 light subpaths per camera sample, c = 1 and 4
CONFIGS = [(0.25, 1), (2.0, 4)]


def layer_means(scene, props, spp, batches, seed0=0, pixel_counts=None):
    """{layer: per-batch image means of its unweighted image}, the batches' images (K, H, W, 3);
    every batch checked: finite pixels, the weighted layers summing to the image.
    ``pixel_counts``: per-pixel counts (pixel_counts.py) for the integrator."""
    integ = mi.load_dict(props)
    integ.pixel_counts = pixel_counts
    out, imgs = {}, []
    for b in range(batches):
        img = np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed0 + b), dtype=np.float64)[:, :, :3]
        assert np.all(np.isfinite(img)), f'batch {b}: non-finite pixels'
        layers = integ.strategy_images
        total = sum(v['weighted'] for v in layers.values())
        np.testing.assert_allclose(total, img, rtol=1e-4, atol=1e-5 * img.max())
        for name, v in layers.items():
            assert np.all(np.isfinite(v['unweighted']))
            out.setdefault(name, []).append(v['unweighted'].mean())
        imgs.append(img)
    return {k: np.array(v) for k, v in out.items()}, np.stack(imgs)


def strategy_of(name):
    s, t = name.split('_')
    return int(s[1:]), int(t[1:])


@pytest.mark.parametrize('light_paths,connections', CONFIGS + [(0.5, 'per pixel')])
def test_closed_sphere_layers_are_analytic(light_paths, connections):
    """Inside the closed emitting sphere (test_analytic) each (s,t) strategy alone, its unweighted
    layer, estimates Le rho^(s+t-2): connections, splats and the camera-side strategies with the
    cache, and the image Le sum rho^k. The connections' layers pooled are measured to 0.15%, so
    a count factor 1% off in the connection estimator (V / (c n_L)) is over 6 sigma away.
    'per pixel': pixel_counts.py's maps (connections 1, 2 or 4 by pixel, pixel_maps; not 0,
    where the connections' unweighted layers are 0), whose factor is V / (c(p) n_L)."""
    rho, max_depth, K = 0.5, 5, 16
    per_pixel = connections == 'per pixel'
    means, imgs = layer_means(sphere_scene(rho), {'type': 'bdpt', 'max_depth': max_depth, 'strategy_images': True,
                                                  'light_paths': light_paths, 'connections': 1 if per_pixel else connections},
                              128, K, pixel_counts=pixel_maps(8, False, (1, 2, 4)) if per_pixel else None)
    per_batch = imgs.mean(axis=(1, 2, 3))
    expected = LE * sum(rho ** k for k in range(max_depth))
    se = per_batch.std(ddof=1) / np.sqrt(K)
    assert abs(per_batch.mean() - expected) <= 4 * se + 1e-6, f'image {per_batch.mean()} vs {expected} (se {se})'
    # the layers the cache changes: connections (s >= 2, t >= 2) and splats (t = 1); the camera
    # side's hits and emitter sampling are the classic estimator's. (Emitter sampling alone read
    # 0.998 of analytic here at 16 x 128 spp: unweighted, its 1/d^2 next to the receiving point
    # gives it infinite variance, so its batch means are skewed low; at 16 x 4096 spp s1_t2..s1_t5
    # read 0.9993-1.0006, and the weighted image of bdpt and pt 0.999997 +- 0.000025 of analytic.)
    tested = {n: v for n, v in means.items() if n != 'other' and np.ptp(v) > 0
              and (strategy_of(n)[0] >= 2 or strategy_of(n)[1] == 1)}
    thr = 1 - 0.99 ** (1 / len(tested))
    pooled = []
    for name, v in tested.items():
        s, t = strategy_of(name)
        ratio = v / (LE * rho ** (s + t - 2))
        p = 2 * stats.t.sf(abs(ratio.mean() - 1) / (ratio.std(ddof=1) / np.sqrt(K)), K - 1)
        assert p >= thr, f'{name}: {ratio.mean():.5f} of Le rho^{s + t - 2} (p {p:.3g} < {thr:.3g})'
        if s >= 2 and t >= 2:
            pooled.append(ratio)
    pooled = np.mean(pooled, axis=0)
    se = pooled.std(ddof=1) / np.sqrt(K)
    assert se < 0.0015, f'the connections pooled: se {se:.4f}, too wide to see a 1% count factor'
    assert abs(pooled.mean() - 1) <= 4 * se, f'connections pooled: {pooled.mean():.5f} of analytic (se {se:.5f})'


@pytest.mark.parametrize('light_paths,connections', CONFIGS)
def test_cornell_layers_agree_with_the_classic_estimator(light_paths, connections):
    """Every (s,t) strategy's unweighted layer (its estimate alone, summed over the image) with
    the cache agrees with the classic estimator's (Welch, Sidak over the layers at 0.01); the
    emitter seen through light tracing (s1_t1) is measured to 0.1% in both, so a splat scale 1%
    off (n / n_L) is far outside."""
    scene = load_scene('cornell-box.xml', RES, 4)
    base = {'type': 'bdpt', 'max_depth': 4, 'strategy_images': True}
    ref, _ = layer_means(scene, base, 16, BATCHES, seed0=REF_SEED)
    mine, _ = layer_means(scene, {**base, 'light_paths': light_paths, 'connections': connections}, 16, BATCHES)
    names = [n for n in ref if n != 'other' and (np.ptp(ref[n]) > 0 or np.ptp(mine[n]) > 0)]
    thr = 1 - 0.99 ** (1 / len(names))
    for name in names:
        a, b = ref[name], mine[name]
        se = np.sqrt(a.var(ddof=1) / BATCHES + b.var(ddof=1) / BATCHES)
        p = 2 * stats.norm.sf(abs(a.mean() - b.mean()) / se)
        assert p >= thr, f'{name}: cache {b.mean():.6g} vs classic {a.mean():.6g} (se {se:.3g}, p {p:.3g})'
    s1t1 = mine['s1_t1']
    assert s1t1.std(ddof=1) / np.sqrt(BATCHES) < 0.001 * s1t1.mean()


AGREEMENT = [('cornell-box.xml', 5), ('caustic.xml', 5)]


def agrees_with_mitsuba(name, scene, max_depth, mine):
    """(passed, message): ``mine`` (batches) per pixel and block against test_agreement.py's
    ptracer reference where no delta surface is seen. Not in the pixels that see one (the
    caustic's glass sphere, 84 of 1024), where the caches' and path's caustic noise is
    heavy-tailed at these sample counts: at 16 x 1024 spp one of those pixels of path's read
    0.0756 of channel G where path at 16 x 4096, ptracer and bdpt read 0.088-0.090 (7 of the
    caches' standard errors away once s=1 sampled the small light's cone and their variance
    fell), and their mean at 16 x 64 spp of the cache 2 x 4 read 2.4% below path's, at 16 x 256
    0.7% (0.6 standard errors). Those paths are the classic estimator's in test_agreement.py
    and the caches' weights, splats and connections are the same in every pixel."""
    mask = no_delta_mask(scene)
    ref_pt = file_reference(name, RES, max_depth, 'ptracer', 1024, BATCHES, REF_SEED)
    return agreement(mine, ref_pt, alpha=0.01, mask=mask)


@pytest.mark.parametrize('light_paths,connections', CONFIGS)
@pytest.mark.parametrize('name,max_depth', AGREEMENT)
def test_agrees_with_mitsuba(name, max_depth, light_paths, connections):
    """Block by block and per pixel against the reference of tests/test_agreement.py where no
    delta surface is seen (ptracer; agrees_with_mitsuba)."""
    scene = load_scene(name, RES, max_depth)
    mine = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'light_paths': light_paths,
                                  'connections': connections}, 64, BATCHES)
    ok, msg = agrees_with_mitsuba(name, scene, max_depth, mine)
    assert ok, f'{name} max_depth={max_depth} light_paths={light_paths} connections={connections}: {msg}'


def pixel_maps(res, merges, values=(0, 1, 4)):
    """Per-pixel counts (pixel_counts.py) that differ between neighbours: c(p) in ``values`` by
    (x + 2 y) mod 3 (0: no connection there), merges on a checkerboard (or none)."""
    from bdpt_jit.pixel_counts import PixelCounts
    y, x = np.mgrid[0:res, 0:res]
    c = np.array(values)[(x + 2 * y) % 3]
    return PixelCounts(c, ((x + y) % 2 == 0) if merges else None)


@pytest.mark.parametrize('name,technique', [('cornell-box.xml', 'bdpt'), ('caustic.xml', 'vcm')])
def test_per_pixel_counts_agree_with_mitsuba(name, technique):
    """Per-pixel connections and merging (pixel_counts.py; auto's per-pixel candidate): the
    counts of a path's MIS are those of its pixel, the camera's or where a splat lands, so with
    maps that differ between every two neighbours (connections 0, 1 or 4 a camera vertex; vcm
    merging everywhere on a checkerboard), any splat or connection weighted with another pixel's
    counts breaks the partition of unity there. Against test_agreement.py's references as the
    fixed caches (agrees_with_mitsuba)."""
    max_depth = 5
    scene = load_scene(name, RES, max_depth)
    extra = {'technique': 'vcm', 'merge_everywhere': True} if technique == 'vcm' else {}
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': max_depth, 'light_paths': 0.5, 'connections': 1, **extra})
    integ.pixel_counts = pixel_maps(RES, technique == 'vcm')
    mine = render_batches(scene, integ, 64, BATCHES)
    ok, msg = agrees_with_mitsuba(name, scene, max_depth, mine)
    assert ok, f'{name} {technique} per-pixel counts: {msg}'


def test_uniform_pixel_counts_are_the_cache():
    """Maps of one value render the fixed cache's image with the same seed (the families' weights
    dotted with the counts equal mis.MIS's with set_counts, the draws and factors the same); vcm
    with a merge map of ones and with none (its merge set decides where it merges: the merges'
    count is 1 there, as the gathers')."""
    from bdpt_jit.pixel_counts import PixelCounts
    scene = load_scene('caustic.xml', 16, 4)
    vcm = {'technique': 'vcm', 'merge_everywhere': True, 'radius': 0.1}     # (gathers that find vertices)
    for c, extra, merges in ((1, {}, None), (4, vcm, np.ones((16, 16), bool)), (2, vcm, None)):
        props = {'type': 'bdpt', 'max_depth': 4, 'light_paths': 0.5, 'connections': c, **extra}
        mapped = mi.load_dict(props)
        mapped.pixel_counts = PixelCounts(np.full((16, 16), c), merges)
        a = np.array(mi.render(scene, integrator=mi.load_dict(props), spp=16, seed=3))
        np.testing.assert_allclose(np.array(mi.render(scene, integrator=mapped, spp=16, seed=3)), a,
                                   rtol=1e-4, atol=1e-6)


def test_light_tracing_with_the_cache_is_analytic():
    """technique lt with n_L = 1/2 per camera sample inside the closed sphere: Le sum rho^k."""
    rho, max_depth, K = 0.5, 3, 16
    b = render_batches(sphere_scene(rho), {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'lt',
                                           'light_paths': 0.5}, 64, K)
    per_batch = b.mean(axis=(1, 2, 3))
    expected = LE * sum(rho ** k for k in range(max_depth))
    se = per_batch.std(ddof=1) / np.sqrt(K)
    assert abs(per_batch.mean() - expected) <= 4 * se, f'{per_batch.mean()} vs {expected} (se {se})'


def test_render_info_reports_the_cache():
    scene = load_scene('cornell-box.xml', 8, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'light_paths': 0.5})
    mi.render(scene, integrator=integ, spp=2)
    info = integ.last_render_info['light_cache']
    assert info['light_paths_per_sample'] == 0.5
    assert info['connections'] == max(1, round(info['pilot_vertices_per_path']))
    assert 0 < info['pilot_vertices_per_path'] <= 2          # max_depth 4: y1, y2 stored


@pytest.mark.parametrize('light_paths,connections', [(0.5, 2), (2.0, 1)])
def test_vcm_caustic_through_glass_with_the_cache(light_paths, connections):
    """Merges with n_L light subpaths a pass (test_merging's caustic through a delta sheet, which
    only merges render): the image mean after 16 iterations in one pass equals the blurred
    analytic value within 4 standard errors; the merge's normalisation 1 / (pi r^2 N) takes N =
    n_L / spp_pass, and a wrong N (the pixel count) would be off by the factor light_paths."""
    import test_merging as tm
    scene = tm.plane_scene(sheet='matched')
    r1, K, spp = 0.8, 8, 16
    rel = r1 / tm.scene_radius(scene)
    means = []
    for k in range(K):
        integ = mi.load_dict({'type': 'bdpt', 'technique': 'vcm', 'max_depth': 4, 'radius': rel,
                              'radius_alpha': 0.5, 'light_paths': light_paths, 'connections': connections})
        img = np.array(mi.render(scene, integrator=integ, spp=spp, seed=300 + k))
        assert np.all(np.isfinite(img))
        means.append(float(np.mean(img)))
    got, se = np.mean(means), np.std(means, ddof=1) / np.sqrt(K)
    want = tm.expected_mean([r1 * i ** -0.25 for i in range(1, spp + 1)])
    assert abs(got - want) < 4 * se, f'{got:.5f} +- {se:.5f}, expected {want:.5f}'


def test_vcm_closed_sphere_with_the_cache():
    """Merging everywhere inside the closed emitting sphere (test_merging.test_closed_sphere: a
    merge is exact there, eta = pi r^2 N ~ 8 carries much weight): Le sum rho^k with the cache."""
    from test_merging import enclosure_scene
    from bdpt_jit.merge import scene_radius
    rho, max_depth = 0.8, 4
    scene = enclosure_scene(rho)
    b = render_batches(scene, {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'vcm', 'radius': 0.05 / scene_radius(scene),
                               'radius_alpha': 1.0, 'merge_everywhere': True, 'light_paths': 0.5,
                               'connections': 2}, spp=16, batches=16)
    expected = LE * sum(rho ** k for k in range(max_depth))
    per_batch = b.mean(axis=(1, 2, 3))
    mean, sigma = per_batch.mean(), per_batch.std(ddof=1) / np.sqrt(len(per_batch))
    assert abs(mean - expected) <= 4 * sigma, f'{mean} vs {expected} (sigma {sigma})'


# ---------------------------------------------------------------------------- technique auto
@pytest.mark.parametrize('cache_var,cache_time,want', [
    (1 / 1.05, 1.0, 'pt'),      # 1.05x pt's efficiency, within PREFER_PT: a near tie, pt
    (1 / 1.2, 1.0, 'cache'),    # 1.2x: the cache
    (1.0, 0.5, 'pt'),           # pt's variance, timed faster than pt (noise): counted at pt's time
])
def test_auto_ranks_with_pt_s_time_as_the_least_and_near_ties_to_pt(cache_var, cache_time, want):
    """auto.ranked on synthetic trials (pt: relMSE 1 at 1 spp, 1 s a sample): no candidate's
    time counts as less than pt's (each does pt's work and more), and another candidate wins only
    if PREFER_PT times as efficient. Without either rule the third case picks the cache."""
    from bdpt_jit import auto
    pt = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    cache = auto.Trial('cache', {}, (0.1, 0.25, 0.0), (0.25, 1))
    for tr, v, t in ((pt, 1.0, 1.0), (cache, cache_var, cache_time)):
        tr.rel_var, tr.seconds, tr.missed = v, t, 0.0
    best, runner = auto.ranked([cache, pt])
    assert best.name == want and runner is not None
    assert cache.efficiency == pytest.approx(1.0 / (cache_var * max(cache_time, 1.0)))
    assert pt.efficiency == pytest.approx(1.0)


def spy_pilots(monkeypatch):
    """The pilot renders of technique auto's decisions: a list that gets (whether the pilot
    merges behind delta vertices only, its candidates' names) for each."""
    from bdpt_jit import auto
    calls, real = [], auto.pilot_group

    def spy(make, trials, behind_delta, *args):
        calls.append((behind_delta, [tr.name for tr in trials]))
        return real(make, trials, behind_delta, *args)
    monkeypatch.setattr(auto, 'pilot_group', spy)
    return calls


def names_of(info):
    return [c['name'] for c in info['candidates'] if 'per pixel' not in c['name']]


def without_caches(monkeypatch):
    """technique auto's candidates less the light vertex caches (as in spectral variants): for
    the tests of its merge sets, whose subject is not the caches (each cache compiles kernels
    of its own: ~20 s of an empty kernel cache in a scene with media)."""
    from bdpt_jit import auto
    real = auto.candidates
    monkeypatch.setattr(auto, 'candidates', lambda *a, **k: [tr for tr in real(*a, **k) if tr.cache is None])


def test_auto_s_behind_delta_candidate_merges_behind_delta_whatever_the_caller_sets(monkeypatch):
    """vcm's own merge set (auto.BEHIND_DELTA) is rendered with merges behind delta vertices
    only, as the pilot predicts it, also where the caller's auto integrator was given
    merge_everywhere=True (the candidates' settings go over the caller's: it would have merged
    everywhere while predicted and reported as vcm's own set)."""
    from bdpt_jit import auto
    captured, real = {}, auto.time_trial

    def spy(make, trial, *args, **kwargs):
        captured['make'] = make         # the render's own integrator maker (integrator.render_auto)
        return real(make, trial, *args, **kwargs)
    monkeypatch.setattr(auto, 'time_trial', spy)
    without_caches(monkeypatch)
    scene = load_scene('caustic.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto', 'merge_everywhere': True})
    mi.render(scene, integrator=integ, spp=1, seed=5)
    info = integ.last_render_info['auto']
    settings = {c['name']: c['settings'] for c in info['candidates']}
    made = captured['make'](settings[auto.BEHIND_DELTA])
    assert made.settings['technique'] == 'vcm' and made.settings['merge_everywhere'] is False
    assert captured['make'](settings['vcm']).settings['merge_everywhere'] is True


def test_auto_in_media_pilots_vcm_s_own_merge_set_apart(monkeypatch):
    """In a scene with media (glass in fog) one pilot cannot predict both merge sets (the merges
    inside media are beams; moments.instrument refuses it): vcm's own merge set (behind delta
    vertices) gets a pilot of its own, the others the pilot merging everywhere, and the image is
    finite."""
    import media_scenes
    from bdpt_jit import auto
    scene = mi.load_dict(media_scenes.volumetric_caustic(res=8))
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto'})
    pilots = spy_pilots(monkeypatch)
    without_caches(monkeypatch)
    img = np.array(mi.render(scene, integrator=integ, spp=2, seed=5))
    names = names_of(integ.last_render_info['auto'])
    assert auto.BEHIND_DELTA in names and np.all(np.isfinite(img))
    assert pilots == [(False, [n for n in names if n != auto.BEHIND_DELTA]), (True, [auto.BEHIND_DELTA])], pilots


def test_a_decision_past_its_share_of_the_budget_chooses_among_the_timed():
    """passes.RenderHooks.decision_over (bdpt-jit render --time gives technique auto's decisions
    half its budget): once it is True no further candidate is timed (auto.out_of_time) and the
    choice is the most efficient of those timed, pt and the probe (auto.clear_pt), on the caustic,
    whose decision otherwise times vcm's and the caches (test_auto_renders_the_chosen_configuration).
    Planted, the hook not read: more candidates are timed."""
    from bdpt_jit import auto
    from bdpt_jit.passes import RenderHooks
    scene = load_scene('caustic.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto'})
    integ.hooks = RenderHooks(decision_over=lambda: True)
    img = np.array(mi.render(scene, integrator=integ, spp=4, seed=5))
    info = integ.last_render_info['auto']
    timed = [c for c in info['candidates'] if c['timed']]
    assert {c['name'] for c in timed} == {'pt', 'cache 0.25x1'}, [c['name'] for c in timed]
    assert info['chosen'] == max(timed, key=lambda c: c['efficiency'])['name'] and info['decisions_cut'] == 1
    assert np.all(np.isfinite(img)) and integ.last_render_info['samples'] == 4 * 16 * 16


@pytest.mark.parametrize('scene_name,merging', [('cornell-box.xml', False), ('caustic.xml', True)])
def test_auto_renders_the_chosen_configuration(monkeypatch, scene_name, merging):
    """technique 'auto' (auto.py): the pilot's predicted variances and the timed trials choose
    the most efficient candidate, and the image is that candidate's render with the caller's seed
    (the pilot and the trials share no sample with it: no bias from the choice). Merging
    candidates (vcm everywhere) where the scene has a glossy or delta BSDF (the caustic's glass),
    and with a delta BSDF vcm's own merge set (behind delta vertices, timed, predicted by the
    same pilot), none among diffuse walls (the Cornell box)."""
    from bdpt_jit import auto
    scene = load_scene(scene_name, 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto'})
    pilots = spy_pilots(monkeypatch)
    img = np.array(mi.render(scene, integrator=integ, spp=4, seed=5))
    info = integ.last_render_info['auto']
    # one pilot render, merging everywhere where merges are offered, that predicts vcm's own merge
    # set too (moments.FamilyMIS's split: no media here)
    assert pilots == [(False, names_of(info))], pilots
    names = [c['name'] for c in info['candidates'] if 'per pixel' not in c['name']]
    caches = [f'cache {n:g}x{c}' for n in auto.LIGHT_PATHS for c in auto.CONNECTIONS]
    merging_caches = [f'vcm cache {n:g}x{c}' for n in auto.MERGING_LIGHT_PATHS for c in auto.CONNECTIONS]
    assert names == ['pt', 'bdpt'] + (['vcm', auto.BEHIND_DELTA] + caches + merging_caches if merging else caches)
    for c in info['candidates']:        # the per-pixel candidates (auto.per_pixel_trials): maps of those caches
        if 'per pixel' in c['name']:
            lp = c['settings']['light_paths']
            m = c['pixel_counts']['merges']
            assert c['name'] == f"{'vcm ' if m is not None else ''}cache {lp:g}x per pixel" and lp in auto.LIGHT_PATHS
            assert m is None or lp in auto.MERGING_LIGHT_PATHS
            conn = c['pixel_counts']['connections']
            # arrays, not lists: mi.render walks the integrator's attributes (last_render_info
            # included) on every call, a list element by element (auto.Trial.report)
            assert isinstance(conn, np.ndarray) and (m is None or isinstance(m, np.ndarray))
            assert conn.shape == (16, 16) and set(np.unique(conn)) <= set(auto.CONNECTIONS)
            assert (m is not None) == (c['settings'].get('technique') == 'vcm') and (merging or m is None)
    # each cache's n_c = c / V with V its own kind's (integrator.auto_vertices): as a cache of that
    # kind measures it rendering with the same seed (a merging cache's light subpaths store more)
    for kind, key in (({}, 'vertices_per_light_path'), ({'technique': 'vcm', 'merge_everywhere': True}, 'vertices_per_merging_light_path')):
        if key == 'vertices_per_merging_light_path' and not merging:
            assert info[key] is None
            continue
        own = mi.load_dict({'type': 'bdpt', 'max_depth': 4, **kind, 'light_paths': 1.0, 'connections': 1})
        mi.render(scene, integrator=own, spp=1, seed=5)
        assert info[key] == own.cache_run[0], key
        for c in info['candidates']:
            if c['name'].startswith('vcm cache ' if kind else 'cache ') and 'per pixel' not in c['name']:
                assert c['counts'][0] == pytest.approx(c['settings']['connections'] / info[key]), c['name']
    # no candidate faster than pt (each does pt's work and more), and a near tie goes to pt;
    # candidates that no timing could make the best have no time (auto.time_points)
    t_pt = info['candidates'][0]['seconds_per_spp']
    known = [c for c in info['candidates'] if c['seconds_per_spp'] is not None]
    best = max(known, key=lambda c: c['efficiency'] * (auto.PREFER_PT if c['name'] == 'pt' else 1)
               / (auto.PER_PIXEL if 'per pixel' in c['name'] else 1))
    assert info['chosen'] == best['name'] and info['trial_spp'] == auto.TRIAL_SPP
    for c in info['candidates']:
        assert c['relmse_1spp'] > 0 and (c['counts'][2] > 0) == ('vcm' in c['name'])
        if c['seconds_per_spp'] is None:
            assert c['efficiency'] is None and not c['timed']
            continue
        assert c['seconds_per_spp'] > 0
        assert c['efficiency'] == 0.0 if c['missed'] >= auto.MAX_MISSED else np.isclose(
            c['efficiency'], 1 / (c['relmse_1spp'] * max(c['seconds_per_spp'], t_pt)), rtol=1e-6)
    # the cost model: linear in light_paths and connections, least squares (scipy's bounded
    # lsq_linear here) through the timed caches, a merging cache's its cache's plus e + g
    # light_paths through vcm's and the timed merging caches' extra times (the best by the model
    # was timed too: the chosen one is); pt and the probe (auto.clear_pt) always timed, the
    # caches modelled only where the model's points were timed (three plain caches at least; a
    # merging cache for the merging ones), none below pt's or the probe's time
    timed = {c['name']: c['seconds_per_spp'] for c in info['candidates'] if c['timed']}
    assert {'pt', 'cache 0.25x1'} <= set(timed) and best['timed']
    from scipy.optimize import lsq_linear
    t = {c['name']: c['seconds_per_spp'] for c in info['candidates']}
    caches = [c for c in info['candidates'] if 'light_paths' in c['settings'] and 'per pixel' not in c['name']]
    plain = [c for c in caches if c['timed'] and 'vcm' not in c['name']]
    modelled = len(plain) >= 3
    if modelled:
        A = np.array([[1.0, c['settings']['light_paths'], c['settings']['connections']] for c in plain])
        a, b, d = lsq_linear(A, np.array([c['seconds_per_spp'] for c in plain]), bounds=([-np.inf, 0, 0], np.inf),
                             method='bvls').x
    merges_modelled = modelled and any(c['timed'] and 'vcm' in c['name'] for c in caches)
    e = g = 0.0
    if merges_modelled:
        pts = [(1.0, t['vcm'] - t['bdpt'])] if t['vcm'] is not None and t['bdpt'] is not None else []
        pts += [(c['settings']['light_paths'], c['seconds_per_spp'] - (a + b * c['settings']['light_paths'] + d * c['settings']['connections']))
                for c in caches if c['timed'] and 'vcm' in c['name']]
        if len({x for x, _ in pts}) >= 2:
            e, g = lsq_linear(np.array([[1.0, x] for x, _ in pts]), np.array([y for _, y in pts]), bounds=(0, np.inf), method='bvls').x
        elif pts:           # merges at one n_L (auto.MERGING_LIGHT_PATHS): their mean extra time
            e = max(np.mean([y for _, y in pts]), 0.0)
    floor = max(t_pt, t['cache 0.25x1'])       # no cache below them (a noisy fit's intercept can go below 0)
    fit = info['cost_model']                    # reported (auto.cost_fit) as fitted
    assert (fit is None) == (not modelled)
    if modelled:
        assert np.allclose([fit[k] for k in 'abdeg'], [a, b, d, e, g], rtol=1e-5, atol=1e-9)
        assert fit['merging'] == merges_modelled and fit['floor'] == floor
        assert set(fit['points']) == {c['name'] for c in caches if c['timed']}
    for c in caches:
        if not c['timed']:
            if not (merges_modelled if 'vcm' in c['name'] else modelled):
                assert c['seconds_per_spp'] is None, c['name']
                continue
            n_l, conn = c['settings']['light_paths'], c['settings']['connections']
            want_t = a + b * n_l + d * conn + ((e + g * n_l) if 'vcm' in c['name'] else 0.0)
            np.testing.assert_allclose(c['seconds_per_spp'], max(want_t, floor), rtol=1e-5, atol=1e-9)
    alone = mi.load_dict({'type': 'bdpt', 'max_depth': 4, **best['settings']})
    if 'pixel_counts' in best:
        from bdpt_jit.pixel_counts import PixelCounts
        m = best['pixel_counts']['merges']
        alone.pixel_counts = PixelCounts(np.array(best['pixel_counts']['connections']), None if m is None else np.array(m))
    # (up to the order of the light image's atomic additions, which varies from run to run)
    np.testing.assert_allclose(img, np.array(mi.render(scene, integrator=alone, spp=4, seed=5)),
                               rtol=1e-4, atol=1e-6)
    # the chosen configuration renders on without choosing again (last_chosen; its merging radius
    # goes on shrinking over its iterations: started again here, it renders the same image)
    assert integ.last_chosen.technique != 'auto'
    assert (integ.last_chosen.pixel_counts is None) == ('pixel_counts' not in best)
    integ.last_chosen.merge_iteration = 0
    np.testing.assert_allclose(np.array(mi.render(scene, integrator=integ.last_chosen, spp=4, seed=5)), img,
                               rtol=1e-4, atol=1e-6)


def test_auto_decides_again_as_the_render_goes(monkeypatch):
    """A long render decides again (auto.segment_spp): each segment renders with the candidate
    chosen before it, from pilots of seeds of their own pooled with the earlier ones (each
    trial's v the mean of the pilots'), segment k with seed + k SEGMENT_SEED, and the image is
    the segments' images weighted by n_k / v_k normalised (auto.segment_weights: independent of
    the images, so the combination is unbiased where each candidate is). REDECIDE made tiny, and
    the later choices forced to other candidates (the last a per-pixel candidate of a fixed map,
    pixel_maps), so that four segments of four configurations combine: the image equals the
    weighted sum of those configurations rendered alone with those seeds and spp, and the
    weighted strategy layers still sum to it."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, 'REDECIDE', 1e-6)
    mapped = auto.Trial('cache 1x per pixel', {'light_paths': 1.0, 'connections': 1}, (1.0, 1.0, 0.0))
    mapped.pixel_counts, mapped.parts, mapped.rel_var, mapped.seconds = pixel_maps(16, False, (1, 2, 4)), [], 0.07, 1e-3
    forced, rechoose = iter(['pt', 'bdpt', mapped]), auto.rechoose

    def forced_rechoose(make, trials, *args):
        rechoose(make, trials, *args)
        name = next(forced)
        return name if isinstance(name, auto.Trial) else next(tr for tr in trials if tr.name == name)
    monkeypatch.setattr(auto, 'rechoose', forced_rechoose)
    from bdpt_jit.integrator import BDPTIntegrator
    segment, rendered = BDPTIntegrator.auto_segment, []     # each segment's Trial (its maps, if per pixel)

    def recorded(self, chosen, trial, *args):
        rendered.append(trial)
        return segment(self, chosen, trial, *args)
    monkeypatch.setattr(BDPTIntegrator, 'auto_segment', recorded)
    scene = load_scene('cornell-box.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto', 'strategy_images': True})
    img = np.array(mi.render(scene, integrator=integ, spp=64, seed=5))
    info = integ.last_render_info
    decisions = info['auto']['decisions']
    cands = {**{c['name']: c for c in info['auto']['candidates']}, mapped.name: mapped.report()}
    assert [d['chosen'] for d in decisions[1:]] == ['pt', 'bdpt', mapped.name]
    assert [d['spp'] for d in decisions] == [1, 1, 1, 61] and info['samples'] == 64 * 16 * 16
    # each segment's v is its candidate's pooled prediction when the segments combine: the
    # candidates' list's, but for a per-pixel candidate of an earlier decision, which each
    # decision builds again (the report's decisions keep the v each weight used)
    v = [d['relmse_1spp'] for d in decisions]
    assert all(x == cands[d['chosen']]['relmse_1spp'] for x, d in zip(v, decisions) if 'per pixel' not in d['chosen'])
    w = np.array([d['spp'] for d in decisions]) / np.array(v)
    np.testing.assert_allclose([d['weight'] for d in decisions], w / w.sum(), rtol=1e-12)
    expect = 0.0
    for k, d in enumerate(decisions):
        alone = mi.load_dict({'type': 'bdpt', 'max_depth': 4, **rendered[k].settings})
        alone.pixel_counts = rendered[k].pixel_counts       # (None but for a per-pixel candidate)
        assert rendered[k].name == d['chosen']
        seed = 5 + k * auto.SEGMENT_SEED if k else 5
        expect = expect + d['weight'] * np.array(mi.render(scene, integrator=alone, spp=int(d['spp']), seed=seed))
    np.testing.assert_allclose(img, expect, rtol=1e-4, atol=1e-6)
    layers = sum(layer['weighted'] for layer in integ.strategy_images.values())
    np.testing.assert_allclose(layers, img[:, :, :3], rtol=1e-4, atol=1e-6)


def test_per_pixel_assignment_minimises_the_image_product():
    """auto.assign: per pixel the cache of least v(p) + lambda t, lambda = mean v / mean t, which
    minimises (mean v)(mean t) over the image, not each pixel's own v t. Two caches, A (t = 1)
    and B (t = 2, lower v everywhere: 0.4 of A's, and 0.1 in a hot 4 x 4 block whose variance is
    most of the image's): a pixel's own v t takes B everywhere (0.8 < 1), which pays B's time for
    small gains where the image's variance is not; the product is least with B in the block only
    (in the filtered v that the choice sees: the block and its filtered edge), and on the true v
    the assignment beats A or B everywhere and each pixel's own choice."""
    from bdpt_jit import auto

    def trial(v, t):
        tr = auto.Trial('x', {}, (1.0, 1.0, 0.0), (1.0, 1))
        tr.pixel_var, tr.seconds = v, t
        return tr
    hot = np.zeros((12, 12), bool)
    hot[4:8, 4:8] = True
    a = trial(np.where(hot, 100.0, 1.0), 1.0)
    b = trial(np.where(hot, 10.0, 0.4), 2.0)
    pick = auto.assign([a, b])

    def product(p, f=lambda v: v):
        v = np.where(p == 0, f(a.pixel_var), f(b.pixel_var)).mean()
        return v * np.where(p == 0, a.seconds, b.seconds).mean()
    assert pick[5:7, 5:7].min() == 1 and pick[0, 0] == 0 and pick[11, 11] == 0
    naive = np.argmin(np.stack([auto.box3(a.pixel_var) * 1.0, auto.box3(b.pixel_var) * 2.0]), axis=0)
    assert naive.min() == 1                 # (each pixel's own v t: B everywhere)
    for other in (np.zeros_like(pick), np.ones_like(pick), naive):
        assert product(pick) < product(other)
    ring = (auto.box3(hot.astype(float)) > 0).astype(int)
    for other in (np.zeros_like(pick), np.ones_like(pick), naive, hot.astype(int), ring):
        assert product(pick, auto.box3) <= product(other, auto.box3) + 1e-12
    # where the pilots' merges carried MERGE_KEEP of the image or more, only merging caches,
    # whatever v says (a non-merging A of lower v and time everywhere; merges carry the block)
    a = trial(np.full((12, 12), 1.0), 1.0)
    b = trial(np.full((12, 12), 2.0), 2.0)
    b.merges = True
    a.merge_share = b.merge_share = np.where(hot, 0.5, 0.0)
    pick = auto.assign([a, b])
    assert np.all(pick[auto.box3(hot * 0.5) > auto.MERGE_KEEP] == 1) and pick[0, 0] == 0


def test_per_pixel_maps_of_a_large_crop():
    """A crop larger than the moment film keeps (moments.MAX_PIXELS: raster pixel j step for kept
    pixel j): auto.box3_lattice averages each kept pixel with the kept pixels nearest to it in the
    rows above and below and their neighbours step pixels to either side (the 3 x 3 mean of the
    kept pixels' grid where the width is a multiple of step), and auto.per_pixel_trials chooses per
    kept pixel and expands the maps to every pixel, each taking its nearest kept pixel's cache in
    raster order: a hot block gets the cache of lower v, the rest the cheaper one (as in
    test_per_pixel_assignment_minimises_the_image_product, on a 24 x 32 crop kept every 4th pixel)."""
    from bdpt_jit import auto
    h, w, step = 24, 32, 4
    rng = np.random.default_rng(3)
    a = rng.random(h * w // step)
    grid = a.reshape(h, w // step)
    got = auto.box3_lattice(a, h, w, step).reshape(grid.shape)
    for y in range(1, h - 1):
        for x in range(1, w // step - 1):
            assert got[y, x] == pytest.approx(grid[y - 1:y + 2, x - 1:x + 2].mean(), rel=1e-12)
    assert np.allclose(auto.box3_lattice(np.full(a.shape, 0.7), h, w, step), 0.7)

    ys, xs = np.divmod(np.arange(h * w // step) * step, w)
    hot = (ys >= 8) & (ys < 16) & (xs >= 12) & (xs < 24)          # at the kept pixels

    def trial(c, v, t):
        tr = auto.Trial(f'cache 1x{c}', {}, (float(c), 1.0, 0.0), (1.0, c))
        tr.pixel_var, tr.seconds, tr.missed, tr.lattice = v, t, 0.0, (h, w, step)
        return tr
    out = auto.per_pixel_trials([trial(1, np.where(hot, 100.0, 1.0), 1.0), trial(4, np.where(hot, 10.0, 0.4), 2.0)])
    assert len(out) == 1 and out[0].name == 'cache 1x per pixel'
    conn = out[0].pixel_counts.connections
    assert conn.shape == (h, w) and conn[10:14, 14:22].min() == 4 and conn[0, 0] == conn[-1, -1] == 1
    near = np.minimum(np.rint(np.arange(h * w) / step).astype(int), len(a) - 1)
    np.testing.assert_array_equal(conn.ravel(), np.array([1, 4])[out[0].pick][near])


def test_auto_decides_at_the_merging_radius_of_the_samples_it_governs(monkeypatch):
    """A decision's pilots and trials merge at the radius of the iterations it governs
    (auto.horizon, auto.pilot_iteration: the radius shrinks with the iterations, merge.py), from
    the render's merging iteration so far; the segments merge at the render's own count. REDECIDE
    made tiny and the later choices forced to vcm, whose segments advance the iteration. Planted:
    the integrators made at the render's iteration (the first decision's at 0), or the segments
    at the pilots' iteration, fails."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, 'REDECIDE', 1e-6)
    scene = load_scene('caustic.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto'})
    seen, hs, rechoose, pilot_group, horizon = [], [], auto.rechoose, auto.pilot_group, auto.horizon

    def forced_rechoose(make, trials, *args):
        rechoose(make, trials, *args)
        vcm = next(tr for tr in trials if tr.name == 'vcm')
        if not vcm.timed:           # (auto.time_points times only what could win: a segment needs its time)
            auto.time_trial(make, vcm, scene, scene.sensors()[0], 5, auto.trial_spp(scene.sensors()[0]))
        return vcm

    def recorded_pilot_group(make, *args):
        def made(settings, *rest):
            out = make(settings, *rest)
            seen.append((out.merge_iteration, integ.merge_iteration, hs[-1]))
            return out
        return pilot_group(made, *args)
    monkeypatch.setattr(auto, 'rechoose', forced_rechoose)
    monkeypatch.setattr(auto, 'pilot_group', recorded_pilot_group)
    monkeypatch.setattr(auto, 'horizon', lambda *a: hs.append(horizon(*a)) or hs[-1])
    mi.render(scene, integrator=integ, spp=64, seed=5)
    decisions = integ.last_render_info['auto']['decisions']
    assert [d['chosen'] for d in decisions[1:]] == ['vcm'] * (len(decisions) - 1) and len(decisions) >= 3
    assert all(own == auto.pilot_iteration(parent, h, 0.75) for own, parent, h in seen)
    assert seen[0][1:] == (0, 64) and seen[0][0] == auto.pilot_iteration(0, 64, 0.75) > 0
    assert max(parent for _, parent, _ in seen) >= 1        # a decision after a merging segment
    merged = sum(d['spp'] for d in decisions if 'vcm' in d['chosen'])
    assert integ.merge_iteration == round(merged)


def test_the_pilots_merging_iteration_is_the_harmonic_mean_of_the_etas():
    """auto.pilot_iteration: the iteration (its first: the result plus 1) whose eta_i, which
    falls as i^(alpha - 1), is the harmonic mean of the etas of the ``h`` iterations after
    ``done`` (by brute force: within 3% or one iteration); the next one where the radius is
    constant (alpha 1) or one iteration is governed. Planted: ``done`` returned, fails."""
    from bdpt_jit import auto
    for alpha in (0.75, 0.5, 0.9):
        p = 1.0 - alpha
        for done, h in ((0, 64), (0, 256), (100, 1500), (5, 3), (4096, 61440)):
            i = np.arange(done + 1, done + h + 1, dtype=np.float64)
            want = np.mean(i ** p) ** (1.0 / p)        # eta(want) = 1 / mean(1 / eta_i)
            got = auto.pilot_iteration(done, h, alpha) + 1
            assert abs(got - want) <= max(1.0, 0.03 * want), (alpha, done, h, got, want)
    assert auto.pilot_iteration(7, 100, 1.0) == 7 and auto.pilot_iteration(7, 1, 0.75) == 7
    assert auto.horizon(1 << 30, 0) == auto.FIRST_HORIZON and auto.horizon(40, 0) == 40
    assert auto.horizon(1 << 30, 1000) == int((auto.REDECIDE - 1) * 1000)


def test_auto_segment_plan():
    """When a render decides again: once it has run REDECIDE ** k times as long as its k
    decisions took (by the chosen candidate's seconds per spp), not where what is left to render
    after the segment is under REDECIDE times a decision's mean cost, not past MAX_DECISIONS."""
    from bdpt_jit import auto
    best = auto.Trial('pt', {}, (0.0, 0.0, 0.0))
    best.seconds = 0.01
    R = auto.REDECIDE
    assert auto.segment_spp(best, 0.0, 1.0, 10 ** 6, 1) == int(R * 1.0 / 0.01) + 1
    assert auto.segment_spp(best, 16.0, 2.0, 10 ** 7, 2) == int((R ** 2 * 2.0 - 16.0) / 0.01) + 1
    assert auto.segment_spp(best, 0.0, 1.0, int(R / 0.01) + 1 + int(R / 0.01) - 1, 1) == 2 * int(R / 0.01)
    assert auto.segment_spp(best, 0.0, 1.0, 10 ** 9, auto.MAX_DECISIONS) == 10 ** 9


def test_auto_stops_between_segments(monkeypatch):
    """The render's stop rule (RenderHooks.should_stop) ends an auto render as a fixed one: after
    its first pass, without deciding again, the samples done and 'interrupted' reported."""
    from bdpt_jit import auto
    from bdpt_jit.passes import RenderHooks
    monkeypatch.setattr(auto, 'REDECIDE', 1e-6)
    scene = load_scene('cornell-box.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto', 'samples_per_pass': 256})
    seen = []
    integ.hooks = RenderHooks(on_pass=lambda done, total: seen.append((done, total)), should_stop=lambda: True)
    img = np.array(mi.render(scene, integrator=integ, spp=64, seed=5))
    info = integ.last_render_info
    assert info['interrupted'] and info['samples'] == 256 and len(info['auto']['decisions']) == 1
    assert seen == [(256, 64 * 256)] and np.all(np.isfinite(img))


def test_auto_with_strategy_images_leaves_merging_out():
    """strategy_images with technique auto in a scene that would offer merging (the caustic's
    glass): no merging candidate (no (s,t) layer holds a merge; the pilot then does not merge,
    and before this the pilot's vcm integrator refused the parameter), and the weighted layers
    sum to the image."""
    scene = load_scene('caustic.xml', 16, 4)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'auto', 'strategy_images': True})
    img = np.array(mi.render(scene, integrator=integ, spp=4, seed=5))
    names = [c['name'] for c in integ.last_render_info['auto']['candidates']]
    assert names[:2] == ['pt', 'bdpt'] and not any('vcm' in n for n in names)
    layers = sum(layer['weighted'] for layer in integ.strategy_images.values())
    np.testing.assert_allclose(layers, img[:, :, :3], rtol=1e-4, atol=1e-6)


def test_auto_refuses_what_it_chooses_itself():
    with pytest.raises(Exception, match="chosen by technique 'auto'"):
        mi.load_dict({'type': 'bdpt', 'technique': 'auto', 'light_paths': 1.0})


class _AllWarm(set):
    """auto._WARM holding every trial render: none is the first of its configuration."""

    def __contains__(self, key):
        return True


def _stub_choice(monkeypatch, rel_var, times, pixel_var=None, merging=False):
    """auto.choose over the trials ``rel_var`` (name: predicted relMSE; names as auto.candidates
    gives them) with the pilot stubbed and each trial render's kernel time the next of
    ``times[name]`` (seconds per spp; the last repeats); ``pixel_var``: name: v per pixel, for
    caches (their rel_var its mean); ``merging``: vcm's, auto.BEHIND_DELTA's and the merging
    caches too. Returns (the chosen, the trials by name, the trial renders made, in order)."""
    from bdpt_jit import auto
    made = []
    trials = [auto.Trial('pt', {'n': 'pt'}, (0.0, 0.0, 0.0)), auto.Trial('bdpt', {'n': 'bdpt'}, (1.0, 1.0, 0.0))]
    if merging:
        trials += [auto.Trial(name, {'n': name}, (1.0, 1.0, 1.0)) for name in ('vcm', auto.BEHIND_DELTA)]
    for m in ('', 'vcm ') if merging else ('',):
        trials += [auto.Trial(f'{m}cache {lp:g}x{c}', {'n': f'{m}cache {lp:g}x{c}'}, (c, lp, lp if m else 0.0), (lp, c))
                   for lp in (auto.MERGING_LIGHT_PATHS if m else auto.LIGHT_PATHS) for c in auto.CONNECTIONS]

    def pilot(make, trials, scene, sensor, seed):
        for tr in trials:
            tr.rel_var, tr.missed = rel_var.get(tr.name, 1.0), 0.0
            if pixel_var and tr.cache is not None:
                tr.pixel_var = pixel_var.get(tr.name, np.full((16, 16), tr.rel_var))
                tr.rel_var = float(np.mean(tr.pixel_var))

    def make(settings, pixel_counts=None):     # the trial render: its kernels' time is the stub's
        made.append(settings.get('n', 'per pixel'))
        return None

    def kernel_seconds(render):
        seq = times[made[-1]]
        return seq[min(made.count(made[-1]) - 1, len(seq) - 1)] * auto.TRIAL_SPP

    monkeypatch.setattr(auto, 'candidates', lambda ctx, vpp, vpp_merging=None: trials)
    monkeypatch.setattr(auto, 'pilot', pilot)
    monkeypatch.setattr(auto, 'kernel_seconds', kernel_seconds)
    monkeypatch.setattr(auto, '_WARM', _AllWarm())     # one timing a trial render, as ``times`` gives
    best, _ = auto.choose(make, None, None, None, 0, 1.0)
    return best, {tr.name: tr for tr in trials}, made


def test_auto_times_close_calls_again(monkeypatch):
    """A close call (the runner-up's efficiency within auto.CLOSE of the best's) is timed again
    and decided by the least of each one's times: pt's first timing met another job's load (4x
    its time), so the cache 1/4 x 1 led by 1.6x; pt's second timing, unloaded, wins. The cost
    model is refitted from the times that fell (a stale model keeps the modelled caches' first
    values), and no candidate is timed more than auto.TIMINGS times, nor again once two of its
    timings agree within auto.SETTLED."""
    from bdpt_jit import auto
    # a later timing under load (5.0) does not undo an earlier one (1.0): the least counts (bdpt's
    # v 0.05 at the probe's 1.5 could beat pt: not auto.clear_pt; at its own 3.0 it is the runner-up)
    rel = {'pt': 0.11, 'cache 0.25x1': 0.11, 'bdpt': 0.05}
    times = {'pt': [1.0, 5.0], 'bdpt': [3.0], 'cache 0.25x1': [1.5], 'cache 1x1': [3.0], 'cache 1x4': [4.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'pt' and by['pt'].seconds == 1.0 and by['pt'].timings == auto.TIMINGS
    times = {'pt': [4.0, 1.0], 'bdpt': [3.0], 'cache 0.25x1': [2.5, 2.5, 2.5],
             'cache 1x1': [3.0, 2.0], 'cache 1x4': [4.0]}
    rel = {'pt': 0.11, 'cache 0.25x1': 0.09}        # (at pt's 4.0 the cache could win: not clear_pt)
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'pt' and by['pt'].seconds == 1.0 and by['pt'].timings == 2
    assert max(tr.timings for tr in by.values()) <= auto.TIMINGS
    # a close call whose timings settle: pt's 1.0, 1.05 and the cache's 1.5, 1.5 agree within
    # SETTLED (the cache still leads by 1.36 < CLOSE): each timed twice, not TIMINGS times
    rel = {'pt': 0.11, 'cache 0.25x1': 0.05}
    times = {'pt': [1.0, 1.05, 0.5], 'bdpt': [3.0], 'cache 0.25x1': [1.5, 1.5, 0.1], 'cache 1x1': [3.0],
             'cache 1x4': [4.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'cache 0.25x1' and by['cache 0.25x1'].seconds == 1.5 and by['pt'].seconds == 1.0
    assert by['pt'].timings == by['cache 0.25x1'].timings == 2
    # a cost-model point in the close call: the cache 1 x 1's time falls 3.0 -> 1.5, so the least
    # squares through (n_L, c, t) = (0.25, 1, 2.5), (1, 1, 1.5), (1, 4, 4.0) would have b = -4/3:
    # b held at 0, a + d c through them is d = 2/3, a = 4/3 (stale: a, b, d = 2, 2/3, 1/3); none
    # below the probe's 2.5 (auto.least_time)
    rel = {'bdpt': 0.12, 'cache 1x1': 0.11}
    times = {'pt': [1.0], 'bdpt': [2.0], 'cache 0.25x1': [2.5], 'cache 1x1': [3.0, 1.5], 'cache 1x4': [4.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'cache 1x1' and by['cache 1x1'].seconds == 1.5
    # cache 1 x 1's two timings disagree (3.0, 1.5): a third; bdpt's agree (2.0, 2.0): settled at two
    assert by['cache 1x1'].timings == auto.TIMINGS and by['bdpt'].timings == 2
    for lp in auto.LIGHT_PATHS:
        for c in auto.CONNECTIONS:
            tr = by[f'cache {lp:g}x{c}']
            if not tr.timed:
                assert np.isclose(tr.seconds, max(4.0 / 3.0 + 2.0 / 3.0 * c, 2.5)), tr.name    # (not below the probe's)


def test_the_cost_model_takes_every_timed_cache():
    """auto.cost_model: a least-squares fit over every timed cache. The three first points put
    the cache 1 x 4 below 1 x 1 (timing noise: from them alone connections cost nothing, d = 0);
    a later timing of the cache 1/4 x 8 joins the fit, which then has d > 0 and models the cache
    1/4 x 4 between its neighbours; the merging caches' extra time (vcm over bdpt at n_L / n = 1,
    the merging 1/4 x 1 over its cache's t) is e + g n_L / n with e, g >= 0. Planted: the fit of
    the three first points only, the 1/4 x 4 at 1.0, fails."""
    from bdpt_jit import auto
    def cache(lp, c, merges=False, t=None):
        tr = auto.Trial(f"{'vcm ' if merges else ''}cache {lp:g}x{c}", {}, (c, lp, lp if merges else 0.0), (lp, c))
        tr.seconds, tr.timed = t, t is not None
        return tr
    bdpt, vcm = auto.Trial('bdpt', {}, (1.0, 1.0, 0.0)), auto.Trial('vcm', {}, (1.0, 1.0, 1.0))
    bdpt.seconds, bdpt.timed, vcm.seconds, vcm.timed = 2.5, True, 3.5, True
    points = [cache(0.25, 1, t=1.0), cache(1.0, 1, t=2.0), cache(1.0, 4, t=1.9), cache(0.25, 8, t=3.1)]
    modelled = [cache(0.25, 4), cache(1.0, 8), cache(0.25, 1, True, t=1.5), cache(1.0, 2, True)]
    auto.cost_model(points + modelled + [bdpt, vcm])
    A = np.array([[1.0, tr.cache[0], tr.cache[1]] for tr in points])
    a, b, d = np.linalg.lstsq(A, np.array([tr.seconds for tr in points]), rcond=None)[0]
    assert b > 0 and d > 0          # the unconstrained fit is feasible here
    assert modelled[0].seconds == pytest.approx(a + 0.25 * b + 4 * d) and 1.0 < modelled[0].seconds < 3.1
    assert modelled[1].seconds == pytest.approx(a + b + 8 * d)
    x1, x0 = 3.5 - 2.5, 1.5 - (a + 0.25 * b + d)      # merges' extra time at n_L / n = 1 and 1/4
    g = (x1 - x0) / 0.75
    assert modelled[3].seconds == pytest.approx(a + b + 2 * d + (x1 - g) + g)
    fit = auto.nonnegative_fit([(1.0, 0.0), (1.0, 1.0)], [1.0, 0.5], free=0)   # a falling line: held flat
    assert fit == pytest.approx([0.75, 0.0])


def test_a_trial_s_first_render_is_two_timings(monkeypatch):
    """auto.time_trial: the first trial render of a configuration at a crop and spp in a process
    is two timed renders (a kernel's first run may be the slow one, or a later run: both count),
    its time the least and ``second`` the other, so that two that agree settle it; later
    timings of it, and of it at that size from another decision, are one render each; another
    spp is two again."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, '_WARM', set())
    times = iter([0.008, 0.004, 0.006, 0.0045, 0.0042, 0.003, 0.002])
    monkeypatch.setattr(auto, 'kernel_seconds', lambda render: next(times))
    scene = mi.load_dict(_sky_only(8, 8))
    trial = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    other = auto.Trial('bdpt', {}, (1.0, 1.0, 0.0))
    make = lambda settings: None        # noqa: E731 (not rendered: kernel_seconds is the stub)
    auto.time_trial(make, trial, scene, scene.sensors()[0], 0, 4)
    assert trial.timings == 2 and trial.seconds == pytest.approx(0.001) and trial.second == pytest.approx(0.002)
    assert not auto.settled(trial)
    auto.time_trial(make, trial, scene, scene.sensors()[0], 0, 4)           # 0.006: one render
    assert trial.timings == 3 and trial.second == pytest.approx(0.0015)
    auto.time_trial(make, other, scene, scene.sensors()[0], 0, 4)           # 0.0045, 0.0042: settled at once
    assert other.timings == 2 and other.seconds == pytest.approx(0.0042 / 4) and auto.settled(other)
    auto.time_trial(make, trial, scene, scene.sensors()[0], 0, 2)           # another spp: 0.003, 0.002
    assert trial.timings == 5 and trial.seconds == pytest.approx(0.001)
    assert next(times, None) is None


def test_a_long_first_trial_render_is_one_timing(monkeypatch):
    """auto.time_trial: a configuration's first trial render whose kernels ran at least
    auto.ONE_TIMING_S counts alone (one render, its time that timing, nothing settled); one just
    under it is two, as above. Planted: every first render two (the old rule), fails."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, '_WARM', set())
    long_s = auto.ONE_TIMING_S * 1.5
    times = iter([long_s, auto.ONE_TIMING_S * 0.99, 0.02])
    monkeypatch.setattr(auto, 'kernel_seconds', lambda render: next(times))
    scene = mi.load_dict(_sky_only(8, 8))
    make = lambda settings: None        # noqa: E731 (not rendered: kernel_seconds is the stub)
    slow = auto.Trial('bdpt', {}, (1.0, 1.0, 0.0))
    auto.time_trial(make, slow, scene, scene.sensors()[0], 0, 2)
    assert slow.timings == 1 and slow.seconds == pytest.approx(long_s / 2) and slow.second is None
    assert not auto.settled(slow)
    short = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    auto.time_trial(make, short, scene, scene.sensors()[0], 0, 2)
    assert short.timings == 2 and short.seconds == pytest.approx(0.01)
    assert next(times, None) is None


def test_each_trial_render_has_a_seed_of_its_own(monkeypatch):
    """auto.time_trial / trial_seed: a trial's renders (the untimed first one included) have
    seeds of their own, none a pilot's (seed + TRIAL_SEED + 2 k), so that the images the
    denominator takes are independent of each other and of the pilots' V; their images are
    kept (channel means at the pilots' pixels). Planted: every render with one seed, fails."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, '_WARM', set())
    monkeypatch.setattr(auto, 'kernel_seconds', lambda render: render() or 0.004)
    seeds = []

    class Render:
        def render(self, scene, sensor, seed, spp):
            seeds.append(seed)
            return np.full((8, 8, 3), float(len(seeds)))
    scene = mi.load_dict(_sky_only(8, 8))
    trial = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    trial.pilot_image = np.zeros(64)
    for _ in range(3):
        auto.time_trial(lambda settings: Render(), trial, scene, scene.sensors()[0], 7, 2)
    pilots = {7 + auto.TRIAL_SEED + 2 * k for k in range(auto.MAX_DECISIONS)}
    assert len(seeds) == 4 and len(set(seeds)) == 4 and not set(seeds) & pilots
    assert trial.images == 4 and trial.image_spp == 2 and np.allclose(trial.image_sum, 1 + 2 + 3 + 4)


def test_auto_does_not_time_a_clear_choice_again(monkeypatch):
    """Where the best leads by more than auto.CLOSE, each trial is timed once: no re-timing (the
    probe of auto.clear_pt excepted: timed until two timings agree); and no cost-model point is
    timed whose candidates could not win at the least time they could take (auto.time_points:
    bdpt, v 0.01 at 3.0, scores 33; the caches, v 1, at most 0.4 at the probe's 2.5)."""
    rel = {'bdpt': 0.01}
    times = {'pt': [1.0], 'bdpt': [3.0], 'cache 0.25x1': [2.5], 'cache 1x1': [3.0], 'cache 1x4': [4.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'bdpt'
    assert sorted(made) == sorted(['pt', 'bdpt', 'cache 0.25x1', 'cache 0.25x1'])
    assert by['cache 1x1'].seconds is None and by['cache 1x1'].efficiency is None


def test_a_clear_pt_times_pt_and_the_cheapest_bidirectional_candidate_only(monkeypatch):
    """auto.clear_pt: pt (v 0.1, 1.0 s) is chosen once no candidate could beat it even at the
    least time of a bidirectional one (the probe, the cache 1/4 x 1: 2.0): the best other v, 0.06,
    gives 1 / (0.06 x 2.0) = 8.3 < 1.1 x 10, so only pt and the probe (twice, until settled) are
    timed. Not clear, and the caches' cost-model points timed: a cache whose v (0.04) could win at the
    probe's time (12.5); a probe whose first timing met load (6.0, then 2.0: at 6.0 the bound
    would be 4.2); per-pixel candidates whose v per pixel (the least cache's in each pixel: 0.04
    on average) could win though no cache's mean v could (0.07). Planted: pt's time as the bound's,
    one timing of the probe, or the per-pixel bound left out, each fails a case. (bdpt, which
    then could not win at the probe's time, is not timed: auto.time_points.)"""
    from bdpt_jit import auto
    clear = ['pt', 'cache 0.25x1', 'cache 0.25x1']
    rel = {'pt': 0.1, 'bdpt': 0.06, 'cache 1x4': 0.07}
    times = {'pt': [1.0], 'bdpt': [3.0], 'cache 0.25x1': [2.0], 'cache 1x1': [2.5], 'cache 1x4': [3.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times)
    assert best.name == 'pt' and made == clear and by['bdpt'].seconds is None
    points = {'pt', 'cache 0.25x1', 'cache 1x1', 'cache 1x4'}
    best, by, made = _stub_choice(monkeypatch, {**rel, 'cache 1x4': 0.04}, times)
    assert set(made) >= points
    best, by, made = _stub_choice(monkeypatch, {**rel, 'cache 1x4': 0.04}, {**times, 'cache 0.25x1': [6.0, 2.0]})
    assert set(made) >= points and by['cache 0.25x1'].seconds == 2.0
    # per pixel: two caches, each v 0.07 on average, 0.01 or 0.13 by halves, the halves crossed
    half = np.repeat([[0.01], [0.13]], 8, axis=0) * np.ones((16, 16))
    maps = {'cache 0.25x2': half, 'cache 0.25x4': half[::-1]}
    best, by, made = _stub_choice(monkeypatch, rel, times | {'per pixel': [2.5]}, maps)
    assert set(made) >= points


def test_auto_times_only_what_could_win(monkeypatch):
    """auto.time_points: after pt and the probe (cache 1/4 x 1, 1.2 s), a cost-model point or
    candidate is timed only while some candidate it decides could still be chosen at the least
    time it could take. veach-bidir's case: vcm (v 0.47) could beat pt (1.1) at the probe's time
    (1.77) but not at the classic estimator's (2.0: 1.06), which vcm behind delta (v 0.32, 2.5 s:
    1.25) beats: vcm is never timed, nor the caches (v 1: 0.83 at most); vcm behind delta is
    chosen. With a merging cache that could win (v 0.2), the plain caches' points and the merging
    ones' (auto.TIMED_MERGING) are timed, not vcm (its bound at the classic estimator's time is
    low), and it is chosen, timed. Planted: vcm's least time the probe's, no bound at all, or the
    merging points left out: each fails."""
    from bdpt_jit import auto
    rel = {'pt': 1.0, 'bdpt': 0.5, 'vcm': 0.47, auto.BEHIND_DELTA: 0.32}
    times = {'pt': [1.0], 'cache 0.25x1': [1.2], 'bdpt': [2.0], auto.BEHIND_DELTA: [2.5], 'vcm': [7.0],
             'cache 1x1': [1.5], 'cache 1x4': [2.5], 'vcm cache 1x1': [2.2], 'vcm cache 1x4': [3.2],
             'vcm cache 1x2': [2.0]}
    best, by, made = _stub_choice(monkeypatch, rel, times, merging=True)
    assert best.name == auto.BEHIND_DELTA and set(made) == {'pt', 'cache 0.25x1', 'bdpt', auto.BEHIND_DELTA}
    assert by['vcm'].seconds is None and by['cache 1x1'].seconds is None and by['vcm cache 1x1'].seconds is None
    best, by, made = _stub_choice(monkeypatch, {**rel, 'vcm cache 1x2': 0.2}, times, merging=True)
    points = {f'vcm cache {lp:g}x{c}' for lp, c in auto.TIMED_MERGING}
    assert {'cache 1x1', 'cache 1x4'} | points <= set(made) and 'vcm' not in made
    assert best.name == 'vcm cache 1x2' and best.timed and best.seconds == 2.0


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_auto_predicts_a_heavy_tailed_candidate_s_variance_over_an_independent_image(seed):
    """auto.normalise / denominator: the relMSE's I^2 not from the pilots' own image. Synthetic
    pilots: the classic estimator (the pilot's own) is heavy-tailed, a sample 1/p times its
    pixel's value with probability p = 0.05 (one-sample relative variance (1 - p) / p = 19), a
    cache light-tailed (1); V is each one's sample variance over the pilot's 4 samples, as the
    moment film's, so the classic's V is large exactly where the pilot's image is. Each has two
    trial renders of 2 spp. Over the pilots' own image the classic's v comes out at ~0.04 of
    the truth (a rare sample divides its own square); over the weighted, 3 x 3 filtered mean of
    all the images within 0.8-1.4 of it, and the cache's within 0.9-1.4 (the I of 36 samples a
    pixel: E[1 / I^2] a little above 1 / R^2). Planted: the denominator from the pilots' image
    alone, or the trials' images with equal weights (the classic's, mostly 0, make I low), fails."""
    from bdpt_jit import auto
    rng = np.random.default_rng(seed)
    h = w = 64
    R = np.exp(rng.normal(0.0, 0.3, h * w))
    p = 0.05
    heavy = lambda n: R[:, None] * (rng.random((h * w, n)) < p) / p       # noqa: E731
    light = lambda n: R[:, None] * (1.0 + rng.normal(size=(h * w, n)))     # noqa: E731
    Y = heavy(auto.PILOT_SPP)
    trials = [auto.Trial('bdpt', {}, (1.0, 1.0, 0.0)), auto.Trial('cache 1x4', {}, (4.0, 1.0, 0.0), (1.0, 4))]
    for tr, V in zip(trials, (Y.var(axis=1, ddof=1), light(auto.PILOT_SPP).var(axis=1, ddof=1))):
        tr.pixel_V, tr.pilot_image, tr.pilot_missed = V.reshape(h, w), Y.mean(axis=1), [0.0]
        tr.own_var = float(np.mean(V / (tr.pilot_image ** 2 + auto.DENOM)))
    for tr, sample in zip(trials, (heavy, light)):
        for _ in range(2):
            auto.add_image(tr, np.repeat(sample(2).mean(axis=1).reshape(h, w, 1), 3, axis=2), 2)
    auto.normalise(trials)
    rel = R ** 2 / (R ** 2 + auto.DENOM)
    truth = np.mean((1 - p) / p * rel), np.mean(rel)
    assert trials[0].own_var < 0.1 * truth[0]
    assert 0.8 < trials[0].rel_var / truth[0] < 1.4 and 0.9 < trials[1].rel_var / truth[1] < 1.4
    assert trials[0].pixel_var.shape == (h, w) and np.mean(trials[0].pixel_var) == pytest.approx(trials[0].rel_var)


def _sky_only(width, height):
    """A sensor under a constant sky and nothing else."""
    return {'type': 'scene', 'sky': {'type': 'constant', 'radiance': {'type': 'rgb', 'value': 0.5}},
            'sensor': {'type': 'perspective', 'fov': 40,
                       'film': {'type': 'hdrfilm', 'width': width, 'height': height}}}


def test_auto_pilots_a_large_crop_at_fewer_samples_per_pixel(monkeypatch):
    """auto.pilot_spp: PILOT_SPP samples per pixel in a crop of up to moments.MAX_PIXELS pixels,
    LATTICE_PILOT_SPP in a larger one (the lattice pilot, whose light side traces every pixel's
    light subpaths). The pilot renders at that count and the moment film's estimates scale by
    it (a V of the other count is off by their ratio); the denominator weighs the pilots'
    image by their samples (an image of a given v and n spp has weight n / v), and a trial's image
    of every other row where it covers a pixel only. Planted: estimates at PILOT_SPP, the
    denominator's weight at PILOT_SPP, or a lattice trial's image counted at every pixel: each fails."""
    from bdpt_jit import auto, moments
    assert auto.LATTICE_PILOT_SPP % 2 == 0 and auto.LATTICE_PILOT_SPP < auto.PILOT_SPP
    for (w, h), want in {(128, 128): auto.PILOT_SPP, (129, 128): auto.LATTICE_PILOT_SPP}.items():
        assert auto.pilot_spp(mi.load_dict(_sky_only(w, h)).sensors()[0]) == want, (w, h)
    monkeypatch.setattr(moments, 'MAX_PIXELS', 64)          # the 16 x 16 box: a lattice of step 4
    scene, seen = load_scene('cornell-box.xml', 16, 4), {}
    real = moments.MomentFilm.estimates

    def estimates(film, spp):
        seen['estimates'] = spp
        return real(film, spp)
    monkeypatch.setattr(moments.MomentFilm, 'estimates', estimates)
    made = []

    def make(settings):
        made.append(mi.load_dict({'type': 'bdpt', 'max_depth': 4, **settings}))
        return made[-1]
    trials = [auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0)), auto.Trial('bdpt', {}, (1.0, 1.0, 0.0))]
    auto.pilot(make, trials, scene, scene.sensors()[0], 0)
    assert made[0].last_render_info['spp'] == auto.LATTICE_PILOT_SPP == seen['estimates']
    assert trials[0].pilot_spp == auto.LATTICE_PILOT_SPP
    film = made[0].moment_film
    assert film.step == 4 and trials[0].pixel_V.size == film.count and np.all(np.isfinite(trials[0].pixel_V))
    # the denominator: one pilot of image a (v 0.5), one trial render of image b (v 0.25, 1 spp)
    for tr in trials:
        tr.pilot_image, tr.pixel_V, tr.lattice = np.full(film.count, 2.0), np.full(film.count, 1.0), trials[0].lattice
        tr.own_var, tr.pilot_missed, tr.pilot_spp = 0.5, [0.0], 2
    trials[1].image_sum, trials[1].images, trials[1].image_spp = np.full(film.count, 5.0), 1, 1
    den = auto.denominator(trials, rounds=0)
    pilot_w, trial_w = 2 / 0.5, 1 / 0.5         # v: both trials' own_var (rounds=0)
    want = ((pilot_w * 2.0 + trial_w * 5.0) / (pilot_w + trial_w)) ** 2 + auto.DENOM
    np.testing.assert_allclose(den, want, rtol=1e-12)
    # a trial of every other row (auto.add_image): its image counts where it covers a pixel only,
    # the pilot's alone elsewhere (planted: its render count as every pixel's, fails)
    covered = np.arange(film.count) % 2 == 0
    trials[1].image_sum, trials[1].image_count = np.where(covered, 5.0, 0.0), covered.astype(np.float64)
    den = auto.denominator(trials, rounds=0)
    mean = np.where(covered, (pilot_w * 2.0 + trial_w * 5.0) / (pilot_w + trial_w), 2.0)
    np.testing.assert_allclose(den, auto.box3_lattice(mean, *trials[0].lattice) ** 2 + auto.DENOM, rtol=1e-12)


def test_auto_times_a_large_crop_at_fewer_samples_per_pixel(monkeypatch):
    """A timed trial renders TRIAL_SPP samples per pixel of a crop of up to TRIAL_SAMPLES /
    TRIAL_SPP pixels, TRIAL_SAMPLES / pixels (at least 1) in a larger one, over the whole crop
    (a merge's cost depends on its iteration's light vertices: one light subpath per pixel), and
    its seconds per sample per pixel are its kernels' time over those samples per pixel."""
    from bdpt_jit import auto
    spp_of = {(64, 64): 4, (90, 90): 4, (128, 128): 2, (200, 180): 1, (1280, 720): 1}
    for (w, h), want in spp_of.items():
        assert auto.trial_spp(mi.load_dict(_sky_only(w, h)).sensors()[0]) == want, (w, h)
    scene = mi.load_dict(_sky_only(128, 128))
    made, seen = [], {}

    def kernel_seconds(render):
        render()
        seen['samples'] = made[0].last_render_info['samples']
        return 0.012
    monkeypatch.setattr(auto, 'kernel_seconds', kernel_seconds)

    def make(settings):
        made.append(mi.load_dict({'type': 'bdpt', 'max_depth': 3, **settings}))
        return made[-1]
    trial = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    monkeypatch.setattr(auto, '_WARM', set())
    auto.time_trial(make, trial, scene, scene.sensors()[0], 0, auto.trial_spp(scene.sensors()[0]))
    assert seen['samples'] == 2 * 128 * 128
    assert trial.seconds == pytest.approx(0.012 / 2, rel=1e-12) and trial.timed and trial.timings == 2    # (the first: two)


def _sky_box_filter(width, height):
    """_sky_only with a box filter: a sample reaches its own pixel only."""
    desc = _sky_only(width, height)
    desc['sensor']['film']['rfilter'] = {'type': 'box'}
    return desc


def test_a_large_crop_s_trial_traces_every_k_th_row(monkeypatch):
    """auto.trial_stride / BDPTIntegrator.camera_stride: in a crop of more than
    auto.TRIAL_PIXELS pixels a timed trial traces camera samples in every k-th row only (k =
    pixels / TRIAL_PIXELS, rounded up), in every pixel of those rows, with one light subpath a
    camera sample (not one a sample of every pixel) and merging at sqrt(k) times the render's
    radius: pi r^2 N, the light vertices a merge finds and the weights' eta, stay the whole
    crop's. Under a constant sky each light subpath is one ray that escapes, so the counts are
    exact; also from another first row (``trial_row``: the trials of a decision take rows 0, 1,
    ..., k - 1 in turn, so that their images cover the crop), and in passes that hold no row of
    the lattice. Planted: every k-th pixel instead of rows, the light subpaths of every pixel,
    the radius unscaled, a pass without a row rendered, or the first row left at 0: each fails."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, 'TRIAL_PIXELS', 64)
    scene = mi.load_dict(_sky_box_filter(16, 16))        # 256 pixels: k = 4, rows 0, 4, 8, 12
    sensor = scene.sensors()[0]
    assert auto.trial_stride(sensor) == 4 and auto.trial_pixels(sensor) == (256, 64)
    assert auto.trial_stride(mi.load_dict(_sky_only(8, 8)).sensors()[0]) == 1
    assert auto.trial_pixels(mi.load_dict(_sky_only(16, 15)).sensors()[0]) == (240, 64)     # (rows 0, 4, 8, 12)
    assert auto.trial_pixels(mi.load_dict(_sky_only(16, 15)).sensors()[0], 4, 3) == (240, 48)   # (rows 3, 7, 11)
    info = {}
    for k, per_pass, row in ((1, None, 0), (4, None, 0), (4, 7, 0), (4, None, 1), (4, 7, 3)):
        # (7 samples a pass: passes without a row of the lattice)
        integ = mi.load_dict({'type': 'bdpt', 'max_depth': 3, 'technique': 'vcm', 'merge_everywhere': True,
                              'statistics': True, **({'samples_per_pass': per_pass} if per_pass else {})})
        integ.trial_stride, integ.trial_row = k, row
        image = np.array(integ.render(scene, sensor, seed=0, spp=2))[..., 0]
        info[k, per_pass, row] = integ.last_render_info['rays'] | {'radius': integ.last_render_info['merge_radius']}
        rows = np.arange(16) % k == row
        assert np.all(image[rows] > 0) and np.all(image[~rows] == 0), (k, per_pass, row)
    assert info[1, None, 0]['camera_rays'] == info[1, None, 0]['light_rays'] == 2 * 256
    for key in ((4, None, 0), (4, 7, 0), (4, None, 1), (4, 7, 3)):
        assert info[key]['camera_rays'] == info[key]['light_rays'] == 2 * 64, key
    assert info[4, None, 0]['radius'] == pytest.approx(2.0 * info[1, None, 0]['radius'], rel=1e-6)
    for k in (1, 4):        # a cache of half a light subpath a camera sample: of the lattice's samples
        integ = mi.load_dict({'type': 'bdpt', 'max_depth': 3, 'light_paths': 0.5, 'connections': 1,
                              'statistics': True})
        integ.trial_stride = k
        integ.render(scene, sensor, seed=0, spp=2)
        assert integ.last_render_info['rays']['light_rays'] == 2 * 256 // (2 * k), k


def test_a_lattice_trial_s_image_is_unbiased_at_its_rows():
    """A trial of every k-th row (k = 4 on the Cornell box, 16 x 16) traces light subpaths for
    its camera samples only, and each splat stands for k of them (integrator pass_state): light
    tracing's image over the whole crop, and the classic estimator's at the lattice's rows,
    agree with the whole crop's renders (means of 6 renders of 16 spp each way, within 4
    standard errors of their difference), so that the denominator may take them (auto.add_image).
    Planted: the splats not scaled (light tracing a quarter of the light), fails."""
    scene = load_scene('cornell-box.xml', 16, 4)
    rows = np.arange(16) % 4 == 0
    for technique, region in (('lt', slice(None)), ('bdpt', rows)):
        means = {1: [], 4: []}
        for k in (1, 4):
            for seed in range(6):
                integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': technique})
                integ.trial_stride = k
                means[k].append(np.array(integ.render(scene, scene.sensors()[0], seed=seed, spp=16))[region].mean())
        a, b = np.array(means[1]), np.array(means[4])
        se = np.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size)
        assert abs(a.mean() - b.mean()) < 4 * se + 1e-4 * a.mean(), (technique, a.mean(), b.mean(), se)


def test_a_lattice_trial_s_time_is_the_crop_s(monkeypatch):
    """auto.time_trial in a crop of more than TRIAL_PIXELS: the trial's kernels over its
    samples and light subpaths count pixels / traced times, those over the film (its pixels
    times 1 to 64 channels) once (developing the crop's film costs the lattice's render what it
    costs the crop's: auto.lattice_weight); its image joins the denominator's at its rows only
    (auto.add_image: they alone have camera samples); whether its first render counts alone goes
    by its kernels' own time. Planted: every kernel scaled, the image at every row, or the first
    render judged by the crop's time: each fails."""
    from bdpt_jit import auto
    monkeypatch.setattr(auto, 'TRIAL_PIXELS', 64)
    monkeypatch.setattr(auto, '_WARM', set())
    monkeypatch.setattr(auto, '_TRIAL_ROWS', itertools.count(1))       # (this trial from row 1)
    scene = mi.load_dict(_sky_box_filter(16, 16))
    history = [(64, 0.010), (3 * 256, 0.002), (256, 0.001), (128, 0.004)]     # (width, seconds)

    def kernel_seconds(render, weight=None):
        render()
        return sum(t * (weight(size) if weight is not None else 1.0) for size, t in history)
    monkeypatch.setattr(auto, 'kernel_seconds', kernel_seconds)
    w = auto.lattice_weight(256, 64)
    assert [w(size) for size, _ in history] == [4.0, 1.0, 1.0, 4.0]
    trial = auto.Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0))
    trial.pilot_image = np.zeros(256)
    made = []

    def make(settings):
        made.append(mi.load_dict({'type': 'bdpt', 'max_depth': 3, **settings}))
        return made[-1]
    auto.time_trial(make, trial, scene, scene.sensors()[0], 0, 2)
    assert made[-1].trial_stride == 4
    assert trial.seconds == pytest.approx((0.010 * 4 + 0.002 + 0.001 + 0.004 * 4) / 2, rel=1e-12)
    # its image at its rows (under the sky, 0.5 each), those rows' counts one a render
    rows = np.repeat(np.arange(16) % 4 == 1, 16)
    assert trial.renders >= 1 and trial.images == trial.renders
    np.testing.assert_array_equal(trial.image_count, rows * trial.renders)
    np.testing.assert_allclose(trial.image_sum, rows * 0.5 * trial.renders, rtol=1e-6)
    # its first render's kernels ran 0.059 x 64 / 256 s, under auto.ONE_TIMING_S: two timings,
    # as a short first render of the whole crop (the crop's 0.059 s would have counted alone)
    assert trial.timings == 2
