"""The report of `benchmarks/compare.py`: `docs/results.md`, its plots and image crops, and the raw
figures as JSON. Reads only what `compare_lib.run_scene` measured (and whether Mitsuba 0.6 was found)."""

import json
import math
import os
import re
from pathlib import Path

import numpy as np

import matplotlib
matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from compare_lib import BASELINE, BUDGET_PASS_SPP, QUOTABLE, EPS_REL, contestant_settings  # noqa: E402

# issue 15's equal-time targets for `vcm` (relMSE ratios): on scenes with specular-diffuse-specular paths, at most
# VCM_CAUSTIC of path's; on scenes without, at most VCM_PLAIN times bdpt's
VCM_CAUSTIC, VCM_PLAIN = 0.25, 1.2

STYLE = {
    'bdpt': ('tab:red', 'o', '-'), 'bdpt-balance': ('tab:orange', 's', '-'), 'bdpt-uniform': ('tab:brown', 'v', '-'),
    'bdpt-pt': ('tab:purple', '^', '--'), 'bdpt-lt': ('tab:pink', 'D', '--'),
    'path': ('tab:blue', 'o', '-'), 'ptracer': ('tab:cyan', 's', '-'),
    'mitsuba06-bdpt': ('tab:green', 'P', ':'), 'mitsuba06-path': ('tab:olive', 'X', ':'),
    'vcm': ('black', '*', '-'), 'vm': ('tab:gray', 'h', '-.'), 'auto': ('goldenrod', 'd', '-'),
}
# issue 22's equal-time targets for `auto` (relMSE ratios): at most AUTO_BIDIR of path's where a bidirectional
# contestant beats path, at most AUTO_PT where path is best, and within AUTO_BEST of the best fixed contestant
AUTO_BIDIR, AUTO_PT, AUTO_BEST = 1.0, 1.1, 1.25
FIXED = ('bdpt', 'vcm', 'vm', 'bdpt-pt', BASELINE)      # the fixed techniques auto is measured against


# ------------------------------------------------------------------------------------------ numbers

def fmt(x, digits=3):
    if x == 0:
        return '0'
    if 1e-3 <= abs(x) < 1e4:
        return f'{x:.{digits}g}'
    return f'{x:.{digits - 1}e}'


def quotable(value, ref_error):
    return value > 0 and ref_error <= QUOTABLE * value


def qfmt(value, ref_error):
    """A figure, or in parentheses with a dagger where the reference's own error is too large to quote it."""
    return fmt(value) if quotable(value, ref_error) else f'({fmt(value)})†'


def ref_err(res, key, field='rel'):
    """The expected error of the reference `key`'s errors are measured against (Mitsuba 0.6's own for its
    contestants): a figure is quotable only well above it."""
    return res[res.get('reference_of', {}).get(key, 'reference')][f'expected_{field}']


def table(header, rows):
    out = ['| ' + ' | '.join(header) + ' |', '|' + '|'.join('---' for _ in header) + '|']
    out += ['| ' + ' | '.join(str(c) for c in row) + ' |' for row in rows]
    return '\n'.join(out)


def finite_json(obj):
    """Fails on a NaN or infinity anywhere in the figures (json would write them as bare NaN)."""
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        if not math.isfinite(float(obj)):
            raise FloatingPointError('non-finite figure in the results')
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


# ------------------------------------------------------------------------------------------ images

def srgb(x):
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(img, scale, region=None):
    out = srgb(img * scale)
    if region is not None:
        out = np.where(region[:, :, None], out, out * 0.25)
    return out


def crop_box(shape, frac):
    h, w = shape[:2]
    x0, y0, x1, y1 = frac
    return int(round(x0 * w)), int(round(y0 * h)), max(int(round(x1 * w)), int(round(x0 * w)) + 1), \
        max(int(round(y1 * h)), int(round(y0 * h)) + 1)


