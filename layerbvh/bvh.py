"""The public LayerBVH object: build once, then trace closest hits or test occlusion in any mode."""
from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import numpy as np

from . import backend as be
from .auto import auto_mode
from .inputs import check_mesh, check_param, rays as _ray_inputs
from .layout import TRI_FLOATS, DeviceLayout, LayerLayout, check_layout, to_layer_layout
from .sah import BinaryBVH, build_binned_sah, triangle_bounds
from .state import NO_HIT, Results
from .stats import BVHStats, TraceStats
from .wavefront import MODES, TAIL_RAYS, trace as _trace

MISS = 0xFFFFFFFF
# Rays traced per batch. The layer modes' work memory is about batch x (tree depth x 8 B of
# entry stack + 2 x 76 B of ray state + 40 B in/out); 1M rays of a depth-40 tree: ~550 MB.
BATCH_RAYS = 1 << 20
AUTO = "auto"
TRACE_MODES = MODES + (AUTO,)


_builder_ready = False


def _load_builder_kernels() -> float:
    """Compile the builder's and the layout's numba kernels (or load them from numba's on-disk
    cache) by building a tiny mesh; the seconds it took, 0.0 once done in this process. Kept
    out of the build time, as Dr.Jit's kernel compilation is kept out of trace times."""
    global _builder_ready
    if _builder_ready:
        return 0.0
    t0 = time.perf_counter()
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3], [0, 1, 2], [0, 2, 3]], np.int64)
    to_layer_layout(build_binned_sah(*triangle_bounds(v, f), 1), v, f, 1)
    _builder_ready = True
    return time.perf_counter() - t0



@dataclass
class Hits:
    """Closest hits, in the caller's array kind. Miss: t = inf, prim = 0xFFFFFFFF.
    p = (1-u-v)*p0 + u*p1 + v*p2 with p0, p1, p2 the vertices of faces[prim]."""

    t: object
    prim: object
    u: object
    v: object
    stats: TraceStats


