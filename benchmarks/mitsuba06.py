"""Mitsuba 0.6 as a contestant of `benchmarks/compare.py`: build it, convert the scenes, render.

The seed paper compares its BDPT with Mitsuba 0.5/0.6's `bdpt` (and `path`). This script builds
Mitsuba 0.6 from a clone of its public repository (github.com/mitsuba-renderer/mitsuba, tested at
master 10af06f3) on Debian 12, converts Mitsuba 3 scene files to its XML, and runs it; the
comparison adds "mitsuba06 bdpt" and "mitsuba06 path" when it finds the built binary.

    git clone https://github.com/mitsuba-renderer/mitsuba ~/src/mitsuba06
    sudo apt-get install <the packages `build` lists when they are missing>
    python benchmarks/mitsuba06.py build --source ~/src/mitsuba06          # 8-16 min with -j2
    python benchmarks/mitsuba06.py check --dist ~/src/mitsuba06/dist       # a 16x16 test render
    python benchmarks/mitsuba06.py speed --dist ~/src/mitsuba06/dist       # samples/s beside bdpt_jit's (SmallVCM box)
    python benchmarks/mitsuba06.py convert scenes/caustic.xml /tmp/caustic06.xml --res 256
    python benchmarks/compare.py --quick --mitsuba06 ~/src/mitsuba06/dist  # or MITSUBA06_DIST=...

`build` checks the Debian packages, makes the source build with Python 3's SCons and current
libraries (the SConscripts' Python 2 `print` statements and `has_key`, OpenEXR 3's API, GLEW
without its MX variant, Boost 1.74's placeholders), adds a `seed` parameter to the `independent`
sampler (see `SEED_EDIT`), writes `config.py` (no Python bindings, Qt or COLLADA: only the
`mitsuba` command is needed) and runs `scons`. `--prepare-only` stops before `scons`. Every edit
is idempotent and fails with a message naming the file when the source is not the one expected.

Scene conversion (`convert_file`): parameter names become camelCase (`to_world` -> `toWorld`,
`int_ior` -> `intIOR`, ...; `alpha`, `distribution`, `eta`, `k` keep theirs), the film writes
float32 OpenEXR without the logo banner, the sampler becomes `independent` with `$spp` and
`$seed`, the integrator `$integrator` with `maxDepth` (which counts edges as Mitsuba 3's
`max_depth` does) and `rrDepth` 5 (Mitsuba 3's default), defaults Mitsuba 3 and 0.6 disagree on
are written out (a conductor without a material is a perfect mirror in Mitsuba 3, copper in 0.6),
relative file names become absolute, and a checkerboard's `to_uv` scale/offset becomes
`uscale`/`vscale`/`uoffset`/`voffset`. Plugins 0.6 does not have are refused.
"""

import argparse
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ENV_VAR = 'MITSUBA06_DIST'      # a dist/ folder (or the `mitsuba` binary in it) when --mitsuba06 is not given
RR_DEPTH = 5                    # Mitsuba 3's default rr_depth (also bdpt's); 0.6's default is 5 as well
KEEP_SYMBOLIC = ('integrator', 'spp', 'seed')   # parameters the converted file leaves to `-D` on the command line
REPO = Path(__file__).resolve().parents[1]


class Mitsuba06Error(RuntimeError):
    """Mitsuba 0.6 cannot be built, a scene cannot be converted, or a render failed."""


# ============================================================================================ build

