"""The comparison benchmark (`benchmarks/compare.py`): its quick mode on a tiny configuration writes
the report, its tables and its plots, with every figure finite, and says that Mitsuba 0.6 was absent;
its realistic mode's settings and the --scene-file option; the Mitsuba 0.6 scene converter, build
script, speed subcommand and contestants (with a stand-in `mitsuba` binary; with a real build where
MITSUBA06_DIST names one, its image agrees with Mitsuba 3's);
the ray-count replica of Mitsuba's `path` agrees with bdpt's own counters where both trace the same
camera subpaths; the caustic close-up keeps the Figure 7 scene's content."""

import json
import math
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import mitsuba as mi
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(REPO, 'scenes')
BENCH = os.path.join(REPO, 'benchmarks')
VEACH_BIDIR = '/work/shared/scenes/bitterli/veach-bidir/scene.xml'     # a user's scene, where present
sys.path.insert(0, BENCH)
BASE_LABELS = ('bdpt power', 'bdpt balance', 'bdpt uniform', 'bdpt pt', 'bdpt lt', 'Mitsuba path', 'Mitsuba ptracer')
VCM_LABELS = ('bdpt vcm', 'bdpt vcm everywhere', 'bdpt vm')   # where this bdpt_jit has vertex merging (issue 15)
TEXT_COLUMNS = {'contestant', 'point', 'scene', 'lowest relMSE', 'runner-up', 'order of relMSE (equal time)', 'S-D-S paths',
                'target', 'met'}
NUMBER = re.compile(r'^[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?$')


def markdown_tables(text):
    """[(header cells, [row cells])] of every pipe table in a markdown text."""
    tables, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith('|') and i + 1 < len(lines) and re.match(r'^\|(-+\|)+$', lines[i + 1]):
            header = [c.strip() for c in lines[i].strip('|').split('|')]
            rows, i = [], i + 2
            while i < len(lines) and lines[i].startswith('|'):
                rows.append([c.strip() for c in lines[i].strip('|').split('|')])
                i += 1
            tables.append((header, rows))
        else:
            i += 1
    return tables


def check_finite_json(obj, where='results.json'):
    if isinstance(obj, dict):
        for k, v in obj.items():
            check_finite_json(v, f'{where}.{k}')
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            check_finite_json(v, f'{where}[{i}]')
    elif isinstance(obj, float):
        assert math.isfinite(obj), where


def reject_constant(name):
    raise AssertionError(f'results.json holds {name}')


def contestant_labels():
    """The quick mode's contestants as the report names them, in its order: vcm and vm where they run here."""
    import compare_lib as lib
    refused = [lib.unavailable(c) for c in lib.CONTESTANTS if c.key in ('vcm', 'vm')]
    labels = list(BASE_LABELS)
    if not any(refused):
        labels[5:5] = VCM_LABELS
    return tuple(labels), not any(refused)


