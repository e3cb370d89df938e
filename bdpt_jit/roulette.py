"""Russian roulette for both subpaths. The survival probability follows the throughput
relative to the subpath's start (as Mitsuba's `path` does for camera paths, whose throughput
starts at 1): a light subpath's throughput also carries Le / p of its emitter, which would
otherwise keep the probability at its cap and never end a light subpath early. On camera
subpaths the start is divided by eta^2 at each refraction (transport.scatter), so the
probability follows the throughput times eta^2, as Mitsuba's `path`: radiance entering glass of
index eta carries 1 / eta^2, which alone would make survival inside glass of index 1.49 0.45
times as likely (below the cap)."""

import drjit as dr


def roulette(beta, beta_start, depth, rr_depth, active, u):
    """Returns (beta, active) after the roulette at ``depth`` (edges so far); survival is
    min(max(beta) / beta_start, 0.95) from ``rr_depth`` on."""
    # the survival probability is a sampling decision: no derivative (gradients.py)
    q = dr.minimum(dr.max(dr.detach(beta)) * dr.select(beta_start > 0, dr.rcp(dr.detach(beta_start)), 0.0), 0.95)
    rr = active & (depth >= rr_depth)
    beta = dr.select(rr, beta * dr.rcp(dr.select(q > 0, q, 1.0)), beta)
    active = active & (~rr | (u < q))
    return beta, active
