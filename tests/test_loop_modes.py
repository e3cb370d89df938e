"""The kernels run with Dr.Jit's evaluated loops (what reverse-mode AD needs: the light
vertices live in global arrays either way) and give the same image as with symbolic loops,
to floating-point rounding, for the same seed."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import scene_path


# max_depth -1 in the slow set (CI time, 19 s cold): the loop bodies are those of 5 (which stays), only the bound differs
@pytest.mark.parametrize('max_depth', [5, pytest.param(-1, marks=pytest.mark.slow)])
def test_evaluated_loops_match_symbolic(max_depth):
    scene = mi.load_file(scene_path('paper-fig6.xml'), res=16, max_depth=max_depth)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': max_depth, 'samples_per_pass': 3000})
    symbolic = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
    dr.set_flag(dr.JitFlag.SymbolicLoops, False)
    try:
        evaluated = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
    finally:
        dr.set_flag(dr.JitFlag.SymbolicLoops, True)
    assert np.all(np.isfinite(evaluated))
    np.testing.assert_allclose(evaluated, symbolic, rtol=1e-4, atol=1e-5)