def test_quick_mode_writes_finite_tables_and_plots(tmp_path):
    CONTESTANT_LABELS, has_vcm = contestant_labels()
    out, figs, cache = tmp_path / 'results.md', tmp_path / 'results', tmp_path / 'cache'
    # ptracer over a region (path + ptracer: the caustic of test_mitsuba06_contestants_join_the_tables)
    scenes = ['fig7-caustic']
    cmd = [sys.executable, os.path.join(REPO, 'benchmarks', 'compare.py'), '--quick', '--res', '12',
           '--probe-spp', '1', '--budgets', '0.03', '--repeats', '1', '--ref-spp', '8', '--ref-batches', '2',
           '--pilot-spp', '2', '--pilot-batches', '2', '--count-spp', '1', '--scenes', ','.join(scenes),
           '--out', str(out), '--fig-dir', str(figs), '--cache-dir', str(cache)]
    env = {k: v for k, v in os.environ.items() if k != 'MITSUBA06_DIST'}      # no Mitsuba 0.6 given
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert '**quick mode**' in text and 'Mitsuba 3.9.1' in text and 'cores' in text
    assert '- Mitsuba 0.6: **absent**: no Mitsuba 0.6 binary given' in text
    assert 'mitsuba06' not in markdown_tables(text)[0][0][2:]
    assert ('**Absent** (this bdpt_jit refuses them): bdpt vcm' in text) != has_vcm

    # every plot the report links is there and is a PNG; one error plot and one crop sheet per scene
    links = re.findall(r'!\[[^\]]*\]\(([^)]+)\)', text)
    for key in scenes:
        assert f'results/{key}-error.png' in links and f'results/{key}-crops.png' in links
    assert 'results/summary.png' in links
    for link in links:
        data = (out.parent / link).read_bytes()
        assert data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) > 1000, link

    # the tables: summary (relMSE and MSE ratios, compile), and per scene the sweep, equal samples, equal time
    # and compile time
    tables = markdown_tables(text)
    assert len(tables) == 4 + has_vcm + 4 * len(scenes)
    summary_header, summary_rows = tables[0]
    assert [r[0] for r in summary_rows] == scenes
    assert all(label in summary_header for label in CONTESTANT_LABELS)
    numbers = 0
    for header, rows in tables:
        for row in rows:
            assert len(row) == len(header), (header, row)
            for col, cell in zip(header, row):
                assert not re.search(r'nan|inf', cell, re.I), (col, cell)
                if col in TEXT_COLUMNS:
                    continue
                value = cell.replace('†', '').strip('()')
                assert NUMBER.match(value), (col, cell)
                assert math.isfinite(float(value)), (col, cell)
                numbers += 1
    assert numbers > 200
    assert [r[0] for r in tables[1][1]] == scenes          # the MSE ratios
    wins = [rows for header, rows in tables if 'lowest relMSE' in header]
    assert len(wins) == 1 and [r[0] for r in wins[0]] == scenes
    for row in wins[0]:
        assert row[1] in CONTESTANT_LABELS and sorted(row[4].split(' < ')) == sorted(CONTESTANT_LABELS)
    vcm = [rows for header, rows in tables if 'vcm / path' in header]
    assert len(vcm) == has_vcm
    if has_vcm:         # both scenes state the caustic target; the check is `met`, `not met` or undecided
        assert [r[0] for r in vcm[0]] == scenes and all(r[-2] == 'vcm / path <= 0.25' for r in vcm[0])
        assert all(r[-1] in ('yes', 'no', 'undecided') for r in vcm[0])
    for header, rows in tables[2:]:
        if 'scene' not in header:
            assert [r[0] for r in rows if r[0] in CONTESTANT_LABELS]
    equal_time = [rows for header, rows in tables if 'relMSE / path' in header]
    assert len(equal_time) == len(scenes)
    for rows in equal_time:
        assert [r[0] for r in rows] == list(CONTESTANT_LABELS)
        assert float(rows[CONTESTANT_LABELS.index('Mitsuba path')][-1].strip('()†')) == 1.0

    # the raw figures: finite everywhere (json would otherwise hold NaN or Infinity)
    data = json.loads((figs / 'results.json').read_text(), parse_constant=reject_constant)
    check_finite_json(data)
    assert [s['spec']['key'] for s in data['scenes']] == scenes
    for s in data['scenes']:
        assert s['reference']['expected_rel'] > 0
        for key, pts in s['sweep'].items():
            assert len(pts) >= 2 and all(p['spp'] >= 1 for p in pts), key
            assert all(p['time'] > 0 and p['mse'] > 0 for p in pts), key
        for key, r in s['rays'].items():
            assert r['rays_per_sample'] >= r['zero_per_sample'] >= 0, key


