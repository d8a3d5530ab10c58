"""The public LayerBVH object: build once, then trace closest hits or test occlusion in any mode, in batches of
bounded memory."""
from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr

from . import backend as be
from .auto import AUTO, AutoPolicy
from .inputs import (DEFAULT_BRANCHING, DEFAULT_TREELET_HEIGHT, RayBatch, check_mesh, check_param, default_leaf_size,
                     ray_batch)
from .instances import Group, Instance, InstancedParts, check_instanced, check_instances, instanced_layout
from .layout import LayerLayout, check_layout
from .relayout import load_builder_kernels, to_layer_layout
from .sah import BinaryBVH, build_binned_sah, triangle_bounds
from .state import MISS, Results
from .stats import BVHStats, TraceStats
from .wavefront import MODES, TAIL_FRACTION, TAIL_RAYS, TAIL_STEPS, trace as _trace, trace_inline

# Rays traced per batch. The layer modes' work memory is about batch x ((K - 1) x tree depth x 8 B
# of entry stack + 2 x 36 B of ray state + 32 B ray record + 40 B in/out); 1M rays, binary depth 40
# or 4-wide depth 20: ~500-620 MB.
BATCH_RAYS = 1 << 20
TRACE_MODES = MODES + (AUTO,)


@dataclass
class Hits:
    """Closest hits, in the caller's array kind. Miss: t = inf, prim = MISS.
    p = (1-u-v)*p0 + u*p1 + v*p2 with p0, p1, p2 the vertices of faces[prim].

    An instanced BVH (build_instanced) also gives `instance`, the instance hit (MISS on a miss),
    and `prim` indexes the faces of that instance's group; None for a BVH over one mesh."""

    t: object
    prim: object
    u: object
    v: object
    stats: TraceStats
    work: dict | None = None  # with stats: per ray, state.WORK counts (inner_nodes, triangles, steps, ...)
    instance: object = None


@dataclass
class Occlusion:
    """Any-hit answers, in the caller's array kind: `occluded` is True for rays with a hit at
    0 < t < tmax."""

    occluded: object
    stats: TraceStats
    work: dict | None = None  # as in Hits


