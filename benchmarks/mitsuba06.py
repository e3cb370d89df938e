"""Mitsuba 0.6 as a contestant of `benchmarks/compare.py`: build it, convert the scenes, render.

The seed paper compares its BDPT with Mitsuba 0.5/0.6's `bdpt` (and `path`). This script builds
Mitsuba 0.6 from a clone of its public repository (github.com/mitsuba-renderer/mitsuba, tested at
master 10af06f3) on Debian 12, converts Mitsuba 3 scene files to its XML, and runs it; the
comparison adds "mitsuba06 bdpt" and "mitsuba06 path" when it finds the built binary.

    git clone https://github.com/mitsuba-renderer/mitsuba ~/src/mitsuba06
    sudo apt-get install <the packages `build` lists when they are missing>
    python benchmarks/mitsuba06.py build --source ~/src/mitsuba06          # 8-16 min with -j2
    python benchmarks/mitsuba06.py check --dist ~/src/mitsuba06/dist       # a 16x16 test render
    python benchmarks/mitsuba06.py speed --dist ~/src/mitsuba06/dist       # samples/s beside bdpt_jit's (SmallVCM box)
    python benchmarks/mitsuba06.py convert scenes/caustic.xml /tmp/caustic06.xml --res 256
    python benchmarks/compare.py --quick --mitsuba06 ~/src/mitsuba06/dist  # or MITSUBA06_DIST=...

`build` checks the Debian packages, makes the source build with Python 3's SCons and current
libraries (the SConscripts' Python 2 `print` statements and `has_key`, OpenEXR 3's API, GLEW
without its MX variant, Boost 1.74's placeholders), adds a `seed` parameter to the `independent`
sampler (see `SEED_EDIT`), writes `config.py` (no Python bindings, Qt or COLLADA: only the
`mitsuba` command is needed) and runs `scons`. `--prepare-only` stops before `scons`. Every edit
is idempotent and fails with a message naming the file when the source is not the one expected.

Scene conversion (`convert_file`): parameter names become camelCase (`to_world` -> `toWorld`,
`int_ior` -> `intIOR`, ...; `alpha`, `distribution`, `eta`, `k` keep theirs), the film writes
float32 OpenEXR without the logo banner, the sampler becomes `independent` with `$spp` and
`$seed`, the integrator `$integrator` with `maxDepth` (which counts edges as Mitsuba 3's
`max_depth` does) and `rrDepth` 5 (Mitsuba 3's default), defaults Mitsuba 3 and 0.6 disagree on
are written out (a conductor without a material is a perfect mirror in Mitsuba 3, copper in 0.6),
relative file names become absolute, and a checkerboard's `to_uv` scale/offset becomes
`uscale`/`vscale`/`uoffset`/`voffset`. Plugins 0.6 does not have are refused.
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mitsuba06_build import (INCLUDE_DIRS, LIB_DIRS, REQUIREMENTS, SEED_EDIT, SOURCE_EDITS, build, check_source,  # noqa: E402,F401
                             missing_packages, prepare, python3_sconscript)
from mitsuba06_common import ENV_VAR, KEEP_SYMBOLIC, REPO, RR_DEPTH, Mitsuba06Error  # noqa: E402,F401
from mitsuba06_scene import camel, convert_file, convert_tree, scene_defaults  # noqa: E402,F401


RENDER_TIME = re.compile(r'Render time: ([0-9.]+)([smhd])')
UNIT = {'s': 1, 'm': 60, 'h': 3600, 'd': 12 * 3600}     # 0.6's timeString divides days by 12 (sic)


class Mitsuba06:
    """A built Mitsuba 0.6: `render(scene_xml, integrator, spp, seed)` -> (render s, wall s, image)."""

    def __init__(self, binary):
        self.binary = Path(binary).resolve()
        self.dist = self.binary.parent
        self.env = dict(os.environ)
        for var in ('LD_LIBRARY_PATH', 'PATH'):
            self.env[var] = os.pathsep.join(x for x in (str(self.dist), os.environ.get(var, '')) if x)
        try:
            proc = subprocess.run([str(self.binary), '-h'], env=self.env, capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise Mitsuba06Error(f'{self.binary} does not run: {e}') from e
        m = re.search(r'Mitsuba version (\S+)', proc.stdout + proc.stderr)
        if not m or not m.group(1).startswith(('0.6', '0.5')):
            raise Mitsuba06Error(f'{self.binary} is not Mitsuba 0.6 (its -h says: '
                                 f'{(proc.stdout + proc.stderr).strip()[:200]!r})')
        self.version = m.group(1)
        st = self.binary.stat()
        self.identity = f'{self.binary}:{st.st_size}:{int(st.st_mtime)}:{self.version}'

    def render(self, scene_xml, integrator, spp, seed, threads=None):
        """Renders and returns (render time as 0.6 logs it, wall time of the process, float32 HxWx3 array).
        The render time leaves out the process start and the scene loading (kd-tree included), as
        the Mitsuba 3 timings leave out mi.load_file."""
        import mitsuba as mi    # only for reading the OpenEXR file
        import numpy as np
        threads = threads or os.cpu_count()
        with tempfile.TemporaryDirectory(prefix='mitsuba06-') as tmp:
            out = Path(tmp) / 'out.exr'
            cmd = [str(self.binary), '-z', '-p', str(threads), f'-Dintegrator={integrator}', f'-Dspp={int(spp)}',
                   f'-Dseed={int(seed)}', '-o', str(out), str(scene_xml)]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, cwd=tmp, env=self.env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            log = proc.stdout + proc.stderr
            if 'Unqueried attribute "seed"' in log:
                raise Mitsuba06Error(f'{self.binary} ignores the sampler\'s seed (built without the seed edit of '
                                     f'benchmarks/mitsuba06.py): its repeated renders would not be independent; '
                                     f'rebuild with `python benchmarks/mitsuba06.py build --source ...`')
            if proc.returncode != 0 or not out.exists():
                raise Mitsuba06Error(f'{" ".join(cmd)} failed (exit status {proc.returncode}):\n{log[-2000:]}')
            m = RENDER_TIME.findall(log)
            if not m:
                raise Mitsuba06Error(f'no "Render time" in the log of {" ".join(cmd)}:\n{log[-2000:]}')
            seconds = float(m[-1][0]) * UNIT[m[-1][1]]
            img = np.array(mi.Bitmap(str(out)), dtype=np.float32)
        if img.ndim != 3 or img.shape[2] < 3:
            raise Mitsuba06Error(f'unexpected image shape {img.shape} from {scene_xml}')
        return seconds, wall, img[:, :, :3]

    def smoke_test(self, res=16):
        """A tiny render of the repository's Cornell box with `bdpt`: raises if anything is wrong."""
        with tempfile.TemporaryDirectory(prefix='mitsuba06-check-') as tmp:
            xml = Path(tmp) / 'cornell-box.xml'
            convert_file(REPO / 'scenes' / 'cornell-box.xml', xml, {'res': res})
            seconds, wall, img = self.render(xml, 'bdpt', 4, seed=1)
        if not (img > 0).any():
            raise Mitsuba06Error(f'{self.binary} rendered a black Cornell box')
        return seconds, wall, img


