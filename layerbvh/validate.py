"""Input checks that turn bad meshes, rays and parameters into ValueErrors naming what is wrong."""
from __future__ import annotations

import numpy as np


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
