"""The kernels are specialised to the scene and the settings: what a setting does not need is
not traced. Measured from Dr.Jit's kernel history (operations in the launched kernels)."""

import gc
import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import bdpt_jit.context as context_module
from helpers import cornell_scene
from stability_cases import cornell


def traced_ops(scene, loops=None, **params):
    """(total operations of the JIT kernels launched by one render, their count, render info).
    ``loops``: a list that receives, per kernel, the labels of the symbolic loops it holds."""
    gc.collect()    # (a virtual call's code depends on how many instances are alive: test_media._kernel_hashes)
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
    if loops is not None:
        loops += [re.findall(r'; Symbolic loop: (\S+)', k['ir'].getvalue()) for k in jit]
    return sum(k.get('operation_count', 0) for k in jit), len(jit), integ.last_render_info


def test_pt_traces_no_light_subpath():
    scene = cornell_scene(8)
    ops_pt, n_pt, info_pt = traced_ops(scene, technique='pt', max_depth=5)
    ops_bd, n_bd, info_bd = traced_ops(scene, technique='bdpt', max_depth=5)
    assert not info_pt['light_pass'] and info_bd['light_pass']
    assert not any('t=1' in s for s in info_pt['strategies'])
    assert ops_pt < 0.6 * ops_bd, (ops_pt, ops_bd)


def test_lt_traces_no_camera_subpath():
    scene = cornell_scene(8)
    ops_lt, _, info = traced_ops(scene, technique='lt', max_depth=5)
    ops_bd, _, _ = traced_ops(scene, technique='bdpt', max_depth=5)
    assert not info['camera_pass'] and info['light_pass']
    assert ops_lt < 0.6 * ops_bd


def test_short_max_depth_leaves_out_connections():
    scene = cornell_scene(8)
    loops2, loops5 = [], []
    ops2, _, info2 = traced_ops(scene, loops2, max_depth=2)
    ops5, _, info5 = traced_ops(scene, loops5, max_depth=5)
    assert not any('s>=2' in s for s in info2['strategies'])
    assert any('s>=2' in s for s in info5['strategies'])
    assert info2['light_vertex_levels'] == 0 and info5['light_vertex_levels'] == 3
    assert not any('bdpt_connect' in k for k in loops2) and any('bdpt_connect' in k for k in loops5)
    assert ops2 < 0.85 * ops5, (ops2, ops5)


def test_light_subpaths_are_traced_once():
    """The camera kernel reads what the light subpaths leave it (the sampler's state, the stored
    vertices' counts) from memory: no kernel but the light pass's replays the light loop."""
    for technique in ('bdpt', 'vcm'):
        loops = []
        traced_ops(cornell_scene(8), loops, technique=technique, max_depth=5)
        holding = [k for k in loops if 'bdpt_light_subpath' in k]
        assert len(holding) == 1 and 'bdpt_camera_subpath' not in holding[0], (technique, loops)


def test_delta_handling_traced_only_when_the_scene_has_delta_bsdfs(monkeypatch):
    # through Mitsuba's BSDF calls: with the constant-diffuse table (all of this scene) the
    # sampled lobe is a constant and Dr.Jit folds the delta tests away either way
    monkeypatch.setattr(context_module, 'diffuse_table', lambda s: None)
    scene = cornell_scene(8)                          # diffuse only
    ops_plain, _, info = traced_ops(scene, max_depth=5)
    assert info['delta_handling'] is False
    monkeypatch.setattr(context_module, 'scene_has_delta_bsdf', lambda s: True)
    ops_forced, _, info_f = traced_ops(scene, max_depth=5)
    assert info_f['delta_handling'] is True
    assert ops_plain < ops_forced, (ops_plain, ops_forced)


def test_render_reports_strategies():
    scene = cornell_scene(8)
    _, _, info = traced_ops(scene, max_depth=5, hide_emitters=True)
    assert info['strategies'] and not any('s=1,t=1' in s for s in info['strategies'])
    _, _, info = traced_ops(scene, max_depth=1)
    assert [s.split(' ')[0] for s in info['strategies']] == ['s=0', 's=1,t=1']


# ---------------------------------------------------------------------------- light-vertex records
def _shapes_scene():
    """Every shape kind the record analysis distinguishes, with BSDFs of each class."""
    T = mi.ScalarTransform4f
    d = cornell(16)
    d['ball'] = {'type': 'sphere', 'center': [0.4, -0.6, 0.2], 'radius': 0.3, 'bsdf': {'type': 'roughconductor', 'alpha': 0.3}}
    d['disk'] = {'type': 'disk', 'to_world': T().translate([-0.4, -0.5, -0.3]).rotate([1, 0, 0], -70).scale(0.3),
                 'bsdf': {'type': 'roughplastic', 'alpha': 0.2}}
    d['cube'] = {'type': 'cube', 'to_world': T().translate([-0.5, -0.8, 0.3]).scale(0.2), 'bsdf': {'type': 'diffuse'}}
    return d


