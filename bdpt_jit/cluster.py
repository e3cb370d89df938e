"""One image's samples rendered on a Ray cluster (``bdpt-jit render SCENE --cluster ...``).

The driver cuts the render into chunks of consecutive passes of the integrator's own pass plan
(``passes.plan_passes``); each chunk is one Ray task that loads the scene on its worker and
renders its passes with the project's one seed scheme (pass ``i`` seeded by
``passes.pass_seed(seed, i)``), for ``vcm``/``vm`` from the merge iteration those passes would
have had in one process. Every chunk builds its context for the render's *total* spp, so its
light image carries the render's 1/spp splat scale (applied once, for the total) and its
strategy layers the render's 1/spp camera scale: the driver only adds the chunks' camera blocks
(values and filter weights), light blocks, layers and ray counts, and develops one film, with
the light image rescaled only if fewer samples than planned were finished. With the same chunk
plan the image is the one the same passes give in one process (``render_chunks_locally``), to
float32 rounding (the driver sums in float64).

Mitsuba's own integrators (``path``, ``ptracer``, ...) run as chunks of one ``mi.render`` call
each, chunk ``k`` seeded with ``passes.pass_seed_value(seed, k)`` (the command's ``--time``
scheme); the driver averages them weighted by their spp.

The integrator's internals are used in two functions only, ``render_chunk_arrays`` (worker)
and ``develop_sum`` (driver); update those when the integrator changes.

Ray is an optional extra (``pip install -e '.[cluster]'``). See docs/cluster.md."""

import dataclasses
import math
import os
import re
import time
import uuid
from typing import Any, Callable, Optional

INSTALL_HINT = "pip install -e '.[cluster]'"
MAX_RETRIES = 3                 # reruns of a chunk whose worker process or node died
POLL_S = 0.2                    # how often the driver looks at stop requests while chunks run
CANCEL_GRACE_S = 5.0            # how long cancelled chunks are waited for before the driver goes on


class ClusterError(Exception):
    """A cluster render failed; the message is one line naming the scene and the cause."""


class ChunkFailed(Exception):
    """Raised on a worker: a chunk could not be rendered (bad input, import failure); one line."""


@dataclasses.dataclass
class Job:
    """Everything a chunk needs; pickled to every worker.

    scene_file: absolute path on the driver; defines: the -D values (strings); integrator: the
    plugin's properties for mi.load_dict (None: the scene's own integrator); spp: the render's
    total spp (the 1/spp scales); variant: the driver's (a worker runs its cuda_ or llvm_ twin);
    bdpt: chunks are ranges of bdpt's passes, else mi.render calls; files: [an ObjectRef of
    the scene's folder, zipped] when it travels through Ray's object store (None: workers read
    ``scene_file`` where it is); hook: called on the worker as
    hook(chunk_index, attempt) before a chunk renders (tests and instrumentation)."""
    scene_file: str
    defines: dict
    integrator: Optional[dict]
    integrator_type: str
    spp: int
    seed: int
    variant: str
    n_pixels: int
    bdpt: bool
    files: Optional[list] = None
    hook: Optional[Callable] = None
    token: str = dataclasses.field(default_factory=lambda: uuid.uuid4().hex)


@dataclasses.dataclass
class Chunk:
    """Chunk ``index``: bdpt's passes [first_pass, end_pass) of the pass plan (``passes``: their
    (spp, pixel_start, pixel_count)) with the merge iteration before them; a Mitsuba
    integrator's chunk: one mi.render of ``spp`` with ``seed``."""
    index: int
    samples: int
    first_pass: int = 0
    end_pass: int = 0
    passes: list = dataclasses.field(default_factory=list)
    merge_iteration: int = 0
    spp: int = 0
    seed: int = 0


# ----------------------------------------------------------------------------- planning
def iter_chunks(job, chunk_spp, passes=()):
    """The chunk plan: consecutive passes of bdpt's pass plan ``passes`` (``pass_plan``; an
    iterable, endless with --time) grouped until a chunk holds at least chunk_spp x pixels
    samples (so a chunk ends where a sweep of the image ends: passes of pixel ranges never
    straddle one); for a Mitsuba integrator, mi.render calls of chunk_spp (the last shorter)."""
    if not job.bdpt:
        yield from _mitsuba_chunks(job, chunk_spp)
        return
    target = chunk_spp * job.n_pixels
    index, first, merge_it, samples, merge_next, end, group = 0, 0, 0, 0, 0, 0, []
    for end, p in enumerate(passes, 1):
        group.append(tuple(p))
        samples += p[0] * p[2]
        merge_next += p[0]                      # integrator.render_pass adds spp_pass per pass
        if samples >= target:
            yield Chunk(index, samples, first, end, group, merge_it)
            index, first, merge_it, samples, group = index + 1, end, merge_next, 0, []
    if samples:
        yield Chunk(index, samples, first, end, group, merge_it)


def _mitsuba_chunks(job, chunk_spp):
    from .passes import pass_seed_value
    done, k = 0, 0
    while job.spp is None or done < job.spp:
        n = chunk_spp if job.spp is None else min(chunk_spp, job.spp - done)
        yield Chunk(k, n * job.n_pixels, spp=n, seed=pass_seed_value(job.seed, k))
        done, k = done + n, k + 1


