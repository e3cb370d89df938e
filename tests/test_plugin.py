"""The plugin contract: registration, parameters and their errors, refused scenes."""

import os
import subprocess
import sys

import mitsuba as mi
import pytest

import bdpt_jit
from bdpt_jit.params import PARAMS, ParameterError
from helpers import scene_path


def error_chain(exc):
    """Messages of an exception and its causes: ``mi.render`` runs the integrator inside a
    Dr.Jit custom operation, which re-raises with the integrator's error as the cause."""
    out = []
    while exc is not None:
        out.append(f'{type(exc).__name__}: {exc}')
        exc = exc.__cause__ or exc.__context__
    return '\n'.join(out)


def test_registered_for_xml_and_dict():
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'mis': 'balance', 'technique': 'pt',
                          'rr_depth': 3, 'hide_emitters': True, 'samples_per_pass': 1000})
    assert integ.settings == {'max_depth': 4, 'mis': 'balance', 'technique': 'pt', 'rr_depth': 3,
                              'hide_emitters': True, 'samples_per_pass': 1000,
                              'strategy_images': False, 'statistics': False, 'aovs': '',
                              'radius': 0.005, 'radius_alpha': 0.75, 'merge_everywhere': False, 'media_merging': 'beams',
                              'beam_paths': None,
                              'light_paths': -1.0, 'connections': -1}
    scene = mi.load_file(scene_path('cornell-box.xml'), res=8)
    assert isinstance(scene.integrator(), bdpt_jit.BDPTIntegrator)
    xml = mi.load_string('<scene version="3.0.0"><integrator type="bdpt"><string name="mis" value="uniform"/>'
                         '<integer name="max_depth" value="3"/></integrator></scene>')
    assert xml.integrator().settings['mis'] == 'uniform' and xml.integrator().settings['max_depth'] == 3


def test_defaults_come_from_the_table():
    integ = mi.load_dict({'type': 'bdpt'})
    assert integ.settings == {p.name: p.default for p in PARAMS}
    doc = bdpt_jit.BDPTIntegrator.__doc__
    for p in PARAMS:
        assert f'`{p.name}`' in doc


@pytest.mark.parametrize('params,needle', [
    ({'mis': 'powr'}, "'mis' must be one of power, balance, uniform"),
    ({'technique': 'sppm'}, "'technique' must be one of bdpt, pt, lt, vcm, vm"),
    ({'max_depth': -2}, "'max_depth' must be >= -1"),
    ({'rr_depth': 0}, "'rr_depth' must be >= 1"),
    ({'samples_per_pass': 0}, "'samples_per_pass' must be >= 1"),
    ({'maxdepth': 3}, "unknown parameter 'maxdepth'"),
    ({'hide_emitters': 'maybe'}, 'hide_emitters'),
])
def test_bad_parameters_name_the_parameter(params, needle):
    with pytest.raises(Exception) as e:
        mi.load_dict({'type': 'bdpt', **params})
    assert needle in str(e.value)


@pytest.mark.parametrize('emitter,name', [
    ({'type': 'timed_sunsky'}, 'timed_sunsky'),
])
def test_unsupported_emitters_are_refused_by_name(emitter, name):
    d = mi.cornell_box()
    d['sensor']['film'].update(width=8, height=8)
    d['extra'] = emitter
    scene = mi.load_dict(d)
    with pytest.raises(Exception) as e:
        mi.render(scene, integrator=mi.load_dict({'type': 'bdpt'}), spp=1)
    msgs = error_chain(e.value)
    assert f"UnsupportedSceneError: bdpt: emitter plugin '{name}' is not supported" in msgs


def test_unsupported_sensor_is_refused():
    d = mi.cornell_box()
    sensor = d.pop('sensor')
    sensor['film'].update(width=8, height=8)
    d['sensor'] = {'type': 'batch', 'a': sensor, 'b': dict(sensor), 'film': {'type': 'hdrfilm', 'width': 16, 'height': 8}}
    with pytest.raises(Exception) as e:
        mi.render(mi.load_dict(d), integrator=mi.load_dict({'type': 'bdpt'}), spp=1)
    assert "sensor plugin 'batch' is not supported" in error_chain(e.value)