def test_section_keeps_the_rest_of_the_report(tmp_path):
    """--section NAME writes the run between markers in --out, after what the file holds, its figures under
    NAME/ of the figure folder; a second run with the same NAME replaces the section, the rest stays."""
    out, cache = tmp_path / 'results.md', tmp_path / 'cache'
    out.write_text('# The full report\n\nkept as it is\n')
    cmd = [sys.executable, os.path.join(BENCH, 'compare.py'), '--quick', '--res', '8', '--probe-spp', '1',
           '--budgets', '0.02', '--repeats', '1', '--ref-spp', '4', '--ref-batches', '2', '--pilot-spp', '2',
           '--pilot-batches', '2', '--count-spp', '1', '--scenes', 'cornell-box', '--contestants', 'bdpt,path',
           '--section', 'extra', '--out', str(out), '--cache-dir', str(cache), '--fig-dir', str(tmp_path / 'figs')]
    env = {k: v for k, v in os.environ.items() if k != 'MITSUBA06_DIST'}
    for run in range(2):
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
        assert proc.returncode == 0, proc.stderr[-3000:]
        text = out.read_text()
        assert text.startswith('# The full report\n\nkept as it is\n\n<!-- compare.py --section extra: begin')
        assert text.count('--section extra: begin') == 1 and text.count('--section extra: end') == 1
        assert text.count('\n# ') == 0 and '\n## Section `extra`: Comparison benchmarks' in text
        assert '\n### Summary: relative MSE at equal time' in text and '\n### Cornell box' in text
        for link in re.findall(r'!\[[^\]]*\]\(([^)]+)\)', text):
            assert (out.parent / link).read_bytes()[:4] == b'\x89PNG', link
    assert (tmp_path / 'figs' / 'cornell-box-error.png').exists()
    # a full report in its place keeps the section
    import compare_report as report
    section = text[text.index('<!-- compare.py --section extra: begin'):]
    assert report.sections_of(text) == [section]
    report.put_section(out, 'other', 'two')
    assert report.sections_of(out.read_text()) == [section, report.section_markers('other')[0] + '\n\ntwo\n\n'
                                                   + report.section_markers('other')[1] + '\n']
    # without --fig-dir, the figures go to docs/results/NAME/
    import compare
    args, _, _ = compare.parse_args(['--quick', '--section', 'vcm'])
    assert args.fig_dir == compare.lib.REPO / 'docs' / 'results' / 'vcm'
    with pytest.raises(SystemExit):
        compare.parse_args(['--quick', '--section', 'a b'])


@pytest.mark.parametrize('name', ['indirect-room.xml', 'torus-in-glass.xml'])
def test_path_replica_counts_the_camera_rays_bdpt_pt_traces(name):
    """bdpt with technique=pt walks camera subpaths as Mitsuba's path does (same sampling, same
    Russian roulette on a camera subpath, on the throughput times eta^2 of the refractions), so
    the replica's camera-ray count must match bdpt's own counter statistically (about 0.3%
    standard error here); through the rough acrylic block (glass=rough) too, where a roulette
    on the throughput alone ends the paths inside the block early."""
    sys.path.insert(0, os.path.join(REPO, 'benchmarks'))
    import raycount
    kw = {'glass': 'rough'} if 'glass' in name else {}
    scene = mi.load_file(os.path.join(SCENES, name), res=16, integrator='path', **kw)
    spp, n = 16, 16 * 16 * 16
    replica = raycount.count('path', scene, 8, spp, seed=5)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 8, 'technique': 'pt', 'statistics': True})
    mi.render(scene, integrator=integ, spp=spp, seed=6)
    mine = integ.last_render_info['rays']
    assert replica['samples'] == n
    assert abs(replica['camera_rays'] / mine['camera_rays'] - 1) < 0.03, (replica, mine)
    if 'room' in name:
        assert replica['camera_rays_missed'] == mine['camera_rays_missed'] == 0      # a closed room
        # ptracer: one emission ray per light path, a connection per vertex
        pt = raycount.count('ptracer', scene, 8, 4, seed=7)
        assert pt['camera_rays'] == 0 and pt['light_rays'] >= 16 * 16 * 4 and pt['shadow_rays'] > 0


def scene_content(path):
    """The scene's elements other than the sensor, as text, in order."""
    root = ET.parse(path).getroot()
    return [ET.tostring(e).decode().strip() for e in root if e.tag != 'sensor']


def test_caustic_closeup_is_the_figure7_scene():
    """sun-room-caustic.xml copies sun-room.xml's geometry, materials and lights; only the camera differs."""
    a = scene_content(os.path.join(SCENES, 'sun-room.xml'))
    b = scene_content(os.path.join(SCENES, 'sun-room-caustic.xml'))
    assert a == b
    sensors = [ET.parse(os.path.join(SCENES, f)).getroot().find('sensor') for f in ('sun-room.xml', 'sun-room-caustic.xml')]
    assert ET.tostring(sensors[0]) != ET.tostring(sensors[1])


# ------------------------------------------------------------------------------------------ realistic mode

