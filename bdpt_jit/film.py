"""The film: camera-subpath samples (s=0, s=1, connections) go into one image block with the
film's reconstruction filter and are normalised by their filter weights, as Mitsuba's
``path`` does; light-image splats (t=1) go into a second block with the filter's weights
unnormalised and no weight channel. The two are developed apart and summed.

Both must estimate the same pixel, or their MIS combination is biased. The camera image's pixel
j is path's: the samples' values weighted by f(x - c_j), over the sum of those weights, so it
estimates the integral of f(x - c_j) L(x) over the crop's film positions x against the
integral of f(x - c_j) there (near the crop's edge the filter is cut at it). A splat at x adds
its value times f(x - c_j) to pixel j, so the light image estimates the first integral; the
second is ``splat_gain``'s, by which each light-image pixel is divided (splat_coverage:
the share of the filter's mass over the crop; filter_mass: the whole). Mitsuba's ``ptracer``
normalises each splat's weights over its footprint instead: that estimates the same pixel
only for filters whose weights sum to one over the pixel grid (box, tent) and where no part of
the footprint lies beyond the crop. Its edge pixels lacked the filter's mass beyond the edge (a
uniform emitter filling the view came out 0.84 there with the Gaussian filter, 0.91 in bdpt's),
and under a Gaussian of standard deviation 0.2, whose weights sum to between 0.6 and 1.0 over
the grid, lt's pixel across the Cornell box light's edge was 2.9 times path's (the image mean
-0.55%; bdpt and lt failed the agreement test, p 1e-34).

One place holds the light image's scale (see ``splat_scale``)."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np

COVERAGE_QUADRATURE = 64        # splat positions a pixel in splat_coverage's quadrature


def _row(rfilter, n):
    """Per pixel of a row of ``n`` pixels (one pixel high), what splats of total mass 1 per pixel
    spread uniformly along the row bring it through Mitsuba's own ImageBlock, unnormalised (a
    midpoint quadrature): the integral of its filter's weight over the row times the weight
    f(0) of the row's own centre in y."""
    block = mi.ImageBlock(mi.ScalarVector2u(n, 1), mi.ScalarPoint2i(0, 0), 1, rfilter=rfilter, normalize=False)
    q = max(COVERAGE_QUADRATURE, math.ceil(COVERAGE_QUADRATURE / 2 / rfilter.radius()))   # (narrow filters: finer)
    k = dr.arange(mi.Float, n * q)
    pos = mi.Point2f((k + 0.5) / q, 0.5)
    block.put(pos, [dr.full(mi.Float, 1.0 / q, n * q)])
    return np.array(block.tensor(), dtype=np.float64).reshape(n)


def _full_row(rfilter):
    """(a row long enough that its middle pixel's footprint lies inside, that pixel's index)."""
    m = 2 * math.ceil(rfilter.radius()) + 3
    return m, m // 2


def splat_coverage(rfilter, length: int):
    """Per pixel of a row of ``length`` pixels, the share of its filter's weight that lies over
    the row (1 away from the ends): the integral of f(x - c_j) over the row's positions against
    the one over the whole line. The filters are separable, so a crop's share is the product of
    its row's and its column's."""
    m, mid = _full_row(rfilter)
    return _row(rfilter, length) / _row(rfilter, m)[mid]


def filter_mass(rfilter):
    """The integral of the filter's weight over the plane, as Mitsuba's ImageBlock weighs
    (separable: the square of the line's)."""
    m, mid = _full_row(rfilter)
    centre = mi.ImageBlock(mi.ScalarVector2u(1, 1), mi.ScalarPoint2i(0, 0), 1, rfilter=rfilter, normalize=False)
    centre.put(mi.Point2f(0.5, 0.5), [mi.Float(1.0)])
    f0 = math.sqrt(float(np.array(centre.tensor()).ravel()[0]))      # f(0) x f(0)
    return (_row(rfilter, m)[mid] / f0) ** 2


_GAINS = {}                     # (variant, filter, width, height) -> splat_gain's array


def _gain(rfilter, width, height):
    key = (mi.variant(), str(rfilter), width, height)
    if key not in _GAINS:
        cov = np.outer(splat_coverage(rfilter, height), splat_coverage(rfilter, width)) * filter_mass(rfilter)
        gain = np.where(cov > 1e-6, 1.0 / np.maximum(cov, 1e-6), 1.0)
        _GAINS[key] = gain.astype(np.float32).reshape(height, width, 1)
    return mi.TensorXf(_GAINS[key])


