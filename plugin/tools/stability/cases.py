"""The stability suite's cases: extreme geometry against Embree (ray level) and stiff light
transport against stock Mitsuba (image level).

Every case is a function `case(scale) -> CaseResult` registered in CASES; `scale` multiplies the
ray count or the image size (the tests run scale 1, `scripts/stability_report.py` more). A case
measures, then decides `passed` by the rule it states in `criterion` with the measured numbers;
`tests/tools/test_stability.py` asserts it and `scripts/stability_report.py` turns the results into
STABILITY.md.

Ray level. Our closest hits (all three traversal modes, which must agree bit for bit) against
Embree in its default and robust (`embree_use_robust_intersections`) modes. A *disagreement* is a
ray where one side hits and the other misses, or where the two hit different triangles at
different distances; rays that hit two triangles at the same distance (shared edges, coplanar
faces: either answer is right) are ties and counted apart (`embree.disagreements`).

Image level. Our `layerbvh` integrator in layer_sorted (treelets of LAYER_HEIGHT levels, so that
the wavefront path runs) against stock `path` on the scenes in scenes/stability/: same seed
(pixels differing by more than 1e-3 x max(1, |stock|) from Embree in default and robust mode),
NaN/Inf pixels, and a negative control: the same rule must fail on stock with one material's
albedo x 1.02 (see image_case).
"""
from __future__ import annotations

# Importing the case modules registers their cases (machinery.case), in this order: ray level
# (precision, then meshes and inputs), then image level.
from layerbvh_mitsuba.tools.stability import ray_cases  # noqa: F401  (isort: keep this order)
from layerbvh_mitsuba.tools.stability import mesh_cases  # noqa: F401
from layerbvh_mitsuba.tools.stability import image_cases  # noqa: F401
from layerbvh_mitsuba.tools.stability import scale_cases  # noqa: F401
from layerbvh_mitsuba.tools.stability.machinery import CASES, RAYS, CaseResult, run_case

__all__ = ["CASES", "RAYS", "CaseResult", "run_case"]
