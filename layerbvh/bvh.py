"""The public LayerBVH object: build once, then trace closest hits or test occlusion in any mode."""
from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import numpy as np

from . import backend as be
from .layout import TRI_FLOATS, LayerLayout, check_layout, to_layer_layout
from .sah import BinaryBVH, build_binned_sah, triangle_bounds
from .stats import TraceStats
from .validate import check_mesh, check_param
from .walk import NO_HIT, DeviceLayout
from .wavefront import MODES, TAIL_RAYS, Results, trace as _trace

MISS = 0xFFFFFFFF
# Rays traced per batch. The layer modes' work memory is about batch x (tree depth x 8 B of
# entry stack + 2 x 76 B of ray state + 40 B in/out); 1M rays of a depth-40 tree: ~550 MB.
BATCH_RAYS = 1 << 20
AUTO = "auto"
TRACE_MODES = MODES + (AUTO,)
# auto: below this many rays a batch goes per_ray without asking (a few rays per treelet cannot
# repay a sort and a launch per step); above it the first batch of each size class is timed both
# ways on a whole batch (up to batch_rays of its rays: sorting pays off with the number of rays
# per treelet, so a smaller sample would favour per_ray) and the faster mode is kept.
AUTO_MIN_RAYS = 1 << 16
AUTO_WARMUP_RAYS = 4096  # compiles both modes' kernels before anything is timed
AUTO_ROUNDS = 3  # timed rounds, alternating which mode goes first; the median decides
AUTO_MARGIN = 0.05  # layer_sorted must be this much faster: it also needs far more memory


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



def _width(x) -> int:
    return dr.width(x) if be.backend_of(x) is not None else len(x)


def _column(x, name: str, backend: str):
    """One per-ray float input as a Dr.Jit Float (any width) or a 1-D float32 numpy array."""
    kind = be.backend_of(x)
    if kind is not None:
        if kind != backend:
            raise ValueError(f"{name} is on the {kind} backend, this BVH on {backend}")
        return be.module(backend).Float(x)
    a = np.asarray(x, np.float32)
    if a.ndim > 1:
        raise ValueError(f"{name} must be a scalar or have shape (N,), got {a.shape}")
    return a.reshape(-1)


def _components(x, name: str, backend: str) -> list:
    """The three components of origins or directions: a Dr.Jit 3-vector (components of any
    width), or numpy of shape (N, 3) or (3,)."""
    if be.backend_of(x) is not None:
        if len(x) != 3:
            raise ValueError(f"{name} must have 3 components, got {len(x)}")
        return [_column(x[c], f"{name}[{c}]", backend) for c in range(3)]
    a = np.asarray(x, np.float32)
    if a.shape == (3,):
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return [np.ascontiguousarray(a[:, c]) for c in range(3)]


def _broadcast(m, x, n: int):
    """A Dr.Jit Float of width n from a column of width n or 1."""
    if be.backend_of(x) is None:
        x = m.Float(x)
    if dr.width(x) == n:
        return x
    return dr.gather(m.Float, x, dr.zeros(m.UInt32, n))


