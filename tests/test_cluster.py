"""Cluster rendering (bdpt_jit/cluster.py) on a local Ray instance bound to 127.0.0.1 with two
CPU slots: the chunked image equals the same passes in one process and mi.render with the same
pass plan; the scene's files travel; a killed worker's chunk is rerun and counted once; bad
input is one line; a stop keeps exactly the finished chunks."""

import os
import signal
import subprocess
import sys
import threading
import time

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

# Ray reads these when it is first imported: its node then binds the loopback address, and it
# sends no usage statistics (nothing leaves 127.0.0.1)
os.environ.setdefault('RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER', '0')
os.environ.setdefault('RAY_USAGE_STATS_ENABLED', '0')
ray = pytest.importorskip('ray')
pytestmark = pytest.mark.xdist_group('ray')      # one local Ray instance: every test on one xdist worker

from bdpt_jit import cli, cluster  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORNELL = os.path.join(REPO, 'scenes', 'cornell-box.xml')
RES = 16
SPP, CHUNK_SPP = 8, 2                   # 4 chunks of one pass each
PIXELS = RES * RES

TEXTURED = """<scene version="3.0.0">
    <default name="res" value="16"/>
    <integrator type="bdpt"/>
    <sensor type="perspective">
        <float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/><integer name="height" value="$res"/>
            <rfilter type="box"/><string name="pixel_format" value="rgb"/>
        </film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2"/></transform>
        <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
            <string name="filename" value="sub/TEXNAME"/><string name="filter_type" value="nearest"/>
        </texture></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="0" y="0" z="1"/><float name="radius" value="0.6"/>
        <bsdf type="dielectric"/>
    </shape>
    <emitter type="point"><point name="position" x="0.3" y="0.4" z="3"/><rgb name="intensity" value="8"/></emitter>
</scene>
"""


@pytest.fixture(scope='module')
def ray_cluster():
    ray.init(address='local', num_cpus=2, include_dashboard=False, _node_ip_address='127.0.0.1',
             log_to_driver=False, logging_level='ERROR', object_store_memory=256 << 20)
    try:
        assert [n['NodeManagerAddress'] for n in ray.nodes()] == ['127.0.0.1']
        yield ray
    finally:
        ray.shutdown()


def textured_scene(folder, texture='tex.png', write_texture=True):
    """A scene in ``folder`` whose diffuse plane takes its reflectance from sub/<texture>."""
    os.makedirs(os.path.join(folder, 'sub'), exist_ok=True)
    if write_texture:
        rng = np.random.default_rng(1)
        tex = rng.uniform(0.1, 0.9, size=(4, 4, 3)).astype(np.float32)
        mi.Bitmap(tex).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True).write(
            os.path.join(folder, 'sub', texture))
    path = os.path.join(folder, 'scene.xml')
    with open(path, 'w') as f:
        f.write(TEXTURED.replace('TEXNAME', texture))
    return path


def plan(scene_file, props, hook=None, chunk_spp=CHUNK_SPP, spp=SPP, seed=3):
    """(driver scene, job, chunks, options) for a render of ``spp`` in chunks of chunk_spp."""
    options = cluster.Options(address='auto', chunk_spp=chunk_spp, hook=hook)
    defines = {'res': str(RES)}
    scene = cluster.driver_scene(scene_file, defines, props['type'])
    integ = mi.load_dict(props)
    job, chunks = cluster.make_job(scene, scene_file, integ, spp, seed, defines, options, props)
    return scene, job, chunks, options


