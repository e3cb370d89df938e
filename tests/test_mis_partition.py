"""Partition of unity of the recursive MIS weights (mis.py) on random paths.

Each random path x_0 (on an emitter) ... x_k (the pinhole) gets random geometry (squared
distances, cosines) and random densities at every vertex: diffuse-like (pdf ~ 1/pi),
glossy (pdf up to 1e4) and delta vertices. An independent brute-force computation forms the
full-path density p_s of every strategy as the product of its per-vertex area densities
(Veach's thesis, eq. 10.9) and the weight h(p_s) / sum_j h(p_j) over the strategies the
technique allows and the delta vertices do not forbid. The recursive weights, obtained by
walking each subpath through mis.py exactly as the kernels do, must equal it (relative 1e-5),
sum to 1 over the strategies, and be finite and in [0, 1].

Technique ``vcm`` adds the merging strategies (mis.py, Georgiev's report): one per non-delta
interior vertex x_i (1 <= i <= k-1), whose density is that of the connection ending the light
subpath at x_i times the camera's density of x_i times eta = pi r^2 N (random per path); the
brute force adds them to the sum, and their recursive weights (``weight_merge``) must be part of
the partition.

Paths start on each emitter kind (endpoints.py): area (a surface point), delta position
(point/spot: discrete position, no s=0 and no s=1,t=1), delta direction (directional: a
discrete direction, its first edge from a disk, per unit projected area) and environment
(constant/envmap: a direction per unit solid angle, first edge from a disk) and a surface
emitting along its normal only (directionalarea: no s=0 and no s=1 at all, since neither a
camera ray nor emitter sampling can find it; x_1's light-side density is common to every
remaining strategy), and end on each
camera kind: a pinhole (z0 fixed) or a thin lens, whose lens point z0 every strategy samples
with the same area density (camera rays and splats alike), which must cancel, or a camera that
light tracing cannot reach (``delta``: orthographic, radiancemeter, ...;
``StrategySet(..., camera_reachable=False)``): no strategy with t=1 exists, bdpt combines hits,
direct and connections, its weights must still sum to one, and ``lt`` is refused."""

import mitsuba as mi
import numpy as np
import pytest

from bdpt_jit.mis import MIS, EmitterDensities, MISState
from bdpt_jit.strategies import StrategySet

M = 512   # random paths per length


KINDS = ('area', 'delta_pos', 'delta_dir', 'env', 'dir_area')


