"""Differentiable bdpt (gradients.py): derivatives of images in forward and reverse mode.

- Linearity in emission: with every emitter's value v scaled by s, d image / d s at s = 1 is
  the image itself (same seed): a forward derivative along v, or sum(grad . v) in reverse mode,
  reproduces the primal image exactly, for every emitter kind and every technique.
- Finite differences: per 8x8 block and for the image mean, the forward-mode derivative with
  respect to a reflectance, a roughness, a mirror's specular reflectance and environment texels
  agrees with central finite differences (both over independent seeds) within 3.5 standard
  errors.
- pt and lt derivatives agree with bdpt's, and pt's with Mitsuba's prb on a scene without
  caustics.
- Reverse-mode memory does not grow with spp; the primal is the same with gradients enabled.
"""

import os
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import scene_path

RES = 16


def load(name, **kw):
    if name == 'rough':         # the Cornell box, its tall box a rough aluminium conductor
        import stability_cases as sc
        d = sc.cornell(RES)
        d['large-box'] = dict(d['large-box'], bsdf={'type': 'roughconductor', 'material': 'Al', 'alpha': 0.15})
        return mi.load_dict(d)
    if name in ('grazing-conductor', 'grazing-glass'):
        return mi.load_dict(grazing_scene(name == 'grazing-glass'))
    return mi.load_file(scene_path(name), res=RES, **kw)


def grazing_scene(glass):
    """A rough plane (aluminium, or a glass interface) under a constant sky, seen at grazing
    angles (57-87 degrees from its normal), where shadowing and masking make the image depend
    strongly on alpha: its derivative is large in every 8x8 block (the glass darkens everywhere;
    the aluminium brightens at the most grazing angles and darkens nearer the camera)."""
    T = mi.ScalarTransform4f
    bsdf = ({'type': 'roughdielectric', 'alpha': 0.4, 'int_ior': 1.5} if glass else
            {'type': 'roughconductor', 'material': 'Al', 'alpha': 0.4})
    return {'type': 'scene',
            'sensor': {'type': 'perspective', 'fov': 30,
                       'to_world': T().look_at([0, 1, 3], [0, 0, 0], [0, 1, 0]),
                       'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'}}},
            'plane': {'type': 'rectangle', 'to_world': T().rotate([1, 0, 0], -90).scale(40), 'bsdf': bsdf},
            'sky': {'type': 'constant', 'radiance': 1.0}}


def attach(params, key):
    """A gradient-enabled copy of a parameter, set into the scene as Mitsuba's optimizers do
    (enabling gradients on the traversed value in place does not reach every plugin: an
    envmap's texture keeps its own copy)."""
    v = type(params[key])(dr.detach(params[key]))
    dr.enable_grad(v)
    params[key] = v
    params.update()
    return v


def emitter_keys(params):
    out = []
    for k in params.keys():
        leaf = k.split('.')
        if k.endswith('radiance.value') or k.endswith('intensity.value') or k.endswith('irradiance.value') \
                or leaf[-1] == 'data':
            out.append(k)
    return out


# ---------------------------------------------------------------------------- linearity
@pytest.mark.parametrize('technique', ['bdpt', 'pt', 'lt'])
@pytest.mark.parametrize('name', ['cornell-box.xml', 'all-lights.xml', 'sun-room.xml'])
def test_image_is_linear_in_emission_forward(name, technique):
    assert_linear_in_emission(load(name), {'type': 'bdpt', 'max_depth': 5, 'technique': technique}, name)


@pytest.mark.parametrize('technique', ['bdpt', 'lt'])
def test_image_is_linear_in_emission_with_emitters_hidden(technique):
    """hide_emitters: the derivative passes hide the directly visible emitter as the primal
    does (camera rays pass its shape, no s=0 at the first vertex, no splat of light vertex 0):
    d image / d s equals the image without the light seen directly. Planted: the derivative pass
    not hiding it fails (the Cornell box's light is in view)."""
    assert_linear_in_emission(load('cornell-box.xml'), {'type': 'bdpt', 'max_depth': 5, 'technique': technique,
                                                        'hide_emitters': True}, 'hide_emitters')