class LayerBVH:
    """A binned-SAH BVH over triangles, laid out as a Layer BVH (see layout.LayerLayout)."""

    def __init__(self, vertices, faces, treelet_height=4, leaf_size=4, backend=None, batch_rays=BATCH_RAYS):
        treelet_height = check_param("treelet_height", treelet_height, 1, 64)
        self.batch_rays = check_param("batch_rays", batch_rays, 1, 1 << 31)
        leaf_size = check_param("leaf_size", leaf_size, 1, 64)
        v, f = check_mesh(vertices, faces)
        self.vertices, self.faces = v, f
        self.backend = backend or be.default_backend()
        self.tail_rays = TAIL_RAYS
        self.auto_choices = {}  # (query, hint, size class) -> {"mode", "seconds"}: auto's decisions
        self.m = be.module(self.backend)
        kernel_load_s = _load_builder_kernels() if len(f) else 0.0
        t0 = time.perf_counter()
        self.binary: BinaryBVH | None = build_binned_sah(*triangle_bounds(v, f), leaf_size) if len(f) else None
        t1 = time.perf_counter()
        self.layout: LayerLayout | None = to_layer_layout(self.binary, v, f, treelet_height) if len(f) else None
        t2 = time.perf_counter()
        lay = self.layout
        m = self.m
        self.device = None if lay is None else DeviceLayout(
            nodes=m.Float(lay.nodes), leaves=m.UInt32(lay.leaves), tris=m.Float(lay.tris),
            treelet_first=m.UInt32(lay.treelet_first), node_treelet=m.UInt32(lay.node_treelet),
            leaf_treelet=m.UInt32(lay.leaf_treelet), depth=lay.depth, height=lay.height,
            treelet_count=lay.treelet_count)
        self.stats = BVHStats(
            triangles=len(f), nodes=lay.node_count if lay else 0, leaves=lay.leaf_count if lay else 0,
            treelets=lay.treelet_count if lay else 0, depth=lay.depth if lay else 0,
            treelet_height=treelet_height, leaf_size=leaf_size,
            treelet_node_counts=lay.treelet_node_counts.tolist() if lay else [],
            bytes=lay.array_bytes() if lay else {}, build_s=t1 - t0, layout_s=t2 - t1,
            kernel_load_s=kernel_load_s)

    def check(self) -> None:
        """Raise AssertionError if a layout invariant is broken (see layout.check_layout)."""
        if self.layout is not None:
            check_layout(self.layout, len(self.faces))

    # -- tracing ---------------------------------------------------------------------------------
    def _run(self, origins, directions, tmax, mode, any_hit, stats=True, hint=""):
        if mode not in TRACE_MODES:
            raise ValueError(f"mode must be one of {', '.join(TRACE_MODES)}; got {mode!r}")
        oj, dj, tm, valid, n, back = _ray_inputs(self.m, self.backend, origins, directions, tmax)
        m = self.m
        t0 = time.perf_counter()
        chosen = None
        if mode == AUTO:
            chosen = mode = auto_mode(self, oj, dj, tm, valid, n, any_hit, hint)
        if self.device is None or n == 0:
            res, st = Results(m, n), TraceStats(mode=mode, rays=n)
        elif n <= self.batch_rays:
            res, st = _trace(m, self.device, oj, dj, tm, valid, mode, any_hit, self.tail_rays, count_work=stats)
        else:
            res, st = self._run_batches(oj, dj, tm, valid, mode, any_hit, stats)
        if stats:
            st.finish(*(int(dr.sum(w)[0]) if n else 0 for w in res.work))
        st.time_total_s = time.perf_counter() - t0
        if chosen is not None:
            st.mode = f"{AUTO}:{chosen}"
        return res, st, back

    def _run_batches(self, oj, dj, tm, valid, mode, any_hit, stats):
        """Trace `batch_rays` rays at a time: the work arrays (entry stacks, queues, ray state
        copies) scale with the batch, not with the ray count, so peak memory is bounded."""
        m, n = self.m, dr.width(tm)
        res, st = Results(m, n), TraceStats(mode=mode, rays=n, batches=0)
        for start in range(0, n, self.batch_rays):
            idx = dr.arange(m.UInt32, start, min(n, start + self.batch_rays))
            take = (lambda x: dr.gather(type(x), x, idx))
            part, part_st = _trace(m, self.device, [take(c) for c in oj], [take(c) for c in dj], take(tm),
                                   take(valid), mode, any_hit, self.tail_rays, count_work=stats)
            res.place(part, idx)
            dr.eval(res.t, res.u, res.v, res.tri, res.work)
            st.absorb(part_st)
        return res, st

    def trace(self, origins, directions, tmax=None, mode="layer_sorted", stats=True, hint="") -> Hits:
        """Closest hits. With stats=False the kernels skip the work counters (hits.stats then
        holds steps and times only). `mode="auto"` picks per batch (see _auto_mode); `hint`
        names the kind of rays (e.g. 'camera', 'bounce') so auto decides for each kind apart."""
        res, stats, back = self._run(origins, directions, tmax, mode, any_hit=False, stats=stats, hint=hint)
        m = self.m
        if stats.rays == 0:  # empty arrays as they are (Dr.Jit cannot compare them with a literal)
            return Hits(t=back(res.t), prim=back(res.tri), u=back(res.u), v=back(res.v), stats=stats)
        hit = res.tri != NO_HIT
        prim = dr.full(m.UInt32, MISS, dr.width(hit))
        if self.device is not None:
            # Hits hold the leaf-order triangle; its record carries the original face index.
            face = dr.reinterpret_array(m.UInt32, dr.gather(m.Float, self.device.tris, res.tri * TRI_FLOATS + 9, hit))
            prim = dr.select(hit, face, prim)
        t = dr.select(hit, res.t, dr.inf)
        u = dr.select(hit, res.u, 0.0)
        v = dr.select(hit, res.v, 0.0)
        return Hits(t=back(t), prim=back(prim), u=back(u), v=back(v), stats=stats)

    def occluded(self, origins, directions, tmax=None, mode="layer_sorted", stats=True, hint=""):
        """True for rays with any hit at 0 < t < tmax (the traversal stops at the first one)."""
        res, stats, back = self._run(origins, directions, tmax, mode, any_hit=True, stats=stats, hint=hint)
        self.last_occluded_stats = stats
        return back(res.tri != NO_HIT if stats.rays else dr.zeros(self.m.Bool, 0))


def build(vertices, faces, treelet_height: int = 4, leaf_size: int = 4, backend: str | None = None,
          batch_rays: int = BATCH_RAYS) -> LayerBVH:
    """Build a Layer BVH over a triangle mesh: vertices (V, 3) float, faces (F, 3) int.
    `batch_rays` bounds how many rays one trace call processes at once (peak memory)."""
    return LayerBVH(vertices, faces, treelet_height=treelet_height, leaf_size=leaf_size, backend=backend,
                    batch_rays=batch_rays)
