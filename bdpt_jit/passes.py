"""How a render is cut into passes (kernel launches), the seed of each pass, and the hooks
through which a caller follows a render and stops it between passes.

One seed scheme serves every caller: the plugin's own pass loop and the command's
``--time`` loop take the seed of pass ``i`` from ``pass_seed``."""

import drjit as dr
import mitsuba as mi

UNBOUNDED = 0x3FFFFFFF          # max_depth = -1, in edges
BYTES_PER_LIGHT_VERTEX = 144    # store.FIELDS: at most 35 words (with media), 9 packets of 4
BYTES_PER_SAMPLE = 1200         # camera and light loop state, film positions
MEMORY_BUDGET = 1 << 30         # the automatic pass size's budget when the machine cannot be asked
GIB = 1 << 30


def memory_budget():
    """Bytes a pass may use, from the machine (automatic samples_per_pass): on the CPU a sixth
    of the physical memory (1 to 16 GiB), on a GPU half of its free memory (nvidia-smi);
    MEMORY_BUDGET where neither can be read. Measured on the SmallVCM box (2 cores): one
    pass of 16 spp instead of three, +2% samples/s."""
    global _BUDGET
    if _BUDGET is not None:
        return _BUDGET
    budget = MEMORY_BUDGET
    variant = mi.variant() or ''
    try:
        if variant.startswith('cuda'):
            import subprocess
            out = subprocess.run(['nvidia-smi', '--query-gpu=memory.free', '--format=csv,noheader,nounits'],
                                 capture_output=True, text=True, timeout=10)
            free_mib = min(int(x) for x in out.stdout.split())
            budget = max(MEMORY_BUDGET, free_mib * (1 << 20) // 2)
        else:
            import os
            ram = os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES')
            budget = int(min(max(ram // 6, MEMORY_BUDGET), 16 * GIB))
    except Exception:
        budget = MEMORY_BUDGET
    _BUDGET = budget
    return budget


_BUDGET = None


def pass_seed_value(seed: int, i: int) -> int:
    """Seed of pass ``i`` of a render with ``seed``: ``(seed * 1000003 + i * 7919) mod 2^32``."""
    return (int(seed) * 1000003 + int(i) * 7919) & 0xFFFFFFFF


def pass_seed(seed, i):
    """``pass_seed_value`` as the kernels take it. ``seed`` is a Python int or a ``mi.UInt32``
    (Mitsuba's render API takes both; its own wrappers, the ``aov`` integrator and
    ``mi.render`` with parameters, pass the latter). The result is opaque: a literal would be
    baked into the kernels and recompile them for every seed."""
    if isinstance(seed, int):
        return dr.opaque(mi.UInt32, pass_seed_value(seed, i))
    s = mi.UInt32(seed)
    if dr.width(s) != 1:
        raise ValueError(f"bdpt: the seed must be one integer, got an array of {dr.width(s)}")
    # 32-bit wrap-around, as the int form (i * 7919 reduced first: the pilot's and the lattice's
    # pass indices make it exceed 32 bits, which a UInt32 cannot take)
    out = s * 1000003 + ((int(i) * 7919) & 0xFFFFFFFF)
    dr.make_opaque(out)
    return out


def light_capacity(strategies, max_depth_edges, unbounded):
    """Levels of light-vertex storage a pass allocates first (store.LightStore): vertices
    y_1 .. y_{max-2} for connections (a camera vertex and an edge follow), y_1 .. y_{max-1}
    for merges (a camera vertex at the same place follows)."""
    if strategies.trace_merge:
        return 8 if unbounded else max_depth_edges - 1
    if not strategies.trace_connect:
        return 0
    return 8 if unbounded else max_depth_edges - 2


def _pass_size(spp, n_pixels, bytes_per_sample, samples_per_pass):
    """(samples per pass from the parameter or the memory budget, spp per pass when a pass
    holds whole images)."""
    budget = samples_per_pass or max(memory_budget() // bytes_per_sample, 1)
    return budget, max(1, min(spp, budget // n_pixels))


def plan_passes(spp, n_pixels, bytes_per_sample, samples_per_pass=None):
    """Split spp x pixels samples into passes of whole pixels: yields (spp_in_pass,
    pixel_start, pixel_count). ``samples_per_pass``: the parameter (None: from the memory
    budget)."""
    budget, spp_pass = _pass_size(spp, n_pixels, bytes_per_sample, samples_per_pass)
    if budget >= n_pixels:
        done = 0
        while done < spp:
            k = min(spp_pass, spp - done)
            yield k, 0, n_pixels
            done += k
        return
    for _ in range(spp):
        for start in range(0, n_pixels, budget):
            yield 1, start, min(budget, n_pixels - start)


def count_passes(spp, n_pixels, bytes_per_sample, samples_per_pass=None):
    """How many passes plan_passes yields, without walking them (the command's --time renders
    ask for 2^30 spp)."""
    budget, spp_pass = _pass_size(spp, n_pixels, bytes_per_sample, samples_per_pass)
    if budget >= n_pixels:
        return -(-spp // spp_pass)
    return spp * -(-n_pixels // budget)


_INDEPENDENT = {}      # per variant: an `independent` sampler to clone (pass_sampler)


def pass_sampler(ctx, spp_pass, seed, index, n):
    """The sampler of the subpaths of ``n`` lanes of ``spp_pass`` samples a pixel, seeded with
    pass_seed(seed, index): a clone of the sensor's where that is `independent`, else of an
    `independent` one. Mitsuba 3.9.1's `stratified`, `multijitter` and `ldsampler` correlate a
    sample's dimensions with each other (at 4 spp a pixel, `stratified`'s first 1D and the next
    2D sample's first coordinate: P(both < 1/4) 0.0005 where 1/16 is due; `ldsampler`'s 1D
    values differ by multiples of 1 / sample_count at any count), which biases every estimator
    drawing a path from them, Mitsuba's `path` included (docs/coverage.md). The sensor's sampler
    places the pixel samples only (pixel_sampler)."""
    scene_sampler = ctx.sensor.sampler()
    if scene_sampler.class_name() == 'IndependentSampler':
        sampler = scene_sampler.clone()
    else:
        if mi.variant() not in _INDEPENDENT:
            _INDEPENDENT[mi.variant()] = mi.load_dict({'type': 'independent'})
        sampler = _INDEPENDENT[mi.variant()].clone()
    sampler.set_sample_count(spp_pass)
    sampler.seed(pass_seed(seed, index), n)
    return sampler


def pixel_sampler(ctx, spp_pass, seed, index, n):
    """The sensor's sampler for the positions in their pixels of ``n`` lanes of ``spp_pass``
    consecutive samples a pixel (one 2D sample each: the stratification a Mitsuba user chose
    it for, among each pixel's samples where its sample count allows), seeded as pass_sampler
    with ``index``; None where the sensor's sampler is `independent` (pass_sampler's then)."""
    sampler = ctx.sensor.sampler()
    if sampler.class_name() == 'IndependentSampler':
        return None
    sampler = sampler.clone()
    sampler.set_sample_count(spp_pass)
    per_pixel = spp_pass if sampler.sample_count() % spp_pass == 0 else 1
    sampler.set_samples_per_wavefront(per_pixel)    # (a clone keeps the last render's)
    sampler.seed(pass_seed(seed, index) ^ 0x5F3759DF, n)
    return sampler


class PassState:
    """What the kernels of one pass share besides the Context (a plain class: Dr.Jit does not
    traverse it, so nothing here becomes loop state). Set by the integrator's render_pass."""

    def __init__(self, sampler, n, spp_pass, pixel_start, film, mis):
        self.sampler = sampler          # the pass's sampler, seeded for its n samples
        self.pixel_sampler = None       # the sensor's sampler for the pixel positions (passes.pixel_sampler), or None
        self.n = n                      # samples in the pass (one camera and one light subpath each)
        self.spp_pass = spp_pass        # consecutive samples per pixel
        self.pixel_start = pixel_start  # the pass's first crop pixel (in units of pixel_stride)
        self.pixel_stride = 1           # camera samples in every pixel_stride-th crop pixel (auto's pilot: lattice_step)
        self.pixel_run = 1              # or in every pixel_stride-th run of pixel_run consecutive ones (auto's trials: rows)
        self.pixel_offset = 0           # from this crop pixel (auto's trials: their first row's)
        self.film = film                # film.FilmAccumulator
        self.mis = mis                  # mis.MIS of the pass (MIS.for_pass: its merging radius)
        self.spectral = None            # spectral variants: (wavelengths, their sampling weight) per sample
        self.u_wl = None                # spectral variants: the wavelength sample that chose them
        self.store = None               # store.LightStore of the light vertices, or None
        self.schedule = None            # merge.MergeSchedule of the pass's iterations (vcm, vm), or None
        self.merger = None              # merge.Merger (vcm, vm), or None
        self.beams = None               # beams.BeamGather (vcm, vm, gray media), or None
        self.n_light = n                # light subpaths of the pass (the light vertex cache: n_L)
        self.light_sampler = sampler    # their sampler (the cache: its own, seeded for n_L)
        self.splat_scale = None         # the light image's scale per splat, or None: the Context's
        self.cache = None               # light_cache.LightCache of the pass, or None (classic)
        self.pilot = False              # light_cache.pilot: a light pass that only counts vertices
        self.mis_light = None           # the light subpaths' mis.MIS where it is not ``mis`` (the cache
        #                                 with merges: each light subpath's own iteration's eta)
        self.vpp = None                 # per-pixel counts (pixel_counts.py): V / n_L of the cache's pilot
        self.n_lt = None                # and the pass's n_lt = n_L / n


class RenderHooks:
    """What a caller may attach to a ``bdpt`` integrator (``integrator.hooks``) to follow a
    render and stop it. Both are called between passes, never inside a kernel:

    - ``on_pass(samples_done, samples_total)`` after each finished pass;
    - ``should_stop()`` before each pass after the first: True ends the render there, and the
      finished passes are developed as a render of that many samples (the light image
      rescaled), with ``last_render_info['interrupted']`` set;
    - ``on_decided()`` after each of technique auto's decisions (its pilots and trials), which
      are not passes: a caller that times passes starts the next one's clock there;
    - ``decision_over()`` between the trial renders of technique auto's decisions: True ends
      the timing there, and the decision chooses among the candidates timed so far (pt and the
      cheapest bidirectional one are timed first, auto.clear_pt): a ``--time`` render's first
      decision, whose kernels compile on a new scene, keeps to a share of the budget.

    A Ctrl-C (KeyboardInterrupt) during a pass after the first has the same effect as
    ``should_stop``."""

    def __init__(self, on_pass=None, should_stop=None, on_decided=None, decision_over=None):
        self.on_pass = on_pass
        self.should_stop = should_stop
        self.on_decided = on_decided
        self.decision_over = decision_over

    def decision_ends(self):
        return self.decision_over is not None and bool(self.decision_over())

    def decided(self):
        if self.on_decided is not None:
            self.on_decided()

    def passed(self, done, total):
        if self.on_pass is not None:
            self.on_pass(done, total)

    def stop(self):
        return self.should_stop is not None and bool(self.should_stop())


def caused_by_interrupt(exc):
    """A KeyboardInterrupt, or an error raised because of one (Ctrl-C while Dr.Jit traces a
    loop arrives as a RuntimeError caused by it)."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False