def assert_linear_in_emission(scene, integrator, what):
    """Every emitted value scaled by s: the forward derivative d image / d s at s = 1 equals the
    image (the same samples: seed_grad of the differentiable pass, seed of the primal), every
    pixel within 1e-4 of the image's mean, and finite."""
    params = mi.traverse(scene)
    keys = emitter_keys(params)
    assert keys
    vs = [attach(params, k) for k in keys]
    integ = mi.load_dict(integrator)
    img = mi.render(scene, params, integrator=integ, spp=4, seed=1, seed_grad=2)
    for v in vs:
        dr.set_grad(v, dr.detach(v))
    dr.forward_to(img)
    g = np.array(dr.grad(img))
    ref = np.array(mi.render(scene, integrator=integ, spp=4, seed=2))
    assert np.all(np.isfinite(g))
    err = np.abs(g - ref).max() / max(ref.mean(), 1e-12)
    assert err < 1e-4, f'{what} {integrator}: d image/d s differs from the image by {err:.3g} of its mean'


@pytest.mark.parametrize('name', ['cornell-box.xml', 'all-lights.xml'])
def test_image_is_linear_in_emission_reverse(name):
    scene = load(name)
    params = mi.traverse(scene)
    keys = emitter_keys(params)
    vs = [attach(params, k) for k in keys]
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5})
    img = mi.render(scene, params, integrator=integ, spp=4, seed=1, seed_grad=2)
    dr.backward(img)
    total = sum(float(np.sum(np.array(dr.grad(v) * dr.detach(v)))) for v in vs)
    ref = np.array(mi.render(scene, integrator=integ, spp=4, seed=2))
    assert abs(total - ref.sum()) < 1e-4 * ref.sum(), (total, ref.sum())


def test_a_smooth_emitter_mesh_is_linear_in_emission():
    """Emitter sampling on a smooth-shaded emitter mesh (smooth_emitters.py) in a
    differentiable pass keeps the radiance by the shading normal: Mitsuba's eval_direction
    reads the side from the sample's normal, its triangle's, and on a mesh whose normals are
    flipped (the camera sees only the radiance behind its triangles) d image / d s was 13.6
    times the image's mean off the image (pt)."""
    from stability_cases import cornell, lowpoly_sphere_mesh
    d = cornell(16)
    d.pop('light')
    d['bulb'] = lowpoly_sphere_mesh(4, 8, radius=0.35, center=(0.1, 0.3, 0.0), flip=True,
                                    emitter={'type': 'area', 'radiance': {'type': 'rgb', 'value': [8.0, 8.0, 8.0]}},
                                    bsdf={'type': 'twosided', 'bsdf': {'type': 'diffuse'}})
    assert_linear_in_emission(mi.load_dict(d), {'type': 'bdpt', 'max_depth': 4, 'technique': 'pt'}, 'flipped smooth bulb')


def test_primal_unchanged_with_gradients_enabled():
    scene = load('paper-fig6.xml')
    params = mi.traverse(scene)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5})
    plain = np.array(mi.render(scene, integrator=integ, spp=4, seed=3))
    for k in ('white.reflectance.value', 'floor.bsdf.alpha', 'light.emitter.radiance.value'):
        attach(params, k)
    with_grad = np.array(mi.render(scene, params, integrator=integ, spp=4, seed=3))
    # (up to float32 rounding: light tracing's splats are atomic adds whose order varies)
    np.testing.assert_allclose(plain, with_grad, rtol=1e-5, atol=1e-7)


def test_geometry_with_delta_bsdfs_is_refused_with_a_reason():
    """Shape parameters in a scene with mirrors or glass: technique lt is refused (every path
    reaches the image through a splat that moves with the geometry) and vcm too (merging is not
    differentiable), each naming the reason; pt and bdpt render their derivative."""
    scene = load('paper-fig6.xml')
    key = next(k for k in mi.traverse(scene).keys() if k.endswith('to_world') and 'floor' in k)
    for technique in ('bdpt', 'pt', 'lt', 'vcm'):
        scene = load('paper-fig6.xml')
        params = mi.traverse(scene)
        attach(params, key)
        img = mi.render(scene, params, integrator=mi.load_dict({'type': 'bdpt', 'technique': technique, 'max_depth': 3}), spp=1)
        if technique in ('pt', 'bdpt'):
            dr.backward(img)
            continue
        with pytest.raises(Exception) as e:
            dr.backward(img)
        text = repr(e.value) + repr(e.value.__cause__)
        assert f"technique '{technique}'" in text and ('boundary' in text or 'not differentiable' in text), text


