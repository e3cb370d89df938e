"""Vertex merging (techniques ``vcm`` and ``vm``): the light vertices of every light subpath of a
pass in a hashed uniform grid, and the density estimate at a camera vertex.

Merging a camera vertex z with a light vertex y closer than r estimates the radiance z sends
towards the camera from the light that reached y (Georgiev et al. 2012, Hachisuka et al. 2008):

    L(z) ~ 1 / (pi r^2 N) * sum_y  f_z(y's incoming direction) * beta_y * w_merge

over the light vertices y of the iteration's N light subpaths within r of z (a constant kernel
over the disc of radius r), where beta_y is the light subpath's throughput up to y (per unit
area at y: no cosine at y) and f_z the camera vertex's BSDF. Mitsuba's ``eval`` gives
f |cos_s|; the estimate needs f |cos_s| / |cos_g|: the light's flux per unit area of the
surface (beta_y) is measured with the geometric normal, y's own (see merge_one). The
estimate is biased (the light is blurred over the disc) and consistent: the radius shrinks from
iteration to iteration (MergeSchedule, parameter ``radius_alpha``).

The grid is built with Dr.Jit alone, by a counting sort: each stored vertex hashes its cell
(cell size 2r) and iteration, the buckets' counts are atomic increments, a prefix sum gives each
bucket its start, and the increments' old values give each vertex its place. A query visits the
2 x 2 x 2 cells nearest to z (they cover the ball of radius r around it), skipping a bucket
that two of them hash to (it would count its vertices twice), in one loop over their entries.

In a scene with participating media a camera vertex in a medium merges with the light vertices
of its medium in the ball of radius r: 1 / (4/3 pi r^3 N) times sigma_s p beta_y w, without
cosines (beta_y per unit volume there; Krivanek et al. 2014, UPBP's point-point 3D)."""

import drjit as dr
import mitsuba as mi

from .jitmath import safe_div
from .rays import scene_bbox
from .vertex import RADIANCE

_PRIMES = (73856093, 19349663, 83492791)    # spatial hash (Teschner et al. 2003)
BUCKETS = 4             # the hash table's buckets per stored vertex, at least


def scene_radius(scene):
    """Radius of the scene's bounding sphere (1 for an empty scene)."""
    bbox = scene_bbox(scene)
    r = float(dr.norm(bbox.max - bbox.min)) * 0.5 if bbox.valid() else 1.0
    return r if r > 0 else 1.0


class MergeSchedule:
    """The iterations of one pass. A pass of spp_pass samples per pixel holds spp_pass
    iterations: sample j of every pixel, its camera subpath and its light subpath (the same
    index), form iteration ``first + j``, whose camera vertices merge only with that
    iteration's light vertices (one light subpath per pixel: N = the pass's pixel count), with
    the radius r_i = r_1 i^((alpha-1)/2) (Knaus and Zwicker 2011, as SmallVCM: r_1 = ``radius``
    times the radius of the scene's bounding sphere). The MIS weights of every strategy of that
    sample take eta_i = pi r_i^2 N. Merging the pass's light vertices with every camera sample
    of a pixel instead would reuse them for all its samples: measured on the repository's
    caustic scene (64 spp a pass), vcm was then 4x noisier than bdpt where neither merges
    anything useful, since the weights assume independent light subpaths.

    Merges by beams inside media (beams.py) use the medium vertices of the first ``beam_cap``
    light subpaths of an iteration at most (parameter ``beam_paths``: N_b = min(N, beam_cap);
    the subpaths are independent of their pixel, so any fixed subset is a sample of N_b): a
    beam gathers along the whole camera segment, so at a radius fixed in the scene's units the
    light vertices it tests, and its time, grow with N while the rest of a sample's work does
    not (in fog behind glass, vcm's time a sample was 1.6, 2.0 and 3.2 times bdpt's at 128,
    256 and 512 pixels square). Surface merges and balls keep all N: a cap there costs the
    paths that only merges sample (docs/merging.md). The weights count N_b for the beams
    (``beam_share`` = N_b / N of a surface merge's eta, mis.MIS.merge_factor)."""

    def __init__(self, scene, radius_rel, alpha, first, spp_pass, paths, beam_cap=None):
        # paths: light subpaths of an iteration (the pass's pixel count; with the light vertex
        # cache its n_L / spp_pass)
        self.r1 = radius_rel * scene_radius(scene)
        self.alpha = alpha
        self.r_last = self.r1 * float(first + spp_pass - 1) ** (0.5 * (alpha - 1.0))
        self.first = dr.opaque(mi.Float, float(first))
        self.paths_f = dr.opaque(mi.Float, float(paths))                # N of an iteration
        self.spp_pass = dr.opaque(mi.UInt32, spp_pass)
        # the beams' N_b (beam_cap 0 or None: N) and the light subpaths they gather from: those
        # of index below beam_lanes (a pixel's samples consecutive: the first N_b of each
        # iteration), None for all
        self.beam_paths = paths if not beam_cap else min(paths, max(int(beam_cap), 1))
        self.beam_paths_f = dr.opaque(mi.Float, float(self.beam_paths))
        self.beam_share = dr.opaque(mi.Float, self.beam_paths / max(paths, 1))
        self.beam_lanes = self.beam_paths * spp_pass if self.beam_paths < paths else None

    def group(self, idx):
        """The iteration (from 0 in the pass) of sample / light subpath ``idx`` (a pixel's
        samples are consecutive)."""
        return idx % self.spp_pass

    def radius(self, group):
        return self.r1 * dr.power(self.first + mi.Float(group), 0.5 * (self.alpha - 1.0))

    def eta(self, idx):
        r = self.radius(self.group(idx))
        return dr.pi * r * r * self.paths_f