def pass_plan(integ, scene, spp, chunk_spp):
    """bdpt's passes for a cluster render (a list; a generator for --time's endless spp):
    ``samples_per_pass`` as given, or the automatic size capped at one chunk, so that a chunk
    is whole passes; returns (passes, samples_per_pass used)."""
    from .passes import memory_budget, plan_passes
    sensor = scene.sensors()[0]
    crop = sensor.film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    per_pass = integ.settings['samples_per_pass']
    if per_pass is None:
        ctx = integ.make_context(scene, sensor, spp)
        per_pass = min(max(memory_budget() // integ.bytes_per_sample(ctx), 1), chunk_spp * n_pixels)
        del ctx
    passes = plan_passes(spp, n_pixels, 1, per_pass)
    return (passes if spp >= 1 << 24 else list(passes)), per_pass


# ----------------------------------------------------------------------------- integrator interface
def render_chunk_arrays(integ, scene, job, chunk):
    """Render one chunk in this process and return its arrays. THE ONLY PLACE (with
    ``develop_sum``) that calls the integrator's internals: make_context for the render's total
    spp (so the splat and layer scales are the total's), a FilmAccumulator, merge_iteration set
    to the chunk's, render_pass for each of its passes, render_info, then the camera and light
    blocks (acc.cam / acc.lt tensors), the strategy layers (ctx.layers.images) and the ray
    counts (ctx.stats.totals) as numpy."""
    import numpy as np
    from .film import FilmAccumulator
    sensor = scene.sensors()[0]
    ctx = integ.make_context(scene, sensor, job.spp)
    acc = FilmAccumulator(sensor.film(), ctx.aov_names)
    integ.merge_iteration = chunk.merge_iteration
    levels = 0
    # pass i of the render's plan: render_pass seeds it with passes.pass_seed(seed, i)
    for i, (spp_pass, pixel_start, pixel_count) in enumerate(chunk.passes, chunk.first_pass):
        levels = max(levels, integ.render_pass(ctx, acc, job.seed, i, spp_pass, pixel_start, pixel_count))
    info = integ.render_info(ctx, job.spp, job.n_pixels, chunk.samples, False, levels)
    return {
        'cam': np.array(acc.cam.tensor(), dtype=np.float32),
        'lt': np.array(acc.lt.tensor(), dtype=np.float32),
        'layers': ctx.layers.images(1.0) if ctx.layers is not None else None,
        'rays': dict(ctx.stats.totals) if ctx.stats is not None else None,
        'aov_names': list(ctx.aov_names),
        'info': info,
    }


class _Block:
    """An image block's stand-in for FilmAccumulator.develop: only ``tensor()`` is read."""

    def __init__(self, array):
        import mitsuba as mi
        self._tensor = mi.TensorXf(array)

    def tensor(self):
        return self._tensor


def develop_sum(scene, cam, lt, aov_names, light_scale):
    """The driver's film: the summed camera block (values and filter weights) and light block
    developed as the integrator develops one render (FilmAccumulator.develop, the light image
    times ``light_scale``: 1 when every planned sample was rendered). Returns an HxWxC array."""
    import numpy as np
    from .film import FilmAccumulator
    acc = FilmAccumulator(scene.sensors()[0].film(), aov_names)
    acc.cam = _Block(np.asarray(cam, dtype=np.float32))
    acc.lt = _Block(np.asarray(lt, dtype=np.float32))
    return np.array(acc.develop(light_scale))


# ----------------------------------------------------------------------------- worker
_SCENE_CACHE = {}               # (job token, variant) -> (scene, path): later chunks of a job on this process


def worker_variant(variant, gpu):
    """The variant a worker renders with: the cuda_ twin of ``variant`` with a GPU, else llvm_."""
    for prefix in ('cuda_', 'llvm_'):
        if variant.startswith(prefix):
            return ('cuda_' if gpu else 'llvm_') + variant[len(prefix):]
    return variant


def _node_and_attempt():
    """(node address, attempt number of this task: 0 first, 1 for its first rerun, GPU
    assigned, CPUs assigned) under Ray; ('local', 0, False, None) in-process."""
    try:
        import ray
        if not ray.is_initialized():
            return 'local', 0, False, None
        from ray._private import worker as _w          # attempt number: no public API in Ray 2.60
        attempt = _w.global_worker.core_worker.get_current_task_attempt_number()
        cpus = ray.get_runtime_context().get_assigned_resources().get('CPU')
        return ray.util.get_node_ip_address(), int(attempt), bool(ray.get_gpu_ids()), cpus
    except Exception:
        return 'local', 0, False, None


def _start_worker(job, gpu, cpus):
    """Set the variant and register the plugin on this worker, Dr.Jit's CPU threads to the
    task's CPUs (LLVM); one clear error if it cannot."""
    variant = worker_variant(job.variant, gpu)
    try:
        import drjit as dr
        import mitsuba as mi
        if mi.variant() != variant:
            mi.set_variant(variant)
        import bdpt_jit
        threads = max(int(cpus), bdpt_jit.MIN_THREADS) if cpus else None     # (one hangs on .exr files)
        if threads and variant.startswith('llvm_') and dr.thread_count() != threads:
            dr.set_thread_count(threads)
        bdpt_jit.register()
    except Exception as e:
        raise ChunkFailed(f"the worker cannot import the bdpt_jit plugin with Mitsuba variant {variant}: "
                          f"{type(e).__name__}: {e}") from None
    return variant


def pack_folder(folder):
    """The scene's folder as zip bytes (what travels to the workers), without caches and VCS."""
    import io
    import zipfile
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, 'w', zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        for root, dirs, files in os.walk(folder):
            dirs[:] = [d for d in dirs if d not in ('__pycache__', '.git')]
            for f in files:
                full = os.path.join(root, f)
                z.write(full, os.path.relpath(full, folder))
    return buf.getvalue()


def _unpacked_folder(job):
    """The job's scene folder on this node, unpacked once per node (atomically: into a
    temporary folder, then renamed); folders of jobs older than a day are removed."""
    import io
    import shutil
    import tempfile
    import zipfile
    import ray
    base = os.path.join(tempfile.gettempdir(), 'bdpt_jit_cluster')
    folder = os.path.join(base, job.token)
    if os.path.isdir(folder):
        return folder
    os.makedirs(base, exist_ok=True)
    for old in os.listdir(base):
        p = os.path.join(base, old)
        try:        # (another worker may rename its temporary folder between listdir and here)
            stale = time.time() - os.path.getmtime(p) > 86400
        except FileNotFoundError:
            continue
        if stale:
            shutil.rmtree(p, ignore_errors=True)
    tmp = tempfile.mkdtemp(prefix=job.token + '.', dir=base)
    zipfile.ZipFile(io.BytesIO(ray.get(job.files[0]))).extractall(tmp)
    try:
        os.rename(tmp, folder)
    except OSError:                                 # another worker of this node was first
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _worker_scene(job, variant):
    """The scene on this worker (cached for the job's later chunks); returns ((scene, the path
    it was loaded from), load seconds)."""
    key = (job.token, variant)
    if key in _SCENE_CACHE:
        return _SCENE_CACHE[key], 0.0
    from .cli.errors import CLIError
    from .cli.session import load_scene
    import mitsuba as mi
    t0 = time.perf_counter()
    path = job.scene_file
    if job.files is not None:
        path = os.path.join(_unpacked_folder(job), os.path.basename(job.scene_file))
    try:
        scene = load_scene(mi, path, job.defines, job.integrator_type)
    except CLIError as e:
        raise ChunkFailed(str(e)) from None
    _SCENE_CACHE.clear()
    _SCENE_CACHE[key] = (scene, path)
    return (scene, path), time.perf_counter() - t0


def _integrator(job, scene):
    import mitsuba as mi
    if job.integrator is None:
        return scene.integrator()
    return mi.load_dict(dict(job.integrator))


def run_chunk(job, chunk):
    """A chunk's task body (a Ray task, or in-process for ``render_chunks_locally``): the
    scene loaded, the chunk rendered, its arrays and timings returned."""
    t0 = time.perf_counter()
    node, attempt, gpu, cpus = _node_and_attempt()
    variant = _start_worker(job, gpu, cpus)
    if job.hook is not None:
        job.hook(chunk.index, attempt)
    (scene, scene_path), load_s = _worker_scene(job, variant)
    from .cli.rendering import KernelCounter
    import numpy as np
    kernels = KernelCounter()
    kernels.start()
    t1 = time.perf_counter()
    try:
        integ = _integrator(job, scene)
        if job.bdpt:
            out = render_chunk_arrays(integ, scene, job, chunk)
        else:
            import mitsuba as mi
            out = {'image': np.array(mi.render(scene, integrator=integ, spp=chunk.spp, seed=chunk.seed))}
    except ChunkFailed:
        raise
    except Exception as e:
        from .cli.errors import error_text
        raise ChunkFailed(error_text(e)) from None
    finally:
        kernels.stop()
    out.update(index=chunk.index, samples=chunk.samples, attempt=attempt, node=node, pid=os.getpid(),
               variant=variant, load_s=load_s, render_s=time.perf_counter() - t1,
               task_s=time.perf_counter() - t0, compile_s=kernels.compile_ms / 1000, scene_path=scene_path,
               kernels=kernels.launched, kernels_compiled=kernels.compiled,
               passes=chunk.end_pass - chunk.first_pass if job.bdpt else 1)
    return out


# ----------------------------------------------------------------------------- combining
class ChunkSum:
    """The finished chunks, keyed by chunk index (a chunk is added once, whatever Ray reran):
    float64 sums of their camera and light blocks and layers (bdpt), or of image x spp (Mitsuba
    integrators); ray counts; per-chunk timings."""

    def __init__(self, job):
        self.job = job
        self.done = {}              # index -> the chunk's result without its arrays
        self.cam = self.lt = self.image = None
        self.layers = None
        self.rays = None
        self.samples = 0
        self.aov_names = []
        self.info = {}
        self.keep_images = False    # render_seeded: each chunk's image kept apart
        self.images = {}

    def add(self, r):
        if r['index'] in self.done:
            return False
        arrays = {k: r.pop(k) for k in ('cam', 'lt', 'image', 'layers') if k in r}
        self.done[r['index']] = r
        self.samples += r['samples']
        if 'image' in arrays:
            if self.keep_images:
                self.images[r['index']] = arrays['image']
            self.image = _add(self.image, arrays['image'].astype('float64') * (r['samples'] / self.job.n_pixels))
            return True
        self.cam = _add(self.cam, arrays['cam'])
        self.lt = _add(self.lt, arrays['lt'])
        self.aov_names, self.info = r.pop('aov_names'), r.pop('info')
        if arrays['layers'] is not None:
            self.layers = self.layers or {n: {k: 0.0 for k in kinds} for n, kinds in arrays['layers'].items()}
            for n, kinds in arrays['layers'].items():
                for k, a in kinds.items():
                    self.layers[n][k] = self.layers[n][k] + a.astype('float64')
        rays = r.pop('rays')
        if rays is not None:
            self.rays = {k: (self.rays or {}).get(k, 0) + int(v) for k, v in rays.items()}
        return True

    @property
    def spp_done(self):
        return self.samples / self.job.n_pixels


def _add(total, a):
    import numpy as np
    a = np.asarray(a, dtype=np.float64)
    return a.copy() if total is None else total + a


@dataclasses.dataclass
class Outcome:
    """A cluster render's result: the image (HxWxC: colour, then the AOV channels; alpha
    dropped), the strategy layers, ray counts, and what the chunks did."""
    image: Any
    layers: Optional[dict]
    rays: Optional[dict]
    info: dict
    spp: float
    samples: int
    chunks: dict                 # index -> timings, node, attempt
    planned: int                 # chunks planned (None: endless, --time)
    interrupted: bool
    wall_s: float
    retried: list = dataclasses.field(default_factory=list)


def finish(scene, total, interrupted=False, planned=None, wall_s=0.0):
    """Develop the sum of the finished chunks into an Outcome (``scene``: the driver's, for
    its film). Raises ClusterError if no chunk finished."""
    import numpy as np
    job = total.job
    if not total.done:
        raise ClusterError(f"{job.scene_file}: no chunk finished; nothing to write")
    layers, rays = None, None
    if job.bdpt:
        light_scale = job.spp * job.n_pixels / total.samples
        arr = develop_sum(scene, total.cam, total.lt, total.aov_names, light_scale)
        n_aov = len(total.aov_names)
        colour = arr[:, :, :arr.shape[2] - n_aov][:, :, :3]
        image = np.concatenate([colour, arr[:, :, arr.shape[2] - n_aov:]], axis=2) if n_aov else colour
        if total.layers is not None:
            layers = {n: {k: (a * light_scale).astype(np.float32) for k, a in kinds.items()}
                      for n, kinds in total.layers.items()}
        if total.rays is not None:
            rays = _ray_summary(total.rays)
    else:
        image = (total.image / total.spp_done)[:, :, :3]        # colour (alpha dropped), as the command
    if not np.isfinite(image).all():
        raise ClusterError(f"{job.scene_file}: the combined image has non-finite values")
    info = dict(total.info, samples=total.samples, interrupted=interrupted,
                passes_done=sum(r['passes'] for r in total.done.values()))
    if rays is not None:
        info['rays'] = rays
    retried = sorted(i for i, r in total.done.items() if r['attempt'] > 0)
    return Outcome(image.astype(np.float32), layers, rays, info, total.spp_done, total.samples,
                   total.done, planned, interrupted, wall_s, retried)


def _ray_summary(totals):
    t = dict(totals)
    t['rays'] = t['camera_rays'] + t['light_rays'] + t['shadow_rays']
    t['zero_contribution_rays'] = t['camera_rays_missed'] + t['light_rays_missed'] + t['shadow_rays_blocked']
    return t


# ----------------------------------------------------------------------------- in one process
def render_chunks_locally(job, chunks, scene=None):
    """The single-process reference: the same chunk plan rendered here, chunk by chunk, with
    the same task body and the same combination. ``chunks``: Chunks (e.g. ``iter_chunks``) or
    a subset of them; ``scene``: the driver's scene for the film (loaded if None)."""
    total = ChunkSum(job)
    for chunk in chunks:
        total.add(run_chunk(job, chunk))
    if scene is None:
        import mitsuba as mi
        from .cli.session import load_scene
        scene = load_scene(mi, job.scene_file, job.defines, job.integrator_type)
    return finish(scene, total)


# ----------------------------------------------------------------------------- Ray
@dataclasses.dataclass
class Options:
    """How a render uses the cluster. address: 'local' (start a Ray instance on 127.0.0.1 for
    this machine's cores and GPUs), 'auto' (join the running cluster) or a Ray address;
    chunk_spp: spp of a chunk (None: the spp over twice the cluster's slots); cpus_per_chunk:
    CPUs a CPU chunk takes (its Dr.Jit thread count); use_gpus: a chunk per GPU with the cuda_
    variant; ship_files / ship_code: the scene's folder and the bdpt_jit package travel in the
    tasks' Ray runtime_env (off: every node has them at the same paths); runtime_env: more of
    it (env_vars, pip, ...); verbose: Ray's and the workers' logs on the driver; hook: Job.hook."""
    address: str = 'local'
    chunk_spp: Optional[int] = None
    cpus_per_chunk: int = 1
    use_gpus: bool = True
    ship_files: bool = True
    ship_code: bool = True
    runtime_env: Optional[dict] = None
    verbose: bool = False
    hook: Optional[Callable] = None


def import_ray():
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--cluster needs Ray, which is not installed here: {INSTALL_HINT}") from None
    return ray


def connect(options):
    """Ray, connected: an existing connection of this process is used as it is; 'local'
    starts an instance bound to the loopback address (no usage statistics sent). Returns
    (ray, started here)."""
    local = options.address == 'local'
    if local:
        # must be set before Ray is first imported: its node address is then 127.0.0.1
        os.environ.setdefault('RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER', '0')
        os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    import logging
    kw = dict(include_dashboard=False, log_to_driver=options.verbose, runtime_env=runtime_env(options),
              logging_level=logging.INFO if options.verbose else logging.ERROR)
    try:
        if local:
            ray.init(address='local', num_cpus=os.cpu_count(), _node_ip_address='127.0.0.1', **kw)
        else:
            ray.init(address=options.address, **kw)
    except Exception as e:
        from .cli.errors import error_text
        what = 'start a local Ray instance' if local else f'join the Ray cluster at {options.address!r}'
        raise ClusterError(f"cannot {what}: {error_text(e)}") from None
    return ray, True


def cluster_slots(ray, options):
    """(GPU slots, CPU slots): chunks that can run at once."""
    res = ray.cluster_resources()
    gpus = int(res.get('GPU', 0)) if options.use_gpus else 0
    cpus = int(res.get('CPU', 0))
    return gpus, max((cpus - gpus) // max(options.cpus_per_chunk, 1), 0 if gpus else 1)


def default_chunk_spp(spp, slots):
    """Twice as many chunks as slots (a slow node's last chunk is then half a share)."""
    return max(1, math.ceil(spp / (2 * max(sum(slots), 1))))


def runtime_env(options):
    """The Ray runtime_env of the job this driver starts or joins: the bdpt_jit package (its
    workers then run the driver's code) and the options' own (env_vars, pip, ...). Ray takes
    local folders only at the job level: a connection made before (ray.init by the caller)
    keeps its own, and the scene's folder travels through the object store (Job.files)."""
    env = dict(options.runtime_env or {})
    if options.ship_code:
        env['py_modules'] = list(env.get('py_modules', [])) + [os.path.dirname(os.path.abspath(__file__))]
    return env or None


def _task_options(options, gpu):
    """A chunk's Ray options: reruns if its worker dies, none for its own errors; its
    resources; the options' runtime_env (what a task may have: env_vars, pip, ...)."""
    opts = dict(max_retries=MAX_RETRIES, retry_exceptions=False,
                num_cpus=1 if gpu else options.cpus_per_chunk, num_gpus=1 if gpu else 0)
    if options.runtime_env:
        opts['runtime_env'] = dict(options.runtime_env)
    return opts


def describe_failure(ray, e, chunk):
    """One line for a chunk's failure seen on the driver."""
    from .cli.errors import error_text
    exc = ray.exceptions
    import_error = re.findall(r'(?:ImportError|ModuleNotFoundError): (.*)', str(e))
    if import_error:            # the task's code or arguments (bdpt_jit's objects) could not be unpickled
        return (f"a worker cannot import the bdpt_jit plugin: {import_error[-1].strip()} (install bdpt_jit, "
                f"Mitsuba and Dr.Jit on every node, or let the driver ship bdpt_jit: Options.ship_code)")
    if isinstance(e, exc.RayTaskError):
        cause = getattr(e, 'cause', None)
        if isinstance(cause, ChunkFailed):
            return str(cause)
        return f"chunk {chunk.index} failed: {error_text(cause) if cause is not None else _first_line(e)}"
    if isinstance(e, (exc.WorkerCrashedError, exc.NodeDiedError, exc.OutOfMemoryError)):
        return (f"chunk {chunk.index}: its worker died {MAX_RETRIES + 1} times "
                f"({type(e).__name__}: {_first_line(e)})")
    if isinstance(e, exc.RuntimeEnvSetupError):
        return f"the workers could not set up the scene's folder and the code (Ray runtime_env): {_first_line(e)}"
    return f"chunk {chunk.index}: {type(e).__name__}: {_first_line(e)}"


def _first_line(e):
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[0] if lines else type(e).__name__


class ClusterRun:
    """The driver's loop: at most one chunk per free slot in flight (so that a stop request
    ends the scheduling), results added as they come (keyed by chunk index), a failure
    turned into one ClusterError (the chunks in flight then dropped, see ``collect``)."""

    def __init__(self, ray, job, chunks, options, slots):
        self.ray, self.job = ray, job
        self.chunks = iter(chunks)
        self.total = ChunkSum(job)
        self.pending = {}                           # ObjectRef -> (chunk, kind, time submitted)
        self.free = {'gpu': slots[0], 'cpu': slots[1]}
        self.task = {kind: _task_options(options, kind == 'gpu') for kind in self.free}
        self.remote = ray.remote(run_chunk)
        self.exhausted = False
        self.submitted = 0

    def submit_free(self):
        for kind in ('gpu', 'cpu'):
            while self.free[kind] > 0 and not self.exhausted:
                chunk = next(self.chunks, None)
                if chunk is None:
                    self.exhausted = True
                    return
                ref = self.remote.options(**self.task[kind]).remote(self.job, chunk)
                self.pending[ref] = (chunk, kind, time.perf_counter())
                self.free[kind] -= 1
                self.submitted += 1

    def collect(self, timeout, on_chunk=None):
        ready, _ = self.ray.wait(list(self.pending), num_returns=len(self.pending), timeout=timeout)
        for ref in ready:
            chunk, kind, t_submit = self.pending.pop(ref)
            self.free[kind] += 1
            try:
                r = self.ray.get(ref)
            except self.ray.exceptions.TaskCancelledError:
                continue
            except Exception as e:
                # The other chunks in flight are dropped, not cancelled: Ray 2.60's driver can abort
                # ("Tried to complete task that was not pending") when a task that is failing is
                # cancelled. They finish or fail on their own; their results are never read.
                self.pending.clear()
                raise ClusterError(f"{self.job.scene_file}: {describe_failure(self.ray, e, chunk)}") from None
            r['latency_s'] = time.perf_counter() - t_submit   # submitted to received, on the driver
            if self.total.add(r) and on_chunk is not None:
                on_chunk(self.total)

    def cancel(self, keep_finished=False):
        """Cancel the chunks in flight; wait a little for them; with keep_finished, add those
        that finished meanwhile."""
        refs = list(self.pending)
        for ref in refs:
            self.ray.cancel(ref, force=False)
        if refs:
            ready, _ = self.ray.wait(refs, num_returns=len(refs), timeout=CANCEL_GRACE_S)
            for ref in ready if keep_finished else ():
                try:
                    self.total.add(self.ray.get(ref))
                except Exception:
                    pass
        self.pending.clear()

    def run(self, stop=None, on_chunk=None):
        """Until every chunk is done, or ``stop()`` returns a time (time.perf_counter): then
        nothing more is scheduled, and the chunks in flight at that time are cancelled.
        Returns True if stopped before the plan's end."""
        deadline = None
        try:
            while True:
                if deadline is None and stop is not None:
                    deadline = stop()
                if deadline is None:
                    self.submit_free()
                if not self.pending:
                    break
                if deadline is not None and time.perf_counter() >= deadline:
                    self.cancel(keep_finished=True)
                    break
                self.collect(POLL_S, on_chunk)
        except BaseException:
            self.cancel()
            raise
        return deadline is not None and not (self.exhausted and not self.pending)


# ----------------------------------------------------------------------------- the API
def driver_scene(scene_file, defines, integrator_type):
    """The scene on the driver (its film, the pass plan): one ClusterError if it cannot load."""
    import mitsuba as mi
    from .cli.errors import CLIError
    from .cli.session import load_scene
    try:
        return load_scene(mi, scene_file, defines, integrator_type)
    except CLIError as e:
        raise ClusterError(f"{scene_file}: {e}") from None


def make_job(scene, scene_file, integ, spp, seed, defines, options, props=None):
    """The Job and its chunk plan (a list, or a generator for an endless spp) for an
    integrator instance ``integ`` on the driver's ``scene``; returns (job, chunks). ``props``
    (Mitsuba integrators): their properties for mi.load_dict, or the plugin name alone when
    ``integ`` is the scene's own integrator (workers then use theirs)."""
    import mitsuba as mi
    from .integrator import BDPTIntegrator
    bdpt = isinstance(integ, BDPTIntegrator)
    crop = scene.sensors()[0].film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    if bdpt:
        props = {'type': 'bdpt', **{k: v for k, v in integ.settings.items() if v is not None}}
    integ_type = props if isinstance(props, str) else props['type']
    job = Job(os.path.abspath(scene_file), dict(defines or {}), props if isinstance(props, dict) else None,
              integ_type, spp, seed, mi.variant(), n_pixels, bdpt, hook=options.hook)
    passes = ()
    if bdpt:
        passes, per_pass = pass_plan(integ, scene, spp, options.chunk_spp)
        job.integrator['samples_per_pass'] = per_pass
    chunks = iter_chunks(job, options.chunk_spp, passes)
    return job, (chunks if spp is None or spp >= 1 << 24 else list(chunks))


def execute(ray, scene, job, chunks, options, stop=None, on_chunk=None):
    """Render ``chunks`` of ``job`` on the connected cluster and develop the finished ones
    (``scene``: the driver's). ``stop``, ``on_chunk``: as ClusterRun.run. Returns an Outcome."""
    t0 = time.perf_counter()
    if options.ship_files and job.files is None:
        job.files = [ray.put(pack_folder(os.path.dirname(job.scene_file)))]
    run = ClusterRun(ray, job, chunks, options, cluster_slots(ray, options))
    stopped = run.run(stop, on_chunk)
    planned = len(chunks) if isinstance(chunks, list) else None
    return finish(scene, run.total, stopped, planned, time.perf_counter() - t0)


def render_file(scene_file, spp, integrator=None, seed=0, defines=None, options=None, stop=None):
    """Render a scene file on a Ray cluster: ``integrator``: the plugin's properties (default
    {'type': 'bdpt'}); ``defines``: the -D values. Returns an Outcome (``.image``: HxWxC)."""
    import mitsuba as mi
    options = dataclasses.replace(options or Options())
    integrator = dict(integrator or {'type': 'bdpt'})
    scene = driver_scene(scene_file, dict(defines or {}), integrator['type'])
    integ = mi.load_dict(integrator)
    ray, started = connect(options)
    try:
        if options.chunk_spp is None:
            options.chunk_spp = default_chunk_spp(spp, cluster_slots(ray, options))
        job, chunks = make_job(scene, scene_file, integ, spp, seed, defines, options, integrator)
        return execute(ray, scene, job, chunks, options, stop)
    finally:
        if started:
            ray.shutdown()


def render_seeded(scene_file, defines, props, spp, seeds, options=None):
    """Independent renders on the cluster, one task each: ``mi.render(scene, integrator,
    spp, seed)`` for each of ``seeds`` (``props``: the integrator's properties; bdpt then
    runs its own pass loop), so that each image is the one the same call gives in one process
    (references of independent batches: benchmarks/compare.py --cluster). Returns the images
    (HxWxC arrays) in the order of ``seeds``. The connection stays open for later calls
    (``ray.shutdown()`` ends it; Ray ends it at exit)."""
    import mitsuba as mi
    options = dataclasses.replace(options or Options())
    scene = driver_scene(scene_file, dict(defines or {}), props['type'])
    crop = scene.sensors()[0].film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    job = Job(os.path.abspath(scene_file), dict(defines or {}), dict(props), props['type'], spp, 0, mi.variant(),
              n_pixels, False, hook=options.hook)
    chunks = [Chunk(k, spp * n_pixels, spp=spp, seed=int(seed)) for k, seed in enumerate(seeds)]
    ray, _ = connect(options)
    if options.ship_files:
        job.files = [ray.put(pack_folder(os.path.dirname(job.scene_file)))]
    run = ClusterRun(ray, job, chunks, options, cluster_slots(ray, options))
    run.total.keep_images = True
    run.run()
    return [run.total.images[k] for k in range(len(chunks))]


# ----------------------------------------------------------------------------- the command
def node_report(outcome):
    """Per node: {address: {variant, chunks, samples, busy_s, msamples_per_s}}: samples per
    second of the render's wall time (what the node added), and busy_s (its chunks' task time)."""
    nodes = {}
    for r in outcome.chunks.values():
        n = nodes.setdefault(r['node'], {'variants': set(), 'chunks': 0, 'samples': 0, 'busy_s': 0.0})
        n['variants'].add(r['variant'])
        n['chunks'] += 1
        n['samples'] += r['samples']
        n['busy_s'] += r['task_s']
    for n in nodes.values():
        n['variant'] = ','.join(sorted(n.pop('variants')))
        n['msamples_per_s'] = n['samples'] / outcome.wall_s / 1e6 if outcome.wall_s > 0 else 0.0
    return nodes


def overheads(outcome):
    """Mean seconds per chunk: scene loading, kernel compilation, rendering (compilation
    included), the whole task on its worker, and from submission to its result on the driver
    (worker start, transfers and queueing included)."""
    rs = list(outcome.chunks.values())
    mean = lambda k: sum(r.get(k, r['task_s']) for r in rs) / len(rs)           # noqa: E731
    return {k: mean(k) for k in ('load_s', 'compile_s', 'render_s', 'task_s', 'latency_s')}


def cli_statistics(outcome, options, slots):
    """The header's ``cluster.*`` keys and the summary's lines."""
    nodes = node_report(outcome)
    ov = overheads(outcome)
    planned = outcome.planned if outcome.planned is not None else 'endless (--time)'
    stats = {'cluster.address': options.address, 'cluster.chunk_spp': options.chunk_spp,
             'cluster.chunks': len(outcome.chunks), 'cluster.chunks_planned': planned,
             'cluster.slots': f'{slots[1]} cpu, {slots[0]} gpu',
             'cluster.retried': ' '.join(str(i) for i in outcome.retried),
             'cluster.chunk_load_s': f"{ov['load_s']:.3f}", 'cluster.chunk_compile_s': f"{ov['compile_s']:.3f}",
             'cluster.chunk_render_s': f"{ov['render_s']:.3f}"}
    retried = (f"; chunk{'s' if len(outcome.retried) > 1 else ''} {', '.join(map(str, outcome.retried))} "
               f"retried (worker died)" if outcome.retried else '; no chunk retried')
    count = f"{len(outcome.chunks)} chunks" if outcome.planned is None else f"{len(outcome.chunks)} of {planned} chunks"
    lines = [f"  cluster         {count} of {options.chunk_spp} spp on "
             f"{len(nodes)} node{'s' if len(nodes) != 1 else ''} ({options.address}), {slots[1]} CPU and "
             f"{slots[0]} GPU slots{retried}",
             f"  per chunk       scene load {ov['load_s']:.3f} s, JIT compile {ov['compile_s']:.3f} s, render "
             f"{ov['render_s']:.3f} s (compile included), task {ov['task_s']:.3f} s, on the driver "
             f"{ov['latency_s']:.3f} s (means)"]
    for addr, n in sorted(nodes.items()):
        stats[f'cluster.node.{addr}'] = (f"{n['variant']} {n['chunks']} chunks {n['samples']} samples "
                                         f"{n['msamples_per_s']:.4f} Msamples/s")
        lines.append(f"  node            {addr} ({n['variant']}): {n['chunks']} chunks, {n['samples']:,} samples, "
                     f"{n['msamples_per_s']:.4g} M samples/s over the render")
    return stats, lines


def _cli_job(args, scene, integ, settings, defines, options, slots):
    """The command's Job and chunk plan: --spp, or --time's endless plan (bdpt: the render's
    TIMED_SPP, the power of two its scales assume; Mitsuba's integrators: endless chunks)."""
    from .cli.rendering import TIMED_SPP
    from .integrator import BDPTIntegrator
    timed = args.time is not None
    spp = args.spp or int(scene.sensors()[0].sampler().sample_count())
    if options.chunk_spp is None:
        options.chunk_spp = args.pass_spp if timed else default_chunk_spp(spp, slots)
    bdpt = isinstance(integ, BDPTIntegrator)
    props = (None if bdpt else args.integrator if integ is scene.integrator()
             else {'type': args.integrator, **settings})
    total_spp = (TIMED_SPP if bdpt else None) if timed else spp
    job, chunks = make_job(scene, args.scene, integ, total_spp, args.seed, defines, options, props)
    if bdpt:
        settings['samples_per_pass'] = job.integrator['samples_per_pass']
    return job, chunks


def _cli_stop(args, guard, seen, why):
    """The command's stop rule: Ctrl-C cancels the chunks in flight at once; --time stops
    scheduling when a chunk (as long as the finished ones, on average) would end after the
    budget, and cancels what is still running at the budget."""
    t0 = time.perf_counter()

    def stop():
        if guard.requested:
            why.append('interrupt')
            return time.perf_counter()
        if args.time is not None and seen:
            done = seen[-1].done.values()
            mean_s = sum(r['task_s'] for r in done) / len(done)
            if time.perf_counter() - t0 + mean_s > args.time:
                why.append('budget')
                return t0 + args.time
        return None
    return stop


def render_cli(args, scene, integ, settings, guard, defines):
    """``bdpt-jit render --cluster``: the render on the cluster, as a rendering.Result (and its
    ``cluster_stats`` and ``cluster_lines`` for the header and the summary)."""
    from .cli.errors import CLIError
    options = Options(address=args.cluster, chunk_spp=args.chunk_spp, verbose=args.debug)
    try:
        ray, started = connect(options)
    except ClusterError as e:
        raise CLIError(str(e)) from None
    try:
        slots = cluster_slots(ray, options)
        job, chunks = _cli_job(args, scene, integ, settings, defines, options, slots)
        outcome = _cli_run(ray, scene, job, chunks, options, args, guard)
    except ClusterError as e:
        raise CLIError(str(e)) from None
    finally:
        if started:
            ray.shutdown()
    return _cli_result(outcome, job, options, slots, args)


def _cli_run(ray, scene, job, chunks, options, args, guard):
    """The chunks run with the progress bar and the stop rule; Ctrl-C before a chunk has
    finished, or a second one, writes nothing."""
    from .cli.errors import Interrupted
    from .cli.progress import Progress
    spp = None if args.time is not None else job.spp
    progress = Progress(args.quiet, total_spp=spp, budget_s=args.time, n_pixels=job.n_pixels)
    seen, why = [], []
    t0 = time.perf_counter()

    def on_chunk(total):
        guard.mode = 'defer'                        # a chunk is done: from now on Ctrl-C keeps it
        seen[:] = [total]
        passes = sum(r['passes'] for r in total.done.values())
        progress.update(passes, round(total.spp_done, 3), time.perf_counter() - t0)

    guard.mode = 'raise'
    try:
        outcome = execute(ray, scene, job, chunks, options, _cli_stop(args, guard, seen, why), on_chunk)
    except KeyboardInterrupt:
        progress.close()
        if guard.aborted:
            raise Interrupted("aborted (second Ctrl-C); nothing was written") from None
        raise Interrupted("interrupted before the first chunk finished; nothing was written") from None
    progress.close(outcome.info.get('passes_done'), round(outcome.spp, 3), outcome.wall_s)
    outcome.interrupted = outcome.interrupted and 'interrupt' in why
    outcome.info['interrupted'] = outcome.interrupted
    return outcome


def _cli_result(outcome, job, options, slots, args):
    """The command's Result from the cluster's Outcome."""
    from .cli.rendering import Result
    res = Result(job.n_pixels, None if args.time is not None else job.spp)
    res.add(outcome.image, outcome.spp)
    res.layers, res.rays = outcome.layers, outcome.rays
    res.info = outcome.info if outcome.info.get('strategies') is not None else {}
    chunks = outcome.chunks.values()
    res.passes = sum(r['passes'] for r in chunks)
    res.render_s = outcome.wall_s
    res.longest_pass_s = max(r['task_s'] for r in chunks)
    res.kernels.launched = sum(r['kernels'] for r in chunks)
    res.kernels.compiled = sum(r['kernels_compiled'] for r in chunks)
    res.kernels.compile_ms = 1000 * sum(r['compile_s'] for r in chunks)
    res.interrupted = outcome.interrupted
    res.cluster_stats, res.cluster_lines = cli_statistics(outcome, options, slots)
    return res


# ----------------------------------------------------------------------------- overhead figures
def measure_overhead(scene_file, defines, spp, chunk_spps, options=None):
    """docs/cluster.md's figures: the same bdpt render (``spp``) in one process (its second
    run: kernels cached) and on the cluster in chunks of each of ``chunk_spps``, after a
    warm-up render on the cluster. Returns (rows, one-process seconds, warm-up Outcome); a
    row: chunk_spp, chunks, wall s, mean load / compile / render / task / driver latency s
    per chunk."""
    import mitsuba as mi
    options = dataclasses.replace(options or Options())
    scene = driver_scene(scene_file, dict(defines), 'bdpt')
    props = {'type': 'bdpt', 'statistics': False}
    for _ in range(2):
        t0 = time.perf_counter()
        mi.render(scene, integrator=mi.load_dict(props), spp=spp, seed=0)
        one_s = time.perf_counter() - t0
    ray, started = connect(options)
    rows, warm = [], None
    try:
        for chunk_spp in [max(chunk_spps)] + list(chunk_spps):
            options.chunk_spp = chunk_spp
            job, chunks = make_job(scene, scene_file, mi.load_dict(props), spp, 0, defines, options, props)
            out = execute(ray, scene, job, chunks, options)
            if warm is None:
                warm = out
                continue
            rows.append(dict(chunk_spp=chunk_spp, chunks=len(chunks), wall_s=out.wall_s, **overheads(out),
                             **_per_worker(out)))
    finally:
        if started:
            ray.shutdown()
    return rows, one_s, warm


def _per_worker(out):
    """Scene loading and compiling per worker process (paid by its first chunk of a job), and
    the mean task time of the other chunks (samples and per-chunk costs only)."""
    firsts, rest = {}, []
    for i in sorted(out.chunks):
        r = out.chunks[i]
        (rest.append(r['task_s']) if r['pid'] in firsts else firsts.setdefault(r['pid'], r))
    setup = [r['load_s'] + r['compile_s'] for r in firsts.values()]
    return dict(workers=len(firsts), setup_s=sum(setup) / len(setup),
                steady_task_s=sum(rest) / len(rest) if rest else float('nan'))


def _main(argv=None):
    """python -m bdpt_jit.cluster SCENE SPP CHUNK_SPP... [-D NAME=VALUE] [--address A]: the
    overhead table of docs/cluster.md on this machine."""
    import argparse
    ap = argparse.ArgumentParser(prog='python -m bdpt_jit.cluster', description=_main.__doc__)
    ap.add_argument('scene')
    ap.add_argument('spp', type=int)
    ap.add_argument('chunk_spp', type=int, nargs='+')
    ap.add_argument('-D', dest='defines', action='append', default=[])
    ap.add_argument('--address', default='local')
    args = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant('llvm_ad_rgb')
    import bdpt_jit
    bdpt_jit.register()
    defines = dict(d.split('=', 1) for d in args.defines)
    rows, one_s, warm = measure_overhead(args.scene, defines, args.spp, args.chunk_spp, Options(address=args.address))
    first = warm.chunks[0]
    print(f"one process: {one_s:.3f} s; cluster warm-up: first chunk on a fresh worker: task {first['task_s']:.3f} s "
          f"(scene load {first['load_s']:.3f} s, JIT compile {first['compile_s']:.3f} s), on the driver "
          f"{first['latency_s']:.3f} s")
    print('| chunk spp | chunks | workers | wall s | one process / wall | load + compile s per worker | '
          'task s (other chunks) | task s (all, mean) | on the driver s (mean) |')
    print('|---|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(f"| {r['chunk_spp']} | {r['chunks']} | {r['workers']} | {r['wall_s']:.3f} | {one_s / r['wall_s']:.2f} | "
              f"{r['setup_s']:.3f} | {r['steady_task_s']:.4f} | {r['task_s']:.4f} | {r['latency_s']:.4f} |")


if __name__ == '__main__':
    _main()