# ---------------------------------------------------------------------------- finite differences
def forward_batches(scene, key, delta, integ, spp, batches, seed0=100):
    params = mi.traverse(scene)
    out = []
    base = type(params[key])(dr.detach(params[key]))
    for b in range(batches):
        v = attach(params, key)
        img = mi.render(scene, params, integrator=integ, spp=spp, seed=seed0 + b, seed_grad=seed0 + 5000 + b)
        dr.set_grad(v, delta)
        dr.forward_to(img)
        out.append(np.array(dr.grad(img), dtype=np.float64)[:, :, :3])
    params[key] = base
    params.update()
    return np.stack(out)


def fd_batches(scene, key, delta, h, integ, spp, batches, seed0=100):
    params = mi.traverse(scene)
    base = mi.TensorXf(params[key]) if isinstance(params[key], mi.TensorXf) else type(params[key])(params[key])
    out = []
    for b in range(batches):
        imgs = []
        for sgn in (1, -1):
            params[key] = base + sgn * h * delta
            params.update()
            imgs.append(np.array(mi.render(scene, integrator=integ, spp=spp, seed=seed0 + 9000 + b), dtype=np.float64))
        out.append((imgs[0] - imgs[1])[:, :, :3] / (2 * h))
    params[key] = base
    params.update()
    return np.stack(out)


def assert_agree(a, b, what, block=8, z=3.5):
    K = a.shape[0]
    def blocks(x):
        k, H, W, C = x.shape
        return x.reshape(k, H // block, block, W // block, block, C).mean(axis=(2, 4, 5))
    for name, (x, y) in (('8x8 block', (blocks(a), blocks(b))),
                         ('image mean', (a.mean(axis=(1, 2, 3)), b.mean(axis=(1, 2, 3))))):
        se = np.sqrt(x.var(axis=0, ddof=1) / K + y.var(axis=0, ddof=1) / y.shape[0])
        d = np.abs(x.mean(axis=0) - y.mean(axis=0))
        bad = d > z * se + 1e-6 * np.abs(y.mean(axis=0)).max()
        assert not np.any(bad), (f'{what}: {name} AD {np.ravel(x.mean(axis=0))[:4]} vs other '
                                 f'{np.ravel(y.mean(axis=0))[:4]}, {np.ravel(d / np.maximum(se, 1e-30))[:8]} SE')


FD_CASES = {
    # name: (scene, key, direction builder, h, max_depth[, spp: 16])
    'cornell_reflectance': ('cornell-box.xml', 'white.reflectance.value', lambda v: mi.Color3f(1, 0, 0), 0.05, 5),
    'caustic_floor_reflectance': ('caustic.xml', 'floor_white.reflectance.value', lambda v: mi.Color3f(0, 1, 0), 0.05, 5),
    # Mitsuba's roughplastic precomputes its Fresnel tables from alpha without derivatives (its
    # own prb is 6x off finite differences there): the roughness case is a rough conductor
    'cornell_rough_conductor': ('rough', 'large-box.bsdf.alpha.value', lambda v: mi.Float(1.0), 0.03, 5),
    'grazing_rough_conductor': ('grazing-conductor', 'plane.bsdf.alpha.value', lambda v: mi.Float(1.0), 0.05, 5, 1024),
    'grazing_rough_glass': ('grazing-glass', 'plane.bsdf.alpha.value', lambda v: mi.Float(1.0), 0.05, 5, 1024),
    'fig6_mirror': ('paper-fig6.xml', 'mirror_sphere.bsdf.specular_reflectance.value', lambda v: mi.Float(1.0), 0.1, 5),
    'fig6_textured_reflectance': ('paper-fig6.xml', 'textured_sphere.bsdf.reflectance.color0.value',
                                  lambda v: mi.Color3f(1, 1, 1), 0.05, 5),
}


@pytest.mark.parametrize('case', list(FD_CASES))
def test_forward_derivative_agrees_with_finite_differences(case):
    name, key, direction, h, max_depth, *spp = FD_CASES[case]
    spp = spp[0] if spp else 16
    scene = load(name)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': max_depth})
    params = mi.traverse(scene)
    delta = direction(params[key])
    ad = forward_batches(scene, key, delta, integ, spp, 12)
    fd = fd_batches(scene, key, delta, h, integ, spp, 12)
    assert np.all(np.isfinite(ad))
    assert np.abs(ad).max() > 0
    assert_agree(ad, fd, case)


def test_envmap_texels_derivative_agrees_with_finite_differences():
    scene = load('all-lights.xml')
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith('.data'))
    shape = params[key].shape
    region = np.zeros(shape, np.float32)
    region[: shape[0] // 2, : shape[1] // 3, :] = 1.0          # the upper-left part of the sky
    delta = mi.TensorXf(region)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4})
    ad = forward_batches(scene, key, delta, integ, 16, 12)
    fd = fd_batches(scene, key, delta, 0.05, integ, 16, 12)
    assert np.abs(ad).max() > 0
    assert_agree(ad, fd, 'envmap region')


