"""The ``bdpt-jit`` command: render a Mitsuba scene file to an EXR and a PNG.

    bdpt-jit render scenes/cornell-box.xml -o out/cornell-box.exr --spp 64

Integrator parameters come from the same table as the plugin (``params.py``)."""

import argparse
import os
import sys
import tempfile
import time


class CLIError(Exception):
    """An error the user can fix; printed as one line, exit status 1."""


def _add_param_options(parser):
    from .params import PARAMS
    for p in PARAMS:
        flag = '--' + p.name.replace('_', '-')
        kw = dict(dest=p.name, default=None, help=f"{p.meaning} (default: {p.default_text})")
        if p.type is bool:
            parser.add_argument(flag, action='store_true', **kw)
        else:
            if p.choices:
                kw['choices'] = p.choices
            parser.add_argument(flag, type=p.type, **kw)


def build_parser():
    ap = argparse.ArgumentParser(prog='bdpt-jit', description='Bidirectional path tracing for Mitsuba 3 scenes.')
    sub = ap.add_subparsers(dest='command', required=True)
    r = sub.add_parser('render', help='render a scene file to EXR + PNG')
    r.add_argument('scene', help='Mitsuba scene file (.xml)')
    r.add_argument('-o', '--output', default=None, help='output EXR path (default: SCENE name in the working directory); a PNG is written beside it')
    r.add_argument('--spp', type=int, default=None, help="samples per pixel (default: the scene's sampler)")
    r.add_argument('--integrator', default='bdpt', help="integrator plugin (default: bdpt; any Mitsuba integrator for comparison)")
    r.add_argument('-D', dest='defines', action='append', default=[], metavar='NAME=VALUE', help='scene parameter, as Mitsuba\'s -D')
    r.add_argument('--variant', default='llvm_ad_rgb', help='Mitsuba variant (default: llvm_ad_rgb)')
    r.add_argument('--seed', type=int, default=0, help='random seed (default: 0)')
    r.add_argument('-q', '--quiet', action='store_true', help='print nothing but errors')
    r.add_argument('--debug', action='store_true', help='show tracebacks')
    _add_param_options(r)
    return ap


def _parse_defines(defines):
    out = {}
    for d in defines:
        if '=' not in d or not d.split('=', 1)[0]:
            raise CLIError(f"-D expects NAME=VALUE, got {d!r}")
        k, v = d.split('=', 1)
        out[k] = v
    return out


def _atomic_write(path, write_fn):
    """Write through a temporary file in the same folder, then rename: an interrupted render
    never leaves a truncated file under the final name."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.' + os.path.basename(path) + '.', suffix=os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)                # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_exr(path, rgb, header_extra):
    import numpy as np
    import OpenEXR
    header = {'compression': OpenEXR.ZIP_COMPRESSION, 'type': OpenEXR.scanlineimage}
    header.update({k: str(v) for k, v in header_extra.items()})
    _atomic_write(path, lambda tmp: OpenEXR.File(header, {'RGB': np.ascontiguousarray(rgb, dtype=np.float32)}).write(tmp))


def write_png(path, rgb):
    import mitsuba as mi
    bmp = mi.Bitmap(rgb, mi.Bitmap.PixelFormat.RGB)
    png = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    _atomic_write(path, lambda tmp: png.write(tmp))


def cmd_render(args):
    import numpy as np
    if not os.path.isfile(args.scene):
        raise CLIError(f"scene file not found: {args.scene}")
    out = args.output or os.path.splitext(os.path.basename(args.scene))[0] + '.exr'
    out_dir = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(out_dir) or not os.access(out_dir, os.W_OK):
        raise CLIError(f"output folder is missing or not writable: {out_dir}")
    import mitsuba as mi
    try:
        mi.set_variant(args.variant)
    except Exception as e:
        raise CLIError(f"Mitsuba variant '{args.variant}' is not available: {e}") from None
    import bdpt_jit
    bdpt_jit.register()
    from .params import PARAMS
    defines = _parse_defines(args.defines)
    try:
        scene = mi.load_file(args.scene, **defines)
    except Exception as e:
        raise CLIError(f"cannot load {args.scene}: {str(e).strip().splitlines()[-1] if str(e).strip() else e}") from None
    integ_dict = {'type': args.integrator}
    if args.integrator == 'bdpt':
        for p in PARAMS:
            v = getattr(args, p.name)
            if v is not None and v is not False:
                integ_dict[p.name] = v
    elif args.max_depth is not None:
        integ_dict['max_depth'] = args.max_depth
    try:
        integrator = mi.load_dict(integ_dict)
    except Exception as e:
        raise CLIError(str(e).strip().splitlines()[-1]) from None
    spp = args.spp or 0
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=args.seed)
    arr = np.array(img)[:, :, :3]
    elapsed = time.perf_counter() - t0
    info = dict(getattr(integrator, 'last_render_info', {}) or {})
    spp_used = spp or scene.sensors()[0].sampler().sample_count()
    header = {'bdpt_integrator': args.integrator, 'bdpt_spp': spp_used, 'bdpt_seed': args.seed,
              'bdpt_time_s': f'{elapsed:.3f}', 'bdpt_scene': os.path.abspath(args.scene)}
    if args.integrator == 'bdpt':
        header.update({f'bdpt_{k}': v for k, v in integrator.settings.items()})
        header['bdpt_strategies'] = '; '.join(info.get('strategies', []))
    write_exr(out, arr, header)
    png = os.path.splitext(out)[0] + '.png'
    write_png(png, arr)
    if not args.quiet:
        h, w = arr.shape[:2]
        print(f"rendered {args.scene} with {args.integrator}: {w}x{h}, {spp_used} spp, {elapsed:.2f} s "
              f"({w * h * spp_used / elapsed / 1e6:.3f} M samples/s)")
        if info.get('strategies'):
            print('strategies: ' + '; '.join(info['strategies']))
        print(f"wrote {out} and {png}")
    return 0


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == 'render':
            return cmd_render(args)
    except (CLIError, ValueError) as e:
        if getattr(args, 'debug', False):
            raise
        print(f"bdpt-jit: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
