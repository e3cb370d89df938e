"""Speed of ``bdpt`` against Mitsuba's ``path`` on the SmallVCM Cornell box, both rendered in one run.

``--stages`` adds the time of each stage (light pass: emission, walk, splats, stored vertices;
camera pass: walk, hits, emitter sampling, connections) for techniques bdpt, pt and lt, timed
by evaluating the kernels after each stage: the connections' share is the bdpt camera pass
less the pt camera pass. ``--light-paths R [--connections C]`` renders bdpt with the light vertex
cache (R light subpaths a camera sample, C cached vertices a camera vertex: docs/light-cache.md)
and adds it to the stages (the classic estimator's row stays: before and after the cache).
``--variant`` picks the backend (e.g. cuda_ad_rgb where a GPU is).

For each integrator: one warm-up render (timed on its own: tracing + kernel compilation + render), then
``--repeats`` timed renders whose median gives samples/s. Dr.Jit keeps compiled kernels in a cache on
disk, so if this was run before, the warm-up may come out cheaper than a true first compilation.

    python benchmarks/bench_speed.py [--spp 16] [--repeats 3] [--res 256] [--max-depth 10] \
        [--stages] [--light-paths 0.25 --connections 1]
"""

import argparse
import datetime
import os
import platform
import statistics
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SCENE = REPO.parent / 'shared' / 'scenes' / 'smallvcm-box' / 'smallvcm-box.xml'


def cpu_model():
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or 'unknown CPU'


def timed_render(scene, integrator, spp):
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=0)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0


class StageClock:
    """Wall time of each stage of bdpt's passes: the integrator's tracers wrapped so that each
    one's kernels are evaluated (and waited for) before the next stage starts."""

    def __init__(self):
        self.times = {}

    def install(self):
        import bdpt_jit.integrator as integ_mod
        clock = self

        def timed(base, stage):
            class Timed(base):
                def trace(self, *a, **kw):
                    dr.eval()
                    dr.sync_thread()
                    t0 = time.perf_counter()
                    out = super().trace(*a, **kw)
                    dr.eval()
                    dr.sync_thread()
                    clock.times[stage] = clock.times.get(stage, 0.0) + time.perf_counter() - t0
                    return out
            return Timed
        self.saved = (integ_mod.LightTracer, integ_mod.CameraTracer)
        integ_mod.LightTracer = timed(integ_mod.LightTracer, 'light pass')
        integ_mod.CameraTracer = timed(integ_mod.CameraTracer, 'camera pass')

    def uninstall(self):
        import bdpt_jit.integrator as integ_mod
        integ_mod.LightTracer, integ_mod.CameraTracer = self.saved


def stages(args):
    """Per-stage medians for each technique."""
    scene = mi.load_file(str(args.scene), res=args.res, max_depth=args.max_depth, spp=args.spp)
    out = {}
    rows = {t: {'technique': t} for t in ('bdpt', 'pt', 'lt')}
    if args.light_paths is not None:
        rows[f'cache {args.light_paths:g}x{args.connections}'] = cache_settings(args)
    for technique, settings in rows.items():
        integ = mi.load_dict({'type': 'bdpt', 'max_depth': args.max_depth, 'mis': args.mis, **settings})
        clock = StageClock()
        clock.install()
        try:
            timed_render(scene, integ, args.spp)            # warm-up (compilation)
            runs = []
            for _ in range(args.repeats):
                clock.times = {}
                timed_render(scene, integ, args.spp)
                runs.append(dict(clock.times))
        finally:
            clock.uninstall()
        out[technique] = {k: statistics.median(r.get(k, 0.0) for r in runs) for k in ('light pass', 'camera pass')}
    return out


def cache_settings(args):
    """bdpt's parameters for the light vertex cache of --light-paths and --connections."""
    return {'technique': args.technique, 'light_paths': args.light_paths, 'connections': args.connections}


def bench(name, args):
    scene = mi.load_file(str(args.scene), res=args.res, max_depth=args.max_depth, spp=args.spp, integrator=name)
    if name == 'bdpt':
        extra = cache_settings(args) if args.light_paths is not None else {'technique': args.technique}
        integrator = mi.load_dict({'type': 'bdpt', 'max_depth': args.max_depth, 'mis': args.mis, **extra})
    else:
        integrator = scene.integrator()
    first = timed_render(scene, integrator, args.spp)
    times = [timed_render(scene, integrator, args.spp) for _ in range(args.repeats)]
    median = statistics.median(times)
    return {'first': first, 'median': median, 'compile': first - median,
            'msps': args.res * args.res * args.spp / median / 1e6}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scene', type=Path, default=DEFAULT_SCENE)
    ap.add_argument('--spp', type=int, default=16)
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--res', type=int, default=256)
    ap.add_argument('--max-depth', type=int, default=10)
    ap.add_argument('--technique', default='bdpt', choices=['bdpt', 'pt', 'lt', 'vcm', 'vm'])
    ap.add_argument('--mis', default='power', choices=['power', 'balance', 'uniform'])
    ap.add_argument('--variant', default='llvm_ad_rgb')
    ap.add_argument('--stages', action='store_true', help='also time each stage of bdpt, pt and lt')
    ap.add_argument('--light-paths', type=float, default=None,
                    help="bdpt with the light vertex cache: light subpaths a camera sample (bdpt's light_paths)")
    ap.add_argument('--connections', type=int, default=1, help="with --light-paths: bdpt's connections")
    args = ap.parse_args()
    mi.set_variant(args.variant)
    import bdpt_jit  # noqa: F401  (registers the 'bdpt' integrator)
    if args.repeats < 1:
        ap.error('--repeats must be at least 1')

    print(f"date:     {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"machine:  {cpu_model()}, {os.cpu_count()} cores")
    print(f"versions: Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}, variant {mi.variant()}")
    print(f"scene:    {args.scene}")
    print(f"settings: {args.res}x{args.res}, {args.spp} spp, max_depth {args.max_depth}, {args.repeats} timed "
          f"repeats; bdpt technique={args.technique} mis={args.mis}"
          + (f" light_paths={args.light_paths:g} connections={args.connections}" if args.light_paths is not None else ''))
    print()

    results = {name: bench(name, args) for name in ('bdpt', 'path')}

    header = f"{'integrator':<10} {'first render (compile + render)':>31} {'median':>9} {'compile est.':>13} {'M samples/s':>12}"
    print(header)
    print('-' * len(header))
    for name, r in results.items():
        print(f"{name:<10} {r['first']:>30.3f}s {r['median']:>8.3f}s {r['compile']:>12.3f}s {r['msps']:>12.3f}")
    print()
    print(f"bdpt / path (samples/s): {results['bdpt']['msps'] / results['path']['msps']:.3f}")
    if args.stages:
        st = stages(args)
        print()
        print(f"{'technique':<14} {'light pass':>11} {'camera pass':>12}   (medians of {args.repeats}, seconds)")
        for technique, r in st.items():
            print(f"{technique:<14} {r['light pass']:>11.3f} {r['camera pass']:>12.3f}")
        conn = st['bdpt']['camera pass'] - st['pt']['camera pass']
        print(f"connections (bdpt camera pass - pt camera pass): {conn:.3f} s; light pass of bdpt "
              f"(splats and stored vertices) {st['bdpt']['light pass']:.3f} s, of lt (splats only) "
              f"{st['lt']['light pass']:.3f} s")


if __name__ == '__main__':
    main()
