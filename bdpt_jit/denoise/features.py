"""The feature pass: the denoiser's albedo and normal images, traced from the camera.

Camera rays are generated as ``bdpt``'s camera pass generates them (a uniform point in the crop
pixel, ``sensor.sample_ray`` at the shutter-open time with the crop-relative film position, a
wavelength sample in spectral variants) and accumulated with the film's reconstruction filter
into an image block of their own, normalised by the filter weights: the features are averaged
over each pixel's samples as the image is. Each ray follows delta (specular) surfaces, mirrors,
glass and null interfaces, until it reaches a surface with a smooth (non-delta) lobe, leaves the
scene or passes ``max_depth`` vertices: that vertex's diffuse reflectance (as Mitsuba's ``aov``
integrator computes its ``albedo``; spectral variants: under D65) and shading normal (world space) are the features, as
Intel Open Image Denoise's documentation asks for surfaces seen through mirrors and glass.

At a delta vertex the ray takes the transmitted direction where the BSDF has one (so a surface
behind glass gives the albedo, not the few percent the glass reflects) and the reflected one
otherwise (mirrors, total internal reflection); the delta vertices' own colours are not
multiplied in. A ray that leaves the scene records the environment's radiance clamped to [0, 1]
as albedo (0 without an environment) and a zero normal; one that is still on delta surfaces
after ``max_depth`` vertices records albedo 1 and the normal there.

This is a pass of its own, not a by-product of ``bdpt``'s camera subpaths, so that it works
with every integrator the command renders with (Mitsuba's too), costs a few rays per sample,
and leaves the render's kernels as they are."""

import drjit as dr
import mitsuba as mi
import numpy as np

from ..rays import RayOffsets, spawn
from ..jit_guard import held

MAX_LANES = 1 << 22             # samples traced per kernel launch (memory: ~100 bytes a lane)
DEFAULT_MAX_DEPTH = 16          # delta vertices followed before giving up
SEED_SALT = 0x5EEDF00D          # the feature pass's seeds differ from the render's


