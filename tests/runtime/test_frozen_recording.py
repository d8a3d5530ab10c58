"""Frozen wavefront steps next to Mitsuba's objects: nothing a render leaves to Python's cycle collector is freed
inside a step's recording (drjit 1.5.0 aborts the process on a host callback there), and scene reading leaves no such
garbage."""
from __future__ import annotations

import gc
import subprocess
import sys
from pathlib import Path

import mitsuba as mi

from layerbvh_mitsuba.runtime import scene_geometry

ROOT = Path(__file__).resolve().parents[2]

# A Mitsuba scene whose last reference sits in a reference cycle becomes garbage just as a frozen
# step starts recording, with the collector set to run at the next allocation: the collection
# frees the scene inside the recording unless the steps hold the collector off
# (layerbvh.collector_held). Measured without it: "enqueue_host_func(): this function cannot be
# recorded!", SIGABRT. In a subprocess: the failure is an abort.
CHILD = """
import gc, sys, drjit as dr, mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import layerbvh
from layerbvh import meshes, wavefront
wavefront.FROZEN_BACKENDS = ("llvm",)
held = []
step = wavefront._step
def dropping_step(*a, **k):
    if held and dr.flag(dr.JitFlag.FreezingScope):
        gc.set_threshold(1)
        held.clear()
    return step(*a, **k)
wavefront._step = dropping_step
v, f = meshes.load_mesh(sys.argv[1] + "/scenes/meshes/bunny.ply")
tree = layerbvh.build(v, f)
class Cycle:
    pass
c = Cycle(); c.c = c; c.scene = mi.load_file(sys.argv[1] + "/scenes/cbox.xml")
dr.eval(mi.render(c.scene, spp=1))
held.append(c); del c
o, d = meshes.incoherent_rays(v, 512, seed=1)
h = tree.trace(o, d, mode="layer_sorted")
gc.set_threshold(700)
print("traced", h.stats.frozen, h.stats.steps, int((h.prim != 0xFFFFFFFF).sum()))
"""


def test_a_scene_freed_by_the_cycle_collector_never_lands_in_a_frozen_recording():
    r = subprocess.run([sys.executable, "-c", CHILD, str(ROOT)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
    traced, frozen, steps, hits = r.stdout.split()[-4:]
    assert traced == "traced" and frozen == "True" and int(steps) >= 2, r.stdout
    assert int(hits) > 0, r.stdout


def test_reading_a_scenes_children_leaves_no_cycle_garbage():
    """scene_geometry._children keeps one callback class per variant: a class made per call is a
    reference cycle, and the scene objects it collected were freed whenever the collector ran.
    (What else the process leaves to the collector, other tests' threads included, is not ours to
    count: the check looks for the callback's class among what a collection finds.)"""
    scene = mi.load_file(str(ROOT / "scenes" / "instancing.xml"))
    gc.collect()
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        for _ in range(3):
            children = scene_geometry._children(scene)
            assert any(scene_geometry._is_shapegroup(obj) for _, obj in children)
        del children
        gc.collect()
        left = [x for x in gc.garbage if isinstance(x, type) and x.__module__ == scene_geometry.__name__]
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
    assert not left, left
