"""``technique='auto'`` (issue 22's efficiency-aware choice): the configuration of the estimator
that renders this scene most efficiently, path tracing included, chosen from the second moments
that a pilot render estimates for every candidate at once (moments.py; Grittmann et al.,
"Efficiency-aware multiple importance sampling for bidirectional rendering algorithms",
SIGGRAPH 2022) and each candidate's measured time.

1. The pilot: bdpt's classic estimator under the balance heuristic, PILOT_SPP samples per pixel
   with seeds of its own (``seed + TRIAL_SEED``), its weights and densities kept per family of
   sample counts (moments.FamilyMIS). From its samples, per pixel, each candidate's variance of a
   one-sample estimate, V = M - sum_t I_t^2 / n_t (moments.MomentFilm), and the share of the image
   no strategy of the candidate samples (path tracing misses what only light subpaths reach: a
   caustic from a point light, a directional area emitter).
2. The cost: each candidate renders TRIAL_SPP samples per pixel twice (the first compiles its
   kernels and is not timed); t is the second's seconds per sample per pixel.
3. The choice: v = the mean over pixels of V / (I^2 + 0.01) (the relative MSE of one sample per
   pixel), the efficiency 1 / (v t), the best candidate of those that miss less than MAX_MISSED
   of the image. The render then runs it with the caller's seed and spp.

The choice depends on the pilot's and the trials' samples only, which share none with the render
(``pass_seed`` keeps seeds ``seed + 2^30`` and up apart from the render's passes), so the image
is the chosen candidate's image: unbiased where that candidate is (the issue's second option:
decide from earlier, independent samples). The candidates use the render's own heuristic
(power by default); their variances are predicted under the balance heuristic, which the power
heuristic's differs from by little (Veach's thesis, section 9.2.4)."""

import time

import mitsuba as mi
import numpy as np

TRIAL_SPP = 2                   # samples per pixel of each timed trial render
PILOT_SPP = 4                   # the pilot's samples per pixel (even: two halves, moments.py)
TRIAL_SEED = 1 << 30            # pilot and trial seeds: the render's seed plus this, plus 0, 1, 2, ...
MAX_MISSED = 1e-3               # a candidate that misses more of the image is not chosen
DENOM = 1e-2                    # relative MSE: V / (I^2 + DENOM), as the benchmarks measure it

# (name, parameters over the caller's, the counts (c, light_paths): n_c = c / (V / n_L), n_lt =
# light_paths; path tracing connects and splats nothing, the classic estimator has both 1)
CANDIDATES = (
    ('pt', {'technique': 'pt'}, (0, 0.0)),
    ('bdpt', {}, None),
    ('cache 0.25x1', {'light_paths': 0.25, 'connections': 1}, (1, 0.25)),
    ('cache 1x1', {'light_paths': 1.0, 'connections': 1}, (1, 1.0)),
    ('cache 1x4', {'light_paths': 1.0, 'connections': 4}, (4, 1.0)),
)


class Trial:
    """One candidate, one field a line."""

    def __init__(self, name, settings, counts):
        self.name = name                # the candidate's name (CANDIDATES)
        self.settings = settings        # its parameters over the caller's
        self.counts = counts            # (n_c, n_lt) of its MIS [Veach 9.2.2]
        self.seconds = None             # wall time of one timed trial render
        self.rel_var = None             # v: predicted relative MSE at one sample per pixel
        self.missed = None              # the share of the image none of its strategies samples
        self.efficiency = None          # 1 / (v t), t per sample per pixel; 0 where it misses light

    def report(self):
        return {'name': self.name, 'settings': self.settings, 'counts': self.counts,
                'seconds_per_spp': self.seconds / TRIAL_SPP, 'relmse_1spp': self.rel_var,
                'missed': self.missed, 'efficiency': self.efficiency}


def candidates(ctx, vpp):
    """The candidates for the scene of Context ``ctx`` (technique bdpt); ``vpp``: the stored
    vertices per light subpath (light_cache.pilot), which the caches' n_c = c / vpp needs."""
    out = []
    for name, settings, cache in CANDIDATES:
        if cache is None:
            counts = (1.0, 1.0)
        elif not ctx.strategies.trace_connect or mi.is_spectral:
            continue            # no connection to draw (max_depth < 3), or a spectral variant (no cache)
        else:
            c, light_paths = cache
            counts = (c / max(vpp, 1e-3), light_paths)
        out.append(Trial(name, settings, counts))
    return out


def time_trial(make, trial, scene, sensor, seed):
    """The candidate's seconds per render of TRIAL_SPP (``make(settings)``: an integrator)."""
    integ = make(trial.settings)
    for k in range(2):
        t0 = time.perf_counter()
        integ.render(scene, sensor, seed=seed + TRIAL_SEED + 1 + k, spp=TRIAL_SPP)
        trial.seconds = time.perf_counter() - t0


def pilot(make, trials, scene, sensor, seed):
    """The pilot render: each trial's predicted relative MSE at one sample per pixel and the
    share it misses (moments.MomentFilm.estimates)."""
    integ = make({'mis': 'balance'})
    integ.moment_counts = [tr.counts for tr in trials]
    integ.render(scene, sensor, seed=seed + TRIAL_SEED, spp=PILOT_SPP)
    image, V, missed = integ.moment_film.estimates(PILOT_SPP)
    denom = image ** 2 + DENOM
    for k, tr in enumerate(trials):
        tr.rel_var = float(np.mean(np.maximum(V[k], 0.0) / denom))
        tr.missed = float(missed[k])


def choose(make, ctx, scene, sensor, seed, vpp):
    """(the chosen Trial, every Trial)."""
    trials = candidates(ctx, vpp)
    pilot(make, trials, scene, sensor, seed)
    for tr in trials:
        time_trial(make, tr, scene, sensor, seed)
        ok = tr.missed < MAX_MISSED
        tr.efficiency = 1.0 / max(tr.rel_var * tr.seconds / TRIAL_SPP, 1e-30) if ok else 0.0
    best = max(trials, key=lambda tr: tr.efficiency)
    return best, trials
