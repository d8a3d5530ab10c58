"""Shared fixtures: the meshes the engine is tested on. numpy and layerbvh only (no Mitsuba): the
engine's tests (tests/engine) run without Mitsuba installed; tests/runtime/conftest.py and
tests/tools/conftest.py set Mitsuba's variant for theirs."""
from __future__ import annotations

from pathlib import Path

import pytest

from layerbvh import meshes

BUNNY = Path(__file__).resolve().parents[1] / "scenes" / "meshes" / "bunny.ply"


@pytest.fixture(scope="session")
def bunny():
    """The Stanford bunny (35,947 vertices, 69,451 triangles), read by layerbvh's own PLY reader:
    the same float32 vertices and faces, bit for bit, as Mitsuba's PLY loader gives."""
    return meshes.load_mesh(BUNNY)


@pytest.fixture(scope="session")
def procedural():
    """At least 100k triangles of overlapping tessellated spheres (deep, overlapping boxes)."""
    v, f = meshes.procedural_mesh(120_000, seed=3)
    assert len(f) >= 100_000
    return v, f
