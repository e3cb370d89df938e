"""Ray counts of Mitsuba's `path` and `ptracer`, for the comparison tables.

Mitsuba's JIT variants count no rays, so this module replays the random walks of its C++
integrators (Mitsuba 3.9.1, `src/integrators/path.cpp` and `ptracer.cpp`) as wavefronts in
Python and counts the rays they trace, with the categories `bdpt`'s ``statistics`` uses
(`bdpt_jit/stats.py`): camera/light rays and those that leave the scene, shadow rays and those
that are blocked. The replay makes the same decisions as the C++ code from the same kinds of
samples (BSDF sampling, emitter sampling, Russian roulette on throughput x eta^2 with the same
thresholds, the same termination tests), but it accumulates no radiance, so its counts are
statistically, not sample-for-sample, those of the C++ renders.

    rays = count_path(scene, max_depth, spp, seed)      # dict like bdpt's last_render_info['rays']
"""

import drjit as dr
import mitsuba as mi

RR_DEPTH = 5    # the default of both Mitsuba integrators, and of bdpt


def _n(mask):
    return int(dr.count(mask)[0])


class _Counts:
    def __init__(self):
        self.t = {k: 0 for k in ('camera_rays', 'camera_rays_missed', 'light_rays', 'light_rays_missed',
                                 'shadow_rays', 'shadow_rays_blocked')}

    def ray(self, kind, active, hit):
        self.t[f'{kind}_rays'] += _n(active)
        self.t[f'{kind}_rays_missed'] += _n(active & ~hit)

    def shadow(self, active, blocked):
        self.t['shadow_rays'] += _n(active)
        self.t['shadow_rays_blocked'] += _n(active & blocked)

    def summary(self, samples):
        t = dict(self.t)
        t['rays'] = t['camera_rays'] + t['light_rays'] + t['shadow_rays']
        t['zero_contribution_rays'] = t['camera_rays_missed'] + t['light_rays_missed'] + t['shadow_rays_blocked']
        t['samples'] = samples
        return t


def _sampler(sensor, spp, seed, n):
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n)
    return sampler


