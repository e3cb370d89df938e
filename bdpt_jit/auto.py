"""``technique='auto'`` (issue 22's efficiency-aware choice): the configuration of the estimator
that renders this scene most efficiently, path tracing included, chosen from the second moments
that a pilot render estimates for every candidate at once (moments.py; Grittmann et al.,
"Efficiency-aware multiple importance sampling for bidirectional rendering algorithms",
SIGGRAPH 2022) and each candidate's measured time.

1. The pilot: bdpt's classic estimator under the balance heuristic, PILOT_SPP samples per pixel
   (where the crop has more than moments.MAX_PIXELS, LATTICE_PILOT_SPP, and camera samples only
   in the pixels the moment film keeps: pilot_spp, integrator.lattice_step) with seeds of its own (``seed + TRIAL_SEED``),
   its weights and densities kept per family of sample counts (moments.FamilyMIS). From its samples, per pixel, each candidate's variance of a
   one-sample estimate, V = M - sum_t I_t^2 / n_t (moments.MomentFilm), and the share of the image
   no strategy of the candidate samples (path tracing misses what only light subpaths reach: a
   caustic from a point light, a directional area emitter). Where merging candidates are
   offered the pilot merges everywhere (vcm, merge_everywhere) and predicts the candidate merging
   behind delta vertices only (BEHIND_DELTA) too (moments.FamilyMIS's ``split``), which in a
   scene with media has a pilot of its own merge set.
2. The cost: first pt and the cheapest bidirectional candidate (``probe``) are timed, and where
   no candidate could be chosen over pt even at the probe's time, pt is (``clear_pt``). Else
   the classic estimator, vcm's and three caches are timed where a candidate they decide could
   still be chosen at the least time it could take (``time_points``). A trial renders TRIAL_SPP
   samples per pixel (fewer, at least 1, in a crop of more than TRIAL_SAMPLES / TRIAL_SPP pixels: trial_spp),
   in a crop of more than TRIAL_PIXELS in every k-th row only, its light subpaths and merges
   scaled to match (``trial_stride``);
   t, seconds per sample per pixel, is the time their kernels run (Dr.Jit's kernel
   history: not the time to trace or compile them, which a long render pays once a pass or once). The other caches' t comes from a cost model fitted to the timed caches
   (cost_model), linear in the light subpaths per camera sample and in the connections per
   camera vertex; the best
   candidate by the model is timed too before it is chosen (until the best is a timed one), and
   while the runner-up's efficiency is within CLOSE of the best's, both are timed again, up to
   TIMINGS times, until a candidate's two least timings agree within SETTLED (``settled``); a
   candidate's time is the least of its timings. Where the caller's hooks say the decision's
   share of a time budget is spent (``out_of_time``: passes.RenderHooks.decision_over; the
   command's --time gives it half), no further candidate is timed, and the choice is among the
   timed ones. Another job's load on the cores
   only adds time, and comes in bursts: under a second test worker, single timings of pt's on a
   96 x 96 image ranged over 0.6-2.3 ms a sample per pixel, and a cache was chosen over it.
3. The choice: v = the mean over pixels of V / (I^2 + 0.01) (the relative MSE of one sample per
   pixel; I from the pilots' and the trials' images, filtered, weighted against their noise:
   ``denominator``), the efficiency 1 / (v t), the best candidate of those that miss less than MAX_MISSED
   of the image. No candidate's t is less than pt's: each runs pt's strategies and more, so a
   lower time is the trials' noise. A near tie goes to pt: another candidate must be PREFER_PT
   times as efficient (in the open, a cache of few light subpaths predicts pt's variance to a
   few per cent, and timing noise alone decided between them). The render then runs the chosen
   candidate with the caller's seed and spp.

4. Again as the render goes (segment_spp, rechoose, segment_weights): a long render decides
   again once it has run REDECIDE times as long as its decisions took (then REDECIDE^2 ...),
   from another pilot pooled with the earlier ones, and combines its segments' images with
   inverse-variance weights from the pilots' predictions (docs/light-cache.md).

The choice depends on the pilot's and the trials' samples only, which share none with the render
(``pass_seed`` keeps seeds ``seed + 2^30`` and up apart from the render's passes), so the image
is the chosen candidate's image: unbiased where that candidate is (the issue's second option:
decide from earlier, independent samples). The candidates use the render's own heuristic
(power by default); their variances are predicted under the balance heuristic, which the power
heuristic's differs from by little (Veach's thesis, section 9.2.4)."""

import itertools

import drjit as dr
import mitsuba as mi
import numpy as np

from .stats import drain_kernel_history

TRIAL_SPP = 4                   # the samples per pixel whose time a trial measures (time_trial)
PILOT_SPP = 4                   # the pilot's samples per pixel (even: two halves, moments.py)
LATTICE_PILOT_SPP = 2           # and in a crop larger than the moment film keeps (``pilot_spp``)
TRIAL_SAMPLES = 1 << 15         # a trial's samples at most, where that leaves it at least 1 spp (trial_spp)
TRIAL_PIXELS = 1 << 15          # a trial in a larger crop traces camera samples in every k-th row (trial_stride)
TRIAL_SEED = 1 << 30            # pilot and trial seeds: the render's seed plus this, plus 0, 1, 2, ...
MAX_MISSED = 1e-3               # a candidate that misses more of the image is not chosen
DENOM = 1e-2                    # relative MSE: V / (I^2 + DENOM), as the benchmarks measure it
LIGHT_PATHS = (0.25, 0.5, 1.0, 2.0)     # the caches' light subpaths per camera sample (n_L / n)
CONNECTIONS = (1, 2, 4, 8)              # and cached vertices per camera vertex (c)
TIMED_CACHES = ((0.25, 1), (1.0, 1), (1.0, 4))   # the caches whose time is measured (the cost model's)
MERGING_LIGHT_PATHS = (1.0,)            # the merging caches' n_L / n: where their prediction holds (``candidates``)
TIMED_MERGING = ((1.0, 1),)               # the merging cache whose time is measured (the merges' cost model)
CLOSE = 2.0                     # a runner-up within this factor of the best's efficiency: both timed again
PREFER_PT = 1.1                 # a bidirectional candidate is chosen over pt only if this many times as efficient
TIMINGS = 3                     # the most trial renders a candidate's time is the least of
ONE_TIMING_S = 0.05             # a configuration's first trial render in a process whose kernels ran this long counts alone
SETTLED = 1.1                   # a candidate whose two least timings are within this factor is not timed again
REDECIDE = 16.0                 # the render decides again once it has run this many times as long as
                                # its decisions so far took, then 16 times as long, ... (segments)
MAX_DECISIONS = 4               # decisions in one render at most, the first included
SEGMENT_SEED = 1 << 29          # segment k of a render renders with the caller's seed plus k times this
FIRST_HORIZON = 256             # the spp a render's first decision governs, for its merges' radius (``horizon``)
PER_PIXEL = 1.1                 # a per-pixel candidate is chosen only if this many times as efficient
                                # as the best of the others (its v is the least of noisy estimates per pixel)
