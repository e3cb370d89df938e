"""The ``bdpt-jit`` command: render a Mitsuba scene file to a multi-layer EXR and a PNG.

    bdpt-jit render scenes/cornell-box.xml -o out/cornell-box.exr --spp 64
    bdpt-jit render scenes/caustic.xml --time 60 --strategies -D res=256

Integrator parameters (their option names, defaults and help) come from the same table as the
plugin (``params.py``). See ``docs/cli.md`` for the options, the EXR layout and its header keys.

Exit status: 0 on success, 1 on an error (one line on stderr, no traceback unless ``--debug``),
2 on a usage error, 130 when interrupted (Ctrl-C): after at least one finished pass the partial
render is written first, and the message says so."""

import argparse
import os
import re
import signal
import sys
import tempfile
import threading
import time

PROG = 'bdpt-jit'
DEFAULT_VARIANT = 'llvm_ad_rgb'
GPU_VARIANT = 'cuda_ad_rgb'
HEADER_PREFIX = 'bdpt.'
# Parameters of the table that Mitsuba's own integrators (path, ptracer, ...) also take
SHARED_PARAMS = ('max_depth', 'rr_depth', 'hide_emitters')
EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 1, 2, 130


class CLIError(Exception):
    """An error the user can fix; printed as one line, exit status 1."""


class Interrupted(Exception):
    """Ctrl-C before anything could be written; exit status 130."""


# ----------------------------------------------------------------------------- options
def _param_flags(p):
    flags = ['--' + p.name.replace('_', '-')]
    if p.name == 'strategy_images':
        flags.append('--strategies')
    return flags


def _add_param_options(parser):
    from .params import PARAMS
    g = parser.add_argument_group(
        'integrator parameters', 'the bdpt plugin\'s parameters (params.py); unset ones come from the '
        'scene\'s integrator if it is bdpt, else take their defaults. max_depth, rr_depth and '
        'hide_emitters also apply to Mitsuba\'s integrators.')
    for p in PARAMS:
        default_text = p.default_text
        if p.name == 'statistics':
            default_text = 'true in this command'
        kw = dict(dest=p.name, default=None, help=f"{_plain(p.meaning)} (default: {default_text})")
        if p.type is bool:
            g.add_argument(*_param_flags(p), action=argparse.BooleanOptionalAction, **kw)
        else:
            if p.choices:
                kw['choices'] = p.choices
            else:
                kw['metavar'] = p.type_name.upper()
            g.add_argument(*_param_flags(p), type=p.type, **kw)


def params_markdown():
    """The integrator options of ``bdpt-jit render`` as a Markdown table, from the parameter
    table (docs/cli.md holds a copy; a test checks that it is current)."""
    from .params import PARAMS
    rows = ['| option | plugin parameter | default | meaning |', '|---|---|---|---|']
    for p in PARAMS:
        flags = _param_flags(p)
        if p.type is bool:
            flags = [f"{f} / --no-{f[2:]}" for f in flags]
        elif p.choices:
            flags = [f"{f} {{{','.join(p.choices)}}}" for f in flags]
        else:
            flags = [f"{f} {p.type_name.upper()}" for f in flags]
        default = 'true' if p.name == 'statistics' else p.default_text
        rows.append(f"| {', '.join(f'`{f}`' for f in flags)} | `{p.name}` | {default} | {p.meaning} |")
    return '\n'.join(rows)


def _plain(text):
    """Markdown of the table -> terminal text (argparse help: no backticks, no %)."""
    return text.replace('`', '').replace('%', '%%')


