"""The comparison benchmark (`benchmarks/compare.py`): its quick mode on a tiny configuration writes
the report, its tables and its plots, with every figure finite; the ray-count replica of Mitsuba's
`path` agrees with bdpt's own counters where both trace the same camera subpaths; the caustic
close-up keeps the Figure 7 scene's content."""

import json
import math
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET

import mitsuba as mi

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(REPO, 'scenes')
CONTESTANT_LABELS = ('bdpt power', 'bdpt balance', 'bdpt uniform', 'bdpt pt', 'bdpt lt', 'Mitsuba path',
                     'Mitsuba ptracer')
TEXT_COLUMNS = {'contestant', 'point', 'scene'}
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


def test_quick_mode_writes_finite_tables_and_plots(tmp_path):
    out, figs, cache = tmp_path / 'results.md', tmp_path / 'results', tmp_path / 'cache'
    scenes = ['caustic', 'fig7-caustic']     # one reference of each kind: path + ptracer, ptracer over a region
    cmd = [sys.executable, os.path.join(REPO, 'benchmarks', 'compare.py'), '--quick', '--res', '12',
           '--probe-spp', '1', '--budgets', '0.03', '--repeats', '1', '--ref-spp', '8', '--ref-batches', '2',
           '--pilot-spp', '2', '--pilot-batches', '2', '--count-spp', '1', '--scenes', ','.join(scenes),
           '--out', str(out), '--fig-dir', str(figs), '--cache-dir', str(cache)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert '**quick mode**' in text and 'Mitsuba 3.9.1' in text and 'cores' in text

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
    assert len(tables) == 3 + 4 * len(scenes)
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
    for header, rows in tables[2:]:
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


def test_path_replica_counts_the_camera_rays_bdpt_pt_traces():
    """bdpt with technique=pt walks camera subpaths as Mitsuba's path does (same sampling, same
    Russian roulette on a camera subpath), so the replica's camera-ray count must match bdpt's own
    counter statistically (about 0.3% standard error here)."""
    sys.path.insert(0, os.path.join(REPO, 'benchmarks'))
    import raycount
    scene = mi.load_file(os.path.join(SCENES, 'indirect-room.xml'), res=16, integrator='path')
    spp, n = 16, 16 * 16 * 16
    replica = raycount.count('path', scene, 8, spp, seed=5)
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 8, 'technique': 'pt', 'statistics': True})
    mi.render(scene, integrator=integ, spp=spp, seed=6)
    mine = integ.last_render_info['rays']
    assert replica['samples'] == n
    assert abs(replica['camera_rays'] / mine['camera_rays'] - 1) < 0.03, (replica, mine)
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