def open_floor(light_y=4.0, light='cube'):
    """A mesh area light (a small cube; or a point or a directional light) above a floor (a
    flat mesh box) that fills the view; the light is out of the camera's view, so moving it or
    the floor moves no visibility boundary."""
    T = mi.ScalarTransform4f
    lights = {
        'cube': {'type': 'cube', 'to_world': T().translate([0.5, light_y, 0]).scale(0.3),
                 'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': 40.0}}},
        'point': {'type': 'point', 'position': [0.5, light_y, 0], 'intensity': {'type': 'rgb', 'value': 20.0}},
        'directional': {'type': 'directional', 'direction': [0.3, -1, 0.2],
                        'irradiance': {'type': 'rgb', 'value': 2.0}},
    }
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 40,
                   'to_world': T().look_at(origin=[0, 1.5, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'floor': {'type': 'cube', 'to_world': T().translate([0, -0.1, 0]).scale([100, 0.1, 100]),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.6}}},
        'light': lights[light],
    })


@pytest.mark.parametrize('technique', ['bdpt', 'pt'])
@pytest.mark.parametrize('shape,direction,light', [
    ('light', (0.0, 1.0, 0.0), 'cube'), ('light', (1.0, 0.0, 0.0), 'cube'), ('floor', (0.0, 1.0, 0.0), 'cube'),
    ('floor', (0.0, 1.0, 0.0), 'point'), ('floor', (0.0, 1.0, 0.0), 'directional')])
def test_vertex_translation_agrees_with_finite_differences(shape, direction, light, technique):
    """The interior derivative with respect to shape vertices (gradients.py: material-point
    vertices, the edge factors differentiated; a camera ray's first hit slides along the ray;
    light-tracing splats out of the derivative's partition of unity): translating the light up
    or sideways, or the floor (seen by the camera) up."""
    scene = open_floor(light=light)
    params = mi.traverse(scene)
    key = f'{shape}.vertex_positions'
    n = dr.width(params[key]) // 3
    delta = dr.ravel(mi.Point3f(*(mi.Float(c) + dr.zeros(mi.Float, n) for c in direction)))
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 3, 'technique': technique})
    ad = forward_batches(scene, key, delta, integ, 64, 12)
    fd = fd_batches(scene, key, delta, 0.02, integ, 64, 12)
    if light == 'directional':
        # a diffuse floor under a directional light looks the same at every height: 0 (a
        # distance falloff applied to it, as once in sample_direct, makes it non-zero)
        assert np.abs(ad).max() < 1e-4 * max(np.abs(fd).max(), 1.0), np.abs(ad).max()
        return
    assert np.abs(ad.mean()) > 0
    assert_agree(ad, fd, f'{shape} {direction} {light} {technique}')


def test_geometry_with_light_tracing_alone_is_refused():
    scene = open_floor()
    params = mi.traverse(scene)
    attach(params, 'light.vertex_positions')
    img = mi.render(scene, params, integrator=mi.load_dict({'type': 'bdpt', 'technique': 'lt'}), spp=1)
    with pytest.raises(Exception) as e:
        dr.backward(img)
    assert "technique 'lt'" in repr(e.value) + repr(e.value.__cause__)