def _positive_int(s):
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {s!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {s!r}")
    return v


def _positive_float(s):
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {s!r}") from None
    if not v > 0 or v == float('inf'):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {s!r}")
    return v


def _seed(s):
    try:
        v = int(s, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
    if not 0 <= v < 2 ** 32:
        raise argparse.ArgumentTypeError(f"expected an integer in [0, 2^32), got {s!r}")
    return v


def build_parser():
    ap = argparse.ArgumentParser(prog=PROG, description='Bidirectional path tracing for Mitsuba 3 scenes.')
    sub = ap.add_subparsers(dest='command', required=True, metavar='COMMAND')
    r = sub.add_parser(
        'render', help='render a scene file to EXR + PNG',
        description='Render a Mitsuba scene file to a multi-layer EXR (settings and statistics in '
                    'its header) and a tone-mapped PNG beside it.')
    r.add_argument('scene', metavar='SCENE.xml', help='Mitsuba scene file')
    r.add_argument('-o', '--output', metavar='OUT.exr', default=None,
                   help='output EXR path (default: the scene\'s name in the working directory); '
                        'a PNG is written beside it')
    budget = r.add_mutually_exclusive_group()
    budget.add_argument('--spp', type=_positive_int, default=None, metavar='N',
                        help="samples per pixel, rendered in one mi.render call (default: the scene's sampler)")
    budget.add_argument('--time', type=_positive_float, default=None, metavar='SECONDS',
                        help='time budget: render passes of --pass-spp samples per pixel until the next '
                             'one would exceed it; reports the spp reached')
    r.add_argument('--pass-spp', type=_positive_int, default=4, metavar='N',
                   help='samples per pixel of each pass with --time (default: 4)')
    r.add_argument('--integrator', default='bdpt', metavar='NAME',
                   help='integrator plugin (default: bdpt; any Mitsuba integrator, e.g. path or '
                        'ptracer, for comparison)')
    r.add_argument('-D', dest='defines', action='append', default=[], metavar='NAME=VALUE',
                   help="scene parameter (a <default> of the scene file), as Mitsuba's -D; repeatable")
    r.add_argument('--variant', default=None,
                   help=f'Mitsuba variant (default: {GPU_VARIANT} where a CUDA GPU is present, '
                        f'else {DEFAULT_VARIANT})')
    r.add_argument('--seed', type=_seed, default=0, help='random seed (default: 0)')
    r.add_argument('-q', '--quiet', action='store_true',
                   help='no progress bar and no summary (errors and interruptions are still reported)')
    r.add_argument('--debug', action='store_true', help='show tracebacks and Dr.Jit\'s own messages')
    _add_param_options(r)
    return ap


def _parse_defines(defines):
    out = {}
    for d in defines:
        name, sep, value = d.partition('=')
        name = name.strip()
        if not sep or not name:
            raise CLIError(f"-D expects NAME=VALUE, got {d!r}")
        if not re.fullmatch(r'[A-Za-z_][A-Za-z0-9_]*', name):
            raise CLIError(f"-D {d}: {name!r} is not a valid parameter name")
        out[name] = value
    return out


# ----------------------------------------------------------------------------- files
def _atomic_write(path, write_fn):
    """Write through a temporary file in the same folder, then rename: an interrupted render
    never leaves a truncated file under the final name."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)                # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _check_output(out):
    """Refuse an output path that cannot be written, before any rendering."""
    if not out.lower().endswith('.exr'):
        raise CLIError(f"output must be an .exr file (the PNG is written beside it): {out}")
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        raise CLIError(f"output folder does not exist: {folder}")
    png = os.path.splitext(out)[0] + '.png'
    for path in (out, png):
        if os.path.isdir(path):
            raise CLIError(f"output path is a folder: {path}")
    try:                                            # os.access says yes to root even on read-only mounts
        fd, probe = tempfile.mkstemp(prefix='.bdpt-jit-probe.', dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise CLIError(f"output folder is not writable: {folder} ({e.strerror})") from None
    return png


def exr_channels(rgb, layers=None):
    """Channel dict for OpenEXR: the image as R, G, B; each strategy layer as
    ``<name>.weighted.R/G/B`` and ``<name>.unweighted.R/G/B``."""
    import numpy as np
    ch = {}
    rgb = np.asarray(rgb, dtype=np.float32)
    for c, cname in enumerate('RGB'):
        ch[cname] = np.ascontiguousarray(rgb[:, :, c])
    for name, kinds in (layers or {}).items():
        for kind in ('weighted', 'unweighted'):
            a = np.asarray(kinds[kind], dtype=np.float32)
            for c, cname in enumerate('RGB'):
                ch[f'{name}.{kind}.{cname}'] = np.ascontiguousarray(a[:, :, c])
    return ch


def write_exr(path, rgb, header_extra, layers=None):
    import OpenEXR
    header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}
    header.update({k: str(v) for k, v in header_extra.items()})
    channels = exr_channels(rgb, layers)
    _atomic_write(path, lambda tmp: OpenEXR.File(header, channels).write(tmp))


def write_png(path, rgb):
    """Tone mapping: clamp to [0, 1], sRGB transfer curve, 8 bits."""
    import numpy as np
    import mitsuba as mi
    a = np.ascontiguousarray(np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0))
    png = mi.Bitmap(a, mi.Bitmap.PixelFormat.RGB).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    _atomic_write(path, lambda tmp: png.write(tmp))


# ----------------------------------------------------------------------------- errors
_SRC_PREFIX = re.compile(r'\[[\w.+-]+:\d+\]\s*|\[[A-Z]\w*\]\s+')   # [parser.cpp:451], [PluginManager]


def _error_text(e):
    """One line from a Mitsuba / Dr.Jit / plugin exception: the position it names (file, line,
    column) kept; source-location tags and Python tracebacks embedded by Mitsuba dropped."""
    while e.__cause__ is not None and ('drjit.custom' in str(e) or '(see above)' in str(e)):
        e = e.__cause__             # mi.render and dr.while_loop wrap the original exception
    text = str(e).strip() or type(e).__name__
    if 'Traceback (most recent call last)' in text:
        head, _, tb = text.partition('Traceback (most recent call last)')
        lines = [ln.strip() for ln in tb.splitlines() if ln.strip()]
        last = lines[-1] if lines else ''
        bdpt = [ln for ln in lines if ln.startswith('bdpt:') or re.match(r'\w+Error: bdpt:', ln)]
        if bdpt:
            last = bdpt[-1]
        last = re.sub(r'^\w+(Error|Exception): ', '', last)
        text = head.rstrip().rstrip(':') + ': ' + last if head.strip() else last
    text = _SRC_PREFIX.sub('', text)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return ' '.join(lines[:1] + [ln.lstrip('- ') for ln in lines[1:]]) if lines else type(e).__name__


def _scene_error(e, scene_path, defines):
    text = _error_text(e)
    unused = re.findall(r'\$(\w+)=', text)
    if 'unused parameters' in text and unused:
        names = ', '.join(unused)
        return f"-D {names}: the scene {scene_path} has no parameter of that name (no <default name=\"...\"> or $name in it)"
    if defines and re.search(r'could not parse|out of bounds|invalid', text, re.I):
        given = ' '.join(f'-D {k}={v}' for k, v in defines.items())
        return f"cannot load scene: {text} (with {given})"
    return f"cannot load scene: {text}"


class _CaptureStderr:
    """Redirect the process's fd 2 (Dr.Jit prints its backend messages there, below Python)."""

    def __enter__(self):
        sys.stderr.flush()
        self.saved = os.dup(2)
        self.file = tempfile.TemporaryFile(mode='w+b')
        os.dup2(self.file.fileno(), 2)
        return self

    def __exit__(self, *exc):
        sys.stderr.flush()
        os.dup2(self.saved, 2)
        os.close(self.saved)
        self.file.seek(0)
        self.text = self.file.read().decode(errors='replace')
        self.file.close()
        return False


def _init_variant(args):
    """Import Mitsuba, choose and set the variant; a missing libLLVM becomes one clear line."""
    err = None
    with _CaptureStderr() as cap:
        import drjit as dr
        import mitsuba as mi
        variant = args.variant
        if variant is None:
            variant = DEFAULT_VARIANT
            if GPU_VARIANT in mi.variants() and dr.has_backend(dr.JitBackend.CUDA):
                variant = GPU_VARIANT
        if variant in mi.variants():
            try:
                mi.set_variant(variant)
            except Exception as e:                  # ImportError when the backend cannot start
                err = e
    if variant not in mi.variants():
        raise CLIError(f"Mitsuba variant '{variant}' does not exist; the variants are "
                       f"{', '.join(mi.variants())}")
    if args.debug and cap.text.strip():
        sys.stderr.write(cap.text)
    if err is not None:
        msg = str(err)
        if variant.startswith('llvm') and ('LLVM' in msg or 'libLLVM' in cap.text):
            where = os.environ.get('DRJIT_LIBLLVM_PATH')
            where = f" (DRJIT_LIBLLVM_PATH={where})" if where else ''
            raise CLIError(f"the LLVM backend could not be started: libLLVM >= 16 was not found{where}; "
                           f"install it (e.g. apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH "
                           f"to its libLLVM.so")
        if variant.startswith('cuda'):
            raise CLIError(f"variant '{variant}' needs a CUDA GPU and driver: {_error_text(err)}")
        raise CLIError(f"Mitsuba variant '{variant}' cannot be used: {_error_text(err)}")
    return variant


# ----------------------------------------------------------------------------- Ctrl-C
class _InterruptGuard:
    """SIGINT policy. Until a first pass has finished, Ctrl-C stops at once (nothing to write,
    exit 130). After that, the first Ctrl-C is noted and the render stops at the start of the
    next pass (see _stop_at_pass_start), keeping the finished passes, which are written; a
    second Ctrl-C aborts at once."""

    def __init__(self):
        self.requested = False
        self.presses = 0
        self.mode = 'raise'             # 'raise' (setup) | 'defer' (rendering, writing)
        self.old = None

    def install(self):
        if threading.current_thread() is threading.main_thread():
            self.old = signal.signal(signal.SIGINT, self._handler)
        return self

    def uninstall(self):
        if self.old is not None:
            signal.signal(signal.SIGINT, self.old)
            self.old = None

    @property
    def aborted(self):
        return self.presses >= 2

    def _handler(self, signum, frame):
        self.presses += 1
        self.requested = True
        if self.mode == 'raise' or self.presses >= 2:
            raise KeyboardInterrupt
        sys.stderr.write(f"\n{PROG}: interrupt: stopping after the current pass (Ctrl-C again to abort)\n")
        sys.stderr.flush()


def _stop_at_pass_start(integ, guard):
    """Make a requested stop happen where the integrator expects it: a KeyboardInterrupt
    raised at the start of its next pass, inside its own handler, which then develops the
    passes done. (Raised from the signal handler instead, it would often land inside a
    dr.while_loop being traced, which turns it into a RuntimeError that the integrator does not
    recognise, and the finished passes would be lost.)"""
    inner = getattr(type(integ), 'render_pass', None)
    if inner is None:
        return

    def render_pass(*a, **kw):
        if guard.requested:
            raise KeyboardInterrupt
        return inner(integ, *a, **kw)
    integ.render_pass = render_pass


# ----------------------------------------------------------------------------- progress
class _Progress:
    """tqdm bar on stderr: passes done, samples per second, time left."""

    def __init__(self, quiet, total_spp=None, budget_s=None, n_pixels=1):
        self.quiet = quiet
        self.n_pixels = n_pixels
        self.total_spp = total_spp
        self.budget_s = budget_s
        self.bar = None
        self.last_refresh = 0.0
        if quiet:
            return
        from tqdm import tqdm
        if budget_s is not None:
            fmt = '{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining} of ' + f'{budget_s:g} s' + '{postfix}]'
            total = budget_s
        else:
            fmt = '{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} spp [{elapsed}<{remaining}{postfix}]'
            total = total_spp
        self.bar = tqdm(total=total, desc='rendering', file=sys.stderr, bar_format=fmt, dynamic_ncols=True,
                        mininterval=0.2, leave=True, smoothing=0.3)

    def update(self, passes, spp_done, render_s):
        if self.bar is None:
            return
        now = time.perf_counter()
        if passes > 1 and now - self.last_refresh < 0.2:        # the first pass always shows
            return
        self.last_refresh = now
        rate = spp_done * self.n_pixels / render_s / 1e6 if render_s > 0 else 0.0
        self.bar.n = min(render_s, self.budget_s) if self.budget_s is not None else min(spp_done, self.total_spp)
        self.bar.set_postfix_str(f"{passes} pass{'es' if passes != 1 else ''}, {spp_done:g} spp, "
                                 f"{rate:.3g} M samples/s", refresh=False)
        self.bar.refresh()

    def close(self, passes=None, spp_done=None, render_s=None):
        """Show the final state (when given), then end the bar's line."""
        if self.bar is None:
            return
        if passes:
            self.last_refresh = float('-inf')
            self.update(passes, spp_done, render_s)
        self.bar.close()
        self.bar = None


# ----------------------------------------------------------------------------- integrator
def _max_depth_of(integrator):
    """The scene integrator's max_depth: bdpt's settings, or the value Mitsuba's integrators print."""
    settings = getattr(integrator, 'settings', None)
    if isinstance(settings, dict) and 'max_depth' in settings:
        return settings['max_depth']
    m = re.search(r'max_depth\s*=\s*(-?\d+)', str(integrator))
    return int(m.group(1)) if m else None


def _make_integrator(args, scene):
    """The integrator to render with, and its parameter values (for the header)."""
    import mitsuba as mi
    from .integrator import BDPTIntegrator
    from .params import PARAMS
    given = {p.name: getattr(args, p.name) for p in PARAMS if getattr(args, p.name) is not None}
    scene_integ = scene.integrator()
    if args.integrator == 'bdpt':
        params = {}
        if isinstance(scene_integ, BDPTIntegrator):
            params.update(scene_integ.settings)
        else:
            md = _max_depth_of(scene_integ) if scene_integ is not None else None
            if md is not None:
                params['max_depth'] = md
        params['statistics'] = True
        params.update(given)
        params = {k: v for k, v in params.items() if v is not None}
        try:
            integ = mi.load_dict({'type': 'bdpt', **params})
        except Exception as e:
            raise CLIError(_error_text(e)) from None
        return integ, dict(integ.settings)
    bdpt_only = [n for n in given if n not in SHARED_PARAMS]
    if bdpt_only:
        flags = ', '.join(_param_flags(next(p for p in PARAMS if p.name == n))[-1] for n in bdpt_only)
        raise CLIError(f"{flags}: bdpt option{'s' if len(bdpt_only) > 1 else ''}, not available with "
                       f"--integrator {args.integrator}")
    try:
        bare = mi.load_dict({'type': args.integrator})
    except Exception as e:
        raise CLIError(f"integrator {args.integrator!r}: {_error_text(e)}") from None
    same = (scene_integ is not None and not isinstance(scene_integ, BDPTIntegrator)
            and scene_integ.class_name() == bare.class_name())
    if same and not given:                          # the scene's own, with all its settings
        md = _max_depth_of(scene_integ)
        return scene_integ, ({} if md is None else {'max_depth': md})
    params = dict(given)
    if 'max_depth' not in params and scene_integ is not None:
        md = _max_depth_of(scene_integ)
        if md is not None:
            try:                                    # the scene's path length, if the plugin takes one
                return mi.load_dict({'type': args.integrator, 'max_depth': md, **params}), {'max_depth': md, **params}
            except Exception:
                pass
    try:
        return mi.load_dict({'type': args.integrator, **params}), params
    except Exception as e:
        raise CLIError(f"integrator {args.integrator!r}: {_error_text(e)}") from None


def _pass_seed(seed, i):
    """Seed of pass i with --time: pass 0 uses the seed itself (so it equals --spp with
    --pass-spp samples); later ones a 32-bit hash of (seed, i)."""
    if i == 0:
        return seed
    h = (seed ^ ((i * 0x9E3779B9) & 0xFFFFFFFF)) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    h ^= h >> 16
    return h


def _is_interrupt(e):
    while e is not None:
        if isinstance(e, KeyboardInterrupt):
            return True
        e = e.__cause__
    return False


def _compile_ms(dr):
    """Codegen + backend compile time (ms) of the JIT kernels since the last call; drains
    Dr.Jit's kernel history."""
    total = 0.0
    n_kernels = n_compiled = 0
    for k in dr.kernel_history():
        if k.get('type') != dr.KernelType.JIT:
            continue
        n_kernels += 1
        total += float(k.get('codegen_time', 0.0)) + float(k.get('backend_time', 0.0))
        if not k.get('cache_hit', 0):
            n_compiled += 1
    return total, n_kernels, n_compiled


class _Result:
    def __init__(self):
        self.image = None           # HxWx3 float64 sum of image * spp
        self.layers = None          # name -> {'weighted','unweighted'} sums (x spp)
        self.spp = 0.0              # spp accumulated (weights)
        self.passes = 0             # passes finished (internal ones for one --spp render)
        self.render_s = 0.0
        self.longest_pass_s = 0.0
        self.compile_ms = 0.0
        self.kernels = 0
        self.kernels_compiled = 0
        self.rays = None
        self.info = {}
        self.interrupted = False

    def add(self, img, spp, layers=None, rays=None):
        import numpy as np
        img = np.asarray(img, dtype=np.float64)
        if self.image is None:
            self.image = img * spp
        else:
            self.image += img * spp
        if layers is not None:
            if self.layers is None:
                self.layers = {n: {k: np.asarray(v, dtype=np.float64) * spp for k, v in d.items()}
                               for n, d in layers.items()}
            else:
                for n, d in layers.items():
                    for k, v in d.items():
                        self.layers[n][k] += np.asarray(v, dtype=np.float64) * spp
        if rays is not None:
            if self.rays is None:
                self.rays = dict(rays)
            else:
                for k, v in rays.items():
                    self.rays[k] = self.rays.get(k, 0) + v
        self.spp += spp

    def mean(self):
        img = self.image / self.spp
        layers = None
        if self.layers is not None:
            layers = {n: {k: v / self.spp for k, v in d.items()} for n, d in self.layers.items()}
        return img, layers


def _render(args, scene, integ, is_bdpt, guard, res):
    """Render (one call for --spp, passes for --time) into ``res``."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    sensor = scene.sensors()[0]
    crop = sensor.film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    timed = args.time is not None
    spp_total = args.spp or int(sensor.sampler().sample_count())
    progress = _Progress(args.quiet, total_spp=None if timed else spp_total,
                         budget_s=args.time, n_pixels=n_pixels)
    res.spp_requested = None if timed else spp_total
    if is_bdpt:
        _stop_at_pass_start(integ, guard)
    guard.mode = 'raise'                            # until a pass has finished: nothing to keep
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    _compile_ms(dr)                                 # drop what scene loading launched
    t_start = time.perf_counter()

    def one_render(spp, seed, spp_before, passes_before):
        state = {'passes': 0, 't_last': time.perf_counter()}

        def on_pass(done, total):
            guard.mode = 'defer'                    # a pass is done: from now on Ctrl-C keeps it
            now = time.perf_counter()
            res.longest_pass_s = max(res.longest_pass_s, now - state['t_last'])
            state['t_last'] = now
            state['passes'] += 1
            spp_now = spp_before + done / n_pixels
            progress.update(passes_before + state['passes'], round(spp_now, 3), now - t_start)

        if is_bdpt:
            integ.progress = on_pass
        t0 = time.perf_counter()
        try:
            img = mi.render(scene, integrator=integ, spp=spp, seed=seed)
            arr = np.array(img)[:, :, :3]
        finally:
            if is_bdpt:
                integ.progress = None
        guard.mode = 'defer'
        if guard.aborted:
            raise KeyboardInterrupt
        dt = time.perf_counter() - t0
        ms, nk, nc = _compile_ms(dr)
        res.compile_ms += ms
        res.kernels += nk
        res.kernels_compiled += nc
        if not is_bdpt:
            res.longest_pass_s = max(res.longest_pass_s, dt)
            return arr, spp, 1, None, None, False
        info = dict(integ.last_render_info)
        res.info = info
        layers = integ.strategy_images
        spp_done = info.get('samples', spp * n_pixels) / n_pixels
        interrupted = bool(info.get('interrupted'))
        if interrupted and layers is not None and info.get('samples'):
            # The layers carry the full render's 1/spp scale; rescale them to the samples traced,
            # as the integrator does for the image.
            scale = spp * n_pixels / info['samples']
            layers = {n: {k: v * scale for k, v in d.items()} for n, d in layers.items()}
        return arr, spp_done, state['passes'], layers, info.get('rays'), interrupted

    try:
        if not timed:
            try:
                arr, spp_done, passes, layers, rays, interrupted = one_render(spp_total, args.seed, 0, 0)
            except Exception as e:
                if _is_interrupt(e):
                    raise KeyboardInterrupt from None
                raise
            res.add(arr, spp_done, layers, rays)
            res.passes = passes
            res.interrupted = interrupted or guard.requested and spp_done < spp_total
        else:
            i = 0
            while True:
                if guard.requested:
                    res.interrupted = True
                    break
                t0 = time.perf_counter()
                presses = guard.presses
                try:
                    arr, spp_done, _, layers, rays, interrupted = one_render(
                        args.pass_spp, _pass_seed(args.seed, i), res.spp, res.passes)
                except Exception as e:
                    if not _is_interrupt(e):
                        raise
                    if res.spp == 0 or guard.aborted:
                        raise KeyboardInterrupt from None
                    res.interrupted = True          # this pass had nothing finished: drop it
                    break
                dt = time.perf_counter() - t0
                if not is_bdpt and guard.presses > presses and res.spp > 0:
                    res.interrupted = True          # Mitsuba may have cut this pass short: drop it
                    break
                res.add(arr, spp_done, layers, rays)
                res.passes += 1
                res.longest_pass_s = max(res.longest_pass_s, dt)
                i += 1
                elapsed = time.perf_counter() - t_start
                progress.update(res.passes, round(res.spp, 3), elapsed)
                if interrupted or guard.requested:
                    res.interrupted = True
                    break
                if elapsed + dt > args.time:        # the next pass would overrun the budget
                    break
    except KeyboardInterrupt:
        progress.close()
        if guard.aborted:
            raise Interrupted("aborted (second Ctrl-C); nothing was written") from None
        raise Interrupted("interrupted before the first pass finished; nothing was written") from None
    res.render_s = time.perf_counter() - t_start   # the render loop's wall time: what --time budgets
    progress.close(res.passes, round(res.spp, 3), res.render_s)
    res.n_pixels = n_pixels
    return res


# ----------------------------------------------------------------------------- reporting
def _all_strategies():
    """Every strategy the integrator can use, named as it names them: its Context with every
    flag on (whatever flags it has), so this list cannot drift from integrator.py."""
    from .integrator import Context

    class _Everything(Context):
        def __getattr__(self, name):
            if name.startswith('_'):
                raise AttributeError(name)
            return True
    try:
        return list(_Everything().strategies())
    except Exception:
        return []


def _features(info):
    """(name, needed?, why) for the parts of the integrator a scene may leave out."""
    if not info:
        return []
    return [
        ('light subpath pass', bool(info.get('light_pass')), 'needed by the light-tracing and connection strategies'),
        ('camera subpath pass', bool(info.get('camera_pass')), 'needed by the s=0, s=1 and connection strategies'),
        ('delta (specular) BSDF handling', bool(info.get('delta_handling')), 'the scene has a BSDF with a delta lobe'),
    ]


def _fmt_count(n):
    return f"{int(n):,}"


def _statistics(args, res, settings, variant, scene_path, defines, wall_s):
    """Ordered (key, value) pairs: the header attributes and the source of the summary."""
    import drjit as dr
    import mitsuba as mi
    from . import __version__
    stats = {}
    stats['integrator'] = args.integrator
    for k, v in settings.items():
        stats[f'param.{k}'] = 'automatic' if v is None else str(v).lower() if isinstance(v, bool) else v
    spp = res.spp
    stats['spp'] = f'{spp:g}'
    if args.time is not None:
        stats['time_budget_s'] = f'{args.time:g}'
        stats['pass_spp'] = args.pass_spp
    else:
        stats['spp_requested'] = res.spp_requested
    stats['passes'] = res.passes
    stats['seed'] = args.seed
    stats['interrupted'] = 'true' if res.interrupted else 'false'
    stats['scene'] = os.path.abspath(scene_path)
    stats['defines'] = ' '.join(f'{k}={v}' for k, v in defines.items())
    stats['variant'] = variant
    stats['version.bdpt_jit'] = __version__
    stats['version.mitsuba'] = mi.__version__
    stats['version.drjit'] = dr.__version__
    stats['resolution'] = f'{res.image.shape[1]}x{res.image.shape[0]}'
    stats['wall_time_s'] = f'{wall_s:.3f}'
    stats['render_time_s'] = f'{res.render_s:.3f}'
    stats['compile_time_s'] = f'{res.compile_ms / 1000:.3f}'
    stats['longest_pass_s'] = f'{res.longest_pass_s:.3f}'
    stats['kernels'] = res.kernels
    stats['kernels_compiled'] = res.kernels_compiled
    samples = int(round(spp * res.n_pixels))
    stats['samples'] = samples
    stats['msamples_per_s'] = f'{samples / res.render_s / 1e6:.4f}' if res.render_s > 0 else '0'
    if res.rays:
        for k, v in res.rays.items():
            stats[f'rays.{k}'] = v
    if args.integrator == 'bdpt' and res.info:
        used = list(res.info.get('strategies', []))
        stats['strategies'] = '; '.join(used)
        stats['strategies_left_out'] = '; '.join(s for s in _all_strategies() if s not in used)
        feats = _features(res.info)
        stats['features'] = '; '.join(n for n, on, _ in feats if on)
        stats['features_left_out'] = '; '.join(n for n, on, _ in feats if not on)
        if 'light_vertex_levels' in res.info:
            stats['light_vertex_levels'] = res.info['light_vertex_levels']
    if res.layers is not None:
        stats['layers'] = ' '.join(res.layers)
    return stats


def _summary(stats, res, out, png):
    p = lambda *a: print(*a)                        # noqa: E731
    params = ', '.join(f"{k[6:]}={v}" for k, v in stats.items() if k.startswith('param.'))
    p(f"{PROG}: {stats['scene']}")
    p(f"  integrator      {stats['integrator']}" + (f" ({params})" if params else ''))
    budget = (f", time budget {stats['time_budget_s']} s in passes of {stats['pass_spp']} spp"
              if 'time_budget_s' in stats else '')
    p(f"  image           {stats['resolution']}, {stats['spp']} spp reached in {stats['passes']} "
      f"pass{'es' if res.passes != 1 else ''}{budget}, seed {stats['seed']}, {stats['variant']}")
    wall, rend, comp = float(stats['wall_time_s']), float(stats['render_time_s']), float(stats['compile_time_s'])
    p(f"  time            wall {wall:.2f} s, render {rend:.2f} s, of which JIT compile {comp:.2f} s "
      f"({stats['kernels_compiled']} of {stats['kernels']} kernel launches compiled, the rest cached)")
    speed = f"{float(stats['msamples_per_s']):.4g} M samples/s"
    if rend - comp > 0.05 * rend and comp > 0:
        speed += f" ({stats['samples'] / (rend - comp) / 1e6:.4g} M samples/s without compiling)"
    p(f"  speed           {speed}; {_fmt_count(stats['samples'])} samples")
    if res.rays:
        r = res.rays
        total = r.get('rays', 0)
        zero = r.get('zero_contribution_rays', 0)
        pct = f" ({100.0 * zero / total:.1f}%)" if total else ''
        p(f"  rays traced     {_fmt_count(total)}: camera {_fmt_count(r.get('camera_rays', 0))}, "
          f"light {_fmt_count(r.get('light_rays', 0))}, shadow {_fmt_count(r.get('shadow_rays', 0))}")
        p(f"  zero-contrib.   {_fmt_count(zero)}{pct}: camera rays missed {_fmt_count(r.get('camera_rays_missed', 0))}, "
          f"light rays missed {_fmt_count(r.get('light_rays_missed', 0))}, shadow rays blocked "
          f"{_fmt_count(r.get('shadow_rays_blocked', 0))}")
    if 'strategies' in stats:
        p(f"  strategies      {stats['strategies'] or 'none (nothing in the scene emits)'}")
        if stats['strategies_left_out']:
            p(f"  left out        {stats['strategies_left_out']}")
        for name, on, why in _features(res.info):
            p(f"  {'needed' if on else 'left out':15} {name}" + (f" ({why})" if on else ''))
    if res.layers is not None:
        p(f"  layers          {len(res.layers)} strategy layers (weighted and unweighted) in the EXR")
    p(f"  wrote           {out}, {png}")


def _load_scene(mi, path, defines, integrator):
    """mi.load_file with the -D values. A scene whose integrator is a parameter (`$integrator`,
    as the bundled scenes have) gets the requested one, with the scene's own settings."""
    if 'integrator' not in defines:
        try:
            return mi.load_file(path, integrator=integrator, **defines)
        except Exception as e:
            text = str(e)
            if not ('unused parameters' in text and '$integrator=' in text):
                raise CLIError(_scene_error(e, path, defines)) from None
    try:
        return mi.load_file(path, **defines)
    except Exception as e:
        raise CLIError(_scene_error(e, path, defines)) from None


def _check_params(args):
    """Validate the integrator options against the table (before anything is loaded)."""
    from .params import PARAMS, ParameterError, check_value
    for p in PARAMS:
        v = getattr(args, p.name)
        if v is not None:
            try:
                setattr(args, p.name, check_value(p, v))
            except ParameterError as e:
                raise CLIError(f"{_param_flags(p)[0]}: {e}") from None


# ----------------------------------------------------------------------------- command
def cmd_render(args, guard):
    t_wall = time.perf_counter()
    defines = _parse_defines(args.defines)
    _check_params(args)
    if not os.path.exists(args.scene):
        raise CLIError(f"scene file not found: {args.scene}")
    if not os.path.isfile(args.scene):
        raise CLIError(f"scene path is not a file: {args.scene}")
    out = args.output or os.path.splitext(os.path.basename(args.scene))[0] + '.exr'
    png = _check_output(out)
    if args.integrator != 'bdpt' and args.strategy_images:
        raise CLIError(f"--strategies needs --integrator bdpt (not {args.integrator})")

    variant = _init_variant(args)
    import mitsuba as mi
    if args.quiet:
        mi.set_log_level(mi.LogLevel.Error)         # Mitsuba's warnings too
    import bdpt_jit
    bdpt_jit.register()
    scene = _load_scene(mi, args.scene, defines, args.integrator)
    if not scene.sensors():
        raise CLIError(f"the scene has no sensor: {args.scene}")
    integ, settings = _make_integrator(args, scene)
    is_bdpt = isinstance(integ, bdpt_jit.BDPTIntegrator)
    if is_bdpt:
        try:
            bdpt_jit.scene_check.check_scene(scene, scene.sensors()[0])
        except bdpt_jit.UnsupportedSceneError as e:
            raise CLIError(f"{e} (render it with another integrator, e.g. --integrator path)") from None

    res = _Result()
    _render(args, scene, integ, is_bdpt, guard, res)
    img, layers = res.mean()
    stats = _statistics(args, res, settings, variant, args.scene, defines, time.perf_counter() - t_wall)
    header = {HEADER_PREFIX + k: v for k, v in stats.items()}
    write_exr(out, img, header, layers)
    write_png(png, img)
    if not args.quiet:
        _summary(stats, res, out, png)
        sys.stdout.flush()
    if res.interrupted:
        print(f"{PROG}: interrupted: wrote the {res.spp:g} spp rendered so far"
              + (f" (of {res.spp_requested})" if res.spp_requested else '') + f" to {out} and {png}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    guard = _InterruptGuard().install()
    try:
        if args.command == 'render':
            return cmd_render(args, guard)
        return EXIT_USAGE
    except CLIError as e:
        if args.debug:
            raise
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return EXIT_ERROR
    except (Interrupted, KeyboardInterrupt) as e:
        if args.debug:
            raise
        msg = str(e) if isinstance(e, Interrupted) else 'interrupted; nothing was written'
        print(f"\n{PROG}: {msg}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:                          # anything else: still one line
        if args.debug:
            raise
        print(f"{PROG}: error: {_error_text(e)} (run with --debug for the traceback)", file=sys.stderr)
        return EXIT_ERROR
    finally:
        guard.uninstall()
        sys.stderr.flush()


if __name__ == '__main__':
    sys.exit(main())