def random_paths(rng, k, delta_prob, emitter='area', media=False):
    # vertex attributes, index 0..k
    d2 = 10.0 ** rng.uniform(-3, 2, size=(M, k))         # edge i: (x_i, x_{i+1})
    cosA = rng.uniform(0.01, 1.0, size=(M, k))            # at x_i towards x_{i+1}
    cosB = rng.uniform(0.01, 1.0, size=(M, k))            # at x_{i+1} towards x_i
    kind = rng.uniform(size=(M, k + 1))
    glossy = 10.0 ** rng.uniform(-1, 4, size=(M, k + 1))
    diffuse = rng.uniform(0.05, 1.0, size=(M, k + 1)) / np.pi
    pL = np.where(kind < 0.5, diffuse, glossy)             # density towards x_{i+1}
    pE = np.where(kind < 0.5, diffuse * rng.uniform(0.3, 3, size=(M, k + 1)),
                  glossy * rng.uniform(0.1, 10, size=(M, k + 1)))  # towards x_{i-1}
    delta = rng.uniform(size=(M, k + 1)) < delta_prob
    delta[:, 0] = False
    delta[:, k] = False
    pL = np.where(delta, 1.0, pL)                          # discrete lobe: same both ways
    pE = np.where(delta, 1.0, pE)
    # participating media (media.py): medium vertices (cosine 1 on both sides, never delta) and
    # every edge's distance densities towards x_{i+1} (lf) and towards x_i (lb): sigma_t T per
    # unit length at a medium vertex, T at a surface, here random over four decades
    lf, lb = np.ones((M, k)), np.ones((M, k))
    med = np.zeros((M, k + 1), bool)
    if media:
        med = rng.uniform(size=(M, k + 1)) < 0.4
        med[:, 0] = med[:, k] = False
        delta &= ~med
        pL, pE = np.where(med, diffuse, pL), np.where(med, diffuse * rng.uniform(0.3, 3, size=(M, k + 1)), pE)
        cosA = np.where(med[:, :k], 1.0, cosA)
        cosB = np.where(med[:, 1:], 1.0, cosB)
        lf, lb = 10.0 ** rng.uniform(-3, 1, size=(M, k)), 10.0 ** rng.uniform(-3, 1, size=(M, k))
    pA_light0 = 10.0 ** rng.uniform(-2, 2, size=M)
    p_direct_a = 10.0 ** rng.uniform(-2, 2, size=M)
    if emitter in ('delta_pos', 'delta_dir'):
        p_direct_a = pA_light0      # emitter sampling of a delta emitter: its choice probability
    return dict(
        k=k, d2=d2, cosA=cosA, cosB=cosB, pL=pL, pE=pE, delta=delta,
        pA_light0=pA_light0,                               # choice x position density of x_0
        p_direct_a=p_direct_a,                             # emitter sampling of x_0 from x_1
        pdir_e=rng.uniform(0.01, 1.0, size=M) / np.pi,     # emitted direction
        p_cam_w=10.0 ** rng.uniform(-1, 2, size=M),        # We of the direction x_k -> x_{k-1}
        p_disk=np.full(M, 10.0 ** rng.uniform(-3, 1)),     # 1 / (pi R^2) of infinite emitters
        eta=10.0 ** rng.uniform(-2, 3, size=M),            # pi r^2 N of vertex merging
        radius=10.0 ** rng.uniform(-3, 1, size=M),         # r (media: a merge at a medium vertex has 4/3 pi r^3 N)
        sigma=10.0 ** rng.uniform(-3, 3, size=(M, k + 1)),  # sigma_t at x_i (beams: merges there 1 / sigma_t)
        emitter=emitter, media=media, lf=lf, lb=lb, med=med,
    )


def allowed(technique, k, s, P):
    """Strategies the technique uses, and delta vertices forbid (connection endpoints)."""
    t = k + 1 - s
    if t < 1:
        return np.zeros(M, bool)
    if P.get('camera') == 'delta' and t == 1:
        return np.zeros(M, bool)           # no light path reaches the camera
    if P['emitter'] != 'area' and s == 1 and t == 1:
        return np.zeros(M, bool)           # only a surface emitter can be seen by the camera
    if P['emitter'] in ('delta_pos', 'delta_dir', 'dir_area') and s == 0:
        return np.zeros(M, bool)           # a delta emitter cannot be hit
    if P['emitter'] == 'dir_area' and s == 1:
        return np.zeros(M, bool)           # nor can emitter sampling find a directional surface
    if technique == 'vm':
        return np.zeros(M, bool)           # (the ppm partition is not a weighting: test_merging)
    if technique == 'pt' and not (s == 0 or (s == 1 and t >= 2)):
        return np.zeros(M, bool)
    if technique == 'lt' and t != 1:
        return np.zeros(M, bool)
    ok = np.ones(M, bool)
    if s >= 1:
        ok &= ~P['delta'][:, s - 1]
        ok &= ~P['delta'][:, s] if s <= k - 1 else True
    return ok


def merge_allowed(k, i, P, everywhere=False):
    """Merging at x_i: an interior vertex (a light vertex y_i, i >= 1, met by a camera vertex
    z_{k-i}, k-i >= 1) with a smooth BSDF; unless merges are everywhere (``vcm_all``: technique
    vcm with merge_everywhere), one whose camera-side neighbour x_{i+1} is delta."""
    if not 1 <= i <= k - 1:
        return np.zeros(M, bool)
    ok = ~P['delta'][:, i]                                 # (medium vertices: never delta)
    return ok if everywhere else ok & P['delta'][:, i + 1]