class LayerBVH:
    """A binned-SAH BVH over triangles, laid out as a Layer BVH (see layout.LayerLayout).

    `branching` is the number of children per inner node: 2 (the binary BVH) or 4, 8 (collapsed
    from it, layerbvh.collapse); `treelet_height` counts levels of that tree.
    `batch_rays` bounds how many rays one kernel pass holds (the work memory); `tail_rays`: when
    this few rays (or `tail_fraction` of a batch) are left in the layer modes, or after `tail_steps`
    wavefront steps, one per-ray kernel finishes them (wavefront.takes_tail); `auto_policy`
    decides mode="auto" (default: auto.AutoPolicy's rules for the backend).

    Given `groups` and `instances` (layerbvh.Group, layerbvh.Instance) in place of vertices and
    faces (None), it is a two-level BVH over instanced geometry (see build_instanced)."""

    def __init__(self, vertices, faces, treelet_height=DEFAULT_TREELET_HEIGHT, leaf_size=None, backend=None,
                 batch_rays=BATCH_RAYS, tail_rays=TAIL_RAYS, auto_policy: AutoPolicy | None = None,
                 tail_fraction: float = TAIL_FRACTION, groups: list[Group] | None = None,
                 instances: list[Instance] | None = None, branching: int = DEFAULT_BRANCHING,
                 tail_steps: int = TAIL_STEPS):
        treelet_height = check_param("treelet_height", treelet_height)
        self.branching = branching = check_param("branching", branching)
        self.batch_rays = check_param("batch_rays", batch_rays)
        self.tail_rays = check_param("tail_rays", tail_rays)
        if not 0.0 <= tail_fraction <= 1.0:
            raise ValueError(f"tail_fraction must be in [0, 1], got {tail_fraction}")
        self.tail_fraction = float(tail_fraction)
        self.tail_steps = check_param("tail_steps", tail_steps)
        leaf_size = check_param("leaf_size", default_leaf_size(branching) if leaf_size is None else leaf_size)
        self.backend = backend or be.default_backend()
        self.m = be.module(self.backend)
        self.auto = auto_policy or AutoPolicy(self.backend)
        self.groups: list[Group] | None = None
        self.instances: list[Instance] | None = None
        self.parts: InstancedParts | None = None
        self.binary: BinaryBVH | None = None
        if instances is None and groups is None:
            v, f = check_mesh(vertices, faces)
            self.vertices, self.faces = v, f
            kernel_load_s = load_builder_kernels() if len(f) else 0.0
            t0 = time.perf_counter()
            self.binary = build_binned_sah(*triangle_bounds(v, f), leaf_size) if len(f) else None
            t1 = time.perf_counter()
            self.layout: LayerLayout | None = to_layer_layout(self.binary, v, f, treelet_height, branching) \
                if len(f) else None
            t2 = time.perf_counter()
            unique = placed = len(f)
        else:
            if vertices is not None or faces is not None or groups is None or instances is None:
                raise ValueError("pass either vertices and faces (one mesh) or groups and instances "
                                 "(instanced geometry)")
            self.vertices = self.faces = None
            self.groups, self.instances = check_instances(groups, instances)
            unique = sum(len(g.faces) for g in self.groups)
            placed = sum(len(self.groups[i.group].faces) for i in self.instances)
            kernel_load_s = load_builder_kernels() if unique else 0.0
            t0 = time.perf_counter()
            self.layout, self.parts = instanced_layout(self.groups, self.instances, treelet_height, leaf_size,
                                                       branching)
            t1 = t2 = time.perf_counter()  # builds and lays out group by group: all of it is build time
        lay = self.layout
        self.device = None if lay is None else lay.to_device(self.m)
        self.stats = BVHStats(
            triangles=unique, nodes=lay.node_count if lay else 0, leaves=lay.leaf_count if lay else 0,
            treelets=lay.treelet_count if lay else 0, depth=lay.depth if lay else 0,
            treelet_height=treelet_height, leaf_size=leaf_size, branching=branching,
            treelet_node_counts=lay.treelet_node_counts.tolist() if lay else [],
            bytes=lay.array_bytes() if lay else {}, build_s=t1 - t0, layout_s=t2 - t1,
            kernel_load_s=kernel_load_s, groups=len(self.groups) if self.groups is not None else 0,
            instances=len(self.instances) if self.instances is not None else 0, placed_triangles=placed)

    @property
    def instanced(self) -> bool:
        """Whether this is a two-level BVH over instances (build_instanced)."""
        return self.instances is not None

    @property
    def auto_choices(self) -> dict:
        """auto's decisions: auto.choice_key -> {"mode", "reason", "seconds", "sample_rays"}."""
        return self.auto.choices

    def check(self) -> None:
        """Raise AssertionError if a layout invariant is broken (see layout.check_layout)."""
        if self.instanced:
            check_instanced(self.parts, self.groups, self.instances)
        elif self.layout is not None:
            check_layout(self.layout, len(self.faces))

    # -- tracing ---------------------------------------------------------------------------------
    def _trace_batch(self, batch: RayBatch, mode: str, any_hit: bool, count_work: bool):
        return _trace(self.m, self.device, batch, mode=mode, any_hit=any_hit, tail_rays=self.tail_rays,
                      count_work=count_work, tail_fraction=self.tail_fraction, tail_steps=self.tail_steps)

    def _run(self, origins, directions, tmax, active, mode, any_hit, count_work, hint):
        if mode not in TRACE_MODES:
            raise ValueError(f"mode must be one of {', '.join(TRACE_MODES)}; got {mode!r}")
        batch = ray_batch(self.m, self.backend, origins, directions, tmax, active)
        n = batch.n
        t0 = time.perf_counter()
        chosen = None
        if mode == AUTO:
            def timed_trace(sample, m):
                res, _ = self._trace_batch(sample, m, any_hit, False)
                dr.eval(res.t, res.prim)
            chosen = mode = "per_ray" if self.device is None else self.auto.decide(
                timed_trace, batch, self.batch_rays, any_hit, hint, self.stats.treelets)
        if self.device is None or n == 0:
            res, st = Results(self.m, n, self.instanced), TraceStats(mode=mode, rays=n)
        elif n <= self.batch_rays:
            res, st = self._trace_batch(batch, mode, any_hit, count_work)
        else:
            res, st = self._run_batches(batch, mode, any_hit, count_work)
        if count_work:
            st.finish({name: int(dr.sum(w)[0]) if n else 0 for name, w in res.work.items()})
        st.time_total_s = time.perf_counter() - t0
        if chosen is not None:
            st.mode = f"{AUTO}:{chosen}"
        return batch, res, st

    def _run_batches(self, batch: RayBatch, mode, any_hit, count_work):
        """Trace `batch_rays` rays at a time: the work arrays (entry stacks, queues, ray state
        copies) scale with the batch, not with the ray count, so peak memory is bounded."""
        m, n = self.m, batch.n
        res, st = Results(m, n, self.instanced), TraceStats(mode=mode, rays=n, batches=0)
        for start in range(0, n, self.batch_rays):
            idx = dr.arange(m.UInt32, start, min(n, start + self.batch_rays))
            part, part_st = self._trace_batch(batch.take(idx), mode, any_hit, count_work)
            res.place(part, idx)
            dr.eval(*res.arrays())
            st.absorb(part_st)
        return res, st

    def trace(self, origins, directions, tmax=None, mode="layer_sorted", stats=True, hint="", active=None) -> Hits:
        """Closest hits at 0 < t < tmax (default inf) of the rays origins + t directions.

        Inputs are Dr.Jit arrays (results come back as Dr.Jit arrays) or numpy; each has one
        entry per ray or one for all (see inputs.ray_batch). Rays where `active` is False are
        misses. With stats=False the kernels skip the work counters (hits.stats then holds steps
        and times only). `mode="auto"` picks per batch (auto.AutoPolicy); `hint` names the kind
        of rays (e.g. 'camera', 'bounce') so auto decides for each kind apart."""
        batch, res, st = self._run(origins, directions, tmax, active, mode, False, stats, hint)
        back = batch.to_caller
        work = {k: back(w) for k, w in res.work.items()} if stats else None
        inst = None if res.inst is None else back(res.inst)
        if st.rays == 0:  # empty arrays as they are (Dr.Jit cannot compare them with a literal)
            return Hits(t=back(res.t), prim=back(res.prim), u=back(res.u), v=back(res.v), stats=st, work=work,
                        instance=inst)
        hit = res.prim != MISS
        t = dr.select(hit, res.t, dr.inf)  # a ray that finished without a hit carries its tmax
        return Hits(t=back(t), prim=back(res.prim), u=back(res.u), v=back(res.v), stats=st, work=work, instance=inst)

    def occluded(self, origins, directions, tmax=None, mode="layer_sorted", stats=True, hint="",
                 active=None) -> Occlusion:
        """Any hit at 0 < t < tmax (the traversal stops at the first one); inputs as in `trace`."""
        batch, res, st = self._run(origins, directions, tmax, active, mode, True, stats, hint)
        occ = res.prim != MISS if st.rays else dr.zeros(self.m.Bool, 0)
        work = {k: batch.to_caller(w) for k, w in res.work.items()} if stats else None
        return Occlusion(occluded=batch.to_caller(occ), stats=st, work=work)

    # -- tracing inside the caller's kernel ------------------------------------------------------
    def trace_inline(self, origins, directions, tmax, active, any_hit: bool = False) -> Hits:
        """per_ray closest (or any) hits with no host synchronisation, so the call can sit inside
        the caller's symbolic loop and compile into the caller's kernel (a renderer's bounce
        loop as one megakernel). Inputs are Dr.Jit arrays of this BVH's backend, one ray per
        lane; nothing is evaluated, batched or counted (hits.stats is None); inactive lanes miss."""
        m = self.m
        o, d = [m.Float(c) for c in origins], [m.Float(c) for c in directions]
        tmax, active = m.Float(tmax), m.Bool(active)
        n = max(dr.width(x) for x in (*o, *d, tmax, active))
        if self.device is None:
            return Hits(t=dr.full(m.Float, dr.inf, n), prim=dr.full(m.UInt32, MISS, n), u=dr.zeros(m.Float, n),
                        v=dr.zeros(m.Float, n), stats=None,
                        instance=dr.full(m.UInt32, MISS, n) if self.instanced else None)
        out = trace_inline(m, self.device, o, d, tmax, active, any_hit=any_hit)
        hit = out.prim != MISS
        return Hits(t=dr.select(hit, out.t, dr.inf), prim=out.prim, u=out.u, v=out.v, stats=None, instance=out.hit_inst)


