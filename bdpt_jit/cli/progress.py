"""The progress bar on stderr while rendering."""

import sys
import time


class Progress:
    """tqdm bar on stderr: passes done, samples per second, time left (of the spp, or of the
    --time budget). Nothing with -q."""

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

    def note(self, text):
        """Show ``text`` in place of the passes' figures until the next pass (None: clear it)."""
        if self.bar is None:
            return
        self.bar.set_postfix_str(text or '', refresh=False)
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
