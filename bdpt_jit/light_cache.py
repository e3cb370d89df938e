"""The light vertex cache (Davidovic, Krivanek, Hasan and Slusallek, "Progressive light transport
simulation on the GPU: survey and improvements", ACM TOG 2014; SeeSharp's ``VertexCacheBidir``):
a pass traces n_L light subpaths, a ratio ``light_paths`` of its n camera samples, not one per
camera sample; their stored vertices (store.LightStore, level-major) form one cache, and each
camera vertex is connected to ``connections`` = c vertices drawn uniformly from all V of them.

The estimator. For a camera vertex z, the classic estimator sums the connections C(z, y) to
the vertices y of one light subpath. Drawing c vertices uniformly from the V cached vertices
of n_L independent light subpaths and weighting each by V / (c n_L) has the same expectation:
given the light subpaths, E[(V / (c n_L)) sum_k C(z, y_k)] = (1 / n_L) sum_{all cached y} C(z, y),
whose expectation is the classic sum (V = 0: no vertex, both 0). Light tracing splats n_L
light subpaths for n camera samples, each with the classic scale times n / n_L.

The MIS counts [Veach 9.2.2] (n_i p_i, relative to one camera sample; mis.MIS.set_counts): a
connection samples a path with density p_light p_camera times the expected number of draws that
land on its light vertex, c n_L p / V, so n_c = c n_L / V; light tracing n_lt = n_L / n; hits
and emitter sampling 1. The weights may use any counts that all strategies share (they still
sum to one), but counts taken from the very samples they weight would correlate with them (V
holds the connected subpath's own vertices: a bias of order 1 / n_L). So n_c is measured once
per render by a pilot light pass of independent samples (``pilot``): n_c = c / (V / n_L)_pilot;
the estimator's own factor V / (c n_L) is the pass's, which makes it exact for any V.

Uniform draws need the slot of the k-th valid vertex: the store's valid slots compressed
(store.LightStore.stored_slots, as the photon grid is built), in one pass over the store."""

import drjit as dr
import mitsuba as mi

from .passes import pass_sampler

PILOT_PATHS = 1 << 13           # light subpaths of the pilot pass: V / n_L to ~1% (it only sets MIS counts)
PILOT_PASS = 1 << 24            # the pilot's pass index for pass_seed: no render has that many


class CacheSettings:
    """The cache's parameters, one field a line (Context.light_cache)."""

    def __init__(self, ratio, connections):
        self.ratio = ratio                  # light subpaths per camera sample (parameter light_paths)
        self.connections = connections      # c (parameter connections); -1: from the pilot

    def light_paths(self, spp_pass, pixel_count):
        """n_L of a pass: whole light subpaths per pixel of each of its spp_pass iterations."""
        return spp_pass * max(1, int(round(self.ratio * pixel_count)))


class LightCache:
    """The pass's cached light vertices as a list of slots, and the uniform draw from it.

    store     store.LightStore of the pass's n_L light subpaths
    slots     mi.UInt32: the store slot of the k-th valid vertex, k < V
    count     mi.UInt32 (width 1): V, the valid vertices
    c         mi.UInt32 (width 1, opaque): connections per camera vertex
    scale     mi.Float (width 1): V / (c n_L), each connection's estimator factor"""

    def __init__(self, store, c):
        self.store = store
        slots = store.stored_slots()
        self.slots = slots if dr.width(slots) > 0 else dr.zeros(mi.UInt32, 1)
        self.count = dr.opaque(mi.UInt32, dr.width(slots))     # (a literal would recompile per V)
        self.c = dr.opaque(mi.UInt32, c)
        self.scale = self.scale_for(self.c)
        dr.eval(self.slots, self.count, self.scale)

    def scale_for(self, c):
        """V / (c n_L) for a draw count ``c`` per lane (per-pixel counts, pixel_counts.py; 0 where c = 0)."""
        cf = mi.Float(c)
        return dr.select(cf > 0, mi.Float(self.count) / (dr.maximum(cf, 1.0) * mi.Float(self.store.n_opaque)), 0.0)

    def draw(self, u, active):
        """A cached vertex drawn by ``u`` (two uniform numbers in [0, 1)): (its slot, its level,
        whether there is one). The rank is the high word of a 32-bit random integer times V (16
        bits of each number): each rank gets 2^32 / V values, rounded down or up, so draws are
        uniform to V / 2^32 (a float u * V would be to V / 2^23, the float's 23 random bits:
        over 1% at 10^5 vertices)."""
        bits = (mi.UInt32(u[0] * 65536.0) << 16) | mi.UInt32(u[1] * 65536.0)
        k = dr.minimum(dr.mul_hi(bits, self.count), self.count - 1)
        ok = active & (self.count > 0)
        slot = dr.gather(mi.UInt32, self.slots, k, ok)
        return slot, slot // self.store.n_opaque, ok


def vertices_per_path(store, n):
    """(V / n_L) of a traced store, as a Python float (one read back)."""
    total = dr.sum(store.count) if store is not None else mi.UInt32(0)
    return float(mi.Float(total)[0]) / max(n, 1)


def pilot(integrator, ctx, seed, n_light):
    """Vertices a light subpath stores on average, from a pilot light pass of independent
    samples (seed ``pass_seed(seed, PILOT_PASS)``, no splats) of ``n_light`` subpaths (the render's
    light subpaths, at least 256), at most PILOT_PATHS."""
    from .light_path import LightTracer
    from .passes import PassState
    from .store import LightStore
    n = max(1, min(n_light, PILOT_PATHS))
    cap = integrator.light_capacity(ctx)
    if cap <= 0:
        return 0.0
    sampler = pass_sampler(ctx, 1, seed, PILOT_PASS, n)
    ps = PassState(sampler, n, 1, 0, None, ctx.mis)
    ps.store = LightStore(n=n, capacity=cap, record=ctx.record)
    ps.pilot = True
    stats, ctx.stats = ctx.stats, None          # the pilot's rays are not the render's
    try:
        LightTracer(ctx, ps).trace()
        return vertices_per_path(ps.store, n)
    finally:
        ctx.stats = stats


def counts(vpp, c, n_light, n_camera, connects):
    """The MIS counts of a pass (mis.MIS.set_counts): (n_c, n_lt) with n_c = c / (V / n_L) of
    the pilot (``vpp``; None without connections), n_lt = n_L / n."""
    n_lt = dr.opaque(mi.Float, n_light / n_camera)
    if not connects:
        return None, n_lt
    return dr.opaque(mi.Float, c / max(vpp, 1e-3)), n_lt
