"""The integrator's parameters: one table that the plugin, its docstring, the command line
and the docs all read, so names, types, defaults and allowed values cannot drift apart."""

from dataclasses import dataclass
from typing import Any, Optional, Tuple


class ParameterError(ValueError):
    """A parameter of the ``bdpt`` integrator has a value it cannot take."""


@dataclass(frozen=True)
class Param:
    name: str
    type: type
    default: Any
    meaning: str
    choices: Optional[Tuple[str, ...]] = None
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    exclusive_minimum: bool = False      # the value must be > minimum (not >=)

    @property
    def type_name(self) -> str:
        return {int: 'int', bool: 'bool', str: 'string', float: 'float'}[self.type]

    @property
    def default_text(self) -> str:
        if self.default is None:
            return 'automatic'
        if self.type is bool:
            return 'true' if self.default else 'false'
        return str(self.default)


PARAMS = (
    Param('max_depth', int, -1,
          'Longest path in edges, as in Mitsuba\'s `path` (-1: no limit; 1: only emitters seen '
          'directly; 2: direct lighting). `bdpt` has the same expected image as `path` for every value.',
          minimum=-1),
    Param('rr_depth', int, 5,
          'Number of edges from which Russian roulette may end a camera or light subpath.',
          minimum=1),
    Param('mis', str, 'power',
          'Weighting of the strategies: `power` (power heuristic, beta=2, paper eq. 18), `balance` '
          '(beta=1), or `uniform` (each path weighted by 1 / the number of strategies that can '
          'sample it).',
          choices=('power', 'balance', 'uniform')),
    Param('technique', str, 'bdpt',
          'Strategies used: `bdpt` (all (s,t)), `pt` (camera subpaths only: s=0 and s=1), `lt` '
          '(light subpaths only: every t=1 strategy, directly visible emitters included), `vcm` '
          '(all of bdpt plus vertex merging: Georgiev et al. 2012, renders caustics seen through '
          'glass), `vm` (vertex merging alone: progressive photon mapping, Hachisuka et al. 2008, '
          'merging at the first non-specular camera vertex). `vcm` and `vm` are consistent, not '
          'unbiased: their bias vanishes as the merging radius shrinks over passes. `auto`: the most '
          'efficient of path tracing and bdpt\'s configurations (the classic estimator and light vertex '
          'caches, with and without merging everywhere where the scene has a glossy or delta BSDF, and '
          'with a delta BSDF the classic estimator merging behind delta vertices), by '
          'the second moments a pilot render estimates for each and their timed trials (Grittmann et '
          'al. 2022; docs/light-cache.md), among the caches of one light_paths also with connections '
          'and merging chosen per pixel; a long render decides again as it goes and combines its '
          'segments with inverse-variance weights; the choices in `last_render_info[\'auto\']`; '
          'consistent, as `vcm`, where it chose to merge.',
          choices=('bdpt', 'pt', 'lt', 'vcm', 'vm', 'auto')),
    Param('radius', float, 0.005,
          'Initial merging radius of `vcm` and `vm`, relative to the radius of the scene\'s bounding '
          'sphere (SmallVCM uses 0.003 at 512x512; a larger radius is less noisy and more biased).',
          minimum=0.0, exclusive_minimum=True),
    Param('radius_alpha', float, 0.75,
          'Progressive radius reduction of `vcm` and `vm`: iteration i (one sample per pixel, counted '
          'over every render of this integrator, from 1) merges within r_i = r_1 i^((alpha-1)/2) '
          '(Knaus and Zwicker 2011); 1 keeps the radius fixed.',
          minimum=0.0, maximum=1.0, exclusive_minimum=True),
    Param('merge_everywhere', bool, False,
          '`vcm`: merge at every non-specular camera vertex, as Georgiev et al. do. By default a '
          'camera vertex merges only where the camera reached it through a specular (delta) vertex: '
          'the specular-diffuse-specular paths that no connection samples all pass there, and a '
          'merge elsewhere only adds a gather beside a connection (in a scene without specular '
          'surfaces `vcm` then renders as `bdpt`). The MIS weights follow either choice.'),
    Param('media_merging', str, 'beams',
          '`vcm` and `vm` inside participating media: `beams` (each camera segment through a medium '
          'gathers the light vertices within the radius of it: Jarosz et al. 2011, point-beam 2D) or '
          '`points` (a ball around each camera vertex in a medium: point-point 3D). Beams need media whose '
          'sigma_t is the same in every channel; elsewhere merges are points (docs/media.md).',
          choices=('beams', 'points')),
    Param('beam_paths', int, None,
          '`vcm` and `vm` with `media_merging=beams`: the light subpaths of an iteration (one sample per '
          'pixel) whose medium vertices the beams gather, at most (0: all, one per pixel). A beam '
          'gathers along its whole segment, so at a fixed radius its time grows with the light '
          'subpaths while the rest of a sample\'s work does not; the MIS weights count the beams\' '
          'own. Automatic: 4096 in `vcm` (its other strategies share the paths beams sample), all in '
          '`vm` (where beams alone sample them); surface merges and balls use every light subpath '
          '(docs/media.md).',
          minimum=0),
    Param('light_paths', float, -1.0,
          'Light vertex cache (Davidovic et al. 2014): light subpaths a pass traces, as a ratio of its '
          'camera samples (e.g. 0.25, 1, 2; rounded to whole subpaths per pixel of an iteration); '
          'their vertices form one cache that every camera vertex draws `connections` vertices from, '
          'and every sample counts in the MIS weights (Veach 9.2.2: n_i p_i). -1: the classic '
          'estimator, one light subpath per camera sample connected to that sample\'s own vertices. '
          '`technique` bdpt, lt or vcm (merging with the n_L subpaths of each iteration), RGB and monochrome variants, no derivatives (docs/light-cache.md).',
          minimum=-1.0),
    Param('connections', int, -1,
          'With the light vertex cache (`light_paths` > 0): light vertices each camera vertex is '
          'connected to, drawn uniformly from all the pass\'s cached vertices. -1: as many as a '
          'light subpath stores on average (rounded, at least 1), measured by the pilot pass.',
          minimum=-1),
    Param('hide_emitters', bool, False,
          "Hide directly visible emitters: camera rays pass through the shapes of emitters, as Mitsuba "
          "3.9.1's `path` lets them, and an environment seen directly is black. In scenes with media the "
          "shapes stay (showing their BSDF, black without one): no emission where a camera ray meets one."),
    Param('strategy_images', bool, False,
          'Also accumulate one image per (s,t) strategy, weighted and unweighted, into '
          '`integrator.strategy_images` after a render (path lengths up to 8 one by one, longer '
          'ones in `other`; nearest-pixel, so with a box filter the weighted layers sum to the image).'),
    Param('statistics', bool, False,
          'Count rays traced and zero-contribution rays (extension rays that leave the scene, '
          'blocked shadow rays), as the paper\'s Table 1; reported in `integrator.last_render_info`.'),
    Param('aovs', str, '',
          "Extra channels from each camera ray's first hit, named as Mitsuba's `aov` integrator names "
          "them: `name:type` pairs separated by commas, types depth, position, uv, geo_normal, "
          "sh_normal, albedo (e.g. `dd:depth,nn:sh_normal,ab:albedo`; RGB and monochrome variants)."),
    Param('samples_per_pass', int, None,
          'Samples traced per kernel launch; bounds memory (light-vertex storage grows with it). '
          "Automatic: as many as fit a sixth of the machine's memory (on a GPU half its free memory), "
          'rounded to whole samples per pixel.',
          minimum=1),
)

