"""Per-pixel connections and merging of the light vertex cache (issue 22: the most efficient
candidate "globally for n_L and, per pixel (filtered), for c and merging"; Grittmann, Yazici,
Georgiev and Slusallek, "Efficiency-aware multiple importance sampling for bidirectional
rendering algorithms", SIGGRAPH 2022, section 5).

A render with ``PixelCounts`` traces n_L light subpaths a pass as the cache does (light_cache.py),
and each camera vertex in crop pixel p draws c(p) cached vertices (0 where connections do not pay
there) and merges there only where merge(p). The MIS counts of a path are its pixel's
[Veach 9.2.2]: n_c(p) = c(p) / (V / n_L), n_lt = n_L / n, n_m(p) = 1 or 0 (the pass's eta already
holds the cache's N). Every strategy of one path sees the same pixel (the camera subpath's; a
splat's is where it lands, the pixel of the same path), so the weights of the strategies that can
sample a path still sum to one. The light subpaths are traced before any pixel is known, so their
MIS quantities keep the counts' families apart (moments.FamilyMIS under the render's heuristic:
h(n p) = h(n) h(p), each family's terms times h of its count at the weight), and the weights dot
them with the pixel's counts: ``counts`` gives them for the lanes of the camera pass (at their
pixel) and of a splat (at the pixel it lands in).

The maps come from technique auto's pilots (auto.per_pixel_trials, auto.assign): among the
caches of one n_L, per pixel the one that keeps the image's (mean v)(mean t) least, v filtered
over the pixel's 3 x 3 neighbourhood, merges kept where they carried the pilots' image."""

import drjit as dr
import mitsuba as mi
import numpy as np


class PixelCounts:
    """The per-pixel maps of a render, one field a line (crop pixels, row-major)."""

    def __init__(self, connections, merges=None):
        self.connections = np.asarray(connections, np.uint32)   # c(p) (height x width): cached vertices drawn
        self.merges = None if merges is None else np.asarray(merges, bool)   # merge(p), or None: no merges
        if self.connections.ndim != 2 or (self.merges is not None and self.merges.shape != self.connections.shape):
            raise ValueError('pixel_counts: the maps must be images of the crop\'s size (height x width)')
        self.height, self.width = self.connections.shape
        self.c_max = int(self.connections.max()) if self.connections.size else 0
        self._c = mi.UInt32(self.connections.ravel())
        self._m = None if self.merges is None else mi.Bool(self.merges.ravel())

    @property
    def pixels(self):
        return self.connections.size

    def c_at(self, pixel, active=True):
        """c(p) of the lanes in crop pixels ``pixel`` (mi.UInt32)."""
        return dr.gather(mi.UInt32, self._c, pixel, active)

    def merge_at(self, pixel, active=True):
        """merge(p) of the lanes (True without a merge map: the technique's merge set decides)."""
        if self._m is None:
            return mi.Bool(True)
        return dr.gather(mi.Bool, self._m, pixel, active)

    def counts(self, pixel, vpp, n_lt, active=True):
        """(n_c, n_lt, n_m) of the lanes in ``pixel`` [Veach 9.2.2]: c(p) / vpp (vpp = V / n_L of
        the render's cache pilot), the pass's n_lt, 1 or 0 for the merges as merge_at says (eta
        holds N; without a merge map 1: the technique merges wherever its merge set does, and a
        technique that does not merge has no merge terms for it to scale)."""
        n_c = mi.Float(self.c_at(pixel, active)) / dr.opaque(mi.Float, max(float(vpp), 1e-3))
        n_m = mi.Float(1.0) if self._m is None else dr.select(self.merge_at(pixel, active), 1.0, 0.0)
        return n_c, n_lt, n_m

    def mean_connections(self):
        return float(np.mean(self.connections)) if self.connections.size else 0.0

    def merge_share(self):
        return 0.0 if self.merges is None else float(np.mean(self.merges))