def build(vertices, faces, treelet_height: int = DEFAULT_TREELET_HEIGHT, leaf_size: int | None = None,
          backend: str | None = None,
          batch_rays: int = BATCH_RAYS, tail_rays: int = TAIL_RAYS, auto_policy: AutoPolicy | None = None,
          tail_fraction: float = TAIL_FRACTION, branching: int = DEFAULT_BRANCHING,
          tail_steps: int = TAIL_STEPS) -> LayerBVH:
    """Build a Layer BVH over a triangle mesh: vertices (V, 3) float, faces (F, 3) int.
    `branching` (2, 4, 8): children per inner node; `leaf_size`: triangles per leaf at most
    (default: inputs.default_leaf_size of the branching); `batch_rays` bounds how many rays one trace
    call processes at once (peak memory)."""
    return LayerBVH(vertices, faces, treelet_height=treelet_height, leaf_size=leaf_size, backend=backend,
                    batch_rays=batch_rays, tail_rays=tail_rays, auto_policy=auto_policy, tail_fraction=tail_fraction,
                    branching=branching, tail_steps=tail_steps)


def build_instanced(groups: list[Group], instances: list[Instance], treelet_height: int = DEFAULT_TREELET_HEIGHT,
                    leaf_size: int | None = None, backend: str | None = None, batch_rays: int = BATCH_RAYS,
                    tail_rays: int = TAIL_RAYS, auto_policy: AutoPolicy | None = None,
                    tail_fraction: float = TAIL_FRACTION, branching: int = DEFAULT_BRANCHING,
                    tail_steps: int = TAIL_STEPS) -> LayerBVH:
    """Build a two-level Layer BVH: each group's mesh (layerbvh.Group) gets its own BVH, stored
    once however many instances (layerbvh.Instance: group index, object -> world affine map)
    place it, under a top-level BVH over the instances' world boxes (layerbvh.instances).
    Memory grows with the unique triangles plus 64 bytes and about two nodes per instance. Hits
    report the instance and the primitive inside its group; ties in t go to the lower instance
    index, then the lower primitive id, in every mode."""
    return LayerBVH(None, None, treelet_height=treelet_height, leaf_size=leaf_size, backend=backend,
                    batch_rays=batch_rays, tail_rays=tail_rays, auto_policy=auto_policy, tail_fraction=tail_fraction,
                    groups=groups, instances=instances, branching=branching, tail_steps=tail_steps)
