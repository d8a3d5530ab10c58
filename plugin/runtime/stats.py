"""What one render of the `layerbvh` integrator reports: `RenderStats`, its `last_stats`."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from layerbvh import BVHStats
from layerbvh_mitsuba.runtime.features import Features


@dataclass
class RenderStats:
    """The integrator's `last_stats`. Times in seconds; work sums over every query of the render
    (counters are zero unless the integrator's `stats` is set). In the megakernel the traversal
    runs after `sample` returns, so `trace_s`, `shading_s` and `bounces` say nothing there and
    are None."""

    loop: str                      # "megakernel" | "wavefront"
    traversal: str                 # the integrator's traversal (settings.Traversal.name)
    treelet_height: int
    branching: int
    features: Features
    bvh: BVHStats | None = None    # None for the embree control (Mitsuba's own BVH)
    build_s: float = 0.0           # BVH build (without numba's one-time kernel load)
    trace_s: float | None = None   # time inside our queries (wavefront loop)
    shading_s: float | None = None # the rest of the render (wavefront loop)
    queries: int = 0               # traversal calls (one per batch of one kind of ray)
    rays: int = 0
    wavefront_steps: int = 0       # kernel launches of the layer modes (per_ray: one per query)
    ray_steps: int = 0             # each ray's steps, summed (with stats only)
    inner_nodes: int = 0
    leaves: int = 0
    triangles: int = 0
    time_sort_s: float = 0.0
    time_traverse_s: float = 0.0
    peak_work_bytes: int = 0
    bounces: int | None = None     # path vertices shaded (bounce-loop iterations)
    modes_used: dict = field(default_factory=dict)    # engine mode (auto: "auto:<mode>") -> queries
    auto_choices: dict = field(default_factory=dict)  # auto's decisions (layerbvh.LayerBVH.auto_choices)
    calibration_s: float = 0.0     # auto's pre-passes and timing runs during this render

    def bvh_dict(self) -> dict:
        """The BVH's statistics as plain values (without the per-treelet node counts)."""
        if self.bvh is None:
            return {}
        return {k: v for k, v in asdict(self.bvh).items() if k != "treelet_node_counts"}

    def traversal_dict(self) -> dict:
        """Everything but the feature plan, as plain values (the report's "traversal" section)."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("features", "bvh")}
        return {**d, "bvh": self.bvh_dict()}

    def as_dict(self) -> dict:
        return {**self.traversal_dict(), "features": self.features.as_dict()}
