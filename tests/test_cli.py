"""The ``bdpt-jit render`` command, run as a subprocess on tiny renders: its EXR equals
``mi.render`` with the plugin, --time keeps to its budget, the strategy layers sum to the image,
every error a user meets is one line with a non-zero status and no file left behind, and
Ctrl-C writes what was rendered."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

import bdpt_jit
from bdpt_jit import cli
from bdpt_jit.cli import session
from bdpt_jit.passes import RenderHooks, pass_seed_value

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORNELL = os.path.join(REPO, 'scenes', 'cornell-box.xml')
VARIANT = ['--variant', 'llvm_ad_rgb']          # the comparisons below render with llvm_ad_rgb


def run_cli(*args, env=None, timeout=120):
    e = dict(os.environ)
    e.update(env or {})
    return subprocess.run([sys.executable, '-m', 'bdpt_jit.cli', 'render', *args],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO, env=e)


def read_exr(path):
    f = OpenEXR.File(str(path), separate_channels=True)
    ch = {name: c.pixels for name, c in f.channels().items()}
    img = np.stack([ch['R'], ch['G'], ch['B']], axis=-1)
    return img, ch, f.header()


def layer(ch, name, kind):
    return np.stack([ch[f'{name}.{kind}.{c}'] for c in 'RGB'], axis=-1)


def leftovers(folder):
    """Files in the output folder (temporary ones included)."""
    return sorted(os.listdir(folder))


# ----------------------------------------------------------------------------- outputs
def test_exr_equals_mi_render_and_png(tmp_path):
    out = tmp_path / 'cornell.exr'
    r = run_cli(CORNELL, '-D', 'res=16', '--spp', '4', '--seed', '3', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    assert leftovers(tmp_path) == ['cornell.exr', 'cornell.png']

    img, ch, header = read_exr(out)
    scene = mi.load_file(CORNELL, res='16', spp='4')
    ref = np.array(mi.render(scene, spp=4, seed=3))[:, :, :3]       # the scene's bdpt, max_depth 8
    assert img.shape == (16, 16, 3) and img.dtype == np.float32
    np.testing.assert_allclose(img, ref, rtol=1e-4, atol=1e-6)
    assert img.mean() > 0

    png = mi.Bitmap(str(tmp_path / 'cornell.png'))
    assert (png.width(), png.height()) == (16, 16)
    assert png.component_format() == mi.Struct.Type.UInt8

    # settings and statistics in the header
    assert header['bdpt.integrator'] == 'bdpt'
    assert header['bdpt.spp'] == '4' and header['bdpt.seed'] == '3'
    assert header['bdpt.param.max_depth'] == '8'                   # from the scene's integrator
    for p in bdpt_jit.PARAMS:
        assert f'bdpt.param.{p.name}' in header
    for key in ('scene', 'variant', 'version.mitsuba', 'version.drjit', 'wall_time_s',
                'compile_time_s', 'render_time_s', 'msamples_per_s', 'rays.rays',
                'rays.zero_contribution_rays', 'strategies', 'strategies_left_out',
                'features', 'features_left_out', 'defines'):
        assert 'bdpt.' + key in header, key
    assert header['bdpt.variant'] == 'llvm_ad_rgb' and header['bdpt.interrupted'] == 'false'
    assert int(header['bdpt.rays.rays']) > int(header['bdpt.rays.zero_contribution_rays']) > 0

    # the summary and the progress bar
    for text in ('wall', 'JIT compile', 'M samples/s', 'rays traced', 'zero-contrib',
                 'strategies', 'left out', 'light subpath pass'):
        assert text in r.stdout, text
    assert re.search(r'1 pass\b', r.stderr) and 'spp' in r.stderr


def test_quiet_and_other_integrator(tmp_path):
    out = tmp_path / 'path.exr'
    r = run_cli(CORNELL, '-D', 'res=8', '--spp', '2', '--integrator', 'path', '-q', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    assert r.stdout == '' and r.stderr == ''
    img, _, header = read_exr(out)
    scene = mi.load_file(CORNELL, res='8', spp='2', integrator='path')
    np.testing.assert_allclose(img, np.array(mi.render(scene, spp=2, seed=0))[:, :, :3], rtol=1e-4, atol=1e-6)
    assert header['bdpt.integrator'] == 'path' and header['bdpt.param.max_depth'] == '8'
    assert 'bdpt.rays.rays' not in header


def test_the_scene_s_integrator_settings_carry_over(tmp_path):
    """A scene written for Mitsuba's path with hidden emitters, a max_depth and an rr_depth:
    bdpt (and another Mitsuba integrator) renders with the same three (SHARED_PARAMS); before,
    only max_depth came over and bdpt showed the emitters the scene hid. Options still win."""
    text = open(CORNELL).read().replace('<integer name="max_depth" value="$max_depth"/>',
                                        '<integer name="max_depth" value="$max_depth"/>'
                                        '<boolean name="hide_emitters" value="true"/><integer name="rr_depth" value="3"/>')
    assert 'hide_emitters' in text
    scene_file = tmp_path / 'hidden.xml'
    scene_file.write_text(text)
    cases = [([], 'bdpt', 'true', '3'), (['--no-hide-emitters'], 'bdpt', 'false', '3'),
             (['--integrator', 'volpath'], 'volpath', 'true', '3')]
    for extra, name, hidden, rr in cases:
        out = tmp_path / f'{name}{len(extra)}.exr'
        r = run_cli(str(scene_file), '-D', 'res=8', '-D', 'integrator=path', '--spp', '1', '-q', '-o', str(out),
                    *extra, *VARIANT)
        assert r.returncode == 0, r.stderr
        header = read_exr(out)[2]
        assert header['bdpt.integrator'] == name, header['bdpt.integrator']
        assert str(header['bdpt.param.hide_emitters']).lower() == hidden, (extra, header['bdpt.param.hide_emitters'])
        assert str(header['bdpt.param.rr_depth']) == rr and str(header['bdpt.param.max_depth']) == '8', extra


def test_time_budget(tmp_path):
    out = tmp_path / 'timed.exr'
    budget = 2.5
    r = run_cli(CORNELL, '-D', 'res=16', '--time', str(budget), '--pass-spp', '1', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    img, _, header = read_exr(out)
    passes, spp = int(header['bdpt.passes']), float(header['bdpt.spp'])
    render_s, longest = float(header['bdpt.render_time_s']), float(header['bdpt.longest_pass_s'])
    assert spp == passes >= 1                           # passes of 1 spp each
    assert header['bdpt.time_budget_s'] == '2.5' and header['bdpt.pass_spp'] == '1'
    # stops within one pass of the budget: before the pass that would overrun it
    assert budget - longest - 0.05 <= render_s <= budget + longest + 0.05, (render_s, longest)
    assert f'{spp:g} spp reached' in r.stdout
    assert np.isfinite(img).all() and img.mean() > 0


def test_time_budget_with_technique_auto(tmp_path):
    """--time with technique auto: the choice (pilots and trials) and then passes until the
    budget, each pass waited for before the budget is read (Dr.Jit returns before a pass's
    kernels finish: a loop that did not wait queued every pass of 2^30 spp first); the summary
    names the choice. The decision is no pass (RenderHooks.on_decided): the passes after it
    fill the budget (planted: the clock not told, the render stopped after one pass)."""
    out = tmp_path / 'auto.exr'
    budget = 4.0
    r = run_cli(CORNELL, '-D', 'res=16', '--time', str(budget), '--pass-spp', '1', '--technique', 'auto',
                '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    img, _, header = read_exr(out)
    render_s, longest = float(header['bdpt.render_time_s']), float(header['bdpt.longest_pass_s'])
    decided = float(re.search(r'after ([0-9.]+) s of pilot and trials', header['bdpt.auto']).group(1))
    assert render_s <= max(budget, decided + longest) + longest + 0.1, (render_s, decided, longest)
    assert longest < decided, (longest, decided)      # no pass timed with the decision in it
    if decided + 3 * longest < budget:      # room for passes: they fill it
        assert render_s >= budget - longest - 0.1, (render_s, decided, longest)
    assert header['bdpt.auto'].startswith('chose ') and float(header['bdpt.spp']) >= 1
    assert np.isfinite(img).all()
    assert 'technique auto: pilots and trials' in r.stderr       # the bar says what the wait before a pass is


def test_technique_auto_s_decision_keeps_to_half_the_time_budget(tmp_path):
    """--time with technique auto: a decision still timing candidates at half the budget
    (cli/rendering.DECISION_SHARE; a first decision on a new scene compiles each candidate's
    kernels, 10-20 s) times no more and chooses among those timed, pt and the probe
    (auto.out_of_time); the summary says so. On the caustic, where pt is never clear (its
    predicted v is tens of times the others'), so that a decision always times more than
    those two. Planted, the command's hook not given: every candidate that could win is timed
    (the render then runs past a short budget)."""
    out = tmp_path / 'cut.exr'
    r = run_cli(os.path.join(REPO, 'scenes', 'caustic.xml'), '-D', 'res=16', '--max-depth', '4', '--time', '0.01',
                '--pass-spp', '1', '--technique', 'auto', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    _, _, header = read_exr(out)
    summary = header['bdpt.auto']
    assert '1 cut at half the time budget' in summary, summary
    timed = re.findall(r'([a-z0-9. ]+?) [0-9.e+-]+ x [0-9.e+-]+(?:,|$| \()', summary.split('s/spp: ', 1)[1])
    assert sorted(t.strip() for t in timed) == ['cache 0.25x1', 'pt'], summary


def test_the_kernel_count_holds_technique_auto_s_trials():
    """cli/rendering.KernelCounter (the summary's kernels and compile time) counts every JIT
    kernel launched between its start and stop, those that technique auto's timed trials read
    from Dr.Jit's kernel history included: auto.kernel_seconds drains the history
    (stats.drain_kernel_history), which hands what it reads to the counter. Before, a first
    decision on a new scene compiled for 20 s while the summary said 0.03 s. Planted, the
    trials' reads kept to themselves: the kernel before the trial and the trial's are missed."""
    import drjit as dr
    from bdpt_jit import auto
    from bdpt_jit.cli.rendering import KernelCounter
    counter = KernelCounter()
    counter.start()
    try:
        dr.eval(dr.arange(mi.Float, 1000) * 2.0)        # pending in the history when the trial starts
        seconds = auto.kernel_seconds(lambda: dr.eval(dr.arange(mi.Float, 100) + 1.0))
        dr.eval(dr.arange(mi.Float, 10) - 1.0)
    finally:
        counter.stop()
    assert seconds >= 0.0 and counter.launched == 3, counter.launched


def test_time_passes_average_to_the_image(tmp_path):
    """--time accumulates an spp-weighted average; its first pass is --spp with the same seed."""
    out = tmp_path / 'one.exr'
    r = run_cli(CORNELL, '-D', 'res=8', '--time', '0.001', '--pass-spp', '2', '--seed', '5', '-q', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    img, _, header = read_exr(out)
    assert header['bdpt.passes'] == '1' and header['bdpt.spp'] == '2'     # always at least one pass
    scene = mi.load_file(CORNELL, res='8')
    ref = np.array(mi.render(scene, spp=2, seed=5))[:, :, :3]
    np.testing.assert_allclose(img, ref, rtol=1e-4, atol=1e-6)


def test_time_with_mitsuba_integrator_uses_pass_seeds(tmp_path):
    """--time with Mitsuba's integrators: mi.render calls of --pass-spp, pass i seeded with
    passes.pass_seed_value(seed, i), the seed scheme of bdpt's own passes."""
    out = tmp_path / 'path.exr'
    r = run_cli(CORNELL, '-D', 'res=8', '--time', '0.001', '--pass-spp', '2', '--seed', '5', '--integrator', 'path',
                '-q', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    img, _, header = read_exr(out)
    assert header['bdpt.passes'] == '1' and header['bdpt.spp'] == '2'
    scene = mi.load_file(CORNELL, res='8', integrator='path')
    ref = np.array(mi.render(scene, spp=2, seed=pass_seed_value(5, 0)))[:, :, :3]
    np.testing.assert_allclose(img, ref, rtol=1e-4, atol=1e-6)


def test_strategy_layers_sum_to_image(tmp_path):
    out = tmp_path / 'layers.exr'
    r = run_cli(CORNELL, '-D', 'res=16', '--spp', '4', '--max-depth', '5', '--strategies', '-q', '-o', str(out), *VARIANT)
    assert r.returncode == 0, r.stderr
    img, ch, header = read_exr(out)
    names = header['bdpt.layers'].split()
    assert 's0_t2' in names and 's1_t1' in names and 's2_t2' in names and 'other' in names
    assert header['bdpt.param.strategy_images'] == 'true'
    for n in names:
        for kind in ('weighted', 'unweighted'):
            assert layer(ch, n, kind).shape == img.shape
    total = sum(layer(ch, n, 'weighted') for n in names)
    np.testing.assert_allclose(total, img, rtol=1e-4, atol=1e-5 * float(img.max()))
    # the strategies differ: the light-tracing (t=1) and camera (s=0) layers are not the same image
    assert not np.allclose(layer(ch, 's2_t1', 'weighted'), layer(ch, 's0_t3', 'weighted'))


@pytest.mark.parametrize('budget', [['--spp', '8'], ['--time', '60', '--pass-spp', '1']], ids=['spp', 'time'])
def test_interrupted_strategy_layers_sum_to_image(tmp_path, monkeypatch, budget):
    """A --strategies render stopped after its first pass (as Ctrl-C stops it: bdpt's
    should_stop hook says stop): the integrator scales its layers, like its image, to the
    samples traced, and the command must not scale them again (it did, by spp asked / spp done)."""
    monkeypatch.setattr(RenderHooks, 'stop', lambda self: True)    # asked before every pass after the first
    out = tmp_path / 'cut.exr'
    rc = cli.main(['render', CORNELL, '-D', 'res=16', *budget, '--samples-per-pass', '256', '--max-depth', '5',
                   '--strategies', '-o', str(out), *VARIANT])     # in this process: the hook patched
    assert rc == 130
    img, ch, header = read_exr(out)
    assert header['bdpt.interrupted'] == 'true'
    assert header['bdpt.passes'] == '1' and header['bdpt.spp'] == '1'  # 256 samples: 1 spp of 16x16
    names = header['bdpt.layers'].split()
    total = sum(layer(ch, n, 'weighted') for n in names)
    assert img.mean() > 0
    np.testing.assert_allclose(total, img, rtol=1e-4, atol=1e-5 * float(img.max()))


# ----------------------------------------------------------------------------- errors
SCENE_HEAD = '''<scene version="3.0.0">
    <default name="res" value="8"/>
    <sensor type="perspective">
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film>
    </sensor>
'''


SPECFILM_SCENE = '''<scene version="3.0.0">
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="specfilm">
            <integer name="width" value="8"/><integer name="height" value="8"/>
            <spectrum name="blue" value="400:1, 500:1"/><spectrum name="long" value="480:0.5, 700:1"/>
        </film>
    </sensor>
    <shape type="rectangle"><transform name="to_world"><scale value="2"/></transform></shape>
    <emitter type="point"><point name="position" x="0.5" y="0.5" z="2"/><spectrum name="intensity" value="5"/></emitter>
</scene>
'''


def _unsupported_emitter_scene():
    """A scene with an emitter bdpt refuses (the supported set grows, so pick one it lacks)."""
    from bdpt_jit.scene_check import SUPPORTED_EMITTERS
    if 'directionalarea' not in SUPPORTED_EMITTERS:
        return (SCENE_HEAD + '    <shape type="rectangle"><emitter type="directionalarea">'
                '<rgb name="radiance" value="1"/></emitter></shape>\n</scene>\n', r"'directionalarea'.*not supported")
    # a textured area light on a mesh (a cube's faces share uvs: Mitsuba samples one face only)
    return (SCENE_HEAD + '    <shape type="cube"><emitter type="area">'
            '<texture name="radiance" type="checkerboard"/></emitter></shape>\n</scene>\n', 'not supported')


# case: (scene XML or None, arguments, what the message must contain)
ERROR_CASES = {
    'missing scene': (None, ['{dir}/nosuch.xml'], r'scene file not found: .*nosuch\.xml'),
    'xml syntax': (SCENE_HEAD + '    <shape type="sphere">\n</scene>\n', [], r'scene\.xml.*line \d+'),
    'unknown plugin': (SCENE_HEAD + '    <shape type="sphere"><bsdf type="nosuchbsdf"/></shape>\n</scene>\n',
                       [], r'line \d+.*nosuchbsdf.*not found'),
    'unsupported emitter': ('UNSUPPORTED', [], None),
    'bad -D value': (None, [CORNELL, '-D', 'res=abc'], r'line \d+.*"abc"'),
    '-D without =': (None, [CORNELL, '-D', 'nonsense'], 'NAME=VALUE'),
    '-D unknown name': (None, [CORNELL, '-D', 'res=8', '-D', 'nonsense=3'], "-D nonsense: .*no parameter"),
    'output folder missing': (None, [CORNELL, '-D', 'res=8', '-o', '{dir}/out/no/such/out.exr'], 'does not exist'),
    'output not exr': (None, [CORNELL, '-D', 'res=8', '-o', '{dir}/out/x.png'], r'\.exr'),
    'bad parameter': (None, [CORNELL, '-D', 'res=8', '--rr-depth', '0'], "--rr-depth: .*'rr_depth' must be >= 1"),
    'unknown integrator': (None, [CORNELL, '-D', 'res=8', '--integrator', 'nosuchintegrator'], 'nosuchintegrator.*not found'),
    'strategies with path': (None, [CORNELL, '-D', 'res=8', '--integrator', 'path', '--strategies'], '--strategies'),
    'bdpt option with path': (None, [CORNELL, '-D', 'res=8', '--integrator', 'path', '--mis', 'balance'], '--mis'),
    'unknown variant': (None, [CORNELL, '-D', 'res=8', '--variant', 'nosuch_rgb'], 'nosuch_rgb'),
    'denoise with a spectral film': (SPECFILM_SCENE, ['--variant', 'llvm_ad_spectral', '--denoise'],
                                     r'--denoise needs an RGB or luminance film.*SpecFilm'),
    # a medium bdpt cannot see (on a shape inside an instanced shape group): refused naming it
    'medium inside an instance': (SCENE_HEAD + '    <emitter type="constant"/>\n'
                                  '    <medium type="homogeneous" id="fog"/>\n'
                                  '    <shape type="shapegroup" id="grp"><shape type="sphere"><bsdf type="null"/>'
                                  '<ref name="interior" id="fog"/></shape></shape>\n'
                                  '    <shape type="instance"><ref id="grp"/></shape>\n</scene>\n', [],
                                  r"the medium 'fog' \(homogeneous\) is not on any shape bdpt can see"),
    # refused by the plugin's constructor, which Mitsuba reports as an "unknown plugin": the
    # command keeps only the plugin's own words
    'parameters that exclude each other': (None, [CORNELL, '-D', 'res=8', '--connections', '4'],
                                           r"error: bdpt: parameter 'connections' \(4\) needs the light vertex cache"),
}


@pytest.mark.parametrize('case', sorted(ERROR_CASES))
def test_error_is_one_line(tmp_path, case):
    xml, args, pattern = ERROR_CASES[case]
    outdir = tmp_path / 'out'
    outdir.mkdir()
    args = [a.format(dir=tmp_path) for a in args]
    if xml is not None:
        if xml == 'UNSUPPORTED':
            xml, pattern = _unsupported_emitter_scene()
        (tmp_path / 'scene.xml').write_text(xml)
        args = [str(tmp_path / 'scene.xml')] + args
    if '-o' not in args:
        args += ['-o', str(outdir / 'x.exr')]
    r = run_cli(*args, *([] if '--variant' in args else VARIANT))
    assert r.returncode == 1, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith('bdpt-jit: error: ')
    assert re.search(pattern, lines[0]), lines[0]
    assert 'Traceback' not in r.stderr and r.stdout == ''
    assert leftovers(outdir) == []
    assert leftovers(tmp_path) == sorted(['out'] + (['scene.xml'] if xml is not None else []))


def test_unwritable_output(tmp_path):
    if os.geteuid() == 0:                             # root writes anywhere a mode allows nothing
        target = '/proc/bdpt-jit-test.exr'
    else:
        ro = tmp_path / 'ro'
        ro.mkdir()
        ro.chmod(0o555)
        target = str(ro / 'x.exr')
    r = run_cli(CORNELL, '-D', 'res=8', '-o', target, *VARIANT)
    assert r.returncode == 1
    assert re.fullmatch(r'bdpt-jit: error: output folder is not writable: .*\n', r.stderr), r.stderr
    assert not os.path.exists(target)


def test_debug_shows_traceback(tmp_path):
    r = run_cli(CORNELL, '--rr-depth', '0', '--debug', '-o', str(tmp_path / 'x.exr'), *VARIANT)
    assert r.returncode != 0 and 'Traceback' in r.stderr


def test_usage_error(tmp_path):
    r = run_cli(CORNELL, '--spp', '0', '-o', str(tmp_path / 'x.exr'))
    assert r.returncode == 2 and '--spp' in r.stderr
    assert leftovers(tmp_path) == []


def test_missing_libllvm(tmp_path):
    r = run_cli(CORNELL, '-D', 'res=8', '-o', str(tmp_path / 'x.exr'), '--variant', 'llvm_ad_rgb',
                env={'DRJIT_LIBLLVM_PATH': '/nonexistent/libLLVM.so'})
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and 'libLLVM >= 16' in lines[0], r.stderr
    assert leftovers(tmp_path) == []


def test_missing_libllvm_message(monkeypatch):
    """What Dr.Jit raises when libLLVM cannot be loaded becomes one line naming libLLVM >= 16."""
    def fail(variant):
        raise ImportError('jit_init_thread_state(): the LLVM backend is inactive because the LLVM shared '
                          'library ("libLLVM.so") could not be found! Set the DRJIT_LIBLLVM_PATH '
                          'environment variable to specify its path.')
    monkeypatch.setattr(mi, 'set_variant', fail)
    monkeypatch.setenv('DRJIT_LIBLLVM_PATH', '/nonexistent/libLLVM.so')
    args = cli.build_parser().parse_args(['render', 'x.xml', '--variant', 'llvm_ad_rgb'])
    with pytest.raises(cli.CLIError) as e:
        session.init_variant(args)
    msg = str(e.value)
    assert 'libLLVM >= 16' in msg and 'apt-get install libllvm' in msg and '/nonexistent/libLLVM.so' in msg
    assert '\n' not in msg


# ----------------------------------------------------------------------------- Ctrl-C
class Running:
    """A render in a subprocess whose stderr is read while it runs."""

    def __init__(self, *args):
        self.proc = subprocess.Popen([sys.executable, '-m', 'bdpt_jit.cli', 'render', *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
        self.err = bytearray()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        while True:
            b = self.proc.stderr.read1(4096)
            if not b:
                return
            self.err.extend(b)

    def wait_for(self, pattern, timeout=60):
        t0 = time.time()
        while not re.search(pattern, bytes(self.err)):
            assert self.proc.poll() is None, bytes(self.err).decode(errors='replace')
            assert time.time() - t0 < timeout, 'timed out waiting for ' + repr(pattern)
            time.sleep(0.01)

    def interrupt(self, timeout=60):
        self.proc.send_signal(signal.SIGINT)
        out = self.proc.stdout.read()
        self.proc.wait(timeout=timeout)
        self.reader.join(timeout=10)
        return self.proc.returncode, out.decode(errors='replace'), bytes(self.err).decode(errors='replace')


@pytest.mark.parametrize('mode', [['--spp', '100000', '--samples-per-pass', '256'],
                                  ['--time', '60', '--pass-spp', '1']], ids=['spp', 'time'])
def test_ctrl_c_writes_partial_render(tmp_path, mode):
    out = tmp_path / 'partial.exr'
    run = Running(CORNELL, '-D', 'res=16', *mode, '-o', str(out), *VARIANT)
    run.wait_for(rb'\b[1-9]\d* pass')               # the progress bar shows a finished pass
    rc, stdout, stderr = run.interrupt()
    assert rc == 130, stderr
    assert re.search(r'interrupted: wrote the \d+ spp rendered so far', stderr), stderr
    assert 'Traceback' not in stderr
    assert leftovers(tmp_path) == ['partial.exr', 'partial.png']
    img, _, header = read_exr(out)
    assert header['bdpt.interrupted'] == 'true'
    spp = float(header['bdpt.spp'])
    assert 1 <= spp < 100000 and f'wrote the {spp:g} spp' in stderr
    assert np.isfinite(img).all()
    # correctly scaled: close to a proper render of the same scene (a loose check at low spp)
    ref = np.array(mi.render(mi.load_file(CORNELL, res='16'), spp=16, seed=1))[:, :, :3]
    assert abs(img.mean() / ref.mean() - 1) < 0.25


def test_ctrl_c_before_first_pass_writes_nothing(tmp_path):
    out = tmp_path / 'none.exr'
    run = Running(CORNELL, '-D', 'res=64', '--spp', '64', '-o', str(out), *VARIANT)
    run.wait_for(rb'rendering')                     # the bar is up: the first (only) pass runs
    rc, stdout, stderr = run.interrupt()
    assert rc == 130, stderr
    assert 'nothing was written' in stderr and 'Traceback' not in stderr
    assert leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- docs
def test_docs_list_the_parameter_options():
    with open(os.path.join(REPO, 'docs', 'cli.md')) as f:
        text = f.read()
    assert cli.params_markdown() in text, \
        'docs/cli.md is out of date: paste python -c "from bdpt_jit.cli import params_markdown; print(params_markdown())"'
    for opt in ('--spp', '--time', '--pass-spp', '--integrator', '-D', '--variant', '--seed', '-o', '-q', '--debug'):
        assert f'`{opt}' in text, opt


@pytest.mark.parametrize('variant,channels', [('llvm_ad_mono', ['Y']), ('llvm_ad_spectral', ['B', 'G', 'R'])])
def test_other_variants_write_their_channels(tmp_path, variant, channels):
    """A monochrome variant's image is one channel (Y in the EXR, a grey PNG); a spectral
    variant's is RGB, as the film develops it."""
    out = tmp_path / 'v.exr'
    r = run_cli(CORNELL, '-o', str(out), '--spp', '2', '-D', 'res=8', '--variant', variant, '-q')
    assert r.returncode == 0, r.stderr
    f = OpenEXR.File(str(out), separate_channels=True)
    ch = {name: c.pixels for name, c in f.channels().items()}
    assert sorted(ch) == channels
    assert all(np.isfinite(ch[k]).all() and ch[k].max() > 0 for k in channels)
    assert (tmp_path / 'v.png').exists()


def test_a_spectral_film_writes_its_bands(tmp_path):
    """A specfilm's image is one channel a band, named as the scene names them (as Mitsuba
    writes it); the PNG shows their mean in gray."""
    (tmp_path / 'scene.xml').write_text(SPECFILM_SCENE)
    out = tmp_path / 'v.exr'
    r = run_cli(str(tmp_path / 'scene.xml'), '-o', str(out), '--spp', '4', '--variant', 'llvm_ad_spectral', '-q')
    assert r.returncode == 0, r.stderr
    f = OpenEXR.File(str(out), separate_channels=True)
    ch = {name: c.pixels for name, c in f.channels().items()}
    assert sorted(ch) == ['blue', 'long']
    assert all(np.isfinite(ch[k]).all() and ch[k].max() > 0 for k in ch)
    assert (tmp_path / 'v.png').exists()


def test_aovs_are_written_as_named_channels(tmp_path):
    out = tmp_path / 'a.exr'
    r = run_cli(CORNELL, '-o', str(out), '--spp', '2', '-D', 'res=8', '--aovs', 'dd:depth,nn:sh_normal', '-q')
    assert r.returncode == 0, r.stderr
    f = OpenEXR.File(str(out), separate_channels=True)
    ch = {name: c.pixels for name, c in f.channels().items()}
    assert {'R', 'G', 'B', 'dd.T', 'nn.X', 'nn.Y', 'nn.Z'} <= set(ch)
    assert ch['dd.T'].max() > 1.0 and abs(ch['nn.Z']).max() <= 1.0 + 1e-5


def test_the_summary_says_how_many_light_subpaths_the_beams_gathered_from():
    """With statistics in a scene with media, the summary's media line counts the collisions and,
    where media merge by beams, the light subpaths an iteration the beams gathered from
    (last_render_info['media']['beam_paths'], parameter beam_paths); no such clause without beams."""
    from bdpt_jit.cli.summary import _bdpt_statistics
    media = {'heterogeneous': False, 'chromatic': False, 'real_collisions': 12, 'null_collisions': 0,
             'medium_inconsistencies': 0}
    beams = _bdpt_statistics({'strategies': [], 'media': {**media, 'merging': 'beams', 'beam_paths': 4096}})['media']
    assert beams.startswith('12 real collisions') and beams.endswith('beams gathered from 4,096 light subpaths an iteration')
    assert 'beams' not in _bdpt_statistics({'strategies': [], 'media': {**media, 'merging': None}})['media']
