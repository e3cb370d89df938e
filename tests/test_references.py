"""The stored references (tests/references, tests/helpers.py): a scene's fingerprint, part of
each reference's key, is the same for two loads of the scene and changes with anything the scene
renders differently, so that a stored reference is never met by an edited scene; the stored
files hold finite float32 batches."""

import glob
import os

import mitsuba as mi
import numpy as np
import pytest

from helpers import STORE, load_scene, scene_fingerprint, scene_path
from stability_cases import cornell


@pytest.mark.parametrize('name', sorted(os.path.basename(p) for p in glob.glob(scene_path('*.xml'))))
def test_a_scene_file_fingerprints_alike_in_two_loads(name):
    assert scene_fingerprint(load_scene(name, 8, 4)) == scene_fingerprint(load_scene(name, 8, 4))


def test_the_fingerprint_changes_with_what_the_scene_renders():
    """Planted: the description left out of the digest (the filter is no parameter), or the
    parameters (a mesh's vertices are not in the description), a case fails."""
    base = scene_fingerprint(mi.load_dict(cornell(8)))
    assert scene_fingerprint(mi.load_dict(cornell(8))) == base        # unnamed objects' addresses left out
    assert scene_fingerprint(mi.load_dict(cornell(10))) != base       # the film's size
    changed = cornell(8)
    key = next(k for k, v in changed.items() if isinstance(v, dict) and v.get('type') == 'rectangle')
    moved = dict(changed, **{key: dict(changed[key], to_world=mi.ScalarTransform4f().translate([0, 1e-3, 0]) @
                                       changed[key].get('to_world', mi.ScalarTransform4f()))})
    assert scene_fingerprint(mi.load_dict(moved)) != base             # a shape moved by 1e-3
    params = mi.traverse(scene := mi.load_dict(cornell(8)))
    name = next(k for k in params.keys() if k.endswith('reflectance.value'))
    params[name] = params[name] * 0.999
    params.update()
    assert scene_fingerprint(scene) != base                            # a reflectance 0.1% lower
    gaussian = cornell(8)
    gaussian['sensor']['film']['rfilter'] = {'type': 'gaussian'}
    assert scene_fingerprint(mi.load_dict(gaussian)) != base           # the film's filter
    torus = load_scene('torus-in-glass.xml', 8, 4)
    before = scene_fingerprint(torus)
    params = mi.traverse(torus)
    v = np.array(params['torus.vertex_positions']).reshape(-1, 3)
    inner = np.argmin(np.linalg.norm(v - v.mean(axis=0), axis=1))      # inside the bounding box
    v[inner] += 1e-4
    params['torus.vertex_positions'] = mi.Float(v.ravel())
    params.update()
    assert scene_fingerprint(torus) != before                          # one vertex of a mesh


def test_stored_references_are_finite_float32_batches():
    files = glob.glob(os.path.join(STORE, '*.npz'))
    assert files
    for path in files:
        with np.load(path) as f:
            batches = f['batches']
        assert batches.dtype == np.float32 and batches.ndim == 4 and batches.shape[0] >= 2, path
        assert np.all(np.isfinite(batches)), path