def test_realistic_mode_settings_and_scene_file():
    import compare
    args, s, scenes = compare.parse_args(['--realistic', '--scene-file', f'mine={SCENES}/caustic.xml,max_depth=5'])
    assert s.mode == 'realistic' and s.res >= 256
    assert s.budgets[0] == 1 and s.budgets[-1] >= 60 and list(s.budgets) == sorted(s.budgets)
    assert {'bdpt', 'path', 'mitsuba06-bdpt', 'mitsuba06-path'} <= set(s.contestants)
    assert s.ref_spp * s.ref_batches >= 16384 and s.ref06_spp * s.ref06_batches >= 1024
    import compare_lib as lib
    assert [sc.key for sc in scenes] == [sc.key for sc in lib.SCENES] + ['mine']
    mine = scenes[-1]
    assert mine.user and mine.max_depth == 5 and mine.path == mine.path.resolve() and mine.path.name == 'caustic.xml'

    # overrides, a scene selection, the references' sizes
    _, s, scenes = compare.parse_args(['--realistic', '--scenes', 'fig6', '--scene-file', f'b={SCENES}/caustic.xml',
                                       '--ref-spp', '64', '--ref06-spp', '16', '--ref06-batches', '4',
                                       '--contestants', 'bdpt,path,mitsuba06-bdpt'])
    assert [sc.key for sc in scenes] == ['fig6', 'b'] and scenes[1].max_depth == 8     # the file's default
    assert (s.ref_spp, s.ref06_spp, s.ref06_batches) == (64, 16, 4)
    assert s.contestants == ('bdpt', 'path', 'mitsuba06-bdpt')
    for bad in (['--scene-file', f'x={SCENES}/nothing.xml'], ['--scene-file', f'x={SCENES}/caustic.xml,depth=3'],
                ['--scene-file', f'fig6={SCENES}/caustic.xml'], ['--contestants', 'bdpt,ptracer']):
        with pytest.raises(SystemExit):
            compare.parse_args(['--realistic'] + bad)


@pytest.mark.skipif(not os.path.exists(VEACH_BIDIR), reason='no copy of Veach\'s bidirectional room here')
def test_veach_bidir_as_a_scene_file():
    """Bitterli's Veach room takes resx/resy, not res: loaded at the mode's resolution all the same."""
    import compare
    import compare_lib as lib
    _, s, scenes = compare.parse_args(['--realistic', '--scenes', '', '--scene-file', f'veach-bidir={VEACH_BIDIR}'])
    assert [sc.key for sc in scenes] == ['veach-bidir'] and scenes[0].max_depth == 7
    scene = lib.load_scene(scenes[0], 8)
    assert list(scene.sensors()[0].film().crop_size()) == [8, 8]


# ------------------------------------------------------------------------------------------ Mitsuba 0.6

def names_of(root):
    return [e.get('name') for e in root.iter() if e.get('name') and e.tag != 'default']


