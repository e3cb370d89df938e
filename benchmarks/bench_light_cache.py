"""The light vertex cache (parameters ``light_paths`` and ``connections``) against the classic
estimator, ``technique=pt`` and Mitsuba's ``path``: samples per second, and the whole image's
relative MSE at equal time against a reference rendered by ``path`` (``--ref-integrator``; cached in ``--cache-dir``).

    python benchmarks/bench_light_cache.py --scene ../shared/scenes/smallvcm-box/smallvcm-box.xml \\
        --res 128 --max-depth 10 --budget 8 --configs path,pt,classic,1:2,0.25:1,1:1,2:4

A configuration ``R:C`` is ``light_paths=R, connections=C`` (``R:auto`` leaves connections -1;
any name takes parameters after ``@``: ``vcm@radius=0.01``);
``classic`` is bdpt's default estimator, ``pt`` its path tracing, ``vcm`` and ``vcm_all`` vertex
merging (behind delta vertices; everywhere), ``vcm:R:C`` and ``vcm_all:R:C`` their light vertex
caches, ``auto`` technique auto (its
choice, the pilot and the trials, inside the budget; the choice in the last column). Mitsuba's path renders one
warm-up batch (compilation), then batches of ``--batch-spp`` until ``--budget`` seconds have
passed; a bdpt contestant, as ``bdpt-jit render --time`` renders, one render of a fresh integrator
in passes of ``--batch-spp`` until the budget has passed (its warm-up such a render of WARM_S
seconds). Each ``--repeats`` times with seeds of their own, the median reported (rare fireflies, such
as veach-bidir's small bright emitter seen through glass, which only s=0 samples, decide a
single run) and the mean: the relative MSE is an expectation, which the mean of the runs
estimates and the median does not where a contestant's error has a heavy tail (veach-bidir:
the classic estimator's 32-spp renders are 0.19 of relMSE times spp in the median and 118-183
in two of 40, paths through the lamp's glass that only its s = 0 samples, which vcm's merges
take: docs/light-cache.md, forty-second section); relMSE = mean((I - R)^2 / (R^2 + 1e-2)) over pixels and channels. The reference's own
error is part of every figure: give it many more samples (``--ref-spp``) than any contestant
reaches. It is estimated from the reference's two halves (mean((A - B)^2 / 4 / (R^2 + 1e-2)):
the variance of R = (A + B) / 2) and printed; the columns "less the reference's" subtract it
(an error and the reference's add, being independent). The scene file takes ``$res`` or ``$resx``/``$resy`` and ``$max_depth``."""

import argparse
import hashlib
import os
import re
import time

import drjit as dr
import mitsuba as mi
import numpy as np


def load(path, res, max_depth, integrator, defines=()):
    """The scene at res x res (whichever of $res, $resx/$resy it takes), with ``integrator``;
    ``defines``: 'KEY=VALUE' strings for the scene's other parameters (--define)."""
    params = dict(res=res, resx=res, resy=res, max_depth=max_depth)
    text = open(path).read()
    kw = {k: v for k, v in params.items() if re.search(r'\$' + k + r'\b', text)}
    for d in defines:
        key, sep, value = d.partition('=')
        if not sep or not re.search(r'\$' + re.escape(key) + r'\b', text):
            raise SystemExit(f'bench_light_cache: --define {d!r}: the scene {path} has no parameter ${key}')
        kw[key] = value
    scene = mi.load_file(path, **kw)
    return scene, mi.load_dict(integrator)


