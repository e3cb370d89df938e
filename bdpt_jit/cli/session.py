"""One ``bdpt-jit render``: the inputs checked, the Mitsuba variant started, the scene loaded,
the integrator chosen, the render run (rendering.py), the files written and the summary printed."""

import os
import re
import sys
import tempfile
import time

from .args import DEFAULT_VARIANT, GPU_VARIANT, check_params, given_params, option_of, parse_defines
from .errors import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK, PROG, CLIError, error_text, scene_error
from .outputs import film_channel_names, output_paths, write_exr, write_png
from .rendering import render
from .summary import header, print_summary, statistics

# Parameters of the table that Mitsuba's own integrators (path, ptracer, ...) also take
SHARED_PARAMS = ('max_depth', 'rr_depth', 'hide_emitters')


def cmd_render(args, guard):
    """``bdpt-jit render``; returns the exit status. ``guard``: interrupts.InterruptGuard."""
    t_wall = time.perf_counter()
    defines = parse_defines(args.defines)
    check_params(args)
    if not os.path.exists(args.scene):
        raise CLIError(f"scene file not found: {args.scene}")
    if not os.path.isfile(args.scene):
        raise CLIError(f"scene path is not a file: {args.scene}")
    out, png = output_paths(args.scene, args.output)
    if args.integrator != 'bdpt' and args.strategy_images:
        raise CLIError(f"--strategies needs --integrator bdpt (not {args.integrator})")

    variant = init_variant(args)
    den = None
    if args.denoise:                                # the denoiser checked now, its error told after writing
        from ..denoise.command import DenoiseStep
        den = DenoiseStep(variant)
    import mitsuba as mi
    if args.quiet:
        mi.set_log_level(mi.LogLevel.Error)         # Mitsuba's warnings too
    import bdpt_jit
    bdpt_jit.register()
    scene = load_scene(mi, args.scene, defines, args.integrator)
    if not scene.sensors():
        raise CLIError(f"the scene has no sensor: {args.scene}")
    if den is not None and scene.sensors()[0].film().flags() & mi.FilmFlags.Special:
        raise CLIError(f"--denoise needs an RGB or luminance film; the scene's film "
                       f"({scene.sensors()[0].film().class_name()}) has channels of its own: {args.scene}")
    integ, settings = make_integrator(args, scene)
    is_bdpt = isinstance(integ, bdpt_jit.BDPTIntegrator)
    if is_bdpt:
        integ = prepare_bdpt(args, scene, integ)
        settings = dict(integ.settings)

    if args.cluster:                                # the samples on a Ray cluster (cluster.py)
        from ..cluster import render_cli
        res = render_cli(args, scene, integ, settings, guard, defines)
    else:
        res = render(args, scene, integ, is_bdpt, guard)
    img, layers = res.mean()
    aov_names = list(getattr(integ, 'aov_channels', ()))
    colour = img[:, :, :img.shape[2] - len(aov_names)]
    extra, png_img = den.run(scene, colour, res.spp, args.seed) if den is not None else ({}, colour)
    stats = statistics(args, res, settings, variant, args.scene, defines, time.perf_counter() - t_wall)
    stats.update(den.stats if den is not None else {})
    write_exr(out, img, header(stats), layers, aov_names, extra, film_channel_names(scene.sensors()[0].film()))
    write_png(png, png_img)
    if not args.quiet:
        print_summary(stats, res, out, png)
        sys.stdout.flush()
    if den is not None and den.error is not None:
        print(f"{PROG}: error: --denoise: {den.error}; wrote the raw image to {out} and {png}", file=sys.stderr)
    if res.interrupted:
        print(f"{PROG}: interrupted: wrote the {res.spp:g} spp rendered so far"
              + (f" (of {res.spp_requested})" if res.spp_requested else '') + f" to {out} and {png}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_ERROR if den is not None and den.error is not None else EXIT_OK


# ----------------------------------------------------------------------------- variant
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


def init_variant(args):
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
        raise CLIError(_variant_error(variant, err, cap.text))
    return variant


def _variant_error(variant, err, captured):
    msg = str(err)
    if variant.startswith('llvm') and ('LLVM' in msg or 'libLLVM' in captured):
        where = os.environ.get('DRJIT_LIBLLVM_PATH')
        where = f" (DRJIT_LIBLLVM_PATH={where})" if where else ''
        return (f"the LLVM backend could not be started: libLLVM >= 16 was not found{where}; "
                f"install it (e.g. apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH to its libLLVM.so")
    if variant.startswith('cuda'):
        return f"variant '{variant}' needs a CUDA GPU and driver: {error_text(err)}"
    return f"Mitsuba variant '{variant}' cannot be used: {error_text(err)}"


# ----------------------------------------------------------------------------- scene
def load_scene(mi, path, defines, integrator):
    """mi.load_file with the -D values. A scene whose integrator is a parameter (`$integrator`,
    as the bundled scenes have) gets the requested one, with the scene's own settings."""
    if 'integrator' not in defines:
        try:
            return mi.load_file(path, integrator=integrator, **defines)
        except Exception as e:
            text = str(e)
            if not ('unused parameters' in text and '$integrator=' in text):
                raise CLIError(scene_error(e, path, defines)) from None
    try:
        return mi.load_file(path, **defines)
    except Exception as e:
        raise CLIError(scene_error(e, path, defines)) from None


# ----------------------------------------------------------------------------- integrator
def _shared_settings_of(integrator):
    """The scene integrator's settings among SHARED_PARAMS that it has: bdpt's, or max_depth and
    rr_depth as Mitsuba's integrators print them and hide_emitters as its sampling integrators
    hold it (a scene written for path with hidden emitters renders them hidden here too)."""
    settings = getattr(integrator, 'settings', None)
    if isinstance(settings, dict):
        return {k: settings[k] for k in SHARED_PARAMS if k in settings}
    found = {}
    for name in ('max_depth', 'rr_depth'):
        m = re.search(name + r'\s*=\s*(-?\d+)', str(integrator))
        if m:
            found[name] = int(m.group(1))
    hide = getattr(integrator, 'hide_emitters', None)
    if isinstance(hide, bool):
        found['hide_emitters'] = hide
    return found


def make_integrator(args, scene):
    """The integrator to render with, and its parameter values (for the header)."""
    if args.integrator == 'bdpt':
        return _make_bdpt(args, scene)
    return _make_mitsuba(args, scene)


def _load_bdpt(params):
    import mitsuba as mi
    try:
        return mi.load_dict({'type': 'bdpt', **{k: v for k, v in params.items() if v is not None}})
    except Exception as e:
        raise CLIError(error_text(e)) from None


def _make_bdpt(args, scene):
    """bdpt with the scene's settings (if its integrator is bdpt; else those of SHARED_PARAMS it
    has), statistics on, and the options given."""
    from ..integrator import BDPTIntegrator
    scene_integ = scene.integrator()
    params = {}
    if isinstance(scene_integ, BDPTIntegrator):
        params.update(scene_integ.settings)
    elif scene_integ is not None:
        params.update(_shared_settings_of(scene_integ))
    params['statistics'] = True
    params.update(given_params(args))
    integ = _load_bdpt(params)
    return integ, dict(integ.settings)


def _make_mitsuba(args, scene):
    """A Mitsuba integrator: the scene's own if it is that plugin and no option is given;
    else a new one with the options given and the scene's SHARED_PARAMS settings, if the plugin
    takes them."""
    import mitsuba as mi
    from ..integrator import BDPTIntegrator
    given = given_params(args)
    bdpt_only = [n for n in given if n not in SHARED_PARAMS]
    if bdpt_only:
        flags = ', '.join(option_of(n) for n in bdpt_only)
        raise CLIError(f"{flags}: bdpt option{'s' if len(bdpt_only) > 1 else ''}, not available with "
                       f"--integrator {args.integrator}")
    try:
        bare = mi.load_dict({'type': args.integrator})
    except Exception as e:
        raise CLIError(f"integrator {args.integrator!r}: {error_text(e)}") from None
    scene_integ = scene.integrator()
    same = (scene_integ is not None and not isinstance(scene_integ, BDPTIntegrator)
            and scene_integ.class_name() == bare.class_name())
    if same and not given:                          # the scene's own, with all its settings
        return scene_integ, _shared_settings_of(scene_integ)
    params = dict(given)
    inherited = {k: v for k, v in _shared_settings_of(scene_integ).items() if k not in params} \
        if scene_integ is not None else {}
    for keep in (inherited, {k: v for k, v in inherited.items() if k == 'max_depth'}):
        if keep:
            try:                                # the scene's settings, if the plugin takes them
                return mi.load_dict({'type': args.integrator, **keep, **params}), {**keep, **params}
            except Exception:
                pass
    try:
        return mi.load_dict({'type': args.integrator, **params}), params
    except Exception as e:
        raise CLIError(f"integrator {args.integrator!r}: {error_text(e)}") from None


def prepare_bdpt(args, scene, integ):
    """Refuse a scene outside bdpt's scope with one line. With --time, return the integrator
    rebuilt to run --time as its own pass loop: ``samples_per_pass`` set to one pass of
    --pass-spp (as the integrator would cut a render of --pass-spp spp: fewer samples if its
    memory budget or --samples-per-pass asks for it)."""
    from ..params import ParameterError
    from ..passes import plan_passes
    from ..scene_check import UnsupportedSceneError
    sensor = scene.sensors()[0]
    try:
        ctx = integ.make_context(scene, sensor)     # the scene, and the parameters against it (media)
    except UnsupportedSceneError as e:
        alt = e.alternative or 'path'
        raise CLIError(f"{e} (render it with another integrator, e.g. --integrator {alt})") from None
    except ParameterError as e:
        raise CLIError(str(e)) from None
    if args.time is None:
        del ctx
        return integ
    crop = sensor.film().crop_size()
    n_pixels = int(crop[0]) * int(crop[1])
    spp_pass, _, pixels = next(plan_passes(args.pass_spp, n_pixels, integ.bytes_per_sample(ctx),
                                           integ.settings['samples_per_pass']))
    del ctx
    return _load_bdpt(dict(integ.settings, samples_per_pass=spp_pass * pixels))