def assert_same(a, b, rel=1e-6):
    """Equal to float32 rounding: relative difference where the pixel is above 1e-3."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape
    big = np.abs(b) > 1e-3
    assert big.mean() > 0.3
    assert (np.abs(a - b)[big] / np.abs(b[big])).max() <= rel
    assert np.abs(a - b)[~big].max(initial=0) <= rel * 1e-3


CASES = {
    'cornell-bdpt': (CORNELL, {'type': 'bdpt', 'max_depth': 8, 'statistics': True, 'strategy_images': True,
                               'aovs': 'dd:depth'}),
    'cornell-vcm': (CORNELL, {'type': 'bdpt', 'max_depth': 8, 'technique': 'vcm', 'merge_everywhere': True,
                              'radius': 0.05, 'statistics': True}),
    'textured-bdpt': (None, {'type': 'bdpt', 'max_depth': 6}),
    'textured-vcm': (None, {'type': 'bdpt', 'max_depth': 6, 'technique': 'vcm', 'radius': 0.05}),
}


@pytest.mark.parametrize('case', list(CASES))
def test_same_image_as_one_process(ray_cluster, tmp_path, case):
    scene_file, props = CASES[case]
    scene_file = scene_file or textured_scene(str(tmp_path))
    scene, job, chunks, options = plan(scene_file, dict(props))
    assert len(chunks) == 4 and [c.end_pass - c.first_pass for c in chunks] == [1] * 4
    out = cluster.execute(ray_cluster, scene, job, chunks, options)
    assert out.samples == SPP * PIXELS and out.spp == SPP and not out.interrupted and out.retried == []
    # the files travelled: every chunk loaded the scene from its unpacked copy, not from tmp_path
    assert all(r['scene_path'] != job.scene_file and r['scene_path'].endswith('scene.xml' if 'textured' in case
               else 'cornell-box.xml') for r in out.chunks.values())
    assert {r['node'] for r in out.chunks.values()} == {'127.0.0.1'}

    local = cluster.render_chunks_locally(job, chunks, scene)
    assert_same(out.image, local.image)
    # mi.render with the same pass plan (the cluster's samples_per_pass: one chunk per pass)
    integ = mi.load_dict(dict(props, samples_per_pass=CHUNK_SPP * PIXELS))
    ref_scene = mi.load_file(scene_file, res=str(RES))
    ref = np.array(mi.render(ref_scene, integrator=integ, spp=SPP, seed=3))
    assert_same(out.image[:, :, :3], ref[:, :, :3])
    info = integ.last_render_info
    if 'vcm' in case:
        assert info['merge_iteration'] == SPP and 'merges' in ' '.join(info['strategies'])
    if props.get('aovs'):                          # the AOV after the colour (mi.render: alpha between)
        assert out.image.shape[2] == 4
        assert_same(out.image[:, :, 3], ref[:, :, -1])
    if props.get('statistics'):
        assert out.rays == info['rays']             # integer counts: exactly the same
    if props.get('strategy_images'):
        assert set(out.layers) == set(integ.strategy_images)
        for name, kinds in integ.strategy_images.items():
            for kind in ('weighted', 'unweighted'):
                np.testing.assert_allclose(out.layers[name][kind], kinds[kind], rtol=1e-5, atol=1e-7)


def test_merge_iterations_matter(ray_cluster):
    """The vcm case would fail with every chunk starting at merge iteration 0 (its radii)."""
    scene, job, chunks, _ = plan(CORNELL, dict(CASES['cornell-vcm'][1]))
    right = cluster.render_chunks_locally(job, chunks, scene).image
    for c in chunks:
        c.merge_iteration = 0
    wrong = cluster.render_chunks_locally(job, chunks, scene).image
    big = right > 1e-3
    assert (np.abs(wrong - right)[big] / right[big]).max() > 1e-4


def test_seeded_renders_equal_the_same_calls_here(ray_cluster):
    """compare.py --cluster's reference batches: one mi.render per seed on a worker."""
    props = {'type': 'path', 'max_depth': 8}
    images = cluster.render_seeded(CORNELL, {'res': '8', 'integrator': 'path'}, props, 4, [11, 12],
                                   cluster.Options(address='auto'))
    scene = mi.load_file(CORNELL, res='8', integrator='path')
    for img, seed in zip(images, (11, 12)):
        ref = np.array(mi.render(scene, integrator=mi.load_dict(props), spp=4, seed=seed))
        assert_same(img, ref)
    assert np.abs(images[0] - images[1]).max() > 1e-3       # the seeds differ


def _kill_second_chunk_hook(flag):
    def hook(index, attempt):
        # the first attempt of chunk 1 tells its pid and waits to be killed
        if index == 1 and attempt == 0:
            with open(flag + '.tmp', 'w') as f:
                f.write(str(os.getpid()))
            os.replace(flag + '.tmp', flag)
            time.sleep(120)
    return hook