def find(path=None):
    """(Mitsuba06 or None, a sentence saying what was used or why none was). `path`: a dist/ folder
    or the `mitsuba` binary; default: the environment variable MITSUBA06_DIST. A `mitsuba` on PATH
    is not used: Mitsuba 3's pip package installs a command of that name."""
    where = path or os.environ.get(ENV_VAR)
    if not where:
        return None, (f'no Mitsuba 0.6 binary given (option --mitsuba06 PATH/TO/dist or environment variable '
                      f'{ENV_VAR}; build one with `python benchmarks/mitsuba06.py build --source DIR`)')
    p = Path(where).expanduser()
    binary = p / 'mitsuba' if p.is_dir() else p
    if not binary.is_file() or not os.access(binary, os.X_OK):
        return None, f'no executable `mitsuba` at {binary}'
    try:
        m = Mitsuba06(binary)
        m.smoke_test()
    except Mitsuba06Error as e:
        return None, f'{binary} cannot be used: {e}'
    return m, f'{m.binary} (version {m.version})'


# ============================================================================================ speed

SMALLVCM_BOX = REPO.parent / 'shared' / 'scenes' / 'smallvcm-box' / 'smallvcm-box.xml'


def speed(m06, scene, res=256, spp=16, max_depth=10, repeats=3, threads=None, log=print):
    """Samples per second of Mitsuba 0.6's `bdpt` and `path` beside bdpt_jit's `bdpt` and Mitsuba 3's
    `path` (llvm_ad_rgb) on one Mitsuba 3 scene file, at the same resolution, spp and max depth. Mitsuba
    0.6's time is the render time it logs (process start and kd-tree build left out), Mitsuba 3's the
    render after one warm-up render (scene loading and kernel compilation left out); `repeats` timed
    renders of each, interleaved so that a change of the machine's load spreads over all of them;
    medians. Returns {name: {'times': [...], 'median_s':, 'msps':}}."""
    import statistics
    import drjit as dr
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant('llvm_ad_rgb')
    import bdpt_jit  # noqa: F401  (registers the 'bdpt' integrator)
    scene = Path(scene).resolve()
    with tempfile.TemporaryDirectory(prefix='mitsuba06-speed-') as tmp:
        xml06 = Path(tmp) / (scene.stem + '-06.xml')
        convert_file(scene, xml06, {'res': res, 'resx': res, 'resy': res}, max_depth)
        text = scene.read_text()        # Mitsuba 3 refuses parameters a scene does not use
        given = {'res': res, 'resx': res, 'resy': res, 'max_depth': max_depth, 'spp': spp, 'integrator': 'path'}
        sc3 = mi.load_file(str(scene), **{k: v for k, v in given.items() if re.search(rf'\${k}\b', text)})
        w, h = (int(v) for v in sc3.sensors()[0].film().crop_size())
        integrators = {'bdpt_jit bdpt': mi.load_dict({'type': 'bdpt', 'max_depth': max_depth}),
                       'Mitsuba 3 path': mi.load_dict({'type': 'path', 'max_depth': max_depth})}

        def render3(integ, seed):
            dr.sync_thread()
            t0 = time.perf_counter()
            img = mi.render(sc3, integrator=integ, spp=spp, seed=seed)
            dr.eval(img)
            dr.sync_thread()
            return time.perf_counter() - t0

        times = {'Mitsuba 0.6 bdpt': [], 'Mitsuba 0.6 path': [], 'bdpt_jit bdpt': [], 'Mitsuba 3 path': []}
        warmup = {name: render3(integ, 0) for name, integ in integrators.items()}
        for r in range(repeats):
            for name in times:
                if name.startswith('Mitsuba 0.6'):
                    t, _, img = m06.render(xml06, name.split()[-1], spp, seed=r + 1, threads=threads)
                    if img.shape[:2] != (h, w):
                        raise Mitsuba06Error(f'Mitsuba 0.6 rendered {img.shape[1]}x{img.shape[0]}, not {w}x{h}')
                else:
                    t = render3(integrators[name], r + 1)
                times[name].append(t)
            log(f'repeat {r + 1}/{repeats}: ' + ', '.join(f'{k} {v[-1]:.2f} s' for k, v in times.items()))
    out = {}
    for name, ts in times.items():
        med = statistics.median(ts)
        out[name] = {'times': ts, 'median_s': med, 'msps': w * h * spp / med / 1e6}
        if name in warmup:
            out[name]['warmup_s'] = warmup[name]
    return out