# (what is looked for, where, the Debian package that provides it)
REQUIREMENTS = [
    ('program', 'scons', 'scons'),
    ('program', 'g++', 'g++'),
    ('header', 'boost/version.hpp', 'libboost-dev'),
    ('library', 'boost_filesystem', 'libboost-filesystem-dev'),
    ('library', 'boost_system', 'libboost-system-dev'),
    ('library', 'boost_thread', 'libboost-thread-dev'),
    ('header', 'xercesc/dom/DOMLSParser.hpp', 'libxerces-c-dev'),
    ('header', 'OpenEXR/ImfRgba.h', 'libopenexr-dev'),
    ('header', 'Imath/ImathBox.h', 'libimath-dev'),
    ('header', 'png.h', 'libpng-dev'),
    ('header', 'jpeglib.h', 'libjpeg-dev'),
    ('header', 'eigen3/Eigen/Core', 'libeigen3-dev'),
    ('header', 'fftw3.h', 'libfftw3-dev'),
    ('header', 'zlib.h', 'zlib1g-dev'),
    ('header', 'GL/glew.h', 'libglew-dev'),
    ('header', 'X11/extensions/xf86vmode.h', 'libxxf86vm-dev'),
    ('header', 'X11/Xlib.h', 'libx11-dev'),
    ('header', 'GL/gl.h', 'libgl-dev'),
    ('header', 'GL/glu.h', 'libglu1-mesa-dev'),
]
INCLUDE_DIRS = ['/usr/include', '/usr/local/include'] + sorted(glob.glob('/usr/include/*-linux-gnu'))
LIB_DIRS = sorted(glob.glob('/usr/lib/*-linux-gnu')) + ['/usr/lib', '/usr/lib64', '/usr/local/lib']


def _find_library(stem):
    """Path of lib<stem>.so (or a versioned name like libOpenEXR-3_1.so for stem 'OpenEXR-*')."""
    for d in LIB_DIRS:
        hits = sorted(glob.glob(os.path.join(d, f'lib{stem}.so')))
        if hits:
            return hits[-1]
    return None


def missing_packages():
    """[(what, package)] for every requirement that is not installed."""
    out = []
    for kind, name, package in REQUIREMENTS:
        if kind == 'program':
            ok = shutil.which(name) is not None
        elif kind == 'header':
            ok = any(os.path.exists(os.path.join(d, name)) for d in INCLUDE_DIRS)
        else:
            ok = _find_library(name) is not None
        if not ok:
            out.append((f'{kind} {name}', package))
    for stem, package in (('OpenEXR-*', 'libopenexr-dev'), ('Imath-*', 'libimath-dev')):
        if _find_library(stem) is None:
            out.append((f'library {stem}', package))
    return out


def _versioned(stem):
    """'OpenEXR' -> 'OpenEXR-3_1' from the installed libOpenEXR-3_1.so."""
    path = _find_library(f'{stem}-*')
    if path is None:
        raise Mitsuba06Error(f'lib{stem}-*.so not found')
    return os.path.basename(path)[3:-3]


def python3_sconscript(text):
    """A Python 2 SConscript in Python 3 form: `print x` -> `print(x)` (continuation lines
    included), `a.has_key(k)` -> `(k) in a`, `except X, e:` -> `except X as e:`."""
    lines, out, i = text.split('\n'), [], 0
    head = re.compile(r'^(\s*)print\s+(?![(\s])(.*)$')
    while i < len(lines):
        m = head.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        stmt = [m.group(2)]
        while stmt[-1].rstrip().endswith('\\') and i + 1 < len(lines):
            i += 1
            stmt.append(lines[i])
        stmt[-1] = stmt[-1].rstrip() + ')'
        out.append(f'{m.group(1)}print(' + '\n'.join(stmt))
        i += 1
    text = '\n'.join(out)
    text = re.sub(r"([\w.]+)\.has_key\(([^()]*)\)", r'(\2) in \1', text)
    text = re.sub(r'except\s+([\w.]+)\s*,\s*(\w+)\s*:', r'except \1 as \2:', text)
    return text


# The independent sampler starts from the same seed on every run (Random() seeds with 5489), so
# repeated renders of a scene are not independent samples: the comparison averages errors over
# repeats and estimates its reference's variance from batches, both of which need independent
# renders. Neither `sampleCount` partitions nor thread counts help (each worker's stream is cloned
# from the same seeded parent). This edit adds an optional `seed` property; without it the
# sampler behaves as before. A binary without the edit warns 'Unqueried attribute "seed"', which
# Mitsuba06.render turns into an error. With the edit, one seed reproduces its image on one thread
# (-p 1) only: with several, image blocks go to the workers' sampler clones in whatever order they
# finish; renders with different seeds are independent either way.
SEED_EDIT = ('src/samplers/independent.cpp',
             '        m_random = new Random();\n    }',
             '        /* bdpt_jit benchmarks (benchmarks/mitsuba06.py): an optional seed, so that repeated\n'
             '           renders are independent (the default seed is the same on every run) */\n'
             '        if (props.hasProperty("seed"))\n'
             '            m_random = new Random((uint64_t) props.getLong("seed"));\n'
             '        else\n'
             '            m_random = new Random();\n    }')

