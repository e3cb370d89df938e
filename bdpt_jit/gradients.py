"""Differentiable rendering: the derivative of a bdpt image with respect to scene parameters
(BSDF and emitter parameters), in forward and reverse mode, pass by pass.

Detached sampling, as Mitsuba's ``prb``: every direction, position and density is sampled
and computed without derivatives; the values that multiply a path's throughput (BSDF values,
emitted radiance) are evaluated again with derivatives, and their gradient replaces that of
the sampled weight: for a smooth BSDF sample the weight f cos / p becomes, for derivatives,
f_ad cos / detach(p). The MIS weights are detached (mis.MIS with ``detached``): any fixed
weights that sum to one over the strategies leave every strategy's estimator unbiased, so the
sum of the weighted derivative estimators is an unbiased estimator of the derivative of the
image, for every parameter on which neither the sampled points nor the visibility depend:
reflectances, roughnesses, specular reflectances and transmittances, emitted radiance and
intensity, environment texels. Not handled: parameters that move geometry (shape vertices and
transforms: visibility silhouettes and the change of the sampled points with the parameter)
and parameters on which a delta lobe's direction depends (the index of refraction of a smooth
dielectric): they are refused (``check_parameters``).

The primal image is never changed: ``dr.replace_grad`` keeps every primal value and only
exchanges gradients.
"""

import drjit as dr
import mitsuba as mi

from . import connect
from .jitmath import safe_div, sel

# parameter keys whose derivative would need moving geometry or delta-direction derivatives
_REFUSED = ('vertex_positions', 'vertex_normals', 'vertex_texcoords', 'to_world', 'faces', 'center',
            'radius', 'position', 'direction')
# BSDFs whose index of refraction turns a delta lobe's direction
_DELTA_IOR = ('SmoothDielectric', 'ThinDielectric')


def check_parameters(params):
    """Refuse gradient-enabled parameters whose derivative bdpt does not compute (see above)."""
    if params is None:
        return
    for key in params.keys():
        try:
            value = params[key]
        except Exception:
            continue
        if not dr.grad_enabled(value):
            continue
        leaf = key.split('.')[-1]
        node = params.properties[key][2] if hasattr(params, 'properties') else None
        delta_ior = (leaf in ('eta', 'int_ior', 'ext_ior') and node is not None
                     and str(node.class_name()) in _DELTA_IOR)
        if leaf in _REFUSED or key.endswith('to_world') or delta_ior:
            raise NotImplementedError(
                f"bdpt: gradients with respect to '{key}' are not supported: bdpt differentiates "
                "BSDF and emitter values (reflectance, roughness, specular reflectance/transmittance, "
                "radiance, intensity, irradiance, environment texels); parameters that move geometry "
                "or a delta lobe's direction (shape vertices and transforms, the index of refraction "
                "of a smooth dielectric) need silhouette and sampling derivatives it does not have")


def sample_bsdf(c, bsdf, mode, si, u1, u2, active):
    """connect.sample_bsdf with detached sampling: the sample (direction, density, lobe) carries
    no derivative; the weight's gradient is that of f_ad cos / detach(pdf) for smooth samples
    and that of the sampled weight (specular reflectance or transmittance) for delta ones."""
    if not c.ad:
        return connect.sample_bsdf(bsdf, mode, si, u1, u2, active, c.diffuse)
    with dr.suspend_grad():
        bs, w = connect.sample_bsdf(bsdf, mode, si, u1, u2, active, c.diffuse)
    f_ad = bsdf.eval(mode, si, bs.wo, active)
    _, w_delta = bsdf.sample(mode, si, u1, u2, active)
    smooth_grad = f_ad * safe_div(1.0, bs.pdf)
    if c.has_delta:
        is_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        smooth_grad = dr.select(is_delta, w_delta, smooth_grad)
    return bs, dr.replace_grad(w, dr.select(active, smooth_grad, 0.0))


def sample_direct(c, si, u, active):
    """EmitterTable.sample_direct (s=1) with detached sampling: the emitter sample carries no
    derivative; the weight Le / pdf takes the gradient of the emitted value evaluated again
    (``eval_direction``) over the detached density."""
    if not c.ad:
        return c.emitters.sample_direct(si, u, active)
    with dr.suspend_grad():
        ds, w = c.emitters.sample_direct(si, u, active)
    le = ds.emitter.eval_direction(si, ds, active & (ds.pdf > 0))
    return ds, dr.replace_grad(w, le * safe_div(1.0, ds.pdf))


def sample_emission(c, time, u_sel, u_pos, u_dir, active):
    """EmitterTable.sample_emission with detached sampling: the light subpath's start carries no
    derivative except its throughput, whose gradient is that of the emitted value evaluated
    again per emitter kind over the detached emission density."""
    if not c.ad:
        return c.emitters.sample_emission(time, u_sel, u_pos, u_dir, active)
    with dr.suspend_grad():
        e = c.emitters.sample_emission(time, u_sel, u_pos, u_dir, active)
    k, emitter = e.kinds, e.emitter
    value = mi.Color3f(0.0)
    if k.area is not False:
        si_e = mi.SurfaceInteraction3f(e.si_e)
        si_e.wi = si_e.to_local(e.d)
        value = sel(k.area, emitter.eval(si_e, e.active & k.area) * e.cos_e, value)
    delta = k.delta
    if delta is not False:
        # points and spots (at distance 1 along the emitted direction) and directional lights:
        # the weight of Mitsuba's sample_direction is the intensity (irradiance) itself
        it = dr.zeros(mi.Interaction3f)
        it.p, it.time = e.origin + e.d, time
        _, w_delta = emitter.sample_direction(it, u_dir, e.active & delta)
        value = sel(delta, w_delta, value)
    if k.env is not False:
        # (eval, not eval_direction: Mitsuba's envmap reads the direction from ds.p - it.p there)
        si_env = dr.zeros(mi.SurfaceInteraction3f)
        si_env.wi, si_env.time = e.d, time           # e.d leaves the environment
        value = sel(k.env, emitter.eval(si_env, e.active & k.env), value)
    e.beta = dr.replace_grad(e.beta, value * safe_div(1.0, e.pdf_emit_w))
    return e