def count_path(scene, max_depth, spp, seed=0, rr_depth=RR_DEPTH):
    """Rays of Mitsuba's `path` (megakernel logic of path.cpp, one wavefront per bounce)."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    n = w * h * spp
    sampler = _sampler(sensor, spp, seed, n)
    c = _Counts()
    idx = dr.arange(mi.UInt32, n) // spp
    pos = mi.Vector2f(mi.Float(idx % w), mi.Float(idx // w)) + sampler.next_2d()
    ray, _ = sensor.sample_ray(0.0, sampler.next_1d(), pos / mi.Vector2f(w, h), sampler.next_2d())
    active = dr.full(mi.Bool, max_depth != 0, n)
    si = scene.ray_intersect(ray, active)
    c.ray('camera', active, si.is_valid())
    throughput, eta, depth = mi.Spectrum(1.0), mi.Float(1.0), mi.UInt32(0)
    ctx = mi.BSDFContext()
    while True:
        dr.eval(si, ray, throughput, eta, depth, active)
        if _n(active) == 0:
            break
        active_next = active & si.is_valid() & (mi.Bool(True) if max_depth < 0 else (depth + 1 < max_depth))
        bsdf = si.bsdf(ray)
        # emitter sampling: a shadow ray wherever the sampled emitter position has a density
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, _ = scene.sample_emitter_direction(si, sampler.next_2d(), False, active_em)
        shadow = active_em & (ds.pdf != 0.0)
        c.shadow(shadow, scene.ray_test(si.spawn_ray_to(ds.p), shadow))
        # BSDF sampling and the stopping criterion (Russian roulette from depth >= rr_depth)
        bs, weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        throughput = dr.select(active_next, throughput * weight, throughput)
        eta = dr.select(active_next, eta * bs.eta, eta)
        depth = dr.select(active & si.is_valid(), depth + 1, depth)
        t_max = dr.max(throughput)
        rr_prob = dr.minimum(t_max * dr.square(eta), 0.95)
        rr_active = depth >= rr_depth
        rr_continue = sampler.next_1d() < rr_prob
        throughput = dr.select(rr_active, throughput / rr_prob, throughput)
        active = active_next & (~rr_active | rr_continue) & (t_max != 0.0)
        ray = si.spawn_ray(si.to_world(bs.wo))
        si = scene.ray_intersect(ray, active)
        c.ray('camera', active, si.is_valid())
    return c.summary(n)


def count_ptracer(scene, max_depth, spp, seed=0, rr_depth=RR_DEPTH):
    """Rays of Mitsuba's `ptracer`: one light path per sample (spp x pixels of them), each with a
    splat of a visible emitter, an emission ray, and a connection to the camera at every vertex."""
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    n = w * h * spp
    sampler = _sampler(sensor, spp, seed, n)
    c = _Counts()
    if max_depth == 0:
        return c.summary(n)
    time = sensor.shutter_open()
    # --- emitters seen directly: a connection from a point on a (non-delta) emitter to the camera
    e_idx, _, _ = scene.sample_emitter(sampler.next_1d())
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), e_idx)
    flags = emitter.flags()
    active = ~mi.has_flag(flags, mi.EmitterFlags.Delta)
    infinite = active & mi.has_flag(flags, mi.EmitterFlags.Infinite)
    finite = active & ~infinite
    ref = dr.zeros(mi.Interaction3f)
    ref.p = sensor.world_transform().translation()
    ref.time = time
    ds, _ = emitter.sample_direction(ref, sampler.next_2d(), infinite)
    ps, _ = emitter.sample_position(time, sampler.next_2d(), finite)
    si = dr.select(infinite, mi.SurfaceInteraction3f(ds, mi.Color0f()), mi.SurfaceInteraction3f(ps, mi.Color0f()))
    sds, _ = sensor.sample_direction(si, sampler.next_2d(), active)
    shadow = active & (sds.pdf > 0.0)
    c.shadow(shadow, scene.ray_test(si.spawn_ray_to(sds.p), shadow))
    # --- emission ray and the walk
    ray, weight, _ = scene.sample_emitter_ray(mi.Float(time), sampler.next_1d(), sampler.next_2d(), sampler.next_2d(),
                                              mi.Bool(True))
    throughput = mi.Spectrum(weight)
    active = dr.max(throughput) != 0.0
    si = scene.ray_intersect(ray, active)
    c.ray('light', active, si.is_valid())
    depth = mi.Int32(1)
    active &= si.is_valid()
    if max_depth >= 0:
        active &= depth < max_depth
    eta = mi.Float(1.0)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    while True:
        dr.eval(si, ray, throughput, eta, depth, active)
        if _n(active) == 0:
            break
        bsdf = si.bsdf(ray)
        sds, s_weight = sensor.sample_direction(si, sampler.next_2d(), active)
        shadow = active & (sds.pdf > 0.0) & dr.any(throughput * s_weight != 0.0)
        c.shadow(shadow, scene.ray_test(si.spawn_ray_to(sds.p), shadow))
        bs, bsdf_val = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active)
        wi_dot_n = dr.dot(si.n, -ray.d)
        wo_world = si.to_world(bs.wo)
        wo_dot_n = dr.dot(si.n, wo_world)
        active &= (wi_dot_n * mi.Frame3f.cos_theta(si.wi) > 0.0) & (wo_dot_n * mi.Frame3f.cos_theta(bs.wo) > 0.0)
        correction = dr.abs((mi.Frame3f.cos_theta(si.wi) * wo_dot_n) / (mi.Frame3f.cos_theta(bs.wo) * wi_dot_n))
        throughput = dr.select(active, throughput * bsdf_val * correction, throughput)
        eta = dr.select(active, eta * bs.eta, eta)
        active &= dr.any(throughput != 0.0)
        depth = dr.select(active, depth + 1, depth)
        if max_depth >= 0:
            active &= depth < max_depth
        use_rr = depth > rr_depth
        q = dr.minimum(dr.max(throughput) * dr.square(eta), 0.95)
        active &= ~use_rr | (sampler.next_1d() < q)
        throughput = dr.select(use_rr, throughput / q, throughput)
        ray = si.spawn_ray(wo_world)
        si = scene.ray_intersect(ray, active)
        c.ray('light', active, si.is_valid())
        active &= si.is_valid()
    return c.summary(n)


def count(name, scene, max_depth, spp, seed=0):
    if name == 'path':
        return count_path(scene, max_depth, spp, seed)
    if name == 'ptracer':
        return count_ptracer(scene, max_depth, spp, seed)
    raise ValueError(f"raycount: no replica of Mitsuba integrator '{name}' (have: path, ptracer)")
