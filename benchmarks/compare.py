"""Comparison benchmarks of `bdpt` against Mitsuba's `path` and `ptracer`: error against run time.

`bdpt` (power, balance and uniform MIS; technique pt and lt; vertex connection and merging, technique
vcm, also with merges at every vertex, `vcm-all`, and vertex merging alone, technique vm) and Mitsuba's
`path` and `ptracer`, on the paper's scenes,
the cases where BDPT should win, caustics seen through glass (where only vertex merging does well) and
a plain Cornell box, and Mitsuba 0.6's `bdpt` and `path` (the seed paper's own comparison) where a
built Mitsuba 0.6 is given. Writes `docs/results.md` with its plots
and crops under `docs/results/` (the realistic mode: `docs/results-realistic.md` and its folder).

    python benchmarks/compare.py --quick      # 64x64, budgets up to 0.8 s: ~20 min, ~10 min with cached references
    python benchmarks/compare.py --full       # 96x96, budgets up to 2 s: ~50 min, ~20 min with cached references
    python benchmarks/compare.py --realistic --scene-file veach-bidir=PATH/TO/veach-bidir/scene.xml
                                              # 256x256, budgets 1, 4, 16, 64 s: bdpt, path, ptracer and
                                              # Mitsuba 0.6's; ~20 min a scene on 2 cores once references
                                              # are cached (they take hours the first time: see compare_lib.MODES)

A run on a few scenes or contestants can be written as a section of the report rather than in its place:
`--section NAME` puts it between markers in `--out` (a later run with the same NAME replaces it) with its
figures under `docs/results/NAME/`; issue 15's figures for `vcm` and `vm` are such a section:

    python benchmarks/compare.py --quick --section vcm --contestants bdpt,vcm,vm,path \\
        --scenes caustic,torus-glass,cornell-box,fig7-caustic
                        # ~3 min on 2 cores once the references are cached; rendering them first takes
                        # ~15-20 min (the torus in glass's alone ~10 min: path is its only reference through the glass)

Scenes: the repository's (`--scenes` picks some), plus any given with `--scene-file KEY=PATH` (a Mitsuba 3
scene file that takes `$res`, or `$resx` and `$resy`; options after commas: max_depth=N,
reference=mixed|light, ref_scale=N, focus=1, title=TEXT). Users' scenes stay where they are.

Mitsuba 0.6: `--mitsuba06 PATH/TO/dist` (or the environment variable MITSUBA06_DIST) names a Mitsuba 0.6
built by `benchmarks/mitsuba06.py build`; its `bdpt` and `path` then join the tables and plots as
"mitsuba06 bdpt" and "mitsuba06 path", measured against a reference rendered by its own `bdpt`.
Issue 13's section of docs/results.md:

    python benchmarks/compare.py --quick --section mitsuba06 --mitsuba06 ~/src/mitsuba06/dist \\
        --contestants bdpt,path,mitsuba06-bdpt,mitsuba06-path --scenes cornell-box,caustic
                        # ~1.5 min on 2 cores once the references are cached; 0.6's own references add
                        # ~80 s the first time (`benchmarks/mitsuba06.py speed` gives samples/s alone)
Without it, the report says it was absent. Likewise `vcm` and `vm` where this bdpt_jit refuses the
technique (before vertex merging landed): left out, and the report says why.

Errors are relative MSE, MSE and FLIP (NVIDIA's `flip_evaluator`, LDR mode, on sRGB images exposed so that the
reference's 98th percentile is white). `--denoise` also denoises every contestant's equal-time image (bdpt_jit.denoise)
and reports its errors beside the noisy image's.

References are cached under `benchmarks/cache/`. Every setting of a mode can be overridden (the test
runs a tiny configuration into a temporary folder):

    python benchmarks/compare.py --quick --res 16 --budgets 0.05 --scenes caustic --out /tmp/r.md --fig-dir /tmp/r
"""

import argparse
import dataclasses
import datetime
import os
import re
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compare_lib as lib  # noqa: E402
import compare_report as report  # noqa: E402
import mitsuba06  # noqa: E402