def test_killed_worker_is_rerun_once(ray_cluster, tmp_path):
    flag = str(tmp_path / 'pid')
    props = dict(CASES['cornell-bdpt'][1])
    scene, job, chunks, options = plan(CORNELL, props, hook=_kill_second_chunk_hook(flag))
    killed = []

    def killer():
        for _ in range(600):
            if os.path.exists(flag):
                pid = int(open(flag).read())
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            time.sleep(0.1)

    t = threading.Thread(target=killer)
    t.start()
    out = cluster.execute(ray_cluster, scene, job, chunks, options)
    t.join()
    assert killed and out.chunks[1]['pid'] != killed[0]
    assert out.retried == [1] and out.chunks[1]['attempt'] == 1
    assert sorted(out.chunks) == [0, 1, 2, 3] and out.samples == SPP * PIXELS    # counted once
    job.hook = None
    assert_same(out.image, cluster.render_chunks_locally(job, chunks, scene).image)
    _, lines = cluster.cli_statistics(out, options, (0, 2))
    assert 'chunk 1 retried (worker died)' in lines[0]


def test_missing_texture_on_the_driver_is_one_line(ray_cluster, tmp_path):
    scene_file = textured_scene(str(tmp_path), texture='missing.png', write_texture=False)
    out = tmp_path / 'out.exr'
    code, err = _main_stderr(['render', scene_file, '--cluster', 'auto', '--spp', '2', '-o', str(out), '-q'])
    assert code == 1
    assert len(err.strip().splitlines()) == 1 and 'missing.png' in err and 'Traceback' not in err
    assert sorted(os.listdir(tmp_path)) == ['scene.xml', 'sub']


def test_missing_texture_on_a_worker_names_scene_and_file(ray_cluster, tmp_path):
    """The texture is there when the driver plans, gone from what travels to the workers."""
    scene_file = textured_scene(str(tmp_path), texture='tex.png')
    scene, job, chunks, options = plan(scene_file, {'type': 'bdpt', 'max_depth': 4})
    os.unlink(os.path.join(str(tmp_path), 'sub', 'tex.png'))
    with pytest.raises(cluster.ClusterError) as e:
        cluster.execute(ray_cluster, scene, job, chunks, options)
    msg = str(e.value)
    assert '\n' not in msg and msg.startswith(scene_file) and 'tex.png' in msg


def test_worker_without_the_plugin_is_reported(ray_cluster, tmp_path):
    fake = tmp_path / 'fake' / 'mitsuba'
    fake.mkdir(parents=True)
    (fake / '__init__.py').write_text('raise ImportError("no Mitsuba on this node (test stand-in)")\n')
    scene, job, chunks, options = plan(CORNELL, {'type': 'bdpt', 'max_depth': 4})
    options.runtime_env = {'env_vars': {'PYTHONPATH': str(tmp_path / 'fake')}}
    with pytest.raises(cluster.ClusterError) as e:
        cluster.execute(ray_cluster, scene, job, chunks, options)
    msg = str(e.value)
    assert '\n' not in msg and 'cannot import the bdpt_jit plugin' in msg and 'no Mitsuba on this node' in msg


def _block_after_two_hook():
    def hook(index, attempt):
        if index >= 2:                  # chunks 2 and 3 never finish on their own
            time.sleep(120)
    return hook


def test_stop_keeps_exactly_the_finished_chunks(ray_cluster):
    props = dict(CASES['cornell-bdpt'][1])
    scene, job, chunks, options = plan(CORNELL, props, hook=_block_after_two_hook())
    seen = []

    def stop():
        return time.perf_counter() if seen and len(seen[-1].done) >= 2 else None

    t0 = time.perf_counter()
    out = cluster.execute(ray_cluster, scene, job, chunks, options, stop, lambda total: seen.append(total))
    assert time.perf_counter() - t0 < 60                    # the blocked chunks were cancelled
    assert out.interrupted and sorted(out.chunks) == [0, 1] and out.spp == 4
    job.hook = None
    assert_same(out.image, cluster.render_chunks_locally(job, chunks[:2], scene).image)
    # with a box filter: the average of the two chunks' own images (each a render of 2 spp)
    one = [cluster.render_chunks_locally(job, [c], scene) for c in chunks[:2]]
    assert all(o.spp == 2 for o in one)
    assert_same(out.image, (one[0].image + one[1].image) / 2, rel=2e-6)
    for name, kinds in out.layers.items():
        for kind, a in kinds.items():
            np.testing.assert_allclose(a, (one[0].layers[name][kind] + one[1].layers[name][kind]) / 2,
                                       rtol=2e-6, atol=1e-7)