@dataclass
class Hits:
    """Closest hits, in the caller's array kind. Miss: t = inf, prim = 0xFFFFFFFF.
    p = (1-u-v)*p0 + u*p1 + v*p2 with p0, p1, p2 the vertices of faces[prim]."""

    t: object
    prim: object
    u: object
    v: object
    stats: TraceStats


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
    kernel_load_s: float = 0.0  # first build in a process: compiling/loading the builder's kernels

    @property
    def total_bytes(self) -> int:
        return sum(self.bytes.values())


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
    def _rays(self, origins, directions, tmax):
        """Rays as (o, d, tmax, valid) Dr.Jit arrays of one common width n, and a function turning
        results back into the input's kind (Dr.Jit if origins or directions are, else numpy).

        Every input is broadcast to the ray count: a width-1 Dr.Jit array (Mitsuba's camera rays
        carry `maxt` as one, a broadcast scalar), a numpy (3,) point or vector, a Python scalar.
        The batching path gathers each input per ray, so a width-1 array left as it is would
        be read out of bounds for every ray but the first. Any other width than 1 or n is a
        ValueError naming the argument and both widths."""
        m = self.m
        parts = {"origins": _components(origins, "origins", self.backend),
                 "directions": _components(directions, "directions", self.backend)}
        if tmax is not None:
            parts["tmax"] = [_column(tmax, "tmax", self.backend)]
        n = max(_width(x) for xs in parts.values() for x in xs)
        if any(_width(x) == 0 for xs in parts.values() for x in xs):
            n = 0  # an empty input is an empty batch (a width-1 input does not make it one ray)
        for name, xs in parts.items():
            for c, x in enumerate(xs):
                w = _width(x)
                if w not in (1, n):
                    comp = f"{name}[{c}]" if name != "tmax" else name
                    raise ValueError(f"{comp} has {w} entries, the other ray inputs {n}: each input must have "
                                     f"one entry per ray or a single one for all rays")
        bcast = (lambda x: _broadcast(m, x, n))
        oj = [bcast(x) for x in parts["origins"]]
        dj = [bcast(x) for x in parts["directions"]]
        tm = bcast(parts["tmax"][0]) if "tmax" in parts else dr.full(m.Float, dr.inf, n)
        on_device = be.backend_of(origins) is not None or be.backend_of(directions) is not None

        def back(x):
            return x if on_device else x.numpy()
        if n == 0:  # Dr.Jit compares a 0-sized array with a literal as a size mismatch
            return oj, dj, tm, dr.zeros(m.Bool, 0), n, back
        finite = dr.isfinite(oj[0]) & dr.isfinite(oj[1]) & dr.isfinite(oj[2])
        finite &= dr.isfinite(dj[0]) & dr.isfinite(dj[1]) & dr.isfinite(dj[2])
        nonzero = (dj[0] != 0) | (dj[1] != 0) | (dj[2] != 0)
        valid = finite & nonzero & ~dr.isnan(tm) & (tm > 0)
        return oj, dj, tm, valid, n, back

    def _auto_mode(self, oj, dj, tm, valid, n, any_hit, hint) -> str:
        """The faster of per_ray and layer_sorted for this kind of batch, measured once per
        (closest/any hit, caller's hint such as 'camera', size class = bit length of the ray count).

        Timing both on real rays captures what a rule cannot: scene size against the caches,
        ray coherence, CPU or GPU. Hits do not depend on the choice (every mode is exact and
        breaks ties by primitive id), only the time does."""
        k = min(n, self.batch_rays)  # what one traced batch holds
        if self.device is None or k < AUTO_MIN_RAYS or self.stats.treelets <= 1:
            return "per_ray"
        key = ("any_hit" if any_hit else "closest_hit", hint, k.bit_length())
        known = self.auto_choices.get(key)
        if known is not None:
            return known["mode"]

        def leading(count):  # the first rays: neighbours, as in the batch itself
            idx = dr.arange(self.m.UInt32, count)
            take = (lambda x: dr.gather(type(x), x, idx))
            return [take(c) for c in oj], [take(c) for c in dj], take(tm), take(valid)

        def timed(sample, mode):
            dr.sync_thread()
            t0 = time.perf_counter()
            res, _ = _trace(self.m, self.device, *sample, mode, any_hit, self.tail_rays, count_work=False)
            dr.eval(res.t, res.tri)
            dr.sync_thread()
            return time.perf_counter() - t0

        warm, batch = leading(min(k, AUTO_WARMUP_RAYS)), leading(k)
        for mode in ("per_ray", "layer_sorted"):  # compiles the kernels; not counted
            timed(warm, mode)
        runs = {"per_ray": [], "layer_sorted": []}
        for rep in range(AUTO_ROUNDS):  # alternate the order so drifts hit both alike
            for mode in (("per_ray", "layer_sorted") if rep % 2 == 0 else ("layer_sorted", "per_ray")):
                runs[mode].append(timed(batch, mode))
        seconds = {mode: float(np.median(t)) for mode, t in runs.items()}
        choice = "layer_sorted" if seconds["layer_sorted"] < (1 - AUTO_MARGIN) * seconds["per_ray"] else "per_ray"
        self.auto_choices[key] = {"mode": choice, "seconds": seconds, "sample_rays": k}
        return choice

    def _run(self, origins, directions, tmax, mode, any_hit, stats=True, hint=""):
        if mode not in TRACE_MODES:
            raise ValueError(f"mode must be one of {', '.join(TRACE_MODES)}; got {mode!r}")
        oj, dj, tm, valid, n, back = self._rays(origins, directions, tmax)
        m = self.m
        t0 = time.perf_counter()
        chosen = None
        if mode == AUTO:
            chosen = mode = self._auto_mode(oj, dj, tm, valid, n, any_hit, hint)
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