# ---------------------------------------------------------------------------- techniques, prb
@pytest.mark.parametrize('technique', ['pt', 'lt'])
def test_techniques_agree_with_bdpt(technique):
    scene = load('cornell-box.xml')
    key, delta = 'red.reflectance.value', mi.Color3f(1, 1, 1)
    a = forward_batches(scene, key, delta, mi.load_dict({'type': 'bdpt', 'max_depth': 4}), 16, 12)
    b = forward_batches(scene, key, delta, mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': technique}),
                        64 if technique == 'lt' else 16, 12, seed0=700)
    assert_agree(a, b, f'{technique} vs bdpt')


def test_pt_agrees_with_prb():
    scene = load('cornell-box.xml')
    key, delta = 'white.reflectance.value', mi.Color3f(0, 0, 1)
    a = forward_batches(scene, key, delta, mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': 'pt'}), 16, 12)
    b = forward_batches(scene, key, delta, mi.load_dict({'type': 'prb', 'max_depth': 4}), 16, 12, seed0=900)
    assert_agree(a, b, 'pt vs prb')


# ---------------------------------------------------------------------------- memory
PEAK = r'''
import resource, sys
import drjit as dr, mitsuba as mi
mi.set_variant('llvm_ad_rgb')
import bdpt_jit
scene = mi.load_file(sys.argv[1], res=32)
params = mi.traverse(scene)
v = mi.Color3f(params['white.reflectance.value']); dr.enable_grad(v)
params['white.reflectance.value'] = v; params.update()
integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'samples_per_pass': 8 * 32 * 32})
img = mi.render(scene, params, integrator=integ, spp=int(sys.argv[2]), seed=1, seed_grad=2)
dr.backward(img)
dr.eval(dr.grad(v))
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
'''


def test_reverse_mode_memory_does_not_grow_with_spp():
    """Peak resident memory of a reverse-mode render at 16 and at 128 spp, each in a fresh
    process, in passes of 8 spp (2 and 16 passes; measured 286 and 289 MB at 64x64 with 256 spp,
    before 32x32 for CI time: a pass's graph kept alive would add 16 of them)."""
    peaks = {}
    for spp in (16, 128):
        out = subprocess.run([sys.executable, '-c', PEAK, scene_path('cornell-box.xml'), str(spp)],
                             capture_output=True, text=True, timeout=600, env=dict(os.environ))
        assert out.returncode == 0, out.stderr[-2000:]
        peaks[spp] = int(out.stdout.strip().splitlines()[-1])
    assert peaks[128] <= 1.15 * peaks[16], f'peak RSS (KiB): {peaks}'


@pytest.mark.parametrize('builder', ['directionalarea_box', 'projector_box', 'textured_box'])
def test_new_emitter_kinds_are_linear_in_emission(builder):
    """The emitters of tests/test_coverage.py (directionalarea, projector, textured area light):
    for each of its values, the forward derivative along that value is the image (same seed;
    one value at a time: a projector's image is scale x irradiance, of degree 2 in both)."""
    import test_coverage as tc
    names = mi.traverse(mi.load_dict(getattr(tc, builder)())).keys()
    keys = [k for k in names if k.endswith(('radiance.value', 'radiance.data', 'irradiance.data', 'intensity.value',
                                            'projector.scale', 'radiance.color0.value'))]
    assert keys, list(names)
    for key in keys:
        scene = mi.load_dict(getattr(tc, builder)())
        params = mi.traverse(scene)
        if not isinstance(params[key], (mi.Float, mi.Color3f, mi.TensorXf)):
            continue
        v = attach(params, key)
        integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4})
        img = mi.render(scene, params, integrator=integ, spp=4, seed=1, seed_grad=2)
        dr.set_grad(v, dr.detach(v))
        dr.forward_to(img)
        g = np.array(dr.grad(img))
        ref = np.array(mi.render(scene, integrator=integ, spp=4, seed=2))
        err = np.abs(g - ref).max() / max(ref.mean(), 1e-12)
        assert err < 1e-3, f'{builder} {key}: d image/d s differs from the image by {err:.3g} of its mean'


