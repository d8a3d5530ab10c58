"""Stock `depth`'s estimator (the distance to each camera ray's closest hit, 0 where it misses), its one query ours.
Follows src/integrators/depth.cpp @ v3.9.1."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import Kinds, Tracing
from layerbvh_mitsuba.runtime.features import Features


class DepthEstimator:
    """Depth: the estimator of stock ``depth``, the simplest there is (added with the estimator
    split, issue 42, as one file plus one registry line).

    Algorithm (stock ``depth``'s ``sample``): one closest-hit query per camera ray; its value is
    the hit distance ``t`` in every channel, 0 where the ray misses, and the sample is valid
    where it hits. No sample is drawn (stock draws none), so a same-seed render matches stock
    ``depth`` up to the hit distance's floating-point noise. Properties: none (a scene's
    ``hide_emitters``, which every sampling integrator takes, changes nothing, as in stock)."""

    PLUGIN = "depth"
    VOLUMETRIC = False

    def __init__(self, props: mi.Properties):
        props.get("hide_emitters", False)  # (read: Mitsuba refuses a property no plugin reads)

    def kinds(self, use: Features) -> Kinds:
        return [(False, "camera")]

    def auto_rule(self, use: Features) -> str | None:
        return None

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass: the camera rays' hits (the one kind of batch it traces)."""
        tr.queries.intersect(cam, dr.full(mi.Bool, True, dr.width(cam.o)), hint="camera")

    def sample(self, scene, sampler, ray: mi.Ray3f, medium, active, tr: Tracing):
        """(hit distance, valid) of the camera rays `ray`."""
        tr.iteration()
        pi = tr.queries.intersect(ray, active, hint="camera")
        return mi.Spectrum(dr.select(pi.is_valid(), pi.t, 0.0)), pi.is_valid()

    def describe(self) -> str:
        return "depth"
