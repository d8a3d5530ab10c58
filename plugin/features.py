"""Which parts of the pipeline a scene needs (emitter sampling, emitter hits, analytic shapes, sort, statistics), with the reasons."""
from __future__ import annotations

import mitsuba as mi

import layerbvh


class Features:
    """What the pipeline runs for one scene: each feature on, or left out with the reason."""

    def __init__(self):
        self.active, self.left_out = [], []

    def decide(self, name: str, needed: bool, why_on: str, why_off: str, force: bool = False):
        if needed or force:
            self.active.append({"feature": name, "reason": why_on if needed else "forced (adaptive=false)"})
        else:
            self.left_out.append({"feature": name, "reason": why_off})

    def on(self, name: str) -> bool:
        return any(f["feature"] == name for f in self.active)

    def as_dict(self) -> dict:
        return {"active": [f["feature"] for f in self.active], "active_detail": self.active,
                "left_out": self.left_out}


def plan_features(scene, tracer, integ: "LayerBVHIntegrator") -> Features:
    """Inspect the scene once and decide which parts of the pipeline it needs."""
    f = Features()
    force = not integ.adaptive
    emitters = scene.emitters()
    hittable = [e for e in emitters if mi.has_flag(e.flags(), mi.EmitterFlags.Surface)
                or mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)]
    n_analytic = len(tracer.geometry.analytic)
    f.decide("emitter_sampling", len(emitters) > 0, f"{len(emitters)} emitter(s) to sample (shadow rays: any-hit traversal)",
             "the scene has no emitter: no emitter sampling, no shadow rays", force)
    f.decide("emitter_hits", len(hittable) > 0, f"{len(hittable)} area/environment emitter(s) can be hit",
             "no area or environment emitter: nothing a ray hits emits", force)
    f.decide("analytic_shapes", n_analytic > 0, f"{n_analytic} sphere/disk/cylinder shape(s)",
             "no sphere, disk or cylinder: BVH hits only", force)
    one_treelet = tracer.bvh.stats.treelets <= 1
    sorted_mode = integ.traversal in ("layer_sorted", layerbvh.AUTO)
    f.decide("sort", sorted_mode and not one_treelet,
             "rays sorted by treelet between wavefront steps" + (
                 " (auto: for the ray batches where layer_sorted timed faster)" if integ.traversal == layerbvh.AUTO else ""),
             "the BVH fits in one treelet: one step, nothing to sort" if sorted_mode and one_treelet
             else f"traversal {integ.traversal} does not sort")
    f.decide("statistics", integ.stats, "stats=true: work counters in the kernels",
             "not asked for (stats=false): no work counters")
    f.active.append({"feature": f"traversal:{integ.traversal}",
                     "reason": "per_ray and layer_sorted, chosen per ray batch by timing" if integ.traversal == layerbvh.AUTO
                     else "the only traversal mode compiled"})
    f.active.append({"feature": "any_hit_shadows", "reason": "shadow rays stop at their first hit"})
    return f
