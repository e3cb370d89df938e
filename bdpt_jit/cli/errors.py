"""What the command does when something goes wrong: its exceptions, the one line it prints for
any error, and its exit statuses.

Exit status: 0 on success, 1 on an error (one line on stderr, no traceback unless ``--debug``),
2 on a usage error (argparse), 130 when interrupted (Ctrl-C)."""

import re

PROG = 'bdpt-jit'
EXIT_OK, EXIT_ERROR, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class CLIError(Exception):
    """An error the user can fix; printed as one line, exit status 1."""


class Interrupted(Exception):
    """Ctrl-C before anything could be written; exit status 130."""


_REFUSED = re.compile(r'^At dictionary node "[^"]*": failed to instantiate unknown plugin of type "bdpt": (?=bdpt: )')
_SRC_PREFIX = re.compile(r'\[[\w.+-]+:\d+\]\s*|\[[A-Z]\w*\]\s+')   # [parser.cpp:451], [PluginManager]


def error_text(e):
    """One line from a Mitsuba / Dr.Jit / plugin exception: the position it names (file, line,
    column) kept; source-location tags and Python tracebacks embedded by Mitsuba dropped."""
    while e.__cause__ is not None and ('drjit.custom' in str(e) or '(see above)' in str(e)):
        e = e.__cause__             # mi.render and dr.while_loop wrap the original exception
    text = str(e).strip() or type(e).__name__
    if 'Traceback (most recent call last)' in text:
        text = _traceback_line(text)
    text = _SRC_PREFIX.sub('', text)
    # a plugin constructor's refusal, which Mitsuba words 'failed to instantiate unknown plugin of
    # type "bdpt": bdpt: ...': the plugin's own sentence is the message
    text = _REFUSED.sub('', text)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return ' '.join(lines[:1] + [ln.lstrip('- ') for ln in lines[1:]]) if lines else type(e).__name__


def _traceback_line(text):
    """A message with a Python traceback inside (Mitsuba embeds them): its head, then the
    traceback's last line, or its last line from bdpt."""
    head, _, tb = text.partition('Traceback (most recent call last)')
    lines = [ln.strip() for ln in tb.splitlines() if ln.strip()]
    last = lines[-1] if lines else ''
    bdpt = [ln for ln in lines if ln.startswith('bdpt:') or re.match(r'\w+Error: bdpt:', ln)]
    if bdpt:
        last = bdpt[-1]
    last = re.sub(r'^\w+(Error|Exception): ', '', last)
    return head.rstrip().rstrip(':') + ': ' + last if head.strip() else last


def scene_error(e, scene_path, defines):
    """The message for a scene that mi.load_file refused, naming the -D values if they are
    the likely cause."""
    text = error_text(e)
    unused = re.findall(r'\$(\w+)=', text)
    if 'unused parameters' in text and unused:
        names = ', '.join(unused)
        return f"-D {names}: the scene {scene_path} has no parameter of that name (no <default name=\"...\"> or $name in it)"
    if defines and re.search(r'could not parse|out of bounds|invalid', text, re.I):
        given = ' '.join(f'-D {k}={v}' for k, v in defines.items())
        return f"cannot load scene: {text} (with {given})"
    return f"cannot load scene: {text}"