BEHIND_DELTA = 'vcm behind delta'     # the classic estimator merging where vcm does by default
MERGE_KEEP = 0.02               # a pixel whose pilot image is this share merges or more keeps merging


class Trial:
    """One candidate, one field a line."""

    def __init__(self, name, settings, counts, cache=None):
        self.name = name                # 'pt', 'bdpt', 'vcm', 'cache NxC' or 'vcm cache NxC'
        self.settings = settings        # its parameters over the caller's
        self.counts = counts            # (n_c, n_lt, n_m) of its MIS [Veach 9.2.2]
        self.cache = cache              # (light_paths, connections) of a cache, or None
        self.merges = counts[2] > 0     # it merges (technique vcm, everywhere unless behind_delta)
        self.behind_delta = settings.get('technique') == 'vcm' and not settings.get('merge_everywhere', False)
        #                                 it merges behind delta vertices only (vcm's default merge set)
        self.own_pilot = False          # behind_delta and predicted by a pilot of its own merge set (``pilot``)
        self.seconds = None             # seconds per sample per pixel: measured (timed) or modelled
        self.timed = False              # its seconds measured by trial renders (not the cost model)
        self.timings = 0                # how many: its seconds are their minimum (a second job's load only adds)
        self.second = None              # the second least of its timings (``settled``)
        self.rel_var = None             # v: predicted relative MSE at one sample per pixel (``normalise``)
        self.missed = None              # the share of the image none of its strategies samples (likewise)
        self.pixel_V = None             # per pixel, the pilots' mean of V, the one-sample variance (pilot)
        self.pilot_image = None         # and of their image (``denominator`` where no trial has rendered)
        self.own_var = None             # v over the pilots' own image (``denominator``'s weights)
        self.pilot_missed = []          # the missed share from each
        self.pilot_spp = PILOT_SPP      # each pilot's samples per pixel (``pilot_spp``)
        self.efficiency = None          # 1 / (v t); 0 where it misses light
        self.pixel_var = None           # v per crop pixel, h x w (the pilots' mean), or per kept pixel of a lattice
        self.lattice = None             # (h, w, step) where the pilots' film keeps every step-th pixel (a large crop)
        self.parts = None               # a per-pixel candidate's caches (per_pixel_trials), else None
        self.pixel_counts = None        # and its pixel_counts.PixelCounts
        self.pick = None                # and per pixel the index of its cache in parts
        self.merge_share = None         # per crop pixel, the share of the pilots' image that merges carried
        self.renders = 0                # its trial renders (``trial_seed``)
        self.image_sum = None           # their images summed (the mean of the colour channels at the
        #                                 pilots' film's pixels: ``add_image``)
        self.images = 0                 # how many
        self.image_count = None         # and per pixel, how many cover it (a large crop's trials: rows, add_image)
        self.image_spp = 0              # their samples per pixel (trial_spp)

    def report(self):
        """The candidate in last_render_info. Its per-pixel maps stay NumPy arrays (copies), not
        lists: Mitsuba's ``mi.render`` hands the integrator to Dr.Jit, which walks the Python
        integrator's attributes, last_render_info included, on every call, element by element in
        a list (at 256 x 256 the per-pixel candidates' lists took 0.56 s of each call; an array
        is one leaf)."""
        out = {'name': self.name, 'settings': self.settings, 'counts': self.counts,
               'seconds_per_spp': self.seconds, 'timed': self.timed, 'timings': self.timings, 'relmse_1spp': self.rel_var,
               'relmse_1spp_over_pilot_image': self.own_var, 'missed': self.missed, 'efficiency': self.efficiency}
        if self.pixel_counts is not None:
            out['pixel_counts'] = {'connections': self.pixel_counts.connections.copy(),
                                   'merges': None if self.pixel_counts.merges is None
                                   else self.pixel_counts.merges.copy()}
        return out


def offers_merging(ctx):
    """Whether merging candidates are offered: where connections exist (merges need a light
    vertex and a camera vertex, as they do) and the scene has a BSDF with a glossy or delta lobe,
    or shapes this test cannot see (instances). Among diffuse surfaces only, a merge samples the
    paths that a connection samples with a density as good, and costs a gather. Not with
    ``strategy_images``: no (s,t) layer holds a merge."""
    from .scene_check import scene_has_lobe
    if not ctx.strategies.trace_connect or ctx.ad or ctx.layers is not None:
        return False
    return scene_has_lobe(ctx.scene, mi.BSDFFlags.Glossy, mi.BSDFFlags.Delta)


def candidates(ctx, vpp, vpp_merging=None):
    """The candidates for the scene of Context ``ctx`` (technique bdpt): path tracing, the
    classic estimator and the light vertex caches of LIGHT_PATHS x CONNECTIONS (where connections
    exist, max_depth >= 3, and not in spectral variants), and where ``offers_merging``, each of
    the bidirectional ones merging everywhere (technique vcm), and in a scene with a delta BSDF
    the classic estimator merging behind delta vertices only (vcm's own merge set, BEHIND_DELTA:
    predicted by the pilot merging everywhere, or in a scene with media by a pilot of that
    merge set: ``pilot``); ``vpp``: the stored vertices per
    light subpath (light_cache.pilot), which a cache's n_c = c / vpp needs, and ``vpp_merging``
    the merging caches' (their light subpaths also store the vertices only a merge can use:
    2.05 against 1.45 on the Cornell box at max_depth 4, and each connection draws among all of
    them; integrator.auto_vertices; default ``vpp``). The merging caches
    take MERGING_LIGHT_PATHS only: at other n_L the prediction misses the merges' covariances
    with the other strategies of their samples, which cancel the merges' own squared mean at
    n_L = 1 only (0.55-0.75 of the renders' v at n_L = 1/4, 1.3 times at 2: docs/light-cache.md,
    twenty-third session); on the caustic auto chose the merging cache 1/4 x 1, which rendered
    1.5 times vcm's error."""
    merging = offers_merging(ctx)
    vcm = {'technique': 'vcm', 'merge_everywhere': True}
    out = [Trial('pt', {'technique': 'pt'}, (0.0, 0.0, 0.0)), Trial('bdpt', {}, (1.0, 1.0, 0.0))]
    if merging:
        out.append(Trial('vcm', vcm, (1.0, 1.0, 1.0)))
    if merging and ctx.has_delta:       # vcm's own merge set: merges behind delta vertices only
        # (merge_everywhere False whatever the caller's: its renders merge as it is predicted)
        out.append(Trial(BEHIND_DELTA, {'technique': 'vcm', 'merge_everywhere': False}, (1.0, 1.0, 1.0)))
        out[-1].own_pilot = ctx.media is not None       # (with media: a pilot of its own, ``pilot``)
    if not ctx.strategies.trace_connect or mi.is_spectral:
        return out
    for m in ((False, True) if merging else (False,)):
        for light_paths in (MERGING_LIGHT_PATHS if m else LIGHT_PATHS):
            for c in CONNECTIONS:
                settings = {**(vcm if m else {}), 'light_paths': light_paths, 'connections': c}
                v = vpp_merging if m and vpp_merging is not None else vpp
                out.append(Trial(f"{'vcm ' if m else ''}cache {light_paths:g}x{c}", settings,
                                 (c / max(v, 1e-3), light_paths, light_paths if m else 0.0),
                                 (light_paths, c)))
    return out