PARAMS_BY_NAME = {p.name: p for p in PARAMS}


def _number(p: Param, value):
    """An int or float parameter's value, converted and within the row's bounds."""
    word = 'an integer' if p.type is int else 'a number'
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ParameterError(f"bdpt: parameter '{p.name}' must be {word}, got {value!r}")
    try:
        x = p.type(value)
    except ValueError:
        raise ParameterError(f"bdpt: parameter '{p.name}' must be {word}, got {value!r}") from None
    if p.type is int and isinstance(value, float) and x != value:
        raise ParameterError(f"bdpt: parameter '{p.name}' must be {word}, got {value!r}")
    low_ok = p.minimum is None or (x > p.minimum if p.exclusive_minimum else x >= p.minimum)
    high_ok = p.maximum is None or x <= p.maximum
    if not (low_ok and high_ok and x == x and abs(x) != float('inf')):
        bounds = [f"{'>' if p.exclusive_minimum else '>='} {p.minimum}"] if p.minimum is not None else []
        bounds += [f"<= {p.maximum}"] if p.maximum is not None else []
        finite = 'a finite number ' if p.type is float else ''
        raise ParameterError(f"bdpt: parameter '{p.name}' must be {finite}{' and '.join(bounds)}, got {x}")
    return x


def check_value(p: Param, value):
    """Validate one value against its row of the table; return it converted."""
    if p.type is bool:
        if isinstance(value, str) and value.lower() in ('true', 'false'):
            value = value.lower() == 'true'
        if not isinstance(value, bool):
            raise ParameterError(f"bdpt: parameter '{p.name}' must be a boolean, got {value!r}")
    elif p.type in (int, float):
        value = _number(p, value)
    elif p.type is str:
        if not isinstance(value, str):
            raise ParameterError(f"bdpt: parameter '{p.name}' must be a string, got {value!r}")
        if p.choices and value not in p.choices:
            raise ParameterError(
                f"bdpt: parameter '{p.name}' must be one of {', '.join(p.choices)}; got {value!r}")
        if p.name == 'aovs':
            parse_aovs(value)
    return value


