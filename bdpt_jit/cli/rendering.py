"""The render itself: one ``mi.render`` call for ``--spp``; for ``--time``, bdpt's own pass
loop stopped by its ``should_stop`` hook, or a loop of ``mi.render`` calls for Mitsuba's
integrators. Progress, Ctrl-C and Dr.Jit's kernel statistics are followed pass by pass.

Ctrl-C (interrupts.InterruptGuard): before a first pass has finished, the render stops at once
and nothing is written (``Interrupted``); after, the render stops where the next pass would
start and the finished passes are kept (``Result.interrupted``)."""

import time

from .errors import Interrupted
from .progress import Progress

# --time with bdpt: the spp the integrator is asked for (a power of two, so that its 1/spp
# scales are exact); its should_stop hook ends the render long before.
TIMED_SPP = 1 << 30
# --time with technique auto: the share of the budget after which its decision times no further
# candidate and chooses among those it has timed (passes.RenderHooks.decision_over). A first
# decision on a new scene compiles each candidate's kernels (10-20 s on 2 cores) and ran past
# short budgets (22 s of a 20 s one, one pass rendered); warm, it takes ~10% of 16 s.
DECISION_SHARE = 0.5


class KernelCounter:
    """Dr.Jit's kernel history while rendering: JIT kernel launches, those compiled (not found
    in the cache), and their code generation plus backend compile time."""

    def __init__(self):
        self.launched = 0
        self.compiled = 0
        self.compile_ms = 0.0
        self._flag = None

    def start(self):
        import drjit as dr
        from ..stats import KERNEL_OBSERVERS
        self._flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                         # drop what scene loading launched
        KERNEL_OBSERVERS.append(self.count)         # (and what others drain: technique auto's trials)

    def count(self, history):
        """Count the JIT kernels of ``history`` (Dr.Jit's kernel history entries)."""
        import drjit as dr
        for k in history:
            if k.get('type') != dr.KernelType.JIT:
                continue
            self.launched += 1
            self.compile_ms += float(k.get('codegen_time', 0.0)) + float(k.get('backend_time', 0.0))
            if not k.get('cache_hit', 0):
                self.compiled += 1

    def drain(self):
        """Count the kernels launched since the last call (drains Dr.Jit's history)."""
        from ..stats import drain_kernel_history
        drain_kernel_history()                      # (this counter is one of its observers)

    def stop(self):
        import drjit as dr
        from ..stats import KERNEL_OBSERVERS
        self.drain()
        if self.count in KERNEL_OBSERVERS:
            KERNEL_OBSERVERS.remove(self.count)
        dr.set_flag(dr.JitFlag.KernelHistory, self._flag)


class PassClock:
    """The render's wall time, its passes' durations, and those of its sweeps: passes that
    end with every pixel at the same spp (every pass, unless bdpt cuts one spp of the image
    into pixel ranges to fit its memory budget)."""

    def __init__(self):
        self.t_start = self.t_last = self.t_sweep = time.perf_counter()
        self.longest_s = 0.0
        self.sweep_s = 0.0

    def lap(self, sweep_ends=True):
        """A pass has ended: its duration is the time since the previous one ended."""
        now = time.perf_counter()
        self.longest_s = max(self.longest_s, now - self.t_last)
        self.t_last = now
        if sweep_ends:
            self.sweep_s = now - self.t_sweep
            self.t_sweep = now

    def skip(self):
        """Time up to now is no pass's (technique auto's decision: RenderHooks.on_decided), so
        that the next pass's duration, and a --time render's estimate of the next one, leave it
        out (with it in, a 64 x 64 Cornell box with --time 6 stopped after one pass: its 4.7 s
        choice made the next pass look too long)."""
        self.t_last = self.t_sweep = time.perf_counter()

    def elapsed(self):
        return time.perf_counter() - self.t_start

    def next_sweep_overruns(self, budget_s):
        """The next sweep, if it takes as long as the last one, would end after the budget."""
        return self.elapsed() + self.sweep_s > budget_s


class Result:
    """What a render produced: the image (an spp-weighted sum of the passes' images), the
    strategy layers and ray counts of bdpt, and the statistics of the render loop."""

    def __init__(self, n_pixels, spp_requested):
        self.n_pixels = n_pixels
        self.spp_requested = spp_requested  # --spp or the scene's count; None with --time
        self.image = None           # HxWx3 float64 sum of image * spp
        self.spp = 0.0              # spp accumulated (weights)
        self.layers = None          # bdpt: name -> {'weighted', 'unweighted'} images
        self.rays = None            # bdpt: ray counters (last_render_info['rays'])
        self.info = {}              # bdpt: last_render_info
        self.passes = 0             # passes finished (bdpt's own passes for a bdpt render)
        self.render_s = 0.0
        self.longest_pass_s = 0.0
        self.kernels = KernelCounter()
        self.interrupted = False

    def add(self, img, spp):
        import numpy as np
        img = np.asarray(img, dtype=np.float64)
        self.image = img * spp if self.image is None else self.image + img * spp
        self.spp += spp

    def mean(self):
        """(the image, the strategy layers or None)."""
        return self.image / self.spp, self.layers