# ---------------------------------------------------------------------------- vertex translation: closed scenes
def empty_cornell_box():
    """Mitsuba's Cornell box without its two boxes, its light a thin box (a convex mesh
    emitter: no part of it hides another) under a black ceiling, the camera tilted down so that
    neither the light nor the ceiling is in view. Moving the light within its plane moves no
    visibility boundary: nothing stands between it and the walls or the floor, the walls and
    the floor form a convex room (no point of them hides another), and the only thing the light
    hides (the ceiling, and a 0.015-high strip of wall above its lower face) reflects nothing or
    is too small to matter. The derivative is not small: the walls and the floor are lit
    directly by the light, and every wall sees the light move towards or away from it."""
    import stability_cases as sc
    T = mi.ScalarTransform4f
    d = sc.cornell(RES)
    for k in ('small-box', 'large-box', 'light'):
        d.pop(k)
    d['black'] = {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.0}}
    d['ceiling'] = dict(d['ceiling'], bsdf={'type': 'ref', 'id': 'black'})
    d['light'] = {'type': 'cube', 'to_world': T().translate([0.0, 0.99, 0.01]).scale([0.23, 0.005, 0.19]),
                  'bsdf': {'type': 'ref', 'id': 'black'},
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [18.4, 14.0, 6.75]}}}
    # 12.3 degrees down: the view's upper edge reaches y = 0.63 at the back wall
    d['sensor']['to_world'] = T().look_at(origin=[0, 0, 3.9], target=[0, -0.85, 0], up=[0, 1, 0])
    return mi.load_dict(d)


