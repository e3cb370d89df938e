"""Moment estimation (issue 22; Grittmann, Yazici, Georgiev and Slusallek, "Efficiency-aware
multiple importance sampling for bidirectional rendering algorithms", SIGGRAPH 2022, sections
4-5): from the samples of one render, the second moment that each candidate configuration of
bdpt's estimator would have, path tracing included.

With the balance heuristic and sample counts n_t [Veach 9.2.2] the combined estimator's second
moment per camera sample is, up to the correlation terms the paper also neglects,

    M(n) = integral of f(x)^2 / S_n(x) dx,        S_n(x) = sum_t n_t p_t(x)          (G22 eq. 8)

(t over the candidate's strategies). A render of any configuration estimates it for every
candidate at once: a sample path x of strategy s with weighted contribution C = w_s f / (n_s p_s)
and unweighted contribution U = f / p_s adds C U / R_n(x) to candidate n's sum, with
R_n(x) = S_n(x) / p_s(x). The candidates of bdpt differ only in the counts of three families:
connections (s, t >= 2: n_c = c n_L / V), light tracing (t = 1: n_lt = n_L / n) and merges
(n_m: 0 without merging; with it the merges' eta = pi r^2 N scales with the light subpaths N of
an iteration, so relative to a pilot of the classic estimator's N, n_m = n_L / n as well); hits
and emitter sampling count 1 in all of them. So

    R_n = A_1 + n_c A_c + n_lt A_lt + n_m A_m,                                  (family sums)

A_f the sum of p_t / p_s over the strategies of family f. Path tracing is (n_c, n_lt, n_m) =
(0, 0, 0), the classic estimator (1, 1, 0), vcm (1, 1, 1), the light vertex cache (c / (V /
n_L), light_paths, 0 or light_paths).

``FamilyMIS`` is mis.MIS under the balance heuristic whose running quantities are vectors over
the four families (one, connect, splat, merge): its counts are the families' unit vectors (a
merge's eta is eta times the merge family's), so the recursion of mis.py (every line of it
linear in its quantities; 1 / eta, the merges' own scale, is a number) carries each family's
terms in its own component. Its weights dot the vector with a configuration's counts: with
counts (1, 1, 1) they are the pilot's own balance weights, and they hand the vector to the
``MomentFilm`` (the tap) that the strategy that asked for them then adds its sample to. Whether
a merge behind a non-delta vertex is a strategy is a fifth family (``split``): a pilot merging
everywhere keeps the merges behind a delta vertex apart from the others and predicts vcm's own
merge set, behind delta vertices only, with the same samples (auto's pilot in scenes without
media). Without it a pilot predicts the candidates of its own merge set, everywhere
(``merge_everywhere``) or behind delta vertices only (the light side's deferred merge terms are
family vectors too), and auto runs one pilot per merge set in scenes with media."""

import drjit as dr
import mitsuba as mi

from .film import layer_index
from .mis import MIS, MISState, _finite, _gate

Family = mi.Vector4f              # a family vector: (one, connect, splat, merge)
SPLIT_WIDTH = 5                   # with both merge sets (``split``): (one, connect, splat, merge behind delta, elsewhere)
MAX_PIXELS = 16384                # pixels whose moments the pilot keeps (a lattice of a larger image)
MAX_LENGTH = 6                    # strategies of longer paths share one layer (MomentFilm.estimates)


def family_count(own, n):
    """The count of a strategy of family ``own`` (0 one, 1 connect, 2 splat, 3 merge; or, a merge
    with both merge sets, its family's unit vector) under counts ``n`` = (n_c, n_lt, n_m) or
    (n_c, n_lt, n_m behind delta, n_m elsewhere)."""
    if isinstance(own, int):
        return 1.0 if own == 0 else n[own - 1]
    return own[3] * n[2] + own[4] * n[3]