def test_other_variants_are_refused():
    mi.set_variant('scalar_rgb')
    try:
        with pytest.raises(bdpt_jit.UnsupportedSceneError, match="variant 'scalar_rgb' is not supported"):
            bdpt_jit.BDPTIntegrator()
    finally:
        mi.set_variant('llvm_ad_rgb')


def test_a_scalar_variant_names_itself_when_a_scene_asks_for_bdpt():
    """In a scalar variant (set before ``import bdpt_jit``, or switched to and registered) a
    scene with ``bdpt`` is refused with the reason, not with Mitsuba's "plugin not found" (the
    kernel modules cannot be imported there)."""
    import subprocess
    import sys
    code = ("import mitsuba as mi; mi.set_variant('scalar_rgb'); import bdpt_jit\n"
            "try:\n    mi.load_dict({'type': 'bdpt'})\nexcept Exception as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120).stdout
    assert "variant 'scalar_rgb' is not supported; use one of llvm_ad_rgb" in out, out
    assert 'not found' not in out, out


def test_readme_parameter_table_is_the_source_table():
    """The README shows the parameter table that params.py defines (one source of truth)."""
    import os
    from bdpt_jit.params import markdown_table
    readme = open(os.path.join(os.path.dirname(os.path.dirname(__file__)), 'README.md')).read()
    assert markdown_table() in readme


def test_seed_as_uint32_renders_the_int_seed():
    """Mitsuba's render API takes an int or a ``mi.UInt32`` seed, and its own wrappers (the
    ``aov`` integrator, ``mi.render`` with parameters) pass the latter: the same pixels, up to
    float32 rounding (light tracing's splats are atomic adds, summed in an order that varies
    between runs: a fresh-clone run differed in the last digit), while another seed moves
    pixels by far more."""
    import numpy as np
    scene = mi.load_file(scene_path('cornell-box.xml'), res=8)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4})
    a = np.array(mi.render(scene, integrator=integ, spp=2, seed=1))
    b = np.array(mi.render(scene, integrator=integ, spp=2, seed=mi.UInt32(1)))
    c = np.array(mi.render(scene, integrator=integ, spp=2, seed=2))
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert np.max(np.abs(a - c)) > 1e-3 * np.max(a)


def test_pass_seeds_of_a_uint32_seed_are_the_int_seed_s():
    """passes.pass_seed takes a UInt32 seed as Mitsuba's wrappers pass it, for every pass index
    bdpt uses: technique auto's pilot and lattice passes (light_cache.PILOT_PASS,
    integrator.LATTICE_PASS) have indices past 2^24, whose term overflowed 32 bits and made a
    UInt32-seeded auto render fail."""
    from bdpt_jit.integrator import LATTICE_PASS
    from bdpt_jit.light_cache import PILOT_PASS
    from bdpt_jit.passes import pass_seed, pass_seed_value
    for seed in (0, 1, 12345, 2**32 - 1):
        for i in (0, 7, PILOT_PASS, PILOT_PASS + 9, LATTICE_PASS + 3):
            assert int(pass_seed(mi.UInt32(seed), i)[0]) == pass_seed_value(seed, i), (seed, i)


def test_render_without_develop_is_refused_with_a_reason():
    scene = mi.load_file(scene_path('cornell-box.xml'), res=8)
    integ = mi.load_dict({'type': 'bdpt'})
    with pytest.raises(NotImplementedError, match='develop=False'):
        integ.render(scene, spp=1, develop=False)


def test_every_pass_launches_the_same_kernels():
    """A render of several passes compiles its kernels once: the first pass launches the same
    kernels (by hash) as the later ones (tables left lazy made the first pass's differ)."""
    import drjit as dr
    from bdpt_jit.passes import RenderHooks
    scene = mi.load_file(scene_path('cornell-box.xml'), res=16)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'samples_per_pass': 16 * 16 * 2})
    n = 16 * 16 * 2
    seen = []

    def on_pass(done, total):
        seen.append(sorted(k['hash'] for k in dr.kernel_history()
                           if k.get('type') == dr.KernelType.JIT and k.get('size') == n))
    integ.hooks = RenderHooks(on_pass=on_pass)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        mi.render(scene, integrator=integ, spp=6, seed=0)
    assert len(seen) == 3 and seen[0], seen
    assert seen[0] == seen[1] == seen[2], seen