def assert_nonzero(fd, z=5.0, block=8):
    """The derivative of the image mean or of some 8x8 block is further than z standard errors
    from 0: the comparison tests a derivative, not noise."""
    k, H, W, C = fd.shape
    b = fd.reshape(k, H // block, block, W // block, block, C).mean(axis=(2, 4, 5)).reshape(k, -1)
    m = np.concatenate([b, fd.mean(axis=(1, 2, 3))[:, None]], axis=1)
    t = np.abs(m.mean(axis=0)) / (m.std(axis=0, ddof=1) / np.sqrt(k))
    assert t.max() > z, t


def translation(params, key, direction):
    n = dr.width(params[key]) // 3
    return dr.ravel(mi.Point3f(*(mi.Float(c) + dr.zeros(mi.Float, n) for c in direction)))


@pytest.mark.parametrize('technique', ['bdpt', 'pt'])
def test_cornell_light_translation_agrees_with_finite_differences(technique):
    """Cornell box (empty_cornell_box): the light moved within its plane (x and z), forward
    derivative against central finite differences per 8x8 block and for the image mean."""
    scene = empty_cornell_box()
    params = mi.traverse(scene)
    key = 'light.vertex_positions'
    delta = translation(params, key, (1.0, 0.0, 0.6))
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': technique})
    ad = forward_batches(scene, key, delta, integ, 32, 12)
    fd = fd_batches(scene, key, delta, 0.02, integ, 32, 12)
    assert np.all(np.isfinite(ad))
    assert_nonzero(fd)
    assert_agree(ad, fd, f'cornell light {technique}')


# ---------------------------------------------------------------------------- vertex translation: delta BSDFs
def flat_floor(bsdf):
    T = mi.ScalarTransform4f
    return {'type': 'cube', 'to_world': T().translate([0, -0.1, 0]).scale([100, 0.1, 100]), 'bsdf': bsdf}


def mirror_ceiling_scene():
    """A floor seen in a mirror: a diffuse floor (y = 0) under a ceiling plane (y = 5) that holds
    a large mirror and, beside it, a small area light facing down; the camera, 1 above the
    floor, looks up into the mirror and sees nothing else. The floor and the ceiling plane are
    two parallel planes with nothing between them: no point of one hides another, so moving
    the floor up moves no visibility boundary. Every path runs floor -> mirror -> floor ...:
    the floor is the neighbour of the mirror's delta vertex on both sides."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 40,
                   'to_world': T().look_at(origin=[0, 1, 0], target=[0, 5, -3], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'floor': flat_floor({'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.6}}),
        'mirror': {'type': 'rectangle', 'to_world': T().translate([0, 5, -3.5]).rotate([1, 0, 0], 90).scale([6, 7, 1]),
                   'bsdf': {'type': 'conductor', 'material': 'none'}},
        'light': {'type': 'rectangle', 'to_world': T().translate([7.5, 5, -3]).rotate([1, 0, 0], 90).scale(1.0),
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.0}},
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': 30.0}}},
    })


def glass_sphere_over_textured_floor():
    """A caustic: a small spherical light above a floating glass sphere that focuses it on a
    floor textured with a smooth pattern (a bilinear bitmap, repeated: continuous, so sliding it
    moves no edge). Moving the floor within its own plane moves no visibility boundary (the
    floor is unbounded and nothing changes but where its texture lies); the image changes where
    the camera sees the texture, directly and through the glass (refracted twice: the floor
    vertex follows a delta vertex)."""
    T = mi.ScalarTransform4f
    rng = np.random.default_rng(7)
    tex = mi.Bitmap(rng.uniform(0.2, 0.9, (6, 6, 3)).astype(np.float32))
    return mi.load_dict({
        'type': 'scene',
        'sensor': {'type': 'perspective', 'fov': 40,
                   'to_world': T().look_at(origin=[0, 2.2, 2.6], target=[0, 0.3, 0], up=[0, 1, 0]),
                   'film': {'type': 'hdrfilm', 'width': RES, 'height': RES, 'rfilter': {'type': 'box'}},
                   'sampler': {'type': 'independent'}},
        'floor': flat_floor({'type': 'diffuse', 'reflectance': {
            'type': 'bitmap', 'bitmap': tex, 'filter_type': 'bilinear', 'wrap_mode': 'repeat',
            'to_uv': mi.ScalarTransform4f().scale([60, 60, 1])}}),
        'glass': {'type': 'sphere', 'center': [0, 0.6, 0], 'radius': 0.4,
                  'bsdf': {'type': 'dielectric', 'int_ior': 1.5}},
        'light': {'type': 'sphere', 'center': [0.8, 2.5, -0.6], 'radius': 0.25,
                  'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.0}},   # no floor vertex after it
                  'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': 40.0}}},
    })


DELTA_CASES = {
    # name: (scene builder, key, direction, h, max_depth)
    'mirror_floor_up': (mirror_ceiling_scene, 'floor.vertex_positions', (0.0, 1.0, 0.0), 0.02, 5),
    'caustic_floor_slides': (glass_sphere_over_textured_floor, 'floor.vertex_positions', (1.0, 0.0, 0.3), 0.01, 6),
}


@pytest.mark.parametrize('technique', ['pt', 'bdpt'])
@pytest.mark.parametrize('case', list(DELTA_CASES))
def test_vertex_translation_next_to_delta_vertices_agrees_with_finite_differences(case, technique):
    """Geometry in scenes with delta BSDFs (gradients.slide): the vertex after a mirror or glass
    vertex is the intersection of the delta direction, which turns when the vertex before it
    moves. A floor seen in a mirror moved up (it is the delta vertex's neighbour on both sides),
    and a textured floor under a glass sphere slid within its plane (seen through the glass).
    With bdpt the strategies whose light subpath crosses a delta vertex are left out
    (mis.MIS.camera_chains): every chain is crossed from the camera side."""
    build, key, direction, h, max_depth = DELTA_CASES[case]
    scene = build()
    params = mi.traverse(scene)
    delta = translation(params, key, direction)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': max_depth, 'technique': technique})
    ad = forward_batches(scene, key, delta, integ, 32, 12)
    fd = fd_batches(scene, key, delta, h, integ, 32, 12)
    assert np.all(np.isfinite(ad))
    assert_nonzero(fd)
    assert_agree(ad, fd, case)


@pytest.mark.parametrize('case', ['mirror_floor_up', 'cornell_light'])
def test_geometry_forward_and_reverse_agree(case):
    """The same render (same seeds) differentiated both ways: the forward derivative along a
    translation, summed over the image, equals the reverse-mode gradient of the image's sum
    dotted with that translation (a floor next to a mirror with pt; a light with bdpt)."""
    if case == 'cornell_light':
        scene, key, direction, technique = empty_cornell_box(), 'light.vertex_positions', (1.0, 0.0, 0.6), 'bdpt'
    else:
        build, key, direction, _, _ = DELTA_CASES[case]
        scene, technique = build(), 'pt'
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'technique': technique})
    params = mi.traverse(scene)
    delta = translation(params, key, direction)
    fwd = forward_batches(scene, key, delta, integ, 8, 1, seed0=11).sum()
    v = attach(params, key)
    img = mi.render(scene, params, integrator=integ, spp=8, seed=11, seed_grad=11 + 5000)
    dr.backward(dr.sum(img[:, :, :3], axis=None))
    rev = float(dr.sum(dr.grad(v) * delta, axis=None)[0])
    assert np.isfinite(rev) and abs(fwd) > 0
    assert abs(rev - fwd) <= 1e-3 * abs(fwd), (fwd, rev)


@pytest.mark.parametrize('camera_side', [True, False], ids=['camera', 'light'])
def test_edge_ratio_against_the_edge_factors_log_derivative(camera_side):
    """gradients.ADSampling.edge_ratio: 1 in value, its derivative that of log(f G) of the edge
    from a vertex on a diffuse floor (normal +y) to a point on a tilted plane (normal
    (0.5, -1, 0.3)) moved along m = (0.2, 0.7, -0.6): f = R/pi |cos at the floor|,
    G = |cos at the moved point| / d^2. Against central differences of the analytic log(f G)
    (relative 1e-4). Every finite-difference geometry test of the renders moves a surface
    parallel to the one it faces, where the two cosines change alike; here a cosine taken at
    the wrong end of the edge is 5-40% off."""
    from bdpt_jit.gradients import ADSampling
    from bdpt_jit.vertex import Vertex

    class Ctx:                      # what edge_ratio reads of a Context, for a scene without delta lobes
        exact_adjoint = False
        has_delta = False
        ad = True

    xs = np.array([-0.5, 0.0, 0.3, 1.0])
    n_next = np.array([0.5, -1.0, 0.3]) / np.linalg.norm([0.5, -1.0, 0.3])
    q0, m = np.array([0.4, 1.5, -0.2]), np.array([0.2, 0.7, -0.6])
    bsdf = mi.load_dict({'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': 0.5}})
    si = dr.zeros(mi.SurfaceInteraction3f, len(xs))
    si.p = mi.Point3f(mi.Float(xs), 0.0, 0.0)
    si.n = mi.Normal3f(0, 1, 0)
    si.sh_frame = mi.Frame3f(si.n)
    si.wi = si.sh_frame.to_local(dr.normalize(mi.Vector3f(-0.3, 1.0, 0.4)))
    si.t = 1.0
    t = dr.zeros(mi.Float, len(xs))
    dr.enable_grad(t)
    nx = dr.zeros(mi.SurfaceInteraction3f, len(xs))
    nx.p = mi.Point3f(*[float(c) for c in q0]) + mi.Vector3f(*[float(c) for c in m]) * t
    nx.n = mi.Normal3f(*[float(c) for c in n_next])
    nx.sh_frame = mi.Frame3f(nx.n)
    nx.t = 1.0
    ctx = Ctx()                     # (ADSampling holds its Context by a weak reference)
    r = ADSampling(ctx).edge_ratio(camera_side, Vertex(si, mi.BSDFPtr(bsdf), mi.Float(0.0)), nx,
                                     mi.Vector3f(0, 1, 0), None, None, mi.Bool(True))
    dr.forward_from(t)
    got = np.array(dr.grad(r))[0]
    assert np.allclose(np.array(r)[0], 1.0)

    def log_fg(x, dt):
        d = q0 + m * dt - np.array([x, 0.0, 0.0])
        d2 = d @ d
        w = d / np.sqrt(d2)
        return np.log(0.5 / np.pi * abs(w[1]) * abs(n_next @ w) / d2)
    h = 1e-4
    want = np.array([(log_fg(x, h) - log_fg(x, -h)) / (2 * h) for x in xs])
    assert np.allclose(got, want, rtol=1e-4, atol=1e-5), (got, want)