class FamilyMIS(MIS):
    """The balance heuristic with the families of the counts kept apart (see above). ``counts``:
    the configuration whose weights it returns, (n_c, n_lt, n_m) (floats, or arrays of the
    lanes whose weights are formed next: per-pixel counts, pixel_counts.py); ``tap``: the
    MomentFilm that receives each weight's family vector R (or None); ``merge_everywhere``: the
    merge set of a pilot that merges (see above). ``kind``: the
    heuristic; under the power heuristic h(n p) = h(n) h(p), so each family's terms are h of
    the densities and the weights dot them with h of the counts (the families' unit vectors
    are their own h), the same linear recursion; the moment film (tap) needs the balance's.

    ``split``: both merge sets from one pilot that merges everywhere (no media). A merge is in
    the family 'behind delta' where its vertex's camera-side neighbour is a delta vertex, else
    'elsewhere', five families, and the counts are (n_c, n_lt, n_m behind delta, n_m
    elsewhere): vcm's own merge set is (1, 1, 1, 0), merging everywhere (1, 1, 1, 1). The camera
    side knows the neighbour (merge_here_camera: the family's unit vector); the light side puts
    a merge at y_i in 'elsewhere' at its scatter (a connection or splat ending at y_{i+1} sees it
    there) and moves it to 'behind delta' at y_{i+1}'s scatter where that vertex is delta
    (its term kept in pend_vc/pend_vm, scaled as d_vc/d_vm since, as mis.MIS.absorb_pending's)."""

    def __init__(self, strategies, counts=None, tap=None, merge_everywhere=False, kind='balance', split=False):
        if tap is not None and kind != 'balance':
            raise ValueError('moments: the moment film predicts balance-heuristic variances')
        super().__init__(kind, strategies, merge_everywhere=merge_everywhere or split)
        self.split = split and self.mis_merges
        self.width = SPLIT_WIDTH if self.split else 4
        self.F = mi.ArrayXf if self.split else Family
        self.n_c = self.unit(1)                 # the families' counts: their unit vectors
        self.n_lt = self.unit(2)
        if self.split:
            self.pending = True                 # the light side's merge terms move at the next vertex
        else:
            self.merge_unit = self.unit(3)
        self.eval_counts = counts if counts is not None else (1.0,) * (self.width - 1)
        self.tap = tap

    # ------------------------------------------------------------------ family vectors
    def vec(self, *xs):
        """The family vector of components ``xs`` (one per family)."""
        return self.F(*xs)

    def bcast(self, x):
        """``x`` in every family."""
        return self.F(*([x] * self.width))

    def unit(self, k, like=None):
        """The unit vector of family k (0 one, 1 connect, 2 splat, 3 merge or merge behind delta,
        4 merge elsewhere) for arrays as wide as ``like`` (None: a literal)."""
        z = 0.0 if like is None else dr.zeros(mi.Float, dr.width(like))
        return self.F(*[z + 1.0 if i == k else z for i in range(self.width)])

    def as_family(self, x):
        """``x`` as a family vector (a number, in practice a zero, in every family)."""
        return x if isinstance(x, self.F) else self.bcast(x)

    def one(self, x):
        """A term of the family of hits and emitter sampling (count 1)."""
        return self.F(x, *([0.0] * (self.width - 1)))

    def merge_here_camera(self, prev_delta):
        """With both merge sets, a camera vertex's merge family: behind delta where the previous
        vertex was delta, else elsewhere (the unit vector: mis._gate multiplies by it)."""
        if not self.split:
            return super().merge_here_camera(prev_delta)
        bd = dr.select(prev_delta, 1.0, 0.0) if not isinstance(prev_delta, bool) else float(prev_delta)
        return self.vec(0.0, 0.0, 0.0, bd, 1.0 - bd)

    def merge_offered(self, prev_delta):
        return True if self.split else super().merge_offered(prev_delta)

    def light_gate(self, merge_y):
        """A light vertex's merge term in the weights (its camera-side neighbour is the camera
        vertex it connects to, or the camera: not delta): with both merge sets, elsewhere's."""
        if not self.split:
            return self.merge_everywhere if merge_y is None else merge_y
        el = self.unit(4)
        return el if merge_y is None or merge_y is True else el * merge_y

    def set_radius(self, eta):
        """A merge's terms in the merge family: vm_factor = eta times its unit vector, vc_factor
        = 1 / eta (the merges' scale, relative to which the others' terms are taken); with both
        merge sets, vm_factor h(eta) and the gate's unit vector the family (merge_here_camera)."""
        if not self.mis_merges:
            return
        self.vm_factor = self.h(eta) if self.split else self.unit(3) * self.h(eta)   # [VCM (20)] n_VM = N
        has_vc = self.s.hits or self.s.direct or self.s.connections or self.s.splats
        self.vc_factor = self.h(1.0 / eta) if has_vc else 0.0               # [VCM (20)] n_VC = 1

    def set_counts(self, n_c, n_lt):
        raise ValueError('moments: FamilyMIS carries the counts as families (its eval_counts)')

    def _weight(self, own, R):
        """The weight of a strategy of family ``own`` (or, a merge's with both merge sets, its
        family's unit vector) whose others' (and own) densities relative to its own are the
        family vector ``R``: n_s / R_n under the configuration's counts."""
        if self.tap is not None:
            self.tap.offer(R, own)
        n = [self.h(x) for x in self.eval_counts]                         # h(n_t): [Veach 9.2.2] h(n_t p_t)
        r = R[0] + sum(n[i] * R[i + 1] for i in range(self.width - 1))    # (family sums)
        return _finite(family_count(own, n) / r)                                           # [eq. 20], [Veach 9.2.2]

    def _zero(self, like):
        if self.tap is not None:
            self.tap.offer(self.bcast(0.0), 0)
        return 0.0 * like

    # ------------------------------------------------------------------ the subpaths' starts
    def camera_before_hit(self, pdf_cam_w, n):
        st = super().camera_before_hit(pdf_cam_w, n)
        if self.mis_merges:                 # d_vm a family vector from the start (the loop's state)
            st.d_vm = self.bcast(st.d_vm)
        return st

    def camera_init(self, pdf_cam_w):
        d_vcm, _ = super().camera_init(pdf_cam_w)       # [Veach 9.2.2] t=1 in the splat family (n_lt)
        return self.as_family(d_vcm), self.bcast(0.0 * pdf_cam_w)

    def light_init(self, pdf_emit_w, cos_e, is_delta=False):
        return self.one(super().light_init(pdf_emit_w, cos_e, is_delta))    # s=0: family one

    def light_start(self, pdf_emit_w, cos_e, is_delta, pdf_direct_a, dist2, cos_hit):
        st = super().light_start(pdf_emit_w, cos_e, is_delta, pdf_direct_a, dist2, cos_hit)
        if self.pending and not self.split:     # merges behind delta vertices: the deferred terms are family vectors
            st.pend_vc, st.pend_vm = self.bcast(st.pend_vc), self.bcast(st.pend_vm)
        return st

    def pending_after_scatter(self, cos_out, pdf_fwd_w, is_delta, mergeable=True):
        pend_vc, pend_vm = super().pending_after_scatter(cos_out, pdf_fwd_w, is_delta, mergeable)
        if self.split:          # numbers: absorb_pending gives them their family
            return pend_vc, pend_vm
        return pend_vc, pend_vm * self.merge_unit        # [VCM (36)] the merge's own term, in the merge family

    def absorb_pending(self, d_vc, d_vm, pend_vc, pend_vm, is_delta):
        """With both merge sets: the previous vertex's merge, in elsewhere's family since its
        scatter, moves to behind delta's where this vertex is delta."""
        if not self.split:
            return super().absorb_pending(d_vc, d_vm, pend_vc, pend_vm, is_delta)
        if is_delta is None:
            return d_vc, d_vm
        move = self.unit(3) - self.unit(4)
        d_vc = d_vc + dr.select(is_delta, pend_vc, 0.0) * move             # [VCM (35)] deferred term, scaled as d_vc since
        d_vm = d_vm + dr.select(is_delta, pend_vm, 0.0) * move             # [VCM (36)] deferred term, scaled as d_vm since
        return d_vc, d_vm

    def scatter(self, st, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, camera_side, merge_here=True):
        """With both merge sets, the light side: the merge at this vertex in elsewhere's family
        now (``light_gate``), its terms kept to move at the next vertex (absorb_pending)."""
        if camera_side or not self.split:
            return super().scatter(st, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, camera_side, merge_here)
        d_vc, d_vm = self.absorb_pending(st.d_vc, st.d_vm, st.pend_vc, st.pend_vm, is_delta)
        pend_vc, pend_vm = self.pending_after_scatter(cos_out, pdf_fwd_w, is_delta, merge_here)
        gate = self.light_gate(merge_here)
        d_vm = self.vm_on_scatter(d_vm, st.d_vcm, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, gate)
        d_vcm, d_vc = self.on_scatter(st.d_vcm, d_vc, cos_out, pdf_fwd_w, pdf_rev_w, is_delta, merge_here=gate)
        return MISState(d_vcm, d_vc, d_vm, pend_vc, pend_vm)

    def light_first_hit(self, d_vc, pdf_emit_w, pdf_direct_a, dist2, cos_hit):
        d_vcm = self.one(self.h(pdf_direct_a / pdf_emit_w))                 # [eq. 22] s=1: family one
        return self.on_hit(d_vcm, d_vc, dist2, cos_hit)

    # ------------------------------------------------------------------ weights
    def weight_s0(self, d_vcm, d_vc, pdf_direct_a, pdf_emit_w, first_hit=False):
        if not self.s.hits:
            return self._zero(pdf_direct_a)
        t = self.h(pdf_direct_a) * self.as_family(d_vcm)                    # [eq. 20, 22] strategy s=1
        # emitter sampling counts 1: where the hit is not the first, the term on_scatter put in
        # the connect family is the s=1 strategy's (at the first hit: the splat s=1, t=1)
        moved = self.vec(t[0] + t[1], 0.0, *[t[i] for i in range(2, self.width)])
        R = self.one(1.0) + dr.select(first_hit, t, moved)
        if self.s.connections:
            R = R + self.h(pdf_emit_w) * self.as_family(d_vc)               # [eq. 20, 21] strategies s>=2
        return self._weight(0, R)

    def weight_s1(self, st, pdf_bsdf_w, pdf_rev_w, cos_z, em, merge_z=True):
        if not self.s.direct:
            return self._zero(pdf_bsdf_w)
        w_light = self.h(pdf_bsdf_w / em.pdf_direct_w)                      # [eq. 20] strategy s=0
        if em.is_delta is not False:
            w_light = dr.select(em.is_delta, 0.0, w_light)                  # [eq. 20] p_0 = 0
        R = self.one(1.0 + w_light)
        if self.s.connections:
            R = R + (self.h(em.pdf_emit_w * cos_z / (em.pdf_direct_w * em.cos_e))     # [eq. 21, 22]
                     * (_gate(self.vm_factor, merge_z) + st.d_vcm + st.d_vc * self.h(pdf_rev_w)))
        return self._weight(0, R)

    def weight_connect(self, light, cam, pdf_cam_to_light_a, pdf_light_to_cam_a, pdf_light_rev_w, pdf_cam_rev_w,
                       merge_z=True, merge_y=None):
        if not self.s.connections:
            return self._zero(pdf_cam_to_light_a)
        merge_y = self.light_gate(merge_y)
        w_light = self.h(pdf_cam_to_light_a) * (_gate(self.vm_factor, merge_y) + light.d_vcm
                                                + light.d_vc * self.h(pdf_light_rev_w))   # [eq. 21, 22], [VCM (40)]
        w_camera = self.h(pdf_light_to_cam_a) * (_gate(self.vm_factor, merge_z) + cam.d_vcm
                                                 + cam.d_vc * self.h(pdf_cam_rev_w))      # [eq. 21, 22], [VCM (41)]
        return self._weight(1, self.unit(1, pdf_cam_to_light_a) + w_light + w_camera)

    def weight_t1(self, l_vcm, l_vc, pdf_cam_a, pdf_light_rev_w, merge_y=None):
        if not self.s.splats:
            return self._zero(pdf_cam_a)
        R = self.unit(2, pdf_cam_a)
        if self.s.hits or self.s.direct or self.s.connections:
            R = R + self.h(pdf_cam_a) * (_gate(self.vm_factor, self.light_gate(merge_y)) + l_vcm
                                         + l_vc * self.h(pdf_light_rev_w))           # [eq. 21, 22], [VCM (46)]
        return self._weight(2, R)

    def weight_s1t1(self, pdf_cam_a, pdf_light_a):
        if not self.s.splats:
            return self._zero(pdf_cam_a)
        R = self.unit(2, pdf_cam_a)
        if self.s.hits:
            R = R + self.one(self.h(pdf_cam_a / pdf_light_a))               # [eq. 20] strategy s=0
        return self._weight(2, R)

    def weight_merge(self, l_vcm, l_vm, c_vcm, c_vm, pdf_cam_dir_w, pdf_cam_rev_w, inv_factor=None, own=True):
        if not self.mis_merges:
            return self._zero(pdf_cam_dir_w)
        others = (l_vcm * self.vc_factor + l_vm * self.h(pdf_cam_dir_w)              # [VCM (38)]
                  + c_vcm * self.vc_factor + c_vm * self.h(pdf_cam_rev_w))           # [VCM (39)]
        if inv_factor is not None:      # [UPBP] the others relative to this merge: / (eta_vol / eta)
            others = others * inv_factor
        if not self.split:
            return self._weight(3, self.unit(3, pdf_cam_dir_w) + others)            # [VCM (37)]
        own = self.merge_here_camera(False) if own is True else own + 0.0 * pdf_cam_dir_w
        return self._weight(own, own + others)                                      # [VCM (37)]