def plot_crops(res, images, contestants, path):
    spec = res['spec']
    ref = images['crops']['reference']
    region = images['region'] if spec['reference'] == 'light' else None
    lum = ref.mean(axis=2)[region] if region is not None and region.any() else ref.mean(axis=2)
    white = float(np.quantile(lum, 0.98))
    scale = 1.0 / (white if white > 0 else max(float(lum.max()), 1e-8))
    x0, y0, x1, y1 = crop_box(ref.shape, spec['crop'])
    et = res['equal_time']['points']
    panels = [('reference (full image)', None), ('reference', 'reference')] + \
             [(c.label, c.key) for c in contestants]
    ncol = 5
    nrow = (len(panels) + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.6 * ncol, 3.1 * nrow))
    axes = np.atleast_1d(axes).ravel()
    for ax in axes:
        ax.axis('off')
    for ax, (title, key) in zip(axes, panels):
        if key is None:
            ax.imshow(tonemap(ref, scale, region), interpolation='nearest')
            ax.add_patch(Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, ec='yellow', lw=1.2))
        else:
            img = images['crops'][key]
            reg = region[y0:y1, x0:x1] if region is not None else None
            ax.imshow(tonemap(img[y0:y1, x0:x1], scale, reg), interpolation='nearest')
            if key != 'reference':
                p = et[key]
                title = f"{title}\n{p['spp']} spp, {p['time']:.2f} s, relMSE {fmt(p['rel'])}" + \
                    (f", FLIP {fmt(p['flip'])}" if 'flip' in p else '')
            else:
                title = f"{title}\n{res['reference']['kind']}"
        ax.set_title(title, fontsize=7.5)
    fig.suptitle(f"{spec['title']}: crops at equal time ({res['equal_time']['budget_s']:g} s budget)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_errors(res, contestants, path):
    spec = res['spec']
    ref = res['reference']
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    for ax, field, name in ((axes[0], 'rel', 'relative MSE'), (axes[1], 'mse', 'MSE'),
                            (axes[2], 'flip', f"FLIP (LDR, exposure {ref.get('flip_exposure', 0):.3g})")):
        for c in contestants:
            pts = sorted(res['sweep'][c.key], key=lambda p: p['time'])
            t = np.array([p['time'] for p in pts])
            e = np.array([p.get(field, np.nan) for p in pts])
            color, marker, ls = STYLE.get(c.key, ('k', 'o', '-'))
            ax.plot(t, e, ls, color=color, lw=1.2, label=c.label)
            ok = np.array([field == 'flip' or quotable(v, ref_err(res, c.key, field)) for v in e])
            ax.plot(t[ok], e[ok], marker, color=color, ms=5, ls='none')
            ax.plot(t[~ok], e[~ok], marker, color=color, ms=5, ls='none', mfc='none')
        if field == 'flip':                 # FLIP has no expected error of the reference to draw
            ax.set_xscale('log')
            ax.set_yscale('log')
            ax.set_xlabel('render time (s, median, after warm-up)')
            ax.set_ylabel(name)
            ax.grid(True, which='both', alpha=0.3)
            continue
        ax.axhline(ref[f'expected_{field}'], color='k', ls=':', lw=1, label="reference's own error")
        ax.axhline(ref[f'expected_{field}'] / QUOTABLE, color='grey', ls='--', lw=0.8, label='quotable above')
        if res.get('reference06'):
            ax.axhline(res['reference06'][f'expected_{field}'], color='tab:green', ls=':', lw=1,
                       label="Mitsuba 0.6 reference's own error")
        ax.axvline(res['equal_time']['budget_s'], color='grey', ls='-.', lw=0.8)
        ax.set_xscale('log')
        ax.set_yscale('log')
        ax.set_xlabel('render time (s, median, after warm-up)')
        ax.set_ylabel(name)
        ax.grid(True, which='both', alpha=0.3)
    axes[0].legend(fontsize=7, loc='lower left')
    where = '' if spec.get('user') else f" ({spec['file']})"         # a user's scene has its file in its title
    fig.suptitle(f"{spec['title']}{where}: error against time; hollow markers: not quotable", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_summary(results, contestants, path):
    fig, ax = plt.subplots(figsize=(10, 3.8))
    n = len(contestants)
    width = 0.8 / n
    for j, c in enumerate(contestants):
        vals = []
        for r in results:
            et = r['equal_time']['points']
            vals.append(et[c.key]['rel'] / et[BASELINE]['rel'])
        color = STYLE.get(c.key, ('k',))[0]
        ax.bar(np.arange(len(results)) + (j - n / 2 + 0.5) * width, vals, width, color=color, label=c.label)
    ax.axhline(1.0, color='k', lw=0.8)
    ax.set_yscale('log')
    ax.set_xticks(np.arange(len(results)))
    ax.set_xticklabels([r['spec']['key'] for r in results])
    ax.set_ylabel('relMSE / Mitsuba path (equal time)')
    ax.legend(fontsize=7, ncol=4)
    ax.grid(True, axis='y', which='both', alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------------ markdown

def ratio_cell(res, key, field='rel'):
    """A contestant's error at equal time over `path`'s, each quotable against its own reference."""
    et = res['equal_time']['points']
    r = et[key][field] / et[BASELINE][field]
    ok = quotable(et[key][field], ref_err(res, key, field)) and quotable(et[BASELINE][field],
                                                                          ref_err(res, BASELINE, field))
    return (f'{r:.3g}' if ok else f'({r:.3g})†'), r, ok


def verdict(res, contestants):
    spec = res['spec']
    et = res['equal_time']['points']
    b, p = et['bdpt'], et[BASELINE]
    cell, r, ok = ratio_cell(res, 'bdpt')
    _, r_mse, ok_mse = ratio_cell(res, 'bdpt', 'mse')
    best = min(contestants, key=lambda c: et[c.key]['rel'])
    figures = (f"relMSE {fmt(b['rel'])} ± {fmt(b['rel_se'])} ({b['spp']} spp, {b['time']:.2f} s) against "
               f"path's {fmt(p['rel'])} ± {fmt(p['rel_se'])} ({p['spp']} spp, {p['time']:.2f} s): ratio {r:.3g}"
               f"{'' if ok else ' (not quotable)'}; in MSE {fmt(b['mse'])} against {fmt(p['mse'])}: ratio "
               f"{r_mse:.3g}{'' if ok_mse else ' (not quotable)'}")
    if not ok:
        head = 'cannot be decided at this reference quality (the reference\'s own error is not well below the figures)'
    elif r < 1:
        head = '`bdpt` (power) **beats** Mitsuba `path` at equal time'
    else:
        head = '`bdpt` (power) **does not beat** Mitsuba `path` at equal time'
    extra = f"; the lowest relMSE at this budget: {best.label}" if best.key != 'bdpt' else ''
    if ok and ok_mse and (r < 1) != (r_mse < 1):
        extra += ('; relMSE and MSE disagree' + (" (path is biased here: it misses the sun's caustics)"
                                                  if spec['reference'] == 'light' else ''))
    if 'mitsuba06-bdpt' in et:
        m = et['mitsuba06-bdpt']
        cell06, _, _ = ratio_cell(res, 'mitsuba06-bdpt')
        extra += (f"; Mitsuba 0.6's bdpt: relMSE {fmt(m['rel'])} ({m['spp']} spp, {m['time']:.2f} s, against its own "
                  f"reference): ratio to path {cell06}, `bdpt`'s relMSE / its {b['rel'] / m['rel']:.3g}")
    return f"- **{spec['title']}** (`{scene_file(spec)}`): {head}: {figures}{extra}."


def pair_ratio(res, a, b, field='rel'):
    """Contestant a's error at equal time over contestant b's: (cell, ratio, quotable)."""
    et = res['equal_time']['points']
    r = et[a][field] / et[b][field]
    ok = quotable(et[a][field], ref_err(res, a, field)) and quotable(et[b][field], ref_err(res, b, field))
    return (f'{r:.3g}' if ok else f'({r:.3g})†'), r, ok


def ranking(res, contestants):
    """Contestants by relMSE at equal time, lowest first."""
    et = res['equal_time']['points']
    return sorted(contestants, key=lambda c: et[c.key]['rel'])


def wins_table(results, contestants, names):
    """Per scene: the contestant with the lowest relMSE at equal time, the runner-up, and how far apart."""
    rows = []
    for r in results:
        order = ranking(r, contestants)
        et = r['equal_time']['points']
        first, second = order[0], order[1] if len(order) > 1 else order[0]
        cell, _, _ = pair_ratio(r, second.key, first.key)
        rows.append([r['spec']['key'], names[first.key], names[second.key], cell,
                     ' < '.join(names[c.key] for c in order)])
    return table(['scene', 'lowest relMSE', 'runner-up', 'runner-up / lowest', 'order of relMSE (equal time)'], rows)


def wins_lines(results, contestants, names, close=1.2):
    """Per contestant: the scenes where it has the lowest relMSE at equal time, and those where it is within
    `close` of the lowest."""
    out = []
    for c in contestants:
        best, near = [], []
        for r in results:
            order = ranking(r, contestants)
            et = r['equal_time']['points']
            if order[0].key == c.key:
                best.append(r['spec']['key'])
            elif et[c.key]['rel'] <= close * et[order[0].key]['rel']:
                near.append(r['spec']['key'])
        text = f"- {names[c.key]}: lowest on " + (', '.join(best) if best else 'none of these scenes')
        if near:
            text += f"; within {close:g}x of the lowest on {', '.join(near)}"
        out.append(text + '.')
    return out


def vcm_rows(results, contestants):
    """Issue 15's targets: per scene, vcm's and vm's relMSE ratios to path and to bdpt at equal time, the
    target where the scene states one, and whether it is met."""
    keys = {c.key for c in contestants}
    rows, verdicts = [], []
    for r in results:
        spec = r['spec']
        kind = spec.get('vcm_target', '')
        row = [spec['key'], {'caustic': 'yes: a caustic scene', 'plain': 'none'}.get(kind, 'a few (no target)')]
        for a, b in (('vcm', BASELINE), ('vm', BASELINE), ('bdpt', BASELINE), ('vcm', 'bdpt'), ('vm', 'bdpt')):
            row.append(pair_ratio(r, a, b)[0] if a in keys and b in keys else '–')
        target, met = '–', '–'
        if 'vcm' in keys and kind in ('caustic', 'plain'):
            other, bound = (BASELINE, VCM_CAUSTIC) if kind == 'caustic' else ('bdpt', VCM_PLAIN)
            _, ratio, ok = pair_ratio(r, 'vcm', other)
            target = f"vcm / {'path' if other == BASELINE else 'bdpt'} <= {bound:g}"
            met = ('yes' if ratio <= bound else 'no') if ok else 'undecided'
            verdicts.append((spec, met, ratio, target))
        rows.append(row + [target, met])
    header = ['scene', 'S-D-S paths', 'vcm / path', 'vm / path', 'bdpt / path', 'vcm / bdpt', 'vm / bdpt', 'target',
              'met']
    return table(header, rows), verdicts


def auto_rows(results, contestants):
    """Issue 22's targets: per scene, auto's relMSE ratio to path and to the best fixed contestant at
    equal time, which targets apply and whether they are met, and what auto chose at that point."""
    keys = {c.key for c in contestants}
    fixed = [k for k in FIXED if k in keys]
    rows = []
    for r in results:
        et = r['equal_time']['points']
        best = min(fixed, key=lambda k: et[k]['rel'])
        bidir = best != BASELINE and best != 'bdpt-pt'
        cell, ratio, ok = pair_ratio(r, 'auto', BASELINE)
        bcell, bratio, bok = pair_ratio(r, 'auto', best)
        bound = AUTO_BIDIR if bidir else AUTO_PT
        met = [('yes' if ratio <= bound else 'no') if ok else 'undecided',
               ('yes' if bratio <= AUTO_BEST else 'no') if bok else 'undecided']
        chose = next((c['chose'] for c in r.get('auto_choices', [])
                      if c['key'] == 'auto' and c['spp'] == et['auto']['spp']), [])
        rows.append([r['spec']['key'], cell, f"auto / path <= {bound:g}", met[0], f'{best}: {bcell}',
                     met[1], ', '.join(chose) or '–'])
    header = ['scene', 'auto / path', 'target', 'met', 'auto / best fixed', f'<= {AUTO_BEST:g}', 'auto chose']
    return table(header, rows)


def auto_lines(results, contestants):
    """Issue 22's targets for technique `auto`, scene by scene."""
    return ['### Technique `auto` (issue 22)', '',
            "`auto` chooses, in every render, the configuration of the estimator (path tracing, the classic "
            "estimator, light vertex caches, merging or not, per pixel) from a pilot's second-moment estimates and "
            "timed trials (docs/light-cache.md); its choice is inside its time. Targets at equal time: relMSE at "
            f"most {AUTO_BIDIR:g}x path's where a bidirectional contestant beats path, {AUTO_PT:g}x where path is "
            f"best, and within {AUTO_BEST:g}x of the best fixed contestant ({', '.join(FIXED)}, those run). "
            "'auto chose': each render at the equal-time point (a render that decided again lists its segments' "
            "choices joined by +). At each budget `auto` renders as `bdpt-jit render --time` does, until the budget "
            "has passed (its time not linear in its spp: each render decides afresh and may choose otherwise).", '',
            auto_rows(results, contestants), '']


def scene_file(spec):
    return spec['file'] if spec.get('user') else f"scenes/{spec['file']}"


def mitsuba06_line(status):
    """The report's line on Mitsuba 0.6: which binary, or that it was absent and why."""
    if status is None or not status.get('wanted'):
        return ("- Mitsuba 0.6: not among the contestants"
                + (f" ({status['how']})" if status and status.get('how') else '') + '.')
    if not status.get('used'):
        return (f"- Mitsuba 0.6: **absent**: {status['how']}. Its contestants ({', '.join(status['wanted'])}) are "
                "not in the tables and plots; build it with `python benchmarks/mitsuba06.py build --source DIR` "
                "and pass `--mitsuba06 DIR/dist`.")
    return (f"- Mitsuba 0.6: {status['how']}; {', '.join(status['wanted'])} render the scene's Mitsuba 0.6 form "
            "(`benchmarks/mitsuba06.py`) and are measured against a reference of 0.6's own `bdpt` (the converted "
            "scene differs from the Mitsuba 3 one by a few percent in places); times are 0.6's own \"Render time\" "
            "(process start and scene loading left out, as `mi.load_file` is for Mitsuba 3), and each render has "
            "its own sampler seed (the seed edit of `benchmarks/mitsuba06.py`).")


def absent_line(absent):
    """The report's line on contestants this bdpt_jit refused (vcm and vm before vertex merging landed)."""
    if not absent:
        return None
    return ('- **Absent** (this bdpt_jit refuses them): '
            + '; '.join(f'{label}: {why}' for label, why in absent.items()) + '.')


def contestant_text(c):
    extra = contestant_settings(c)
    text = f'{c.label} (`{json.dumps(c.props)}`'
    if extra:
        text += ', ' + ', '.join(f'{k} {v:g}' for k, v in extra.items()) + ' by default'
    if c.progressive:
        text += ', a fresh integrator per render'
    if c.budgeted:
        text += (f', at a budget one render stopped once the budget has passed (passes of {BUDGET_PASS_SPP} spp, '
                 'as `bdpt-jit render --time`; its spp the samples it rendered)')
    return text + (', Mitsuba 0.6)' if c.renderer == 'mitsuba06' else ')')


def section_markers(name):
    return f'<!-- compare.py --section {name}: begin (generated; rerun the command to replace) -->', \
        f'<!-- compare.py --section {name}: end -->'


def put_section(out_md, name, text):
    """Writes `text` into out_md between the section's markers: in place of an earlier run's section of that
    name, or appended to what the file holds (the rest of the file is kept as it is)."""
    begin, end = section_markers(name)
    block = f'{begin}\n\n{text.rstrip()}\n\n{end}\n'
    old = out_md.read_text() if out_md.exists() else ''
    i, j = old.find(begin), old.find(end)
    if i >= 0 and j > i:
        new = old[:i] + block + old[j + len(end):].lstrip('\n')
    else:
        new = old.rstrip('\n') + ('\n\n' if old.strip() else '') + block
    out_md.write_text(new)


def sections_of(text):
    """The --section blocks a report holds (markers included), in order: a full run keeps them."""
    out = []
    for m in re.finditer(r'<!-- compare\.py --section ([A-Za-z0-9_.-]+): begin', text):
        end = section_markers(m.group(1))[1]
        j = text.find(end, m.start())
        if j > 0:
            out.append(text[m.start():j + len(end)] + '\n')
    return out


def demote(lines, title):
    """The report as a section of another document: its title becomes `title` at level 2, its headings go one
    level down."""
    out = []
    for line in lines:
        if line.startswith('# '):
            out.append('## ' + title)
        elif line.startswith('#'):
            out.append('#' + line)
        else:
            out.append(line)
    return out


def header_lines(contestants, settings, info, command, elapsed, mitsuba06, absent):
    """The title, how the report was generated, the machine, the settings and the contestants."""
    used06 = any(c.renderer == 'mitsuba06' for c in contestants)
    dirty = ' (with uncommitted changes)' if info['dirty'] else ''
    L = ['# Comparison benchmarks: `bdpt` against Mitsuba 3' + (' and Mitsuba 0.6' if used06 else ''), '',
         f"Generated by `{command}` (**{settings.mode} mode**) on {info['date']} in {elapsed / 60:.1f} min.",
         '',
         f"- Machine: {info['cpu']}, {info['cores']} cores"
         + (f", {info['memory_gib']:.0f} GiB" if info['memory_gib'] else '') + f"; {info['os']}; "
         f"load average at the start {', '.join(f'{x:.2f}' for x in info['load_average'] or [])} "
         "(other work on the machine slows every contestant alike: they are interleaved).",
         f"- Versions: Mitsuba {info['mitsuba']}, Dr.Jit {info['drjit']}, variant `{info['variant']}`, "
         f"Python {info['python']}, NumPy {info['numpy']}; bdpt_jit at commit `{info['commit']}`{dirty}.",
         f"- Settings: {settings.res}x{settings.res} pixels; time budgets {', '.join(f'{b:g}' for b in settings.budgets)} s "
         f"(the last is the equal-time budget) after probes at {', '.join(map(str, settings.probe_spp))} spp; "
         f"{settings.repeats} timed renders per point after one warm-up render; references in "
         f"{settings.ref_batches} batches of {settings.ref_spp} spp times a per-scene factor (below); rays counted at "
         f"{settings.count_spp} spp" + (f"; Mitsuba 0.6's references in {settings.ref06_batches} batches of "
                                        f"{settings.ref06_spp} spp of its `bdpt`" if used06 else '') + '.',
         f"- Contestants, all with the scene's `max_depth` and `rr_depth` 5: "
         + ', '.join(contestant_text(c) for c in contestants) + '.',
         mitsuba06_line(mitsuba06)]
    return L + [line for line in (absent_line(absent),) if line] + ['']


def summary_lines(results, contestants, names, fig_dir, rel):
    """The equal-time ratios to `path` (relMSE and MSE), their plot, and the verdicts per scene."""
    L = ['## Summary: relative MSE at equal time, as a ratio to Mitsuba `path`', '',
         f"Each cell is a contestant's relative MSE divided by `path`'s, both rendered with the same wall-clock budget "
         f"(the last budget above; the exact times are in each scene's table). Below 1: lower error than `path`. "
         f"† marks a figure that is not quotable: the reference's own expected error exceeds {QUOTABLE:g} of it.", '']
    header = ['scene', 'budget (s)'] + [names[c.key] for c in contestants]

    def ratios(field):
        return table(header, [[r['spec']['key'], f"{r['equal_time']['budget_s']:g}"] +
                              [ratio_cell(r, c.key, field)[0] for c in contestants] for r in results])
    L += [ratios('rel'), '']
    L += ["The same for MSE (not normalised per pixel: bright pixels weigh most). The two can disagree where a "
          "contestant is biased: `path` misses the sun's caustics in the Figure 7 scenes, which costs it at most "
          "a relative error of 1 in each caustic pixel but a large absolute one.", '']
    L += [ratios('mse'), '']
    plot_summary(results, contestants, fig_dir / 'summary.png')
    L += [f"![equal-time ratios]({rel(fig_dir / 'summary.png')})", '']
    L += ['### Where `bdpt` wins and where it does not', '']
    focus = [r for r in results if r['spec']['focus']]
    others = [r for r in results if not r['spec']['focus']]
    if focus:
        L += ['Scenes where `bdpt` should win (caustics, indirect light):', '']
        L += [verdict(r, contestants) for r in focus] + ['']
    if others:
        L += ['The other scenes:', '']
        L += [verdict(r, contestants) for r in others] + ['']
    L += ['### Where each technique wins', '',
          'Per scene, the contestants ordered by relative MSE at equal time (lowest first), and how far the runner-up '
          'is behind the winner (its relMSE over the winner\'s; † where the reference cannot tell them apart).', '',
          wins_table(results, contestants, names), ''] + wins_lines(results, contestants, names) + ['']
    return L


def vcm_lines(results, contestants):
    """Issue 15's targets for `vcm` and `vm`, scene by scene."""
    vt, verdicts = vcm_rows(results, contestants)
    L = ['### Vertex connection and merging: `vcm` and `vm` (issue 15)', '',
         f"`vcm` is `bdpt` with every connection strategy plus vertex merging (Georgiev et al. 2012); `vm` merges "
         f"alone (progressive photon mapping: a merge at the first non-specular camera vertex). Both are "
         f"consistent, not unbiased: their merging radius shrinks pass by pass, and their error here includes "
         f"their bias. The issue's equal-time targets: relMSE at most {VCM_CAUSTIC:g} of `path`'s on scenes with "
         f"specular-diffuse-specular (S-D-S) paths (caustics seen through glass or in a mirror), and within "
         f"{VCM_PLAIN:g}x of `bdpt`'s on scenes without. Ratios of relMSE at equal time; † as above.", '',
         vt, '']
    for spec, met, ratio, target in verdicts:
        res = next(r for r in results if r['spec']['key'] == spec['key'])
        where = ''
        if res['reference']['kind'] == 'light':
            where = (f" Measured over the {res['reference']['region_fraction'] * 100:.0f}% of the pixels `ptracer` "
                     "renders, not the whole image: the pixels that see the glass (the sun's caustic seen through "
                     "it) have no reference here (no unbiased technique of Mitsuba 3 or bdpt_jit renders sun, "
                     "glass, diffuse, glass, camera), and `path`'s error is mostly its bias (the caustics it "
                     "misses), which no budget reduces; in MSE, vcm / path is "
                     f"{pair_ratio(res, 'vcm', BASELINE, 'mse')[0]}.")
        L.append(f"- **{spec['title']}** (`{scene_file(spec)}`): {target}: "
                 + {'yes': f'met ({ratio:.3g})', 'no': f'**not met** ({ratio:.3g})',
                    'undecided': f'cannot be decided at this reference quality ({ratio:.3g})'}[met] + '.' + where)
    return L + ['']


def compile_lines(results, jit, used06):
    """Compilation time of the Dr.Jit contestants over all scenes."""
    L = ['### Compile time, all scenes together', '',
         'Kernel compilation is kept out of the render times: every point starts with a warm-up render at its '
         'sample count, whose compilation Dr.Jit\'s kernel history records (LLVM codegen and backend). '
         '"New kernels per warm-up" counts kernels compiled or loaded from the disk cache, i.e. not already in '
         'memory: well above 0 means the contestant\'s kernels depend on the sample count, so every new sample '
         'count costs a compilation (or a disk-cache load when the benchmark ran before).'
         + (' Mitsuba 0.6 compiles nothing at run time: its contestants are not in these tables.' if used06 else ''),
         '']
    rows = []
    for c in jit:
        recs = [x for r in results for x in r['compile'][c.key]]
        firsts = [r['sweep'][c.key][0] for r in results]
        rows.append([c.label, len(recs), sum(x['compiled'] for x in recs),
                     f"{sum(x['compiled'] + x['from_disk'] for x in recs) / max(len(recs), 1):.2f}",
                     sum(x['from_disk'] for x in recs),
                     f"{sum(x['codegen_s'] + x['backend_s'] for x in recs):.2f}",
                     f"{sum(x['backend_s'] for x in recs) / max(sum(x['compiled'] for x in recs), 1):.3f}",
                     f"{np.mean([p['warmup_s'] - p['time'] for p in firsts]):.3f}"])
    return L + [table(['contestant', 'warm-up renders', 'kernels compiled', 'new kernels per warm-up',
                       'loaded from disk cache', 'codegen + backend (s)', 'backend per compiled kernel (s)',
                       'first render minus warm render (s, mean)'], rows), '']


def reference_lines(r):
    """How a scene's reference was made and its own expected error (and Mitsuba 0.6's reference)."""
    ref = r['reference']
    if ref['kind'] == 'light':
        L = [f"Reference: Mitsuba `ptracer`, {ref['spp_ptracer']} spp ({ref['batches']} batches). `path` cannot "
             f"be the reference here: it never hits the directional sun, so it misses the sun's caustics. Errors "
             f"are measured over the {ref['region_fraction'] * 100:.1f}% of the pixels whose footprint sees no "
             f"delta (mirror, glass) surface and no sky, where `ptracer` renders every path; the other pixels are "
             f"darkened in the crops. `path`'s error here includes its bias (the missing caustics)."]
    else:
        L = [f"Reference: Mitsuba `path` and `ptracer`, {ref['spp_path']} spp each ({ref['batches']} batches), "
             f"combined per pixel with inverse-variance weights from independent pilot renders "
             f"({ref['pilot']}; their variances averaged over {ref['weight_window']}x{ref['weight_window']} "
             f"pixels), `path` alone where a pixel's footprint sees a delta surface or nothing (where `ptracer` "
             f"cannot render every path); mean weight of `ptracer` {ref['ptracer_weight_mean']:.2f}. Errors over "
             f"the whole image."]
    how = 'cached' if ref['cached'] else 'rendered in %.0f s' % ref['render_s']
    L += ['', f"Reference's own expected error (the batch variance of its mean, averaged like the errors): MSE "
          f"{fmt(ref['expected_mse'])}, relMSE {fmt(ref['expected_rel'])} ({how}). "
          f"Contestants' errors include it; figures below {1 / QUOTABLE:g}x it are marked †."
          + (f" FLIP exposure: {ref['flip_exposure']:.4g} (the reference's 98th percentile maps to white)."
             if 'flip_exposure' in ref else ''), '']
    r06 = r.get('reference06')
    if r06:
        how06 = 'cached' if r06['cached'] else 'rendered in %.0f s' % r06['render_s']
        ag = r06['agreement']
        L += [f"Mitsuba 0.6's contestants are measured against 0.6's own `bdpt` at {r06['spp']} spp "
              f"({r06['batches']} batches, {how06}) over the same pixels: its expected MSE {fmt(r06['expected_mse'])}, "
              f"relMSE {fmt(r06['expected_rel'])}. Set beside the Mitsuba 3 reference: relMSE {fmt(ag['rel'])} where "
              f"their own errors account for {fmt(ag['expected_rel'])}, mean ratio {ag['mean_ratio']:.4f} (0.6 / 3)"
              + (': the converted scene differs from the Mitsuba 3 one' if ag['rel'] > 3 * ag['expected_rel'] else '')
              + (f". Each 0.6 render also spent a median {r['overhead06_s']:.2f} s starting and loading the scene "
                 f"(not in its time)" if r.get('overhead06_s') is not None else '') + '.', '']
    return L


def rays_cells(r, key, spp):
    """Rays, zero-contribution rays (millions) and their share, for `spp` samples per pixel."""
    w = r['reference']['res']
    ry = r['rays'][key]
    if ry is None:              # Mitsuba 0.6 counts no rays
        return ['–'] * 3
    n = w * w * spp
    tot, zero = ry['rays_per_sample'] * n, ry['zero_per_sample'] * n
    return [f'{tot / 1e6:.3g}', f'{zero / 1e6:.3g}', f"{100 * zero / tot if tot else 0:.1f}"]


def point_tables(r, contestants, names):
    """A scene's sweep (folded), its equal-samples table and its equal-time table."""
    L = ['<details><summary>All points of the sweep</summary>', '']
    rows = []
    for c in contestants:
        for p in r['sweep'][c.key]:
            rows.append([names[c.key], p['stage'], p['spp'], f"{p['time']:.3f}",
                         qfmt(p['mse'], ref_err(r, c.key, 'mse')), qfmt(p['rel'], ref_err(r, c.key)),
                         fmt(p['rel_se']), flip_cell(p)])
    L += [table(['contestant', 'point', 'spp', 'time (s)', 'MSE', 'relMSE', 'relMSE s.e.', 'FLIP'], rows), '',
          '</details>', '']
    es = r['equal_samples']
    L += [f"### Equal samples ({es['spp']} spp; the form of the paper's Table 1)", '']
    rows = []
    for c in contestants:
        p = es['points'][c.key]
        rows.append([names[c.key], p['spp'], qfmt(p['mse'], ref_err(r, c.key, 'mse')),
                     qfmt(p['rel'], ref_err(r, c.key)), flip_cell(p), f"{p['time']:.3f}"]
                    + rays_cells(r, c.key, p['spp']))
    L += [table(['contestant', 'spp', 'MSE', 'relMSE', 'FLIP', 'time (s)', 'rays (M)', 'zero-contribution rays (M)',
                 'zero (%)'], rows), '']
    et = r['equal_time']
    L += [f"### Equal time ({et['budget_s']:g} s budget; the form of the paper's Tables 2 and 3)", '']
    rows = []
    for c in contestants:
        p = et['points'][c.key]
        rows.append([names[c.key], p['spp'], f"{p['time']:.3f}", qfmt(p['mse'], ref_err(r, c.key, 'mse')),
                     qfmt(p['rel'], ref_err(r, c.key)), fmt(p['rel_se'])] + rays_cells(r, c.key, p['spp'])
                    + [flip_cell(p), ratio_cell(r, c.key)[0]])
    L += [table(['contestant', 'spp', 'time (s)', 'MSE', 'relMSE', 'relMSE s.e.', 'rays (M)',
                 'zero-contribution rays (M)', 'zero (%)', 'FLIP', 'relMSE / path'], rows), '']
    return L + denoised_lines(r, contestants, names)


def flip_cell(p):
    """A point's mean FLIP (results.json of runs before FLIP have none)."""
    return fmt(p['flip']) if 'flip' in p else '–'


def denoised_lines(r, contestants, names):
    """--denoise: each contestant's equal-time image, noisy and denoised, in relMSE and FLIP."""
    d = r.get('denoised')
    if not d:
        return []
    pts = d['points']
    st = d['settings']
    base = pts[BASELINE]['denoised']['rel']
    L = [f"### Denoised at equal time ({r['equal_time']['budget_s']:g} s budget)", '',
         f"Each contestant's last timed render at the budget, denoised by {st.get('denoiser', '?')} on the "
         f"{st.get('device', '?')} ({st.get('filter', '?')} filter, HDR, quality {st.get('quality', '?')}) with the "
         f"albedo and normal of one feature pass at {d['feature_spp']} spp ({d['feature_s']:.2f} s), shared by every "
         f"contestant; the denoiser's time is not in the budget. Noisy and denoised figures are of that one image "
         f"(the tables above average every render of the point).", '']
    rows = []
    for c in contestants:
        p = pts[c.key]
        rows.append([names[c.key], p['spp'], f"{p['time']:.3f}", fmt(p['noisy']['rel']), fmt(p['denoised']['rel']),
                     fmt(p['noisy']['flip']), fmt(p['denoised']['flip']), f"{p['denoise_s']:.3f}",
                     f"{p['denoised']['rel'] / base:.3g}" if base > 0 else '–'])
    return L + [table(['contestant', 'spp', 'time (s)', 'relMSE noisy', 'relMSE denoised', 'FLIP noisy',
                       'FLIP denoised', 'denoiser (s)', 'denoised relMSE / path denoised'], rows), '']


def scene_compile_lines(r, jit, names):
    """A scene's compilation table (the Dr.Jit contestants)."""
    L = ['### Compile time (apart from render time)', '']
    rows = []
    for c in jit:
        recs = r['compile'][c.key]
        first = r['sweep'][c.key][0]
        rows.append([names[c.key], len(recs), sum(x['kernels'] for x in recs),
                     sum(x['compiled'] for x in recs), sum(x['from_disk'] for x in recs),
                     f"{sum(x['codegen_s'] for x in recs):.3f}", f"{sum(x['backend_s'] for x in recs):.3f}",
                     f"{first['warmup_s']:.3f}", f"{first['time']:.3f}"])
    return L + [table(['contestant', 'warm-up renders', 'kernels launched', 'compiled', 'loaded from disk cache',
                       'codegen (s)', 'LLVM backend (s)', f"first render at {r['sweep'][jit[0].key][0]['spp']} spp (s)",
                       'same, warm (s)'], rows), '']


def scene_lines(r, images, contestants, names, jit, fig_dir, rel):
    """One scene's part of the report: reference, error plot, tables and crops."""
    spec = r['spec']
    key = spec['key']
    L = [f"## {spec['title']} (`{scene_file(spec)}`)", '', f"What it tests: {spec['tests']}. "
         f"max_depth {spec['max_depth']}. Measured in {r['seconds']:.0f} s.", '']
    L += reference_lines(r)
    plot_errors(r, contestants, fig_dir / f'{key}-error.png')
    L += [f"![error against time]({rel(fig_dir / f'{key}-error.png')})", '']
    L += point_tables(r, contestants, names)
    L += scene_compile_lines(r, jit, names)
    plot_crops(r, images[key], contestants, fig_dir / f'{key}-crops.png')
    return L + [f"![crops]({rel(fig_dir / f'{key}-crops.png')})", '']


def method_lines(settings, used06):
    """How every figure of the report is measured."""
    return ['## Method', '',
            '- **Error metrics.** MSE: mean over the measured pixels and the three channels of (image - reference)^2. '
            f'Relative MSE: the same terms divided by reference^2 + eps, eps = ({EPS_REL:g} m)^2 with m the mean of '
            'the reference over the measured pixels (so that dark pixels do not dominate). Each point averages the '
            'errors of all its renders (the warm-up and the timed repeats, each with its own seed); "s.e." is the '
            'standard error of that average (large where a contestant is heavy-tailed).',
            '- **FLIP.** NVIDIA\'s FLIP (package `flip_evaluator`, its LDR mode at its default 67 pixels per degree) '
            'of each render against the reference, both tone-mapped the same way: linear radiance times the scene\'s '
            'exposure (the scale that maps the 98th percentile of the reference\'s luminance over the measured pixels '
            'to white, stated per scene), clamped to [0, 1], sRGB-encoded; the mean of its error map over the measured '
            'pixels (over the whole image, flip_evaluator\'s own mean). Averaged over a point\'s renders like the '
            'MSE. FLIP has no quotability mark: the reference\'s own noise is not separated from it.',
            "- **References.** Rendered once per scene, mode and scene file, and cached under `benchmarks/cache/` "
            "(keyed by the scene file's hash, resolution, depth and sample counts). Their own remaining error is the "
            "variance of their mean estimated from independent batches, summed over the measured pixels: a contestant's "
            "measured error is its own error plus this (they are independent), so a figure is quoted only where the "
            f"reference's error is below {QUOTABLE:g} of it; otherwise it is shown in parentheses with †. Batch "
            "variances underestimate heavy tails (caustics seen through `path`), so where a pixel relies on `path` for "
            "a caustic, the estimate is optimistic.",
            '- **Time.** Wall clock of `mi.render` with `dr.sync_thread()` before the clock stops, the median of the '
            'timed renders after one warm-up render at the same spp (kernels depend on the sample count). Each '
            'contestant\'s spp for a budget comes from a linear fit of time against spp over its earlier points, so '
            'the achieved times differ a little from the budgets; the tables give them. Contestants are interleaved '
            'render by render.',
            '- **Compile time.** From Dr.Jit\'s kernel history during the warm-up renders: LLVM codegen and backend '
            'time of every kernel launched; "loaded from disk cache" counts kernels found in `~/.drjit` (compiled '
            'in an earlier run), whose backend time is only the load. The Python tracing of the kernels is in every '
            'render and so in the render times.',
            "- **Rays.** `bdpt`: its `statistics` counters. Mitsuba's `path` and `ptracer` count no rays, so "
            '`benchmarks/raycount.py` replays their random walks (same sampling and Russian roulette decisions as '
            "Mitsuba 3.9.1's C++) and counts the same categories; zero-contribution rays are extension rays that leave "
            'the scene and blocked shadow rays (a shadow ray to the back of a one-sided light counts as a ray, not as a '
            f'zero-contribution one). Counted at {settings.count_spp} spp and scaled to each table\'s spp.',
            '- **Crops.** The last timed render of each contestant at the equal-time budget, same exposure as the '
            'reference (its 98th percentile maps to white), sRGB.',
            *(["- **Mitsuba 0.6.** Built from its public repository by `benchmarks/mitsuba06.py build` (Python 3 SCons, "
               "OpenEXR 3, GLEW without MX, Boost 1.74, and a `seed` parameter for its `independent` sampler, whose "
               "fixed seed would otherwise make repeated renders identical draws); scenes converted by "
               "`benchmarks/mitsuba06.py` (camelCase parameters, float32 OpenEXR without banner, `maxDepth` = "
               "`max_depth`, `rrDepth` 5). Each render is a `mitsuba` process on all cores; its time is the \"Render "
               "time\" it logs. Its errors are measured against its own `bdpt` reference, its ratios divided by "
               "Mitsuba 3 `path`'s error against the Mitsuba 3 reference. It counts no rays ('–' in the tables)."]
              if used06 else []),
            '']


def write_report(results, images, contestants, settings, info, out_md, fig_dir, command, elapsed, mitsuba06=None,
                 absent=None, section=None):
    """Writes the report to out_md, or with `section` (a name) as a section of out_md: between markers,
    replacing an earlier run's section of that name and keeping the rest of the file. A full report keeps
    the sections the file held (appended after it)."""
    out_md = Path(out_md)
    fig_dir = Path(fig_dir)
    fig_dir.mkdir(parents=True, exist_ok=True)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    rel = lambda p: os.path.relpath(p, out_md.parent).replace(os.sep, '/')  # noqa: E731
    names = {c.key: c.label for c in contestants}
    jit = [c for c in contestants if c.renderer == 'mitsuba3']      # the contestants Dr.Jit compiles kernels for
    used06 = any(c.renderer == 'mitsuba06' for c in contestants)
    L = header_lines(contestants, settings, info, command, elapsed, mitsuba06, absent)
    L += summary_lines(results, contestants, names, fig_dir, rel)
    if {'vcm', 'vm'} & set(names):
        L += vcm_lines(results, contestants)
    if 'auto' in names and BASELINE in names:
        L += auto_lines(results, contestants)
    L += compile_lines(results, jit, used06)
    for r in results:
        L += scene_lines(r, images, contestants, names, jit, fig_dir, rel)
    L += method_lines(settings, used06)
    L += [f"Raw figures: [`{rel(fig_dir / 'results.json')}`]({rel(fig_dir / 'results.json')}).", '']
    if section:
        put_section(out_md, section, '\n'.join(demote(L, f"Section `{section}`: {L[0].lstrip('# ')}")))
    else:
        kept = sections_of(out_md.read_text()) if out_md.exists() else []
        out_md.write_text('\n'.join(L) + ''.join('\n' + block for block in kept))
    with open(fig_dir / 'results.json', 'w') as f:
        json.dump(finite_json({'settings': settings.__dict__, 'machine': info, 'command': command,
                               'elapsed_s': elapsed, 'mitsuba06': mitsuba06, 'scenes': results}),
                  f, indent=1, allow_nan=False)