# ============================================================================================ command line

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    sub = ap.add_subparsers(dest='command', required=True)
    b = sub.add_parser('build', help='build Mitsuba 0.6 from a clone of its repository')
    b.add_argument('--source', required=True, type=Path, help='a clone of github.com/mitsuba-renderer/mitsuba')
    b.add_argument('--jobs', type=int, default=os.cpu_count(), help='scons -j (default: %(default)s)')
    b.add_argument('--prepare-only', action='store_true', help='apply the edits and write config.py, do not build')
    c = sub.add_parser('convert', help='convert a Mitsuba 3 scene file to Mitsuba 0.6 XML')
    c.add_argument('src', type=Path)
    c.add_argument('dst', type=Path)
    c.add_argument('--res', type=int, help='overrides the scene\'s res (and resx, resy) default')
    c.add_argument('--max-depth', type=int)
    k = sub.add_parser('check', help='find a built Mitsuba 0.6 and render a 16x16 Cornell box')
    k.add_argument('--dist', help=f'dist/ folder or binary (default: ${ENV_VAR})')
    v = sub.add_parser('speed', help='samples/s of Mitsuba 0.6 bdpt and path beside bdpt_jit bdpt and Mitsuba 3 path')
    v.add_argument('--dist', help=f'dist/ folder or binary (default: ${ENV_VAR})')
    v.add_argument('--scene', type=Path, default=SMALLVCM_BOX, help='a Mitsuba 3 scene file (default: %(default)s)')
    v.add_argument('--res', type=int, default=256)
    v.add_argument('--spp', type=int, default=16)
    v.add_argument('--max-depth', type=int, default=10)
    v.add_argument('--repeats', type=int, default=3)
    v.add_argument('--threads', type=int, help='Mitsuba 0.6 -p (default: all cores, as Mitsuba 3 uses)')
    v.add_argument('--json', type=Path, help='also write the figures to this file')
    args = ap.parse_args(argv)
    try:
        if args.command == 'build':
            dist = build(args.source, args.jobs, args.prepare_only)
            if dist:
                m = Mitsuba06(dist / 'mitsuba')
                seconds, _, _ = m.smoke_test()
                print(f'Mitsuba {m.version} works (16x16 test render in {seconds:.2f} s). Use it with:\n'
                      f'  python benchmarks/compare.py --quick --mitsuba06 {dist}')
        elif args.command == 'convert':
            params = {'res': args.res, 'resx': args.res, 'resy': args.res} if args.res else {}
            convert_file(args.src, args.dst, params, args.max_depth)
            print(f'wrote {args.dst}')
        elif args.command == 'speed':
            m, how = find(args.dist)
            if m is None:
                raise Mitsuba06Error(how)
            if args.repeats < 1:
                raise Mitsuba06Error('--repeats must be at least 1')
            import platform
            print(f'Mitsuba 0.6: {how}\nscene: {args.scene}, {args.res}x{args.res}, {args.spp} spp, max depth '
                  f'{args.max_depth}, {args.repeats} timed repeats; {os.cpu_count()} cores, {platform.platform()}')
            res = speed(m, args.scene, args.res, args.spp, args.max_depth, args.repeats, args.threads)
            print(f"\n{'renderer':<18} {'median s':>9} {'M samples/s':>12}   (times)")
            for name, r in res.items():
                print(f"{name:<18} {r['median_s']:>9.3f} {r['msps']:>12.3f}   "
                      + ' '.join(f'{t:.2f}' for t in r['times']))
            b06, b3 = res['Mitsuba 0.6 bdpt']['msps'], res['bdpt_jit bdpt']['msps']
            print(f'\nbdpt_jit bdpt / Mitsuba 0.6 bdpt (samples/s): {b3 / b06:.2f}')
            if args.json:
                import json
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({'mitsuba06': how, 'scene': str(args.scene), 'res': args.res,
                                                 'spp': args.spp, 'max_depth': args.max_depth,
                                                 'repeats': args.repeats, 'cores': os.cpu_count(),
                                                 'results': res}, indent=1))
        else:
            m, how = find(args.dist)
            if m is None:
                raise Mitsuba06Error(how)
            print(f'Mitsuba 0.6 found and working: {how}')
    except Mitsuba06Error as e:
        print(f'mitsuba06.py {args.command}: {e}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