def channel_mean(x):
    """The mean of a Spectrum's channels (RGB, monochrome, or a spectral sample's wavelengths)."""
    n = dr.size_v(mi.Spectrum)
    return sum(x[i] for i in range(n)) * (1.0 / n)


def layer_families(max_length):
    """The family (0 one, 1 connect, 2 splat) of each strategy layer of film.StrategyLayers'
    order (s + t - 1 edges up to ``max_length``, then 'other', whose family is -1: mixed)."""
    out = []
    for k in range(1, max_length + 1):
        for s_ in range(0, k + 1):
            t = k + 1 - s_
            out.append(2 if t == 1 else (0 if s_ <= 1 else 1))
    return out + [-1]


class MomentFilm:
    """Per crop pixel, for the mean of the colour channels (the estimates are of its moments; C
    and U below are channel means): the image I (of the weighted contributions C) and, for each
    candidate k of counts (n_c, n_lt): the sum of C U / R_k, the |C| that the candidate cannot
    sample (R_k = 0: none of its strategies samples the path), and per strategy layer (s, t)
    (film.StrategyLayers' order) the candidate's weighted image of that strategy, from the
    strategy's own samples: U n_s / R_k, in two halves of the samples (``group``: the parity of
    the sample's number in its pixel), whose product estimates its square without the bias of a
    square of one estimate (E[I_a I_b] = I^2 for independent halves). A contribution goes to the pixel that contains it, as in
    film.StrategyLayers; with the render's scales (1/spp per camera sample, the splat scale) an
    image of spp samples per pixel gives the second moment of the candidate's one-sample pixel
    estimate as spp times the sum (``estimates``). Of an image of more than MAX_PIXELS pixels
    only every step-th pixel's moments are kept (the candidates are compared by their mean)."""

    def __init__(self, pixels, counts, max_length, max_pixels=MAX_PIXELS):
        self.pixels = pixels                    # film.NearestPixel of the crop
        # the pixels whose moments are kept: every step-th (all of an image of max_pixels or fewer)
        self.step = -(-pixels.count // max_pixels)
        self.count = -(-pixels.count // self.step)
        # (n_c, n_lt, n_m), or with both merge sets (split) (n_c, n_lt, n_m behind delta, n_m elsewhere)
        width = max(3, max((len(k) for k in counts), default=3))
        self.counts = [tuple(float(x) for x in k) + (0.0,) * (width - len(k)) for k in counts]
        # the counts as opaque values: n_c = c / (V / n_L) varies from pilot to pilot, and as
        # literals it would make every pilot's kernels new ones (compiled again: ~1 s a pilot)
        self.opaque_counts = [tuple(dr.opaque(mi.Float, x) for x in k) for k in self.counts]
        # the candidates that can miss a path the pilot samples (its counts (1, 1, 1) make every such
        # path's family sum positive): those with a count of 0, merges' only where the pilot merges
        # (some candidate does); the others' 'missed' sums stay 0 and are not scattered
        merging = any(x > 0 for k in self.counts for x in k[2:])
        self.can_miss = [k[0] == 0 or k[1] == 0 or (merging and min(k[2:]) == 0) for k in self.counts]
        self.max_length = max(int(max_length), 1)
        self.families = layer_families(self.max_length)
        K, L = len(self.counts), len(self.families)
        self.stride = 1 + 2 * K + 2 * K * L + 1     # (the last: the merges' part of the image, ``merged``)
        self.groups = {}                        # each lane's half, 0 or 1, by the lanes' number (begin_pass)
        self.buf = dr.zeros(mi.Float, self.count * self.stride)
        self.pending = None                     # the (family vector, own family) of the weight just formed
        self.merged = None                      # after estimates: the merges' part of the image per kept pixel
        #                                         (their weighted contributions; auto keeps merges where it is large)

    def begin_pass(self, n, spp_pass, spp_before, n_camera=None):
        """The halves of a pass of ``n`` light subpaths and ``n_camera`` camera samples (default
        ``n``; fewer in a lattice pilot, integrator.lattice_step), ``spp_pass`` consecutive ones
        a pixel, after ``spp_before`` samples a pixel in earlier passes: a light subpath's half
        is that of its lane's camera sample (the classic estimator), so both halves are
        independent samples."""
        self.groups = {}
        for width in {n, n if n_camera is None else n_camera} - {0}:     # (a lattice pass may have no camera sample)
            idx = dr.arange(mi.UInt32, width)
            self.groups[width] = ((idx % dr.opaque(mi.UInt32, spp_pass)) + dr.opaque(mi.UInt32, spp_before)) & 1
            dr.eval(self.groups[width])

    def offer(self, R, own):
        """FamilyMIS: the family vector of the weight it has just returned, and its family."""
        self.pending = (R, own)

    def add(self, s, t, film_pos, weighted, unweighted, active):
        """Strategy (s, t)'s sample (the arguments of film.StrategyLayers.add; s = t = None: a
        merge), whose weight was the last one formed (``offer``). A merge returns its unweighted
        U times each candidate's weight (``add_cross``'s terms)."""
        if self.pending is None:
            raise RuntimeError('moments: a sample reached the moment film without its family vector')
        (R, own), self.pending = self.pending, None
        pixel, inside = self.pixels.index(film_pos, active)
        if self.step > 1:
            inside = inside & (pixel % self.step == 0)
            pixel = pixel // self.step
        c_mean, u_mean = channel_mean(weighted), channel_mean(unweighted)
        cu = c_mean * u_mean
        ok = inside & (u_mean != 0) & dr.isfinite(cu) & dr.isfinite(u_mean)
        base = pixel * self.stride
        K = len(self.counts)
        # (Local: lanes of a SIMD packet that add to one pixel reduce first, then one atomic add:
        # 5x faster on veach-bidir than an atomic per lane, 3.2 s -> 0.6 s a 4 spp pilot at 128x128)
        add = lambda value, at, mask: dr.scatter_reduce(dr.ReduceOp.Add, self.buf, value, at, mask,  # noqa: E731
                                                        mode=dr.ReduceMode.Local)
        add(c_mean, base, ok)
        if s is None:               # a merge: its weighted contribution, the merges' image (``merged``)
            add(c_mean, base + self.stride - 1, ok)
        lay = None if s is None else layer_index(mi.UInt32(s), mi.UInt32(t), self.max_length)
        group = None if lay is None else self.groups[dr.width(pixel)]     # the lanes' halves (begin_pass)
        terms = []
        for k, n in enumerate(self.opaque_counts):
            r = R[0] + sum(n[i] * R[i + 1] for i in range(len(n)))          # (family sums)
            has = r > 0
            inv_r = dr.select(has, 1.0 / dr.select(has, r, 1.0), 0.0)
            m = cu * inv_r                                                  # C U / R_k
            add(m, base + 1 + k, ok & dr.isfinite(m))
            if self.can_miss[k]:
                add(dr.abs(c_mean), base + 1 + K + k, ok & ~has)
            if lay is None:         # merges: their I^2 / N_t, N_t = P n_m light subpaths, is left out
                t_k = u_mean * (family_count(own, n) * inv_r)               # U w_m of candidate k
                terms.append(dr.select(ok & dr.isfinite(t_k), t_k, 0.0))
                continue
            i_t = u_mean * (family_count(own, n) * inv_r)                   # U w_s of candidate k
            at = base + 1 + 2 * K + (2 * k + group) * len(self.families) + lay
            add(i_t, at, ok & dr.isfinite(i_t))
        return tuple(terms)

    def add_cross(self, film_pos, sums, squares, active):
        """The merges of one camera vertex with the light vertices of N light subpaths: their
        products with each other, which share the camera subpath, (sum of U w)^2 - sum of (U w)^2
        per candidate (``sums``, ``squares``), an unbiased estimate of the N (N - 1) cross terms
        of its merge estimate's second moment. Left out, the second moment of a merging
        candidate is underestimated as its radius grows (a gather then finds several light
        vertices: 2x at 10 light vertices a gather on the Cornell box)."""
        pixel, inside = self.pixels.index(film_pos, active)
        if self.step > 1:
            inside = inside & (pixel % self.step == 0)
            pixel = pixel // self.step
        base = pixel * self.stride
        for k, (a, b) in enumerate(zip(sums, squares)):
            x = a * a - b
            dr.scatter_reduce(dr.ReduceOp.Add, self.buf, x, base + 1 + k, inside & dr.isfinite(x),
                              mode=dr.ReduceMode.Local)

    def estimates(self, spp):
        """(I, V, missed) as numpy arrays: the image (the kept pixels); each candidate's variance of its
        one-sample pixel estimate (candidates x pixels), M - sum_t I_t^2 / n_t (the second moment
        less each strategy's squared image over its samples in the estimate; the 'other' layer's paths, longer than
        max_length, keep their squares: an overestimate); the share of the image's magnitude each
        candidate cannot sample (candidates)."""
        import numpy as np
        # (a view of the film's memory, float32, converted to float64 part by part: a float64 copy
        # of all of it, 137 MB of fresh pages for the Cornell box at 128 x 128, took ~0.1 s of
        # its choice)
        a = self.buf.numpy().reshape(self.count, self.stride)
        self.merged = a[:, -1].astype(np.float64)
        K, L = len(self.counts), len(self.families)
        image = a[:, 0].astype(np.float64)
        M = spp * a[:, 1:1 + K].T.astype(np.float64)
        missed = a[:, 1 + K:1 + 2 * K].sum(axis=0, dtype=np.float64) / max(float(np.sum(np.abs(image))), 1e-30)
        halves = a[:, 1 + 2 * K:-1].reshape(-1, K, 2, L)
        P = self.pixels.count           # the crop's pixels: light subpaths a one-sample image traces
        # a strategy's samples in a one-sample pixel estimate: the camera sample's (count 1 or
        # n_c), and light tracing's P n_lt light subpaths, each of which may reach the pixel; the
        # 'other' layer's (and a count of 0's) squares are kept: 1 / n = 0
        n = np.array([[(1.0, k[0], P * k[1])[f] if f >= 0 else np.inf for f in self.families]
                      for k in self.counts])
        inv_n = np.where(n > 0, 1.0 / np.where(n > 0, n, 1.0), 0.0)
        # (2 I_a)(2 I_b) = I_t^2 of each strategy, over its samples, summed: all candidates at once,
        # in float64 without a float64 copy of the halves (a loop over the candidates took 0.12 s
        # of a 0.37 s pilot on the Cornell box at 128 x 128; a copy of 35 candidates' halves, 130 MB)
        sq = np.einsum('pkl,pkl,kl->kp', halves[:, :, 0, :], halves[:, :, 1, :], 4.0 * inv_n, dtype=np.float64)
        return image, M - sq, missed


def family_record(record, family=Family):
    """The light-vertex record type ``record`` with its MIS quantities as family vectors of
    type ``family`` (FamilyMIS.F)."""
    fields = {**record.DRJIT_STRUCT, 'd_vcm': family, 'd_vc': family}
    if 'd_vm' in fields:
        fields['d_vm'] = family
    return type(record.__name__ + '_families', (record,), {'DRJIT_STRUCT': fields})


def instrument(ctx, counts):
    """Context ``ctx`` (technique bdpt, or vcm merging everywhere; the classic estimator) made
    to estimate the moments of the candidates of ``counts`` (a list of (n_c, n_lt, n_m), or of
    (n_c, n_lt, n_m behind delta, n_m elsewhere): both merge sets from one pilot, FamilyMIS's
    ``split``, vcm merging everywhere in a scene without media): its weights FamilyMIS's (the
    balance heuristic with counts 1), its records carrying family vectors, and ``ctx.moments``."""
    from .film import NearestPixel
    if ctx.light_cache is not None or ctx.ad:
        raise ValueError('moments: the pilot is the classic estimator, without derivatives')
    split = any(len(k) == 4 for k in counts)
    if split and not (ctx.mis.mis_merges and ctx.mis.merge_everywhere and ctx.media is None):
        raise ValueError('moments: both merge sets are predicted by a pilot merging everywhere, without media')
    ctx.moments = MomentFilm(NearestPixel(ctx.sensor.film()), counts, min(ctx.max_depth_edges, MAX_LENGTH),
                             MAX_PIXELS)
    ctx.mis = FamilyMIS(ctx.strategies, tap=ctx.moments, merge_everywhere=ctx.mis.merge_everywhere, split=split)
    ctx.record = family_record(ctx.record, ctx.mis.F)
    return ctx.moments
