"""Input checks that turn bad meshes, rays and parameters into ValueErrors naming what is wrong."""
from __future__ import annotations

import drjit as dr
import numpy as np

from . import backend as be


def _first_bad_row(mask: np.ndarray) -> int:
    return int(np.nonzero(mask.reshape(len(mask), -1).any(axis=1))[0][0])


def check_mesh(vertices, faces, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
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
    return v, f


def check_param(name: str, value, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value}")
    return int(value)


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


def rays(m, backend: str, origins, directions, tmax):
    """Rays as (o, d, tmax, valid) Dr.Jit arrays of one common width n, and a function turning
    results back into the input's kind (Dr.Jit if origins or directions are, else numpy).

    Every input is broadcast to the ray count: a width-1 Dr.Jit array (Mitsuba's camera rays
    carry `maxt` as one, a broadcast scalar), a numpy (3,) point or vector, a Python scalar.
    The batching path gathers each input per ray, so a width-1 array left as it is would
    be read out of bounds for every ray but the first. Any other width than 1 or n is a
    ValueError naming the argument and both widths."""
    parts = {"origins": _components(origins, "origins", backend),
             "directions": _components(directions, "directions", backend)}
    if tmax is not None:
        parts["tmax"] = [_column(tmax, "tmax", backend)]
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
