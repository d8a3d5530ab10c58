"""A render must not abort the process when Python's garbage collector frees Mitsuba objects of an earlier scene
while Dr.Jit records it (issue 39: the suite's worker aborts; runtime/held_instances.py says why)."""
from __future__ import annotations

import gc
import subprocess
import sys
from pathlib import Path

import pytest

from layerbvh_mitsuba.runtime.held_instances import instances_held

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "media" / "test_homo_obj_inside_medium_volpath.xml"

# The child renders the scene with ours once to count the shadow walks its kernel records, then
# again with a copy of the scene left as garbage in a reference cycle (a dead earlier scene, its
# medium still in Dr.Jit's registry). At the last shadow walk, after the main loop has recorded its
# medium calls over both media, the collector runs as it could there on its own: if it is enabled
# (its thresholds are set so that it runs nowhere else). Without the hold, the walk's medium calls
# are recorded over the one medium left, and Dr.Jit 1.5.0 aborts at compile ("invalid
# redefinition of function 'func_...'"); measured.
CHILD = r"""
import gc, sys
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
from layerbvh_mitsuba.runtime import registry
from layerbvh_mitsuba.runtime.estimators.media import MediaWalk

walks, collect_at = [0], [None]
walk = MediaWalk.shadow_walk
def counted_walk(self, *args, **kwargs):
    walks[0] += 1
    if walks[0] == collect_at[0] and gc.isenabled():
        print("collected mid-recording:", gc.collect())
    return walk(self, *args, **kwargs)
MediaWalk.shadow_walk = counted_walk
registry.register()

def render(scene):
    integrator = mi.load_dict({"type": "layerbvh_volpath", "traversal": "per_ray", "max_depth": 4})
    return mi.TensorXf(mi.render(scene, integrator=integrator, spp=2, seed=0)).numpy()

gc.set_threshold(1 << 30)  # (enabled, but collecting only where this test says)
scene = mi.load_file(sys.argv[1])
clean = render(scene)
collect_at[0], walks[0] = walks[0], 0
dead = [mi.load_file(sys.argv[1])]
dead.append(dead)
del dead
assert (render(scene) == clean).all(), "the image changed"
print("rendered", collect_at[0], "shadow walks")
"""


def test_a_collection_during_recording_cannot_abort_the_render():
    r = subprocess.run([sys.executable, "-c", CHILD, str(SCENE)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, (f"the render aborted (exit {r.returncode}): "
                               f"{[l for l in r.stderr.splitlines() if 'error' in l][:3] or r.stderr[-2000:]}")
    assert "rendered" in r.stdout and "collected mid-recording" not in r.stdout, r.stdout


def test_the_hold_pauses_the_collector_and_gives_it_back():
    enabled = gc.isenabled()
    try:
        gc.enable()
        with instances_held():
            with instances_held():  # (nested: a render pass inside the render driver's hold)
                assert not gc.isenabled()
            assert not gc.isenabled()
        assert gc.isenabled()
        with pytest.raises(RuntimeError):
            with instances_held():
                raise RuntimeError("a render that fails")
        assert gc.isenabled(), "an exception during a render left the collector paused"
        gc.disable()
        with instances_held():
            pass
        assert not gc.isenabled(), "a collector the caller had paused was switched on"
    finally:
        (gc.enable if enabled else gc.disable)()


def test_a_differentiable_render_holds_the_collector_across_forward_and_backward(monkeypatch):
    """Mitsuba's render_forward and render_backward record kernels outside our `sample` too (the
    primal pass, the replay, the film): the driver's layerbvh_prb holds the collector across each
    whole call, so it is off when Mitsuba's own method begins. (The suite's prb tests aborted
    without the hold only where a collection happened to fall inside a recording; this asks
    the collector's state itself.)"""
    import mitsuba as mi
    import layerbvh_mitsuba  # noqa: F401  (registers the integrators)
    from layerbvh_mitsuba import testing
    from layerbvh_mitsuba.ab import gradient
    from layerbvh_mitsuba.runtime.registry import integrator_class
    base = integrator_class("layerbvh_prb")._base  # this variant's RBIntegrator
    seen = []
    for name in ("render_forward", "render_backward"):
        def spy(self, *args, _method=getattr(base, name), _name=name, **kwargs):
            seen.append((_name, gc.isenabled()))
            return _method(self, *args, **kwargs)
        monkeypatch.setattr(base, name, spy)
    scene = testing.load(SCENE.parents[1] / "cbox.xml", (8, 8))
    key = next(k for k in mi.traverse(scene).keys() if k.endswith("reflectance.value"))
    ours = mi.load_dict({"type": "layerbvh_prb", "max_depth": 3, "traversal": "per_ray"})
    was = gc.isenabled()
    gc.enable()
    try:
        gradient.gradients(mi, scene, ours, key, 1, 0, forward=True)
    finally:
        if not was:
            gc.disable()
    assert seen == [("render_forward", False), ("render_backward", False)], seen
