"""pytest plugin `layerbvh` (entry point pytest11, installed with the package): the `layerbvh_ab` fixture and `layerbvh_compare` marker that check a scene against stock Mitsuba with the two-step verdict, its options, kept failure pages and one summary across the run."""
from __future__ import annotations

import hashlib
import html
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

TRAVERSALS = ("auto", "per_ray", "layer_sorted", "layer_unsorted")
RECORDS = "records"  # DIR/records/<test>.json, one per check: the summary is built from them


@dataclass
class ABResult:
    """What a `layerbvh_ab` check found (returned when it passes)."""

    scene: str
    traversal: str
    verdict: object            # verdict.Verdict
    metrics: dict              # metrics.compare_images
    stock_s: float             # stock's render (0 when it came from the cache)
    ours_s: float
    stock_cached: bool
    page: str | None = None    # index.html of its compare page, where one was kept
    stock: object = field(default=None, repr=False)
    ours: object = field(default=None, repr=False)

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    def message(self) -> str:
        """One readable paragraph: the verdict, its numbers, where the page is."""
        m = self.metrics
        where = f" Page: {self.page}" if self.page else " (run with --layerbvh-results DIR to keep its page)"
        return (f"{self.scene} ({self.traversal}): {self.verdict.label}. {self.verdict.summary()}. "
                f"RMSE {m['rmse']:.3g}, relMSE {m['rel_mse']:.3g}, pixels over 1e-3 "
                f"{100 * m['frac_pixels_over_1e-3']:.2f}%; stock {self.stock_s:.2f} s"
                f"{' (cached)' if self.stock_cached else ''}, ours {self.ours_s:.2f} s.{where}")


def pytest_addoption(parser):
    g = parser.getgroup("layerbvh", "layerbvh: image checks against stock Mitsuba")
    g.addoption("--layerbvh-results", metavar="DIR", help="keep the compare page of every failing check in "
                "DIR/<test>/, and write DIR/index.html and DIR/summary.json across the run")
    g.addoption("--layerbvh-keep-all", action="store_true", help="keep the pages of passing checks too")
    g.addoption("--layerbvh-traversal", metavar="MODE", help=f"render every check in MODE ({', '.join(TRAVERSALS)}), "
                "or 'all' to run each check once per mode")
    g.addoption("--layerbvh-variant", metavar="V", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    g.addoption("--layerbvh-no-cache", action="store_true", help="render stock again instead of reading its cache")


def pytest_configure(config):
    config.addinivalue_line("markers", "layerbvh_compare(scene, **kw): check the scene against stock Mitsuba with the "
                            "layerbvh_ab fixture's arguments (the test body may use the returned result as "
                            "`layerbvh_result`)")
    mode = config.getoption("--layerbvh-traversal")
    if mode is not None and mode not in TRAVERSALS + ("all",):
        raise pytest.UsageError(f"--layerbvh-traversal must be one of {', '.join(TRAVERSALS)} or all, got {mode!r}")


def pytest_generate_tests(metafunc):
    checks = "layerbvh_ab" in metafunc.fixturenames or metafunc.definition.get_closest_marker("layerbvh_compare")
    if metafunc.config.getoption("--layerbvh-traversal") == "all" and checks:
        metafunc.parametrize("layerbvh_traversal", TRAVERSALS)


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


def run_check(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, variant="llvm_ad_rgb",
              use_cache=True, keep_dir: Path | None = None, keep_all=False, **params) -> ABResult:
    """Stock `path` (scene's own path settings; cached by scene content and settings) against
    layerbvh with `ours` integrator properties on top, same seed, then the two-step verdict; the
    compare page is written to `keep_dir` when the check fails (or always with `keep_all`)."""
    import mitsuba
    import layerbvh
    from . import metrics
    from .converge import cached_stock
    from .render import cache_dir, load_integrator, load_scene, path_props, render_passes, use_variant
    from .report import write_report
    from .verdict import judge
    mi = use_variant(variant)
    scene_path = Path(scene).resolve()
    sc = load_scene(mi, str(scene_path), tuple(res), **params)
    props = path_props(mi, sc)
    settings = {"resolution": list(res), "integrator": props, "variant": variant, "params": params,
                "versions": {"mitsuba": mitsuba.__version__, "layerbvh": layerbvh.__version__}}
    t0 = time.perf_counter()
    if use_cache:
        stock, info = cached_stock(mi, sc, scene_path, settings, spp, seed, cache_dir("pytest"), "stock", False)
        cached = bool(info.get("cached"))
    else:
        stock = render_passes(mi, sc, load_integrator(mi, {"type": "path", **props}), spp, seed, "stock", False)[0]
        cached = False
    stock_s = 0.0 if cached else time.perf_counter() - t0
    ours_props = {"traversal": traversal, **props, **(ours or {})}
    integ = load_integrator(mi, {"type": "layerbvh", **ours_props})
    img, ours_s = render_passes(mi, sc, integ, spp, seed, "layerbvh", False)
    judged = judge(mi, scene_path, stock, img, spp, props, ours_props, params)
    result = ABResult(scene=str(scene), traversal=traversal, verdict=judged, metrics=metrics.compare_images(stock, img),
                      stock_s=stock_s, ours_s=ours_s, stock_cached=cached, stock=stock, ours=img)
    if keep_dir is not None and (keep_all or not judged.passed):
        info = {"scene": str(scene_path), "spp": spp, "resolution": list(res), "seed": seed, "variant": variant,
                "integrator": props, "ours": {"traversal": traversal, "render_s": ours_s, **(ours or {})},
                "stock": {"render_s": stock_s, "cached": cached}}
        write_report(keep_dir, stock, img, info, judged=judged)
        result.page = str(keep_dir / "index.html")
    return result


def _record(config, nodeid: str, result: ABResult) -> None:
    out = _results_dir(config)
    if out is None:
        return
    from . import atomic
    rec = {"test": nodeid, "scene": result.scene, "traversal": result.traversal, "label": result.verdict.label,
           "passed": result.passed, "summary": result.verdict.summary(), "stock_s": result.stock_s,
           "stock_cached": result.stock_cached, "ours_s": result.ours_s, "rmse": result.metrics["rmse"],
           "page": os.path.relpath(result.page, out) if result.page else None}
    (out / RECORDS).mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / RECORDS / f"{_slug(nodeid)}.json", json.dumps(rec, indent=1))


@pytest.fixture
def layerbvh_ab(request, layerbvh_traversal):
    """`layerbvh_ab(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours={...}, **params)`:
    render the scene with stock `path` and with layerbvh (`ours`: integrator properties for our
    side only; `params`: the scene's $parameters), same seed, and assert the two-step verdict
    (same paths, or agreement within Monte Carlo noise at independent seeds). Returns the
    ABResult; raises an AssertionError with one readable paragraph when the verdict fails."""
    config = request.config
    calls = []

    def check(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, **params) -> ABResult:
        __tracebackhide__ = True  # a failure shows the user's line and the message, not ours
        mode = layerbvh_traversal or traversal
        out = _results_dir(config)
        keep = None if out is None else out / _slug(request.node.nodeid + (f"-{len(calls)}" if calls else ""))
        result = run_check(scene, spp=spp, res=res, traversal=mode, seed=seed, ours=ours,
                           variant=config.getoption("--layerbvh-variant"),
                           use_cache=not config.getoption("--layerbvh-no-cache"), keep_dir=keep,
                           keep_all=config.getoption("--layerbvh-keep-all"), **params)
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
    from . import atomic
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
