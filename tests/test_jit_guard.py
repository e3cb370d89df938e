"""The cyclic garbage collector does not run while bdpt traces and evaluates kernels
(bdpt_jit/jit_guard.py: a collection there may free a Mitsuba object between two recordings of
one virtual call and abort the process in Dr.Jit 1.5.0)."""

import gc

import mitsuba as mi
import pytest

from bdpt_jit.integrator import BDPTIntegrator
from media_scenes import fog_room


@pytest.fixture
def eager_collector():
    """The collector on, collecting at every allocation (as late in a long render as it may)."""
    was, thresholds = gc.isenabled(), gc.get_threshold()
    gc.enable()
    gc.set_threshold(1, 1, 1)
    yield
    gc.set_threshold(*thresholds)
    if not was:
        gc.disable()


@pytest.mark.parametrize('technique', ['bdpt', 'vcm'])
def test_no_collection_while_a_render_traces(monkeypatch, eager_collector, technique):
    inside, collections = [False], []

    def callback(phase, info):
        if phase == 'start' and inside[0]:
            collections.append(info['generation'])

    original = BDPTIntegrator.render_pass

    def render_pass(self, *args, **kwargs):
        inside[0] = True
        try:
            return original(self, *args, **kwargs)
        finally:
            inside[0] = False
    monkeypatch.setattr(BDPTIntegrator, 'render_pass', render_pass)
    gc.callbacks.append(callback)
    try:
        scene = mi.load_dict(fog_room())
        mi.render(scene, integrator=mi.load_dict({'type': 'bdpt', 'technique': technique, 'max_depth': 4}), spp=2)
    finally:
        gc.callbacks.remove(callback)
    assert collections == []
    assert gc.isenabled()        # restored after the render