def splat_gain(film: mi.Film):
    """The light image's per-pixel factor (H x W x 1) that makes its pixels the camera image's
    (module docstring); None for ``box``, whose weight is 1 over a pixel and 0 beyond. Every
    other filter needs it, however narrow: a Gaussian of standard deviation 0.1 (radius 0.4)
    weighs a splat by at most 1 and 0.063 on average over its pixel (lt 94% dark without it)."""
    rfilter = film.rfilter()
    if str(rfilter.class_name()) == 'BoxFilter':
        return None
    w, h = (int(v) for v in film.crop_size())
    return _gain(rfilter, w, h)


class FilmAccumulator:
    """Channels of both blocks, in Mitsuba's order: colour (3), alpha if the film has it, the
    filter weight, then the AOVs (parameter ``aovs``: camera samples only). A film with
    Mitsuba's ``Special`` flag (``specfilm``) has its own: one channel a band, then the weight."""

    def __init__(self, film: mi.Film, aov_names=()):
        self.film = film
        self.aov_names = list(aov_names)
        film.prepare(self.aov_names)
        self.cam = film.create_block()
        self.lt = film.create_block(normalize=False)
        self.lt.set_coalesce(False)
        self.n_channels = self.cam.channel_count()
        self.n_aov = len(self.aov_names)
        # a film of its own layout (specfilm: one channel a spectral band, then the weight) converts
        # each sample with prepare_sample, as Mitsuba's integrators do; no alpha, no AOVs (spectral)
        self.special = bool(film.flags() & mi.FilmFlags.Special)
        self.has_alpha = not self.special and self.n_channels - self.n_aov == 5
        self.n_colour = self.n_channels - self.n_aov - 1 - int(self.has_alpha) if self.special else 3
        self.weight_index = self.n_colour + int(self.has_alpha)
        self.aov_start = self.weight_index + 1
        self.crop_offset = mi.ScalarPoint2f(film.crop_offset())
        self.gain = splat_gain(film)

    def light_image(self, channels):
        """The light image's first ``channels`` channels, edge pixels by ``splat_gain``."""
        lt = self.lt.tensor()[:, :, 0:channels]
        return lt if self.gain is None else lt * self.gain

    @staticmethod
    def splat_scale(spp: int):
        """Light paths are traced one per camera sample (spp per pixel of the crop), and the
        sensor's importance is normalised over the crop: each splat carries 1/spp."""
        return 1.0 / spp

    def put_camera(self, pos, value, alpha, active, wavelengths, aov_values=()):
        """A camera sample (weight 1 in the filter's normalisation). ``value``: a spectrum at
        ``wavelengths`` (spectral variants: converted by the block, as Mitsuba's path does);
        ``aov_values``: one Float per AOV channel (RGB and monochrome variants)."""
        if self.special:
            self.cam.put(pos, self.film.prepare_sample(value, wavelengths, self.n_channels, 1.0, alpha, active),
                         active)
            return
        if not self.n_aov:
            self.cam.put(pos, wavelengths, value, alpha, 1.0, active)
            return
        self.cam.put(pos, self._channels(value, alpha, list(aov_values), 1.0), active)

    def put_splat(self, uv_in_crop, value, active, wavelengths):
        """A light-image splat: no alpha, no weight; the filter's weights unnormalised (module docstring)."""
        pos = uv_in_crop + self.crop_offset
        if self.special:
            self.lt.put(pos, self.film.prepare_sample(value, wavelengths, self.n_channels, 0.0, 0.0, active),
                        active)
            return
        if not self.n_aov:
            self.lt.put(pos, wavelengths, value, 0.0, 0.0, active)
            return
        zeros = dr.zeros(mi.Float, dr.width(value))
        self.lt.put(pos, self._channels(value, zeros, [zeros] * self.n_aov, zeros), active)

    def _channels(self, value, alpha, aovs, weight):
        """The block's channel list (colour: a monochrome value in all three, as the block's
        spectral put does)."""
        n = dr.width(value)
        colour = [value[i if dr.size_v(value) == 3 else 0] for i in range(3)]
        out = colour + ([alpha] if self.has_alpha else []) + [weight] + aovs
        return [x if dr.width(x) == n and not isinstance(x, float) else mi.Float(x) + dr.zeros(mi.Float, n)
                for x in out]

    def develop(self, light_scale=1.0) -> mi.TensorXf:
        """Sum of the normalised camera image and the light image, handed to the film so that
        ``film.bitmap()`` and ``mi.render`` both see it. Returns the developed tensor."""
        cam = self.cam.tensor()
        wi = self.weight_index
        w = cam[:, :, wi:wi + 1]
        inv_w = dr.select(w > 0, 1.0 / dr.select(w > 0, w, 1.0), 0.0)
        nc = self.n_colour
        rgb = cam[:, :, 0:nc] * inv_w + self.light_image(nc) * light_scale
        parts = [rgb]
        if self.has_alpha:
            parts.append(cam[:, :, 3:4] * inv_w)
        parts.append(dr.ones(mi.TensorXf, shape=(rgb.shape[0], rgb.shape[1], 1)))
        if self.n_aov:
            parts.append(cam[:, :, self.aov_start:self.aov_start + self.n_aov] * inv_w)
        total = dr.concat(parts, axis=2)
        block = mi.ImageBlock(total, offset=self.film.crop_offset(), rfilter=None)
        self.film.clear()
        self.film.put_block(block)
        return self.film.develop()


    def pass_image(self, camera_share):
        """A differentiable image of one pass, in the layout ``film.develop()`` gives (rgb, and
        alpha if the film has it): the pass's camera image normalised by its own filter weights
        times ``camera_share`` (its share of the render's samples), plus its light image (already
        scaled by the render's 1/spp). Summed over the passes this is the developed image; with
        a box filter exactly (every sample weighs 1 in its pixel), with another filter up to the
        spread of the passes' weight sums."""
        cam = self.cam.tensor()
        wi = self.weight_index
        w = dr.detach(cam[:, :, wi:wi + 1])
        inv_w = dr.select(w > 0, camera_share / dr.select(w > 0, w, 1.0), 0.0)
        n = self.n_colour if self.special else 1 if mi.is_monochromatic else 3   # film.develop's colour channels
        parts = [cam[:, :, 0:n] * inv_w + self.light_image(n)]
        if self.has_alpha:
            parts.append(dr.detach(cam[:, :, 3:4]) * inv_w)
        if self.n_aov:
            parts.append(dr.detach(cam[:, :, self.aov_start:self.aov_start + self.n_aov]) * inv_w)
        return dr.concat(parts, axis=2) if len(parts) > 1 else parts[0]