def render(args, scene, integ, is_bdpt, guard):
    """Render (one call for --spp, passes for --time); returns a Result."""
    sensor = scene.sensors()[0]
    crop = sensor.film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    timed = args.time is not None
    res = Result(n_pixels, None if timed else args.spp or int(sensor.sampler().sample_count()))
    progress = Progress(args.quiet, total_spp=res.spp_requested, budget_s=args.time, n_pixels=n_pixels)
    guard.mode = 'raise'                            # until a pass has finished: nothing to keep
    res.kernels.start()
    clock = PassClock()
    try:
        if is_bdpt:
            _render_bdpt(args, scene, integ, guard, res, progress, clock)
        elif timed:
            _render_mitsuba_passes(args, scene, integ, guard, res, progress, clock)
        else:
            _render_mitsuba_once(args, scene, integ, guard, res, clock)
    except KeyboardInterrupt:
        progress.close()
        if guard.aborted:
            raise Interrupted("aborted (second Ctrl-C); nothing was written") from None
        raise Interrupted("interrupted before the first pass finished; nothing was written") from None
    finally:
        res.kernels.stop()
    res.render_s = clock.elapsed()                  # the render loop's wall time: what --time budgets
    res.longest_pass_s = clock.longest_s
    progress.close(res.passes, round(res.spp, 3), res.render_s)
    return res


def _mi_render(scene, integ, spp, seed):
    """mi.render as an HxWxC array: colour (3, or 1 in a monochrome variant), then bdpt's AOV
    channels if it has any (alpha dropped); a Ctrl-C that arrives wrapped becomes a
    KeyboardInterrupt."""
    import mitsuba as mi
    import numpy as np
    from ..passes import caused_by_interrupt
    try:
        arr = np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed))
        n_aov = len(getattr(integ, 'aov_channels', ()))
        colour = arr[:, :, :arr.shape[2] - n_aov][:, :, :3]
        return np.concatenate([colour, arr[:, :, arr.shape[2] - n_aov:]], axis=2) if n_aov else colour
    except Exception as e:
        if caused_by_interrupt(e):
            raise KeyboardInterrupt from None
        raise


def _render_bdpt(args, scene, integ, guard, res, progress, clock):
    """One bdpt render. With --time it asks for TIMED_SPP samples per pixel in passes of
    --pass-spp (session.prepare_bdpt set samples_per_pass), and its should_stop hook ends it
    when the next pass would overrun the budget (only where every pixel has the same spp).
    Ctrl-C ends it the same way, after any pass (--spp too)."""
    from ..passes import RenderHooks
    timed = args.time is not None
    stopped_for = []                                # why should_stop ended the render
    sweep_ended = [False]

    def on_pass(done, total):
        guard.mode = 'defer'                        # a pass is done: from now on Ctrl-C keeps it
        sweep_ended[0] = done % res.n_pixels == 0
        clock.lap(sweep_ended[0])
        res.passes += 1
        res.kernels.drain()
        progress.update(res.passes, round(done / res.n_pixels, 3), clock.elapsed())

    def should_stop():
        if guard.requested:
            stopped_for.append('interrupt')
        elif timed and sweep_ended[0] and clock.next_sweep_overruns(args.time):
            stopped_for.append('budget')
        return bool(stopped_for)

    def on_decided():
        clock.skip()
        progress.note(None)

    def decision_over():
        return timed and clock.elapsed() >= DECISION_SHARE * args.time

    integ.hooks = RenderHooks(on_pass=on_pass, should_stop=should_stop, on_decided=on_decided,
                              decision_over=decision_over)
    if getattr(integ, 'technique', None) == 'auto':   # its first decision runs before any pass
        progress.note('technique auto: pilots and trials')
    try:
        img = _mi_render(scene, integ, TIMED_SPP if timed else res.spp_requested, args.seed)
    finally:
        integ.hooks = RenderHooks()
    guard.mode = 'defer'
    if guard.aborted:
        raise KeyboardInterrupt
    info = dict(integ.last_render_info)
    spp_done = info['samples'] / res.n_pixels
    res.add(img, spp_done)
    # The integrator's layers, like its image, are scaled to the samples it traced (an
    # interrupted render's too): they are used as they are.
    res.layers = integ.strategy_images
    res.rays = info.get('rays')
    res.info = info
    stopped = bool(info.get('interrupted')) and stopped_for != ['budget']
    res.interrupted = stopped or guard.requested and (timed or spp_done < res.spp_requested)


def _render_mitsuba_once(args, scene, integ, guard, res, clock):
    """--spp with a Mitsuba integrator: one mi.render call."""
    img = _mi_render(scene, integ, res.spp_requested, args.seed)
    guard.mode = 'defer'
    if guard.aborted:
        raise KeyboardInterrupt
    clock.lap()
    res.add(img, res.spp_requested)
    res.passes = 1


def _render_mitsuba_passes(args, scene, integ, guard, res, progress, clock):
    """--time with a Mitsuba integrator: mi.render calls of --pass-spp, pass i with seed
    passes.pass_seed_value(seed, i), until the next one would overrun the budget."""
    from ..passes import pass_seed_value
    i, cut_short = 0, False
    while not guard.requested:
        presses = guard.presses
        try:
            img = _mi_render(scene, integ, args.pass_spp, pass_seed_value(args.seed, i))
        except KeyboardInterrupt:
            if res.spp == 0 or guard.aborted:
                raise
            cut_short = True                        # this pass had nothing finished: drop it
            break
        guard.mode = 'defer'
        if guard.aborted:
            raise KeyboardInterrupt
        if guard.presses > presses and res.spp > 0:
            cut_short = True                        # Mitsuba may have cut this pass short: drop it
            break
        clock.lap()
        res.add(img, args.pass_spp)
        res.passes += 1
        res.kernels.drain()
        i += 1
        progress.update(res.passes, round(res.spp, 3), clock.elapsed())
        if clock.next_sweep_overruns(args.time):
            break
    res.interrupted = cut_short or guard.requested
