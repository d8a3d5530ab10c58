"""Which parts of an integrator a scene needs (emitter sampling, emitter hits, analytic shapes, media, transmittance
rays, sort, statistics), with the reasons."""
from __future__ import annotations

from dataclasses import dataclass, fields

import mitsuba as mi

import layerbvh
from layerbvh_mitsuba.runtime.scene_geometry import sensor_medium


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
    # volpath only (None for the surface integrators, which ignore media):
    media: Feature | None = None          # sample free flights in the media the scene holds
    transmittance: Feature | None = None  # shadow rays cross null surfaces and media (closest-hit steps)

    def as_dict(self) -> dict:
        flags = [(f.name, getattr(self, f.name)) for f in fields(self)
                 if f.name != "traversal" and getattr(self, f.name) is not None]
        on = [{"feature": name, "reason": f.reason} for name, f in flags if f.on]
        on += [{"feature": f"traversal:{self.traversal}",
                "reason": "per_ray and layer_sorted, chosen per ray batch by timing" if self.traversal == layerbvh.AUTO
                else "the only traversal mode compiled"},
               ]
        if self.transmittance is None or not self.transmittance.on:
            on.append({"feature": "any_hit_shadows", "reason": "shadow rays stop at their first hit"})
        return {"active": [f["feature"] for f in on], "active_detail": on,
                "left_out": [{"feature": name, "reason": f.reason} for name, f in flags if not f.on]}


def _decide(needed: bool, why_on: str, why_off: str, force: bool = False) -> Feature:
    if needed or force:
        return Feature(True, why_on if needed else "forced (adaptive=false)")
    return Feature(False, why_off)


def scene_media(scene) -> list:
    """The distinct media a scene holds: its shapes' interiors and exteriors and its sensors' media."""
    found = [m for s in scene.shapes() for m in (s.interior_medium(), s.exterior_medium())]
    found += [sensor_medium(s) for s in scene.sensors()]
    media = []
    for m in found:
        if m is not None and all(m is not x for x in media):
            media.append(m)
    return media


def null_surfaces(scene) -> int:
    """Shapes whose BSDF has a null component (`null`, `mask`, ...): light passes through them unscattered."""
    return sum(mi.has_flag(s.bsdf().flags(), mi.BSDFFlags.Null) for s in scene.shapes())


def _volumetric(scene, force: bool) -> tuple[Feature, Feature]:
    media, nulls = scene_media(scene), null_surfaces(scene)
    kinds = sorted({"homogeneous" if m.is_homogeneous() else "heterogeneous" for m in media})
    media_f = _decide(bool(media), f"{len(media)} medium/media ({', '.join(kinds)}): free-flight sampling, "
                      f"null and real scattering, phase functions",
                      "the scene holds no medium: no free-flight sampling", force)
    crossed = [f"{len(media)} medium/media"] * bool(media) + [f"{nulls} null-BSDF shape(s)"] * bool(nulls)
    trans_f = _decide(bool(media or nulls), f"shadow rays cross {' and '.join(crossed)}: transmittance "
                      f"estimated with closest-hit steps",
                      "no medium and no null-BSDF surface: a shadow ray is blocked by its first hit (any-hit "
                      "traversal)", force)
    return media_f, trans_f


def plan_features(scene, analytic_shapes: int, treelets: int, traversal: str, stats: bool, adaptive: bool,
                  volumetric: bool = False) -> Features:
    """Inspect the scene once and decide which parts of the integrator it needs; with
    `adaptive` False everything a scene could need runs. `volumetric`: the integrator handles
    media (volpath), so the media and transmittance features are planned too."""
    force = not adaptive
    media, transmittance = _volumetric(scene, force) if volumetric else (None, None)
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
        traversal=traversal, media=media, transmittance=transmittance)