SAME_KERNELS = [('cornell-box', {'technique': 'bdpt'}),
                ('cornell-box', {'technique': 'vcm', 'merge_everywhere': True, 'radius': 0.01}),
                ('cornell-box', {'technique': 'bdpt', 'light_paths': 0.5}),
                ('fog-area', {'technique': 'bdpt'}),
                ('fog-area', {'technique': 'vm', 'radius': 0.05})]


@pytest.mark.parametrize('name,extra', SAME_KERNELS)
def test_sample_counts_share_kernels(name, extra):
    """Renders at 2 and 5 samples per pixel (one pass each) launch the same kernels by hash: no
    sample count (nor a size made from it) is baked into the code as a literal, so that a
    progressive render, a time budget or a cluster chunk compiles its kernels once (media.mean
    used dr.mean, which divides by the wavefront's whole size: every scene with a medium
    compiled again for every spp)."""
    import drjit as dr
    from test_media_render import SCENES
    scene = mi.load_file(scene_path('cornell-box.xml'), res=8) if name == 'cornell-box' else mi.load_dict(SCENES[name]())
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, **extra})
    mi.render(scene, integrator=integ, spp=1)          # (tables built on the first render)
    hashes = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for spp in (2, 5):
            dr.kernel_history()
            mi.render(scene, integrator=integ, spp=spp, seed=spp)
            hashes.append({k['hash'] for k in dr.kernel_history() if k.get('type') == dr.KernelType.JIT})
    assert hashes[0] and hashes[0] == hashes[1], f'{sorted(hashes[1] - hashes[0])} new at 5 spp'


AOVS = 'dd:depth,pp:position,uv:uv,gn:geo_normal,nn:sh_normal,ab:albedo'


def test_aovs_are_mitsubas_and_leave_the_image_unchanged():
    """bdpt's own AOV channels (parameter aovs, named and ordered as Mitsuba's aov integrator
    names them) agree with Mitsuba's aov integrator pixel by pixel, and the colour channels
    are those of the same render without AOVs."""
    import numpy as np
    d = mi.cornell_box()
    d['sensor']['film'].update(width=16, height=16, rfilter={'type': 'box'})
    scene = mi.load_dict(d)
    mine_integ = mi.load_dict({'type': 'bdpt', 'max_depth': 4, 'aovs': AOVS})
    assert mine_integ.aov_names() == mi.load_dict({'type': 'aov', 'aovs': AOVS}).aov_names()
    mine = np.array(mi.render(scene, integrator=mine_integ, spp=256, seed=3))
    plain = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'max_depth': 4}), spp=256, seed=3))
    ref = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'aov', 'aovs': AOVS}), spp=256, seed=5))
    n = len(mine_integ.aov_names())                              # 15 channels
    assert mine.shape == (16, 16, 3 + n) and ref.shape[2] >= n
    np.testing.assert_allclose(mine[..., :3], plain[..., :3], rtol=1e-4, atol=1e-6)
    # each AOV: the pixel's average over its footprint; two sample sets differ only in the
    # pixels an edge crosses (measured: 1-3% of a channel's mean value at 256 spp), while the
    # whole image's mean agrees closely (a channel in the wrong place or of the wrong kind
    # would be off by tens of percent)
    a, b = mine[..., 3:], ref[..., -n:]
    scale = np.maximum(np.abs(b).mean(axis=(0, 1)), 0.05)
    names = mine_integ.aov_names()
    per_pixel = np.abs(a - b).mean(axis=(0, 1)) / scale
    whole = np.abs(a.mean(axis=(0, 1)) - b.mean(axis=(0, 1))) / scale
    assert np.all(per_pixel < 0.06), dict(zip(names, per_pixel))
    assert np.all(whole < 0.01), dict(zip(names, whole))