def merge_volume(P, i):
    """A merge at x_i relative to a surface merge at a medium vertex: a ball, eta_vol / eta =
    4 r / 3; a beam (``P['beams']``), P(s) / (sigma_t T) = 1 / sigma_t(x_i) (beams.py), times
    the beams' share of the light subpaths, N_b / N (``P['beam_share']``, merge.MergeSchedule)."""
    vol = P.get('beam_share', 1.0) / P['sigma'][:, i] if P.get('beams') else 4.0 * P['radius'] / 3.0
    return np.where(P['med'][:, i], vol, 1.0)


def camera_density(P, i):
    """The camera subpath's density of x_i per unit area (from x_{i+1}; the pinhole's from x_k),
    with the distance density of edge i (media; 1 without)."""
    k = P['k']
    if i == k - 1:
        return P['p_cam_w'] * P['cosA'][:, k - 1] / P['d2'][:, k - 1] * P['lb'][:, k - 1]
    return P['pE'][:, i + 1] * P['cosA'][:, i] / P['d2'][:, i] * P['lb'][:, i]


def chain_free(k, s, P):
    """The light subpath x_0 .. x_{s-1} has no delta vertex (MIS.camera_chains)."""
    return ~P['delta'][:, 1:max(s, 1)].any(axis=1) if s > 1 else np.ones(M, bool)


def strategy_count(k, s, counts):
    """The sample count of strategy s on a path of k edges [Veach 9.2.2] (light vertex cache,
    tests/test_light_cache.py: ``counts`` = (n_c, n_lt) or (n_c, n_lt, n_m) per path; None: all
    1): hits and emitter sampling 1, connections n_c, light tracing (t=1) n_lt."""
    if counts is None:
        return 1.0
    n_c, n_lt = counts[:2]
    t = k + 1 - s
    if t == 1:
        return n_lt
    return n_c if s >= 2 else 1.0


def merge_count(counts):
    """The merges' count relative to eta (moments.py's merge family: ``counts`` (n_c, n_lt, n_m));
    1 where ``counts`` has none."""
    return 1.0 if counts is None or len(counts) < 3 else counts[2]


def brute_force(kind, technique, P, p_lens=None, chains=False, counts=None):
    everywhere = technique == 'vcm_all'
    technique = 'vcm' if everywhere else technique
    k = P['k']
    d2, cosA, cosB, pL, pE = P['d2'], P['cosA'], P['cosB'], P['pL'], P['pE']
    beta = {'power': 2.0, 'balance': 1.0}.get(kind)
    dens, raw = [], []
    for s in range(k + 1):
        t = k + 1 - s
        p = np.ones(M)
        ek = P['emitter']
        infinite = ek in ('delta_dir', 'env')
        for i in range(s):                                  # light-side vertices
            if i == 0:
                if ek == 'env':                             # a direction, per unit solid angle
                    p = p * (P['p_direct_a'] if (s == 1 and t >= 2) else P['pA_light0'] * P['pdir_e'])
                else:
                    p = p * (P['p_direct_a'] if (s == 1 and t >= 2) else P['pA_light0'])
            elif i == 1:
                if ek == 'env':
                    p = p * P['p_disk'] * cosB[:, 0]
                elif ek == 'delta_dir':
                    p = p * P['p_disk'] * cosB[:, 0]
                elif ek == 'dir_area':                     # along x_0's normal: common to all
                    p = p * cosB[:, 0]
                else:
                    p = p * P['pdir_e'] * cosB[:, 0] / d2[:, 0]
            else:
                p = p * pL[:, i - 1] * cosB[:, i - 1] / d2[:, i - 1]
            if i >= 1:
                p = p * P['lf'][:, i - 1]                   # x_i sampled along edge i-1 (media)
        for i in range(s, k):                               # camera-side vertices (x_k: pinhole, 1)
            p = p * P['lb'][:, i]                           # x_i sampled along edge i (media)
            if i == k - 1:
                p = p * P['p_cam_w'] * cosA[:, k - 1] / d2[:, k - 1]
            elif i == 0 and infinite:                       # the camera samples a direction
                p = p * pE[:, 1]
            else:
                p = p * pE[:, i + 1] * cosA[:, i] / d2[:, i]
        if p_lens is not None:                              # thin lens: z0 sampled on the lens
            p = p * p_lens
        raw.append(p)
        p = p * strategy_count(k, s, counts)
        ok = allowed(technique, k, s, P) & (chain_free(k, s, P) if chains else True)
        dens.append(np.where(ok, p, 0.0))
    if technique == 'vcm':
        dens += [np.where(merge_allowed(k, i, P, everywhere),
                          raw[i + 1] * camera_density(P, i) * P['eta'] * merge_volume(P, i)
                          * merge_count(counts), 0.0)
                 for i in range(1, k)]
    dens = np.array(dens)
    if kind == 'uniform':
        hp = (dens > 0).astype(float)
    else:
        scale = np.maximum(dens.max(axis=0, keepdims=True), 1e-300)
        hp = (dens / scale) ** beta
    total = hp.sum(axis=0, keepdims=True)
    return np.where(total > 0, hp / np.where(total > 0, total, 1.0), 0.0)


