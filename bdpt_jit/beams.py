"""Merging inside participating media by beams: each segment a camera subpath travels through
a medium gathers the light vertices of that medium within the merging radius r of it (the
point-beam 2D estimate with short query beams: Jarosz, Nowrouzezahrai, Sadeghi and Jensen,
"A comprehensive theory of volumetric radiance estimation using photon points and beams",
TOG 2011; Krivanek et al., "Unifying points, beams, and paths in volumetric light transport
simulation", SIGGRAPH 2014). A ball around a camera vertex (merge.py's point-point estimate)
finds a light vertex only where the camera subpath happened to collide next to it; a segment
finds every light vertex along its whole length, 3 / (4 r sigma_t) times as many in a medium of
extinction sigma_t (about 280 for the fog of scenes/media/volumetric-caustic.xml).

Estimate. A camera subpath that scattered at z (throughput beta_z, the scatter's factor
included) towards d and reached its next vertex at distance t_end (a collision or a surface)
passes every point z + s d with s < t_end. For a light vertex y of the same iteration within r
of the segment (s its projection):

    L ~ beta_z * sigma_s(y) p(-d, w_y) * beta_y * w / (pi r^2 N)

over the disc of radius r across the beam. Distance sampling reaches s with the probability
P(s), and in a gray medium (sigma_t the same in every channel: media.MediaInfo.gray) P(s) is
the transmittance T(z, s) itself, so T / P = 1 and neither appears. (In a chromatic medium P is
a mixture over channels and T / P a ratio the walk does not keep: there merges stay balls,
merge.py.) The MIS density of this strategy relative to the camera sampling y as a vertex
(sigma_t T per unit length) is P / (sigma_t T) = 1 / sigma_t(y) (mis.MIS.merge_factor); its
weight's camera side is the camera subpath's MIS state after the scatter at z, carried to s by
the distance densities of the edge z -> s (media.MediumTracer.edge without tracking).

Search. The light vertices inside media go into their own hashed grid (BeamGrid), each into
every cell its ball of radius r overlaps (up to 8: cells are at least 2 r wide). A segment walks
the cells it crosses (Amanatides and Woo's traversal), clipped to the bounding box of the light
vertices' balls; each cell covers an interval [t_enter, t_exit) of the segment, and a light
vertex counts in the cell whose interval holds its projection s: once, whichever of its cells
the segment crosses and whatever buckets they share. Cells are wider than 2 r where the light
vertices are sparse: a cell holds CELL_VERTICES of an iteration's vertices on average (the cost is
cells crossed plus vertices tested, and a cell crossed costs more than a vertex tested: its
bucket's two words are a random read of a table of 4 words a vertex, the vertices' positions are
read in bucket order)."""

import drjit as dr
import mitsuba as mi

from .jitmath import safe_div
from .rays import scene_bbox
from .media import DensityFactor, MediumVertex, interaction_at
from . import merge
from .merge import _PRIMES
from .vertex import RADIANCE

_WIDE = 1e30           # an axis the direction does not move along: its next crossing
# an iteration's vertices in a cell on average, where that makes cells wider than 2 r: 0.5 (a
# cell crossed costing what a vertex tested costs) put vcm's camera kernel 8-12% above 3 on
# scenes/media/volumetric-caustic.xml at 128 x 128 and 256 x 256 (16 spp; at 64 x 64 the same
# either way; the least of 4 renders a setting, cells 1.5 to 4 times 0.5's tried: 2.5 on slower)
CELL_VERTICES = 3.0
# the light subpaths of an iteration that vcm's beams gather from, at most (parameter beam_paths,
# ``beam_cap``): on scenes/media/volumetric-caustic.xml at 16 s, 128 x 128 (16384 an iteration),
# vcm's relMSE 0.082 of volpath's with all, 0.074 with 4096, 0.075 with 2048, 0.083 with 8192
# (docs/media.md, thirty-eighth session)
BEAM_PATHS = 4096


def beam_cap(strategies, beam_paths):
    """The beams' cap on an iteration's light subpaths (merge.MergeSchedule): parameter
    ``beam_paths``, or where it is automatic (None) BEAM_PATHS, and all of them (0) in vm,
    where beams alone sample the paths they sample (at 128 x 128 on the volumetric caustic,
    vm's relMSE 0.56 of volpath's with all, 0.74 with 4096)."""
    if beam_paths is not None:
        return beam_paths
    return 0 if strategies.ppm else BEAM_PATHS