def test_mitsuba06_converter_renames_parameters(tmp_path):
    import mitsuba06
    dst = tmp_path / 'fig6.xml'
    mitsuba06.convert_file(os.path.join(SCENES, 'paper-fig6.xml'), dst, {'res': 32})
    root = ET.parse(dst).getroot()
    assert root.get('version') == '0.6.0'
    names = names_of(root)
    for new in ('toWorld', 'fovAxis', 'intIOR', 'extIOR', 'diffuseReflectance', 'pixelFormat', 'sampleCount',
                'maxDepth', 'rrDepth', 'componentFormat', 'banner', 'alpha', 'distribution'):
        assert new in names, new
    assert not [n for n in names if '_' in n], names
    film = root.find('sensor/film')
    assert film.find("integer[@name='width']").get('value') == '32'
    assert film.find("boolean[@name='banner']").get('value') == 'false'
    assert film.find("string[@name='componentFormat']").get('value') == 'float32'
    sampler = root.find('sensor/sampler')
    assert sampler.get('type') == 'independent'
    assert {e.get('name'): e.get('value') for e in sampler} == {'sampleCount': '$spp', 'seed': '$seed'}
    integ = root.find('integrator')
    assert integ.get('type') == '$integrator'
    assert {e.get('name'): e.get('value') for e in integ} == {'maxDepth': '8', 'rrDepth': '5'}
    # Mitsuba 3's conductor without a material is a mirror; 0.6's default would be copper
    mirror = root.find("shape[@id='mirror_sphere']/bsdf")
    assert mirror.find("string[@name='material']").get('value') == 'none'
    # the checkerboard's to_uv scale becomes uscale/vscale
    tex = root.find("shape[@id='textured_sphere']/bsdf/texture")
    assert float(tex.find("float[@name='uscale']").get('value')) == 8.0
    assert float(tex.find("float[@name='vscale']").get('value')) == 4.0
    assert '$res' not in dst.read_text() and '$max_depth' not in dst.read_text()

    # every scene of the repository converts; names of more plugins
    for f in sorted(os.listdir(SCENES)):
        if f.endswith('.xml'):
            mitsuba06.convert_file(os.path.join(SCENES, f), tmp_path / f, {'res': 16})
            names = names_of(ET.parse(tmp_path / f).getroot())
            assert not [n for n in names if '_' in n], (f, names)
    lights = names_of(ET.parse(tmp_path / 'all-lights.xml').getroot())
    assert {'cutoffAngle', 'beamWidth', 'irradiance', 'intensity', 'position', 'direction'} <= set(lights)
    with open(tmp_path / 'all-lights.xml') as fh:
        assert os.path.join(SCENES, 'textures', 'sky.exr') in fh.read()     # relative file names made absolute

    # what 0.6 does not have is refused
    bad = tmp_path / 'bad.xml'
    bad.write_text('<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm"/></sensor>'
                   '<shape type="sphere"><bsdf type="principled"/></shape></scene>')
    with pytest.raises(mitsuba06.Mitsuba06Error, match='principled'):
        mitsuba06.convert_file(bad, tmp_path / 'bad06.xml')


@pytest.mark.skipif(not os.path.exists(VEACH_BIDIR), reason='no copy of Veach\'s bidirectional room here')
def test_mitsuba06_converter_on_veach_bidir(tmp_path):
    import mitsuba06
    dst = tmp_path / 'veach06.xml'
    mitsuba06.convert_file(VEACH_BIDIR, dst, {'resx': 64, 'resy': 64}, max_depth=7)
    root = ET.parse(dst).getroot()
    names = names_of(root)
    assert {'faceNormals', 'specularReflectance', 'eta', 'k', 'alpha', 'distribution', 'intIOR', 'extIOR'} <= set(names)
    assert not [n for n in names if '_' in n]
    files = [e.get('value') for e in root.iter('string') if e.get('name') == 'filename']
    assert files and all(os.path.isabs(f) and os.path.exists(f) for f in files)
    film = root.find('sensor/film')
    assert (film.find("integer[@name='width']").get('value'), film.find("integer[@name='height']").get('value')) == \
        ('64', '64')


def test_mitsuba06_absent_is_reported_not_fatal(monkeypatch):
    import compare_report as report
    import mitsuba06
    monkeypatch.delenv(mitsuba06.ENV_VAR, raising=False)
    m06, how = mitsuba06.find(None)
    assert m06 is None and '--mitsuba06' in how and mitsuba06.ENV_VAR in how
    line = report.mitsuba06_line({'wanted': ['mitsuba06 bdpt', 'mitsuba06 path'], 'used': False, 'how': how})
    assert line.startswith('- Mitsuba 0.6: **absent**') and 'mitsuba06 bdpt' in line
    # a `mitsuba` that is not 0.6 (Mitsuba 3's command has that name) is refused, with the reason
    m06, how = mitsuba06.find(os.path.dirname(sys.executable))
    assert m06 is None and ('not Mitsuba 0.6' in how or 'no executable' in how)


def test_mitsuba06_build_script_says_what_it_needs(tmp_path, capsys):
    import mitsuba06
    assert mitsuba06.main(['build', '--source', str(tmp_path / 'nothing')]) == 1
    err = capsys.readouterr().err
    assert 'no such folder' in err and 'git clone https://github.com/mitsuba-renderer/mitsuba' in err
    assert mitsuba06.main(['build', '--source', str(tmp_path)]) == 1
    assert 'not a clone' in capsys.readouterr().err
    # the SConscripts' Python 2, in Python 3 form
    py2 = ("if env.has_key('X'):\n        print 'a' + \\\n            'b'\nelse:\n    print MTS_VERSION\n"
           "try:\n    pass\nexcept OSError, e:\n    pass\n")
    py3 = mitsuba06.python3_sconscript(py2)
    compile(py3, 'SConscript', 'exec')
    assert "('X') in env" in py3 and "print('a' + \\\n            'b')" in py3 and 'print(MTS_VERSION)' in py3
    assert 'except OSError as e:' in py3 and mitsuba06.python3_sconscript(py3) == py3


