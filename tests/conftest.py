"""Shared fixtures: meshes the engine is tested on and Embree (stock Mitsuba) as ground truth."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from layerbvh_mitsuba.bench import meshes  # noqa: E402
from layerbvh_mitsuba.repo import SCENES  # noqa: E402

BUNNY = SCENES / "meshes" / "bunny.ply"


@pytest.fixture(scope="session")
def bunny():
    mesh = mi.load_dict({"type": "ply", "filename": str(BUNNY)})
    v = np.array(mesh.vertex_positions_buffer()).reshape(-1, 3)
    f = np.array(mesh.faces_buffer()).reshape(-1, 3).astype(np.int64)
    return v, f


@pytest.fixture(scope="session")
def procedural():
    """At least 100k triangles of overlapping tessellated spheres (deep, overlapping boxes)."""
    v, f = meshes.procedural_mesh(120_000, seed=3)
    assert len(f) >= 100_000
    return v, f