def aligned(cls, a, dtype):
    """``a`` as a Dr.Jit array in memory of Dr.Jit's own (64-byte aligned). An array made from
    numpy reads numpy's buffer, whose alignment enters the kernel's code: the same weights then
    compile again in every test (a kernel-cache miss per evaluation, 0.25 s per test)."""
    return cls(np.broadcast_to(np.asarray(a, dtype=dtype), (M,)).tolist())


def recursive(kind, technique, P, chains=False, counts=None, make_mis=None):
    """Every strategy's weight by the kernels' recursion (``make_mis(strategies)``: another
    mis.MIS than MIS(kind, ...), moments.FamilyMIS)."""
    everywhere = technique == 'vcm_all'
    technique = 'vcm' if everywhere else technique
    k = P['k']
    reachable = P.get('camera') != 'delta'
    strategies = StrategySet(technique, camera_reachable=reachable)
    mis = (MIS(kind, strategies, camera_chains=chains, merge_everywhere=everywhere) if make_mis is None
           else make_mis(strategies))
    F = lambda a: aligned(mi.Float, a, np.float64)           # noqa: E731
    B = lambda a: aligned(mi.Bool, a, bool)                   # noqa: E731
    d2, cosA, cosB, pL, pE, delta_v = (P[n] for n in ('d2', 'cosA', 'cosB', 'pL', 'pE', 'delta'))
    ek = P['emitter']
    infinite = ek in ('delta_dir', 'env')
    delta = ek in ('delta_pos', 'delta_dir', 'dir_area')
    if ek == 'dir_area':
        pdf_emit_w = F(P['pA_light0'])                       # position; the direction is discrete
    elif ek == 'area' or ek == 'delta_pos':
        pdf_emit_w = F(P['pA_light0'] * P['pdir_e'])
    elif ek == 'delta_dir':
        pdf_emit_w = F(P['pA_light0'] * P['p_disk'])         # discrete direction, disk position
    else:
        pdf_emit_w = F(P['pA_light0'] * P['pdir_e'] * P['p_disk'])
    cos_e0 = np.ones(M) if infinite or ek == 'delta_pos' else cosA[:, 0]

    mis.set_radius(F(P['eta']))
    if P.get('media', False):
        mis.set_volume(F(P['radius']), beams=bool(P.get('beams')), beam_share=F(P.get('beam_share', np.ones(M))))
    if counts is not None:
        mis.set_counts(F(counts[0]), F(counts[1]))

    # The subpaths' MIS quantities through the kernels' own event functions (mis.MIS.light_start,
    # camera_start, scatter, hit): each of eqs. 20-22 is then checked where the kernels apply it.
    media = P.get('media', False)
    lf, lb = P['lf'], P['lb']

    def distance(st, fwd, rev):              # an edge distance-sampled through media (MIS.distance)
        return mis.distance(st, F(fwd), F(rev)) if media else st

    def surface(here, i):                    # media: a merge at x_i relative to a surface merge
        if not media or here is False:
            return here
        return mis.merge_factor(B(P['med'][:, i]), here, F(P['sigma'][:, i]))

    def light_state(last):                                   # at x_last (last >= 1): (d_vcm, d_vc, d_vm)
        d2_0 = np.ones(M) if infinite else d2[:, 0]
        p_direct = np.zeros(M) if ek == 'dir_area' else P['p_direct_a']     # endpoints: never sampled
        st = mis.light_start(pdf_emit_w, F(cos_e0), B(np.full(M, delta)), F(p_direct), F(d2_0), F(cosB[:, 0]))
        st = distance(st, lf[:, 0], lb[:, 0])
        for i in range(1, last):
            st = mis.scatter(st, F(cosA[:, i]), F(pL[:, i]), F(pE[:, i]), B(delta_v[:, i]), camera_side=False,
                             merge_here=surface(True, i))
            st = distance(st, lf[:, i], lb[:, i])
            st = mis.hit(st, F(d2[:, i]), F(cosB[:, i]), camera_side=False)
        return st.d_vcm, st.d_vc, st.d_vm

    def camera_state(last):                                  # at x_last (last <= k-1): (d_vcm, d_vc, d_vm)
        st = mis.camera_start(F(P['p_cam_w']), F(d2[:, k - 1]), F(cosA[:, k - 1]))
        st = distance(st, lb[:, k - 1], lf[:, k - 1])
        for i in range(k - 1, last, -1):
            here = surface(mis.merge_here_camera(B(delta_v[:, i + 1])), i)   # the camera (x_k) is not delta
            st = mis.scatter(st, F(cosB[:, i - 1]), F(pE[:, i]), F(pL[:, i]), B(delta_v[:, i]),
                             camera_side=True, merge_here=here)
            st = distance(st, lb[:, i - 1], lf[:, i - 1])
            if not (i - 1 == 0 and infinite):                # an environment is not hit: no conversion
                st = mis.hit(st, F(d2[:, i - 1]), F(cosA[:, i - 1]), camera_side=True)
        return st.d_vcm, st.d_vc, st.d_vm

    out = []
    for s in range(k + 1):
        t = k + 1 - s
        if s == 0:
            c_vcm, c_vc, _ = camera_state(0)
            if ek == 'env':
                w = mis.weight_s0(c_vcm, c_vc, F(P['p_direct_a']), pdf_emit_w) if k > 1 else F(np.ones(M))
            elif delta:
                w = F(np.zeros(M))
            else:
                pdf_direct_a = P['pA_light0'] if k == 1 else P['p_direct_a']
                w = mis.weight_s0(c_vcm, c_vc, F(pdf_direct_a), pdf_emit_w, first_hit=k == 1)
        elif s == 1 and ek == 'dir_area':
            w = F(np.zeros(M))                               # the kernels never form it
        elif s == 1 and t == 1:
            w = mis.weight_s1t1(F(P['p_cam_w'] * cosA[:, 0] / d2[:, 0] * lb[:, 0]), F(P['pA_light0']))
        elif s == 1:
            c_vcm, c_vc, _ = camera_state(1)
            if ek == 'area':
                pdf_direct_w, cos_e = P['p_direct_a'] * d2[:, 0] / cosA[:, 0], cosA[:, 0]
            elif ek == 'delta_pos':
                pdf_direct_w, cos_e = P['p_direct_a'] * d2[:, 0], np.ones(M)
            else:
                pdf_direct_w, cos_e = P['p_direct_a'], np.ones(M)
            # (media: the s=0 strategy reaches x_0 along edge 0 with lb, the light subpath x_1 with lf)
            w = mis.weight_s1(MISState(c_vcm, c_vc), F(pE[:, 1] * lb[:, 0]), F(pL[:, 1]), F(cosB[:, 0]),
                              EmitterDensities(F(pdf_direct_w), pdf_emit_w * F(lf[:, 0]), F(cos_e),
                                               B(np.full(M, delta))),
                              merge_z=surface(mis.merge_here_camera(B(delta_v[:, 2])), 1))
        elif t == 1:
            l_vcm, l_vc, _ = light_state(k - 1)
            w = mis.weight_t1(l_vcm, l_vc, F(P['p_cam_w'] * cosA[:, k - 1] / d2[:, k - 1] * lb[:, k - 1]),
                              F(pE[:, k - 1]), merge_y=surface(everywhere, k - 1) if media else None)
        else:
            l_vcm, l_vc, _ = light_state(s - 1)
            c_vcm, c_vc, _ = camera_state(s)
            w = mis.weight_connect(MISState(l_vcm, l_vc), MISState(c_vcm, c_vc),
                                   F(pE[:, s] * cosA[:, s - 1] / d2[:, s - 1] * lb[:, s - 1]),
                                   F(pL[:, s - 1] * cosB[:, s - 1] / d2[:, s - 1] * lf[:, s - 1]),
                                   F(pE[:, s - 1]), F(pL[:, s]), merge_z=surface(mis.merge_here_camera(B(delta_v[:, s + 1])), s),
                                   merge_y=surface(everywhere, s - 1) if media else None)
        w = np.array(w if isinstance(w, mi.Float) else mi.Float(w), dtype=np.float64)
        w = np.broadcast_to(w, (M,)) if w.size == 1 else w
        if not reachable and t == 1:
            assert np.all(w == 0), f'a light-tracing weight (s={s}, t=1) for an unreachable camera'
        ok = allowed(technique, k, s, P) & (chain_free(k, s, P) if chains else True)
        out.append(np.where(ok, w, 0.0))
    if technique == 'vcm':
        for i in range(1, k):                                # merging at x_i
            l_vcm, _, l_vm = light_state(i)
            c_vcm, _, c_vm = camera_state(i)
            inv_factor = 1.0 / mis.merge_factor(B(P['med'][:, i]), True, F(P['sigma'][:, i])) if media else None
            w = np.array(mis.weight_merge(l_vcm, l_vm, c_vcm, c_vm, F(pE[:, i]), F(pL[:, i]), inv_factor,
                                          own=mis.merge_here_camera(B(delta_v[:, i + 1]))), dtype=np.float64)
            out.append(np.where(merge_allowed(k, i, P, everywhere), w, 0.0))
    return np.array(out)


