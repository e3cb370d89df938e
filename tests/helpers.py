"""Rendering in independent batches and the statistical tests built on them.

A render's error is estimated from K independent batches (different seeds): the batch means'
spread gives the variance of their average without assuming anything about the per-sample
distribution, and works for light-image splats, which cross pixels."""

import fcntl
import hashlib
import os
import re

import drjit as dr
import mitsuba as mi
import numpy as np
from scipy import stats

from bdpt_jit.jit_guard import collector_paused

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = os.path.join(REPO, 'scenes')
CACHE = os.path.join(REPO, 'tests', '.refcache')
STORE = os.path.join(REPO, 'tests', 'references')      # committed: see tests/references/README.md


def assert_finite(img, what='image'):
    a = np.asarray(img)
    bad = ~np.isfinite(a)
    assert not bad.any(), f"{what}: {bad.sum()} non-finite values"
    return a


def render_batches(scene, integrator, spp, batches, seed0=0):
    """K renders with seeds seed0..seed0+K-1; returns an array (K, H, W, 3). Every pixel of
    every batch is checked finite."""
    if isinstance(integrator, dict):
        integrator = mi.load_dict(integrator)
    out = []
    for b in range(batches):
        # no cyclic collection inside the render: Mitsuba's own integrators (the references)
        # too, whose kernels Dr.Jit 1.5.0 may fail to compile if an earlier test's object is
        # freed while they are traced (bdpt_jit/jit_guard.py does this for bdpt's renders)
        with collector_paused():
            img = mi.render(scene, integrator=integrator, spp=spp, seed=seed0 + b)
        a = assert_finite(img, f'batch {b}')[:, :, :3]
        out.append(np.array(a, dtype=np.float64))
    return np.stack(out)


