"""The ``bdpt-jit`` command: render a Mitsuba scene file to a multi-layer EXR and a PNG.

    bdpt-jit render scenes/cornell-box.xml -o out/cornell-box.exr --spp 64
    bdpt-jit render scenes/caustic.xml --time 60 --strategies -D res=256

Integrator parameters (their option names, defaults and help) come from the same table as the
plugin (``params.py``). See ``docs/cli.md`` for the options, the EXR layout and its header keys.

Exit status: 0 on success, 1 on an error (one line on stderr, no traceback unless ``--debug``),
2 on a usage error, 130 when interrupted (Ctrl-C): after at least one finished pass the partial
render is written first, and the message says so.

The modules, one concern each: ``args`` (the parser, -D, the parameter options), ``session``
(one render command: variant, scene, integrator, then render, write, report), ``rendering``
(the render loop: --spp, --time, passes), ``interrupts`` (Ctrl-C), ``progress`` (the bar),
``outputs`` (EXR and PNG files), ``summary`` (header statistics and the printed summary),
``errors`` (exceptions, one-line messages, exit statuses)."""

import sys

from .args import build_parser, params_markdown
from .errors import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_USAGE, PROG, CLIError, Interrupted, error_text
from .interrupts import InterruptGuard
from .session import cmd_render

__all__ = ['main', 'build_parser', 'params_markdown', 'cmd_render', 'CLIError', 'Interrupted',
           'EXIT_ERROR', 'EXIT_USAGE', 'EXIT_INTERRUPTED']


def main(argv=None):
    """Entry point of ``bdpt-jit``; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    guard = InterruptGuard().install()
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
        print(f"{PROG}: error: {error_text(e)} (run with --debug for the traceback)", file=sys.stderr)
        return EXIT_ERROR
    finally:
        guard.uninstall()
        sys.stderr.flush()