def build_parser():
    """The command line: modes, scenes, contestants, outputs and overrides of the mode's settings."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument('--quick', action='store_const', const='quick', dest='mode', help='the quick mode')
    mode.add_argument('--full', action='store_const', const='full', dest='mode', help='the full mode')
    mode.add_argument('--realistic', action='store_const', const='realistic', dest='mode',
                      help='256x256, budgets 1 to 64 s (long: see the module docstring)')
    ap.add_argument('--scenes', default=','.join(s.key for s in lib.SCENES),
                    help='comma-separated keys of the repository\'s scenes, \'\' for none (default: all: %(default)s)')
    ap.add_argument('--scene-file', action='append', default=[], metavar='KEY=PATH[,name=value...]',
                    help='add a scene file of your own (repeatable); options: max_depth, reference, ref_scale, '
                         'focus, title')
    ap.add_argument('--contestants', help='comma-separated contestant keys (default: the mode\'s); known: '
                    + ', '.join(c.key for c in lib.ALL_CONTESTANTS))
    ap.add_argument('--mitsuba06', metavar='PATH/TO/dist',
                    help=f'a built Mitsuba 0.6 (its dist/ folder or its `mitsuba`; default: ${mitsuba06.ENV_VAR})')
    ap.add_argument('--out', type=Path, help='report (default: docs/results.md; --realistic: docs/results-realistic.md)')
    ap.add_argument('--fig-dir', type=Path, help='plots, crops and results.json (default: docs/results/; '
                    '--realistic: docs/results-realistic/; with --section NAME: that folder\'s NAME/)')
    ap.add_argument('--section', metavar='NAME', help='write the report as a section NAME of --out (between '
                    'markers, replacing an earlier section NAME, the rest of the file kept), its figures under '
                    'NAME/ of the figure folder: a run on a few scenes or contestants beside the full report')
    ap.add_argument('--cache-dir', type=Path, default=lib.REPO / 'benchmarks' / 'cache',
                    help='reference cache (default: %(default)s)')
    ap.add_argument('--denoise', action='store_true',
                    help='also denoise each contestant\'s equal-time image (Open Image Denoise, albedo and normal from '
                         'a feature pass) and report its relMSE and FLIP (needs pip install -e \'.[denoise]\')')
    ap.add_argument('--cluster', metavar='auto|local|ADDRESS',
                    help='render the references\' batches on a Ray cluster, one task each (bdpt_jit.cluster: \'local\' '
                         'starts one for this machine, \'auto\' joins the running one; docs/cluster.md); the same images')
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
    g.add_argument('--ref06-spp', type=int, help='spp of one batch of the Mitsuba 0.6 reference')
    g.add_argument('--ref06-batches', type=int)
    return ap


def settings_of(ap, args):
    """The mode's settings with the command line's overrides (and the output paths in args)."""
    name = 'results-realistic' if args.mode == 'realistic' else 'results'     # the realistic report apart
    args.out = args.out or lib.REPO / 'docs' / f'{name}.md'
    if args.section is not None and not re.fullmatch(r'[A-Za-z0-9_.-]+', args.section):
        ap.error('--section: a name of letters, digits, -, _ or .')
    args.fig_dir = args.fig_dir or lib.REPO / 'docs' / name / (args.section or '')
    s = dataclasses.replace(lib.MODES[args.mode])
    for field in ('res', 'repeats', 'ref_spp', 'ref_batches', 'pilot_spp', 'pilot_batches', 'count_spp',
                  'ref06_spp', 'ref06_batches'):
        v = getattr(args, field)
        if v is not None:
            setattr(s, field, v)
    if args.budgets:
        s.budgets = tuple(args.budgets)
    if args.probe_spp:
        s.probe_spp = tuple(args.probe_spp)
    s.denoise = bool(args.denoise)
    s.cluster = args.cluster
    if list(s.budgets) != sorted(s.budgets) or min(s.budgets) <= 0:
        ap.error('--budgets must be positive and increasing')
    if s.repeats < 1 or s.ref_batches < 2 or s.pilot_batches < 2 or s.ref06_batches < 2 or s.res < 4:
        ap.error('need --repeats >= 1, --ref-batches >= 2, --pilot-batches >= 2, --ref06-batches >= 2, --res >= 4')
    return s


def check_contestants(ap, args, s):
    """--contestants, checked, into s.contestants."""
    if args.contestants is not None:
        keys = [k.strip() for k in args.contestants.split(',') if k.strip()]
        known = [c.key for c in lib.ALL_CONTESTANTS]
        unknown = [k for k in keys if k not in known]
        if unknown:
            ap.error(f"--contestants: unknown {', '.join(unknown)}; known: {', '.join(known)}")
        missing = [k for k in lib.REQUIRED if k not in keys]
        if missing:
            ap.error(f"--contestants must include {', '.join(lib.REQUIRED)} (the tables are relative to them)")
        s.contestants = tuple(keys)


def scenes_of(ap, args):
    """The repository's scenes that --scenes names and the users' --scene-file ones."""
    known = {sc.key: sc for sc in lib.SCENES}
    keys = [k.strip() for k in args.scenes.split(',') if k.strip()]
    unknown = [k for k in keys if k not in known]
    if unknown or (not keys and not args.scene_file):
        ap.error(f"--scenes: unknown {', '.join(unknown) or '(none given)'}; known: {', '.join(known)}")
    scenes = [known[k] for k in keys]
    for text in args.scene_file:
        try:
            spec = lib.user_scene(text)
        except ValueError as e:
            ap.error(f'--scene-file {e}')
        if spec.key in [sc.key for sc in scenes]:
            ap.error(f'--scene-file: the key {spec.key} is taken')
        scenes.append(spec)
    return scenes


def parse_args(argv=None):
    ap = build_parser()
    args = ap.parse_args(argv)
    s = settings_of(ap, args)
    check_contestants(ap, args, s)
    return args, s, scenes_of(ap, args)


def find_mitsuba06(args, settings, scenes):
    """(Mitsuba06 or None, status for the report). Mitsuba 0.6's absence never stops the comparison: its
    contestants are then left out and the report says why. Where it is found, every scene is converted
    up front, so that a scene 0.6 cannot render fails now, not hours into the run."""
    wanted = [c for c in lib.contestants_of(settings.contestants) if c.renderer == 'mitsuba06']
    status = {'wanted': [c.label for c in wanted], 'used': False, 'how': None, 'version': None}
    if not wanted:
        status['how'] = 'not among the contestants (--contestants)'
        return None, status
    m06, how = mitsuba06.find(args.mitsuba06)
    status['how'] = how
    if m06 is None:
        lib.log(f'Mitsuba 0.6 absent: {how}; the comparison goes on without {", ".join(status["wanted"])}')
        return None, status
    for spec in scenes:
        try:
            lib.scene06_file(spec, settings, args.cache_dir)
        except mitsuba06.Mitsuba06Error as e:
            sys.exit(f'compare.py: {spec.key} cannot be converted for Mitsuba 0.6: {e}\n'
                     f'(leave its contestants out with --contestants, or the scene out)')
    lib.log(f'Mitsuba 0.6: {how}')
    status.update(used=True, version=m06.version, binary=str(m06.binary))
    return m06, status


def check_packages(settings):
    """FLIP's package, and with --denoise the denoiser's, before anything is rendered."""
    why = lib.check_flip()
    if why:
        sys.exit(f'compare.py: {why}')
    if settings.denoise:
        from bdpt_jit.denoise import DenoiseError, backends
        try:
            backends.choose(lib.mi.variant())
        except DenoiseError as e:
            sys.exit(f'compare.py: --denoise: {e}')


def main(argv=None):
    args, settings, scenes = parse_args(argv)
    check_packages(settings)
    command = 'python benchmarks/compare.py ' + ' '.join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    info = lib.machine_info()
    info['date'] = datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M %Z')
    m06, m06_status = find_mitsuba06(args, settings, scenes)
    contestants = [c for c in lib.contestants_of(settings.contestants) if c.renderer != 'mitsuba06' or m06]
    absent = {}                         # a technique this bdpt_jit refuses (vcm and vm before they landed)
    for c in contestants:
        why = lib.unavailable(c)
        if why:
            absent[c.label] = why
            lib.log(f'{c.label}: absent ({why}); the comparison goes on without it')
    contestants = [c for c in contestants if c.label not in absent]
    missing = [k for k in lib.REQUIRED if k not in [c.key for c in contestants]]
    if missing:
        sys.exit(f"compare.py: {', '.join(missing)} cannot run here: {absent}")
    t0 = time.perf_counter()
    results, images = [], {}
    for spec in scenes:
        lib.log(f'scene {spec.key} ({spec.file})')
        res, img = lib.run_scene(spec, settings, contestants, args.cache_dir, m06)
        results.append(res)
        images[spec.key] = img
    elapsed = time.perf_counter() - t0
    report.write_report(results, images, contestants, settings, info, args.out, args.fig_dir, command, elapsed,
                        mitsuba06=m06_status, absent=absent, section=args.section)
    lib.log(f'wrote {args.out} and {args.fig_dir}/ in {elapsed / 60:.1f} min')


if __name__ == '__main__':
    main()
