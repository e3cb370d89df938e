"""Vertex merging (techniques ``vcm`` and ``vm``): the light vertices of every light subpath of a
pass in a hashed uniform grid, and the density estimate at a camera vertex.

Merging a camera vertex z with a light vertex y closer than r estimates the radiance z sends
towards the camera from the light that reached y (Georgiev et al. 2012, Hachisuka et al. 2008):

    L(z) ~ 1 / (pi r^2 N) * sum_y  f_z(y's incoming direction) * beta_y * w_merge

over the light vertices y of the pass's N light subpaths within r of z (a constant kernel over
the disc of radius r), where beta_y is the light subpath's throughput up to y (per unit area at
y: no cosine at y) and f_z the camera vertex's BSDF. Mitsuba's ``eval`` gives f |cos_s|; the
estimate needs f |cos_s| / |cos_g|: the light's flux per unit area of the surface (beta_y) is
measured with the geometric normal. The estimate is biased (the light is blurred over the disc)
and consistent: the radius shrinks with the passes (integrator.py, parameter ``radius_alpha``).

The grid is built with Dr.Jit alone, by a counting sort: each stored vertex hashes its cell
(cell size 2r), the cells' counts are atomic increments, a prefix sum gives each cell its start,
and a second atomic increment gives each vertex its place. A query visits the 2 x 2 x 2 cells
nearest to z (they cover the disc of radius r around it), skipping a bucket that two of them hash
to (it would count its vertices twice), in one flattened loop over cells and entries."""

import drjit as dr
import mitsuba as mi

from .connect import eval_camera_vertex
from .jitmath import safe_div

_PRIMES = (73856093, 19349663, 83492791)    # spatial hash (Teschner et al. 2003)


def merge_radius(scene, radius_rel, alpha, iteration):
    """r_i = r_1 i^((alpha-1)/2) for pass ``iteration`` (from 1), r_1 = ``radius_rel`` times the
    radius of the scene's bounding sphere (Knaus and Zwicker 2011; as SmallVCM)."""
    bbox = scene.bbox()
    scene_radius = float(dr.norm(bbox.max - bbox.min)) * 0.5 if bbox.valid() else 1.0
    if not scene_radius > 0:
        scene_radius = 1.0
    return radius_rel * scene_radius * float(iteration) ** (0.5 * (alpha - 1.0))


class PhotonGrid:
    """The light vertices of one pass (store.LightStore), sorted by hashed cell.

    radius, radius2, inv_cell   the merging radius, its square, 1 / (2 r) (opaque)
    origin                      the scene's bounding-box minimum (cell coordinates from there)
    mask                        table size - 1 (a power of two), opaque
    start, counts               per bucket: first entry and number of entries
    slots                       the store's slots in bucket order
    norm                        1 / (pi r^2 N): the estimate's normalisation (opaque)"""

    def __init__(self, scene, store, radius):
        n_slots = store.n * store.capacity
        size = 1               # buckets: twice the slots, so that empty cells rarely share one
        while size < max(2 * n_slots, 1):
            size *= 2
        bbox = scene.bbox()
        self.origin = mi.Point3f(bbox.min) if bbox.valid() else mi.Point3f(0.0)
        self.radius = dr.opaque(mi.Float, radius)
        self.radius2 = dr.opaque(mi.Float, radius * radius)
        self.inv_cell = dr.opaque(mi.Float, 0.5 / radius)
        self.mask = dr.opaque(mi.UInt32, size - 1)
        self.norm = dr.opaque(mi.Float, 1.0 / (dr.pi * radius * radius * store.n))
        self.store = store

        slot = dr.arange(mi.UInt32, n_slots)
        level = slot // store.n_opaque
        valid = level < dr.gather(mi.UInt32, store.count, slot - level * store.n_opaque)
        first = dr.gather(mi.Vector4f, store.v, slot * store.record.packets(), valid)  # 'p' leads every record
        bucket = self.bucket(self.cell(mi.Point3f(first.x, first.y, first.z)))
        dr.eval(bucket, valid)
        self.counts = dr.zeros(mi.UInt32, size)
        place = dr.scatter_inc(self.counts, bucket, valid)           # place within the bucket
        dr.eval(place)                                                # (a result read once only)
        self.start = dr.prefix_sum(self.counts)                      # exclusive
        self.slots = dr.zeros(mi.UInt32, max(n_slots, 1))
        dr.scatter(self.slots, slot, dr.gather(mi.UInt32, self.start, bucket, valid) + place, valid)
        dr.eval(self.counts, self.start, self.slots)

    def cell(self, p):
        return mi.Vector3i(dr.floor((p - self.origin) * self.inv_cell))

    def bucket(self, c):
        u = [dr.reinterpret_array(mi.UInt32, c[i]) * _PRIMES[i] for i in range(3)]
        return (u[0] ^ u[1] ^ u[2]) & self.mask

    def neighbourhood(self, p):
        """The buckets of the 2 x 2 x 2 cells around ``p`` (a list of 8) and, for each, whether
        an earlier one of the 8 is the same bucket."""
        x = (p - self.origin) * self.inv_cell
        c0 = mi.Vector3i(dr.floor(x))
        step = mi.Vector3i(dr.select(x - dr.floor(x) < 0.5, -1, 1))
        buckets, dup = [], []
        for q in range(8):
            c = c0 + mi.Vector3i(step.x * (q & 1), step.y * ((q >> 1) & 1), step.z * ((q >> 2) & 1))
            b = self.bucket(c)
            d = mi.Bool(False)
            for e in buckets:
                d |= e == b
            buckets.append(b)
            dup.append(d)
        return buckets, dup


