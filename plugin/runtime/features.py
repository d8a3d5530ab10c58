"""Which parts of the path tracer a scene needs (emitter sampling, emitter hits, analytic shapes, sort, statistics), with the reasons."""
from __future__ import annotations

from dataclasses import dataclass, fields

import mitsuba as mi

import layerbvh


@dataclass(frozen=True)
class Feature:
    on: bool
    reason: str


@dataclass(frozen=True)
class Features:
    """What the integrator runs for one scene: each feature on, or left out with the reason.
    Leaving a feature out never changes the image (random numbers are drawn in stock order)."""

    emitter_sampling: Feature  # sample an emitter and trace a shadow ray per vertex
    emitter_hits: Feature      # look up emission where a ray hits an area or environment emitter
    analytic_shapes: Feature   # spheres, disks, cylinders, ellipsoids (also in instances): Mitsuba's per-shape test
    sort: Feature              # sort rays by treelet between wavefront steps
    statistics: Feature        # work counters in the traversal kernels
    traversal: str             # the integrator's traversal mode

    def as_dict(self) -> dict:
        flags = [(f.name, getattr(self, f.name)) for f in fields(self) if f.name != "traversal"]
        on = [{"feature": name, "reason": f.reason} for name, f in flags if f.on]
        on += [{"feature": f"traversal:{self.traversal}",
                "reason": "per_ray and layer_sorted, chosen per ray batch by timing" if self.traversal == layerbvh.AUTO
                else "the only traversal mode compiled"},
               {"feature": "any_hit_shadows", "reason": "shadow rays stop at their first hit"}]
        return {"active": [f["feature"] for f in on], "active_detail": on,
                "left_out": [{"feature": name, "reason": f.reason} for name, f in flags if not f.on]}


def _decide(needed: bool, why_on: str, why_off: str, force: bool = False) -> Feature:
    if needed or force:
        return Feature(True, why_on if needed else "forced (adaptive=false)")
    return Feature(False, why_off)


def plan_features(scene, analytic_shapes: int, treelets: int, traversal: str, stats: bool, adaptive: bool) -> Features:
    """Inspect the scene once and decide which parts of the path tracer it needs; with
    `adaptive` False everything a scene could need runs."""
    force = not adaptive
    emitters = scene.emitters()
    hittable = [e for e in emitters if mi.has_flag(e.flags(), mi.EmitterFlags.Surface)
                or mi.has_flag(e.flags(), mi.EmitterFlags.Infinite)]
    one_treelet = treelets <= 1
    sorted_mode = traversal in ("layer_sorted", layerbvh.AUTO)
    return Features(
        emitter_sampling=_decide(len(emitters) > 0,
                                 f"{len(emitters)} emitter(s) to sample (shadow rays: any-hit traversal)",
                                 "the scene has no emitter: no emitter sampling, no shadow rays", force),
        emitter_hits=_decide(len(hittable) > 0, f"{len(hittable)} area/environment emitter(s) can be hit",
                             "no area or environment emitter: nothing a ray hits emits", force),
        analytic_shapes=_decide(analytic_shapes > 0,
                                f"{analytic_shapes} per-shape test(s) per ray (spheres, disks, cylinders, ellipsoids; "
                                f"one per instance of one)",
                                "no sphere, disk, cylinder or ellipsoid: BVH hits only", force),
        sort=_decide(sorted_mode and not one_treelet,
                     "rays sorted by treelet between wavefront steps" + (
                         " (auto: for the ray batches where layer_sorted timed faster)"
                         if traversal == layerbvh.AUTO else ""),
                     "the BVH fits in one treelet: one step, nothing to sort" if sorted_mode and one_treelet
                     else f"traversal {traversal} does not sort"),
        statistics=_decide(stats, "stats=true: work counters in the kernels",
                           "not asked for (stats=false): no work counters"),
        traversal=traversal)
