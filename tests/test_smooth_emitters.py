"""bdpt's own position sampling on smooth-shaded emitter meshes (bdpt_jit/smooth_emitters.py):
uniform by area, on the surface rays hit, with the triangle's and the shading normal Mitsuba's
hits have there. The renders that depend on it: test_lights.py::test_a_coarse_smooth_shaded_emitter_mesh."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

from bdpt_jit.smooth_emitters import UNIFORM_SHARE, SmoothEmitters, emission_direction, emission_pdf_w
from stability_cases import lowpoly_sphere_mesh

EMITTER = {'type': 'area', 'radiance': {'type': 'rgb', 'value': [1.0, 1.0, 1.0]}}


def scene_with(flip):
    """Two emitter meshes of 48 and 96 triangles (one smooth-shaded sphere, flipped or not,
    and one moved and larger) and a rectangle light."""
    return mi.load_dict({
        'type': 'scene',
        'a': lowpoly_sphere_mesh(4, 8, radius=0.5, emitter=EMITTER, flip=flip),
        'b': lowpoly_sphere_mesh(6, 8, radius=1.5, center=(4.0, 0.0, 0.0), emitter=EMITTER),
        'c': {'type': 'rectangle', 'to_world': mi.ScalarTransform4f().translate([0, 5, 0]), 'emitter': EMITTER}})


def table(scene):
    emitters = scene.emitters()
    ids = [int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(e))[0]) for e in emitters]
    return SmoothEmitters(scene, emitters, ids, max(ids) + 1), ids


@pytest.mark.parametrize('flip', [False, True])
def test_positions_are_uniform_on_the_surface_with_mitsubas_normals(flip):
    """Per mesh: the face counts of 200k samples against the face areas (chi-square, p > 1e-3);
    a ray from each sample's point along its normal, traced back, hits the point (1e-5) with
    Mitsuba's geometric and shading normals there (1e-5). The rectangle is not sampled here."""
    scene = scene_with(flip)
    smooth, ids = table(scene)
    n = 200_000
    rng = np.random.default_rng(7)
    for k, emitter in enumerate(scene.emitters()):
        em = dr.gather(mi.EmitterPtr, scene.emitters_dr(), mi.UInt32(np.full(n, k, np.uint32)))
        u = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
        ok, p, n_geo, n_sh, _ = smooth.sample(em, u, mi.Bool(True))
        mesh = next(s for s in scene.shapes()
                    if s.is_emitter() and int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(s.emitter()))[0]) == ids[k])
        if mesh.id() == 'c':        # the rectangle (its vertex normals are its face's)
            assert not np.array(ok).any()
            continue
        assert np.array(ok).all()
        o = p + n_geo * 0.01
        si = scene.ray_intersect(mi.Ray3f(o, -n_geo))
        assert np.abs(np.array(si.t) - 0.01).max() < 1e-5
        assert np.abs(np.array(si.n - n_geo)).max() < 1e-5
        assert np.abs(np.array(si.sh_frame.n - n_sh)).max() < 1e-5
        prim = np.array(si.prim_index)
        pos = np.array(mesh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
        f = np.array(mesh.faces_buffer()).reshape(-1, 3)
        area = 0.5 * np.linalg.norm(np.cross(pos[f[:, 1]] - pos[f[:, 0]], pos[f[:, 2]] - pos[f[:, 0]]), axis=1)
        counts = np.bincount(prim, minlength=len(f))
        assert stats.chisquare(counts, n * area / area.sum()).pvalue > 1e-3


def test_flat_and_textured_meshes_keep_mitsubas_sampling():
    """A mesh whose vertex normals are its faces' (a cube: 24 vertices) is not smooth-shaded;
    a textured emitter keeps Mitsuba's texture-driven sampling."""
    scene = mi.load_dict({'type': 'scene', 'box': {'type': 'cube', 'emitter': EMITTER},
                          'ball': lowpoly_sphere_mesh(4, 8, emitter={'type': 'area', 'radiance': {'type': 'checkerboard'}})})
    smooth, _ = table(scene)
    assert not smooth.present


def test_emission_directions_have_their_density():
    """emission_direction's samples against emission_pdf_w: the share behind the triangle is
    UNIFORM_SHARE / 2, and a histogram of cos to the normal in 20 bins matches the density's
    integral per bin (chi-square, p > 1e-3)."""
    n = 400_000
    rng = np.random.default_rng(3)
    n_geo = dr.normalize(mi.Vector3f(0.3, -0.5, 0.8))
    u = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    d, pdf = emission_direction(n_geo, u)
    assert np.allclose(np.array(pdf), np.array(emission_pdf_w(n_geo, d)), rtol=1e-5)
    cos = np.array(dr.dot(n_geo, d))
    assert abs((cos < 0).mean() - UNIFORM_SHARE / 2) < 5 * np.sqrt(UNIFORM_SHARE / 2 / n)
    edges = np.linspace(-1, 1, 21)
    counts = np.histogram(cos, edges)[0]
    # density in cos: uniform part 1/2 over [-1, 1], cosine part 2 c over [0, 1]
    cdf = lambda c: UNIFORM_SHARE * (c + 1) / 2 + (1 - UNIFORM_SHARE) * np.clip(c, 0, 1) ** 2   # noqa: E731
    expected = n * np.diff(cdf(edges))
    assert stats.chisquare(counts, expected).pvalue > 1e-3