class NearestPixel:
    """The crop pixel that contains a film position (no reconstruction filter)."""

    def __init__(self, film: mi.Film):
        self.w, self.h = (int(v) for v in film.crop_size())
        self.count = self.w * self.h
        self.crop_offset = mi.ScalarPoint2f(film.crop_offset())

    def index(self, film_pos, active):
        """(the pixel's index in the crop, row-major; whether the position is inside and active)."""
        p = mi.Point2i(dr.floor(film_pos - self.crop_offset))
        inside = active & (p.x >= 0) & (p.y >= 0) & (p.x < self.w) & (p.y < self.h)
        pixel = mi.UInt32(dr.clip(p.y, 0, self.h - 1) * self.w + dr.clip(p.x, 0, self.w - 1))
        return pixel, inside


def layer_index(s, t, max_length):
    """The layer of strategy (s, t) (UInt32s) in StrategyLayers' order: by path length
    s + t - 1 up to ``max_length``, then s; longer paths share the last ('other')."""
    k = s + t - 1
    return dr.select(k <= max_length, (k - 1) * (k + 2) // 2 + s, max_length * (max_length + 3) // 2)


class StrategyLayers:
    """One image per (s,t) strategy, weighted (as it enters the render) and unweighted (its
    estimate alone), like pbrt's visualizestrategies and Mitsuba 0.6's debug images.
    Contributions are added to the pixel that contains them (nearest pixel), camera samples
    scaled by 1/spp and splats by their usual scale, so with a box filter the weighted layers
    sum to the rendered image. Paths of more than ``max_length`` edges go to ``other``."""

    def __init__(self, film: mi.Film, max_length: int):
        self.max_length = max(int(max_length), 1)
        self.w, self.h = (int(v) for v in film.crop_size())
        self.names = []
        for k in range(1, self.max_length + 1):
            for s in range(0, k + 1):
                self.names.append(f's{s}_t{k + 1 - s}')
        self.names.append('other')
        self.buf = dr.zeros(mi.Float, len(self.names) * 2 * self.w * self.h * 3)
        self.pixels = NearestPixel(film)

    def layer_index(self, s, t):
        return layer_index(s, t, self.max_length)

    def add(self, s, t, film_pos, weighted, unweighted, active):
        s, t = mi.UInt32(s), mi.UInt32(t)
        pixel, inside = self.pixels.index(film_pos, active)
        base = (self.layer_index(s, t) * 2 * self.w * self.h + pixel) * 3
        for kind, value in ((0, weighted), (1, unweighted)):
            off = base + kind * self.w * self.h * 3
            for c in range(3):
                dr.scatter_reduce(dr.ReduceOp.Add, self.buf, value[c], off + c, inside)

    def images(self, scale=1.0):
        """The layers as numpy arrays; ``scale`` as the render's (an interrupted render traced
        fewer samples than its 1/spp factors assume; passes cover whole images then)."""
        import numpy as np
        a = np.array(self.buf).reshape(len(self.names), 2, self.h, self.w, 3) * scale
        return {name: {'weighted': a[i, 0], 'unweighted': a[i, 1]} for i, name in enumerate(self.names)}