def contestant(name, max_depth):
    """The integrator dict of a configuration name, with the parameters after an ``@``
    (``vcm@radius=0.01+connections=2+merge_everywhere=true``: integers, numbers, true/false,
    else strings)."""
    if '@' in name:
        name, extra = name.split('@', 1)
        out = contestant(name, max_depth)
        for item in extra.split('+'):
            key, _, value = item.partition('=')
            out[key] = parameter_value(value)
        return out
    if name == 'path':
        return {'type': 'path', 'max_depth': max_depth}
    if name == 'pt':
        return {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'pt'}
    if name == 'classic':
        return {'type': 'bdpt', 'max_depth': max_depth}
    if name == 'auto':
        return {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'auto'}
    if name in ('vcm', 'vcm_all'):
        return {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'vcm', 'merge_everywhere': name == 'vcm_all'}
    if name.startswith(('vcm:', 'vcm_all:')):          # a merging cache: vcm[_all]:RATIO:C
        kind, ratio, c = name.split(':')
        return {'type': 'bdpt', 'max_depth': max_depth, 'technique': 'vcm', 'merge_everywhere': kind == 'vcm_all',
                'light_paths': float(ratio), 'connections': int(c)}
    ratio, c = name.split(':')
    return {'type': 'bdpt', 'max_depth': max_depth, 'light_paths': float(ratio),
            'connections': -1 if c == 'auto' else int(c)}


