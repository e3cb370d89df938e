"""``technique='auto'`` (a first part of issue 22's efficiency-aware choice): the configuration
of bdpt's estimator that renders this scene most efficiently, chosen from trial renders.

Each candidate (CANDIDATES: the classic bdpt estimator and light vertex caches of light_paths x
connections, every one with all of bdpt's strategies) renders three trial images of
TRIAL_SPP samples per pixel with seeds of their own: the first compiles its kernels and is not
timed; the other two give the candidate's time per render t and its variance per pixel,
(I_2 - I_3)^2 / 2, whose mean relative to the pooled trial image M (over pixels and channels,
/ (M^2 + 0.01)) is v, the relative MSE of one trial render. The efficiency is 1 / (v t); the
render then runs the best candidate with the caller's seed and spp. The choice depends on the
trial renders only, which share no sample with the render (their seeds are ``seed + 2^30`` and
up: ``pass_seed`` keeps them apart from the render's passes), so the image is that candidate's
image: unbiased where bdpt is. This is a cost, not the paper's moment estimation from the render's
own samples (Grittmann et al. 2022): the trials are wasted work, and a candidate's heavy tails
(fireflies no trial met) are invisible to them.

Path tracing (technique pt) is not a candidate: trial renders cannot see its heavy tails. On
scenes/indirect-room.xml (32x32, max_depth 8) two trial renders of 2 spp put pt's relative MSE
at one sample per pixel at 1.9 (bdpt's 1.2) and chose it, where path's measured relMSE at 314
spp, 2.49 (docs/results.md), is ~780 at one: bdpt is 12x more efficient there. Choosing pt needs
the paper's moment estimates from the bidirectional samples (every strategy's density at each
path), which is left to do; pt also renders another image where light subpaths alone sample some
paths (mirrors and glass before a point light, directionalarea emitters)."""

import time

import numpy as np

TRIAL_SPP = 2                   # samples per pixel of each trial render
TRIAL_SEED = 1 << 30            # trial seeds: the render's seed plus this, plus 0, 1, 2, ...

CANDIDATES = (
    ('bdpt', {}),
    ('cache 0.25x1', {'light_paths': 0.25, 'connections': 1}),
    ('cache 1x1', {'light_paths': 1.0, 'connections': 1}),
    ('cache 1x4', {'light_paths': 1.0, 'connections': 4}),
)


class Trial:
    """One candidate's trial, one field a line."""

    def __init__(self, name, settings):
        self.name = name                # the candidate's name (CANDIDATES)
        self.settings = settings        # its parameters over the caller's
        self.seconds = None             # wall time of one trial render (the timed two's mean)
        self.sq_diff = None             # (I_2 - I_3)^2 / 2 per pixel and channel
        self.mean = None                # the mean of its three trial images
        self.rel_var = None             # v: relative MSE of one trial render
        self.efficiency = None          # 1 / (v t)

    def report(self):
        return {'name': self.name, 'settings': self.settings, 'seconds_per_spp': self.seconds / TRIAL_SPP,
                'relmse_1spp': self.rel_var * TRIAL_SPP, 'efficiency': self.efficiency}


def candidates(ctx):
    """The candidates for the scene of Context ``ctx`` (built with technique bdpt)."""
    out = []
    for name, settings in CANDIDATES:
        if 'light_paths' in settings and not ctx.strategies.trace_connect:
            continue            # no connection to draw (max_depth < 3): the cache is the classic
        out.append(Trial(name, settings))
    return out


def run_trial(make, trial, scene, sensor, seed):
    """The three trial renders of one candidate (``make(settings)``: a bdpt integrator)."""
    integ = make(trial.settings)
    imgs, times = [], []
    for k in range(3):
        t0 = time.perf_counter()
        img = np.array(integ.render(scene, sensor, seed=seed + TRIAL_SEED + k, spp=TRIAL_SPP), np.float64)
        times.append(time.perf_counter() - t0)
        imgs.append(img[:, :, :3])
    trial.seconds = 0.5 * (times[1] + times[2])
    trial.sq_diff = 0.5 * (imgs[1] - imgs[2]) ** 2
    trial.mean = sum(imgs) / 3.0


def choose(make, ctx, scene, sensor, seed):
    """(the chosen Trial, every Trial) after the trial renders."""
    trials = candidates(ctx)
    for tr in trials:
        run_trial(make, tr, scene, sensor, seed)
    pooled = sum(tr.mean for tr in trials) / len(trials)
    denom = pooled ** 2 + 1e-2
    for tr in trials:
        tr.rel_var = float(np.mean(tr.sq_diff / denom))
        tr.efficiency = 1.0 / max(tr.rel_var * tr.seconds, 1e-30)
    best = max(trials, key=lambda tr: tr.efficiency)
    return best, trials
