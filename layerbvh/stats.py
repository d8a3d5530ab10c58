"""Traversal and BVH statistics: what a trace did (steps, work per ray, time split, memory)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass
class StepTime:
    """One wavefront step's host-timed split (issue 57 item 4: on the H200 the host's share per
    step outweighed the kernels). `trace_s`: Python building the step (tracing the walk, or a
    frozen step's replay, which launches as it goes); `kernel_s`: from there until its kernels
    finished and the finished count was read back; `sort_s`: the next step's permutation."""

    rays: int
    trace_s: float
    kernel_s: float
    sort_s: float
    tail: bool = False  # the per-ray kernel that finished the rays left

    def as_dict(self) -> dict:
        return {"rays": self.rays, "trace_s": self.trace_s, "kernel_s": self.kernel_s, "sort_s": self.sort_s,
                "tail": self.tail}


@dataclass
class TraceStats:
    """Statistics of one trace/occluded call.

    `steps` counts kernel launches of the traversal (the last one may be the per-ray tail, see
    `tail_rays`). Work counts are totals over all rays; `*_per_ray` divide by the ray count. Leaf
    intersection runs inline in the traversal kernel, so `time_leaf_s` and
    `time_treelet_s` split the kernel time by the share of loop iterations spent on
    triangles (an estimate, marked as such by `time_split_estimated`)."""

    mode: str
    rays: int
    steps: int = 0
    active_per_step: list = field(default_factory=list)
    inner_nodes: int = 0
    leaves: int = 0
    triangles: int = 0
    iterations: int = 0
    ray_steps: int = 0  # kernel calls summed over rays (each ray's wavefront steps)
    top_inner_nodes: int = 0  # instanced layouts: of inner_nodes, those of the top level
    instance_entries: int = 0  # instanced layouts: instances entered (object-space walks begun)
    time_sort_s: float = 0.0
    time_traverse_s: float = 0.0
    time_treelet_s: float = 0.0
    time_leaf_s: float = 0.0
    time_other_s: float = 0.0  # host-timed kernels between steps besides the sort: none since the
    # held-entry move went into the step kernel (PERFORMANCE.md entry 45); kept for old reports
    time_split_estimated: bool = True
    time_total_s: float = 0.0
    work_bytes: int = 0
    tail_rays: int = 0  # rays finished by one per-ray kernel after the last sorted step
    batches: int = 1  # ray batches traced one after another (LayerBVH.batch_rays bounds memory)
    frozen: bool = False  # the wavefront steps replayed frozen kernels (wavefront.FROZEN_STACK_BYTES)
    step_times: list = field(default_factory=list)  # [StepTime] per step, in order (the tail last)

    def absorb(self, other: "TraceStats") -> None:
        """Add the figures of one more ray batch traced with the same mode."""
        self.steps += other.steps
        self.active_per_step += other.active_per_step
        self.step_times += other.step_times
        self.frozen = self.frozen or other.frozen
        for name in ("time_sort_s", "time_traverse_s", "time_other_s"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.tail_rays += other.tail_rays
        self.work_bytes = max(self.work_bytes, other.work_bytes)  # batches run one after another
        self.batches += 1

    def finish(self, totals: dict) -> None:
        """Work totals over all rays (state.WORK names)."""
        self.inner_nodes, self.leaves = totals["inner_nodes"], totals["leaves"]
        self.triangles, self.iterations = totals["triangles"], totals["iterations"]
        self.ray_steps = totals["steps"]
        self.top_inner_nodes = totals.get("top_inner_nodes", 0)
        self.instance_entries = totals.get("instance_entries", 0)
        tris, iters = self.triangles, self.iterations
        share = tris / iters if iters else 0.0
        self.time_leaf_s = self.time_traverse_s * share
        self.time_treelet_s = self.time_traverse_s - self.time_leaf_s

    def per_ray(self, name: str) -> float:
        return getattr(self, name) / self.rays if self.rays else 0.0

    @property
    def inner_nodes_per_ray(self) -> float:
        return self.per_ray("inner_nodes")

    @property
    def leaves_per_ray(self) -> float:
        return self.per_ray("leaves")

    @property
    def triangles_per_ray(self) -> float:
        return self.per_ray("triangles")

    def as_dict(self) -> dict:
        d = asdict(self)
        d.update(inner_nodes_per_ray=self.inner_nodes_per_ray, leaves_per_ray=self.leaves_per_ray,
                 triangles_per_ray=self.triangles_per_ray, top_inner_nodes_per_ray=self.per_ray("top_inner_nodes"),
                 instance_entries_per_ray=self.per_ray("instance_entries"))
        return d


@dataclass
class BVHStats:
    triangles: int
    nodes: int
    leaves: int
    treelets: int
    depth: int
    treelet_height: int
    leaf_size: int
    treelet_node_counts: list
    bytes: dict
    build_s: float
    layout_s: float
    branching: int = 2  # children per inner node (layerbvh.layout.BRANCHINGS)
    kernel_load_s: float = 0.0  # first build in a process: compiling/loading the builder's kernels
    groups: int = 0  # instanced BVH: groups of unique geometry (`triangles` counts theirs, each once)
    instances: int = 0  # instanced BVH: instances placing them
    placed_triangles: int = 0  # triangles in the scene as placed (what a flattened copy would hold)

    @property
    def total_bytes(self) -> int:
        return sum(self.bytes.values())
