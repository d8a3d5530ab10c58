"""Shared fixtures: the meshes the engine is tested on. numpy and layerbvh only (no Mitsuba): the
engine's tests (tests/engine) run without Mitsuba installed; tests/runtime/conftest.py and
tests/tools/conftest.py set Mitsuba's variant for theirs."""
from __future__ import annotations

import os
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


# Dr.Jit keeps the kernels it compiled in $HOME/.drjit (no other setting in drjit 1.5.0). A test
# that runs a process with a HOME of its own (pytester does, to keep the user's configuration
# out; others to isolate our own caches) would compile every kernel again there, each run: the
# warm suite's kernel census found ~17 s of LLVM compiling in pytester's runs alone. Such a HOME
# gets a link to the suite's kernel cache instead (compiled kernels do not depend on what the
# tests isolate). Taken here, before any test changes HOME.
DRJIT_KERNEL_CACHE = Path.home() / ".drjit"


@pytest.fixture(scope="session")
def share_kernel_cache():
    """share_kernel_cache(home): `home`/.drjit becomes a link to the suite's Dr.Jit kernel cache."""
    def link(home) -> None:
        target = Path(home) / ".drjit"
        if not target.exists() and not target.is_symlink():
            DRJIT_KERNEL_CACHE.mkdir(exist_ok=True)
            target.symlink_to(DRJIT_KERNEL_CACHE, target_is_directory=True)
    return link


# The tests running now, kept in the file scripts/test.sh names, which prints them if it has to
# stop a run that hangs (issue 39). Kept by the controller alone (xdist relays each worker's test
# starts and ends to it), written then renamed: never read half-written.
_RUNNING_FILE = os.environ.get("LAYERBVH_RUNNING_TESTS")
_running: dict[str, None] = {}


def _write_running() -> None:
    if _RUNNING_FILE and not os.environ.get("PYTEST_XDIST_WORKER"):
        tmp = f"{_RUNNING_FILE}.tmp"
        Path(tmp).write_text("".join(f"{nodeid}\n" for nodeid in _running))
        os.replace(tmp, _RUNNING_FILE)


def pytest_runtest_logstart(nodeid, location):
    _running[nodeid] = None
    _write_running()


def pytest_runtest_logfinish(nodeid, location):
    _running.pop(nodeid, None)
    _write_running()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    yield
    # The kernel census (LAYERBVH_KERNEL_CENSUS, scripts/kernel_census.py): what this test and its
    # fixtures compiled, recorded while PYTEST_CURRENT_TEST still names it.
    from layerbvh import kernel_census
    kernel_census.flush()