class BeamGrid:
    """The medium light vertices of one pass (store.LightStore) in a hashed uniform grid, each
    in every cell its iteration's ball overlaps (module docstring).

    origin          the grid's origin (the scene's bounding-box minimum)
    size            the cell size (opaque)
    lo, hi          the bounding box of the light vertices' balls (width-1 arrays; empty: lo > hi)
    mask            table size - 1 (a power of two), opaque
    start           per bucket: its first entry (and the next bucket's: its end)
    slots           the store's slots in bucket order
    points          and their positions, with their iteration's bits in w (BeamGather.candidate)"""

    def __init__(self, scene, store, schedule):
        self.store, self.schedule = store, schedule
        bbox = scene_bbox(scene)
        self.origin = mi.Point3f(bbox.min) if bbox.valid() else mi.Point3f(0.0)
        slot = store.stored_slots(in_medium=True, lanes=schedule.beam_lanes)   # (a few of the slots: compacted first)
        empty = dr.width(slot) == 0
        if empty:                   # no medium vertex: one masked-off entry (slot 0 is allocated)
            slot = mi.UInt32([0])
        idx = slot - (slot // store.n_opaque) * store.n_opaque
        first = dr.gather(mi.Vector4f, store.v, slot * store.record.packets())    # 'p' leads every record
        p = mi.Point3f(first.x, first.y, first.z)
        group = schedule.group(idx)
        r = schedule.radius(group)
        dr.eval(p, group, r)        # (once: the bounds' reductions and the sort's kernels read them)
        valid = dr.full(mi.Bool, not empty, dr.width(slot))
        self.bounds(p, r, valid)
        self.size = dr.opaque(mi.Float, self.cell_size(bbox, schedule, dr.width(slot)))
        size = 1               # buckets: merge.BUCKETS per vertex at least (up to 8 entries each, ~1-2 typically)
        while size < max(merge.BUCKETS * dr.width(slot), 1):
            size *= 2
        self.mask = dr.opaque(mi.UInt32, size - 1)
        self.sort(p, r, group, slot, valid, size)

    def bounds(self, p, r, valid):
        """lo, hi: the box around every valid vertex's ball (empty where there is none)."""
        big = mi.Float(dr.largest(mi.Float))
        self.lo = mi.Point3f(*[dr.min(dr.select(valid, p[i] - r, big)) for i in range(3)])
        self.hi = mi.Point3f(*[dr.max(dr.select(valid, p[i] + r, -big)) for i in range(3)])
        dr.eval(self.lo, self.hi)

    def cell_size(self, bbox, schedule, count):
        """At least 2 r (the pass's first, largest radius); (CELL_VERTICES V / n)^(1/3) for the n
        vertices of an iteration (``count`` in the pass) in the volume V of their box, where that
        is larger."""
        n = max(count / max(int(schedule.spp_pass[0]), 1), 1.0)
        ext = [max(float(self.hi[i][0] - self.lo[i][0]), 0.0) for i in range(3)]
        volume = max(ext[0] * ext[1] * ext[2], 1e-30)
        return max(2.0 * schedule.r1 * float(schedule.first[0]) ** (0.5 * (schedule.alpha - 1.0)),
                   (CELL_VERTICES * volume / n) ** (1.0 / 3.0))

    def sort(self, p, r, group, slot, valid, size):
        """The counting sort (as merge.PhotonGrid's) of the entries (vertex, corner q < 8) of the
        medium vertices at ``slot``: the corner's cell on each axis is the cell of p - r (bit
        clear) or of p + r (bit set), an entry only where that differs or the bit is clear, and
        where no earlier corner has its bucket."""
        n = dr.width(slot)
        c_lo, c_hi = self.cell(p - r), self.cell(p + r)
        buckets, use = [], []
        for q in range(8):
            bits = [(q >> i) & 1 for i in range(3)]
            c = mi.Vector3i(*[c_hi[i] if bits[i] else c_lo[i] for i in range(3)])
            ok = mi.Bool(valid)
            for i in range(3):
                if bits[i]:
                    ok &= c_hi[i] != c_lo[i]
            b = self.bucket(c, group)
            for e, u in zip(buckets, use):
                ok &= ~(u & (e == b))
            buckets.append(b)
            use.append(ok)
        dr.eval(buckets, use)       # (in one kernel; each count below then reads them)
        counts = dr.zeros(mi.UInt32, size + 1)
        places = []
        for b, ok in zip(buckets, use):     # (each result read once: evaluated one by one)
            places.append(dr.scatter_inc(counts, b, ok))
            dr.eval(places[-1])
        self.start = dr.prefix_sum(counts)
        self.slots = dr.zeros(mi.UInt32, max(8 * n, 1))
        self.points = dr.zeros(mi.Vector4f, max(8 * n, 1))
        point = mi.Vector4f(p.x, p.y, p.z, dr.reinterpret_array(mi.Float, group))
        for b, ok, place in zip(buckets, use, places):
            at = dr.gather(mi.UInt32, self.start, b, ok) + place
            dr.scatter(self.slots, slot, at, ok)
            dr.scatter(self.points, point, at, ok)
        dr.eval(self.start, self.slots, self.points)

    def cell(self, p):
        return mi.Vector3i(dr.floor((p - self.origin) * dr.rcp(self.size)))

    def bucket(self, c, group):
        u = [dr.reinterpret_array(mi.UInt32, c[i]) * _PRIMES[i] for i in range(3)]
        return (u[0] ^ u[1] ^ u[2] ^ (group * 2654435761)) & self.mask

    def entries(self, c, group, active):
        """The entries [first, end) of cell ``c``'s bucket in iteration ``group``."""
        b = self.bucket(c, group)
        return dr.gather(mi.UInt32, self.start, b, active), dr.gather(mi.UInt32, self.start, b + 1, active)

    def clip(self, o, d, t_end):
        """[t_a, t_b): the part of the segment o + t d, 0 <= t < t_end, inside the box lo, hi."""
        t_a, t_b = mi.Float(0.0), mi.Float(t_end)
        lo, hi = self.lo, self.hi
        for i in range(3):
            flat = dr.abs(d[i]) < 1e-20
            inv = dr.rcp(dr.select(flat, 1.0, d[i]))
            t0, t1 = (lo[i] - o[i]) * inv, (hi[i] - o[i]) * inv
            inside = (o[i] >= lo[i]) & (o[i] <= hi[i])
            near = dr.select(flat, dr.select(inside, -_WIDE, _WIDE), dr.minimum(t0, t1))
            far = dr.select(flat, dr.select(inside, _WIDE, -_WIDE), dr.maximum(t0, t1))
            t_a, t_b = dr.maximum(t_a, near), dr.minimum(t_b, far)
        return t_a, t_b


class Traversal:
    """The state of one segment's walk through the grid's cells, one field a line."""
    DRJIT_STRUCT = {
        'cell': mi.Vector3i,      # the current cell
        't_next': mi.Vector3f,    # per axis: the t at which the segment leaves it across that axis
        't_enter': mi.Float,      # the t at which the segment entered it
        'e': mi.UInt32,           # the next entry of its bucket
        'e_end': mi.UInt32,       # the bucket's end
    }

    def __init__(self, cell=None, t_next=None, t_enter=None, e=None, e_end=None):
        self.cell, self.t_next, self.t_enter, self.e, self.e_end = cell, t_next, t_enter, e, e_end


class Segment:
    """A camera subpath's segment through media, as the gather needs it, one field a line."""

    def __init__(self, v, ray, medium, t_end, sub, first):
        self.v = v                # the vertex it leaves (media_path.PathVertex), or None: the camera
        self.ray = ray            # its ray (unit direction)
        self.medium = medium      # the medium it starts in
        self.t_end = t_end        # where it ends (a collision, a surface; inf: it left the scene)
        self.sub = sub            # the camera Subpath after the scatter at v (throughput, MIS, depth of v)
        self.first = first        # the camera's first segment (v None: distances from the lens)


class BeamGather:
    """The beam estimate along camera segments, for the CameraTracer (owned per pass)."""

    def __init__(self, ctx, grid, mis):
        self.ctx, self.grid, self.mis = ctx, grid, mis

    def start(self, seg, t_a, group, active):
        """The Traversal at t_a (the cell there and its entries)."""
        g, o, d = self.grid, seg.ray.o, seg.ray.d
        cell = g.cell(o + d * t_a)
        nxt = []
        for i in range(3):
            flat = dr.abs(d[i]) < 1e-20
            edge = g.origin[i] + (mi.Float(cell[i]) + dr.select(d[i] > 0, 1.0, 0.0)) * g.size
            nxt.append(dr.select(flat, _WIDE, (edge - o[i]) * dr.rcp(dr.select(flat, 1.0, d[i]))))
        e, e_end = g.entries(cell, group, active)
        return Traversal(cell, mi.Vector3f(*nxt), mi.Float(t_a), e, e_end)

    def step(self, tv, seg, t_b, group, adv):
        """Lanes ``adv``: on to the next cell along the axis crossed first, and its entries.
        Returns (the Traversal, the lanes still inside [.., t_b))."""
        g, d = self.grid, seg.ray.d
        tn = tv.t_next
        ax = [(tn.x <= tn.y) & (tn.x <= tn.z)]
        ax.append(~ax[0] & (tn.y <= tn.z))
        ax.append(~ax[0] & ~ax[1])
        t_exit = dr.minimum(dr.minimum(dr.minimum(tn.x, tn.y), tn.z), t_b)
        t_enter = dr.select(adv, t_exit, tv.t_enter)
        cell, nxt = [], []
        for i in range(3):
            move = adv & ax[i]
            cell.append(tv.cell[i] + dr.select(move, dr.select(d[i] > 0, mi.Int32(1), mi.Int32(-1)), mi.Int32(0)))
            nxt.append(tn[i] + dr.select(move, g.size * dr.rcp(dr.abs(d[i])), 0.0))
        cell = mi.Vector3i(*cell)
        inside = ~adv | (t_enter < t_b)
        e, e_end = g.entries(cell, group, adv & inside)
        return Traversal(cell, mi.Vector3f(*nxt), t_enter, dr.select(adv, e, tv.e),
                         dr.select(adv, e_end, tv.e_end)), inside

    @dr.syntax
    def gather(self, idx, seg, active, film_pos=None):
        """Radiance towards the camera from the light vertices of sample ``idx``'s iteration
        within its radius of the Segment ``seg`` (``film_pos``: the sample's, for technique
        auto's pilot)."""
        c, g = self.ctx, self.grid
        sched = g.schedule
        group = sched.group(idx)
        r = sched.radius(group)
        norm = 1.0 / (dr.pi * r * r * sched.beam_paths_f)
        t_a, t_b = g.clip(seg.ray.o, seg.ray.d, seg.t_end)
        going = active & (t_a < t_b)
        tv = self.start(seg, t_a, group, going)
        tap = None if c.moments is None else (film_pos, seg.sub.beta * norm * c.inv_spp)
        n_cand = 0 if tap is None else len(c.moments.counts)
        sums = squares = (dr.zeros(mi.Float, dr.width(t_a)),) * n_cand
        total = mi.Spectrum(0.0)
        while dr.hint(going, label='bdpt_beam'):
            has = going & (tv.e < tv.e_end)
            t_exit = dr.minimum(dr.minimum(dr.minimum(tv.t_next.x, tv.t_next.y), tv.t_next.z), t_b)
            value, terms = self.merge_one(tv.e, (tv.t_enter, t_exit), seg, (group, r * r), has, tap)
            total += value
            sums = tuple(sums[q] + terms[q] for q in range(n_cand))
            squares = tuple(squares[q] + terms[q] * terms[q] for q in range(n_cand))
            tv.e = dr.select(has, tv.e + 1, tv.e)
            tv, inside = self.step(tv, seg, t_b, group, going & ~has)
            going = going & inside
        if tap is not None:
            c.moments.add_cross(film_pos, sums, squares, active)
        return seg.sub.beta * total * norm

    def candidate(self, k, interval, seg, group_r2, active):
        """Entry ``k`` of the grid: whether it counts for the segment here (its iteration, its
        projection s in ``interval`` = (t_enter, t_exit) of the current cell and on the segment,
        within r of it; ``group_r2``: the iteration and its radius squared). Returns (that mask,
        its slot, its level, its position, (its projection q, s))."""
        g = self.grid
        st = g.store
        group, r2 = group_r2
        o, d = seg.ray.o, seg.ray.d
        # the grid's own copy of the positions in bucket order (consecutive words), then the
        # slot of an entry that counts only
        first = dr.gather(mi.Vector4f, g.points, k, active)
        ok = active & (dr.reinterpret_array(mi.UInt32, first.w) == group)     # (the iteration's bits)
        y_p = mi.Point3f(first.x, first.y, first.z)
        s = dr.dot(y_p - o, d)
        ok &= (s >= interval[0]) & (s < interval[1]) & (s >= 0.0) & (s < seg.t_end)
        q = o + d * s
        ok &= dr.squared_norm(y_p - q) <= r2
        slot = dr.gather(mi.UInt32, g.slots, k, ok)
        level = slot // st.n_opaque
        return ok, slot, level, y_p, (q, s)

    @dr.syntax
    def merge_one(self, k, interval, seg, group_r2, active, tap=None):
        """Entry ``k`` of the grid merged with the segment (``candidate``'s arguments).
        Returns (the value, unnormalised; the moment film's terms). The merge itself is
        evaluated only where the entry counts (a symbolic branch: ~1 entry in 100 lies within
        r of the segment, and the rest skip the record, the phase function and the edge)."""
        ok, slot, level, y_p, qs = self.candidate(k, interval, seg, group_r2, active)
        value = dr.zeros(mi.Spectrum, dr.width(ok))
        terms = () if tap is None else tuple(dr.zeros(mi.Float, dr.width(ok)) for _ in self.ctx.moments.counts)
        if ok:
            value, terms = self.evaluate((slot, level, y_p, qs), seg, ok, tap)
        return value, terms

    def evaluate(self, entry, seg, ok, tap):
        """The merge of the entry (its slot, level, position and (q, s)) with the segment."""
        c, st = self.ctx, self.grid.store
        slot, level, y_p, qs = entry
        rec = st.record.load(st.v, slot, ok)
        ok &= rec.depth_at(level) + seg.sub.depth + 1 <= c.max_depth_edges
        y = rec.interaction(c.time, seg.ray.wavelengths)
        wl = y.to_world(y.wi)                   # towards the light subpath's previous vertex
        z = MediumVertex(self.point(rec.medium, y_p, seg.ray, ok))
        f, pdf_dir_w, pdf_rev_w, _ = z.eval(c, wl, RADIANCE, ok)
        value = f * rec.beta
        ok &= (dr.max(value) > 0) & (dr.max(value) < dr.inf)
        w = self.weight(rec, seg, qs, z, (pdf_dir_w, pdf_rev_w), ok)
        terms = ()
        if tap is not None:
            film_pos, scale = tap
            terms = c.moments.add(None, None, film_pos, value * (w * scale), value * scale, ok)
        return dr.select(ok, value * w, 0.0), terms

    def point(self, medium, p, ray, active):
        """The camera's point of the beam at ``p``: a medium interaction of ``medium`` whose wi
        points back along the segment's ``ray``, its coefficients there."""
        return interaction_at(medium, mi.Ray3f(p, ray.d, 0.0, ray.time, ray.wavelengths), active)

    def weight(self, rec, seg, qs, z, pdfs, active):
        """The MIS weight of the merge of light vertex ``rec`` with the segment at its
        projection ``qs`` = (q, s); ``z``: the camera's MediumVertex there; ``pdfs``: its phase
        function's densities of the light's direction and of its own given that one."""
        c, mis = self.ctx, self.mis
        q, s = qs
        info = c.media.info
        ray = mi.Ray3f(seg.ray.o, seg.ray.d, s * (1.0 - 1e-4), seg.ray.time, seg.ray.wavelengths)
        n = dr.width(s)
        et = c.media.edge(ray, (q, mi.Normal3f(0.0), mi.Float(0.0)), seg.medium, None, active, tracking=False)
        near = seg.v.density_factor(info) if seg.v is not None else DensityFactor.surface(n)
        far = z.density_factor(info, active)
        st = mis.distance(seg.sub.mis, et.pdf_l(far), et.pdf_l(near))
        if seg.first:
            dist2 = c.camera.first_edge_dist2(seg.ray, q)
        else:
            dist2 = dr.squared_norm(q - seg.v.p)
        st = mis.hit(st, dist2, mi.Float(1.0), True)
        inv_factor = safe_div(1.0, mis.merge_factor(True, True, far.sigma()))
        l_vm = rec.d_vm if 'd_vm' in rec.DRJIT_STRUCT else 0.0
        return mis.weight_merge(rec.d_vcm, l_vm, st.d_vcm, st.d_vm, pdfs[0], pdfs[1], inv_factor)
