"""Mitsuba 0.6 as a contestant (mitsuba06.py): Mitsuba 3 scene files converted to Mitsuba 0.6's XML
(see mitsuba06.py's docstring for the rules)."""

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from mitsuba06_common import KEEP_SYMBOLIC, RR_DEPTH, Mitsuba06Error


RENAME = {'int_ior': 'intIOR', 'ext_ior': 'extIOR'}             # not plain camelCase
NO_COUNTERPART = {'principled', 'principledthin', 'measured', 'pplastic', 'polarizer', 'retarder', 'circular',
                  'hair', 'normalmap', 'bumpmap', 'volpath', 'volpathmis', 'prb', 'direct_projective'}
PROPERTY_TAGS = {'float', 'integer', 'boolean', 'string', 'rgb', 'spectrum', 'point', 'vector', 'transform', 'ref'}
PARAM = re.compile(r'\$([A-Za-z_][A-Za-z0-9_]*)')


def camel(name):
    """A Mitsuba 3 parameter name in Mitsuba 0.6's form."""
    if name in RENAME:
        return RENAME[name]
    return re.sub(r'_([a-z0-9])', lambda m: m.group(1).upper(), name)


def _split3(value):
    parts = [p for p in re.split(r'[,\s]+', value.strip()) if p]
    if len(parts) == 1:
        parts *= 3
    if len(parts) != 3:
        raise Mitsuba06Error(f'expected 1 or 3 numbers, got {value!r}')
    return parts


def _substitute(value, params):
    def one(m):
        name = m.group(1)
        if name in KEEP_SYMBOLIC:
            return m.group(0)
        if name not in params:
            raise Mitsuba06Error(f'the scene uses ${name}, which it gives no default for')
        return str(params[name])
    return PARAM.sub(one, value)


def _uv_transform(elem):
    """A Mitsuba 3 `to_uv` transform of scales and translations as 0.6's uscale/vscale/uoffset/voffset."""
    su = sv = 1.0
    ou = ov = 0.0
    for op in elem:
        if op.tag == 'scale':
            if 'value' in op.attrib:
                x, y = (float(v) for v in _split3(op.get('value'))[:2])
            else:
                x, y = float(op.get('x', 1)), float(op.get('y', 1))
            su, sv, ou, ov = su * x, sv * y, ou * x, ov * y
        elif op.tag == 'translate':
            if 'value' in op.attrib:
                x, y = (float(v) for v in _split3(op.get('value'))[:2])
            else:
                x, y = float(op.get('x', 0)), float(op.get('y', 0))
            ou, ov = ou + x, ov + y
        else:
            raise Mitsuba06Error(f'to_uv: <{op.tag}> has no Mitsuba 0.6 counterpart (only scale and translate)')
    out = []
    for name, v, default in (('uscale', su, 1.0), ('vscale', sv, 1.0), ('uoffset', ou, 0.0), ('voffset', ov, 0.0)):
        if v != default:
            out.append(ET.Element('float', name=name, value=repr(v)))
    return out


def _convert(elem, base_dir):
    """Converts one element (attributes already substituted) and its children, in place."""
    kind = elem.get('type')
    if kind in NO_COUNTERPART:
        raise Mitsuba06Error(f'<{elem.tag} type="{kind}"> has no Mitsuba 0.6 counterpart')
    if elem.tag in PROPERTY_TAGS and 'name' in elem.attrib:
        elem.set('name', camel(elem.get('name')))
    if elem.tag in ('point', 'vector') and 'value' in elem.attrib:
        x, y, z = _split3(elem.attrib.pop('value'))
        elem.set('x', x), elem.set('y', y), elem.set('z', z)
    if elem.tag in ('point', 'vector'):
        for axis in 'xyz':
            elem.set(axis, elem.get(axis, '0'))
    if elem.tag in ('translate', 'rotate') and 'value' in elem.attrib:
        x, y, z = _split3(elem.attrib.pop('value'))
        elem.set('x', x), elem.set('y', y), elem.set('z', z)
    if elem.tag == 'scale' and 'value' in elem.attrib:        # 0.6 takes value="s" but not value="x, y, z"
        parts = [p for p in re.split(r'[,\s]+', elem.get('value').strip()) if p]
        if len(parts) == 3:
            del elem.attrib['value']
            elem.set('x', parts[0]), elem.set('y', parts[1]), elem.set('z', parts[2])
    if elem.tag == 'string' and elem.get('name') == 'filename' and not os.path.isabs(elem.get('value', '')):
        elem.set('value', str((base_dir / elem.get('value')).resolve()))
    if elem.tag == 'bsdf' and kind in ('conductor', 'roughconductor'):
        if not any(c.get('name') in ('material', 'eta', 'k') for c in elem):
            elem.insert(0, ET.Element('string', name='material', value='none'))   # Mitsuba 3's default
    for child in list(elem):
        if child.tag == 'transform' and child.get('name') == 'to_uv':
            idx = list(elem).index(child)
            elem.remove(child)
            for j, e in enumerate(_uv_transform(child)):
                elem.insert(idx + j, e)
            continue
        _convert(child, base_dir)