FAKE_MITSUBA06 = '''#!{python}
# A stand-in for Mitsuba 0.6's `mitsuba` command (none is built here): its command line and log line,
# a flat image with noise of 1/sqrt(spp) drawn from the seed, and a render time proportional to spp.
import os, re, sys
args = sys.argv[1:]
if '-h' in args:
    print('Mitsuba version 0.6.0 (stand-in for tests)')
    sys.exit(0)
import numpy as np
import mitsuba as mi
d = dict(a[2:].split('=', 1) for a in args if a.startswith('-D'))
text = open(args[-1]).read()
if os.environ.get('FAKE_UNPATCHED'):
    print('WARN  main  [xml] Unqueried attribute "seed" in element "sampler"')
w = int(re.search(r'name="width" value="(\\d+)"', text).group(1))
h = int(re.search(r'name="height" value="(\\d+)"', text).group(1))
spp = int(d['spp'])
noise = 0.3 if d['integrator'] == 'bdpt' else 0.6
img = 0.5 + noise / spp ** 0.5 * np.random.default_rng(int(d['seed'])).standard_normal((h, w, 3))
mi.Bitmap(img.astype(np.float32)).write(args[args.index('-o') + 1])
print('INFO  main  [RenderJob] Render time: %.4fs' % (1e-4 * spp))
'''


def test_mitsuba06_contestants_join_the_tables(tmp_path, monkeypatch):
    """With a (stand-in) Mitsuba 0.6, "mitsuba06 bdpt" and "mitsuba06 path" are in every table and plot,
    measured against their own reference; without the seed edit the binary is refused."""
    dist = tmp_path / 'dist'
    dist.mkdir()
    fake = dist / 'mitsuba'
    fake.write_text(FAKE_MITSUBA06.replace('{python}', sys.executable))
    fake.chmod(0o755)
    import mitsuba06
    with monkeypatch.context() as mp:
        mp.setenv('FAKE_UNPATCHED', '1')
        m06, how = mitsuba06.find(str(dist))
    assert m06 is None and 'seed' in how

    out, figs, cache = tmp_path / 'results.md', tmp_path / 'results', tmp_path / 'cache'
    cmd = [sys.executable, os.path.join(BENCH, 'compare.py'), '--quick', '--res', '8', '--probe-spp', '1',
           '--budgets', '0.03', '--repeats', '1', '--ref-spp', '4', '--ref-batches', '2', '--pilot-spp', '2',
           '--pilot-batches', '2', '--count-spp', '1', '--ref06-spp', '4', '--ref06-batches', '2', '--scenes',
           'caustic', '--contestants', 'bdpt,path,mitsuba06-bdpt,mitsuba06-path', '--mitsuba06', str(dist),
           '--out', str(out), '--fig-dir', str(figs), '--cache-dir', str(cache)]
    env = {k: v for k, v in os.environ.items() if k != 'FAKE_UNPATCHED'}
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert '**absent**' not in text and f'- Mitsuba 0.6: {fake}' in text
    tables = markdown_tables(text)
    assert tables[0][0][2:] == ['bdpt power', 'Mitsuba path', 'mitsuba06 bdpt', 'mitsuba06 path']
    compile_rows = [rows for header, rows in tables if 'kernels compiled' in header][0]
    assert [r[0] for r in compile_rows] == ['bdpt power', 'Mitsuba path']      # 0.6 compiles nothing
    equal_time = [rows for header, rows in tables if 'relMSE / path' in header][0]
    assert [r[0] for r in equal_time][2:] == ['mitsuba06 bdpt', 'mitsuba06 path']
    assert all(r[6] == '–' for r in equal_time[2:])                        # no ray counts
    data = json.loads((figs / 'results.json').read_text(), parse_constant=reject_constant)
    assert data['mitsuba06']['used'] and data['mitsuba06']['version'].startswith('0.6')
    scene = data['scenes'][0]
    assert scene['reference06']['spp'] == 8 and scene['reference06']['expected_rel'] > 0
    assert scene['reference_of']['mitsuba06-path'] == 'reference06' and scene['reference_of']['path'] == 'reference'
    for key in ('mitsuba06-bdpt', 'mitsuba06-path'):
        pts = scene['sweep'][key]
        assert all(p['time'] == pytest.approx(1e-4 * p['spp'], abs=1e-4) for p in pts), pts
        assert all(p['rel'] > 0 for p in pts)
    # the stand-in's bdpt has half its path's noise: a quarter of its error at equal samples
    es = scene['equal_samples']['points']
    assert es['mitsuba06-bdpt']['rel'] < es['mitsuba06-path']['rel']
    assert (cache / 'mitsuba06' / 'caustic-8.xml').exists()