def parse_properties(props) -> dict:
    """Read the table's parameters from a Mitsuba ``Properties`` (or a plain dict) and refuse
    unknown names and bad values with an error that names the parameter."""
    if isinstance(props, dict):
        items = dict(props)
    else:
        items = {k: props[k] for k in props.keys()}
    out = {}
    for name, value in items.items():
        if name in ('type', 'id'):
            continue
        if name not in PARAMS_BY_NAME:
            raise ParameterError(
                f"bdpt: unknown parameter '{name}'; the parameters are "
                f"{', '.join(p.name for p in PARAMS)}")
        out[name] = check_value(PARAMS_BY_NAME[name], value)
    for p in PARAMS:
        out.setdefault(p.name, p.default)
    check_light_cache(out)
    if out['strategy_images'] and out['technique'] in ('vcm', 'vm'):
        raise ParameterError(
            f"bdpt: parameter 'strategy_images' is for the (s,t) strategies; technique "
            f"'{out['technique']}' also merges, which no (s,t) layer holds: use technique bdpt")
    return out


def check_light_cache(out):
    """The light vertex cache's parameters against each other and the technique."""
    n_l, c, tech = out['light_paths'], out['connections'], out['technique']
    if n_l != -1.0 and not n_l > 0:
        raise ParameterError(f"bdpt: parameter 'light_paths' must be -1 (the classic estimator) or > 0 "
                             f"(light subpaths per camera sample), got {n_l}")
    if c == 0:
        raise ParameterError("bdpt: parameter 'connections' must be -1 (automatic) or >= 1, got 0 "
                             "(technique pt renders without connections)")
    if n_l == -1.0 and c != -1:
        raise ParameterError(f"bdpt: parameter 'connections' ({c}) needs the light vertex cache: set "
                             "light_paths > 0 (the classic estimator connects to all vertices of the "
                             "sample's own light subpath)")
    if tech == 'auto' and (n_l != -1.0 or c != -1):
        raise ParameterError("bdpt: parameters 'light_paths' and 'connections' are chosen by technique "
                             "'auto'; leave them at -1 or choose a technique")
    if n_l != -1.0 and tech not in ('bdpt', 'lt', 'vcm'):
        raise ParameterError(f"bdpt: parameter 'light_paths' needs technique bdpt, lt or vcm, not {tech!r} "
                             "(pt traces no light subpaths; vm with the cache is not implemented)")


AOV_TYPES = {'depth': 'T', 'position': 'XYZ', 'uv': 'UV', 'geo_normal': 'XYZ', 'sh_normal': 'XYZ',
             'albedo': 'RGB'}


def parse_aovs(text: str):
    """``'dd:depth,nn:sh_normal'`` -> [('dd', 'depth'), ('nn', 'sh_normal')], refusing bad entries
    with an error naming the parameter and the allowed types."""
    out = []
    for item in [x.strip() for x in text.split(',') if x.strip()]:
        name, sep, kind = item.partition(':')
        if not sep or not name or kind not in AOV_TYPES:
            raise ParameterError(
                f"bdpt: parameter 'aovs' entry {item!r} must be name:type with a type among "
                f"{', '.join(AOV_TYPES)}")
        out.append((name, kind))
    return out


def aov_channel_names(aovs):
    """Film channel names of parsed AOVs, as Mitsuba's aov integrator names them (``dd.T``)."""
    return [f'{name}.{c}' for name, kind in aovs for c in AOV_TYPES[kind]]


def markdown_table() -> str:
    rows = ['| name | type | default | meaning |', '|---|---|---|---|']
    for p in PARAMS:
        rows.append(f'| `{p.name}` | {p.type_name} | {p.default_text} | {p.meaning} |')
    return '\n'.join(rows)
