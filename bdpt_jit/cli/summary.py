"""What the command reports about a render: the statistics (the EXR's ``bdpt.*`` header keys,
in order) and the summary printed from them."""

import os

from .errors import PROG

HEADER_PREFIX = 'bdpt.'


def header(stats):
    """The EXR header attributes: every statistic under ``bdpt.``."""
    return {HEADER_PREFIX + k: v for k, v in stats.items()}


def features(info):
    """(name, needed?, why) for the parts of the integrator a scene may leave out."""
    if not info:
        return []
    return [
        ('light subpath pass', bool(info.get('light_pass')), 'needed by the light-tracing, connection and merging strategies'),
        ('camera subpath pass', bool(info.get('camera_pass')), 'needed by the s=0, s=1, connection and merging strategies'),
        ('delta (specular) BSDF handling', bool(info.get('delta_handling')), 'the scene has a BSDF with a delta lobe'),
        ('participating media', 'media' in info, 'the scene has a medium: distance sampling, transmittance on every edge'),
        ('heterogeneous media tracking', bool(info.get('media', {}).get('heterogeneous')),
         'delta and ratio tracking with the majorant'),
    ]


def _fmt_count(n):
    return f"{int(n):,}"


def statistics(args, res, settings, variant, scene_path, defines, wall_s):
    """Ordered (key, value) pairs: the header attributes and the source of the summary.
    ``res``: rendering.Result; ``settings``: the integrator's parameter values."""
    import drjit as dr
    import mitsuba as mi
    from .. import __version__
    stats = {'integrator': args.integrator}
    for k, v in settings.items():
        stats[f'param.{k}'] = 'automatic' if v is None else str(v).lower() if isinstance(v, bool) else v
    stats['spp'] = f'{res.spp:g}'
    if args.time is not None:
        stats['time_budget_s'] = f'{args.time:g}'
        stats['pass_spp'] = args.pass_spp
    else:
        stats['spp_requested'] = res.spp_requested
    stats['passes'] = res.passes
    stats['seed'] = args.seed
    stats['interrupted'] = 'true' if res.interrupted else 'false'
    stats['scene'] = os.path.abspath(scene_path)
    stats['defines'] = ' '.join(f'{k}={v}' for k, v in defines.items())
    stats['variant'] = variant
    stats['version.bdpt_jit'] = __version__
    stats['version.mitsuba'] = mi.__version__
    stats['version.drjit'] = dr.__version__
    stats['resolution'] = f'{res.image.shape[1]}x{res.image.shape[0]}'
    stats['wall_time_s'] = f'{wall_s:.3f}'
    stats['render_time_s'] = f'{res.render_s:.3f}'
    stats['compile_time_s'] = f'{res.kernels.compile_ms / 1000:.3f}'
    stats['longest_pass_s'] = f'{res.longest_pass_s:.3f}'
    stats['kernels'] = res.kernels.launched
    stats['kernels_compiled'] = res.kernels.compiled
    samples = int(round(res.spp * res.n_pixels))
    stats['samples'] = samples
    stats['msamples_per_s'] = f'{samples / res.render_s / 1e6:.4f}' if res.render_s > 0 else '0'
    for k, v in (res.rays or {}).items():
        stats[f'rays.{k}'] = v
    if args.integrator == 'bdpt' and res.info:
        stats.update(_bdpt_statistics(res.info))
    if res.layers is not None:
        stats['layers'] = ' '.join(res.layers)
    stats.update(getattr(res, 'cluster_stats', None) or {})     # --cluster: cluster.* (cluster.py)
    return stats


