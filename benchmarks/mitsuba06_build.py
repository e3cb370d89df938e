"""Mitsuba 0.6 as a contestant (mitsuba06.py): its build from a clone of the public source on
Debian 12 with Python 3's SCons and current libraries (see mitsuba06.py's docstring)."""

import glob
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

from mitsuba06_common import Mitsuba06Error


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