@pytest.mark.parametrize('camera', ['pinhole', 'thinlens', 'delta'])
@pytest.mark.parametrize('emitter', KINDS)
@pytest.mark.parametrize('technique', ['bdpt', 'pt', 'lt', 'vcm', 'vcm_all'])
@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
@pytest.mark.parametrize('k', list(range(1, 11)))
def test_weights_partition_of_unity(k, kind, technique, emitter, camera):
    rng = np.random.default_rng(1000 * k + 31 * KINDS.index(emitter) + ['power', 'balance', 'uniform'].index(kind))
    P = random_paths(rng, k, delta_prob=0.3, emitter=emitter)
    P['camera'] = camera
    if camera == 'delta' and technique == 'lt':
        with pytest.raises(ValueError, match='lt'):
            StrategySet('lt', camera_reachable=False)      # no strategy left
        return
    w_rec = recursive(kind, technique, P)
    p_lens = 10.0 ** rng.uniform(-1, 3, size=M) if camera == 'thinlens' else None
    w_ref = brute_force(kind, technique, P, p_lens)
    assert np.all(np.isfinite(w_rec))
    assert np.all((w_rec >= 0) & (w_rec <= 1 + 1e-6))
    tech = 'vcm' if technique == 'vcm_all' else technique
    any_strategy = np.array([allowed(tech, k, s, P) for s in range(k + 1)]
                            + ([merge_allowed(k, i, P, technique == 'vcm_all') for i in range(1, k)]
                               if tech == 'vcm' else [])).any(axis=0)
    total = w_rec.sum(axis=0)
    np.testing.assert_allclose(total[any_strategy], 1.0, rtol=1e-5)
    np.testing.assert_allclose(w_rec, w_ref, rtol=1e-5, atol=1e-7)
    assert np.all(w_rec[:, ~any_strategy] == 0)


