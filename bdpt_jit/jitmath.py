"""Small Dr.Jit helpers every stage uses, and the one change of measure between densities
per unit solid angle (``pdf_w``) and per unit area (``pdf_a``)."""

import drjit as dr

INV_PI = 1.0 / dr.pi


def safe_div(a, b):
    """a / b, and 0 where b is 0 (a density or a squared distance that vanished)."""
    return dr.select(b != 0, a / dr.select(b != 0, b, 1.0), 0.0)


def finite_or_zero(x):
    """x where it is finite, else 0 (a density a sampler reports as +inf or NaN where it
    cannot produce the point: that strategy cannot sample the path)."""
    return dr.select(dr.isfinite(x), x, 0.0)


def pdf_w_to_a(pdf_w, cos_target, dist2):
    """A density per unit solid angle at one vertex turned into a density per unit area at the
    target vertex: pdf_w |cos_target| / dist^2 (seed paper eq. 9); 0 for a vanished distance."""
    return pdf_w * dr.abs(cos_target) * safe_div(1.0, dist2)


def neg(mask):
    """Logical not of a per-lane mask or a Python bool (``~True`` is -2 in Python)."""
    if mask is True or mask is False:
        return not mask
    return ~mask


def sel(mask, a, b):
    """dr.select that also takes a Python bool mask (a kind absent from the scene: its code is
    not traced)."""
    if mask is True:
        return a
    if mask is False:
        return b
    return dr.select(mask, a, b)
