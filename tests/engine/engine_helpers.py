"""What the engine's tests (tests/engine) share with their comparisons against Embree
(tests/runtime/test_engine_vs_embree.py): test rays, a report of the rays that differ, and the
instanced forest. numpy and layerbvh only.

Imported by name (`from engine_helpers import ...`): pytest's default import mode puts this folder
on sys.path for the tests in it; tests/runtime/test_engine_vs_embree.py puts it there itself."""
from __future__ import annotations

import numpy as np
import pytest

from layerbvh import Group, Instance, meshes

N_RAYS = 40_000     # rays of a hit test on one mesh
FOREST_RAYS = 30_000  # rays of each kind through the instanced forest


def rays(v, kind, n=N_RAYS, seed=7):
    """`n` camera or incoherent rays at the mesh with vertices `v`: origins, directions (N, 3)."""
    return meshes.camera_rays(v, n, seed) if kind == "camera" else meshes.incoherent_rays(v, n, seed)


def report(mask, *cols, names=()):
    """The first 8 rays of `mask`, one line each with the value of every column."""
    idx = np.nonzero(mask)[0][:8]
    return "\n".join(f"ray {i}: " + ", ".join(f"{n}={c[i]}" for n, c in zip(names, cols)) for i in idx)


def rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def placements(n: int, groups: int, seed: int, spread: float) -> list[Instance]:
    """`n` overlapping instances: random rotation, non-uniform scale (0.5-2) and translation;
    every third one mirrored (x scaled by -1: a negative determinant flips the winding)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        m = np.eye(4)
        mirror = np.array([-1.0 if k % 3 == 2 else 1.0, 1.0, 1.0])
        m[:3, :3] = rotation(rng) @ np.diag(rng.uniform(0.5, 2.0, 3) * mirror)
        m[:3, 3] = rng.uniform(-spread, spread, 3)
        out.append(Instance(k % groups, m))
    return out


def flatten(groups, instances):
    """World-space triangles of every instance (float64 map, rounded once) and the flat id of
    (instance, prim): offset[instance] + prim."""
    vs, fs, offset, nv, nf = [], [], [], 0, 0
    for inst in instances:
        g = groups[inst.group]
        m = np.asarray(inst.to_world, np.float64)
        vs.append(g.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3])
        fs.append(np.asarray(g.faces) + nv)
        offset.append(nf)
        nv += len(g.vertices)
        nf += len(g.faces)
    return np.concatenate(vs).astype(np.float32), np.concatenate(fs), np.array(offset, np.int64)


@pytest.fixture(scope="module")
def forest(bunny):
    """The bunny and a sphere soup as two groups, 24 overlapping instances, and rays through them.
    A fixture: a test module takes it with `from engine_helpers import forest`."""
    soup_v, soup_f = meshes.procedural_mesh(8_000, seed=5)
    soup_v = (soup_v - soup_v.mean(0)) / np.abs(soup_v - soup_v.mean(0)).max() * 0.1
    groups = [Group(*bunny), Group(soup_v, soup_f)]
    instances = placements(24, 2, seed=11, spread=0.15)
    world_v, world_f, offset = flatten(groups, instances)
    o, d = meshes.incoherent_rays(world_v, FOREST_RAYS, seed=2)
    co, cd = meshes.camera_rays(world_v, FOREST_RAYS, seed=3)
    return {"groups": groups, "instances": instances, "world_v": world_v, "world_f": world_f, "offset": offset,
            "rays": {"incoherent": (o, d), "camera": (co, cd)}}
