"""Evaluating a vertex of a subpath towards another point: the BSDF value times the cosine,
the forward density of that direction and the reverse density of the vertex's incoming
direction. Camera vertices transport radiance; light vertices transport importance, with the
adjoint BSDF's shading-normal correction (Veach's thesis, section 5.3, eq. 5.17), or, where
BSDFs perturb their own shading frame (normal and bump maps), the exact adjoint from a
radiance-mode evaluation with the directions swapped (adjoint_eval)."""

import drjit as dr
import mitsuba as mi
import numpy as np

CTX_RADIANCE = mi.BSDFContext(mi.TransportMode.Radiance)
CTX_IMPORTANCE = mi.BSDFContext(mi.TransportMode.Importance)
INV_PI = 1.0 / dr.pi


def reverse_pdf_w(bsdf, ctx, si, wo_local, active, table=None):
    """Density of sampling the vertex's incoming direction ``si.wi`` when arriving from
    ``wo_local``: the same BSDF queried with the two directions swapped."""
    if table is not None:
        return table.pdf_rev_w(si, wo_local, active)
    si_rev = mi.SurfaceInteraction3f(si)
    si_rev.wi = wo_local
    return bsdf.pdf(ctx, si_rev, si.wi, active)


def constant_value(obj, key, others=()):
    """The value of the parameter ``key`` of the Mitsuba object ``obj`` (mi.traverse), where it is
    a constant (an RGB or a uniform spectrum) and ``others`` are the object's only other
    parameters: its 1 or 3 values (NumPy), else None (a texture, a spectrum of wavelengths, ...)."""
    params = mi.traverse(obj)
    if sorted(params.keys()) != sorted((key,) + tuple(others)):
        return None
    if str(params.properties[key][2].class_name()) not in ('SRGBReflectanceSpectrum', 'UniformSpectrum'):
        return None
    v = np.array(params[key], dtype=np.float64).ravel()
    return v if v.size in (1, 3) else None


class DiffuseTable:
    """Mitsuba's ``diffuse`` BSDF with a constant reflectance, evaluated without a virtual
    call: its value R/pi cos_o and densities cos/pi (src/bsdfs/diffuse.cpp, one-sided: zero
    unless both directions are above the surface) from a table of reflectances indexed by
    the BSDF's registry id. Used only where every BSDF of the scene is such a diffuse one
    (``everything``; context.diffuse_table): no BSDF call is traced at all. On the SmallVCM box
    (all diffuse) this replaced 4 of the 5 virtual calls of each connection (+9% samples/s).
    In a scene that mixes them with other BSDFs, a table for some lanes beside Mitsuba's calls
    for the others was slower than the calls alone (the gathers and selects; the calls stay):
    veach-mis pt 5%, bdpt 7%, caustic.xml pt 3%, bdpt 6% (seventeenth session). The value is the
    same in both transport modes."""

    def __init__(self, scene):
        bsdfs = {}
        for shape in scene.shapes():
            b = shape.bsdf()
            if b is not None:
                bsdfs[int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0])] = b
        size = max(list(bsdfs) + [0]) + 1
        refl = np.zeros((3, size), np.float32)
        covered = np.zeros(size, bool)
        for i, b in bsdfs.items():
            r = self.constant_reflectance(b)
            if r is not None:
                refl[:, i], covered[i] = r, True
        self.everything = bool(bsdfs) and all(bool(covered[i]) for i in bsdfs)
        self.refl = mi.Color3f(refl[0], refl[1], refl[2])

    @staticmethod
    def constant_reflectance(bsdf):
        v = constant_value(bsdf, 'reflectance.value') if str(bsdf.class_name()) == 'SmoothDiffuse' else None
        return None if v is None else np.broadcast_to(v, 3)

    def eval_pdf(self, si, bsdf, wo_local, active):
        """(R/pi cos_o, cos_o/pi, cos_i/pi): value, forward and reverse densities."""
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo_local)
        ok = active & (cos_i > 0) & (cos_o > 0)
        r = dr.gather(mi.Color3f, self.refl, dr.reinterpret_array(mi.UInt32, bsdf), ok)
        return (dr.select(ok, r * (cos_o * INV_PI), 0.0), dr.select(ok, cos_o * INV_PI, 0.0),
                dr.select(ok, cos_i * INV_PI, 0.0))

    def sample(self, si, bsdf, u2, active):
        """Cosine-weighted hemisphere sample, as diffuse.cpp draws it: (BSDFSample3f, R)."""
        ok = active & (mi.Frame3f.cos_theta(si.wi) > 0)
        bs = dr.zeros(mi.BSDFSample3f, dr.width(u2))
        bs.wo = mi.warp.square_to_cosine_hemisphere(u2)
        bs.pdf = dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(bs.wo), 0.0)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(int(mi.BSDFFlags.DiffuseReflection))
        bs.sampled_component = mi.UInt32(0)
        r = dr.gather(mi.Color3f, self.refl, dr.reinterpret_array(mi.UInt32, bsdf), ok)
        return bs, dr.select(ok & (bs.pdf > 0), r, 0.0)

    def pdf_rev_w(self, si, wo_local, active):
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo_local)
        return dr.select(active & (cos_i > 0) & (cos_o > 0), cos_i * INV_PI, 0.0)


