"""Comparison benchmarks of `bdpt` against Mitsuba's `path` and `ptracer`: error against run time.

`bdpt` (power, balance and uniform MIS; technique pt and lt) and Mitsuba's `path` and `ptracer`, on the
paper's scenes and the cases where BDPT should win. Writes `docs/results.md` with its plots and crops
under `docs/results/`.

    python benchmarks/compare.py --quick      # 64x64, budgets up to 0.8 s: ~20 min, ~10 min with cached references
    python benchmarks/compare.py --full       # 96x96, budgets up to 2 s: ~50 min, ~20 min with cached references

References are cached under `benchmarks/cache/`. Every setting of a mode can be overridden (the test
runs a tiny configuration into a temporary folder):

    python benchmarks/compare.py --quick --res 16 --budgets 0.05 --scenes caustic --out /tmp/r.md --fig-dir /tmp/r
"""

import argparse
import dataclasses
import datetime
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compare_lib as lib  # noqa: E402
import compare_report as report  # noqa: E402


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument('--quick', action='store_const', const='quick', dest='mode', help='the quick mode')
    mode.add_argument('--full', action='store_const', const='full', dest='mode', help='the full mode')
    ap.add_argument('--scenes', default=','.join(s.key for s in lib.SCENES),
                    help='comma-separated scene keys (default: all: %(default)s)')
    ap.add_argument('--out', type=Path, default=lib.REPO / 'docs' / 'results.md', help='report (default: %(default)s)')
    ap.add_argument('--fig-dir', type=Path, default=lib.REPO / 'docs' / 'results',
                    help='plots, crops and results.json (default: %(default)s)')
    ap.add_argument('--cache-dir', type=Path, default=lib.REPO / 'benchmarks' / 'cache',
                    help='reference cache (default: %(default)s)')
    g = ap.add_argument_group('overrides of the mode\'s settings')
    g.add_argument('--res', type=int)
    g.add_argument('--budgets', type=float, nargs='+', help='time budgets in seconds, increasing')
    g.add_argument('--repeats', type=int)
    g.add_argument('--probe-spp', type=int, nargs='+')
    g.add_argument('--ref-spp', type=int, help='spp of one reference batch')
    g.add_argument('--ref-batches', type=int)
    g.add_argument('--pilot-spp', type=int)
    g.add_argument('--pilot-batches', type=int)
    g.add_argument('--count-spp', type=int)
    args = ap.parse_args(argv)
    s = dataclasses.replace(lib.MODES[args.mode])
    for field in ('res', 'repeats', 'ref_spp', 'ref_batches', 'pilot_spp', 'pilot_batches', 'count_spp'):
        v = getattr(args, field)
        if v is not None:
            setattr(s, field, v)
    if args.budgets:
        s.budgets = tuple(args.budgets)
    if args.probe_spp:
        s.probe_spp = tuple(args.probe_spp)
    if list(s.budgets) != sorted(s.budgets) or min(s.budgets) <= 0:
        ap.error('--budgets must be positive and increasing')
    if s.repeats < 1 or s.ref_batches < 2 or s.pilot_batches < 2 or s.res < 4:
        ap.error('need --repeats >= 1, --ref-batches >= 2, --pilot-batches >= 2, --res >= 4')
    known = {sc.key: sc for sc in lib.SCENES}
    keys = [k.strip() for k in args.scenes.split(',') if k.strip()]
    unknown = [k for k in keys if k not in known]
    if unknown or not keys:
        ap.error(f"--scenes: unknown {', '.join(unknown) or '(none given)'}; known: {', '.join(known)}")
    return args, s, [known[k] for k in keys]


def main(argv=None):
    args, settings, scenes = parse_args(argv)
    command = 'python benchmarks/compare.py ' + ' '.join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    info = lib.machine_info()
    info['date'] = datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')
    t0 = time.perf_counter()
    results, images = [], {}
    for spec in scenes:
        lib.log(f'scene {spec.key} ({spec.file})')
        res, img = lib.run_scene(spec, settings, lib.CONTESTANTS, args.cache_dir)
        results.append(res)
        images[spec.key] = img
    elapsed = time.perf_counter() - t0
    report.write_report(results, images, lib.CONTESTANTS, settings, info, args.out, args.fig_dir, command, elapsed)
    lib.log(f'wrote {args.out} and {args.fig_dir}/ in {elapsed / 60:.1f} min')


if __name__ == '__main__':
    main()