@held
def feature_images(scene, sensor=0, spp=16, seed=0, max_depth=DEFAULT_MAX_DEPTH):
    """(albedo, normal) of the sensor's crop as float32 arrays: albedo (H, W, 3), or (H, W, 1)
    in a monochrome variant, in [0, 1]; normal (H, W, 3), world space, the average of the
    samples' unit normals (not renormalised), 0 where the rays leave the scene. ``spp``
    samples per pixel, in passes of at most MAX_LANES samples."""
    if isinstance(sensor, int):
        sensor = scene.sensors()[sensor]
    film = sensor.film()
    w, h = (int(v) for v in film.crop_size())
    n_albedo = 1 if mi.is_monochromatic else 3
    block = mi.ImageBlock(film.crop_size(), mi.ScalarPoint2i(film.crop_offset()), n_albedo + 4,
                          rfilter=film.rfilter())
    spp = max(int(spp), 1)
    spp_pass = max(1, min(spp, MAX_LANES // max(w * h, 1)))
    done, i = 0, 0
    while done < spp:
        k = min(spp_pass, spp - done)
        _trace_pass(scene, sensor, block, k, (seed * 1000003 + i * 7919 + SEED_SALT) % 2 ** 32,
                    max(int(max_depth), 1))
        dr.eval(block.tensor())
        done, i = done + k, i + 1
    t = np.array(block.tensor(), dtype=np.float64)
    wsum = t[:, :, -1:]
    avg = np.where(wsum > 0, t[:, :, :-1] / np.where(wsum > 0, wsum, 1.0), 0.0)
    avg = np.nan_to_num(avg, nan=0.0, posinf=0.0, neginf=0.0)
    albedo = np.clip(avg[:, :, :n_albedo], 0.0, 1.0).astype(np.float32)
    normal = np.clip(avg[:, :, n_albedo:n_albedo + 3], -1.0, 1.0).astype(np.float32)
    return albedo, normal


def _camera_rays(sensor, sampler, n, spp):
    """Film positions (crop offset included) and rays of n samples, spp per crop pixel."""
    film = sensor.film()
    crop = mi.ScalarVector2f(film.crop_size())
    idx = dr.arange(mi.UInt32, n)
    pixel = idx // dr.opaque(mi.UInt32, spp)
    crop_w = int(film.crop_size()[0])
    pos = mi.Point2f(mi.Float(pixel % crop_w), mi.Float(pixel // crop_w)) + sampler.next_2d()
    u_wl = sampler.next_1d()
    ray, _ = sensor.sample_ray_differential(sensor.shutter_open(), u_wl, pos / crop, sampler.next_2d())
    return pos + mi.ScalarVector2f(film.crop_offset()), mi.Ray3f(ray)


def _to_colour(value, wavelengths, active, reflectance=True):
    """A BSDF's reflectance (or an emitter's radiance) as the film's colour: RGB (3 Floats) or
    mono (1). Spectral variants: divided by the sensor's wavelength density, as the ``aov``
    integrator converts an albedo, and a reflectance lit by D65 (the white of Mitsuba's RGB
    emitters), whose sRGB is (1, 1, 1): so that an sRGB reflectance comes back as itself."""
    if mi.is_monochromatic:
        return [value[0]]
    if mi.is_spectral:
        pdf = mi.pdf_rgb_spectrum(wavelengths)
        value = value * dr.select(pdf != 0, dr.rcp(pdf), 0.0)
        if reflectance:
            value = value * mi.Spectrum([mi.cie_d65(wavelengths[i]) for i in range(dr.size_v(mi.Spectrum))])
        rgb = mi.spectrum_to_srgb(mi.UnpolarizedSpectrum(value), wavelengths, active)
        return [rgb[0], rgb[1], rgb[2]]
    return [value[0], value[1], value[2]]


def _follow_delta(bsdf, si, sampler, active):
    """The next direction at a delta vertex (world space): transmitted if the BSDF transmits
    there, else reflected. Returns (direction, valid)."""
    ctx_t = mi.BSDFContext()
    ctx_t.type_mask = mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.Null
    u1, u2 = sampler.next_1d(), sampler.next_2d()
    bs_t, w_t = bsdf.sample(ctx_t, si, u1, u2, active)
    ok_t = active & (bs_t.pdf > 0) & (dr.max(mi.UnpolarizedSpectrum(w_t)) > 0)
    bs_r, w_r = bsdf.sample(mi.BSDFContext(), si, u1, u2, active & ~ok_t)
    ok_r = active & ~ok_t & (bs_r.pdf > 0) & (dr.max(mi.UnpolarizedSpectrum(w_r)) > 0)
    wo = dr.select(ok_t, bs_t.wo, bs_r.wo)
    return si.to_world(wo), ok_t | ok_r


@dr.syntax
def _walk(scene, sampler, ray, max_depth, n_albedo):
    """Follow delta vertices; returns (albedo Floats, normal Vector3f) of each sample. Rays leave
    their surfaces as every other ray of bdpt_jit does (rays.RayOffsets, rays.spawn)."""
    tracing = (scene, RayOffsets(scene))
    n = dr.width(ray.o)
    albedo = [dr.zeros(mi.Float, n) for _ in range(n_albedo)]
    normal = dr.zeros(mi.Vector3f, n)
    active = dr.full(mi.Bool, True, n)
    depth = mi.UInt32(0)
    while dr.hint(active, label='bdpt_feature_pass'):
        ray, active, albedo, normal = _step(tracing, sampler, ray, active, depth, max_depth, albedo, normal)
        depth += 1
    return albedo, normal


def _step(tracing, sampler, ray, active, depth, max_depth, albedo, normal):
    """One vertex of the walk: record the features where it stops, else the next ray
    (``tracing``: the scene and its rays.RayOffsets)."""
    scene, offsets = tracing
    si = offsets.intersect(scene, ray, active)
    hit = active & si.is_valid()
    bsdf = si.bsdf(ray)
    flags = bsdf.flags()
    delta = hit & ~mi.has_flag(flags, mi.BSDFFlags.Smooth) & \
        (mi.has_flag(flags, mi.BSDFFlags.Delta) | mi.has_flag(flags, mi.BSDFFlags.Null))
    stop = hit & ~delta
    value = _to_colour(bsdf.eval_diffuse_reflectance(si, stop), ray.wavelengths, stop)
    miss = active & ~si.is_valid()
    env = scene.environment()
    if env is not None:
        si_env = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray.o))
        si_env.wi, si_env.wavelengths, si_env.time = -ray.d, ray.wavelengths, ray.time
        sky = _to_colour(mi.UnpolarizedSpectrum(env.eval(si_env, miss)), ray.wavelengths, miss, False)
        value = [dr.select(miss, s, v) for s, v in zip(sky, value)]
    d, ok = _follow_delta(bsdf, si, sampler, delta & (depth + 1 < max_depth))
    give_up = delta & ~ok
    value = [dr.select(give_up, 1.0, v) for v in value]
    record = stop | miss | give_up
    albedo = [dr.select(record, v, a) for v, a in zip(value, albedo)]
    normal = dr.select(stop | give_up, si.sh_frame.n, normal)
    return spawn(si.p, si.n, offsets.error(si.p, si.shape), d, si.time, ray.wavelengths), delta & ok, albedo, normal


def _trace_pass(scene, sensor, block, spp, seed, max_depth):
    """One pass of spp samples per crop pixel, put into ``block`` (albedo, normal, weight 1)."""
    film = sensor.film()
    n = int(film.crop_size()[0]) * int(film.crop_size()[1]) * spp
    sampler = mi.load_dict({'type': 'independent', 'sample_count': spp})
    sampler.seed(seed, n)
    pos, ray = _camera_rays(sensor, sampler, n, spp)
    n_albedo = 1 if mi.is_monochromatic else 3
    albedo, normal = _walk(scene, sampler, ray, mi.UInt32(max_depth), n_albedo)
    values = [*albedo, normal.x, normal.y, normal.z, dr.ones(mi.Float, n)]
    values = [dr.select(dr.isfinite(v), v, 0.0) for v in values]
    block.put(pos, values, dr.full(mi.Bool, True, n))
