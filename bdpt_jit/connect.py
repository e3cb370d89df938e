"""Evaluating a vertex of a subpath towards another point: the BSDF value times the cosine,
the forward density of that direction and the reverse density of the vertex's incoming
direction. Camera vertices transport radiance; light vertices transport importance, with the
adjoint BSDF's shading-normal correction (Veach's thesis, section 5.3, eq. 5.17), or, where
BSDFs perturb their own shading frame (normal and bump maps), the exact adjoint from a
radiance-mode evaluation with the directions swapped (adjoint_eval)."""

import drjit as dr
import mitsuba as mi

CTX_RADIANCE = mi.BSDFContext(mi.TransportMode.Radiance)
CTX_IMPORTANCE = mi.BSDFContext(mi.TransportMode.Importance)


def reverse_pdf_w(bsdf, ctx, si, wo_local, active):
    """Density of sampling the vertex's incoming direction ``si.wi`` when arriving from
    ``wo_local``: the same BSDF queried with the two directions swapped."""
    si_rev = mi.SurfaceInteraction3f(si)
    si_rev.wi = wo_local
    return bsdf.pdf(ctx, si_rev, si.wi, active)


def _cosines(si, wo_local, wo_world, active):
    """Geometric and shading cosines of the incoming (``si.wi``, towards the previous vertex)
    and outgoing directions, and the mask that refuses light leaks (shading and geometric
    normals disagreeing about the side of a direction)."""
    wi_world = si.to_world(si.wi)
    # Mirrored (negative-determinant) transforms give a geometric normal opposite to the
    # shading normal: orient it to the shading side, or every direction reads as a light leak.
    n_g = dr.mulsign(si.n, dr.dot(si.n, si.sh_frame.n))
    cos_g_wi = dr.dot(n_g, wi_world)
    cos_g_wo = dr.dot(n_g, wo_world)
    cos_s_wi = mi.Frame3f.cos_theta(si.wi)
    cos_s_wo = mi.Frame3f.cos_theta(wo_local)
    valid = active & (cos_g_wi * cos_s_wi > 0) & (cos_g_wo * cos_s_wo > 0)
    return cos_g_wi, cos_g_wo, cos_s_wi, cos_s_wo, valid


def adjoint_correction(si, wo_local, wo_world, active):
    """Shading-normal factor of the adjoint BSDF, |cos_s(wi) cos_g(wo)| / |cos_s(wo) cos_g(wi)|
    (Veach's eq. 5.17), for BSDFs reciprocal in the surface's shading frame, and the leak mask."""
    cos_g_wi, cos_g_wo, cos_s_wi, cos_s_wo, valid = _cosines(si, wo_local, wo_world, active)
    denom = cos_s_wo * cos_g_wi
    factor = dr.select(valid & (denom != 0), dr.abs(cos_s_wi * cos_g_wo / denom), 0.0)
    return factor, valid


def adjoint_eval(si, bsdf, wo_local, wo_world, active):
    """The adjoint BSDF value for any BSDF, reciprocal or not: Mitsuba's radiance-mode value
    with the two directions swapped, f(wo -> wi) |cos_s'(wi)| -- exactly what a camera subpath
    multiplies at this vertex for the reversed path -- times |cos_g(wo)| / |cos_g(wi)|, the
    change of measure to the light subpath's side. Needed where the BSDF's shading frame is not
    the surface's: ``normalmap`` and ``bumpmap`` perturb the frame depending on wi and attenuate
    by a shadowing term of wo (Mitsuba 3.9 src/bsdfs/normalmap.cpp), so Veach's factor built
    from ``si.sh_frame`` is wrong there (lt +13% on tests/stability_cases.normal_mapped).
    The same call gives the reverse density of wi (radiance mode, as a camera subpath samples).
    Returns (value, pdf_rev_w, valid)."""
    cos_g_wi, cos_g_wo, _, _, valid = _cosines(si, wo_local, wo_world, active)
    si_rev = mi.SurfaceInteraction3f(si)
    si_rev.wi = wo_local
    f, pdf_rev_w = bsdf.eval_pdf(CTX_RADIANCE, si_rev, si.wi, valid)
    factor = dr.select(valid & (cos_g_wi != 0), dr.abs(cos_g_wo / cos_g_wi), 0.0)
    return f * factor, pdf_rev_w, valid


def eval_camera_vertex(si, bsdf, wo_world, active):
    """f(wi -> wo) |cos_s(wo)| in radiance mode; forward density of wo; reverse density of wi."""
    wo_local = si.to_local(wo_world)
    f, pdf_fwd_w = bsdf.eval_pdf(CTX_RADIANCE, si, wo_local, active)
    pdf_rev_w = reverse_pdf_w(bsdf, CTX_RADIANCE, si, wo_local, active)
    return f, pdf_fwd_w, pdf_rev_w


def eval_light_vertex(si, bsdf, wo_world, active, exact_adjoint=False):
    """Adjoint f*(wi -> wo) times the geometric-cosine measure, as the light subpath carries it:
    Mitsuba's importance-mode value times the shading-normal correction; densities as above.
    ``exact_adjoint`` (scenes with normal or bump maps): adjoint_eval instead."""
    wo_local = si.to_local(wo_world)
    if exact_adjoint:
        f, pdf_rev_w, valid = adjoint_eval(si, bsdf, wo_local, wo_world, active)
        pdf_fwd_w = bsdf.pdf(CTX_IMPORTANCE, si, wo_local, valid)
        return f, pdf_fwd_w, pdf_rev_w, valid
    corr, valid = adjoint_correction(si, wo_local, wo_world, active)
    f, pdf_fwd_w = bsdf.eval_pdf(CTX_IMPORTANCE, si, wo_local, valid)
    pdf_rev_w = reverse_pdf_w(bsdf, CTX_IMPORTANCE, si, wo_local, valid)
    return f * corr, pdf_fwd_w, pdf_rev_w, valid