# (file, text of master 10af06f3, its replacement); each applies once (a second run finds the replacement)
SOURCE_EDITS = [
    # OpenEXR 3: Imf::Int64 is gone (a 64-bit unsigned integer), and FrameBuffer needs its own header
    ('src/libcore/bitmap.cpp', 'Imf::Int64 tellg()', 'uint64_t tellg()'),
    ('src/libcore/bitmap.cpp', 'void seekg(Imf::Int64 pos)', 'void seekg(uint64_t pos)'),
    ('src/libcore/bitmap.cpp', 'Imf::Int64 tellp()', 'uint64_t tellp()'),
    ('src/libcore/bitmap.cpp', 'void seekp(Imf::Int64 pos)', 'void seekp(uint64_t pos)'),
    ('src/libcore/bitmap.cpp', '#include <ImfIO.h>\n', '#include <ImfIO.h>\n#include <ImfFrameBuffer.h>\n'),
    # Debian's GLEW has no MX variant: the per-thread GLEW context only with GLEW_MX
    ('include/mitsuba/hw/glrenderer.h',
     'struct GLEWContextStruct;\n\n/// Get the per-thread context for GLEW-MX\n'
     'extern MTS_EXPORT_HW GLEWContextStruct *glewGetContext();\n',
     '#if defined(GLEW_MX)\nstruct GLEWContextStruct;\n\n/// Get the per-thread context for GLEW-MX\n'
     'extern MTS_EXPORT_HW GLEWContextStruct *glewGetContext();\n#endif\n'),
    ('src/libhw/glrenderer.cpp',
     'static mitsuba::PrimitiveThreadLocal<GLEWContextStruct> glewContext;\n\n'
     'GLEWContextStruct *glewGetContext() {\n    return &glewContext.get();\n}\n',
     '#if defined(GLEW_MX)\nstatic mitsuba::PrimitiveThreadLocal<GLEWContextStruct> glewContext;\n\n'
     'GLEWContextStruct *glewGetContext() {\n    return &glewContext.get();\n}\n#endif\n'),
    # Boost 1.74: the placeholders of boost::bind live in boost::placeholders
    ('src/volume/volcache.cpp', '&CachingDataSource::renderBlock, this, _1)',
     '&CachingDataSource::renderBlock, this, boost::placeholders::_1)'),
    ('src/volume/volcache.cpp', '&CachingDataSource::destroyBlock, this, _1)',
     '&CachingDataSource::destroyBlock, this, boost::placeholders::_1)'),
    SEED_EDIT,
]

CONFIG = """\
# Written by bdpt_jit's benchmarks/mitsuba06.py: build/config-linux-gcc.py for Debian 12 (Python 3
# SCons, OpenEXR 3, GLEW without MX, Boost 1.74) with -std=gnu++14; no Python bindings, Qt or COLLADA.
BUILDDIR       = '#build/release'
DISTDIR        = '#dist'
CXX            = 'g++'
CC             = 'gcc'
CXXFLAGS       = ['-O3', '-Wall', '-g', '-pipe', '-march=nocona', '-msse2', '-ftree-vectorize', '-mfpmath=sse',
                  '-funsafe-math-optimizations', '-fno-rounding-math', '-fno-signaling-nans', '-fno-math-errno',
                  '-fomit-frame-pointer', '-DMTS_DEBUG', '-DSINGLE_PRECISION', '-DSPECTRUM_SAMPLES=3', '-DMTS_SSE',
                  '-DMTS_HAS_COHERENT_RT', '-fopenmp', '-fvisibility=hidden', '-mtls-dialect=gnu2', '-std=gnu++14']
LINKFLAGS      = []
SHLINKFLAGS    = ['-rdynamic', '-shared', '-fPIC', '-lstdc++']
BASEINCLUDE    = ['#include']
BASELIB        = ['dl', 'm', 'pthread', 'gomp']
EIGENINCLUDE   = ['/usr/include/eigen3']
OEXRINCLUDE    = ['/usr/include/OpenEXR', '/usr/include/Imath']
OEXRLIB        = [{oexr_libs}, 'z']
PNGLIB         = ['png']
JPEGLIB        = ['jpeg']
XERCESINCLUDE  = []
XERCESLIB      = ['xerces-c']
GLLIB          = ['GL', 'GLU', 'GLEW', 'Xxf86vm', 'X11']
GLFLAGS        = []
BOOSTLIB       = ['boost_system', 'boost_filesystem', 'boost_thread']
FFTWLIB        = ['fftw3_threads', 'fftw3']
"""