@pytest.mark.parametrize('variant', ['plain', 'smooth_mesh', 'textured', 'anisotropic', 'delta'])
def test_light_vertex_record_drops_only_unread_fields(variant, monkeypatch):
    """Light vertices store only the fields the scene's BSDFs and shapes read (scene_check.
    VertexNeeds): with the same seed the image equals the one rendered with every field stored
    (relative 1e-4 of the mean: the reconstructed frames differ by rounding), and each field
    appears exactly in the scenes that need it."""
    from bdpt_jit.store import StoredVertex
    d = _shapes_scene()
    want = {'n': False, 's': False, 'uv': False, 'depth': False}
    if variant == 'smooth_mesh':      # a mesh with interpolated normals: n_s != n
        import stability_cases
        d['blob'] = stability_cases.lowpoly_sphere_mesh(radius=0.25, center=(0.0, 0.3, 0.0),
                                                        bsdf={'type': 'diffuse'})
        want['n'] = True
    elif variant == 'textured':
        d['ball']['bsdf'] = {'type': 'diffuse', 'reflectance': {'type': 'checkerboard'}}
        want.update(uv=True, s=True)
    elif variant == 'anisotropic':
        d['ball']['bsdf'] = {'type': 'roughconductor', 'alpha_u': 0.05, 'alpha_v': 0.4}
        want['s'] = True
    elif variant == 'delta':
        d['ball']['bsdf'] = {'type': 'dielectric'}
        want['depth'] = True
    scene = mi.load_dict(d)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 6})
    a = np.array(mi.render(scene, integrator=integ, spp=16, seed=4))
    fields = integ.last_render_info['light_vertex_fields']
    for k, need in want.items():
        assert (k in fields) == need, f'{variant}: field {k} stored={k in fields}, needed={need} ({fields})'
    monkeypatch.setattr(context_module, 'record_type', lambda needs, **kw: StoredVertex)
    b = np.array(mi.render(scene, integrator=integ, spp=16, seed=4))
    assert integ.last_render_info['light_vertex_fields'] == list(StoredVertex.DRJIT_STRUCT)
    assert np.isfinite(a).all()
    err = np.abs(a - b).max() / b.mean()
    assert err < 1e-4, f'{variant}: max deviation {err:.3g} of the mean'


@pytest.mark.parametrize('variant', ['all_diffuse', 'mixed', 'textured_diffuse'])
def test_constant_diffuse_bsdfs_without_virtual_calls(variant, monkeypatch):
    """connect.DiffuseTable evaluates and samples Mitsuba's `diffuse` with a constant reflectance
    without a virtual call, in scenes where every BSDF is such a diffuse one. With the same
    seed the image equals the one rendered through Mitsuba's BSDF calls (relative 1e-4 of the
    mean), with fewer operations traced; a scene that mixes it with other BSDFs, and one whose
    only diffuse BSDF is textured, get no table (a table beside the calls was slower)."""
    d = _shapes_scene()
    if variant == 'all_diffuse':
        for k in ('ball', 'disk'):
            d[k]['bsdf'] = {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.3, 0.6, 0.2]}}
    elif variant == 'textured_diffuse':
        d = cornell(16)
        for k in d:
            if isinstance(d[k], dict) and d[k].get('type') == 'diffuse':
                d[k]['reflectance'] = {'type': 'checkerboard'}
    scene = mi.load_dict(d)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 6})
    ctx = integ.make_context(scene, scene.sensors()[0])
    assert (ctx.diffuse is not None) == (variant == 'all_diffuse')
    a = np.array(mi.render(scene, integrator=integ, spp=16, seed=5))
    ops_a, _, _ = traced_ops(scene, max_depth=6)
    monkeypatch.setattr(context_module, 'diffuse_table', lambda s: None)
    b = np.array(mi.render(scene, integrator=integ, spp=16, seed=5))
    ops_b, _, _ = traced_ops(scene, max_depth=6)
    assert np.isfinite(a).all()
    err = np.abs(a - b).max() / b.mean()
    assert err < 1e-4, f'{variant}: max deviation {err:.3g} of the mean'
    if variant == 'all_diffuse':
        assert ops_a < ops_b, (ops_a, ops_b)


@pytest.mark.parametrize('technique', ['pt', 'lt', 'bdpt'])
def test_one_bsdf_call_for_the_evaluation_and_the_scatter(technique, monkeypatch):
    """vertex.Vertex.eval_and_draw: a vertex's emitter-sampling evaluation (camera side) or its
    splat's (light side) and its scatter's BSDF sample come from one BSDF call, the scatter's
    samples drawn in the order the scatter draws them. With the same seed the image equals the
    one rendered with two calls up to rounding (the calls are compiled apart, and the light
    image's atomic sums add in any order): every pixel within 1e-3 of the mean, 99% of them
    within 1e-4 (with 1e-5, lt failed 1 run in 3). At max_depth 3 the light subpath's vertices
    at depth 2 are splatted but do not scatter: the call must serve both sets of lanes."""
    scene = mi.load_dict(_shapes_scene())          # no constant-diffuse table: Mitsuba's calls
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 3, 'technique': technique})
    assert integ.make_context(scene, scene.sensors()[0]).fuse_draw
    a = np.array(mi.render(scene, integrator=integ, spp=16, seed=7))
    monkeypatch.setattr(context_module, 'FUSE_DRAW', False)
    assert not integ.make_context(scene, scene.sensors()[0]).fuse_draw
    b = np.array(mi.render(scene, integrator=integ, spp=16, seed=7))
    assert np.isfinite(a).all()
    dev = np.abs(a - b).max(axis=-1) / b.mean()
    assert dev.max() < 1e-3 and np.mean(dev < 1e-4) > 0.99, (technique, dev.max(), np.mean(dev < 1e-4))