class PhotonGrid:
    """The light vertices of one pass (store.LightStore), sorted by hashed (cell, iteration);
    each iteration's cells are twice its radius wide.

    origin          the scene's bounding-box minimum (cell coordinates from there)
    mask            table size - 1 (a power of two), opaque
    start           per bucket: its first entry (and the next bucket's: its end)
    slots           the store's slots in bucket order
    points          and their positions, with their iteration's bits in w (Merger.near)

    ``surface_only``: the vertices on surfaces alone (where media merge by beams, beams.py, no
    camera vertex merges with a medium vertex here: Merger.merge_one)."""

    def __init__(self, scene, store, schedule, surface_only=False):
        slot = store.stored_slots(in_medium=False if surface_only else None)
        n = dr.width(slot)
        size = 1               # buckets: BUCKETS times the entries, so that empty cells rarely share one
        while size < max(BUCKETS * n, 1):
            size *= 2
        bbox = scene_bbox(scene)
        self.origin = mi.Point3f(bbox.min) if bbox.valid() else mi.Point3f(0.0)
        self.mask = dr.opaque(mi.UInt32, size - 1)
        self.store = store
        self.schedule = schedule
        counts = dr.zeros(mi.UInt32, size + 1)                        # (the last: no bucket)
        self.slots = dr.zeros(mi.UInt32, max(n, 1))
        if n > 0:
            idx = slot - (slot // store.n_opaque) * store.n_opaque
            first = dr.gather(mi.Vector4f, store.v, slot * store.record.packets())  # 'p' leads every record
            group = schedule.group(idx)
            bucket = self.bucket(self.cell(mi.Point3f(first.x, first.y, first.z), group), group)
            dr.eval(bucket, first, group)        # (the sort's last kernel reads them again)
            place = dr.scatter_inc(counts, bucket)                   # place within the bucket
            dr.eval(place)                                            # (a result read once only)
        # exclusive: bucket b holds entries start[b] .. start[b + 1] - 1 (one array: a query's
        # two reads of a bucket share a cache line)
        self.start = dr.prefix_sum(counts)
        # and in bucket order, each entry's position and iteration (its bits in w): a query tests
        # the entries of its cells reading consecutive words, not the store's records
        self.points = dr.zeros(mi.Vector4f, max(n, 1))
        if n > 0:
            at = dr.gather(mi.UInt32, self.start, bucket) + place
            dr.scatter(self.slots, slot, at)
            dr.scatter(self.points, mi.Vector4f(first.x, first.y, first.z, dr.reinterpret_array(mi.Float, group)), at)
        dr.eval(self.start, self.slots, self.points)

    def inv_cell(self, group):
        """1 / the cell size of iteration ``group``: twice its radius (the radius shrinks
        within a pass: cells of the pass's first radius held 3x the candidates at its end)."""
        return 0.5 / self.schedule.radius(group)

    def cell(self, p, group):
        return mi.Vector3i(dr.floor((p - self.origin) * self.inv_cell(group)))

    def bucket(self, c, group):
        u = [dr.reinterpret_array(mi.UInt32, c[i]) * _PRIMES[i] for i in range(3)]
        return (u[0] ^ u[1] ^ u[2] ^ (group * 2654435761)) & self.mask

    def neighbourhood(self, p, group):
        """The buckets of the 2 x 2 x 2 cells around ``p`` in iteration ``group`` (a list of 8)
        and, for each, whether an earlier one of the 8 is the same bucket."""
        x = (p - self.origin) * self.inv_cell(group)
        c0 = mi.Vector3i(dr.floor(x))
        step = mi.Vector3i(dr.select(x - dr.floor(x) < 0.5, -1, 1))
        buckets, dup = [], []
        for q in range(8):
            c = c0 + mi.Vector3i(step.x * (q & 1), step.y * ((q >> 1) & 1), step.z * ((q >> 2) & 1))
            b = self.bucket(c, group)
            d = mi.Bool(False)
            for e in buckets:
                d |= e == b
            buckets.append(b)
            dup.append(d)
        return buckets, dup


class Merger:
    """The merging estimate at camera vertices, for the CameraTracer (owned per pass)."""

    def __init__(self, ctx, grid, mis):
        self.ctx = ctx
        self.grid = grid
        self.mis = mis              # the pass's mis.MIS (its merging radius)

    def ranges(self, p, group, active=True):
        """The entries of the 2 x 2 x 2 cells around ``p`` in iteration ``group``: each cell's
        first entry, and the running totals (9 values, the last the number of entries); a bucket
        that two of the cells hash to counts once. Lanes not ``active`` read nothing (none)."""
        g = self.grid
        buckets, dup = g.neighbourhood(p, group)
        starts, totals = [], [mi.UInt32(0)]
        for b, d in zip(buckets, dup):
            first, end = dr.gather(mi.UInt32, g.start, b, active), dr.gather(mi.UInt32, g.start, b + 1, active)
            starts.append(first)
            totals.append(totals[-1] + dr.select(d, 0, end - first))
        return starts, totals

    @staticmethod
    def entry(e, starts, totals):
        """The grid's entry number ``e`` of a query's cells (``ranges``: their starts and running
        totals)."""
        k = starts[0] + e
        for q in range(1, 8):
            k = dr.select(e >= totals[q], starts[q] + (e - totals[q]), k)
        return k

    def near(self, k, p, group, radius2, active):
        """Whether entry ``k`` of the sorted grid is a light vertex of iteration ``group`` within
        the radius of ``p``, from the grid's own copy of the positions in bucket order (a query's
        entries are consecutive words there; the store's records lie wherever their subpaths
        put them)."""
        q = dr.gather(mi.Vector4f, self.grid.points, k, active)
        same = dr.reinterpret_array(mi.UInt32, q.w) == group     # (its bits: exact for any iteration count)
        return active & same & (dr.squared_norm(mi.Point3f(q.x, q.y, q.z) - p) <= radius2)

    def merge_one(self, k, v, sub, active, inv_factor=None, tap=None):
        """Entry ``k`` of the sorted grid, a light vertex of the camera vertex's iteration within
        its radius where ``active`` (``near``), merged with camera vertex ``v`` (vertex.Vertex,
        or media_path.PathVertex) of the camera subpath ``sub`` (unnormalised); ``inv_factor``:
        mis.MIS.weight_merge's (scenes with media); ``tap``: (film position, scale to the film,
        the merge's family: ``gather``'s ``own``) of technique auto's pilot, whose moment film
        takes each merge (moments.py). Returns (the
        merge's value, the moment film's per-candidate terms of it: none without ``tap``)."""
        c, g = self.ctx, self.grid
        si = v.si
        st = g.store
        slot = dr.gather(mi.UInt32, g.slots, k, active)
        record = st.record
        level = slot // st.n_opaque
        rec = record.load(st.v, slot, active)
        ok = active & (rec.depth_at(level) + sub.depth <= c.max_depth_edges)
        if c.media is not None:                     # a surface with a surface, a medium vertex with one of its medium
            ok &= (rec.in_medium != 0) == v.in_medium
            ok &= ~v.in_medium | (rec.medium == v.medium)
        y = rec.interaction(c.time, si.wavelengths)
        wl = y.to_world(y.wi)                       # towards the light subpath's previous vertex
        f, pdf_dir_w, pdf_rev_w, _ = v.eval(c, wl, RADIANCE, ok)
        # beta_y is flux per unit area of y's surface (its geometric normal): on a mesh with
        # interpolated normals a light vertex on the neighbouring triangle reaches z's triangle
        # at grazing angles, where 1 / |cos_g| of z would explode (fireflies up to 42x the
        # median on a smooth torus); for light vertices on z's own plane the two are one
        inv_cos = safe_div(1.0, dr.abs(dr.dot(y.n, wl)))
        if c.media is not None:     # a medium vertex: beta_y per unit volume, sigma_s p in f, no cosine
            inv_cos = dr.select(v.in_medium, 1.0, inv_cos)
        value = f * rec.beta * inv_cos
        ok &= (dr.max(value) > 0) & (dr.max(value) < dr.inf)
        l_vm = rec.d_vm if 'd_vm' in record.DRJIT_STRUCT else 0.0
        w = self.mis.weight_merge(rec.d_vcm, l_vm, sub.mis.d_vcm, sub.mis.d_vm, pdf_dir_w, pdf_rev_w, inv_factor,
                                  True if tap is None else tap[2])
        terms = ()
        if tap is not None:
            film_pos, scale, _ = tap
            terms = c.moments.add(None, None, film_pos, value * (w * scale), value * scale, ok)
        return dr.select(ok, value * w, 0.0), terms

    @dr.syntax
    def gather(self, idx, v, sub, active, film_pos=None, own=True):
        """Radiance towards the camera subpath ``sub`` of sample ``idx`` from merging at its
        vertex ``v``: the estimate over its iteration's light vertices within that iteration's
        radius, times the camera throughput (``film_pos``: the sample's, for technique auto's
        pilot; ``own``: the merges' term in the weights there, mis.MIS.merge_here_camera, whose
        family the pilot's moments.FamilyMIS reads)."""
        si = v.si
        sched = self.grid.schedule
        group = sched.group(idx)
        r = sched.radius(group)
        radius2 = r * r
        norm = 1.0 / (dr.pi * radius2 * sched.paths_f)
        inv_factor = None
        if self.ctx.media is not None:      # inside media: the ball, 4/3 pi r^3 N
            norm = dr.select(v.in_medium, norm * (0.75 / r), norm)
            if self.mis.mis_merges:         # (vm: no weights)
                inv_factor = safe_div(1.0, v.merge_factor(self.mis, self.ctx.media.info))
        tap = None if self.ctx.moments is None else (film_pos, sub.beta * norm * self.ctx.inv_spp, own)
        starts, totals = self.ranges(si.p, group, active)
        total = mi.Spectrum(0.0)
        e = dr.zeros(mi.UInt32, dr.width(si.p))
        # technique auto's pilot: per candidate, the sum of this vertex's merges and of their
        # squares (moments.MomentFilm.add_cross; empty otherwise)
        n_cand = 0 if tap is None else len(self.ctx.moments.counts)
        sums = squares = (dr.zeros(mi.Float, dr.width(si.p)),) * n_cand
        # one iteration per entry of the 8 cells within the radius (empty cells cost nothing:
        # ~2 entries a query on the Cornell box, against 8 cell steps a query before): the
        # entries outside it are skipped by a loop that reads their positions only (``near``),
        # so that the merge's own work (the record, the BSDF, the weight), which a SIMD packet
        # runs whenever one of its lanes merges, runs once per entry within the radius of some
        # lane, not once per entry of the cells (on veach-bidir at 256 x 256, merging
        # everywhere: 3.5 of 20 entries a query within the radius; its camera kernel 0.78 ->
        # 0.40 s at 2 spp, the skip loop alone 0.84, the sorted positions alone 0.65)
        while dr.hint(active & (e < totals[8]), label='bdpt_merge'):
            while dr.hint(active & (e < totals[8]) & ~self.near(self.entry(e, starts, totals), si.p, group,
                                                                radius2, active & (e < totals[8])),
                          label='bdpt_merge_skip'):
                e += 1          # (an entry past the query's last is not read: its index may lie past the grid's)
            value, terms = self.merge_one(self.entry(e, starts, totals), v, sub, active & (e < totals[8]),
                                          inv_factor, tap)
            total += value
            sums = tuple(sums[q] + terms[q] for q in range(n_cand))
            squares = tuple(squares[q] + terms[q] * terms[q] for q in range(n_cand))
            e += 1
        if tap is not None:
            self.ctx.moments.add_cross(film_pos, sums, squares, active)
        return sub.beta * total * norm
