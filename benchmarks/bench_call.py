"""A render call's fixed cost against the number of lights: ``bdpt`` and Mitsuba's ``path`` (or
``volpath`` with fog) on a closed room of diffuse walls holding N small sphere lights at random,
with and without a homogeneous fog filling it (the lights then declare the fog outside them),
at a few pixels and 1 sample a pixel, so that what a call costs besides its samples decides the
figure: bdpt builds its tables of the scene's emitters and, with media, finds the medium each
light lies in (media_path.EmitterMedia) and walks rays from the sensor (media_path.sensor_walk)
on every call. Medians of --repeats warm calls (the kernels compiled by a first one).

    python benchmarks/bench_call.py [--lights 0,10,40,160] [--res 16] [--repeats 7]
"""

import argparse
import statistics
import time

import drjit as dr
import mitsuba as mi
import numpy as np

T = None    # mi.ScalarTransform4f, once a variant is set


def room(n_lights, fog, res, seed=1):
    """The scene dict: the box [-1, 1]^3 of diffuse walls facing in, the camera inside it."""
    d = {'type': 'scene',
         'sensor': {'type': 'perspective', 'fov': 70,
                    'to_world': T().look_at(origin=[0, 0, 0.9], target=[0, 0, -1], up=[0, 1, 0]),
                    'film': {'type': 'hdrfilm', 'width': res, 'height': res, 'rfilter': {'type': 'box'}}}}
    walls = {'floor': T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
             'ceiling': T().translate([0, 1, 0]).rotate([1, 0, 0], 90),
             'back': T().translate([0, 0, -1]), 'front': T().translate([0, 0, 1]).rotate([0, 1, 0], 180),
             'left': T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
             'right': T().translate([1, 0, 0]).rotate([0, 1, 0], -90)}
    if fog:
        d['fog'] = {'type': 'homogeneous', 'sigma_t': 0.5, 'albedo': 0.8}
        d['sensor']['medium'] = {'type': 'ref', 'id': 'fog'}
    for name, tf in walls.items():
        d[name] = {'type': 'rectangle', 'to_world': tf.scale([1.01, 1.01, 1.0]),
                   'bsdf': {'type': 'diffuse', 'reflectance': {'type': 'rgb', 'value': [0.7, 0.7, 0.7]}}}
        if fog:
            d[name].update(interior={'type': 'ref', 'id': 'fog'}, exterior={'type': 'ref', 'id': 'fog'})
    rng = np.random.default_rng(seed)
    for i in range(n_lights):
        d[f'lamp{i}'] = {'type': 'sphere', 'center': rng.uniform(-0.8, 0.8, 3).tolist(), 'radius': 0.02,
                         'emitter': {'type': 'area', 'radiance': {'type': 'rgb', 'value': [5.0, 5.0, 5.0]}}}
        if fog:
            d[f'lamp{i}']['exterior'] = {'type': 'ref', 'id': 'fog'}
    return d


def per_call(scene, integ, repeats):
    """Median seconds of a 1-spp render call, warm."""
    mi.render(scene, integrator=integ, spp=1, seed=0)
    times = []
    for k in range(repeats):
        t = time.perf_counter()
        dr.eval(mi.render(scene, integrator=integ, spp=1, seed=1 + k))
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def light_counts(text):
    """--lights: non-negative integers, comma-separated."""
    try:
        counts = [int(x) for x in text.split(',')]
    except ValueError:
        counts = [-1]
    if any(n < 0 for n in counts):
        raise argparse.ArgumentTypeError(f'--lights takes non-negative integers, comma-separated (got {text!r})')
    return counts


def main():
    global T
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--lights', type=light_counts, default='0,10,40,160',
                    help='numbers of sphere lights, comma-separated')
    ap.add_argument('--res', type=int, default=16)
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--variant', default='llvm_ad_rgb')
    args = ap.parse_args()
    mi.set_variant(args.variant)
    T = mi.ScalarTransform4f
    import bdpt_jit  # noqa: F401  (registers the plugin)
    print(f'{args.variant}, {args.res}x{args.res}, 1 spp a call, medians of {args.repeats} warm calls (ms)')
    print('| lights | fog | bdpt | Mitsuba | bdpt / Mitsuba |\n|---|---|---|---|---|')
    for n in args.lights:
        for fog in (False, True):
            scene = mi.load_dict(room(n, fog, args.res))
            mine = per_call(scene, mi.load_dict({'type': 'bdpt', 'max_depth': 5}), args.repeats)
            theirs = per_call(scene, mi.load_dict({'type': 'volpath' if fog else 'path', 'max_depth': 5}),
                              args.repeats)
            print(f'| {n} | {"yes" if fog else "no"} | {1e3 * mine:.1f} | {1e3 * theirs:.1f} '
                  f'({"volpath" if fog else "path"}) | {mine / theirs:.1f} |', flush=True)


if __name__ == '__main__':
    main()