def scene_defaults(root):
    return {d.get('name'): d.get('value') for d in root.iter('default')}


def convert_tree(root, base_dir, params=None, max_depth=None):
    """The Mitsuba 0.6 form of a parsed Mitsuba 3 scene (a new tree). `params` override or add to
    the scene's `<default>` values; `max_depth` overrides its integrator's `max_depth` (default:
    the scene's own, else -1, infinite, Mitsuba 3's default and 0.6's)."""
    if root.tag != 'scene':
        raise Mitsuba06Error(f'not a Mitsuba scene (root element <{root.tag}>)')
    values = scene_defaults(root)
    values.update({k: str(v) for k, v in (params or {}).items() if v is not None})
    src = ET.fromstring(ET.tostring(root))                    # a copy
    for e in src.iter():
        for k, v in list(e.attrib.items()):
            if '$' in v:
                e.set(k, _substitute(v, values))
    depth = max_depth
    if depth is None:
        for integ in src.iter('integrator'):
            for c in integ:
                if c.get('name') == 'max_depth':
                    depth = int(c.get('value'))
    if depth is None:
        depth = -1

    out = ET.Element('scene', version='0.6.0')
    for name, value in (('integrator', 'path'), ('spp', values.get('spp', '16')), ('seed', '0')):
        out.append(ET.Element('default', name=name, value=str(value)))
    integ = ET.SubElement(out, 'integrator', type='$integrator')
    ET.SubElement(integ, 'integer', name='maxDepth', value=str(depth))
    ET.SubElement(integ, 'integer', name='rrDepth', value=str(RR_DEPTH))
    sensors = 0
    for elem in src:
        if elem.tag in ('default', 'integrator'):
            continue
        if elem.tag == 'sensor':
            sensors += 1
            for c in list(elem):
                if c.tag == 'sampler':
                    elem.remove(c)
                elif c.tag == 'film':
                    _film(c)
            sampler = ET.Element('sampler', type='independent')
            ET.SubElement(sampler, 'integer', name='sampleCount', value='$spp')
            ET.SubElement(sampler, 'integer', name='seed', value='$seed')      # see SEED_EDIT
            elem.append(sampler)
        _convert(elem, base_dir)
        out.append(elem)
    if sensors != 1:
        raise Mitsuba06Error(f'expected one <sensor>, found {sensors}')
    return out


def _film(film):
    if film.get('type') != 'hdrfilm':
        raise Mitsuba06Error(f'film type {film.get("type")!r}: only hdrfilm is converted')
    for c in list(film):
        if c.get('name') in ('pixel_format', 'file_format', 'component_format', 'banner'):
            film.remove(c)
    for tag, name, value in (('string', 'pixelFormat', 'rgb'), ('string', 'fileFormat', 'openexr'),
                             ('string', 'componentFormat', 'float32'),      # 0.6 writes float16 otherwise
                             ('boolean', 'banner', 'false')):               # 0.6 stamps its logo otherwise
        film.append(ET.Element(tag, name=name, value=value))


def convert_file(src, dst, params=None, max_depth=None):
    """Writes the Mitsuba 0.6 form of the Mitsuba 3 scene file `src` to `dst`; returns dst's text."""
    src = Path(src).resolve()
    try:
        root = ET.parse(src).getroot()
    except (ET.ParseError, OSError) as e:
        raise Mitsuba06Error(f'{src}: {e}') from e
    out = convert_tree(root, src.parent, params, max_depth)
    ET.indent(out, '    ')
    note = (f' Mitsuba 0.6 form of {src}, written by bdpt_jit benchmarks/mitsuba06.py. Render with\n'
            f'     mitsuba -z -p 2 -Dintegrator=bdpt -Dspp=16 -Dseed=1 -o out.exr {Path(dst).name}\n'
            f'     ($seed needs the seed edit of benchmarks/mitsuba06.py). ')
    text = '<?xml version="1.0" encoding="utf-8"?>\n<!--' + note + '-->\n' + ET.tostring(out, encoding='unicode') + '\n'
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    Path(dst).write_text(text)
    return text


# ============================================================================================ running
