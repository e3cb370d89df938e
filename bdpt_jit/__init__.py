"""bdpt_jit: a bidirectional path tracer for Mitsuba 3, written in Dr.Jit.

``import bdpt_jit`` registers the integrator ``bdpt`` with Mitsuba for the active variant
(``llvm_ad_rgb`` is selected if none is active yet). After switching variants, call
``bdpt_jit.register()`` again. If no variant can be activated (no libLLVM >= 16 for the LLVM
backend), the import still succeeds and ``register()`` raises with the reason.
"""

import os
import sys
import tempfile

__version__ = '0.1.0'


def _capture_fd2(fn):
    """Run ``fn`` with file descriptor 2 captured; returns (result or exception, text)."""
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode='w+b') as log:
        os.dup2(log.fileno(), 2)
        try:
            result = fn()
        except Exception as e:
            result = e
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        log.seek(0)
        return result, log.read().decode(errors='replace')


# Dr.Jit starts its LLVM backend on import and, without libLLVM, writes its own lines to
# stderr before any error can be handled: keep them, and show them only if they matter.
_mi, _import_log = _capture_fd2(lambda: __import__('mitsuba'))
if isinstance(_mi, Exception):
    raise _mi
mi = _mi

# Fewest threads in Dr.Jit's pool: Mitsuba 3.9.1 reads and writes OpenEXR files with tasks in
# that pool that wait on one another, so with one thread (a machine or container of one CPU, or
# DRJIT_NUM_THREADS=1) mi.Bitmap hangs for good on every .exr: an envmap, a texture, the CLI's
# output. Two threads on one CPU cost nothing measurable.
MIN_THREADS = 2


def ensure_min_threads():
    """At least MIN_THREADS threads in Dr.Jit's pool (see there)."""
    import drjit as dr
    if dr.thread_count() < MIN_THREADS:
        dr.set_thread_count(MIN_THREADS)


ensure_min_threads()

# the kernels' modules, in import order: they hold the active variant's types (contexts,
# record layouts, the plugin's base class), and are imported again when the variant changes
_KERNEL_MODULES = ('jitmath', 'rays', 'strategies', 'cameras', 'direct', 'emitter_tables', 'endpoints', 'connect', 'vertex',
                   'store', 'film', 'stats', 'roulette', 'mis', 'passes', 'scene_check', 'sampling', 'gradients', 'transport',
                   'context', 'merge', 'light_path', 'camera_path', 'integrator')
_loaded_variant = None


def _reload_kernels():
    import importlib
    for name in _KERNEL_MODULES:
        module = sys.modules.get(f'{__name__}.{name}')
        if module is not None:
            importlib.reload(module)


def register():
    """Register ``bdpt`` for the active Mitsuba variant (``llvm_ad_rgb`` if none is active).
    Raises, with what Dr.Jit reported, if no variant can be activated."""
    global _loaded_variant
    if mi.variant() is None:
        set_variant_quietly('llvm_ad_rgb')
    if not mi.variant().startswith(('llvm_', 'cuda_')):
        # the kernels need a JIT variant; a scene asking for bdpt in a scalar one gets the
        # reason (scene_check.check_variant), not Mitsuba's "plugin not found"
        mi.register_integrator('bdpt', _refuse_variant)
        return
    if _loaded_variant is not None and mi.variant() != _loaded_variant:
        _reload_kernels()
    _loaded_variant = mi.variant()
    from .integrator import BDPTIntegrator
    mi.register_integrator('bdpt', lambda props: BDPTIntegrator(props))


def _refuse_variant(props):
    from .scene_check import check_variant
    check_variant()


def set_variant_quietly(variant):
    """``mi.set_variant`` that, when it fails (e.g. no libLLVM for the LLVM backend), keeps what
    Dr.Jit's C library wrote to stderr in the raised error instead of on the terminal."""
    result, text = _capture_fd2(lambda: mi.set_variant(variant))
    if isinstance(result, Exception):
        result.args = ((str(result) + '\n' + _import_log + text).strip(),)
        raise result
    if text:
        sys.stderr.write(text)


def _register_quietly():
    if mi.variant() is None:
        set_variant_quietly('llvm_ad_rgb')
    elif _import_log:
        sys.stderr.write(_import_log)
    register()


try:
    _register_quietly()
except Exception:               # e.g. Dr.Jit's LLVM backend without libLLVM: register() says why
    pass


def __getattr__(name):
    # the kernels' modules need an active JIT variant: import them on first use
    if name == 'BDPTIntegrator':
        from .integrator import BDPTIntegrator
        return BDPTIntegrator
    if name in ('PARAMS', 'ParameterError'):
        from . import params
        return getattr(params, name)
    if name == 'UnsupportedSceneError':
        from .scene_check import UnsupportedSceneError
        return UnsupportedSceneError
    raise AttributeError(f"module 'bdpt_jit' has no attribute {name!r}")


__all__ = ['BDPTIntegrator', 'PARAMS', 'ParameterError', 'UnsupportedSceneError', 'register']
