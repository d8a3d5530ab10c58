"""The engine's tests need no Mitsuba: in a fresh process where `import mitsuba` fails, pytest collects
every test of tests/engine (the root conftest and the engine's helpers included) and a few of them pass."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENGINE = ROOT / "tests" / "engine"

# Cheap tests that build and trace: the bunny (the root conftest's PLY reader), the procedural mesh,
# Dr.Jit traversal with the engine's shared rays (engine_helpers), numba's memory model.
RUN = ("test_engine_layout.py::test_layout_invariants_bunny[4]",
       "test_engine_layout.py::test_layout_invariants_random_and_procedural[16]",
       "test_engine_batches.py::test_batch_size_is_checked",
       "test_engine_hits.py::test_modes_agree_exactly[camera-bunny]",
       "test_memmodel.py::test_coalesce_broadcast_is_one_segment")

# The child: pytest on tests/engine, the plugins that would import mitsuba (the project's pytest11
# entry point `layerbvh`) or spawn workers off. "block": mitsuba unimportable, every engine test
# collected, RUN's run; "collect": mitsuba importable, collection only (the tests there are with it).
CHILD = r"""
import json, sys
if sys.argv[2] == "block":
    sys.modules["mitsuba"] = None  # `import mitsuba` raises ImportError
import pytest

run = set(json.loads(sys.argv[1]))
seen = {"collected": [], "passed": [], "other": []}


class Select:
    def pytest_collection_modifyitems(self, config, items):
        seen["collected"] = [it.nodeid for it in items]
        keep = [it for it in items if it.nodeid.split("tests/engine/", 1)[-1] in run]
        config.hook.pytest_deselected(items=[it for it in items if it not in keep])
        items[:] = keep

    def pytest_runtest_logreport(self, report):
        if report.when == "call" and report.passed:
            seen["passed"].append(report.nodeid)
        elif report.failed or report.skipped:
            seen["other"].append(f"{report.nodeid} ({report.when}: {report.outcome})")


rc = pytest.main(["-q", "-p", "no:layerbvh", "-p", "no:xdist", "-p", "no:cacheprovider", "-p", "no:randomly",
                  *(["--collect-only"] if sys.argv[2] == "collect" else []), "tests/engine"], plugins=[Select()])
mods = sorted(m for m in sys.modules
              if m.split(".")[0] in ("mitsuba", "layerbvh_mitsuba") and sys.modules[m] is not None)
print("RESULT " + json.dumps({"rc": int(rc), "mitsuba_modules": mods, **seen}))
"""


def _child(how: str) -> tuple[dict, str]:
    p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(RUN), how], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    out = "\n".join(ln for ln in p.stdout.splitlines() if not ln.startswith("RESULT ")) + "\n" + p.stderr
    assert lines, f"{how}: the child printed no result (exit {p.returncode}):\n{out[-4000:]}"
    r = json.loads(lines[-1][len("RESULT "):])
    assert r["rc"] == 0 and p.returncode == 0, f"{how}: pytest exit {r['rc']}:\n{out[-4000:]}"
    return r, out


def test_engine_tests_run_without_mitsuba():
    r, out = _child("block")
    assert r["mitsuba_modules"] == [], r["mitsuba_modules"]
    # Every engine test file collected, and every test that collects with Mitsuba there (none
    # skipped or left out for want of it, say by an importorskip).
    files = {n.split("::")[0] for n in r["collected"]}
    expected = {f"tests/engine/{f.name}" for f in ENGINE.glob("test_*.py")}
    assert files == expected, f"not collected without mitsuba: {sorted(expected - files)}"
    with_mitsuba, _ = _child("collect")
    assert r["collected"] == with_mitsuba["collected"], \
        f"only with mitsuba: {sorted(set(with_mitsuba['collected']) - set(r['collected']))}"
    assert sorted(n.split("tests/engine/", 1)[-1] for n in r["passed"]) == sorted(RUN), \
        f"passed: {r['passed']}; not passed: {r['other']}\n{out[-4000:]}"