@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
def test_weights_are_never_nan(kind):
    """A degenerate vertex (a ray that scraped its own surface: cos ~ 0, so the running
    quantities overflow to inf) met by a zero density gives inf * 0 inside a weight: the weight
    is then 0 (mis._finite), never NaN, for every strategy's weight."""
    mis = MIS(kind, StrategySet('bdpt'))
    inf, zero, one = mi.Float(np.inf), mi.Float(0.0), mi.Float(1.0)
    ws = [mis.weight_s0(inf, one, zero, one), mis.weight_s0(one, inf, one, zero),
          mis.weight_s1(MISState(inf, one), one, one, one, EmitterDensities(one, zero, one)),
          mis.weight_connect(MISState(inf, one), MISState(one, one), zero, one, one, one),
          mis.weight_connect(MISState(one, one), MISState(inf, inf), one, zero, one, zero),
          mis.weight_t1(inf, one, zero, one)]
    for w in ws:
        a = np.array(w, dtype=np.float64)
        assert np.all(np.isfinite(a)) and np.all((a >= 0) & (a <= 1))


@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
@pytest.mark.parametrize('emitter', KINDS)
@pytest.mark.parametrize('k', list(range(2, 9)))
def test_camera_chains_partition_of_unity(k, emitter, kind):
    """MIS.camera_chains (geometry derivatives next to mirrors and glass, bdpt): the strategies
    whose light subpath contains a delta vertex are left out; the others' recursive weights
    equal the brute force over that smaller set and sum to one wherever one is left."""
    rng = np.random.default_rng(7000 + 100 * k + 7 * KINDS.index(emitter))
    P = random_paths(rng, k, delta_prob=0.4, emitter=emitter)
    P['camera'] = 'pinhole'
    w_rec = recursive(kind, 'bdpt', P, chains=True)
    w_ref = brute_force(kind, 'bdpt', P, chains=True)
    assert np.all(np.isfinite(w_rec)) and np.all((w_rec >= 0) & (w_rec <= 1 + 1e-6))
    left = np.array([allowed('bdpt', k, s, P) & chain_free(k, s, P) for s in range(k + 1)]).any(axis=0)
    np.testing.assert_allclose(w_rec.sum(axis=0)[left], 1.0, rtol=1e-5)
    np.testing.assert_allclose(w_rec, w_ref, rtol=1e-5, atol=1e-7)


