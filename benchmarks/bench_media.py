"""Equal time with participating media (issue 23's figures): `bdpt` against Mitsuba's `volpath` and
`volpathmis` on a volumetric caustic (a small light above a glass sphere in fog,
scenes/media/volumetric-caustic.xml) and on the same fog without the glass (scenes/media/fog.xml):
relative MSE against time.

    python benchmarks/bench_media.py --scenes caustic,fog --res 32 --budget 16 --repeats 2 \\
        --integrators volpath,volpathmis,bdpt --ref-integrator bdpt --ref-spp 16384

Issue 23's targets: at 16 s, bdpt's relMSE <= 0.05 x volpath's on the caustic and <= 1.0 x on the
fog. For each scene: a reference (``--ref-integrator`` at ``--ref-spp``, in batches of 64; cached
in ``--cache-dir``), then each integrator renders one warm-up image (compilation), then batches of
``--batch-spp`` until ``--budget`` seconds, its running mean's relMSE taken at the checkpoints
budget/8, budget/4, budget/2 and budget (``--repeats`` runs with seeds of their own, medians
reported; the ratio to volpath is taken at the same checkpoint, the time column says when each
was reached). ``--region no-delta`` measures only the pixels that do not see glass (the caustic
cone in the fog, not the caustic seen through the sphere, which no connection renders).
relMSE = mean((I - R)^2 / (R^2 + 1e-2)) over pixels and channels (as bench_light_cache.py). The
reference's own error is part of every figure; it is estimated from the reference's two halves
(independent seeds) and printed, and each figure is also given less it (as bench_light_cache.py).
On the caustic, `volpath` and `volpathmis`
converge slowly (that is the point of the scene), so the default reference is bdpt (its
agreement with volpath on these scenes is tested), at many more samples than any contestant reaches.

``--fig-dir DIR`` also writes, per scene, ``KEY-images.png`` (the reference and each integrator's
image at the budget, its first run, side by side at one exposure: the reference's 98th
percentile of luminance is white) and ``KEY-error.png`` (the medians' relMSE less the
reference's own against time, log-log), as docs/media.md shows them."""

import argparse
import hashlib
import os
import sys
import time

import mitsuba as mi
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_light_cache import load, long_render, parameter_value, relmse  # noqa: E402  (the scene at res x res; a long render)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = {'caustic': os.path.join(REPO, 'scenes', 'media', 'volumetric-caustic.xml'),
          'fog': os.path.join(REPO, 'scenes', 'media', 'fog.xml')}
CHECKPOINTS = (0.125, 0.25, 0.5, 1.0)       # fractions of the budget


def integrator(name, max_depth):
    """The integrator dict of a contestant: Mitsuba's volpath or volpathmis, or bdpt with a
    technique (bdpt, pt, lt, vcm, vm), each with bdpt parameters after a colon
    (``vcm:radius=0.02+radius_alpha=1``)."""
    name, _, extra = name.partition(':')
    params = {}
    for item in filter(None, extra.split('+')):
        key, _, value = item.partition('=')
        params[key] = parameter_value(value)
    if name in ('volpath', 'volpathmis') and not params:
        return {'type': name, 'max_depth': max_depth}
    if name in ('bdpt', 'pt', 'lt', 'vcm', 'vm', 'auto'):
        return {'type': 'bdpt', 'max_depth': max_depth, 'technique': name, **params}
    raise ValueError(f'unknown integrator {name!r} (volpath, volpathmis, bdpt, pt, lt, vcm, vm, auto; '
                     'bdpt parameters after a colon)')


def region(path, args):
    """The pixels measured: None (all), or with ``--region no-delta`` those whose footprint ends on
    surfaces without a delta lobe (tests/media_scenes.media_lt_mask: glass seen directly, with
    what it shows, left out; the volumetric caustic in the fog stays)."""
    if args.region == 'all':
        return None
    sys.path.insert(0, os.path.join(REPO, 'tests'))
    from media_scenes import media_lt_mask
    scene, _ = load(path, args.res, args.max_depth, integrator('volpath', args.max_depth))
    return media_lt_mask(scene)


