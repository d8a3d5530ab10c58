"""pytest plugin `layerbvh` (entry point pytest11, installed with the package): the `layerbvh_ab` fixture and
`layerbvh_compare` marker that check a scene against stock Mitsuba with the two-step verdict, its options, kept
failure pages and one summary across the run."""
from __future__ import annotations

import hashlib
import html
import json
import os
import re
from pathlib import Path

import pytest

from layerbvh_mitsuba import atomic

# Nothing heavy is imported here: pytest loads this plugin in every run of a user's environment,
# and Mitsuba, Dr.Jit and numba load only when a check, its marker or our traversal option is used
# (issue 42: the import cost 1.1 s warm, 14.6 s the first time, and broke pytest where Mitsuba
# cannot be imported).
RECORDS = "records"  # DIR/records/<test>.json, one per check: the summary is built from them


def traversals() -> tuple[str, ...]:
    """The engine modes a check can render in (the embree control is not a check of ours)."""
    import layerbvh  # local: the engine (Dr.Jit, numba) loads only when a check or the option asks
    return layerbvh.TRACE_MODES


def pytest_addoption(parser):
    g = parser.getgroup("layerbvh", "layerbvh: image checks against stock Mitsuba")
    g.addoption("--layerbvh-results", metavar="DIR", help="keep the compare page of every failing check in "
                "DIR/<test>/, and write DIR/index.html and DIR/summary.json across the run")
    g.addoption("--layerbvh-keep-all", action="store_true", help="keep the pages of passing checks too")
    g.addoption("--layerbvh-traversal", metavar="MODE", help="render every check in MODE (a layerbvh trace mode: "
                "layerbvh.TRACE_MODES), or 'all' to run each check once per mode")
    g.addoption("--layerbvh-variant", metavar="V", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    g.addoption("--layerbvh-no-cache", action="store_true", help="render stock again instead of reading its cache")


def pytest_configure(config):
    config.addinivalue_line("markers", "layerbvh_compare(scene, **kw): check the scene against stock Mitsuba with the "
                            "layerbvh_ab fixture's arguments (the test body may use the returned result as "
                            "`layerbvh_result`)")
    mode = config.getoption("--layerbvh-traversal")
    if mode is not None and mode != "all" and mode not in traversals():
        raise pytest.UsageError(f"--layerbvh-traversal must be one of {', '.join(traversals())} or all, got {mode!r}")


def pytest_generate_tests(metafunc):
    checks = "layerbvh_ab" in metafunc.fixturenames or metafunc.definition.get_closest_marker("layerbvh_compare")
    if metafunc.config.getoption("--layerbvh-traversal") == "all" and checks:
        metafunc.parametrize("layerbvh_traversal", traversals())


@pytest.fixture
def layerbvh_traversal(request):
    """The traversal every check renders in (--layerbvh-traversal), None for each check's own."""
    mode = request.config.getoption("--layerbvh-traversal")
    return None if mode == "all" else mode  # ("all": the checks are parametrized over the modes)


def _results_dir(config) -> Path | None:
    d = config.getoption("--layerbvh-results")
    return Path(d).resolve() if d else None


def _slug(nodeid: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", nodeid).strip("_")[-80:]
    return f"{name}-{hashlib.sha256(nodeid.encode()).hexdigest()[:8]}"


def _record(config, nodeid: str, result) -> None:
    """Keep one check's record (result: testing.ABResult) for the run's summary."""
    out = _results_dir(config)
    if out is None:
        return
    summary = result.verdict.summary() + ("" if result.gradient is None else f"; {result.gradient.summary()}")
    rec = {"test": nodeid, "scene": result.scene, "traversal": result.traversal, "label": result.verdict.label,
           "passed": result.passed, "summary": summary, "stock_s": result.stock_s,
           "stock_cached": result.stock_cached, "ours_s": result.ours_s, "rmse": result.metrics["rmse"],
           "page": os.path.relpath(result.page, out) if result.page else None}
    (out / RECORDS).mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / RECORDS / f"{_slug(nodeid)}.json", json.dumps(rec, indent=1))


@pytest.fixture
def layerbvh_ab(request, layerbvh_traversal):
    """`layerbvh_ab(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours={...}, grad=None, mde=None, **params)`:
    render the scene with stock `path` and with layerbvh (`ours`: integrator properties for our
    side only; `params`: the scene's $parameters), same seed, and assert the two-step verdict
    (same paths, or agreement within Monte Carlo noise at independent seeds). With `grad` (a
    mi.traverse key of a prb, prb_basic or prbvolpath scene) the derivatives with respect to that
    parameter must pass the same two steps too (`layerbvh compare --grad`). With `mde` (e.g.
    0.01) the verdict must also rule out every bias of the image mean above that share: the check
    takes more samples per pixel until it does, up to `mde_max_spp` (testing.run_check). Returns
    the ABResult; raises an AssertionError with one readable paragraph when a verdict fails."""
    from layerbvh_mitsuba.testing import run_check  # local: Mitsuba loads when a test asks for a check
    config = request.config
    calls = []

    def check(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, grad=None, mde=None,
              mde_max_spp=None, **params):
        __tracebackhide__ = True  # a failure shows the user's line and the message, not ours
        mode = layerbvh_traversal or traversal
        out = _results_dir(config)
        keep = None if out is None else out / _slug(request.node.nodeid + (f"-{len(calls)}" if calls else ""))
        result = run_check(scene, spp=spp, res=res, traversal=mode, seed=seed, ours=ours,
                           variant=config.getoption("--layerbvh-variant"),
                           use_cache=not config.getoption("--layerbvh-no-cache"), keep_dir=keep,
                           keep_all=config.getoption("--layerbvh-keep-all"), grad=grad, mde=mde,
                           mde_max_spp=mde_max_spp, **params)
        calls.append(result)
        _record(config, request.node.nodeid + (f" [{len(calls)}]" if len(calls) > 1 else ""), result)
        if not result.passed:
            raise AssertionError(result.message())
        return result
    return check


@pytest.fixture
def layerbvh_result(request, layerbvh_ab):
    """The result of the test's `layerbvh_compare` marker (its check runs before the body)."""
    marker = request.node.get_closest_marker("layerbvh_compare")
    if marker is None:
        raise pytest.UsageError("layerbvh_result needs @pytest.mark.layerbvh_compare(scene=..., ...)")
    kw = dict(marker.kwargs)
    scene = marker.args[0] if marker.args else kw.pop("scene")
    return layerbvh_ab(scene, **kw)


@pytest.fixture(autouse=True)
def _layerbvh_marker(request, layerbvh_traversal):
    """A test marked `layerbvh_compare` checks its scene even when its body does not ask for
    `layerbvh_result` (and takes part in --layerbvh-traversal all)."""
    if request.node.get_closest_marker("layerbvh_compare") is not None:
        request.getfixturevalue("layerbvh_result")


def pytest_sessionfinish(session):
    """DIR/summary.json and DIR/index.html from every check's record, once, on the controller
    (pytest-xdist workers write records only)."""
    config = session.config
    out = _results_dir(config)
    if out is None or hasattr(config, "workerinput"):
        return
    records = sorted((json.loads(p.read_text()) for p in (out / RECORDS).glob("*.json")),
                     key=lambda r: r["test"]) if (out / RECORDS).is_dir() else []
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "summary.json", json.dumps({"checks": records}, indent=1))
    atomic.write_text(out / "index.html", summary_html(records))


