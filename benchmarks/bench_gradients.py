"""Cost and error of bdpt's image derivatives beside Mitsuba's ``prb``.

1. Time of a reverse-mode gradient (render + backward of an image adjoint) against the primal
   render, for bdpt and for prb (medians of --repeats, side by side in one run).
2. Error at equal time of the forward-mode image derivative with respect to a parameter (by
   default the floor's reflectance of the caustic scene, whose floor is lit through a glass
   sphere): MSE against a reference, central finite differences of bdpt's primal with common
   random numbers at --ref-spp, for bdpt and prb given the same wall time.

    python benchmarks/bench_gradients.py [--scene scenes/caustic.xml] [--key floor_white.reflectance.value]
"""

import argparse
import statistics
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

mi.set_variant('llvm_ad_rgb')
import bdpt_jit  # noqa: E402,F401

REPO = Path(__file__).resolve().parents[1]


def load(args):
    return mi.load_file(str(args.scene), res=args.res, max_depth=args.max_depth)


def attach(params, key):
    v = type(params[key])(dr.detach(params[key]))
    dr.enable_grad(v)
    params[key] = v
    params.update()
    return v


def timed(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def forward_grad(scene, key, integ, spp, seed):
    params = mi.traverse(scene)
    base = type(params[key])(dr.detach(params[key]))
    v = attach(params, key)
    img = mi.render(scene, params, integrator=integ, spp=spp, seed=seed, seed_grad=seed + 77777)
    dr.set_grad(v, dr.ones(type(v), dr.shape(v)) if not isinstance(v, mi.TensorXf) else dr.ones(mi.TensorXf, v.shape))
    dr.forward_to(img)
    g = np.array(dr.grad(img), dtype=np.float64)[:, :, :3]
    params[key] = base
    params.update()
    return g


def reference(scene, key, args):
    params = mi.traverse(scene)
    base = type(params[key])(dr.detach(params[key]))
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': args.max_depth})
    out = []
    for sgn in (1, -1):
        params[key] = base + sgn * args.h
        params.update()
        out.append(np.array(mi.render(scene, integrator=integ, spp=args.ref_spp, seed=4242), dtype=np.float64))
    params[key] = base
    params.update()
    return (out[0] - out[1])[:, :, :3] / (2 * args.h)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scene', type=Path, default=REPO / 'scenes' / 'caustic.xml')
    ap.add_argument('--key', default='floor_white.reflectance.value')
    ap.add_argument('--res', type=int, default=64)
    ap.add_argument('--max-depth', type=int, default=6)
    ap.add_argument('--spp', type=int, default=16, help='bdpt samples per pixel for the timings and the error')
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--ref-spp', type=int, default=4096)
    ap.add_argument('--h', type=float, default=0.05)
    ap.add_argument('--seeds', type=int, default=4, help='independent runs averaged for each MSE')
    args = ap.parse_args()

    scene = load(args)
    integs = {'bdpt': mi.load_dict({'type': 'bdpt', 'max_depth': args.max_depth}),
              'prb': mi.load_dict({'type': 'prb', 'max_depth': args.max_depth})}
    print(f"scene {args.scene}, {args.res}x{args.res}, max_depth {args.max_depth}, parameter {args.key}")
    times = {}
    for name, integ in integs.items():
        def primal():
            dr.eval(mi.render(scene, integrator=integ, spp=args.spp, seed=1))

        def reverse():
            params = mi.traverse(scene)
            base = type(params[args.key])(dr.detach(params[args.key]))
            v = attach(params, args.key)
            img = mi.render(scene, params, integrator=integ, spp=args.spp, seed=1, seed_grad=2)
            dr.backward(img)
            dr.eval(dr.grad(v))
            params[args.key] = base
            params.update()
        tp, tg = timed(primal, args.repeats), timed(reverse, args.repeats)
        times[name] = tp
        print(f"{name:5s} primal {tp:7.3f} s   primal + reverse-mode gradient {tg:7.3f} s   ratio {tg / tp:5.2f}"
              f"   ({args.spp} spp)")

    ref = reference(scene, args.key, args)
    spp = {'bdpt': args.spp, 'prb': max(1, int(round(args.spp * times['bdpt'] / times['prb'])))}
    mse = {}
    for name, integ in integs.items():
        errs = [np.mean((forward_grad(scene, args.key, integ, spp[name], 100 + s) - ref) ** 2)
                for s in range(args.seeds)]
        mse[name] = float(np.mean(errs))
        print(f"{name:5s} equal time: {spp[name]} spp, MSE of the image derivative {mse[name]:.4g}")
    print(f"bdpt / prb MSE at equal time: {mse['bdpt'] / mse['prb']:.3f}  (reference: finite differences, "
          f"h={args.h}, {args.ref_spp} spp)")


if __name__ == '__main__':
    main()