def _bdpt_statistics(info):
    """The strategies and integrator parts a bdpt render used, from its last_render_info."""
    from ..strategies import StrategySet
    used = list(info.get('strategies', []))
    feats = features(info)
    stats = {
        'strategies': '; '.join(used),
        'strategies_left_out': '; '.join(s for s in StrategySet.every_strategy() if s not in used),
        'features': '; '.join(n for n, on, _ in feats if on),
        'features_left_out': '; '.join(n for n, on, _ in feats if not on),
    }
    if 'light_vertex_levels' in info:
        stats['light_vertex_levels'] = info['light_vertex_levels']
    if 'light_cache' in info:              # light_paths > 0 (light_cache.py)
        lc = info['light_cache']
        c = lc['connections']
        stats['light_cache'] = (f"{lc['light_paths_per_sample']:g} light subpaths per camera sample, {c} "
                                f"connection{'' if c == 1 else 's'} per camera vertex, "
                                f"{lc['pilot_vertices_per_path']:.3g} vertices per light subpath (pilot)")
    media = info.get('media', {})
    if 'real_collisions' in media:         # statistics with media (media.py)
        stats['media'] = (f"{media['real_collisions']:,} real collisions, {media['null_collisions']:,} null collisions, "
                          f"{media['medium_inconsistencies']:,} connections refused (their ends disagree about the medium)")
        if media.get('beam_paths') is not None:     # merges inside media by beams (beams.py)
            stats['media'] += f"; beams gathered from {media['beam_paths']:,} light subpaths an iteration"
    if media.get('around_sensor', media.get('sensor')) != media.get('sensor'):     # media_path.around_sensor
        stats['sensor_medium'] = (f"the sensor declares {media['sensor'] or 'no medium'} but lies in "
                                  f"{media['around_sensor'] or 'vacuum'} by the shapes' declarations: its rays "
                                  "travel in its own up to their first medium boundary, as Mitsuba's volpath renders it")
    if 'auto' in info:                     # technique auto (auto.py)
        a = info['auto']
        decided = a.get('decisions', [])
        steps = '' if len(decided) < 2 else ' (decided {} times: {})'.format(len(decided), ', '.join(
            f"{d['chosen']} {d['spp']:.4g} spp weight {d['weight']:.3g} after {d['seconds']:.2f} s" for d in decided))
        cut = ('' if not a.get('decisions_cut') else
               f" ({a['decisions_cut']} cut at half the time budget: the choice among the candidates timed by then)")
        stats['auto'] = (f"chose {a['chosen']} after {a['trial_s']:.2f} s of pilot and trials{cut}{steps}; predicted relMSE at "
                         "1 spp x s/spp: " + ', '.join(
                             f"{c['name']} {c['relmse_1spp']:.3g} x "
                             + ('not timed' if c['seconds_per_spp'] is None else f"{c['seconds_per_spp']:.3g}")
                             + (f" (misses {c['missed']:.1%})" if c['efficiency'] == 0 else '')
                             for c in a['candidates']))
        fit = a.get('cost_model')
        if fit:                             # auto.cost_fit
            stats['auto'] += ("; cost model (s/spp): {a:.3g} + {b:.3g} n_L/n + {d:.3g} c".format(**fit)
                              + (", merging + {e:.3g} + {g:.3g} n_L/n".format(**fit) if fit['merging'] else '')
                              + f", from {', '.join(fit['points'])}")
    return stats


def print_summary(stats, res, out, png):
    """The summary on stdout (unless -q)."""
    p = print
    params = ', '.join(f"{k[6:]}={v}" for k, v in stats.items() if k.startswith('param.'))
    p(f"{PROG}: {stats['scene']}")
    p(f"  integrator      {stats['integrator']}" + (f" ({params})" if params else ''))
    budget = (f", time budget {stats['time_budget_s']} s in passes of {stats['pass_spp']} spp"
              if 'time_budget_s' in stats else '')
    p(f"  image           {stats['resolution']}, {stats['spp']} spp reached in {stats['passes']} "
      f"pass{'es' if res.passes != 1 else ''}{budget}, seed {stats['seed']}, {stats['variant']}")
    wall, rend, comp = float(stats['wall_time_s']), float(stats['render_time_s']), float(stats['compile_time_s'])
    p(f"  time            wall {wall:.2f} s, render {rend:.2f} s, of which JIT compile {comp:.2f} s "
      f"({stats['kernels_compiled']} of {stats['kernels']} kernel launches compiled, the rest cached)")
    speed = f"{float(stats['msamples_per_s']):.4g} M samples/s"
    if rend - comp > 0.05 * rend and comp > 0:
        speed += f" ({stats['samples'] / (rend - comp) / 1e6:.4g} M samples/s without compiling)"
    p(f"  speed           {speed}; {_fmt_count(stats['samples'])} samples")
    if res.rays:
        _print_rays(res.rays)
    if 'strategies' in stats:
        p(f"  strategies      {stats['strategies'] or 'none (nothing in the scene emits)'}")
        if stats['strategies_left_out']:
            p(f"  left out        {stats['strategies_left_out']}")
        for name, on, why in features(res.info):
            p(f"  {'needed' if on else 'left out':15} {name}" + (f" ({why})" if on else ''))
    for key in ('light_cache', 'auto', 'media', 'sensor_medium'):
        if key in stats:
            p(f"  {key.replace('_', ' '):15} {stats[key]}")
    if res.layers is not None:
        p(f"  layers          {len(res.layers)} strategy layers (weighted and unweighted) in the EXR")
    if any(k.startswith('denoise.') for k in stats):
        from ..denoise.command import summary_text
        p(f"  denoised        {summary_text(stats)}")
    for line in getattr(res, 'cluster_lines', ()):               # --cluster: chunks, nodes, overheads
        p(line)
    p(f"  wrote           {out}, {png}")


def _print_rays(r):
    total = r.get('rays', 0)
    zero = r.get('zero_contribution_rays', 0)
    pct = f" ({100.0 * zero / total:.1f}%)" if total else ''
    print(f"  rays traced     {_fmt_count(total)}: camera {_fmt_count(r.get('camera_rays', 0))}, "
          f"light {_fmt_count(r.get('light_rays', 0))}, shadow {_fmt_count(r.get('shadow_rays', 0))}")
    print(f"  zero-contrib.   {_fmt_count(zero)}{pct}: camera rays missed {_fmt_count(r.get('camera_rays_missed', 0))}, "
          f"light rays missed {_fmt_count(r.get('light_rays_missed', 0))}, shadow rays blocked "
          f"{_fmt_count(r.get('shadow_rays_blocked', 0))}")