MEDIA_CASES = [(t, m) for t in ('bdpt', 'pt', 'lt', 'vcm', 'vcm_all') for m in ('points', 'beams')
               if m == 'points' or t.startswith('vcm')]


@pytest.mark.parametrize('camera', ['pinhole', 'delta'])
@pytest.mark.parametrize('emitter', KINDS)
@pytest.mark.parametrize('technique,merging', MEDIA_CASES)
@pytest.mark.parametrize('kind', ['power', 'balance', 'uniform'])
@pytest.mark.parametrize('k', [1, 2, 3, 5, 8])
def test_weights_partition_of_unity_with_media(k, kind, technique, merging, emitter, camera):
    """Paths with medium vertices (cosine 1, phase-function densities) and every edge
    distance-sampled (random forward and reverse distance densities, mis.MIS.distance and the
    strategies' pdf_l): the recursive weights equal the brute force's and sum to 1 (issue 23,
    test 3). vcm merges inside media too: in a ball (4/3 pi r^3 N) or along beams (1 / sigma_t
    of the vertex relative to a surface merge, times the share N_b / N of the light subpaths the
    beams gather from, random here; mis.MIS.set_volume)."""
    rng = np.random.default_rng(7000 + 1000 * k + 31 * KINDS.index(emitter) + ['power', 'balance', 'uniform'].index(kind))
    P = random_paths(rng, k, delta_prob=0.3, emitter=emitter, media=True)
    P['camera'] = camera
    P['beams'] = merging == 'beams'
    if P['beams']:
        P['beam_share'] = rng.uniform(0.05, 1.0, size=M)
    if camera == 'delta' and technique == 'lt':
        return
    w_rec = recursive(kind, technique, P)
    w_ref = brute_force(kind, technique, P)
    assert np.all(np.isfinite(w_rec))
    tech = 'vcm' if technique == 'vcm_all' else technique
    any_strategy = np.array([allowed(tech, k, s, P) for s in range(k + 1)]
                            + ([merge_allowed(k, i, P, technique == 'vcm_all') for i in range(1, k)]
                               if tech == 'vcm' else [])).any(axis=0)
    np.testing.assert_allclose(w_rec.sum(axis=0)[any_strategy], 1.0, rtol=1e-5)
    np.testing.assert_allclose(w_rec, w_ref, rtol=1e-5, atol=1e-7)