def summary_html(records: list) -> str:
    esc = html.escape
    rows = []
    for r in records:
        thumb = (f'<a href="{esc(r["page"])}"><img src="{esc(str(Path(r["page"]).parent / "ours.png"))}" '
                 f'height="64" alt="ours"></a>') if r.get("page") else ""
        link = f'<a href="{esc(r["page"])}">page</a>' if r.get("page") else "—"
        rows.append(f'<tr class="{"pass" if r["passed"] else "fail"}"><td>{esc(r["test"])}</td><td>{esc(r["scene"])}'
                    f'</td><td>{esc(r["traversal"])}</td><td><b>{esc(r["label"])}</b><div class="small">'
                    f'{esc(r["summary"])}</div></td><td>{r["stock_s"]:.2f}{" (cached)" if r["stock_cached"] else ""}'
                    f'</td><td>{r["ours_s"]:.2f}</td><td>{thumb}</td><td>{link}</td></tr>')
    failed = sum(not r["passed"] for r in records)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>layerbvh checks</title><style>"
            "body{font-family:system-ui,sans-serif;margin:1.2em 2em} table{border-collapse:collapse} td,th{border:1px "
            "solid #ccc;padding:.3em .6em;vertical-align:top} tr.fail{background:#fbe3e3} tr.pass{background:#e3f6e3}"
            " .small{color:#666;font-size:.85em}</style></head><body>"
            f"<h1>layerbvh checks: {len(records) - failed} passed, {failed} failed</h1>"
            "<table id=\"checks\"><tr><th>test</th><th>scene</th><th>traversal</th><th>verdict</th><th>stock s</th>"
            "<th>ours s</th><th>ours</th><th>page</th></tr>" + "".join(rows) + "</table></body></html>\n")
