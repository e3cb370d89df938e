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

import mitsuba as mi
import numpy as np
import pytest

import test_mis_partition as tmp
from bdpt_jit.strategies import StrategySet


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
@pytest.mark.parametrize('technique', ['bdpt', 'lt', 'vcm', 'vcm_all'])
@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
@pytest.mark.parametrize('k', [1, 2, 3, 4, 6, 9])
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