def cached_reference(key_parts, make):
    """A reference render: from tests/references (committed, float32, see its README) where it
    holds one, else from tests/.refcache (ignored by git), else ``make()`` (cached there), keyed
    by what made it (``key_parts``: scene_fingerprint where a scene is rendered) and the Mitsuba
    version. With BDPT_STORE_REFERENCES set, every reference a test uses is written to
    tests/references too."""
    key = hashlib.sha1(repr((mi.__version__,) + tuple(key_parts)).encode()).hexdigest()[:16]
    stored = os.path.join(STORE, key + '.npz')
    if os.path.exists(stored):
        with np.load(stored) as f:
            return f['batches'].astype(np.float64)
    path = os.path.join(CACHE, key + '.npy')
    if os.path.exists(path):
        return store_reference(stored, np.load(path))
    os.makedirs(CACHE, exist_ok=True)
    # pytest-xdist workers (scripts/test.sh with BDPT_TEST_WORKERS) that need the same reference
    # wait for the one rendering it instead of rendering it again
    with open(path + '.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if os.path.exists(path):
            return store_reference(stored, np.load(path))
        arr = make()
        tmp = path + f'.{os.getpid()}.tmp.npy'
        np.save(tmp, arr)
        os.replace(tmp, path)
    return store_reference(stored, arr)


def store_reference(path, arr):
    """``arr``, written to the committed store at ``path`` first where BDPT_STORE_REFERENCES is
    set: as float32, which holds it exactly (renders are float32; render_batches widens them)."""
    if os.environ.get('BDPT_STORE_REFERENCES') and not os.path.exists(path):
        narrow = arr.astype(np.float32)
        assert np.array_equal(narrow.astype(np.float64), arr), 'a reference that float32 does not hold'
        os.makedirs(STORE, exist_ok=True)
        tmp = path + f'.{os.getpid()}.tmp.npz'
        np.savez_compressed(tmp, batches=narrow)
        os.replace(tmp, path)
    return arr


def scene_fingerprint(scene):
    """A digest of what ``scene`` (a loaded mi.Scene) renders: its description (str: every
    object, its type and settings) and the value of each of its parameters (mi.traverse: meshes,
    textures, transforms), both independent of the order Mitsuba lists them in and of
    addresses. Part of a reference's key, so that an edited scene never meets a stored
    reference of its old form."""
    params = mi.traverse(scene)
    entries = []
    for name in params.keys():
        if name.endswith('vertex_normals'):     # computed from the positions and faces, in any order
            continue
        try:
            value = params[name]
        except TypeError:               # Mitsuba 3.9.1's hair lists a parameter it cannot return
            value = None
        try:
            data = np.asarray(value, dtype=np.float64).tobytes()
        except (TypeError, ValueError, RuntimeError):
            data = repr(value).encode()
        # unnamed objects are named by their address ('object_140377449984736.position')
        entries.append((re.sub(r'object_\d+', 'object', name), hashlib.sha1(data).hexdigest()))
    # (the description's lines as a multiset: Mitsuba lists a scene's children in no fixed order)
    lines = sorted(line.strip() for line in str(scene).splitlines())
    return hashlib.sha1(repr((lines, sorted(entries))).encode()).hexdigest()[:16]


def cornell_scene(*args, **kwargs):
    """The tests' one Cornell box, stability_cases.cornell (same arguments), loaded."""
    from stability_cases import cornell
    return mi.load_dict(cornell(*args, **kwargs))


def load_scene(name, res, max_depth):
    """The scene file ``name`` of scenes/ at ``res`` x ``res`` (its own integrator: Mitsuba's
    ``path``; every test passes the one it renders with)."""
    return mi.load_file(scene_path(name), res=res, max_depth=max_depth, integrator='path')


def reference(scene_key, load, integrator, spp, batches, seed0):
    """Reference batches (render_batches), cached (cached_reference): ``integrator`` (a dict) on
    the scene ``load()`` in ``batches`` batches of ``spp`` samples, seeds from ``seed0``.
    ``scene_key`` names the scene, scene_fingerprint tells its content; the integrator's
    parameters, spp, batches and seed0 complete the key."""
    scene = load()
    key = (scene_key, scene_fingerprint(scene), tuple(sorted(integrator.items())), spp, batches, seed0)
    return cached_reference(key, lambda: render_batches(scene, integrator, spp, batches, seed0=seed0))


def file_reference(name, res, max_depth, which, spp, batches, seed0, **params):
    """``reference`` of Mitsuba's integrator ``which`` (with max_depth and ``params``) on the
    scene file ``name`` (load_scene)."""
    return reference((name, res, max_depth), lambda: load_scene(name, res, max_depth),
                     {'type': which, 'max_depth': max_depth, **params}, spp, batches, seed0)


def welch(a, b, floor=0.0):
    """Per-entry Welch t-test of the means of batches a (K1, ...) and b (K2, ...).
    Returns two-sided p-values (1 where both are noise-free and equal, 0 where they differ).
    ``floor``: a relative resolution added to the standard error (floor times the larger mean),
    for entries that are deterministic up to float32 rounding in one estimator and not the other."""
    k1, k2 = a.shape[0], b.shape[0]
    m1, m2 = a.mean(0), b.mean(0)
    v1, v2 = a.var(0, ddof=1) / k1, b.var(0, ddof=1) / k2
    se2 = v1 + v2 + (floor * np.maximum(np.abs(m1), np.abs(m2))) ** 2
    diff = m1 - m2
    with np.errstate(divide='ignore', invalid='ignore'):
        t = diff / np.sqrt(se2)
        df = se2 ** 2 / (v1 ** 2 / (k1 - 1) + v2 ** 2 / (k2 - 1))
    p = 2 * stats.t.sf(np.abs(t), np.where(np.isfinite(df), df, 1.0))
    exact = se2 == 0
    p = np.where(exact, np.where(np.abs(diff) <= 1e-6 * np.maximum(np.abs(m1), np.abs(m2)) + 1e-12, 1.0, 0.0), p)
    return p


def agreement(a, b, alpha=0.01, mask=None, floor=0.0, pixels=True):
    """Welch's t per pixel and channel with Sidak's correction at level alpha over all the
    tested entries, plus the same test on 4x4-pixel blocks (more power against small regional
    bias). ``floor``: welch's relative resolution. ``pixels`` False: the pixels' test is
    reported, not required (where a strategy with a fixed share of some pixel's light samples it
    less than once in all the batches, as uniform weights leave it). Returns (passed, message)."""
    if mask is None:
        mask = np.ones(a.shape[1:3], bool)
    p_px = welch(a, b, floor)[mask]
    def blocks(x):
        K, H, W, C = x.shape
        h, w = H // 4 * 4, W // 4 * 4
        return x[:, :h, :w].reshape(K, h // 4, 4, w // 4, 4, C).mean(axis=(2, 4))
    bm = mask[:mask.shape[0] // 4 * 4, :mask.shape[1] // 4 * 4]
    bm = bm.reshape(bm.shape[0] // 4, 4, bm.shape[1] // 4, 4).all(axis=(1, 3))
    p_bl = welch(blocks(a), blocks(b), floor)[bm]
    msgs, ok = [], True
    for name, p in (('pixel', p_px), ('4x4 block', p_bl)):
        n = p.size
        if n == 0:
            continue
        thr = 1 - (1 - alpha) ** (1 / n)
        worst = p.min()
        if worst < thr and (pixels or name != 'pixel'):
            ok = False
        msgs.append(f'{name}: {n} tests, min p {worst:.3g} vs Sidak threshold {thr:.3g}'
                    + ('' if pixels or name != 'pixel' else ' (not required)'))
    ma, mb = a.mean(axis=0)[mask].mean(), b.mean(axis=0)[mask].mean()
    msgs.append(f'masked means {ma:.6g} vs {mb:.6g} ({(ma - mb) / mb * 100 if mb else 0:+.3f}%)')
    return ok, '; '.join(msgs)


def scene_path(name):
    return os.path.join(SCENES, name)


def no_delta_mask(scene):
    """Pixels whose whole footprint (8x8 sub-pixel probes, dilated by one pixel) sees only
    surfaces without a delta lobe, and no environment: where light tracing (ptracer, lt) can
    render every path."""
    sensor = scene.sensors()[0]
    film = sensor.film()
    w, h = film.crop_size()
    g = 8
    iy, ix, sy, sx = np.meshgrid(np.arange(h), np.arange(w), np.arange(g), np.arange(g), indexing='ij')
    u = (ix + (sx + 0.5) / g) / w
    v = (iy + (sy + 0.5) / g) / h
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u.ravel(), v.ravel()), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    bad_probe = (mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta) & si.is_valid()) | ~si.is_valid()
    bad = np.array(bad_probe, dtype=bool).reshape(h, w, g * g).any(axis=2)
    dil = bad.copy()
    dil[1:] |= bad[:-1]; dil[:-1] |= bad[1:]; dil[:, 1:] |= bad[:, :-1]; dil[:, :-1] |= bad[:, 1:]
    return ~dil


def uv_sphere(n_theta, n_phi):
    """Unit UV sphere: vertices (V, 3) float64 (each also its own outward normal) and triangles
    (F, 3) uint32 with outward winding, poles first."""
    verts = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    for i in range(1, n_theta):
        th = np.pi * i / n_theta
        for j in range(n_phi):
            ph = 2 * np.pi * j / n_phi
            verts.append([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])

    def ring(i, j):
        return 2 + (i - 1) * n_phi + j % n_phi
    faces = []
    for j in range(n_phi):
        faces.append([0, ring(1, j), ring(1, j + 1)])
        faces.append([1, ring(n_theta - 1, j + 1), ring(n_theta - 1, j)])
    for i in range(1, n_theta - 1):
        for j in range(n_phi):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    return np.array(verts, np.float64), np.array(faces, np.uint32)
