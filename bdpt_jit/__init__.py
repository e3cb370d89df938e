"""bdpt_jit: a bidirectional path tracer for Mitsuba 3, written in Dr.Jit.

``import bdpt_jit`` registers the integrator ``bdpt`` with Mitsuba for the active variant
(``llvm_ad_rgb`` is selected if none is active yet). After switching variants, call
``bdpt_jit.register()`` again.
"""

import mitsuba as mi

__version__ = '0.1.0'


def register():
    """Register ``bdpt`` for the active Mitsuba variant."""
    if mi.variant() is None:
        mi.set_variant('llvm_ad_rgb')
    from .integrator import BDPTIntegrator
    mi.register_integrator('bdpt', lambda props: BDPTIntegrator(props))


register()

from .integrator import BDPTIntegrator  # noqa: E402
from .params import PARAMS, ParameterError  # noqa: E402
from .scene_check import UnsupportedSceneError  # noqa: E402

__all__ = ['BDPTIntegrator', 'PARAMS', 'ParameterError', 'UnsupportedSceneError', 'register']
