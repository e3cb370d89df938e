"""The command line: the argument parser, the ``-D`` scene parameters, and the integrator
options, which come from the plugin's parameter table (``params.py``) with their names,
defaults, help and checks."""

import argparse
import re

from .errors import PROG, CLIError

DEFAULT_VARIANT = 'llvm_ad_rgb'
GPU_VARIANT = 'cuda_ad_rgb'


# ----------------------------------------------------------------------------- parameter options
def param_flags(p):
    """The options of parameter ``p`` of the table (the first is the one messages name)."""
    flags = ['--' + p.name.replace('_', '-')]
    if p.name == 'strategy_images':
        flags.append('--strategies')
    return flags


def _add_param_options(parser):
    from ..params import PARAMS
    g = parser.add_argument_group(
        'integrator parameters', 'the bdpt plugin\'s parameters (params.py); unset ones come from the '
        'scene\'s integrator if it is bdpt, else take their defaults (max_depth, rr_depth and '
        'hide_emitters from any scene integrator that has them); these three also apply to '
        'Mitsuba\'s integrators.')
    for p in PARAMS:
        default_text = p.default_text
        if p.name == 'statistics':
            default_text = 'true in this command'
        kw = dict(dest=p.name, default=None, help=f"{_plain(p.meaning)} (default: {default_text})")
        if p.type is bool:
            g.add_argument(*param_flags(p), action=argparse.BooleanOptionalAction, **kw)
        else:
            if p.choices:
                kw['choices'] = p.choices
            else:
                kw['metavar'] = p.type_name.upper()
            g.add_argument(*param_flags(p), type=p.type, **kw)


def params_markdown():
    """The integrator options of ``bdpt-jit render`` as a Markdown table, from the parameter
    table (docs/cli.md holds a copy; a test checks that it is current)."""
    from ..params import PARAMS
    rows = ['| option | plugin parameter | default | meaning |', '|---|---|---|---|']
    for p in PARAMS:
        flags = param_flags(p)
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


def check_params(args):
    """Validate the integrator options against the table (before anything is loaded)."""
    from ..params import PARAMS, ParameterError, check_value
    for p in PARAMS:
        v = getattr(args, p.name)
        if v is not None:
            try:
                setattr(args, p.name, check_value(p, v))
            except ParameterError as e:
                raise CLIError(f"{param_flags(p)[0]}: {e}") from None


def given_params(args):
    """The integrator options given on the command line: {parameter name: value}."""
    from ..params import PARAMS
    return {p.name: getattr(args, p.name) for p in PARAMS if getattr(args, p.name) is not None}


def option_of(name):
    """The option a message names for parameter ``name`` (the last of its flags)."""
    from ..params import PARAMS_BY_NAME
    return param_flags(PARAMS_BY_NAME[name])[-1]


# ----------------------------------------------------------------------------- value types
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


# ----------------------------------------------------------------------------- parser
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
    r.add_argument('--cluster', metavar='auto|local|ADDRESS', default=None,
                   help="render the samples on a Ray cluster, in chunks (docs/cluster.md): 'local' starts "
                        "a Ray instance for this machine's cores and GPUs, 'auto' joins the running cluster, "
                        "or a Ray address (needs pip install -e '.[cluster]')")
    r.add_argument('--chunk-spp', type=_positive_int, default=None, metavar='N',
                   help='with --cluster: samples per pixel of a chunk (one Ray task; default: the spp over '
                        'twice the cluster\'s slots, with --time --pass-spp)')
    r.add_argument('--denoise', action='store_true',
                   help="also denoise the image (Open Image Denoise on llvm_* variants, OptiX on cuda_*; "
                        "albedo and normal from a feature pass): denoised, albedo and normal EXR layers, and "
                        "the PNG from the denoised image. Needs pip install -e '.[denoise]'")
    r.add_argument('-q', '--quiet', action='store_true',
                   help='no progress bar and no summary (errors and interruptions are still reported)')
    r.add_argument('--debug', action='store_true', help='show tracebacks and Dr.Jit\'s own messages')
    _add_param_options(r)
    return ap


def parse_defines(defines):
    """The -D NAME=VALUE arguments as {name: value}."""
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