def check_source(src):
    """The folder is a clone of Mitsuba 0.6's repository; raises with what is wrong."""
    src = Path(src).expanduser()
    if not src.is_dir():
        raise Mitsuba06Error(f'--source {src}: no such folder; clone Mitsuba 0.6 there first: '
                             f'git clone https://github.com/mitsuba-renderer/mitsuba {src}')
    needed = ['SConstruct', 'build/SConscript.configure', 'build/config-linux-gcc.py',
              'include/mitsuba/core/version.h'] + sorted({e[0] for e in SOURCE_EDITS})
    missing = [p for p in needed if not (src / p).exists()]
    if missing:
        raise Mitsuba06Error(f'--source {src} is not a clone of github.com/mitsuba-renderer/mitsuba '
                             f'(missing: {", ".join(missing)})')
    version = re.search(r'#define MTS_VERSION "([^"]+)"', (src / 'include/mitsuba/core/version.h').read_text())
    if not version or not version.group(1).startswith('0.6'):
        raise Mitsuba06Error(f'--source {src}: Mitsuba version {version.group(1) if version else "unknown"}, '
                             f'expected 0.6.x')
    return src


def sconscripts(src):
    return [src / 'build/SConscript.configure', src / 'build/SConscript.install'] + \
        sorted(src.glob('src/*/SConscript'))


def prepare(src, log=print):
    """Applies the SConscript and source edits and writes config.py (idempotent)."""
    src = check_source(src)
    for path in sconscripts(src):
        old = path.read_text()
        new = python3_sconscript(old)
        try:
            compile(new, str(path), 'exec')
        except SyntaxError as e:
            raise Mitsuba06Error(f'{path}: still not Python 3 after the edits ({e}); edit it by hand') from e
        if new != old:
            path.write_text(new)
            log(f'edited {path.relative_to(src)} (Python 3)')
    for rel, old, new in SOURCE_EDITS:
        path = src / rel
        text = path.read_text()
        if new in text:
            continue
        if text.count(old) != 1:
            raise Mitsuba06Error(f'{path}: cannot apply the edit (expected once: {old.strip()[:60]!r}); '
                                 f'the source differs from master 10af06f3')
        path.write_text(text.replace(old, new))
        log(f'edited {rel}')
    libs = [_versioned(s) for s in ('OpenEXR', 'OpenEXRUtil', 'OpenEXRCore', 'Iex', 'IlmThread', 'Imath')]
    (src / 'config.py').write_text(CONFIG.format(oexr_libs=', '.join(repr(x) for x in libs)))
    log(f'wrote {src / "config.py"}')
    return src


def build(src, jobs, prepare_only=False, log=print):
    src = check_source(src)
    missing = missing_packages()
    if missing:
        packages = sorted({p for _, p in missing})
        raise Mitsuba06Error('Mitsuba 0.6 needs packages that are not installed:\n'
                             + '\n'.join(f'  {what} (Debian package {p})' for what, p in missing)
                             + f'\ninstall them with:\n  sudo apt-get install {" ".join(packages)}')
    prepare(src, log)
    if prepare_only:
        log(f'prepared {src}; build with: cd {src} && scons -j{jobs}')
        return None
    log(f'building in {src} with scons -j{jobs} (8-16 minutes on 2 cores)')
    t0 = time.perf_counter()
    proc = subprocess.run(['scons', f'-j{jobs}'], cwd=src)
    if proc.returncode != 0:
        raise Mitsuba06Error(f'scons failed (exit status {proc.returncode}); its log is above, and '
                             f'{src}/build/config.log has the configuration checks')
    binary = src / 'dist' / 'mitsuba'
    if not binary.exists():
        raise Mitsuba06Error(f'scons succeeded but {binary} is missing')
    log(f'built {binary} in {(time.perf_counter() - t0) / 60:.1f} min')
    return src / 'dist'


# ============================================================================================ scenes

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