def _cosines(si, wo_local, wo_world, active):
    """Geometric and shading cosines of the incoming (``si.wi``, towards the previous vertex)
    and outgoing directions, and the lanes where the adjoint is defined (a geometric cosine of
    wi and a shading cosine of wo that are not 0). Directions on which the shading and
    geometric normals disagree about the side (light passing a smooth-shaded surface) are kept:
    Mitsuba's BSDFs evaluate them in the shading frame from the camera side, so its path renders
    the light they carry, and a light side that refused them left the strategies that sample
    them from the camera weighted by the ones that cannot (bdpt 93% dark and lt black on light
    leaking from a point light inside a coarse smooth-shaded shell)."""
    wi_world = si.to_world(si.wi)
    # Mirrored (negative-determinant) transforms give a geometric normal opposite to the
    # shading normal: oriented to the shading side (the cosines' signs then agree on ordinary
    # directions; every factor built from them takes absolute values).
    n_g = dr.mulsign(si.n, dr.dot(si.n, si.sh_frame.n))
    cos_g_wi = dr.dot(n_g, wi_world)
    cos_g_wo = dr.dot(n_g, wo_world)
    cos_s_wi = mi.Frame3f.cos_theta(si.wi)
    cos_s_wo = mi.Frame3f.cos_theta(wo_local)
    valid = active & (cos_g_wi != 0) & (cos_s_wo != 0)
    return cos_g_wi, cos_g_wo, cos_s_wi, cos_s_wo, valid


def adjoint_correction(si, wo_local, wo_world, active):
    """Shading-normal factor of the adjoint BSDF, |cos_s(wi) cos_g(wo)| / |cos_s(wo) cos_g(wi)|
    (Veach's eq. 5.17), for BSDFs reciprocal in the surface's shading frame, and the lanes where it
    is defined (_cosines)."""
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


def sample_bsdf(bsdf, mode, si, u1, u2, active, table=None):
    """``bsdf.sample``, or the table's sample without a virtual call."""
    if table is not None:
        return table.sample(si, bsdf, u2, active)
    return bsdf.sample(mode, si, u1, u2, active)


def smooth_mask(bsdf, table=None):
    """Lanes whose BSDF has a smooth (non-delta) component: all of them in a table-only scene."""
    if table is not None:
        return mi.Bool(True)
    return mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)


def _eval_pdf_both(bsdf, mode, si, wo_local, active, table):
    """(value, forward density, reverse density): the table's, or Mitsuba's."""
    if table is not None:
        return table.eval_pdf(si, bsdf, wo_local, active)
    f, pdf_fwd_w = bsdf.eval_pdf(mode, si, wo_local, active)
    return f, pdf_fwd_w, reverse_pdf_w(bsdf, mode, si, wo_local, active)


def eval_camera_vertex(si, bsdf, wo_world, active, table=None):
    """f(wi -> wo) |cos_s(wo)| in radiance mode; forward density of wo; reverse density of wi.
    ``table``: a DiffuseTable (or None)."""
    wo_local = si.to_local(wo_world)
    return _eval_pdf_both(bsdf, CTX_RADIANCE, si, wo_local, active, table)


def eval_light_vertex(si, bsdf, wo_world, active, exact_adjoint=False, table=None):
    """Adjoint f*(wi -> wo) times the geometric-cosine measure, as the light subpath carries it:
    Mitsuba's importance-mode value times the shading-normal correction; densities as above.
    ``exact_adjoint`` (scenes with normal or bump maps): adjoint_eval instead."""
    wo_local = si.to_local(wo_world)
    if exact_adjoint:
        f, pdf_rev_w, valid = adjoint_eval(si, bsdf, wo_local, wo_world, active)
        pdf_fwd_w = bsdf.pdf(CTX_IMPORTANCE, si, wo_local, valid)
        return f, pdf_fwd_w, pdf_rev_w, valid
    corr, valid = adjoint_correction(si, wo_local, wo_world, active)
    f, pdf_fwd_w, pdf_rev_w = _eval_pdf_both(bsdf, CTX_IMPORTANCE, si, wo_local, valid, table)
    return f * corr, pdf_fwd_w, pdf_rev_w, valid
