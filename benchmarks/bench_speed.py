"""Speed of ``bdpt`` against Mitsuba's ``path`` on the SmallVCM Cornell box, both rendered in one run.

For each integrator: one warm-up render (timed on its own: tracing + kernel compilation + render), then
``--repeats`` timed renders whose median gives samples/s. Dr.Jit keeps compiled kernels in a cache on
disk, so if this was run before, the warm-up may come out cheaper than a true first compilation.

    python benchmarks/bench_speed.py [--spp 16] [--repeats 3] [--res 256] [--max-depth 10]
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

mi.set_variant('llvm_ad_rgb')
import bdpt_jit  # noqa: E402,F401  (registers the 'bdpt' integrator)

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


def bench(name, args):
    scene = mi.load_file(str(args.scene), res=args.res, max_depth=args.max_depth, spp=args.spp, integrator=name)
    if name == 'bdpt':
        integrator = mi.load_dict({'type': 'bdpt', 'max_depth': args.max_depth,
                                   'technique': args.technique, 'mis': args.mis})
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
    ap.add_argument('--technique', default='bdpt', choices=['bdpt', 'pt', 'lt'])
    ap.add_argument('--mis', default='power', choices=['power', 'balance', 'uniform'])
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error('--repeats must be at least 1')

    print(f"date:     {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"machine:  {cpu_model()}, {os.cpu_count()} cores")
    print(f"versions: Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}, variant {mi.variant()}")
    print(f"scene:    {args.scene}")
    print(f"settings: {args.res}x{args.res}, {args.spp} spp, max_depth {args.max_depth}, {args.repeats} timed "
          f"repeats; bdpt technique={args.technique} mis={args.mis}")
    print()

    results = {name: bench(name, args) for name in ('bdpt', 'path')}

    header = f"{'integrator':<10} {'first render (compile + render)':>31} {'median':>9} {'compile est.':>13} {'M samples/s':>12}"
    print(header)
    print('-' * len(header))
    for name, r in results.items():
        print(f"{name:<10} {r['first']:>30.3f}s {r['median']:>8.3f}s {r['compile']:>12.3f}s {r['msps']:>12.3f}")
    print()
    print(f"bdpt / path (samples/s): {results['bdpt']['msps'] / results['path']['msps']:.3f}")


if __name__ == '__main__':
    main()
