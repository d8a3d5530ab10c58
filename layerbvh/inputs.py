"""What the engine takes in: meshes, parameters and rays checked (bad input is a ValueError naming what is wrong),
rays as a RayBatch."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from . import backend as be
from .layout import BRANCHINGS, MAX_TRIANGLES


def _first_bad_row(mask: np.ndarray) -> int:
    return int(np.nonzero(mask.reshape(len(mask), -1).any(axis=1))[0][0])


def check_mesh(vertices, faces, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """(float32 (V, 3) vertices, int64 (F, 3) faces), or a ValueError naming `name` and the bad row."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name}: faces must have shape (F, 3), got {f.shape}")
    if not np.issubdtype(v.dtype, np.number):
        raise ValueError(f"{name}: vertices must be numeric, got dtype {v.dtype}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        if np.issubdtype(f.dtype, np.floating) and np.all(np.mod(f, 1) == 0):
            f = f.astype(np.int64)
        else:
            raise ValueError(f"{name}: faces must be integer vertex indices, got dtype {f.dtype}")
    v = v.astype(np.float32)
    bad = ~np.isfinite(v)
    if bad.any():
        i = _first_bad_row(bad)
        raise ValueError(f"{name}: vertices[{i}] = {v[i].tolist()} is not finite "
                         f"({int(bad.any(axis=1).sum())} non-finite vertices)")
    f = f.astype(np.int64)
    if f.size:
        if (f < 0).any():
            i = _first_bad_row(f < 0)
            raise ValueError(f"{name}: faces[{i}] = {f[i].tolist()} has a negative vertex index")
        if (f >= len(v)).any():
            i = _first_bad_row(f >= len(v))
            raise ValueError(f"{name}: faces[{i}] references vertex {int(f[i].max())}, only {len(v)} vertices")
    if len(f) > MAX_TRIANGLES:
        raise ValueError(f"{name}: {len(f):,} triangles; a Layer BVH addresses at most {MAX_TRIANGLES:,}")
    return v, f


# Defaults of the build parameters (PERFORMANCE.md entry 20: h = 8 was the best treelet height
# of both per_ray and the layer modes across the benchmark's ray sets).
DEFAULT_TREELET_HEIGHT = 8
DEFAULT_LEAF_SIZE = 4  # the binary BVH's
# Children per inner node (layout.BRANCHINGS: 2, the paper's binary BVH, or 4, 8 collapsed
# from it); the default is the fastest measured (PERFORMANCE.md entry 27).
DEFAULT_BRANCHING = 4
# A wide BVH is collapsed from a binary tree with smaller leaves: the collapse cannot open a
# leaf, so smaller leaves fill its nodes, and a triangle costs a loop iteration while a node
# visit costs one for all its children (PERFORMANCE.md entry 27: leaves of 2 were fastest for
# 4 and 8 children, leaves of 4 for the binary tree).
WIDE_LEAF_SIZE = 2


def default_leaf_size(branching: int) -> int:
    """The leaf size a BVH of `branching` children per node is built with unless one is given."""
    return DEFAULT_LEAF_SIZE if branching == 2 else WIDE_LEAF_SIZE

# Bounds (inclusive) of the build and trace parameters: the one place they are defined.
PARAM_RANGES = {
    "treelet_height": (1, 64),   # levels per treelet; the BVH is at most sah.MAX_DEPTH deep
    "leaf_size": (1, 16),        # triangles per leaf at most (a leaf link holds counts up to 31)
    "batch_rays": (1, 1 << 31),  # rays per traced batch (work memory)
    "tail_rays": (0, 1 << 31),   # rays left when the layer modes finish with one per-ray kernel
    "tail_steps": (1, 1 << 16),  # wavefront steps after which they do, however many rays are left
}


def check_param(name: str, value) -> int:
    """`value` as an int if it is an integer within PARAM_RANGES[name] (branching: one of
    layout.BRANCHINGS), else a ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if name == "branching":
        if value not in BRANCHINGS:
            raise ValueError(f"branching must be one of {', '.join(map(str, BRANCHINGS))}, got {value}")
        return int(value)
    lo, hi = PARAM_RANGES[name]
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value}")
    return int(value)


def _width(x) -> int:
    return dr.width(x) if be.backend_of(x) is not None else len(x)


def _column(x, name: str, backend: str, kind: str = "Float"):
    """One per-ray input as a Dr.Jit array of `kind` (any width) or a 1-D numpy array."""
    on = be.backend_of(x)
    if on is not None:
        if on != backend:
            raise ValueError(f"{name} is on the {on} backend, this BVH on {backend}")
        return getattr(be.module(backend), kind)(x)
    a = np.asarray(x, np.float32 if kind == "Float" else bool)
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


def _name(arg: str, c: int, x, xs, given) -> str:
    """How an error names one input column: `origins[1]` for a component of a Dr.Jit vector."""
    return f"{arg}[{c}]" if len(xs) > 1 and be.backend_of(given) is not None else arg


def _broadcast(m, x, n: int):
    """A Dr.Jit array of width n from a column of width n or 1."""
    if be.backend_of(x) is None:
        x = be.from_numpy(m.Float if x.dtype == np.float32 else m.Bool, x)
    if dr.width(x) == n:
        return x
    return dr.gather(type(x), x, dr.zeros(m.UInt32, n))


@dataclass
class RayBatch:
    """Rays ready for the traversal: Dr.Jit arrays of one width on the BVH's backend.

    `valid` is False for rays that are misses without tracing: inactive (the caller's mask),
    NaN/Inf origin or direction, zero direction, tmax NaN or <= 0. `on_device` says whether the
    caller passed Dr.Jit arrays (results go back as Dr.Jit arrays) or numpy."""

    o: list
    d: list
    tmax: object
    valid: object
    on_device: bool

    @property
    def n(self) -> int:
        return dr.width(self.tmax)

    def take(self, idx) -> "RayBatch":
        """The rays `idx` (a sub-batch), as a new batch."""
        g = (lambda x: dr.gather(type(x), x, idx))
        return RayBatch([g(c) for c in self.o], [g(c) for c in self.d], g(self.tmax), g(self.valid), self.on_device)

    def to_caller(self, x):
        """A result array in the caller's kind: Dr.Jit as it is, else numpy."""
        return x if self.on_device else x.numpy()


def ray_batch(m, backend: str, origins, directions, tmax=None, active=None) -> RayBatch:
    """The caller's rays as a RayBatch of one common width n.

    Every input is broadcast to the ray count: a width-1 Dr.Jit array (Mitsuba's camera rays
    carry `maxt` as one, a broadcast scalar), a numpy (3,) point or vector, a Python scalar.
    The batching path gathers each input per ray, so a width-1 array left as it is would
    be read out of bounds for every ray but the first. Any other width than 1 or n is a
    ValueError naming the argument and both widths."""
    parts = {"origins": _components(origins, "origins", backend),
             "directions": _components(directions, "directions", backend)}
    if tmax is not None:
        parts["tmax"] = [_column(tmax, "tmax", backend)]
    if active is not None:
        parts["active"] = [_column(active, "active", backend, "Bool")]
    named = [(_name(k, c, x, xs, origins if k == "origins" else directions), _width(x))
             for k, xs in parts.items() for c, x in enumerate(xs)]
    n = 0 if any(w == 0 for _, w in named) else max(w for _, w in named)  # empty input: empty batch
    longest = next(name for name, w in named if w == n)
    for name, w in named:
        if w not in (1, n):
            raise ValueError(f"{name} has {w} entries, {longest} has {n}: each ray input needs one entry per ray "
                             f"or a single one for all rays")
    o = [_broadcast(m, x, n) for x in parts["origins"]]
    d = [_broadcast(m, x, n) for x in parts["directions"]]
    tm = _broadcast(m, parts["tmax"][0], n) if "tmax" in parts else dr.full(m.Float, dr.inf, n)
    on_device = be.backend_of(origins) is not None or be.backend_of(directions) is not None
    if n == 0:  # Dr.Jit compares a 0-sized array with a literal as a size mismatch
        return RayBatch(o, d, tm, dr.zeros(m.Bool, 0), on_device)
    finite = dr.isfinite(o[0]) & dr.isfinite(o[1]) & dr.isfinite(o[2])
    finite &= dr.isfinite(d[0]) & dr.isfinite(d[1]) & dr.isfinite(d[2])
    nonzero = (d[0] != 0) | (d[1] != 0) | (d[2] != 0)
    valid = finite & nonzero & ~dr.isnan(tm) & (tm > 0)
    if "active" in parts:
        valid &= _broadcast(m, parts["active"][0], n)
    # Evaluated together, in one kernel: the traversal gathers each column separately (batches,
    # ray records), and Dr.Jit evaluates a gather's unevaluated source on its own, so a caller's
    # lazy rays (a renderer's shading) were computed once per column, each a kernel of its own
    # to compile (issue 39: 3 of every 4 kernels of a counted render were such repeats).
    dr.eval(o, d, tm, valid)
    return RayBatch(o, d, tm, valid, on_device)