def _main_stderr(argv):
    """bdpt-jit in this process (it joins the module's Ray instance): (status, stderr)."""
    import contextlib
    import io
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, err.getvalue()


def test_command_writes_the_cluster_image(ray_cluster, tmp_path):
    scene_file = textured_scene(str(tmp_path))
    out = tmp_path / 'out.exr'
    code, err = _main_stderr(['render', scene_file, '--cluster', 'auto', '--spp', str(SPP), '--chunk-spp',
                              str(CHUNK_SPP), '--seed', '3', '--max-depth', '6', '-D', f'res={RES}', '-o', str(out), '-q'])
    assert code == 0, err
    f = OpenEXR.File(str(out), separate_channels=True)
    ch = {k: c.pixels for k, c in f.channels().items()}
    img = np.stack([ch[c] for c in 'RGB'], -1)
    h = f.header()
    assert h['bdpt.spp'] == str(SPP) and h['bdpt.cluster.chunks'] == '4' and h['bdpt.passes'] == '4'
    assert h['bdpt.cluster.retried'] == '' and h['bdpt.param.samples_per_pass'] == str(CHUNK_SPP * PIXELS)
    assert int(h['bdpt.samples']) == SPP * PIXELS and int(h['bdpt.rays.rays']) > 0
    scene, job, chunks, _ = plan(scene_file, {'type': 'bdpt', 'max_depth': 6, 'statistics': True})
    assert_same(img, cluster.render_chunks_locally(job, chunks, scene).image)


def test_command_time_budget_keeps_whole_chunks(ray_cluster, tmp_path):
    out = tmp_path / 'timed.exr'
    budget = 1.5
    code, err = _main_stderr(['render', CORNELL, '--cluster', 'auto', '--time', str(budget), '--pass-spp', '1',
                              '-D', f'res={RES}', '-o', str(out), '-q'])
    assert code == 0, err
    f = OpenEXR.File(str(out), separate_channels=True)
    h = f.header()
    chunks = int(h['bdpt.cluster.chunks'])
    assert chunks >= 1 and h['bdpt.spp'] == str(chunks) and h['bdpt.interrupted'] == 'false'   # 1 spp each
    assert int(h['bdpt.samples']) == chunks * PIXELS and h['bdpt.cluster.chunks_planned'] == 'endless (--time)'
    # the budget is checked between chunks: one chunk (its compilation too, with an empty kernel
    # cache: 3.7 s against a 1.5 s budget once on a fresh clone) may run past it
    assert float(h['bdpt.render_time_s']) <= budget + float(h['bdpt.longest_pass_s']) + 1.0
    img = np.stack([f.channels()[c].pixels for c in 'RGB'], -1)
    assert np.isfinite(img).all() and img.mean() > 0


def test_without_ray_the_command_says_how_to_install_it(tmp_path):
    fake = tmp_path / 'fake' / 'ray'
    fake.mkdir(parents=True)
    (fake / '__init__.py').write_text('raise ImportError("No module named ray")\n')
    env = dict(os.environ, PYTHONPATH=str(tmp_path / 'fake'))
    r = subprocess.run([sys.executable, '-m', 'bdpt_jit.cli', 'render', CORNELL, '-D', 'res=8', '--spp', '1',
                        '--cluster', 'local', '-o', str(tmp_path / 'o.exr')],
                       capture_output=True, text=True, timeout=120, cwd=REPO, env=env)
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        "bdpt-jit: error: --cluster needs Ray, which is not installed here: pip install -e '.[cluster]'"]
    assert not (tmp_path / 'o.exr').exists()