def test_light_tracing_writes_alpha_and_aovs_from_its_camera_rays():
    """Technique lt traces no camera subpath, but a film with alpha or AOVs gets them from one
    first hit a sample, as path's (before: zero everywhere). With the same seed, bdpt's camera
    rays are the same rays: the same channels exactly; lt's colour is lt's without them."""
    import numpy as np
    d = mi.cornell_box()
    d['sensor']['film'].update(width=16, height=16, rfilter={'type': 'box'}, pixel_format='rgba')
    scene = mi.load_dict(d)
    def render(technique, aovs):
        return np.array(mi.render(scene, integrator=mi.load_dict(
            {'type': 'bdpt', 'max_depth': 3, 'technique': technique, 'aovs': aovs}), spp=16, seed=3))
    lt, bd, plain = render('lt', 'dd:depth'), render('bdpt', 'dd:depth'), render('lt', '')
    assert lt.shape == (16, 16, 5) and 0 < lt[..., 3].mean() < 1    # the box's opening: alpha 0
    np.testing.assert_array_equal(lt[..., 3:], bd[..., 3:])
    np.testing.assert_allclose(lt[..., :3], plain[..., :3], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize('value', ['dd', 'dd:depths', ':depth', 'dd:depth,xx'])
def test_bad_aovs_name_the_parameter_and_the_types(value):
    with pytest.raises(Exception) as e:
        mi.load_dict({'type': 'bdpt', 'aovs': value})
    assert "'aovs'" in str(e.value) and 'sh_normal' in str(e.value)


@pytest.mark.parametrize('spp,n_pixels,per_pass', [(16, 64, None), (7, 100, 250), (5, 100, 30), (1, 1, 1), (33, 9, 40)])
def test_pass_count_is_the_plans_length(spp, n_pixels, per_pass):
    """last_render_info['passes'] (passes.count_passes) counts what plan_passes yields, and the
    plan covers spp samples of every pixel exactly."""
    from bdpt_jit.passes import count_passes, plan_passes
    plan = list(plan_passes(spp, n_pixels, 1000, per_pass))
    assert count_passes(spp, n_pixels, 1000, per_pass) == len(plan)
    cover = [0] * n_pixels
    for k, start, count in plan:
        for p in range(start, start + count):
            cover[p] += k
    assert cover == [spp] * n_pixels


ONE_CPU = r'''
import sys
import numpy as np
import bdpt_jit, drjit as dr, mitsuba as mi
print(dr.thread_count(), flush=True)
mi.Bitmap(np.ones((4, 4, 3), np.float32)).write(sys.argv[1])
print(float(np.array(mi.Bitmap(sys.argv[1])).sum()), flush=True)
'''


@pytest.mark.skipif(not hasattr(os, 'sched_setaffinity'), reason='needs Linux CPU affinity')
def test_one_cpu_reads_and_writes_exr_files(tmp_path):
    """On one CPU Dr.Jit's pool has one thread, in which Mitsuba 3.9.1's OpenEXR reader and writer
    wait for good (an envmap, a texture, the CLI's output): ``import bdpt_jit`` gives the pool
    two threads (bdpt_jit.MIN_THREADS)."""
    env = {k: v for k, v in os.environ.items() if k != 'DRJIT_NUM_THREADS'}
    cpu = min(os.sched_getaffinity(0))         # (one this process may run on: CPU 0 may not be)
    try:
        r = subprocess.run([sys.executable, '-c', ONE_CPU, str(tmp_path / 'one.exr')], capture_output=True,
                           text=True, timeout=120, env=env, preexec_fn=lambda: os.sched_setaffinity(0, {cpu}))
    except subprocess.TimeoutExpired:
        pytest.fail('an .exr file written and read on one CPU: no answer in 120 s')
    assert r.returncode == 0, r.stderr[-2000:]
    threads, total = r.stdout.split()
    assert int(threads) >= 2 and float(total) == 48.0