def parameter_value(text):
    """A parameter's value from its text: an int, a float, a bool (true/false), else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return {'true': True, 'false': False}.get(text.lower(), text)


def reference(args):
    """(the image, its own relMSE) of ``--ref-integrator`` (a configuration name; default
    Mitsuba's path) at --ref-spp, in batches of 64, in two halves of independent seeds, cached by
    scene, resolution, depth and integrator."""
    key = hashlib.sha1(repr((os.path.abspath(args.scene), args.res, args.max_depth, args.ref_spp,
                             args.ref_integrator, mi.__version__) + tuple(args.define)).encode()).hexdigest()[:16]
    path = os.path.join(args.cache_dir, f'lc-ref-halves-{key}.npy')
    if os.path.exists(path):
        halves = np.load(path)
    else:
        scene, integ = load(args.scene, args.res, args.max_depth, contestant(args.ref_integrator, args.max_depth),
                            args.define)
        n = max(args.ref_spp // 2, 1)
        halves = np.stack([long_render(scene, integ, n), long_render(scene, integ, n, seed0=10_000 + (1 << 24))])
        os.makedirs(args.cache_dir, exist_ok=True)
        np.save(path, halves)
    ref = halves.mean(axis=0)
    return ref, float(np.mean((halves[0] - halves[1]) ** 2 / 4 / (ref ** 2 + 1e-2)))


def relmse(img, ref, mask=None):
    """mean((I - R)^2 / (R^2 + 1e-2)) over the pixels of ``mask`` (None: all) and the channels."""
    e = (img - ref) ** 2 / (ref ** 2 + 1e-2)
    return float(np.mean(e if mask is None else e[mask]))


def long_render(scene, integ, spp, seed0=10_000):
    """The mean of ``spp`` samples rendered in calls of at most 64 (seeds from ``seed0``), RGB float64."""
    acc, done = 0.0, 0
    while done < spp:
        k = min(64, spp - done)
        acc = acc + np.array(mi.render(scene, integrator=integ, spp=k, seed=seed0 + done), np.float64)[:, :, :3] * k
        done += k
    return acc / done


def equal_time(scene, integ, budget, batch_spp, seed0=0):
    """(mean image, spp done, seconds) of batches until ``budget`` seconds have passed."""
    acc, spp, t0, b = 0.0, 0, time.perf_counter(), 0
    while time.perf_counter() - t0 < budget:
        img = mi.render(scene, integrator=integ, spp=batch_spp, seed=seed0 + b)
        acc = acc + np.array(img, np.float64)[:, :, :3] * batch_spp
        spp += batch_spp
        b += 1
    return acc / spp, spp, time.perf_counter() - t0


WARM_S = 1.0               # a bdpt contestant's warm-up render: seconds (prepare)


def equal_time_render(scene, props, budget, batch_spp, seed0=0):
    """equal_time for a bdpt contestant, rendered as ``bdpt-jit render --time`` renders it: one
    render of 2^30 samples per pixel in passes of ``batch_spp``, stopped by its should_stop hook
    once ``budget`` seconds have passed (as equal_time's batches: the pass under way finishes),
    a fresh integrator (``props``) each run. Returns (image, spp, seconds, the integrator, what
    auto chose: its segments' choices joined by ' + ', or None).

    Fresh, since an integrator carries its merges' iteration count from render to render (their
    radius shrinks with it): until the forty-second session the fixed contestants rendered
    separate batches with one integrator for the warm-up and every run, so that vcm's runs were
    not alike (the third started near iteration 600 on the caustic, its radius 0.45 of the
    first's where a fresh render's starts at 1) and none was the render a user's ``--time``
    gets. auto always rendered so: until the twenty-first session its first batch chose and the
    chosen configuration rendered the other batches, a choice governing the whole budget while
    it took the merges' radius of its own batch (auto.horizon)."""
    from bdpt_jit.passes import RenderHooks
    integ = mi.load_dict(props)
    t0 = time.perf_counter()
    # (each pass waited for: Dr.Jit launches a pass's kernels and returns, so that without it the
    # Python loop queues every pass before the budget's end is seen)
    integ.hooks = RenderHooks(on_pass=lambda done, total: dr.sync_thread(),
                              should_stop=lambda: time.perf_counter() - t0 >= budget)
    img = mi.render(scene, integrator=integ, spp=1 << 30, seed=seed0)
    secs = time.perf_counter() - t0
    info = integ.last_render_info
    size = scene.sensors()[0].film().crop_size()
    spp = info['samples'] / (int(size[0]) * int(size[1]))
    chosen = ' + '.join(d['chosen'] for d in info['auto']['decisions']) if 'auto' in info else None
    return np.array(img, np.float64)[:, :, :3], spp, secs, integ, chosen


def prepare(args, name):
    """A contestant: its scene and integrator, warmed up as its runs render (the first render of
    a kernel compiles it): Mitsuba's path one batch of --batch-spp; a bdpt contestant a budgeted
    render of WARM_S seconds in passes of --batch-spp (auto: its decision's trials and pilots,
    and its passes; with a 1-spp warm-up, its first run's decision took 4.7 s against 2.8-2.9 s
    in the later ones on veach-bidir at 256 x 256)."""
    props = contestant(name, args.max_depth)
    bdpt = props['type'] == 'bdpt'
    if bdpt:                    # passes of --batch-spp (equal_time_render)
        props['samples_per_pass'] = args.batch_spp * args.res * args.res
    scene, integ = load(args.scene, args.res, args.max_depth, props, args.define)
    t0 = time.perf_counter()
    if bdpt:
        integ = equal_time_render(scene, props, WARM_S, args.batch_spp, seed0=999)[3]
    else:
        dr.eval(mi.render(scene, integrator=integ, spp=args.batch_spp, seed=999))
    return dict(name=name, scene=scene, integ=integ, props=props, bdpt=bdpt, warm=time.perf_counter() - t0,
                rels=[], spps=[], sps=[], chosen=[])


def run_once(args, c, r, ref):
    """Equal-time run ``r`` of contestant ``c`` (seeds of its own: --seed + 1000 r + batch)."""
    seed0 = args.seed + 1000 * r
    if c['bdpt']:
        img, spp, secs, c['integ'], chosen = equal_time_render(c['scene'], c['props'], args.budget, args.batch_spp, seed0=seed0)
        if chosen is not None:
            c['chosen'].append(chosen)
    else:
        img, spp, secs = equal_time(c['scene'], c['integ'], args.budget, args.batch_spp, seed0=seed0)
    c['rels'].append(relmse(img, ref))
    c['spps'].append(spp)
    c['sps'].append(spp * args.res * args.res / secs)


def summary(c):
    """A contestant's row: medians over its runs."""
    info = getattr(c['integ'], 'last_render_info', {}).get('light_cache', {})
    if c['chosen']:
        info = {'chose': ' / '.join(c['chosen'])}
    return dict(name=c['name'], warm=c['warm'], spp=int(np.median(c['spps'])), sps=float(np.median(c['sps'])),
                relmse=float(np.median(c['rels'])), mean=float(np.mean(c['rels'])), rels=c['rels'], info=info)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--scene', required=True)
    ap.add_argument('--res', type=int, default=128)
    ap.add_argument('--max-depth', type=int, default=10)
    ap.add_argument('--budget', type=float, default=8.0, help='seconds per contestant')
    ap.add_argument('--batch-spp', type=int, default=4)
    ap.add_argument('--repeats', type=int, default=1,
                    help='equal-time runs per contestant (seeds of their own, the contestants in turn); the median is reported')
    ap.add_argument('--seed', type=int, default=0,
                    help='the first run\'s seed (run r: this plus 1000 r); the same seeds in every invocation '
                         'give the same samples, auto\'s pilots included, so a new --seed samples its choices afresh')
    ap.add_argument('--ref-spp', type=int, default=4096)
    ap.add_argument('--ref-integrator', default='path',
                    help='configuration of the reference (classic where path cannot converge)')
    ap.add_argument('--configs', default='path,pt,classic,1:1,0.25:1,2:4')
    ap.add_argument('--variant', default='llvm_ad_rgb')
    ap.add_argument('--cache-dir', default=os.path.join(os.path.dirname(__file__), 'cache'))
    ap.add_argument('--define', action='append', default=[], metavar='KEY=VALUE',
                    help="a scene parameter ($KEY), e.g. --define glass=rough (scenes/torus-in-glass.xml)")
    args = ap.parse_args()
    mi.set_variant(args.variant)
    import bdpt_jit  # noqa: F401  (registers bdpt)
    t0 = time.perf_counter()
    ref, ref_err = reference(args)
    print(f'# {args.scene} {args.res}x{args.res} max_depth {args.max_depth}, reference {args.ref_integrator} {args.ref_spp} spp '
          f'({time.perf_counter() - t0:.0f} s; its own relMSE {ref_err:.3g}), budget {args.budget} s, {mi.variant()}, '
          f'{os.cpu_count()} cores')
    # the contestants' runs interleaved (run r of each in turn): the machine's slow spells fall
    # on all of them alike rather than on whichever ran then
    contestants = [prepare(args, name) for name in args.configs.split(',')]
    for r in range(args.repeats):
        for c in contestants:
            run_once(args, c, r, ref)
    rows = [summary(c) for c in contestants]
    base = next((r for r in rows if r['name'] == 'path'), rows[0])
    print('| configuration | M samples/s | /path | spp in budget | relMSE (median) | relMSE / path | '
          "less the reference's | / path's | mean of the runs, less the reference's | / path's | runs | warm-up s | cache |")
    print('|---|---|---|---|---|---|---|---|---|---|---|---|---|')
    own = lambda r, key='relmse': max(r[key] - ref_err, 0.0)      # noqa: E731
    for r in rows:
        ratio = f"{own(r) / own(base):.2f}" if own(base) > 0 else '-'
        ratio_mean = f"{own(r, 'mean') / own(base, 'mean'):.2f}" if own(base, 'mean') > 0 else '-'
        print(f"| {r['name']} | {r['sps'] / 1e6:.3f} | {r['sps'] / base['sps']:.2f} | {r['spp']} | {r['relmse']:.4g} | "
              f"{r['relmse'] / base['relmse']:.2f} | {own(r):.4g} | {ratio} | {own(r, 'mean'):.4g} | {ratio_mean} | "
              f"{' '.join(f'{x:.3g}' for x in r['rels'])} | {r['warm']:.1f} | {r['info'] or ''} |")


if __name__ == '__main__':
    main()