def test_mitsuba06_speed_subcommand(tmp_path, capsys):
    """`mitsuba06.py speed` sets Mitsuba 0.6's bdpt and path (here the stand-in) beside bdpt_jit's bdpt and
    Mitsuba 3's path at the same resolution and spp, and writes its figures."""
    dist = tmp_path / 'dist'
    dist.mkdir()
    fake = dist / 'mitsuba'
    fake.write_text(FAKE_MITSUBA06.replace('{python}', sys.executable))
    fake.chmod(0o755)
    import mitsuba06
    out = tmp_path / 'speed.json'
    assert mitsuba06.main(['speed', '--dist', str(dist), '--scene', os.path.join(SCENES, 'cornell-box.xml'),
                           '--res', '8', '--spp', '2', '--max-depth', '4', '--repeats', '2', '--json', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'bdpt_jit bdpt / Mitsuba 0.6 bdpt (samples/s)' in text
    data = json.loads(out.read_text())
    assert set(data['results']) == {'Mitsuba 0.6 bdpt', 'Mitsuba 0.6 path', 'bdpt_jit bdpt', 'Mitsuba 3 path'}
    assert all(len(r['times']) == 2 and r['msps'] > 0 for r in data['results'].values())
    # the stand-in's render time is 1e-4 s a sample per pixel: 8 x 8 x 2 samples in 2e-4 s
    assert data['results']['Mitsuba 0.6 bdpt']['msps'] == pytest.approx(8 * 8 * 2 / 2e-4 / 1e6)


@pytest.mark.skipif(not os.environ.get('MITSUBA06_DIST'), reason='no Mitsuba 0.6 built (MITSUBA06_DIST)')
def test_mitsuba06_real_build_agrees_with_mitsuba3(tmp_path):
    """With a real Mitsuba 0.6 (MITSUBA06_DIST): it works, its seed edit makes renders independent, and its
    bdpt on the converted Cornell box has the image mean of Mitsuba 3's path."""
    import mitsuba06
    import numpy as np
    m06, how = mitsuba06.find(None)
    assert m06 is not None, how
    xml = tmp_path / 'cb06.xml'
    mitsuba06.convert_file(os.path.join(SCENES, 'cornell-box.xml'), xml, {'res': 24})
    # one thread: the same seed gives the same image (with several, blocks go to the workers' samplers in
    # whatever order they finish, so only the seed's independence holds), another seed another image
    _, _, a = m06.render(xml, 'bdpt', 64, seed=1, threads=1)
    _, _, b = m06.render(xml, 'bdpt', 64, seed=1, threads=1)
    _, _, c = m06.render(xml, 'bdpt', 64, seed=2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    mi.set_variant('llvm_ad_rgb')
    scene = mi.load_file(os.path.join(SCENES, 'cornell-box.xml'), res=24)
    ref = np.array(mi.render(scene, integrator=mi.load_dict({'type': 'path', 'max_depth': 8}), spp=256))
    assert (a.mean() + c.mean()) / 2 == pytest.approx(ref.mean(), rel=0.03)


def test_auto_targets_in_the_report():
    """Issue 22's targets for technique auto, as the report states them (compare_report.auto_rows): the
    bound to path is 1.0 where a bidirectional contestant is best and 1.1 where path is; auto is within
    1.25 of the best fixed contestant or not; a figure the reference cannot tell is undecided; the
    equal-time point's choices are listed. Made-up figures: no rendering."""
    import compare_lib as lib
    import compare_report as rep

    def result(key, rel, chose, ref_error=1e-9):
        points = {k: {'rel': v, 'mse': v, 'spp': 7 if k == 'auto' else 5} for k, v in rel.items()}
        return {'spec': {'key': key}, 'equal_time': {'budget_s': 16.0, 'points': points},
                'reference': {'expected_rel': ref_error, 'expected_mse': ref_error},
                'auto_choices': [{'key': 'auto', 'spp': 3, 'chose': ['bdpt']},
                                 {'key': 'auto', 'spp': 7, 'chose': chose}]}
    results = [result('open', {'bdpt': 2.0, 'path': 1.0, 'auto': 1.08}, ['pt', 'pt + pt']),
               result('near', {'bdpt': 2.0, 'path': 1.0, 'auto': 1.12}, ['pt']),
               result('room', {'bdpt': 0.1, 'path': 1.0, 'auto': 0.13}, ['bdpt']),
               result('door', {'bdpt': 0.5, 'path': 1.0, 'auto': 1.05}, ['cache 0.25x1']),
               result('noisy', {'bdpt': 0.1, 'path': 1.0, 'auto': 0.12}, ['bdpt'], ref_error=0.05)]
    header, rows = markdown_tables(rep.auto_rows(results, lib.contestants_of(['bdpt', 'path', 'auto'])))[0]
    got = {row[0]: dict(zip(header, row)) for row in rows}
    assert got['open']['target'] == 'auto / path <= 1.1' and got['open']['met'] == 'yes'
    assert got['open']['auto / best fixed'] == 'path: 1.08' and got['open']['<= 1.25'] == 'yes'
    assert got['open']['auto chose'] == 'pt, pt + pt'
    assert got['near']['met'] == 'no' and got['near']['<= 1.25'] == 'yes'
    assert got['room']['target'] == 'auto / path <= 1' and got['room']['met'] == 'yes'
    assert got['room']['auto / best fixed'] == 'bdpt: 1.3' and got['room']['<= 1.25'] == 'no'
    assert got['door']['met'] == 'no' and got['door']['<= 1.25'] == 'no'
    assert got['noisy']['met'] == 'undecided' and got['noisy']['<= 1.25'] == 'undecided'


def test_a_budgeted_contestant_renders_its_budget():
    """compare_lib.Runner.render_budgeted (technique auto's protocol, as `bdpt-jit render --time`):
    at a budget a budgeted contestant renders until the budget has passed, in passes of
    BUDGET_PASS_SPP, and its point holds the spp it rendered (the mean of its renders: a multiple
    of the pass here, where each render is the same whole passes' count or close), its image
    and choices under that spp; at a probe's spp it renders that spp. A stand-in for auto (technique pt) keeps the test's kernels few."""
    import numpy as np
    import compare_lib as lib
    spec = next(sc for sc in lib.SCENES if sc.key == 'cornell-box')
    scene = lib.load_scene(spec, 8)
    c = lib.Contestant('x', 'x', {'type': 'bdpt', 'technique': 'pt'}, progressive=True, budgeted=True)
    s = lib.Settings('t', res=8, budgets=(0.3,), repeats=1, probe_spp=(1,), ref_spp=1, ref_batches=1,
                     pilot_spp=1, pilot_batches=1, count_spp=1)
    ones = np.ones((8, 8, 3))
    ref = lib.Reference(ones, ones, np.ones((8, 8), bool), np.zeros((8, 8)), {})
    runner = lib.Runner(spec, scene, ref, s, [c])
    probe = runner.stage({'x': 2})['x']
    assert probe['spp'] == 2 and ('x', 2) in runner.images
    probe_image = runner.images[('x', 2)]
    point = runner.stage({'x': 2}, budget=0.3)['x']       # (requested 2: the probe's point keeps its own)
    assert point['time'] >= 0.3 and point['spp'] >= lib.BUDGET_PASS_SPP
    assert ('x', point['spp']) in runner.images and runner.images[('x', 2)] is probe_image
    assert runner.compile['x'][-1]['spp'] % lib.BUDGET_PASS_SPP == 0