def reference(path, args):
    """The two halves of ``--ref-integrator`` at --ref-spp (independent seeds, batches of 64),
    cached by scene, resolution, depth, integrator and Mitsuba's version; their mean is the
    reference and their difference its own error (own_error)."""
    key = hashlib.sha1(repr((os.path.abspath(path), args.res, args.max_depth, args.ref_spp, args.ref_integrator,
                             mi.__version__, mi.variant())).encode()).hexdigest()[:16]
    cached = os.path.join(args.cache_dir, f'media-ref-halves-{key}.npy')
    if os.path.exists(cached):
        return np.load(cached)
    scene, integ = load(path, args.res, args.max_depth, integrator(args.ref_integrator, args.max_depth))
    n = max(args.ref_spp // 2, 1)
    halves = np.stack([long_render(scene, integ, n), long_render(scene, integ, n, seed0=10_000 + (1 << 24))])
    os.makedirs(args.cache_dir, exist_ok=True)
    np.save(cached, halves)
    return halves


def own_error(halves, mask=None):
    """The reference's own relMSE over ``mask``: mean((A - B)^2 / 4 / (R^2 + 1e-2)), R = (A + B) / 2
    (the variance of the mean of two independent halves), which every contestant's figure holds
    on top of its own."""
    ref = halves.mean(axis=0)
    e = (halves[0] - halves[1]) ** 2 / 4 / (ref ** 2 + 1e-2)
    return float(np.mean(e if mask is None else e[mask]))


def curve(scene, integ, ref, budget, batch_spp, seed0, mask=None):
    """([(seconds, spp, relMSE)] of the running mean of batches at each checkpoint of ``budget``,
    the image at the budget) (technique auto: its first batch chooses, with the choice's time in
    the budget, the others render the chosen configuration, ``last_chosen``)."""
    acc, spp, b, out = 0.0, 0, 0, []
    t0 = time.perf_counter()
    for frac in CHECKPOINTS:
        while time.perf_counter() - t0 < frac * budget:
            img = mi.render(scene, integrator=integ, spp=batch_spp, seed=seed0 + b)
            if getattr(integ, 'technique', None) == 'auto':     # its first batch chose (in the budget):
                integ = integ.last_chosen                       # the others render the choice
            acc = acc + np.array(img, np.float64)[:, :, :3] * batch_spp
            spp += batch_spp
            b += 1
        out.append((time.perf_counter() - t0, spp, relmse(acc / max(spp, 1), ref, mask)))
    return out, acc / max(spp, 1)


def measure(path, name, ref, args, mask=None):
    """([(median seconds, median spp, median relMSE, mean relMSE)] per checkpoint over --repeats
    runs, the first run's image): the relative MSE is an expectation, which the runs' mean
    estimates and their median does not where an error has a heavy tail (docs/light-cache.md,
    forty-second section).
    Each run renders with a fresh integrator, as a user's render starts: a bdpt integrator carries
    its merges' iteration count from render to render (their radius shrinks with it), so that
    until the forty-second session, one integrator rendering the warm-up and every run, vcm's
    runs were not alike (its third run started near iteration 750 on the caustic at 128 x 128,
    its radius 0.44 of a fresh render's first). The warm-up renders one batch of --batch-spp
    (a kernel is compiled for each samples per pixel of a call: until then the warm-up rendered
    1 spp, and the first run's first batch compiled)."""
    props = integrator(name, args.max_depth)
    scene, integ = load(path, args.res, args.max_depth, props)
    mi.render(scene, integrator=integ, spp=args.batch_spp, seed=999)      # warm-up: compiles the kernels
    runs = [curve(scene, mi.load_dict(props), ref, args.budget, args.batch_spp, 1000 * (r + 1), mask)
            for r in range(args.repeats)]
    rows = [tuple(float(np.median([run[i][j] for run, _ in runs])) for j in range(3))
            + (float(np.mean([run[i][2] for run, _ in runs])),) for i in range(len(CHECKPOINTS))]
    return rows, runs[0][1]


def save_figures(key, ref, results, ref_err, fig_dir):
    """``KEY-images.png`` and ``KEY-error.png`` in ``fig_dir`` (see the module's docstring);
    ``results``: {integrator: (rows, image)}, ``measure``'s."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    os.makedirs(fig_dir, exist_ok=True)
    white = max(float(np.quantile(ref.mean(axis=2), 0.98)), 1e-6)
    show = lambda img: np.clip(np.clip(img / white, 0.0, None) ** (1 / 2.2), 0.0, 1.0)     # noqa: E731
    base = results.get('volpath')
    own = lambda e: e - ref_err                 # noqa: E731  (<= 0: within the reference's own error)
    fig, axes = plt.subplots(1, len(results) + 1, figsize=(2.6 * (len(results) + 1), 3.0))
    axes[0].imshow(show(ref), interpolation='nearest')
    axes[0].set_title('reference', fontsize=9)
    for ax, (name, (rows, img)) in zip(axes[1:], results.items()):
        ax.imshow(show(img), interpolation='nearest')
        ratio = f', {max(own(rows[-1][2]), 0.0) / own(base[0][-1][2]):.3g} x volpath' \
            if base and own(base[0][-1][2]) > 0 else ''
        ax.set_title(f'{name}: {rows[-1][1]:.0f} spp{ratio}', fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(os.path.join(fig_dir, f'{key}-images.png'), dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    for name, (rows, _) in results.items():
        kept = [(r[0], own(r[2])) for r in rows if own(r[2]) > 0]       # (a log axis: the positive ones)
        ax.loglog([t for t, _ in kept], [e for _, e in kept], 'o-', label=name)
    ax.set_xlabel('seconds')
    ax.set_ylabel("relMSE less the reference's")
    ax.set_title(f'{key}: error against time', fontsize=10)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(fig_dir, f'{key}-error.png'), dpi=110)
    plt.close(fig)


def table(key, rows, ref_err):
    """Print one scene's table: time, spp, relMSE, relMSE less the reference's own, and its ratio to
    volpath's (likewise less the reference's) at the same checkpoint."""
    base = rows.get('volpath')
    own = lambda e: max(e - ref_err, 0.0)      # noqa: E731
    print(f'\n## {key}\n')
    print("| integrator | time s | spp | relMSE (median) | less the reference's | / volpath's at equal time "
          "| mean of the runs, less the reference's | / volpath's |")
    print('|---|---|---|---|---|---|---|---|')
    for name, r in rows.items():
        for i, (secs, spp, err, mean) in enumerate(r):
            ratio = f'{own(err) / own(base[i][2]):.3g}' if base and own(base[i][2]) > 0 else '-'
            ratio_mean = f'{own(mean) / own(base[i][3]):.3g}' if base and own(base[i][3]) > 0 else '-'
            print(f'| {name} | {secs:.1f} | {spp:.0f} | {err:.4g} | {own(err):.4g} | {ratio} | {own(mean):.4g} | {ratio_mean} |')


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scenes', default='caustic,fog', help=f'comma-separated: {", ".join(SCENES)}, or scene files')
    ap.add_argument('--integrators', default='volpath,volpathmis,bdpt')
    ap.add_argument('--res', type=int, default=32)
    ap.add_argument('--max-depth', type=int, default=8)
    ap.add_argument('--budget', type=float, default=16.0, help='seconds per run')
    ap.add_argument('--batch-spp', type=int, default=16,
                    help='samples per render call (bdpt has a fixed cost per call: ~0.05 s at 32x32)')
    ap.add_argument('--repeats', type=int, default=3, help='runs per integrator (seeds of their own); medians')
    ap.add_argument('--ref-spp', type=int, default=8192)
    ap.add_argument('--ref-integrator', default='bdpt')
    ap.add_argument('--region', default='all', choices=('all', 'no-delta'),
                    help='pixels measured: all, or those not seeing glass (tests/media_scenes.media_lt_mask)')
    ap.add_argument('--variant', default='llvm_ad_rgb')
    ap.add_argument('--cache-dir', default=os.path.join(os.path.dirname(os.path.abspath(__file__)), 'cache'))
    ap.add_argument('--fig-dir', help='also write each scene\'s images side by side and its error against time here')
    args = ap.parse_args()
    mi.set_variant(args.variant)
    mi.set_log_level(mi.LogLevel.Error)
    import bdpt_jit  # noqa: F401  (registers bdpt)
    print(f'# media equal time: {args.res}x{args.res}, max_depth {args.max_depth}, budget {args.budget} s, '
          f'{args.repeats} repeats, reference {args.ref_integrator} {args.ref_spp} spp, {mi.variant()}, '
          f'{os.cpu_count()} cores')
    for key in args.scenes.split(','):
        path = SCENES.get(key, key)
        t0 = time.perf_counter()
        halves = reference(path, args)
        ref = halves.mean(axis=0)
        mask = region(path, args)
        share = 1.0 if mask is None else mask.mean()
        ref_err = own_error(halves, mask)
        print(f'# {key}: {path}, reference in {time.perf_counter() - t0:.0f} s (0 if cached), its own relMSE '
              f'{ref_err:.3g}; region {args.region} ({share:.0%} of the pixels)')
        results = {name: measure(path, name, ref, args, mask) for name in args.integrators.split(',')}
        table(key, {name: rows for name, (rows, _) in results.items()}, ref_err)
        if args.fig_dir:
            save_figures(key, ref, results, ref_err, args.fig_dir)


if __name__ == '__main__':
    main()