RENDER_TIME = re.compile(r'Render time: ([0-9.]+)([smhd])')
UNIT = {'s': 1, 'm': 60, 'h': 3600, 'd': 12 * 3600}     # 0.6's timeString divides days by 12 (sic)


class Mitsuba06:
    """A built Mitsuba 0.6: `render(scene_xml, integrator, spp, seed)` -> (render s, wall s, image)."""

    def __init__(self, binary):
        self.binary = Path(binary).resolve()
        self.dist = self.binary.parent
        self.env = dict(os.environ)
        for var in ('LD_LIBRARY_PATH', 'PATH'):
            self.env[var] = os.pathsep.join(x for x in (str(self.dist), os.environ.get(var, '')) if x)
        try:
            proc = subprocess.run([str(self.binary), '-h'], env=self.env, capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired) as e:
            raise Mitsuba06Error(f'{self.binary} does not run: {e}') from e
        m = re.search(r'Mitsuba version (\S+)', proc.stdout + proc.stderr)
        if not m or not m.group(1).startswith(('0.6', '0.5')):
            raise Mitsuba06Error(f'{self.binary} is not Mitsuba 0.6 (its -h says: '
                                 f'{(proc.stdout + proc.stderr).strip()[:200]!r})')
        self.version = m.group(1)
        st = self.binary.stat()
        self.identity = f'{self.binary}:{st.st_size}:{int(st.st_mtime)}:{self.version}'

    def render(self, scene_xml, integrator, spp, seed, threads=None):
        """Renders and returns (render time as 0.6 logs it, wall time of the process, float32 HxWx3 array).
        The render time leaves out the process start and the scene loading (kd-tree included), as
        the Mitsuba 3 timings leave out mi.load_file."""
        import mitsuba as mi    # only for reading the OpenEXR file
        import numpy as np
        threads = threads or os.cpu_count()
        with tempfile.TemporaryDirectory(prefix='mitsuba06-') as tmp:
            out = Path(tmp) / 'out.exr'
            cmd = [str(self.binary), '-z', '-p', str(threads), f'-Dintegrator={integrator}', f'-Dspp={int(spp)}',
                   f'-Dseed={int(seed)}', '-o', str(out), str(scene_xml)]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, cwd=tmp, env=self.env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            log = proc.stdout + proc.stderr
            if 'Unqueried attribute "seed"' in log:
                raise Mitsuba06Error(f'{self.binary} ignores the sampler\'s seed (built without the seed edit of '
                                     f'benchmarks/mitsuba06.py): its repeated renders would not be independent; '
                                     f'rebuild with `python benchmarks/mitsuba06.py build --source ...`')
            if proc.returncode != 0 or not out.exists():
                raise Mitsuba06Error(f'{" ".join(cmd)} failed (exit status {proc.returncode}):\n{log[-2000:]}')
            m = RENDER_TIME.findall(log)
            if not m:
                raise Mitsuba06Error(f'no "Render time" in the log of {" ".join(cmd)}:\n{log[-2000:]}')
            seconds = float(m[-1][0]) * UNIT[m[-1][1]]
            img = np.array(mi.Bitmap(str(out)), dtype=np.float32)
        if img.ndim != 3 or img.shape[2] < 3:
            raise Mitsuba06Error(f'unexpected image shape {img.shape} from {scene_xml}')
        return seconds, wall, img[:, :, :3]

    def smoke_test(self, res=16):
        """A tiny render of the repository's Cornell box with `bdpt`: raises if anything is wrong."""
        with tempfile.TemporaryDirectory(prefix='mitsuba06-check-') as tmp:
            xml = Path(tmp) / 'cornell-box.xml'
            convert_file(REPO / 'scenes' / 'cornell-box.xml', xml, {'res': res})
            seconds, wall, img = self.render(xml, 'bdpt', 4, seed=1)
        if not (img > 0).any():
            raise Mitsuba06Error(f'{self.binary} rendered a black Cornell box')
        return seconds, wall, img


