"""The kernels are specialised to the scene and the settings: what a setting does not need is
not traced. Measured from Dr.Jit's kernel history (operations in the launched kernels)."""

import drjit as dr
import mitsuba as mi
import pytest

import bdpt_jit.integrator as integrator_module


def cornell(delta_sphere=False):
    d = mi.cornell_box()
    d['sensor']['film'].update(width=8, height=8)
    return mi.load_dict(d)


def traced_ops(scene, **params):
    """(total operations of the JIT kernels launched by one render, their count, render info)."""
    integ = mi.load_dict({'type': 'bdpt', **params})
    mi.render(scene, integrator=integ, spp=1)     # warm-up: one-off setup kernels (emitter tables)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                       # clear
        mi.render(scene, integrator=integ, spp=1)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [k for k in hist if k['type'] == dr.KernelType.JIT]
    return sum(k.get('operation_count', 0) for k in jit), len(jit), integ.last_render_info


def test_pt_traces_no_light_subpath():
    scene = cornell()
    ops_pt, n_pt, info_pt = traced_ops(scene, technique='pt', max_depth=5)
    ops_bd, n_bd, info_bd = traced_ops(scene, technique='bdpt', max_depth=5)
    assert not info_pt['light_pass'] and info_bd['light_pass']
    assert not any('t=1' in s for s in info_pt['strategies'])
    assert ops_pt < 0.6 * ops_bd, (ops_pt, ops_bd)


def test_lt_traces_no_camera_subpath():
    scene = cornell()
    ops_lt, _, info = traced_ops(scene, technique='lt', max_depth=5)
    ops_bd, _, _ = traced_ops(scene, technique='bdpt', max_depth=5)
    assert not info['camera_pass'] and info['light_pass']
    assert ops_lt < 0.6 * ops_bd


def test_short_max_depth_leaves_out_connections():
    scene = cornell()
    ops2, _, info2 = traced_ops(scene, max_depth=2)
    ops5, _, info5 = traced_ops(scene, max_depth=5)
    assert not any('s>=2' in s for s in info2['strategies'])
    assert any('s>=2' in s for s in info5['strategies'])
    assert info2['light_vertex_levels'] == 0 and info5['light_vertex_levels'] == 3
    assert ops2 < 0.8 * ops5, (ops2, ops5)


def test_delta_handling_traced_only_when_the_scene_has_delta_bsdfs(monkeypatch):
    scene = cornell()                                  # diffuse only
    ops_plain, _, info = traced_ops(scene, max_depth=5)
    assert info['delta_handling'] is False
    monkeypatch.setattr(integrator_module, 'scene_has_delta_bsdf', lambda s: True)
    ops_forced, _, info_f = traced_ops(scene, max_depth=5)
    assert info_f['delta_handling'] is True
    assert ops_plain < ops_forced, (ops_plain, ops_forced)


def test_render_reports_strategies():
    scene = cornell()
    _, _, info = traced_ops(scene, max_depth=5, hide_emitters=True)
    assert info['strategies'] and not any('s=1,t=1' in s for s in info['strategies'])
    _, _, info = traced_ops(scene, max_depth=1)
    assert [s.split(' ')[0] for s in info['strategies']] == ['s=0', 's=1,t=1']