@pytest.mark.parametrize('name,technique', [('all-lights.xml', 'pt'), ('all-lights.xml', 'bdpt'),
                                            ('media/fog.xml', 'bdpt'), ('caustic.xml', 'vcm'),
                                            ('media/volumetric-caustic.xml', 'vcm')])
def test_sparse_strategies_in_branches(name, technique, monkeypatch):
    """camera_path.where: s=0 at emitters hit and at the environment, and the merges at camera
    vertices and along camera segments in media (vcm's default merge set: behind delta vertices
    only), are computed in a symbolic branch that packets without such a lane skip. With the
    same seed the image and every strategy layer (whose splats are side effects inside the
    branch) equal those computed in every lane, to rounding. vcm has no strategy layers: there
    the merges are shown to be in the image (it changes when their gathers return 0)."""
    import bdpt_jit.camera_path as camera_path
    from helpers import scene_path
    scene = mi.load_file(scene_path(name), res=16, max_depth=4)
    layered = technique != 'vcm'
    merging = {} if layered else {'radius': 0.05}       # (a radius at which a 16 x 16 image's merges find light)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': technique, 'strategy_images': layered, **merging})
    out = {}
    for sparse in (True, False):
        monkeypatch.setattr(camera_path, 'SPARSE_IF', sparse)
        integ.merge_iteration = 0           # (each render's merges at the same radius: merge.py)
        img = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
        out[sparse] = img, ({k: {kind: np.array(v) for kind, v in d.items()} for k, d in integ.strategy_images.items()}
                            if layered else {})
    scale = out[False][0].max()
    np.testing.assert_allclose(out[True][0], out[False][0], rtol=1e-5, atol=1e-6 * scale)
    if not layered:
        from bdpt_jit.beams import BeamGather
        from bdpt_jit.merge import Merger
        monkeypatch.setattr(Merger, 'gather', lambda self, idx, v, sub, active, film_pos=None, own=True: mi.Spectrum(0.0))
        monkeypatch.setattr(BeamGather, 'gather', lambda self, idx, seg, active, film_pos=None: mi.Spectrum(0.0))
        integ.merge_iteration = 0
        without = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
        assert np.abs(without - out[True][0]).max() > 1e-3 * scale
        return
    assert out[True][1].keys() == out[False][1].keys()
    assert any(k.startswith('s0_') and out[True][1][k]['weighted'].max() > 0 for k in out[True][1]), list(out[True][1])
    for k, layers in out[True][1].items():
        for kind, layer in layers.items():
            np.testing.assert_allclose(layer, out[False][1][k][kind], rtol=1e-5, atol=1e-6 * scale, err_msg=k)


def test_reverse_densities_only_where_a_weight_reads_them(monkeypatch):
    """mis.MIS.reads_reverse: pt's camera subpaths ask for no reverse BSDF density (no weight of
    pt reads d_vc or d_vm), and its image with the same seed equals the one rendered with them
    (to rounding): a weight that did read them would change. Light subpaths always ask for it:
    vm's, on a normal-mapped scene, carry the exact adjoint that comes with it
    (transport._reverse_pdf). Planted: pt asking for them, or vm's light subpaths not, fails."""
    import bdpt_jit.transport as transport
    from bdpt_jit.mis import MIS
    from stability_cases import normal_mapped
    modes, reverse_pdf = [], transport._reverse_pdf

    def recorded(ctx, mode, *args):
        modes.append(mode)
        return reverse_pdf(ctx, mode, *args)
    monkeypatch.setattr(transport, '_reverse_pdf', recorded)
    scene = mi.load_dict(_shapes_scene())
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'pt'})
    a = np.array(mi.render(scene, integrator=integ, spp=16, seed=7))
    assert modes == []
    monkeypatch.setattr(MIS, 'reads_reverse', property(lambda self: True))
    b = np.array(mi.render(scene, integrator=integ, spp=16, seed=7))
    assert modes and set(modes) == {'radiance'}
    assert np.isfinite(a).all() and a.max() > 0
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * b.max())
    monkeypatch.undo()
    monkeypatch.setattr(transport, '_reverse_pdf', recorded)
    modes.clear()
    vm = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'vm'})
    mi.render(mi.load_dict(normal_mapped(8)), integrator=vm, spp=1, seed=7)
    assert 'importance' in modes and 'radiance' not in modes