def find(path=None):
    """(Mitsuba06 or None, a sentence saying what was used or why none was). `path`: a dist/ folder
    or the `mitsuba` binary; default: the environment variable MITSUBA06_DIST. A `mitsuba` on PATH
    is not used: Mitsuba 3's pip package installs a command of that name."""
    where = path or os.environ.get(ENV_VAR)
    if not where:
        return None, (f'no Mitsuba 0.6 binary given (option --mitsuba06 PATH/TO/dist or environment variable '
                      f'{ENV_VAR}; build one with `python benchmarks/mitsuba06.py build --source DIR`)')
    p = Path(where).expanduser()
    binary = p / 'mitsuba' if p.is_dir() else p
    if not binary.is_file() or not os.access(binary, os.X_OK):
        return None, f'no executable `mitsuba` at {binary}'
    try:
        m = Mitsuba06(binary)
        m.smoke_test()
    except Mitsuba06Error as e:
        return None, f'{binary} cannot be used: {e}'
    return m, f'{m.binary} (version {m.version})'


# ============================================================================================ speed

SMALLVCM_BOX = REPO.parent / 'shared' / 'scenes' / 'smallvcm-box' / 'smallvcm-box.xml'


def speed(m06, scene, res=256, spp=16, max_depth=10, repeats=3, threads=None, log=print):
    """Samples per second of Mitsuba 0.6's `bdpt` and `path` beside bdpt_jit's `bdpt` and Mitsuba 3's
    `path` (llvm_ad_rgb) on one Mitsuba 3 scene file, at the same resolution, spp and max depth. Mitsuba
    0.6's time is the render time it logs (process start and kd-tree build left out), Mitsuba 3's the
    render after one warm-up render (scene loading and kernel compilation left out); `repeats` timed
    renders of each, interleaved so that a change of the machine's load spreads over all of them;
    medians. Returns {name: {'times': [...], 'median_s':, 'msps':}}."""
    import statistics
    import drjit as dr
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant('llvm_ad_rgb')
    import bdpt_jit  # noqa: F401  (registers the 'bdpt' integrator)
    scene = Path(scene).resolve()
    with tempfile.TemporaryDirectory(prefix='mitsuba06-speed-') as tmp:
        xml06 = Path(tmp) / (scene.stem + '-06.xml')
        convert_file(scene, xml06, {'res': res, 'resx': res, 'resy': res}, max_depth)
        text = scene.read_text()        # Mitsuba 3 refuses parameters a scene does not use
        given = {'res': res, 'resx': res, 'resy': res, 'max_depth': max_depth, 'spp': spp, 'integrator': 'path'}
        sc3 = mi.load_file(str(scene), **{k: v for k, v in given.items() if re.search(rf'\${k}\b', text)})
        w, h = (int(v) for v in sc3.sensors()[0].film().crop_size())
        integrators = {'bdpt_jit bdpt': mi.load_dict({'type': 'bdpt', 'max_depth': max_depth}),
                       'Mitsuba 3 path': mi.load_dict({'type': 'path', 'max_depth': max_depth})}

        def render3(integ, seed):
            dr.sync_thread()
            t0 = time.perf_counter()
            img = mi.render(sc3, integrator=integ, spp=spp, seed=seed)
            dr.eval(img)
            dr.sync_thread()
            return time.perf_counter() - t0

        times = {'Mitsuba 0.6 bdpt': [], 'Mitsuba 0.6 path': [], 'bdpt_jit bdpt': [], 'Mitsuba 3 path': []}
        warmup = {name: render3(integ, 0) for name, integ in integrators.items()}
        for r in range(repeats):
            for name in times:
                if name.startswith('Mitsuba 0.6'):
                    t, _, img = m06.render(xml06, name.split()[-1], spp, seed=r + 1, threads=threads)
                    if img.shape[:2] != (h, w):
                        raise Mitsuba06Error(f'Mitsuba 0.6 rendered {img.shape[1]}x{img.shape[0]}, not {w}x{h}')
                else:
                    t = render3(integrators[name], r + 1)
                times[name].append(t)
            log(f'repeat {r + 1}/{repeats}: ' + ', '.join(f'{k} {v[-1]:.2f} s' for k, v in times.items()))
    out = {}
    for name, ts in times.items():
        med = statistics.median(ts)
        out[name] = {'times': ts, 'median_s': med, 'msps': w * h * spp / med / 1e6}
        if name in warmup:
            out[name]['warmup_s'] = warmup[name]
    return out


