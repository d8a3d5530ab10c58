"""The pytest plugin (entry point `layerbvh`) in a user's own project, run by pytest's pytester in a fresh process: a
passing check, a failing one with its page kept, the summary across the run, the stock cache on a second run, the
options."""
from __future__ import annotations

import json

import pytest

from layerbvh_mitsuba.ab import report_schema
from layerbvh_mitsuba.repo import SCENES

TESTS = f'''
import pytest
SCENE = {str(SCENES / "cbox.xml")!r}

def test_same(layerbvh_ab):
    r = layerbvh_ab(SCENE, spp=8, res=(32, 32))
    assert r.verdict.label == "same paths" and r.metrics["rmse"] < 1e-4

def test_other_depth(layerbvh_ab):
    # Negative control: ours with max_depth 1 (direct light only) against the scene's 8.
    layerbvh_ab(SCENE, spp=8, res=(32, 32), ours={{"max_depth": 1}})

@pytest.mark.layerbvh_compare(SCENE, spp=4, res=(16, 16), traversal="per_ray")
def test_marked(layerbvh_result):
    assert layerbvh_result.passed and layerbvh_result.stock.shape == (16, 16, 3)
'''


@pytest.fixture
def project(pytester, monkeypatch, tmp_path, share_kernel_cache):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # an empty stock cache
    share_kernel_cache(pytester.path)  # (pytester's HOME: the compiled kernels, not compiled again)
    pytester.makepyfile(test_user=TESTS)
    return pytester


def _records(path):
    return {r["test"].split("::")[-1]: r for r in json.loads((path / "summary.json").read_text())["checks"]}


def test_checks_pages_summary_and_cache(project):
    out = project.path / "results"
    run = project.runpytest_subprocess("-p", "no:cacheprovider", "--layerbvh-results", str(out))
    run.assert_outcomes(passed=2, failed=1)
    text = run.stdout.str()
    # One readable paragraph: the verdict, the numbers, the page.
    assert "AssertionError:" in text and "differs beyond noise" in text and "Page: " in text
    rec = _records(out)
    assert set(rec) == {"test_same", "test_other_depth", "test_marked"}
    assert rec["test_same"]["label"] == "same paths" and rec["test_same"]["page"] is None
    failed = rec["test_other_depth"]
    assert not failed["passed"] and failed["page"].endswith("index.html")
    page_dir = (out / failed["page"]).parent
    for f in ("stock.exr", "ours.exr", "report.json", "z_fail.png"):
        assert (page_dir / f).is_file(), f
    rep = json.loads((page_dir / "report.json").read_text())
    assert rep["verdict"]["label"] == "differs beyond noise" and report_schema.validate(rep) == []
    index = (out / "index.html").read_text()
    assert "2 passed, 1 failed" in index and failed["page"] in index
    # Stock was rendered once per (scene, settings): test_other_depth found test_same's render.
    assert not rec["test_same"]["stock_cached"] and rec["test_other_depth"]["stock_cached"]

    again = project.runpytest_subprocess("-p", "no:cacheprovider", "--layerbvh-results", str(out),
                                         "--layerbvh-keep-all", "-k", "same or marked")
    again.assert_outcomes(passed=2)
    rec = _records(out)
    assert rec["test_same"]["stock_cached"] and rec["test_marked"]["stock_cached"]
    assert (out / rec["test_same"]["page"]).is_file()  # --layerbvh-keep-all kept a passing check's page

    fresh = project.runpytest_subprocess("-p", "no:cacheprovider", "--layerbvh-results", str(out),
                                         "--layerbvh-no-cache", "-k", "same")
    fresh.assert_outcomes(passed=1)
    assert not _records(out)["test_same"]["stock_cached"]


def test_traversal_option(project):
    run = project.runpytest_subprocess("-p", "no:cacheprovider", "--layerbvh-traversal", "all", "-k", "same or marked",
                                       "-v")
    run.assert_outcomes(passed=8)  # each check once per mode
    assert "test_same[layer_sorted]" in run.stdout.str() and "test_marked[layer_unsorted]" in run.stdout.str()
    bad = project.runpytest_subprocess("-p", "no:cacheprovider", "--layerbvh-traversal", "fast")
    assert bad.ret != 0 and "--layerbvh-traversal must be one of" in bad.stderr.str()


def test_under_xdist_the_summary_is_built_once(project):
    out = project.path / "results"
    run = project.runpytest_subprocess("-p", "no:cacheprovider", "-n", "2", "--layerbvh-results", str(out))
    run.assert_outcomes(passed=2, failed=1)
    assert set(_records(out)) == {"test_same", "test_other_depth", "test_marked"}  # every worker's records
    assert "2 passed, 1 failed" in (out / "index.html").read_text()


PLAIN = '''
import sys

def test_plain():
    assert not {"mitsuba", "drjit", "numba", "layerbvh"} & set(sys.modules), \\
        sorted({"mitsuba", "drjit", "numba", "layerbvh"} & set(sys.modules))
'''


def _pytest_plain(cwd, *args, env=None) -> float:
    """Wall time of `pytest -q test_plain.py ARGS` in a fresh process, which must pass."""
    import subprocess  # local: only these start-up tests run pytest as a plain subprocess
    import sys
    import time
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_plain.py", *args],
                       cwd=cwd, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    return time.perf_counter() - t0


def test_the_plugin_costs_nothing_until_used(tmp_path):
    """Issue 42: a run that never touches a scene imports no Mitsuba, Dr.Jit, numba or engine
    (the test asserts it from inside), and pytest's start-up with the plugin is within 0.2 s of
    the same run without it (`-p no:layerbvh`): the best of three each, taken in turns (the suite
    runs beside another process)."""
    (tmp_path / "test_plain.py").write_text(PLAIN)
    times = [(_pytest_plain(tmp_path), _pytest_plain(tmp_path, "-p", "no:layerbvh")) for _ in range(3)]
    with_plugin, without = min(t[0] for t in times), min(t[1] for t in times)
    assert with_plugin - without < 0.2, (with_plugin, without)


def test_the_plugin_loads_where_mitsuba_cannot_be_imported(tmp_path):
    """A Mitsuba that cannot be imported breaks no pytest run that does not use it."""
    import os  # local: as above
    (tmp_path / "test_plain.py").write_text(PLAIN)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "mitsuba.py").write_text("raise ImportError('no Mitsuba here')\n")
    _pytest_plain(tmp_path, env={**os.environ, "PYTHONPATH": str(broken)})