class Merger:
    """The merging estimate at camera vertices, for the CameraTracer (owned per pass)."""

    def __init__(self, ctx, grid):
        self.ctx = ctx
        self.grid = grid

    @staticmethod
    def _pick(values, q):
        out = values[0]
        for j in range(1, len(values)):
            out = dr.select(q == j, values[j], out)
        return out

    def _range(self, buckets, dup, q):
        g = self.grid
        b = self._pick(buckets, q)
        start = dr.gather(mi.UInt32, g.start, b, q < 8)
        count = dr.select(self._pick(dup, q) | (q >= 8), 0, dr.gather(mi.UInt32, g.counts, b, q < 8))
        return start, start + count

    def merge_one(self, k, si, bsdf, depth, d_vcm, d_vm, active):
        """Entry ``k`` of the sorted grid merged with camera vertex ``si`` (unnormalised)."""
        c, g = self.ctx, self.grid
        slot = dr.gather(mi.UInt32, g.slots, k, active)
        record = g.store.record
        # the position first ('p' leads every record): ~4/5 of the candidates in the 8 cells lie
        # outside the radius, and their masked-off lanes then read nothing more
        first = dr.gather(mi.Vector4f, g.store.v, slot * record.packets(), active)
        ok = active & (dr.squared_norm(mi.Point3f(first.x, first.y, first.z) - si.p) <= g.radius2)
        v = record.load(g.store.v, slot, ok)
        level = slot // g.store.n_opaque
        ok &= v.depth_at(level) + depth <= c.max_depth_edges
        y = v.interaction(c.time, si.wavelengths)
        wl = y.to_world(y.wi)                       # towards the light subpath's previous vertex
        f, pdf_dir_w, pdf_rev_w = eval_camera_vertex(si, bsdf, wl, ok, c.diffuse)
        value = f * v.beta * safe_div(1.0, dr.abs(dr.dot(si.n, wl)))
        ok &= (dr.max(value) > 0) & (dr.max(value) < dr.inf)
        l_vm = v.d_vm if 'd_vm' in record.DRJIT_STRUCT else 0.0
        w = c.mis.weight_merge(v.d_vcm, l_vm, d_vcm, d_vm, pdf_dir_w, pdf_rev_w)
        return dr.select(ok, value * w, 0.0)

    @dr.syntax
    def gather(self, si, bsdf, depth, beta, d_vcm, d_vm, active):
        """Radiance towards the camera subpath from merging at ``si``: the estimate over the
        light vertices within the radius, times the camera throughput ``beta``."""
        buckets, dup = self.grid.neighbourhood(si.p)
        q = dr.zeros(mi.UInt32, dr.width(si.p))
        k, end = self._range(buckets, dup, q)
        total = mi.Spectrum(0.0)
        while dr.hint(active & (q < 8), label='bdpt_merge'):
            entry = k < end
            total += self.merge_one(k, si, bsdf, depth, d_vcm, d_vm, entry)
            k[entry] += 1
            q[~entry] += 1
            k_next, end_next = self._range(buckets, dup, q)
            k = dr.select(entry, k, k_next)
            end = dr.select(entry, end, end_next)
        return beta * total * self.grid.norm
