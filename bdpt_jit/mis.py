"""Multiple importance sampling weights of every (s,t) strategy, computed recursively.

This module is the only place where MIS weights are formed. Tags ``[eq. N]`` refer to the seed
paper, M. Vlnas, "Bidirectional Path Tracing" (Brno University of Technology), eqs. (17)-(22),
after Veach and Georgiev: the weight of strategy (s,t) is

    w_{s,t} = 1 / (w_light + 1 + w_camera)                                          (eq. 20)

where w_light sums h(p_i / p_s) over the strategies with fewer light vertices (i < s) and
w_camera over those with more (i > s); h(x) = x^beta is the heuristic (eq. 17/18). Both sums
are built up vertex by vertex while each subpath is traced (eq. 21), in the split form of
eq. (22), which Georgiev's report ("Implementing Vertex Connection and Merging", 2012) writes
with the two running quantities that this code calls ``d_vcm`` and ``d_vc``:

    paper eq. 22          this code
    vc_i  = 1 / p->_i     d_vcm   (holds 1 / the forward density of the last vertex)
    vcm_i = recursion     d_vc    (holds the sum over all strategies further back)

Every quantity is already passed through the heuristic h, so the same recursion gives the
power (beta=2), balance (beta=1) and uniform (beta=0, with h(0)=0) weightings: h is
multiplicative, h(ab) = h(a) h(b), for all three.

Densities carry their measure in their names: ``pdf_w`` per unit solid angle, ``pdf_a`` per
unit area (per unit volume at a medium vertex), ``pdf_l`` the distance density of an edge
through media.

Participating media (media.py, media_path.py): a vertex sampled across an edge through media
has the edge's distance density ``pdf_l`` in its density (sigma_t T per unit length at a
medium vertex, T at a surface), and no cosine at a medium vertex (cos = 1). The walk's edges
enter the running quantities through ``distance``; the strategies pass every density of a
vertex sampled across their own edge with its ``pdf_l`` already in it (pdf_a = pdf_w |cos| /
d^2 * pdf_l, eq. 9 with distance sampling), so the weights below read the same with and
without media. A merge at a medium vertex y is a beam (beams.py: the camera ray's segment
through the medium gathers the light vertices within r of it; its density relative to a
surface merge's is 1 / sigma_t(y)) or, in media whose sigma_t differs between channels, a
ball (eta_vol = 4/3 pi r^3 N, against pi r^2 N on a surface: 4 r / 3): the running
quantities stay relative to a surface merge, and where a merge may be made the ``merge_*``
arguments carry, in scenes with media, that merge's factor (``merge_factor``: 1 on a
surface, h(1 / sigma_t) or h(4 r / 3) at a medium vertex, 0 where no merge is offered)
instead of a mask.

Conventions for the strategies (s light vertices, t camera vertices, endpoints counted):
- camera paths are sampled one per light path, so the light-tracing strategies (t=1) are
  weighted with the camera's solid-angle density We(omega) normalised over the crop window;
- s=1 with t>=2 is emitter sampling from the camera vertex (endpoints.EmitterTable.sample_direct:
  Mitsuba's ``sample_emitter_direction``, or the visible cone of a small-looking sphere); its
  density ``pdf_direct_a`` may depend on that vertex (the cone or cap a sphere shows it), which
  is why the light subpath evaluates it at its first hit;
- s=1, t=1 splats the light subpath's first vertex y0 (its density: emission position).
- Russian roulette is left out of all densities (a valid choice: the weights still sum to 1).
- Sample counts [Veach 9.2.2] (n_i p_i; the light vertex cache, light_cache.py, ``set_counts``):
  hits and emitter sampling count 1, connections n_c = c n_L / V (c draws from V cached vertices
  of n_L light subpaths per camera vertex), light tracing n_lt = n_L / n (n camera samples), merges
  eta. Without the cache both are 1 and nothing of them is traced. Each scatter's new d_vcm holds
  h(n_c) (the strategy ending the light subpath there is a connection), the camera's start h(n_lt);
  weight_s0 takes n_c back out where its s=1 term is emitter sampling, and the weights of a
  connection and a splat divide the others' sum by their own count.

Vertex merging (technique ``vcm``) adds one strategy per non-delta interior vertex: the camera
vertex merged with a light vertex of any light subpath of the pass within the radius r
(merge.py). Its density relative to the connection that ends the light subpath at the same
vertex is eta = pi r^2 N (N light subpaths). Tags ``[VCM (N)]`` are equation numbers of
Georgiev, Krivanek, Davidovic and Slusallek, "Implementing Vertex Connection and Merging"
(technical report, 2012), whose third running quantity this code calls ``d_vm``; the merging
terms enter the connection weights through ``vm_factor`` = h(eta) and the merging weights
through ``vc_factor`` = h(1/eta) (0 for a family the technique does not use). Technique ``vm``
(progressive photon mapping) needs no weights: its strategies are a partition (strategies.py).

Where merging is offered (``merge_everywhere``): Georgiev et al. merge at every non-delta
interior vertex. By default this code merges only at a vertex whose camera-side neighbour is a
delta vertex (the camera reached it through a mirror or glass): the specular-diffuse-specular
paths that no connection samples all have one, and a merge anywhere else only duplicates a
connection at the cost of a gather. The strategy set is then still a function of the path, so
the weights still sum to one: the camera side knows the neighbour when it scatters (its previous
vertex), and the light side learns it one vertex later, so the term of a merge at a light vertex
waits in ``pend_vc``/``pend_vm`` until the next vertex turns out delta (``absorb_pending``) or
not (dropped); the last light vertex of a connection, splat or merge has a non-delta neighbour.
"""