# ============================================================================================ command line

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    sub = ap.add_subparsers(dest='command', required=True)
    b = sub.add_parser('build', help='build Mitsuba 0.6 from a clone of its repository')
    b.add_argument('--source', required=True, type=Path, help='a clone of github.com/mitsuba-renderer/mitsuba')
    b.add_argument('--jobs', type=int, default=os.cpu_count(), help='scons -j (default: %(default)s)')
    b.add_argument('--prepare-only', action='store_true', help='apply the edits and write config.py, do not build')
    c = sub.add_parser('convert', help='convert a Mitsuba 3 scene file to Mitsuba 0.6 XML')
    c.add_argument('src', type=Path)
    c.add_argument('dst', type=Path)
    c.add_argument('--res', type=int, help='overrides the scene\'s res (and resx, resy) default')
    c.add_argument('--max-depth', type=int)
    k = sub.add_parser('check', help='find a built Mitsuba 0.6 and render a 16x16 Cornell box')
    k.add_argument('--dist', help=f'dist/ folder or binary (default: ${ENV_VAR})')
    v = sub.add_parser('speed', help='samples/s of Mitsuba 0.6 bdpt and path beside bdpt_jit bdpt and Mitsuba 3 path')
    v.add_argument('--dist', help=f'dist/ folder or binary (default: ${ENV_VAR})')
    v.add_argument('--scene', type=Path, default=SMALLVCM_BOX, help='a Mitsuba 3 scene file (default: %(default)s)')
    v.add_argument('--res', type=int, default=256)
    v.add_argument('--spp', type=int, default=16)
    v.add_argument('--max-depth', type=int, default=10)
    v.add_argument('--repeats', type=int, default=3)
    v.add_argument('--threads', type=int, help='Mitsuba 0.6 -p (default: all cores, as Mitsuba 3 uses)')
    v.add_argument('--json', type=Path, help='also write the figures to this file')
    args = ap.parse_args(argv)
    try:
        if args.command == 'build':
            dist = build(args.source, args.jobs, args.prepare_only)
            if dist:
                m = Mitsuba06(dist / 'mitsuba')
                seconds, _, _ = m.smoke_test()
                print(f'Mitsuba {m.version} works (16x16 test render in {seconds:.2f} s). Use it with:\n'
                      f'  python benchmarks/compare.py --quick --mitsuba06 {dist}')
        elif args.command == 'convert':
            params = {'res': args.res, 'resx': args.res, 'resy': args.res} if args.res else {}
            convert_file(args.src, args.dst, params, args.max_depth)
            print(f'wrote {args.dst}')
        elif args.command == 'speed':
            m, how = find(args.dist)
            if m is None:
                raise Mitsuba06Error(how)
            if args.repeats < 1:
                raise Mitsuba06Error('--repeats must be at least 1')
            import platform
            print(f'Mitsuba 0.6: {how}\nscene: {args.scene}, {args.res}x{args.res}, {args.spp} spp, max depth '
                  f'{args.max_depth}, {args.repeats} timed repeats; {os.cpu_count()} cores, {platform.platform()}')
            res = speed(m, args.scene, args.res, args.spp, args.max_depth, args.repeats, args.threads)
            print(f"\n{'renderer':<18} {'median s':>9} {'M samples/s':>12}   (times)")
            for name, r in res.items():
                print(f"{name:<18} {r['median_s']:>9.3f} {r['msps']:>12.3f}   "
                      + ' '.join(f'{t:.2f}' for t in r['times']))
            b06, b3 = res['Mitsuba 0.6 bdpt']['msps'], res['bdpt_jit bdpt']['msps']
            print(f'\nbdpt_jit bdpt / Mitsuba 0.6 bdpt (samples/s): {b3 / b06:.2f}')
            if args.json:
                import json
                args.json.parent.mkdir(parents=True, exist_ok=True)
                args.json.write_text(json.dumps({'mitsuba06': how, 'scene': str(args.scene), 'res': args.res,
                                                 'spp': args.spp, 'max_depth': args.max_depth,
                                                 'repeats': args.repeats, 'cores': os.cpu_count(),
                                                 'results': res}, indent=1))
        else:
            m, how = find(args.dist)
            if m is None:
                raise Mitsuba06Error(how)
            print(f'Mitsuba 0.6 found and working: {how}')
    except Mitsuba06Error as e:
        print(f'mitsuba06.py {args.command}: {e}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
