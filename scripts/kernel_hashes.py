"""Dr.Jit kernel hashes of a render of a scene without media, to show that a change leaves its
kernels as they were (issue 23: "a scene without media traces kernels with no medium code").

    PYTHONPATH=<tree> .venv/bin/python scripts/kernel_hashes.py out.json [before.json]

Renders the Cornell box (mi.cornell_box(), bdpt, max_depth 5, spp 1, techniques bdpt and vcm;
and scenes/caustic.xml at 32x32 for a scene with delta BSDFs) once to warm up, then once with
Dr.Jit's kernel history on, and writes each launched JIT kernel's hash and operation count.
With a second file, compares and exits 1 if any kernel differs. The image itself is not compared:
light-image splats are atomic adds whose order varies between runs (the sum differs in the 10th
digit between two runs of the same tree)."""

import json
import os
import sys

import drjit as dr
import mitsuba as mi

mi.set_variant('llvm_ad_rgb')
import bdpt_jit  # noqa: E402,F401

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def hashes(scene, technique):
    integ = mi.load_dict({'type': 'bdpt', 'max_depth': 5, 'technique': technique})
    mi.render(scene, integrator=integ, spp=1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        mi.render(scene, integrator=integ, spp=1, seed=3)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return [[str(k['hash']), k.get('operation_count')] for k in hist if k['type'] == dr.KernelType.JIT]


def main():
    cornell = mi.load_dict(mi.cornell_box())
    caustic = mi.load_file(os.path.join(REPO, 'scenes', 'caustic.xml'), res=32)
    out = {f'{name}/{tech}': hashes(scene, tech)
           for name, scene in (('cornell', cornell), ('caustic', caustic)) for tech in ('bdpt', 'vcm')}
    print('loaded from', bdpt_jit.__file__)
    with open(sys.argv[1], 'w') as f:
        json.dump(out, f, indent=1)
    if len(sys.argv) > 2:
        with open(sys.argv[2]) as f:
            before = json.load(f)
        diff = [k for k in out if out[k] != before.get(k)]
        print('kernels differ:', diff if diff else 'none',
              f"({sum(len(v) for v in out.values())} kernels, "
              f"{sum(op for v in out.values() for _, op in v)} operations)")
        sys.exit(1 if diff else 0)


if __name__ == '__main__':
    main()