import copy

import drjit as dr
import mitsuba as mi

from .strategies import StrategySet


class MISState:
    """The running MIS quantities of one subpath, as its walk carries them (all under h)."""
    DRJIT_STRUCT = {
        'd_vcm': mi.Float,      # [eq. 22] vc_i: 1 / the forward density of the current vertex
        'd_vc': mi.Float,       # [eq. 22] vcm_i: the strategies further back, recursively (eq. 21)
        'd_vm': mi.Float,       # [VCM (33), (36)] the merges further back (vcm; 0 otherwise)
        'pend_vc': mi.Float,    # light side, merges behind delta only: the last vertex's merge in d_vc, waiting
        'pend_vm': mi.Float,    # the same merge's term in d_vm (absorb_pending)
    }

    def __init__(self, d_vcm=None, d_vc=None, d_vm=None, pend_vc=None, pend_vm=None):
        self.d_vcm, self.d_vc, self.d_vm = d_vcm, d_vc, d_vm
        self.pend_vc, self.pend_vm = pend_vc, pend_vm


def _gate(x, ok):
    """x where ``ok`` (a mask, or True/False), else 0; x times ``ok`` where it is a factor (a
    merge's density relative to a surface merge: merges inside media, ``MIS.merge_factor``) or
    a family vector (the merge's family: moments.FamilyMIS's ``split``)."""
    if ok is True:
        return x
    if ok is False:
        return 0.0 * x
    if isinstance(ok, mi.Bool):
        return dr.select(ok, x, 0.0 * x)
    return x * ok       # a factor, or a family vector (moments.FamilyMIS with both merge sets)


def _finite(w):
    """A weight, 0 where it is not a number: a degenerate vertex (a ray that scraped its own
    surface, cos ~ 1e-20) overflows the running quantities, and inf * 0 in a sum of densities
    gives NaN; such a strategy defers to the others (they are infinitely more likely)."""
    return dr.select(dr.isnan(w), 0.0, w)


class EmitterDensities:
    """What emitter sampling's weight (s=1) needs of the emitter point, one field a line."""

    def __init__(self, pdf_direct_w, pdf_emit_w, cos_e, is_delta=False):
        self.pdf_direct_w = pdf_direct_w    # emitter sampling's density per unit solid angle at z
        #                                     (delta-position emitters: their discrete density times d^2)
        self.pdf_emit_w = pdf_emit_w        # emission density from the emitter point towards z
        self.cos_e = cos_e                  # |cos| at the emitter point (1 for point and infinite emitters)
        self.is_delta = is_delta            # a delta emitter (no s=0 strategy behind it)