def kernel_seconds(render, weight=None):
    """Seconds the kernels that ``render()`` launches run (Dr.Jit's kernel history): neither
    tracing them in Python nor compiling them, which a long render pays once a pass or once;
    with ``weight``, each kernel's seconds times weight(its width)."""
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    drain_kernel_history()          # (what ran before: its observers', not timed)
    try:
        render()
        dr.sync_thread()
    finally:
        history = drain_kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    if weight is None:
        return sum(k.get('execution_time', 0.0) for k in history) / 1e3
    return sum(k.get('execution_time', 0.0) * weight(k.get('size', 0)) for k in history) / 1e3


def trial_spp(sensor):
    """The samples per pixel of a timed trial: TRIAL_SPP in a crop of up to TRIAL_SAMPLES /
    TRIAL_SPP pixels, fewer in a larger one (TRIAL_SAMPLES / the pixels it traces, at least 1:
    ``trial_stride``)."""
    if sensor is None:
        return TRIAL_SPP
    return int(min(TRIAL_SPP, max(1, TRIAL_SAMPLES // trial_pixels(sensor)[1])))


def trial_stride(sensor):
    """k: a timed trial traces camera samples in every k-th row of a crop of more than
    TRIAL_PIXELS pixels (k = pixels / TRIAL_PIXELS, rounded up), and light subpaths for
    those samples only, merging at sqrt(k) times the radius (integrator.BDPTIntegrator.
    camera_stride): each sample's work is then the whole crop's, whose time it measures (a
    merge finds as many light vertices: pi r^2 N is the render's). A trial of every pixel took
    time in proportion to them, and merging everywhere in proportion to their square (its
    iterations' light vertices within the radius, at a radius fixed in scene units):
    veach-bidir at 1024 x 1024, the merging cache 1 x 1's trial of 1 spp 37 s, the decision
    59-64 s against a 16-spp render of 43 s. Rows, not every k-th pixel: their camera rays are
    as coherent as the crop's (at k = 16 pt's time came out 1.43 times the crop's with rays 16
    pixels apart, 1.30 with rows; the rest was the film's kernels, ``lattice_weight``). Not fewer pixels with
    all their light subpaths: a kernel's fixed cost scaled up with the pixels left out (every
    56th pixel of a 1280 x 720 crop: pt's seconds per spp came out 1.42 times the whole
    image's, vcm's 0.67). 1 in spectral variants (as the pilot's lattice, integrator.lattice_step)."""
    if sensor is None or mi.is_spectral:
        return 1
    pixels = trial_pixels(sensor, 1)[0]
    return 1 if pixels <= TRIAL_PIXELS else -(-pixels // TRIAL_PIXELS)


def trial_pixels(sensor, k=None, row=0):
    """(the crop's pixels, those a trial traces camera samples in: every k-th row from ``row``,
    ``trial_stride``)."""
    from .integrator import camera_lattice
    crop = sensor.film().crop_size()
    w, h = int(crop[0]), int(crop[1])
    k = trial_stride(sensor) if k is None else k
    return w * h, camera_lattice(k, 0, w * h, w, row)[1]


_WARM = set()       # the trial renders (settings, crop, spp) run once in this process (time_trial)
_TRIAL_ROWS = itertools.count()     # a large crop's trials start at rows 0, 1, ..., k - 1 in turn (time_trial)


def time_trial(make, trial, scene, sensor, seed, spp=TRIAL_SPP):
    """The candidate's seconds per sample per pixel (``make(settings)``: an integrator): its
    kernels' time in a render of ``spp`` (trial_spp), the least over its timings. The first
    trial render of a configuration, scene and size in a process is two timings where its
    kernels ran less than ONE_TIMING_S: a short kernel's first run in a fresh process took up to
    twice the time of later ones (the caustic at 128 x 128, 10-25 ms a render: the cache 1 x 1
    23 then 10 ms, 26 then 12), which chose the caches and pt over them in one-shot renders (the
    command's); and a later run is as often the slow one, so both count, the least is the time,
    and two that agree settle it (``settled``: no re-timing in a close call). A longer first
    render counts alone: since the reference cycle of the thirty-third session is gone the two
    agree there (veach-bidir at 256 x 256 in fresh processes, 35-750 ms a render: second over
    first 0.74-1.1, the merging cache's 0.74-0.84), and the second cost a fresh process's
    decision 1.3 s of 4.6-6.9."""
    integ = make(trial.settings) if trial.pixel_counts is None else make(trial.settings, trial.pixel_counts)
    crop = tuple(int(x) for x in sensor.film().crop_size()) if sensor is not None else None
    key = (id(scene), repr(sorted(trial.settings.items())), trial.pixel_counts is not None, crop, spp)
    k = trial_stride(sensor)
    row = next(_TRIAL_ROWS) % k         # (the trials' images cover the crop's rows in turn: ``denominator``)
    pixels, traced = trial_pixels(sensor, k, row) if sensor is not None else (1, 1)
    if k > 1:
        integ.trial_stride, integ.trial_row = k, row

    def render():
        trial.renders += 1
        image = integ.render(scene, sensor, seed=trial_seed(seed, trial.renders - 1), spp=spp)
        add_image(trial, image, spp, k, row)
    measure = (lambda: kernel_seconds(render)) if k == 1 else (lambda: kernel_seconds(render, lattice_weight(pixels, traced)))
    if key not in _WARM:
        _WARM.add(key)
        first = measure()
        add_timing(trial, first / spp)
        if first * traced / pixels >= ONE_TIMING_S:     # (the kernels' own time, not the crop's)
            return
    add_timing(trial, measure() / spp)


def out_of_time(make):
    """Whether the caller's share of a time budget for this decision is spent
    (``make.decision_over``, the render's passes.RenderHooks.decision_ends; absent: never):
    then no further candidate is timed, and the choice is among those timed so far. Asked only
    where a timing would follow, so that True marks the decision cut short (``make.cut_short``,
    which the caller clears before each decision)."""
    over = getattr(make, 'decision_over', None)
    if over is None or not over():
        return False
    make.cut_short = True
    return True


def lattice_weight(pixels, traced):
    """A lattice trial's kernel weights (``trial_stride``): the kernels over its samples and
    light subpaths count pixels / traced times (the whole crop's would have as many more
    lanes), those over the film (its pixels times 1 to 64 channels) once: developing the
    crop's film costs the lattice's render as much as the crop's (veach-bidir at 1024 x 1024,
    k = 16: 5.9 of pt's 42.7 ms of kernels, 94 ms of 630 scaled by k)."""
    film = {pixels * m for m in range(1, 65)}
    scale = pixels / traced
    return lambda size: 1.0 if size in film else scale


def add_timing(trial, t):
    """One timing of ``trial``, ``t`` seconds per spp: its time the least so far, ``second`` the
    second least."""
    t = max(t, 1e-12)
    if trial.timed:
        trial.second = min(max(trial.seconds, t), trial.second or np.inf)
    trial.seconds = t if not trial.timed else min(trial.seconds, t)
    trial.timed = True
    trial.timings += 1


def trial_seed(seed, k):
    """The seed of a trial's render ``k`` (0, 1, ...): odd offsets
    over TRIAL_SEED, where the pilots' are even (``pilot``), so that each render's image is
    independent of the pilots' samples and of the trial's other renders (``denominator``)."""
    return seed + TRIAL_SEED + 2 * k + 1


def add_image(trial, image, spp, rows=1, first=0):
    """Adds the image of one of ``trial``'s renders (``spp`` samples per pixel) to its sum: the
    mean of its colour channels at the pixels the pilots' film keeps (``trial.lattice``), of a
    trial of every ``rows``-th row from row ``first`` (``trial_stride``) at those rows only (its camera samples;
    its light image covers the crop, its splats scaled to stand for every pixel's light
    subpaths, so that its rows' mean is unbiased; weighed in the denominator as the whole
    crop's: its splats' larger variance mattered less there than the pilots' image's weight, which
    V correlates with), each pixel's count in ``image_count``. Not in spectral variants, whose pilots'
    image is the mean over each sample's wavelengths, not the film's RGB; nor before a pilot."""
    if mi.is_spectral or image is None or trial.pilot_image is None:
        return
    a = np.asarray(image, dtype=np.float64)
    covered = np.broadcast_to((np.arange(a.shape[0]) % rows == first)[:, None], a.shape[:2]).reshape(-1)
    a = a.reshape(-1, a.shape[-1])[:, :1 if mi.is_monochromatic else 3].mean(axis=1)
    if trial.lattice is not None:
        a, covered = a[::trial.lattice[2]], covered[::trial.lattice[2]]
    if a.size != trial.pilot_image.size or (trial.images and trial.image_spp != spp):
        return
    a, n = np.where(covered, a, 0.0), covered.astype(np.float64)
    trial.image_sum = a if trial.image_sum is None else trial.image_sum + a
    trial.image_count = n if trial.image_count is None else trial.image_count + n
    trial.images += 1
    trial.image_spp = spp


def denominator(trials, rounds=3):
    """Per pixel (the pilots' film's), I^2 + DENOM of the relative MSE, with I the mean over each
    pixel's 3 x 3 neighbourhood (``box3``) of the pilots' image and the trial renders' images,
    weighted by the inverse of each one's variance (samples per pixel over v; the pilots' image's
    v that of the classic estimator, the pilots' own configuration): the weights from the v over
    the pilots' own image first, then ``rounds`` times from the v over this mean. No weight
    depends on these images (each v is the pilots'), so the mean is unbiased. Not the pilots'
    image alone: a pixel's rare bright pilot sample raised both its V and its I, so that
    heavy-tailed candidates' v came out low (on the caustic, over the pilots' image, the caches
    and bdpt 0.12-0.16 against 0.47-0.57 over a 512-spp reference, the merging ones 0.08-0.12
    against 0.12-0.19: auto chose caches that rendered 2.7 times vcm's error); over nine pixels
    and more samples such a sample is a small part of I. Nor a pixel's samples alone: where it
    partly covers a small bright emitter (veach-mis' lights), a few samples' I is often near 0
    and that pixel's V / I^2 decided every candidate's v; nor the images of a heavy-tailed
    candidate in full, mostly too low (hence the weights)."""
    first = next(tr for tr in trials if tr.pilot_image is not None)
    merging = any(tr.merges and not tr.behind_delta for tr in trials)       # the (first) pilot was vcm's
    pilot = next((tr for tr in trials if tr.name == ('vcm' if merging else 'bdpt')), first)
    timed = [tr for tr in trials if tr.images]
    v = {id(tr): tr.own_var for tr in trials}
    for r in range(rounds + 1):
        if r:
            v = {id(tr): float(np.mean(tr.pixel_V.reshape(-1) / den)) for tr in trials}
        w = first.pilot_spp * len(first.pilot_missed) / positive(v[id(pilot)])
        num, w_sum = w * first.pilot_image, w
        for tr in timed:
            w = tr.image_spp / positive(v[id(tr)])
            count = tr.image_count if tr.image_count is not None else tr.images
            num, w_sum = num + w * tr.image_sum, w_sum + w * count
        image = num / w_sum
        image = box3(image.reshape(first.pixel_V.shape)) if first.lattice is None else box3_lattice(image, *first.lattice)
        den = image.reshape(-1) ** 2 + DENOM
    return den


def positive(x):
    """``x`` where it is a positive finite number, else 1."""
    return x if x is not None and np.isfinite(x) and x > 0 else 1.0


def normalise(trials):
    """Each trial's v (rel_var) and v per pixel (pixel_var) from its pilots' V, over ``denominator``."""
    pilots = [tr for tr in trials if tr.pixel_V is not None]
    if not pilots:
        return
    den = denominator(pilots)
    for tr in pilots:
        tr.pixel_var = tr.pixel_V / den.reshape(tr.pixel_V.shape)
        tr.rel_var = float(np.mean(tr.pixel_var))


def cost_model(trials):
    """The caches' seconds per sample per pixel, t = a + b n_L/n + d c, fitted by least squares to
    the timed caches' times (b, d at least 0: noise must not make a cost negative), for the caches
    not timed; a merging cache's, t + e + g n_L/n (its gathers find more light vertices as n_L
    grows; e, g at least 0), fitted to each timed merging cache's extra time over its cache's t
    (and vcm's over the classic estimator's, n_L/n = 1, where both were timed); where those are
    at one n_L/n (MERGING_LIGHT_PATHS), t + e, e their mean. At first the points are TIMED_CACHES and TIMED_MERGING;
    each cache timed later (the best by the model, before it is chosen) joins them. From the
    first three alone a noisy point set a slope to 0 (on veach-bidir the cache 1 x 4 timed below
    1 x 1, so connections cost nothing), and each cache with more connections was timed in turn
    as the best (8-21 trial renders in a choice there, 2-6 s). No prediction goes below pt's
    and the probe's times (``least_time``: each cache does their work and more; the free
    intercept of a noisy fit can be negative: a 16 x 16 caustic on CI's machine predicted
    -9e-6 s). Without a timed merging cache (``time_points`` found none could win) the merging
    caches keep seconds None."""
    fit = cost_fit(trials)
    if fit is None:
        return
    for tr in trials:
        if tr.cache is not None and not tr.timed and (fit['merging'] or not tr.merges):
            lp, c = tr.cache
            t = fit['a'] + fit['b'] * lp + fit['d'] * c + ((fit['e'] + fit['g'] * lp) if tr.merges else 0.0)
            tr.seconds = max(t, fit['floor'])


def cost_fit(trials):
    """``cost_model``'s fit from the trials timed so far: {'a', 'b', 'd', 'e', 'g' (seconds per
    spp, n_L/n and c as cost_model writes them), 'merging' (whether merging caches are modelled),
    'floor' (no prediction below), 'points' (the timed caches' names)}, or None with fewer than
    three timed caches that do not merge. In last_render_info['auto']['cost_model']."""
    plain = [(tr.cache, tr.seconds) for tr in trials if tr.timed and tr.cache is not None and not tr.merges]
    if len({cache for cache, _ in plain}) < 3:
        return None
    a, b, d = nonnegative_fit([(1.0, lp, c) for (lp, c), _ in plain], [t for _, t in plain], free=1)
    named = {tr.name: tr.seconds for tr in trials if tr.timed}
    extra = [(1.0, named['vcm'] - named['bdpt'])] if 'vcm' in named and 'bdpt' in named else []
    for tr in trials:               # (n_L/n, the merges' extra time)
        if tr.timed and tr.merges and tr.cache is not None:
            lp, c = tr.cache
            extra.append((lp, tr.seconds - (a + b * lp + d * c)))
    e = g = 0.0
    if len({lp for lp, _ in extra}) >= 2:           # merges at two n_L/n at least
        e, g = nonnegative_fit([(1.0, lp) for lp, _ in extra], [x for _, x in extra], free=0)
    elif extra:                                      # at one: a constant
        e = max(float(np.mean([x for _, x in extra])), 0.0)
    return {'a': float(a), 'b': float(b), 'd': float(d), 'e': float(e), 'g': float(g),
            'merging': any(tr.timed and tr.merges and tr.cache is not None for tr in trials),
            'floor': least_time(probe(trials), trials),         # (a free intercept can go below)
            'points': [tr.name for tr in trials if tr.timed and tr.cache is not None]}


def nonnegative_fit(rows, values, free):
    """Least squares y = rows . x with x[j] >= 0 for j >= ``free`` (the first ``free`` of any
    sign): the least residual over the sets of bounded coefficients held at 0 whose solution
    keeps the others non-negative (few coefficients: every set is tried)."""
    A, y = np.asarray(rows, dtype=np.float64), np.asarray(values, dtype=np.float64)
    n = A.shape[1]
    best, out = np.inf, np.zeros(n)
    for mask in range(1 << (n - free)):
        on = [j for j in range(n) if j < free or mask >> (j - free) & 1]
        x = np.zeros(n)
        if on:
            x[on] = np.linalg.lstsq(A[:, on], y, rcond=None)[0]
        if np.all(x[free:] >= 0.0):
            r = float(np.sum((A @ x - y) ** 2))
            if r < best:
                best, out = r, x
    return out


def pilot_spp(sensor):
    """A pilot's samples per pixel: PILOT_SPP, or LATTICE_PILOT_SPP in a crop of more pixels than
    the moment film keeps (moments.MAX_PIXELS). There the pilot traces camera samples in the kept
    pixels only (but in spectral variants: integrator.lattice_step) and every light subpath of the classic estimator, one per sample of every pixel
    (integrator.lattice_pass_state), and its light side is most of its cost: on veach-bidir at
    256 x 256 the pilot merging everywhere took 1.6 s of kernels at 4 spp (the two pilots 1.7 of
    a 4 s choice), where a plain 4-spp render of the same estimator took 2.1 s. Its kept pixels
    still hold 2 MAX_PIXELS camera samples, half of a 128 x 128 pilot's. At 2 spp there: 0.9-1.0 s
    for the two, and veach-bidir's error at 16 s 1.37 times the classic estimator's, from 1.55
    (benchmarks/bench_light_cache.py, three runs each, one invocation each: docs/light-cache.md)."""
    if sensor is None:
        return PILOT_SPP
    from .moments import MAX_PIXELS
    crop = sensor.film().crop_size()
    return PILOT_SPP if int(crop[0]) * int(crop[1]) <= MAX_PIXELS else LATTICE_PILOT_SPP


def pilot(make, trials, scene, sensor, seed, index=0):
    """Pilot render ``index`` (0 for the first decision, 1, 2, ... for the later ones, seeds of
    their own): each trial's predicted relative MSE at one sample per pixel and the share it
    misses (moments.MomentFilm.estimates), pooled with the earlier pilots' (their mean: each
    estimates the same quantities from independent samples)."""
    trials = [tr for tr in trials if tr.parts is None]          # (per-pixel candidates: from these)
    for group, behind_delta in (([tr for tr in trials if not tr.own_pilot], False),
                                ([tr for tr in trials if tr.own_pilot], True)):
        if group:
            pilot_group(make, group, behind_delta, scene, sensor, seed + TRIAL_SEED + 2 * index)
    normalise(trials)


def pilot_counts(trial, split):
    """The counts a pilot predicts ``trial`` with: (n_c, n_lt, n_m), or where the pilot predicts
    both merge sets (``split``) (n_c, n_lt, n_m behind delta vertices, n_m elsewhere)."""
    if not split:
        return trial.counts
    n_c, n_lt, n_m = trial.counts
    return n_c, n_lt, n_m, 0.0 if trial.behind_delta else n_m


def pilot_group(make, trials, behind_delta, scene, sensor, seed):
    """``pilot`` for the trials of one merge set (``behind_delta``: vcm's own, merges behind
    delta vertices only; else everywhere where a trial merges): one pilot render. A pilot
    merging everywhere predicts the trials merging behind delta vertices too (moments.FamilyMIS's
    ``split``: one render fewer, and both merge sets' v from the same samples), save in scenes
    with media (``own_pilot``)."""
    merging = any(tr.merges for tr in trials)
    split = not behind_delta and any(tr.behind_delta for tr in trials)
    settings = {'mis': 'balance'}
    if merging:
        settings.update(technique='vcm', merge_everywhere=not behind_delta)
    integ = make(settings)
    integ.moment_counts = [pilot_counts(tr, split) for tr in trials]
    spp = pilot_spp(sensor)
    integ.render(scene, sensor, seed=seed, spp=spp)
    film = integ.moment_film
    image, V, missed = film.estimates(spp)
    share = film.merged / np.maximum(np.abs(image), 1e-30)      # the merges' part of each pixel
    for k, tr in enumerate(trials):
        tr.pilot_spp = spp
        tr.pilot_missed.append(float(missed[k]))
        tr.missed = float(np.mean(tr.pilot_missed))
        # per pixel, the pilots' mean: an h x w image, or a large crop's kept pixels (moments.MAX_PIXELS)
        shape = (film.pixels.h, film.pixels.w) if film.step == 1 else (film.count,)
        tr.lattice = None if film.step == 1 else (film.pixels.h, film.pixels.w, film.step)
        v, s, n = np.maximum(V[k], 0.0).reshape(shape), share.reshape(shape), len(tr.pilot_missed)
        tr.pixel_V = v if tr.pixel_V is None else tr.pixel_V + (v - tr.pixel_V) / n
        tr.merge_share = s if tr.merge_share is None else tr.merge_share + (s - tr.merge_share) / n
        tr.pilot_image = image if tr.pilot_image is None else tr.pilot_image + (image - tr.pilot_image) / n
        tr.own_var = float(np.mean(tr.pixel_V.reshape(-1) / (tr.pilot_image ** 2 + DENOM)))


def choose(make, ctx, scene, sensor, seed, vpp, vpp_merging=None):
    """The first decision of a render: (the chosen Trial, every Trial); ``vpp``, ``vpp_merging``
    as ``candidates``'."""
    trials = candidates(ctx, vpp, vpp_merging)
    pilot(make, trials, scene, sensor, seed)
    return timed_choice(make, trials, scene, sensor, seed, trial_spp(sensor)), trials


def rechoose(make, trials, scene, sensor, seed, index):
    """Decision ``index`` (1, 2, ...) of a render: another pilot, pooled with the earlier ones,
    and the choice again over the trials as they stand (their timings kept; the best by the
    model and close calls timed as in the first decision; the per-pixel candidates' maps made
    again from the pooled pilots). Returns the chosen Trial."""
    pilot(make, trials, scene, sensor, seed, index)
    return timed_choice(make, trials, scene, sensor, seed, trial_spp(sensor))


def timed_choice(make, trials, scene, sensor, seed, spp):
    """The choice after the pilots: pt where it is clear (``clear_pt``); else the cost-model
    points and candidates that could still win timed (``time_points``: of the classic
    estimator, vcm's, BEHIND_DELTA's, TIMED_CACHES and TIMED_MERGING), the cost model, the
    per-pixel candidates (made again from the pilots so far) and ``decide``. Returns the chosen
    Trial; ``trials`` gets the per-pixel ones."""
    if clear_pt(make, trials, scene, sensor, seed, spp):
        return trials[0]
    trials[:] = [tr for tr in trials if tr.parts is None]
    time_points(make, trials, scene, sensor, seed, spp)
    normalise(trials)               # over the trials' images (``denominator``)
    cost_model(trials)
    trials[:] = [tr for tr in trials if tr.parts is None] + per_pixel_trials(trials)
    return decide(make, trials, scene, sensor, seed, spp)


def time_points(make, trials, scene, sensor, seed, spp):
    """Times the trials of the groups of ``point_groups`` that could still give the choice, one
    trial at a time, from the group of the highest bound, in the group's order: a group whose
    bound is at most the best score among the trials timed so far (``score``) is not timed
    further (a bound falls as the least times rise, and a timed trial's score rises as its time
    falls; the v of each is the one it has when the group is weighed: the trials' images move
    the denominator, ``normalise``, by a few per cent, which could make a group left out
    competitive again, and is accepted). On veach-bidir vcm's trial (0.6 s a sample per pixel at 256 x 256, 3.6 times the
    time of vcm behind delta, with v 0.47 against its 0.32) could not win and was timed in every
    decision: now the classic estimator's time (vcm's least) leaves it out."""
    while True:
        best = max((score(tr, trials[0]) for tr in trials if tr.timed), default=0.0)
        todo = [(bound, group) for bound, group in point_groups(trials)
                if bound > best and any(not tr.timed for tr in group)]
        if not todo or out_of_time(make):
            return
        group = max(todo, key=lambda x: x[0])[1]
        time_trial(make, next(tr for tr in group if not tr.timed), scene, sensor, seed, spp)
        normalise(trials)


def point_groups(trials):
    """[(a bound on the score of the candidates a group's timings decide, the group)]: the
    classic estimator's trial; vcm's and BEHIND_DELTA's, each after the classic estimator's (its
    time is their least); the plain caches of TIMED_CACHES (the cost model's points: every
    cache's and every per-pixel candidate's time); and where merging caches are offered,
    TIMED_MERGING (the merges' extra time, one constant while the merging caches are offered at
    one n_L/n, MERGING_LIGHT_PATHS: one point; a second, 1 x 4, cost veach-bidir's decisions at
    256 x 256 0.6 s of 3.3 s. Not vcm's over the classic estimator's,
    which on veach-bidir at 256 x 256 cost 0.46-0.62 s a spp against the merging cache 1 x 1's
    ~0.3, and the classic estimator's besides). Each bound is
    the score at the least time the candidate could take (``least_time``), a per-pixel
    candidate's from the mean of the least v per pixel over the caches (over PER_PIXEL)."""
    pt = trials[0]
    named = {tr.name: tr for tr in trials}
    caches = [tr for tr in trials if tr.cache is not None]
    out = [(upper(named[name], least_time(named[name], trials), pt), [named['bdpt'], named[name]])
           for name in ('bdpt', 'vcm', BEHIND_DELTA) if name in named]
    if caches:
        pixel = per_pixel_bound(caches, least_time(probe(trials), trials))
        bound = {tr.name: upper(tr, least_time(tr, trials), pt) for tr in caches}
        plain = [tr for tr in caches if not tr.merges and tr.cache in TIMED_CACHES]
        out.append((max(list(bound.values()) + [pixel]), plain))
        merging = [tr for tr in caches if tr.merges]
        if merging:
            point = [tr for point in TIMED_MERGING for tr in merging if tr.cache == point]
            out.append((max([bound[tr.name] for tr in merging] + [pixel]), point))
    return out


def least_time(trial, trials):
    """The least seconds per spp ``trial`` could take, from the timed ones: pt's and the probe's
    (``probe``: each bidirectional candidate does its work and more); for vcm's and
    BEHIND_DELTA's the classic estimator's too (they merge besides), and for a merging cache the
    merging cache of the fewest light subpaths and one connection's."""
    named = {tr.name: tr for tr in trials}
    t = max((named['pt'].seconds or 0.0) if 'pt' in named else 0.0, probe(trials).seconds or 0.0)
    if trial.merges:
        least = named.get('bdpt') if trial.cache is None else \
            next((tr for tr in trials if tr.merges and tr.cache == (min(MERGING_LIGHT_PATHS), 1)), None)
        if least is not None and least.timed:
            t = max(t, least.seconds)
    return t


def ok(trial):
    """Whether ``trial`` can be chosen: a predicted v, and it misses less than MAX_MISSED."""
    return trial.rel_var is not None and trial.missed is not None and trial.missed < MAX_MISSED


def upper(trial, t, pt):
    """``trial``'s score (``score``) if it took ``t`` seconds per spp; 0 where it cannot be chosen."""
    if not ok(trial):
        return 0.0
    t_pt = (pt.seconds or 0.0) if pt is not None else 0.0
    return 1.0 / max(trial.rel_var * max(t, t_pt), 1e-30) * (PREFER_PT if trial is pt else 1.0)


def score(trial, pt):
    """What the choice ranks (``ranked``): the efficiency 1 / (v max(t, pt's t)), pt's counted
    PREFER_PT times, a per-pixel candidate's over PER_PIXEL; 0 where it cannot be chosen."""
    return upper(trial, trial.seconds, pt) / (PER_PIXEL if trial.parts is not None else 1.0)


def per_pixel_bound(caches, t):
    """The score a per-pixel candidate of ``caches`` could have at ``t`` seconds per spp: the
    mean over pixels of the least v per pixel (over PER_PIXEL); 0 without per-pixel v."""
    maps = [tr.pixel_var for tr in caches if ok(tr) and tr.pixel_var is not None]
    if not maps:
        return 0.0
    least = float(np.mean(np.min(np.stack(maps), axis=0)))
    return 1.0 / max(least * t, 1e-30) / PER_PIXEL


def probe(trials):
    """The bidirectional candidate that takes the least time: the cache of the fewest light
    subpaths and one connection, not merging (each other candidate does its work and more: more
    light subpaths, connections or merges, or the classic estimator's light subpath per sample
    with all its connections), or the classic estimator where there are no caches."""
    lp = min(LIGHT_PATHS)
    return next((tr for tr in trials if tr.cache == (lp, 1) and not tr.merges), trials[1])


def clear_pt(make, trials, scene, sensor, seed, spp):
    """Whether pt (``trials[0]``) is the choice without timing the others: with pt and ``probe``
    timed (the probe until ``settled``: load only adds time, and a probe timed too long would
    make every bound too low), no candidate could be chosen over pt even if it took the probe's
    time, the least a bidirectional one takes: for each, 1 / (v max(t_probe, t_pt)) below
    PREFER_PT / (v_pt t_pt), and for the per-pixel candidates (per_pixel_trials), whose v is
    a mean over pixels of some cache's v there, the mean of the least v per pixel, their
    efficiency over PER_PIXEL (``ranked``). On the Cornell box and veach-mis this leaves out 4-8 of
    the 7-11 trial renders of a decision. The candidates not timed keep seconds and efficiency
    None."""
    pt, cheap = trials[0], probe(trials)
    renders = pt.renders + cheap.renders
    for tr in (pt, cheap):
        if not tr.timed:
            time_trial(make, tr, scene, sensor, seed, spp)
    while not settled(cheap) and not out_of_time(make):
        time_trial(make, cheap, scene, sensor, seed, spp)
    if pt.renders + cheap.renders > renders:       # new images for the denominator (pilot: the pilots')
        normalise(trials)
    if not ok(pt):
        return False
    for tr in (pt, cheap):          # (reported; ``ranked``'s)
        tr.efficiency = upper(tr, tr.seconds, pt) / (PREFER_PT if tr is pt else 1.0) if tr.rel_var is not None else None
    return max((bound for bound, _ in point_groups(trials)), default=0.0) <= score(pt, pt)


def box3(a):
    """The mean over each pixel's 3 x 3 neighbourhood (edges repeated)."""
    p = np.pad(a, 1, mode='edge')
    h, w = a.shape
    return sum(p[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


def box3_lattice(a, h, w, step):
    """box3 over the kept pixels of a large crop (moments.MomentFilm keeps raster pixel j step,
    ``a[j]``): the mean over the kept pixels nearest to the rows above, at and below each one
    (edges repeated), and each of those with its kept neighbours in raster order (step pixels to
    either side, the row before or after at a row's ends)."""
    count = len(a)
    x, y = np.arange(count) * step % w, np.arange(count) * step // w
    out = np.zeros(count)
    for dy in (-1, 0, 1):
        near = np.minimum(np.rint((np.clip(y + dy, 0, h - 1) * w + x) / step).astype(np.int64), count - 1)
        for dj in (-1, 0, 1):
            out += a[np.clip(near + dj, 0, count - 1)]
    return out / 9.0


def expand(pick, lattice):
    """A per-pixel ``pick`` over the crop (h x w): as it is, or from a large crop's kept pixels
    (``lattice``: (h, w, step)), each pixel taking its nearest kept pixel's in raster order (step / 2
    pixels away or less, in its row but at a row's ends)."""
    if lattice is None:
        return pick
    h, w, step = lattice
    near = np.minimum(np.rint(np.arange(h * w) / step).astype(np.int64), len(pick) - 1)
    return pick[near].reshape(h, w)


def assign(parts, rounds=8):
    """Per pixel, the index of the cache in ``parts`` for a per-pixel candidate: the least
    (mean v) (mean t) over the image is where each pixel takes the least v(p) + lambda t with
    lambda = mean v / mean t of the assignment (the Lagrangian of the product; a pixel's own
    v(p) t would let the few pixels that hold most of the variance decide nothing and the many
    others buy small gains at full cost); lambda from the best cache's, then refined, keeping
    the best assignment met (the fixed point is a necessary condition only). v filtered over
    each pixel's 3 x 3 neighbourhood. Where merges carried MERGE_KEEP of the pilots' image or
    more (filtered alike), only merging caches: there the other strategies sample those paths
    poorly, and a pixel's few pilot samples may show none of the rare paths that only merges
    render well (on the volumetric caustic, without this rule, the per-pixel candidate left
    merges out behind the glass and rendered twice vcm's error at vcm's speed). A large crop's
    per kept pixel (``box3_lattice``; per_pixel_trials expands the result)."""
    lattice = parts[0].lattice
    smooth = box3 if lattice is None else (lambda a: box3_lattice(a, *lattice))    # noqa: E731
    fv = np.stack([smooth(tr.pixel_var) for tr in parts])
    t = np.array([max(tr.seconds, 1e-12) for tr in parts])
    share = parts[0].merge_share
    if share is not None and any(tr.merges for tr in parts):     # merges kept where they carry the image
        keep = smooth(np.clip(share, 0.0, 1.0)) > MERGE_KEEP
        nonmerging = np.array([not tr.merges for tr in parts]).reshape((-1,) + (1,) * keep.ndim)
        fv = np.where(nonmerging & keep[None], np.inf, fv)

    def product(pick):
        return np.mean(np.take_along_axis(fv, pick[None], 0)) * np.mean(t[pick])
    k = int(np.argmin(fv.reshape(len(parts), -1).mean(axis=1) * t))
    best = np.full(fv.shape[1:], k)             # the best cache everywhere, then refined
    pick = best
    for _ in range(rounds):
        lam = np.mean(np.take_along_axis(fv, pick[None], 0)) / np.mean(t[pick])
        pick = np.argmin(fv + lam * t.reshape((-1,) + (1,) * (fv.ndim - 1)), axis=0)
        if product(pick) < product(best):
            best = pick
    return best


def per_pixel_trials(trials):
    """For each light_paths, the candidate that renders every pixel with the cache of that
    light_paths (connections c, merging or not) whose v t is least there, v filtered over the
    pixel's 3 x 3 neighbourhood (the pilots' few samples a pixel alone are too noisy to decide
    on) and the image's time in the balance (``assign``); its v the mean over pixels of the
    chosen caches' (unfiltered), its t the mean of their t (the cost model is linear in c and in
    the merges). In a crop larger than the moment film keeps, chosen per kept pixel and
    expanded to every pixel (``expand``). None where every pixel takes the same cache (the
    global candidate)."""
    from .pixel_counts import PixelCounts
    out = []
    for lp in LIGHT_PATHS:
        parts = [tr for tr in trials if tr.cache is not None and tr.cache[0] == lp and tr.pixel_var is not None
                 and tr.seconds is not None]
        if len(parts) < 2:
            continue
        pick = assign(parts)
        if np.all(pick == pick.flat[0]):
            continue
        full = expand(pick, parts[0].lattice)
        merges = np.array([tr.merges for tr in parts])[full]
        counts = PixelCounts(np.array([tr.cache[1] for tr in parts])[full], merges if merges.any() else None)
        vcm = {'technique': 'vcm', 'merge_everywhere': True} if merges.any() else {}
        per_c = parts[0].counts[0] / parts[0].cache[1]         # n_c per connection: 1 / (V / n_L)
        tr = Trial(f"{'vcm ' if vcm else ''}cache {lp:g}x per pixel", {**vcm, 'light_paths': lp, 'connections': 1},
                   (counts.mean_connections() * per_c, lp, lp * counts.merge_share()))
        tr.parts, tr.pixel_counts, tr.pick = parts, counts, pick
        tr.rel_var = float(np.mean(np.choose(pick, [p.pixel_var for p in parts])))
        tr.missed = max(p.missed for p in parts)
        out.append(tr)
    return out


def decide(make, trials, scene, sensor, seed, spp):
    """The most efficient trial (ranked), timing the best by the cost model before it is chosen
    and both of a close call again (up to TIMINGS each); once ``out_of_time``, the most
    efficient of the trials timed so far."""
    while True:
        cost_model(trials)              # again after each timing: its points' times may have fallen
        for tr in trials:               # a per-pixel candidate's t: the mean of its pixels' caches'
            if tr.parts is not None and not tr.timed:
                tr.seconds = float(np.mean(np.array([p.seconds for p in tr.parts])[tr.pick]))
        best, runner = ranked(trials)
        close = runner is not None and runner.efficiency * CLOSE > best.efficiency \
            and not (settled(best) and settled(runner))
        if (close or not best.timed) and out_of_time(make):
            return ranked([tr for tr in trials if tr.timed])[0]
        if not best.timed:          # the best by the model is timed before it is chosen
            time_trial(make, best, scene, sensor, seed, spp)
        elif close:
            for tr in (best, runner):       # a close call: both timed again (the least of their times)
                if not settled(tr):
                    time_trial(make, tr, scene, sensor, seed, spp)
        else:
            return best


def settled(trial):
    """Whether a close call times ``trial`` no more: TIMINGS timings, or two that agree within
    SETTLED (another job's load comes in bursts, which seldom lengthen two timings alike; on the
    Cornell box pt's agree within 3%, and a third cost a choice ~5% of its time)."""
    return trial.timings >= TIMINGS or (trial.second is not None and trial.second <= SETTLED * trial.seconds)


def segment_spp(best, render_s, decided_s, spp_left, index, seconds=None):
    """The samples per pixel the render takes with ``best`` before decision ``index`` (1, 2, ...),
    or all of ``spp_left`` where there is none: the render re-decides once it has run REDECIDE
    ** index times as long as its decisions so far took (``decided_s``; ``render_s`` rendered so
    far), by ``seconds`` per spp (the render's own, where it has rendered with ``best``; else the
    trials' kernel time, which leaves out each pass's Python time: the segment then runs
    longer); not where that leaves less than REDECIDE times a decision's cost to render after
    it, nor past MAX_DECISIONS."""
    seconds = seconds or best.seconds
    if index >= MAX_DECISIONS or not seconds:
        return spp_left
    n = int(max(REDECIDE ** index * decided_s - render_s, 0.0) / max(seconds, 1e-12)) + 1
    cost = decided_s / index                    # a decision's mean cost so far
    if (spp_left - n) * seconds < REDECIDE * cost:
        return spp_left
    return n


def horizon(spp_left, done):
    """The samples per pixel a decision governs, ``done`` rendered and ``spp_left`` to come (its
    merges are predicted at their radius there:
    ``pilot_iteration``): the render's samples left, at most the segment the decision starts.
    A first segment runs REDECIDE times as long as its decision took (``segment_spp``), and a
    decision costs about 16 spp of rendering wherever the image's size (two 4-spp pilots, which
    cost more a sample than a render, and 8-13 trial renders of 1-4 spp: 4-6 s against 0.16 s a
    spp on veach-bidir at 256 x 256, 0.4-0.8 s against 0.025-0.04 on the Cornell box), so
    FIRST_HORIZON = 16 REDECIDE; a later segment runs about REDECIDE - 1 times as long as the
    render so far, so (REDECIDE - 1) ``done`` samples."""
    return max(1, min(spp_left, max(FIRST_HORIZON, int((REDECIDE - 1) * done))))


def pilot_iteration(done, h, alpha):
    """The merging iteration count a decision's pilots and trials start from (their first
    iteration is this plus 1: merge.MergeSchedule), ``done`` iterations rendered and ``h`` to
    come (``horizon``): the iteration whose eta is the harmonic mean of the etas of iterations
    done + 1 .. done + h. eta_i = pi r_i^2 N falls as i^(alpha - 1), a merge's variance grows as
    1 / eta_i, and a segment's variance is the mean of its iterations': predicted at its
    first iteration's radius instead, the merging caches of few light subpaths came out best on
    the caustic at 256 x 256 (v 1.24-1.34 times vcm's over 1.44-1.64 at iteration 64-700, about
    2 rendered: nineteenth session) and rendered 1.6 times vcm's error at equal time. The mean
    of i^(1 - alpha) by its integral over (done + 1/2, done + h + 1/2)."""
    if alpha >= 1.0 or h <= 1:
        return done
    p = 1.0 - alpha
    lo, hi = done + 0.5, done + h + 0.5
    mean = (hi ** (1.0 + p) - lo ** (1.0 + p)) / ((1.0 + p) * h)
    return max(done, int(round(mean ** (1.0 / p))) - 1)


def segment_weights(segments):
    """The weights of a render's segments [(Trial, samples per pixel rendered)] in the image:
    inverse variance, n_k / v_k with v_k the pooled pilots' prediction for the segment's
    candidate, normalised to sum 1 (a segment of n_k samples per pixel has variance v_k / n_k).
    The pilots share no sample with the segments, so the weights are independent of the images
    they weight, and the combination is unbiased where each segment's candidate is; equal
    candidates get weights in proportion to their samples, as one render of all of them."""
    v = [tr.rel_var if tr.rel_var is not None and np.isfinite(tr.rel_var) and tr.rel_var > 0 else None
         for tr, _ in segments]
    if any(x is None for x in v):
        v = [1.0] * len(segments)
    w = [n / x for (_, n), x in zip(segments, v)]
    total = sum(w)
    return [x / total for x in w]


def ranked(trials):
    """Each trial's efficiency, 1 / (v max(t, pt's t)) (0 where it misses more than MAX_MISSED;
    None where it has no time: neither timed nor modelled, ``time_points``): (the best by
    ``score``; the runner-up or None)."""
    pt = next((tr for tr in trials if tr.name == 'pt' and tr.seconds is not None), None)
    known = [tr for tr in trials if tr.seconds is not None]
    for tr in trials:
        tr.efficiency = None if tr.seconds is None else upper(tr, tr.seconds, pt) / (PREFER_PT if tr is pt else 1.0)
    order = sorted(known, key=lambda tr: -score(tr, pt))
    return order[0], (order[1] if len(order) > 1 and order[1].efficiency > 0 else None)
