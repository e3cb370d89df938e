"""Ray statistics of a render, as the seed paper's Table 1 reports them: rays traced and rays
whose contribution is zero (an extension ray that leaves the scene, a shadow ray that is
blocked). Traced into the kernels only when the ``statistics`` parameter asks for them."""

import drjit as dr
import mitsuba as mi

NAMES = (
    'camera_rays',            # primary and extension rays of camera subpaths
    'camera_rays_missed',     #   ... that left the scene
    'light_rays',             # emission and extension rays of light subpaths
    'light_rays_missed',      #   ... that left the scene
    'shadow_rays',            # emitter sampling, connections, splats to the camera
    'shadow_rays_blocked',    #   ... that were occluded
)


class RayStats:
    NAMES = NAMES                 # the counters, in the order of ``buf``

    def __init__(self):
        self.buf = dr.zeros(mi.UInt32, len(self.NAMES))
        self.totals = {name: 0 for name in self.NAMES}

    def count(self, name, active):
        """Add the active lanes to counter ``name`` (pre-reduced within each packet)."""
        dr.scatter_reduce(dr.ReduceOp.Add, self.buf, mi.UInt32(1),
                          mi.UInt32(self.NAMES.index(name)), active)

    def ray(self, kind, active, hit):
        self.count(f'{kind}_rays', active)
        self.count(f'{kind}_rays_missed', active & ~hit)

    def shadow(self, active, blocked):
        self.count('shadow_rays', active)
        self.count('shadow_rays_blocked', active & blocked)

    def end_pass(self):
        import numpy as np
        for name, v in zip(self.NAMES, np.array(self.buf, dtype=np.uint64)):
            self.totals[name] += int(v)
        self.buf = dr.zeros(mi.UInt32, len(self.NAMES))

    def summary(self):
        t = dict(self.totals)
        t['rays'] = t['camera_rays'] + t['light_rays'] + t['shadow_rays']
        t['zero_contribution_rays'] = (t['camera_rays_missed'] + t['light_rays_missed']
                                       + t['shadow_rays_blocked'])
        return t


MEDIUM_NAMES = (
    'medium_inconsistencies',  # edges not made: their ends disagree about the medium between them
    'real_collisions',         # distance samples that ended at a real collision (medium vertices)
    'null_collisions',         # tentative collisions rejected by delta tracking or weighed by ratio tracking
)


class MediumStats(RayStats):
    """The media's counters (media.MediumTracer), kept apart from RayStats so that renders
    without media count, trace and report exactly as before; RayStats.summary can merge them
    once media are wired."""
    NAMES = MEDIUM_NAMES

    def summary(self):
        return dict(self.totals)


# Dr.Jit's kernel history is one queue, emptied by whoever reads it: technique auto's timed trials
# read their kernels' times from it (auto.kernel_seconds), and the command counts a render's
# kernels and their compilation from it (cli/rendering.KernelCounter). A reader drains it with
# ``drain_kernel_history``, which hands what it read to every observer registered here, so that
# each sees every kernel (the command's summary had counted none of a decision's trials, whose
# kernels' compilation is most of a first decision on a new scene).
KERNEL_OBSERVERS = []


def drain_kernel_history():
    """Dr.Jit's kernel history since the last drain (a list of dicts), also handed to each
    callable of KERNEL_OBSERVERS."""
    history = dr.kernel_history()
    for observe in list(KERNEL_OBSERVERS):
        observe(history)
    return history