class MIS:
    """Heuristic and strategy set. ``kind``: power | balance | uniform; ``strategies``: a
    strategies.StrategySet (or a technique name, bdpt | pt | lt, for its full set): a weight
    sums the densities of the families it offers. All methods are plain arithmetic on Dr.Jit
    arrays (or Python floats), so they trace into any kernel, symbolic or evaluated, and
    differentiate."""

    def __init__(self, kind: str = 'power', strategies='bdpt', detached=False, camera_chains=False,
                 merge_everywhere=False):
        if kind not in ('power', 'balance', 'uniform'):
            raise ValueError(f"mis must be power, balance or uniform, got {kind!r}")
        if isinstance(strategies, str):
            strategies = StrategySet(strategies)
        self.kind = kind
        self.s = strategies
        self.detached = detached      # weights without derivatives (gradients.py)
        # delta chains crossed from the camera side only (derivatives with respect to geometry
        # next to mirrors and glass, gradients.slide): every strategy whose light subpath
        # contains a delta vertex is left out (the light subpaths end at their first delta
        # vertex, and the camera side's sums drop those strategies at each of its delta vertices)
        self.camera_chains = camera_chains
        self.vm_factor = 0.0          # h(eta): set per pass by for_pass (merges)
        self.merge_unit = 1.0         # a merge's own term in d_vm (moments.FamilyMIS: the merge family)
        self.vc_factor = 0.0          # h(1/eta)
        self.vol_factor = None        # h(eta_vol / eta): a merge at a medium vertex (for_pass; media)
        self.beams = False            # merges at medium vertices are beams (set_volume; media)
        self.beam_share = 1.0         # and their light subpaths' share of N (set_volume)
        self.mis_merges = strategies.merges and not strategies.ppm
        # merges at every non-delta vertex (Georgiev et al.), or only behind a delta vertex
        self.merge_everywhere = merge_everywhere
        self.pending = self.mis_merges and not merge_everywhere     # light side defers its merge terms
        # sample counts of the light vertex cache (light_cache.py), per camera sample; None: the
        # classic estimator (one light subpath per camera sample, all its vertices: both 1)
        self.n_c = None               # connections per camera vertex: c n_L / V (set_counts)
        self.n_lt = None              # light subpaths per camera sample: n_L / n (set_counts)

    @property
    def reads_reverse(self):
        """Whether a weight reads a reverse density: d_vc and d_vm hold them (the strategies
        behind a vertex), which the connections, light tracing's splats and the merges read.
        Without them (pt, and vm's partition) the camera subpaths need none: transport.scatter
        asks for none there, nor strategy_s1 (pt's kernels on the Cornell box 0.98 -> 1.00 of
        path's speed)."""
        return self.s.connections or self.s.splats or self.mis_merges

    def for_pass(self, eta=None, counts=None, radius=None, beams=False, beam_share=1.0):
        """This MIS with the pass's eta = pi r^2 N (merges; None: no merges), the light vertex
        cache's sample counts (n_c, n_lt) (None: the classic estimator) and, in scenes with
        media, the merging ``radius`` r, whether merges inside media are ``beams`` and their
        light subpaths' share of N (``set_volume``): a copy, so that per-pass values travel with
        the pass and the Context's MIS is never written."""
        out = copy.copy(self)
        if eta is not None:
            out.set_radius(eta)
        if radius is not None:
            out.set_volume(radius, beams, beam_share)
        if counts is not None:
            out.set_counts(*counts)
        return out

    def set_counts(self, n_c, n_lt):
        """Sample counts relative to one camera sample [Veach 9.2.2] (n_i p_i): ``n_c``, the
        connections' (c n_L / V: c of the V cached vertices of n_L light subpaths per camera
        vertex); ``n_lt``, light tracing's (n_L light subpaths for n camera samples). Hits and
        emitter sampling count 1; merges eta = pi r^2 N (set_radius), already in these units."""
        self.n_c = n_c
        self.n_lt = n_lt

    def _count(self, which):
        """h(n) of a technique's sample count, or None where it is 1 (the classic estimator:
        nothing is traced for it, so its kernels stay as they were)."""
        n = getattr(self, which)
        return None if n is None else self.h(n)

    def set_radius(self, eta):
        """The pass's eta = pi r^2 N (an opaque mi.Float: changing it recompiles nothing)."""
        if not self.mis_merges:
            return
        self.vm_factor = self.h(eta)                                        # [VCM (20)] n_VM = N
        has_vc = self.s.hits or self.s.direct or self.s.connections or self.s.splats
        self.vc_factor = self.h(1.0 / eta) if has_vc else 0.0               # [VCM (20)] n_VC = 1

    def set_volume(self, radius, beams=False, beam_share=1.0):
        """Merges inside media (media scenes only), relative to a surface merge (eta = pi r^2 N;
        per unit length: densities at medium vertices are per unit volume). The running
        quantities stay relative to a surface merge; a medium vertex's merge enters them with
        its factor (``merge_factor``).
        - ``beams`` (beams.py): the camera subpath's segment leaving z gathers y within r of
          it, wherever it passes y (probability T(z, y) for a short beam in a gray medium) with
          eta = pi r^2 N_b, where the camera sampling y itself has the density sigma_t T: relative,
          (N_b / N) / sigma_t(y) [UPBP: Krivanek et al. 2014, point-beam 2D with short query
          beams], N_b / N = ``beam_share`` (the beams' light subpaths, merge.MergeSchedule);
        - else a ball of radius r around the camera vertex, eta_vol = 4/3 pi r^3 N: 4 r / 3
          [UPBP, point-point 3D]."""
        if self.mis_merges:
            self.beams = beams
            self.beam_share = beam_share
            self.vol_factor = None if beams else self.h(radius * (4.0 / 3.0))    # [UPBP] eta_vol / eta

    def merge_factor(self, in_medium, offered=True, sigma=None):
        """A vertex's merge relative to a surface merge, for the ``merge_*`` arguments in scenes
        with media: 0 where no merge is offered (``offered``, a mask or True), the volume
        factor at a medium vertex (beams: h(N_b / N / ``sigma``), ``sigma`` the vertex's
        media.DensityFactor.sigma), 1 on a surface."""
        if self.beams:
            vol = self.h(dr.select(sigma > 0, self.beam_share / sigma, 0.0))   # [UPBP] point-beam: (N_b / N) / sigma_t
        else:
            vol = self.vol_factor if self.vol_factor is not None else 0.0     # (no merges: unused)
        f = dr.select(in_medium, vol, 1.0)
        return f if offered is True else dr.select(offered, f, 0.0)

    # ------------------------------------------------------------------ heuristic
    def h(self, x):
        """h(x) = x^beta, the ratio p_i / p_s under the heuristic [eq. 17, 18]. Every weight is
        built from h's values, so detaching here detaches all of them."""
        if self.detached:
            x = dr.detach(x)
        if self.kind == 'power':
            return x * x                                   # [eq. 18] beta = 2
        if self.kind == 'balance':
            return x                                       # [eq. 17] beta = 1
        return dr.select(x > 0, 1.0, 0.0)                  # [eq. 17] beta = 0: uniform, h(0)=0

    # ------------------------------------------------------------------ recursion
    # Camera subpath start. The camera samples z1 with the density We per unit solid angle.
    def camera_init(self, pdf_cam_w):
        """(d_vcm, d_vc) at the camera vertex z0, before the first hit."""
        if not self.s.splats:
            # No light tracing (pt, or a camera no light path reaches): nothing competes with
            # s=0 at the first hit.
            return 0.0 * pdf_cam_w, 0.0 * pdf_cam_w
        d_vcm = self.h(1.0 / pdf_cam_w)                     # [eq. 22] vc_0 = 1 / p->_0
        if self.n_lt is not None:
            d_vcm = d_vcm * self._count('n_lt')             # [Veach 9.2.2] n_i p_i: t=1 counts n_lt
        d_vc = 0.0 * pdf_cam_w                              # [eq. 22] no strategy behind z0
        return d_vcm, d_vc

    def light_init(self, pdf_emit_w, cos_e, is_delta=False):
        """d_vc at the light vertex y0 (emission density per unit solid angle, position and
        emitter choice included; cos_e: cosine of the emitted direction at y0, 1 for infinite
        emitters). d_vcm needs the emitter-sampling density seen from y1 and is set by
        ``light_first_hit``. A delta emitter cannot be hit: no strategy s=0 behind it."""
        d_vc = self.h(cos_e / pdf_emit_w)                   # [eq. 22] vcm_1: strategy s=0 behind y0
        if is_delta is False:
            return d_vc
        return dr.select(is_delta, 0.0, d_vc)              # [eq. 20] p_0 = 0 for delta emitters

    def light_first_hit(self, d_vc, pdf_emit_w, pdf_direct_a, dist2, cos_hit):
        """(d_vcm, d_vc) at the light subpath's first hit y1. ``pdf_direct_a``: density of
        emitter sampling choosing y0 from y1 (per unit area; per unit solid angle for infinite
        emitters, whose first edge then takes ``dist2 = 1``; discrete for delta emitters)."""
        d_vcm = self.h(pdf_direct_a / pdf_emit_w)           # [eq. 22] vc_1 with p<- of s=1
        return self.on_hit(d_vcm, d_vc, dist2, cos_hit)

    def on_hit(self, d_vcm, d_vc, dist2, cos_hit):
        """Account for the solid-angle -> area conversion of the edge just traced."""
        d_vcm = d_vcm * self.h(dist2) / self.h(cos_hit)     # [eq. 9, 22] g<-: p->_i in area measure
        d_vc = d_vc / self.h(cos_hit)                       # [eq. 9, 22]
        return d_vcm, d_vc

    def on_scatter(self, d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, camera_side=False,
                   merge_here=True):
        """Update at a vertex after sampling the next direction. ``pdf_fwd_w``: density of the
        sampled direction; ``pdf_rev_w``: density of sampling the incoming direction given the
        outgoing one; ``cos_out``: |cos| of the outgoing direction (geometric normal).
        ``is_delta=None``: the scene has no delta lobe, and the delta case is not traced.
        ``camera_side``: a camera subpath's vertex (see ``camera_chains``). ``merge_here``:
        whether a merge at this vertex is a strategy (``merge_here_camera``; False on the light
        side when its term is deferred, ``pending_after_scatter``)."""
        inv_fwd = dr.select(pdf_fwd_w > 0, 1.0 / pdf_fwd_w, 0.0)
        d_vc_smooth = self.h(cos_out * inv_fwd) * (d_vc * self.h(pdf_rev_w) + d_vcm
                                                   + _gate(self.vm_factor, merge_here))  # [eq. 21, 22] vcm_i, [VCM (35)]
        d_vcm_smooth = self.h(inv_fwd)                                                  # [eq. 22] vc_i = 1/p->_i
        if self.n_c is not None:
            # the strategy that ends the light subpath at this vertex is a connection (count n_c);
            # on the camera side it is emitter sampling (count 1) where the next vertex is the
            # emitter hit: weight_s0 takes the n_c back out there
            d_vcm_smooth = d_vcm_smooth * self._count('n_c')                           # [Veach 9.2.2] n_i p_i
        if is_delta is None:
            return d_vcm_smooth, d_vc_smooth
        # A delta vertex cannot be connected: the strategies that would end a subpath there
        # have density 0, and the forward and reverse discrete lobe probabilities cancel.
        d_vc_delta = d_vc * self.h(cos_out)                                             # [eq. 21] p<-/p-> = 1
        if self.camera_chains and camera_side:
            d_vc_delta = 0.0 * d_vc     # the strategies whose light subpath would cross this vertex: none
        d_vcm_delta = 0.0 * d_vcm                                                       # [eq. 22] no connection here
        return (dr.select(is_delta, d_vcm_delta, d_vcm_smooth),
                dr.select(is_delta, d_vc_delta, d_vc_smooth))

    # ------------------------------------------------------------------ events of a walk
    # Each event of a subpath updates its MISState in one place: the start (camera_start,
    # light_start), the hit of the next vertex (hit) and the scatter there (scatter).
    def camera_start(self, pdf_cam_w, dist2, cos_hit):
        """The camera subpath's state at its first hit z1 (``dist2``: the first edge's squared
        length from the lens point; ``cos_hit``: |cos| at z1)."""
        return self.hit(self.camera_before_hit(pdf_cam_w, dr.width(cos_hit)), dist2, cos_hit, True)

    def camera_before_hit(self, pdf_cam_w, n):
        """The camera subpath's state before its first hit (``n`` lanes), whose MIS event
        ``hit`` takes (camera_start; with a transport.PendingHit once the hit is resolved)."""
        d_vcm, d_vc = self.camera_init(pdf_cam_w)
        zero = dr.zeros(mi.Float, n)                         # [VCM (31)-(33)] no merge behind the camera
        return MISState(d_vcm + zero, d_vc + zero, zero, mi.Float(0.0), mi.Float(0.0))

    def light_start(self, pdf_emit_w, cos_e, is_delta, pdf_direct_a, dist2, cos_hit):
        """The light subpath's state at its first hit y1 (arguments as light_init's and
        light_first_hit's)."""
        n = dr.width(cos_hit)
        d_vc = self.light_init(pdf_emit_w, cos_e, is_delta)
        d_vm = self.vm_init_light(d_vc)                      # (vc_factor 0 without merges: unused then)
        d_vcm, d_vc = self.light_first_hit(d_vc, pdf_emit_w, pdf_direct_a, dist2, cos_hit)
        d_vm = self.vm_on_hit(d_vm, cos_hit) if self.mis_merges else dr.zeros(mi.Float, n)
        # a merge's terms waiting for the next vertex (none behind y0)
        pend = (dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)) if self.pending else (mi.Float(0.0), mi.Float(0.0))
        return MISState(d_vcm, d_vc, d_vm, pend[0], pend[1])

    def hit(self, st, dist2, cos_hit, camera_side):
        """The next vertex found at squared distance ``dist2``, |cos| ``cos_hit`` there."""
        d_vcm, d_vc = self.on_hit(st.d_vcm, st.d_vc, dist2, cos_hit)
        d_vm = self.vm_on_hit(st.d_vm, cos_hit) if self.mis_merges else st.d_vm
        pend_vc, pend_vm = st.pend_vc, st.pend_vm
        if self.pending and not camera_side:
            pend_vc, pend_vm = self.vm_on_hit(pend_vc, cos_hit), self.vm_on_hit(pend_vm, cos_hit)
        return MISState(d_vcm, d_vc, d_vm, pend_vc, pend_vm)

    def distance(self, st, pdf_fwd_l, pdf_rev_l):
        """The edge just traced was distance-sampled through media (media_path.step):
        ``pdf_fwd_l``, its distance density at the vertex it reached (sigma_t T per unit length
        at a medium vertex, T at a surface; media.py), joins that vertex's forward density;
        ``pdf_rev_l``, the same edge's density sampled from that vertex back to the one it left,
        joins the reverse density of the vertex it left (the cosine there is already in d_vc,
        from on_scatter). Applied before ``hit``, whose factors it multiplies."""
        inv_fwd = self.h(dr.select(pdf_fwd_l > 0, 1.0 / pdf_fwd_l, 0.0))
        ratio = self.h(pdf_rev_l) * inv_fwd
        d_vcm = st.d_vcm * inv_fwd                          # [eq. 9, 22] vc_i: p->_i with its distance density
        d_vc = st.d_vc * ratio                              # [eq. 21, 22] p<-_{i-1} / p->_i with theirs
        d_vm = st.d_vm * ratio if self.mis_merges else st.d_vm      # [VCM (36)] as d_vc
        pend_vc, pend_vm = st.pend_vc, st.pend_vm
        if self.pending:            # [VCM (35), (36)] a deferred merge term, scaled as d_vc since
            pend_vc, pend_vm = pend_vc * ratio, pend_vm * ratio
        return MISState(d_vcm, d_vc, d_vm, pend_vc, pend_vm)

    def scatter(self, st, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, camera_side, merge_here=True):
        """The vertex scattered towards a direction of density ``pdf_fwd_w`` (arguments as
        on_scatter's; ``merge_here`` on the camera side only: the light side defers its merge
        terms where merges exist behind delta vertices only)."""
        d_vcm, d_vc, d_vm, pend_vc, pend_vm = st.d_vcm, st.d_vc, st.d_vm, st.pend_vc, st.pend_vm
        if not camera_side:
            # light side: ``merge_here`` says whether a merge at this vertex can be a strategy at
            # all (with media: its factor, merge_factor); where merges exist behind delta
            # vertices only, its term waits for the next vertex (pending)
            mergeable = merge_here
            merge_here = False if self.pending else mergeable
            if self.pending:
                d_vc, d_vm = self.absorb_pending(d_vc, d_vm, pend_vc, pend_vm, is_delta)
                pend_vc, pend_vm = self.pending_after_scatter(cos_out, pdf_fwd_w, is_delta, mergeable)
        if self.mis_merges:
            d_vm = self.vm_on_scatter(d_vm, d_vcm, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, merge_here)
        d_vcm, d_vc = self.on_scatter(d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, is_delta,
                                      camera_side=camera_side, merge_here=merge_here)
        return MISState(d_vcm, d_vc, d_vm, pend_vc, pend_vm)

    # ------------------------------------------------------------------ merging recursion
    # d_vm: the merging strategies (and, through vc_factor, the connections) further back,
    # relative to merging at the current vertex. Used only with mis_merges.
    def vm_init_light(self, d_vc):
        """d_vm at the light vertex y0, from its d_vc (light_init)."""
        return d_vc * self.vc_factor                        # [VCM (33)]

    def vm_on_hit(self, d_vm, cos_hit):
        return d_vm / self.h(cos_hit)                        # [VCM (33), (36)] area measure at the hit

    def vm_on_scatter(self, d_vm, d_vcm, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, merge_here=True):
        """d_vm after sampling the next direction; ``d_vcm``: the value before this scatter
        (the other arguments as on_scatter's)."""
        inv_fwd = dr.select(pdf_fwd_w > 0, 1.0 / pdf_fwd_w, 0.0)
        d_vm_smooth = self.h(cos_out * inv_fwd) * (d_vm * self.h(pdf_rev_w) + d_vcm * self.vc_factor
                                                   + _gate(self.merge_unit, merge_here))   # [VCM (36)]
        if is_delta is None:
            return d_vm_smooth
        return dr.select(is_delta, d_vm * self.h(cos_out), d_vm_smooth)              # [VCM (36)] delta

    # ------------------------------------------------------------------ where merges exist
    def merge_here_camera(self, prev_delta):
        """Whether a merge at a camera vertex is a strategy, from whether the camera subpath's
        previous vertex was delta (False at the first hit: the camera is not). True where the
        weights have no merges (vm_factor 0) and for ``vm`` (its own rule: strategies.py)."""
        return True if (self.merge_everywhere or not self.mis_merges) else prev_delta

    def merge_offered(self, prev_delta):
        """Whether the camera gathers at a vertex (the sampling; ``merge_here_camera`` is its
        term in the weights, which moments.FamilyMIS makes a family vector): the same here."""
        return self.merge_here_camera(prev_delta)

    def pending_after_scatter(self, cos_out, pdf_fwd_w, is_delta, mergeable=True):
        """Light side (merges behind delta vertices only): the terms that a merge at the vertex
        just scattered from adds to (d_vc, d_vm) [VCM (35), (36)], kept apart until the next vertex
        shows whether it is delta (0 where this one is delta: no merge there)."""
        inv_fwd = dr.select(pdf_fwd_w > 0, 1.0 / pdf_fwd_w, 0.0)
        g = self.h(cos_out * inv_fwd)
        pend_vc = g * self.vm_factor                        # [VCM (35)] the merge at this vertex in d_vc
        pend_vm = g                                         # [VCM (36)] and in d_vm
        if mergeable is not True:                           # no merge at a medium vertex
            pend_vc, pend_vm = _gate(pend_vc, mergeable), _gate(pend_vm, mergeable)
        if is_delta is None:
            return pend_vc, pend_vm
        return dr.select(is_delta, 0.0, pend_vc), dr.select(is_delta, 0.0, pend_vm)

    def absorb_pending(self, d_vc, d_vm, pend_vc, pend_vm, is_delta):
        """Light side, at the scatter of the next vertex (before on_scatter): the previous
        vertex's merge counts where this vertex is delta; elsewhere it is dropped."""
        if is_delta is None:
            return d_vc, d_vm
        d_vc = d_vc + dr.select(is_delta, pend_vc, 0.0)     # [VCM (35)] deferred term, scaled as d_vc since
        d_vm = d_vm + dr.select(is_delta, pend_vm, 0.0)     # [VCM (36)] deferred term, scaled as d_vm since
        return d_vc, d_vm

    # ------------------------------------------------------------------ weights
    def weight_s0(self, d_vcm, d_vc, pdf_direct_a, pdf_emit_w, first_hit=False):
        """Camera subpath hits an emitter (s=0). ``pdf_direct_a``: emitter sampling density of the
        hit point (per unit area; for the first hit the light subpath's position density);
        ``pdf_emit_w``: light subpath's density of emitting towards the previous vertex;
        ``first_hit``: the emitter is the camera subpath's first vertex (a mask), where the
        strategy s=1 is the splat s=1,t=1 (its count is in d_vcm from camera_init)."""
        if not self.s.hits:
            return 0.0 * d_vcm
        if self.s.ppm:
            return 1.0 + 0.0 * d_vcm                        # vm: the kernel counts delta chains only
        w_camera = self.h(pdf_direct_a) * d_vcm             # [eq. 20, 22] strategy s=1, [VCM (43)]
        if self.n_c is not None:
            # [Veach 9.2.2] emitter sampling counts 1, not the n_c that on_scatter gave d_vcm
            w_camera = w_camera * dr.select(first_hit, 1.0, 1.0 / self._count('n_c'))
        if self.s.connections:
            w_camera = w_camera + self.h(pdf_emit_w) * d_vc  # [eq. 20, 21] strategies s>=2
        return _finite(1.0 / (1.0 + w_camera))              # [eq. 20] w_light = 0

    def weight_s1(self, st, pdf_bsdf_w, pdf_rev_w, cos_z, em, merge_z=True):
        """Emitter sampling (s=1, t>=2) at camera vertex z, whose MISState is ``st``.
        ``pdf_bsdf_w``: z's BSDF density towards the emitter point; ``pdf_rev_w``: z's BSDF
        density of its incoming direction given the emitter direction; ``cos_z``: |cos| at z;
        ``em``: the emitter point's EmitterDensities; ``merge_z``: whether a merge at z is a
        strategy (merge_here_camera)."""
        if not self.s.direct:
            return 0.0 * st.d_vcm
        w_light = self.h(pdf_bsdf_w / em.pdf_direct_w)                            # [eq. 20] strategy s=0
        if em.is_delta is not False:
            w_light = dr.select(em.is_delta, 0.0, w_light)                         # [eq. 20] p_0 = 0
        if not self.s.connections:
            return _finite(1.0 / (w_light + 1.0))           # [eq. 20] w_camera = 0
        w_camera = (self.h(em.pdf_emit_w * cos_z / (em.pdf_direct_w * em.cos_e))   # [eq. 21, 22], [VCM (45)]
                    * (_gate(self.vm_factor, merge_z) + st.d_vcm + st.d_vc * self.h(pdf_rev_w)))
        return _finite(1.0 / (w_light + 1.0 + w_camera))    # [eq. 20]

    def weight_connect(self, light, cam, pdf_cam_to_light_a, pdf_light_to_cam_a, pdf_light_rev_w, pdf_cam_rev_w,
                       merge_z=True, merge_y=None):
        """Connection of light vertex y_{s-1} and camera vertex z_{t-1} (s,t>=2): ``light``,
        ``cam`` their MIS quantities (a MISState, or a stored record: d_vcm, d_vc).
        ``pdf_cam_to_light_a``: z's BSDF density of y (per unit area at y);
        ``pdf_light_to_cam_a``: y's BSDF density of z (per unit area at z);
        ``pdf_light_rev_w``: y's density of its incoming direction given the direction to z;
        ``pdf_cam_rev_w``: z's density of its incoming direction given the direction to y;
        ``merge_z``: whether a merge at z is a strategy (merge_here_camera). A merge at y is one
        only where merges are everywhere (y's camera-side neighbour is z, not delta), and y is on a
        surface or has its factor (``merge_y``: with media, merge_factor of y; None:
        merge_everywhere)."""
        if not self.s.connections:
            return 0.0 * light.d_vcm
        merge_y = self.merge_everywhere if merge_y is None else merge_y
        w_light = self.h(pdf_cam_to_light_a) * (_gate(self.vm_factor, merge_y) + light.d_vcm
                                                + light.d_vc * self.h(pdf_light_rev_w))   # [eq. 21, 22], [VCM (40)]
        w_camera = self.h(pdf_light_to_cam_a) * (_gate(self.vm_factor, merge_z) + cam.d_vcm
                                                 + cam.d_vc * self.h(pdf_cam_rev_w))      # [eq. 21, 22], [VCM (41)]
        if self.n_c is not None:
            return _finite(1.0 / ((w_light + w_camera) / self._count('n_c') + 1.0))      # [Veach 9.2.2] / h(n_c)
        return _finite(1.0 / (w_light + 1.0 + w_camera))                                  # [eq. 20]

    def weight_t1(self, l_vcm, l_vc, pdf_cam_a, pdf_light_rev_w, merge_y=None):
        """Light vertex y_{s-1} (s>=2) connected to the camera (t=1). ``pdf_cam_a``: density of
        the camera sampling y (We converted to area at y); ``merge_y`` as weight_connect's."""
        if not self.s.splats:
            return 0.0 * l_vcm
        if not (self.s.hits or self.s.direct or self.s.connections):
            return 1.0 + 0.0 * l_vcm                        # light tracing alone (lt)
        if merge_y is None:
            merge_y = self.merge_everywhere        # y's camera-side neighbour: the camera, not delta
        w_light = self.h(pdf_cam_a) * (_gate(self.vm_factor, merge_y) + l_vcm
                                       + l_vc * self.h(pdf_light_rev_w))            # [eq. 21, 22], [VCM (46)]
        if self.n_lt is not None:
            w_light = w_light / self._count('n_lt')                              # [Veach 9.2.2] / h(n_lt)
        return _finite(1.0 / (w_light + 1.0))                                    # [eq. 20] w_camera = 0

    def weight_s1t1(self, pdf_cam_a, pdf_light_a):
        """The emitter vertex y0 splatted to the camera (s=1, t=1); the other strategy for a
        one-edge path is s=0 (the camera ray hits the emitter)."""
        if not self.s.splats:
            return 0.0 * pdf_cam_a
        if not self.s.hits:
            return 1.0 + 0.0 * pdf_cam_a                    # light tracing alone (lt)
        if self.n_lt is not None:
            return _finite(1.0 / (1.0 + self.h(pdf_cam_a / (self.n_lt * pdf_light_a))))  # [eq. 20], [Veach 9.2.2]
        return _finite(1.0 / (1.0 + self.h(pdf_cam_a / pdf_light_a)))  # [eq. 20]

    def weight_merge(self, l_vcm, l_vm, c_vcm, c_vm, pdf_cam_dir_w, pdf_cam_rev_w, inv_factor=None, own=True):
        """Merge of camera vertex z with a light vertex y within the radius (merge.py).
        ``pdf_cam_dir_w``: z's BSDF density of y's incoming direction (the camera subpath going
        on where the light subpath came from); ``pdf_cam_rev_w``: z's density of its own incoming
        direction given y's (the light subpath going on where the camera subpath came from);
        ``inv_factor``: 1 / this merge's density relative to a surface merge (1 / merge_factor,
        scenes with media; None: 1); ``own``: z's merge_here_camera (read by moments.FamilyMIS:
        the merge's family)."""
        if self.s.ppm:
            return 1.0 + 0.0 * l_vcm                        # vm: a partition, no MIS
        if not self.mis_merges:
            return 0.0 * l_vcm
        w_light = l_vcm * self.vc_factor + l_vm * self.h(pdf_cam_dir_w)    # [VCM (38)]
        w_camera = c_vcm * self.vc_factor + c_vm * self.h(pdf_cam_rev_w)   # [VCM (39)]
        if inv_factor is not None:  # [UPBP] the others relative to this merge: / (eta_vol / eta)
            return _finite(1.0 / ((w_light + w_camera) * inv_factor + 1.0))
        return _finite(1.0 / (w_light + 1.0 + w_camera))                   # [VCM (37)]
