"""Ctrl-C while rendering: what a first and a second press do."""

import signal
import sys
import threading

from .errors import PROG


class InterruptGuard:
    """SIGINT policy. Until a first pass has finished (``mode`` 'raise'), Ctrl-C stops at once
    (nothing to write, exit 130). After that (``mode`` 'defer'), the first Ctrl-C is only noted
    (``requested``): the render stops where the next pass would start (for ``bdpt``, its
    ``RenderHooks.should_stop`` reads it), keeping the finished passes, which are written. A
    second Ctrl-C aborts at once (``aborted``).

    The stop is left to the pass boundary because a KeyboardInterrupt raised from the handler
    would often land inside a dr.while_loop being traced, which wraps it in a RuntimeError."""

    def __init__(self):
        self.requested = False
        self.presses = 0
        self.mode = 'raise'             # 'raise' (setup, first pass) | 'defer' (later passes, writing)
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
