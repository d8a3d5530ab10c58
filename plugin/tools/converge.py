"""Error against run time: each configuration renders at 1, 2, 4, ... spp within a time budget and is scored against
a cached stock reference."""
from __future__ import annotations

import csv
import html
import io
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.render import load_integrator, load_scene, timed_render
from layerbvh_mitsuba.ab.scene_integrator import PathSettings, path_settings
from layerbvh_mitsuba.ab.stock_cache import cached_stock
from layerbvh_mitsuba.runtime.cache import cache_dir
from layerbvh_mitsuba.runtime.settings import CHOICES, EMBREE, Traversal

REFERENCE_SEED = 100_000  # the reference's passes use seeds 791.9M + k, far from any config's
EXTRAPOLATION_SLACK = 1.25  # a fit read within 25% of the rendered time range counts as measured
MAX_EXTRAPOLATION = 2.0  # a fit is never read further than this factor outside the rendered times
MIN_FIT_R2 = 0.9  # a log-log fit below this R² gives no ratio (its points do not follow a power law)
MIN_FIT_SPP = 4  # below this, fixed per-render overhead bends the time axis; fits skip it when they can
METRICS = ("rel_mse", "flip", "delta_e2000")
CSV_COLUMNS = ("config", "spp", "seconds", "rel_mse", "flip", "delta_e2000", "seed")


class ConvergeError(ValueError):
    """Bad input to `layerbvh converge`, reported as one line."""


# -- configurations ---------------------------------------------------------------------------------


@dataclass
class Config:
    """One renderer under test: stock `path` (Embree) or the layerbvh integrator in one traversal mode."""

    name: str
    traversal: str | None = None  # None: stock path
    treelet_height: int = layerbvh.DEFAULT_TREELET_HEIGHT
    build_s: float = 0.0
    first_render_s: float = 0.0
    compile_s: float = 0.0
    calibration_s: float = 0.0  # auto's timing runs, taken out of the render times
    points: list = field(default_factory=list)
    fit: dict = field(default_factory=dict)

    @property
    def stock(self) -> bool:
        return self.traversal is None


def parse_configs(text: str) -> list[Config]:
    """`stock,embree,per_ray,layer_sorted:4,layer_sorted:6`: names with an optional treelet height
    (`embree`: the layerbvh integrator's loop with Mitsuba's queries, the control that isolates
    the traversal)."""
    out, seen = [], set()
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        mode, _, height = item.partition(":")
        try:
            traversal = None if mode == "stock" else Traversal.parse(mode)
        except ValueError:
            raise ConvergeError(f"--configs: unknown configuration {item!r}; use stock or one of {', '.join(CHOICES)} "
                                f"(a layer mode optionally :HEIGHT)") from None
        if traversal is None or traversal.control:
            if height:
                raise ConvergeError(f"--configs: {mode!r} takes no treelet height, got {item!r}")
            cfg = Config(mode, traversal=None if traversal is None else EMBREE)
        else:
            try:
                h = layerbvh.check_param("treelet_height", int(height) if height else layerbvh.DEFAULT_TREELET_HEIGHT)
            except ValueError as e:
                raise ConvergeError(f"--configs: treelet height in {item!r}: {e}") from None
            plain = mode == "per_ray" or (mode == "auto" and not height)
            cfg = Config(mode if plain else f"{mode}:{h}", traversal=mode, treelet_height=h)
        if cfg.name in seen:
            raise ConvergeError(f"--configs: {cfg.name!r} is listed twice")
        seen.add(cfg.name)
        out.append(cfg)
    if not out:
        raise ConvergeError("--configs is empty")
    return out


# -- the reference, cached by content ---------------------------------------------------------------


def reference(mi, scene, scene_path: Path, settings: dict, cache: Path, progress: bool) -> tuple[np.ndarray, dict]:
    """The stock reference image at settings["ref_spp"] (`cached_stock`)."""
    return cached_stock(mi, scene, scene_path, settings, settings["ref_spp"], REFERENCE_SEED, cache,
                        "reference (stock)", progress)


# -- the measurement --------------------------------------------------------------------------------


def _seed(config_index: int, level: int) -> int:
    # Independent of each other, of the warm-up (level -1) and of the reference.
    return 1 + 1000 * config_index + (level + 1)


def _integrator(mi, cfg: Config, path: PathSettings, build: dict):
    """The configuration's integrator (the scene's estimator: stock's, or ours standing in for
    it); `build` holds the BVH's leaf_size and branching."""
    if cfg.stock:
        return load_integrator(mi, path.stock_inner())
    return load_integrator(mi, {"type": path.ours_type, "traversal": cfg.traversal,
                                "treelet_height": cfg.treelet_height, **build, **path.props})


def run_config(mi, scene, cfg: Config, index: int, path: PathSettings, ref: np.ndarray, budget: float,
               max_spp: int, build: dict, bar) -> None:
    """Render at doubling spp while the next render (predicted: twice the last) fits in the budget."""
    integ = _integrator(mi, cfg, path, build)
    tracer = None if cfg.stock else integ.tracer(scene)  # built once here, outside every timed render
    cfg.build_s = tracer.build_s if tracer is not None else 0.0
    # Warm-up with its own seed: most kernels compile here; any later compile is subtracted too.
    warm = timed_render(mi, scene, integ, 1, _seed(index, -1))
    cfg.compile_s, cfg.calibration_s = warm.compile_s, warm.calibration_s
    cfg.first_render_s = warm.wall_s
    spent, spp, level = 0.0, 1, 0
    while spp <= max_spp:
        r = timed_render(mi, scene, integ, spp, _seed(index, level))
        img, secs, compile_s = r.image, r.seconds, r.compile_s
        cfg.compile_s += compile_s
        cfg.calibration_s += r.calibration_s
        m = metrics.compare_images(ref, img)
        cfg.points.append({"config": cfg.name, "spp": spp, "seconds": secs, "compile_s": compile_s,
                           "rel_mse": m["rel_mse"],
                           "flip": m["flip_mean"], "delta_e2000": m["delta_e2000_mean"], "seed": _seed(index, level)})
        spent += secs
        bar.update(1)
        bar.set_postfix_str(f"{cfg.name} {spp} spp {secs:.2f} s")
        if spent + 2 * secs > budget:
            break
        spp, level = spp * 2, level + 1


# -- fits and tables --------------------------------------------------------------------------------


def _fit_points(points: list, axis: str) -> list:
    if axis == "spp":  # error against samples has no overhead term: every point counts
        return points
    big = [p for p in points if p["spp"] >= MIN_FIT_SPP]
    return big if len(big) >= 3 else points


def loglog_fit(x, y) -> tuple[float, float, float] | None:
    """(intercept, slope, R²) of log y = a + b log x by least squares; None with fewer than 2 points."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ok = (x > 0) & (y > 0)
    if ok.sum() < 2 or np.ptp(np.log(x[ok])) == 0:
        return None
    lx, ly = np.log(x[ok]), np.log(y[ok])
    b, a = np.polyfit(lx, ly, 1)
    resid = ly - (a + b * lx)
    spread = float(np.sum((ly - ly.mean()) ** 2))
    r2 = 1.0 - float(np.sum(resid ** 2)) / spread if spread > 0 else 1.0
    return float(a), float(b), r2


def fits(cfg: Config) -> dict:
    """Fitted power laws per metric, against spp and against seconds."""
    out = {}
    for m in METRICS:
        for axis in ("spp", "seconds"):
            pts = _fit_points(cfg.points, axis)
            f = loglog_fit([p[axis] for p in pts], [p[m] for p in pts])
            out[f"{m}_vs_{axis}"] = None if f is None else {"intercept": f[0], "slope": f[1], "r2": f[2]}
    return out


def equal_time_error_table(configs: list[Config]) -> dict:
    """relMSE at a common time and time to reach stock's error, both from each config's fitted
    power law (relMSE vs seconds) and relative to stock when stock is among the configs.

    Common time: the longest render every configuration reached. Equal error: the relMSE stock
    reached in its longest render (or the first config's, without stock). A read of a fit is
    given only where it can be trusted: the fit's log-log R² is at least MIN_FIT_R2 and the read
    lies within MAX_EXTRAPOLATION of the times that configuration rendered; otherwise the value
    is None with the reason. Reads outside the rendered times (within that factor) are flagged."""
    base = next((c for c in configs if c.stock), configs[0])
    t_common = min(max(p["seconds"] for p in c.points) for c in configs)
    e_target = min(base.points, key=lambda p: -p["seconds"])["rel_mse"]
    rows = {}
    for c in configs:
        f = c.fit["rel_mse_vs_seconds"]
        lo, hi = min(p["seconds"] for p in c.points), max(p["seconds"] for p in c.points)
        row = {"rel_mse_at_equal_time": None, "seconds_to_equal_error": None}
        if f is None or f["slope"] >= 0:
            row["why_not"] = "no falling fit (too few points, or error does not fall with time)"
        elif f["r2"] < MIN_FIT_R2:
            row["why_not"] = f"fit R² {f['r2']:.2f} < {MIN_FIT_R2}: the points do not follow a power law"
        else:
            a, b = f["intercept"], f["slope"]
            t_eq = math.exp((math.log(e_target) - a) / b)
            reads = {"rel_mse_at_equal_time": (t_common, math.exp(a + b * math.log(t_common)), "equal_time"),
                     "seconds_to_equal_error": (t_eq, t_eq, "equal_error")}
            why = []
            for key, (t, value, flag) in reads.items():
                if t < lo / MAX_EXTRAPOLATION or t > hi * MAX_EXTRAPOLATION:
                    why.append(f"{key} would read the fit at {t:.3g} s, beyond {MAX_EXTRAPOLATION:g}x the rendered "
                               f"{lo:.3g}-{hi:.3g} s")
                    continue
                row[key] = value
                row[f"{flag}_extrapolated"] = not lo / EXTRAPOLATION_SLACK <= t <= hi * EXTRAPOLATION_SLACK
            if why:
                row["why_not"] = "; ".join(why)
        rows[c.name] = row
    ref = rows[base.name]
    for r in rows.values():
        for k, rel in (("rel_mse_at_equal_time", "error_vs_base"), ("seconds_to_equal_error", "time_vs_base")):
            r[rel] = r[k] / ref[k] if r[k] is not None and ref[k] else None
    return {"base": base.name, "equal_time_s": t_common, "equal_error_rel_mse": e_target, "rows": rows}


def _g(x, spec=".3g"):
    return "n/a" if x is None else format(x, spec)


def table_markdown(configs: list[Config], table: dict) -> str:
    base = table["base"]
    lines = [f"relMSE at equal time ({table['equal_time_s']:.3g} s per render) and time to reach "
             f"{base}'s relMSE {table['equal_error_rel_mse']:.3g}, from each configuration's fitted "
             f"log-log line (relMSE vs seconds); ratios are against {base}. Render times exclude "
             f"kernel compilation (Dr.Jit's kernel history), which is listed with the BVH build. "
             f"* = read outside the times that configuration rendered (never beyond "
             f"{MAX_EXTRAPOLATION:g}x); n/a = no trustworthy read (reason below; fits with R² < {MIN_FIT_R2} "
             f"give none).", "",
             "| config | build s | compile s | spp reached | slope vs spp | relMSE at equal time | × " + base
             + " | seconds to equal error | × " + base + " |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    notes = []
    for c in configs:
        r = table["rows"][c.name]
        slope = c.fit["rel_mse_vs_spp"]
        lines.append(f"| {c.name} | {c.build_s:.2f} | {c.compile_s:.2f} | {c.points[-1]['spp']} "
                     f"| {_g(slope and slope['slope'], '.2f')} | {_g(r['rel_mse_at_equal_time'])} "
                     f"| {_g(r['error_vs_base'], '.2f')}{'*' if r.get('equal_time_extrapolated') else ''} "
                     f"| {_g(r['seconds_to_equal_error'])} "
                     f"| {_g(r['time_vs_base'], '.2f')}{'*' if r.get('equal_error_extrapolated') else ''} |")
        if r.get("why_not"):
            notes.append(f"- {c.name}: n/a where shown – because {r['why_not']}")
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


# -- outputs ----------------------------------------------------------------------------------------


def csv_text(configs: list[Config]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    for c in configs:
        for p in c.points:
            w.writerow({k: p[k] for k in CSV_COLUMNS})
    return buf.getvalue()


def plot_png(configs: list[Config], title: str, table: dict | None = None) -> bytes:
    """Log-log error vs seconds per metric: each configuration's renders as points in time order,
    labelled with their spp, the fitted line the table's numbers come from (dashed), and the
    ideal Monte Carlo slope from each configuration's first point (dotted). On the relMSE plot
    the table's reads are marked: the common time (vertical) with each configuration's error
    there (x), and stock's final error (horizontal) with the time each reaches it (+)."""
    import matplotlib  # local: matplotlib loads only when a plot is drawn
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # local: matplotlib loads only when a plot is drawn
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    labels = {"rel_mse": ("relMSE", -1.0), "flip": ("mean ꟻLIP", -0.5), "delta_e2000": ("mean ΔE2000", -0.5)}
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, m in zip(axes, METRICS):
        name, ideal = labels[m]
        for i, c in enumerate(configs):
            color = colors[i % len(colors)]
            pts = sorted(c.points, key=lambda p: p["seconds"])
            t = np.array([p["seconds"] for p in pts])
            ax.plot(t, [p[m] for p in pts], "o", color=color, ms=4, label=c.name)
            for p in pts:
                ax.annotate(str(p["spp"]), (p["seconds"], p[m]), textcoords="offset points", xytext=(3, 3),
                            fontsize=6, color=color)
            f = c.fit.get(f"{m}_vs_seconds")
            if f is not None:
                tt = np.geomspace(t.min(), t.max(), 20)
                ax.plot(tt, np.exp(f["intercept"] + f["slope"] * np.log(tt)), "--", color=color, lw=1)
            first = min(pts, key=lambda p: p["seconds"])
            ax.plot(t, first[m] * (t / first["seconds"]) ** ideal, ":", color=color, lw=1)
        if m == "rel_mse" and table is not None:
            ax.axvline(table["equal_time_s"], color="0.5", lw=0.8, ls="-.", label="equal time")
            ax.axhline(table["equal_error_rel_mse"], color="0.5", lw=0.8, ls="-.", label=f"{table['base']}'s error")
            for i, c in enumerate(configs):
                r = table["rows"][c.name]
                color = colors[i % len(colors)]
                if r["rel_mse_at_equal_time"] is not None:
                    ax.plot(table["equal_time_s"], r["rel_mse_at_equal_time"], "x", color=color, ms=9, mew=2)
                if r["seconds_to_equal_error"] is not None:
                    ax.plot(r["seconds_to_equal_error"], table["equal_error_rel_mse"], "+", color=color, ms=11, mew=2)
        ax.plot([], [], "k--", lw=1, label="fitted line")
        ax.plot([], [], "k:", lw=1, label=f"ideal slope {ideal:g}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("render time per image (s); labels: spp")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


OUTPUT_MARKER = "convergence.json"  # the file that makes a folder a converge output


def html_page(configs: list[Config], table: dict, title: str) -> str:
    """convergence.html: the plot and the table, with the reasons for every n/a."""
    esc = html.escape
    base = table["base"]
    head = ("<tr><th>config</th><th>build s</th><th>compile s</th><th>spp reached</th><th>slope vs spp</th>"
            f"<th>relMSE at equal time</th><th>× {esc(base)}</th><th>seconds to equal error</th>"
            f"<th>× {esc(base)}</th></tr>")
    rows, notes = [], []
    for c in configs:
        r = table["rows"][c.name]
        slope = c.fit["rel_mse_vs_spp"]
        cells = [c.name, f"{c.build_s:.2f}", f"{c.compile_s:.2f}", str(c.points[-1]["spp"]),
                 _g(slope and slope["slope"], ".2f"), _g(r["rel_mse_at_equal_time"]),
                 _g(r["error_vs_base"], ".2f") + ("*" if r.get("equal_time_extrapolated") else ""),
                 _g(r["seconds_to_equal_error"]),
                 _g(r["time_vs_base"], ".2f") + ("*" if r.get("equal_error_extrapolated") else "")]
        rows.append("<tr>" + "".join(f"<td>{esc(x)}</td>" for x in cells) + "</tr>")
        if r.get("why_not"):
            notes.append(f"<li>{esc(c.name)}: n/a because {esc(r['why_not'])}</li>")
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Error against run time</title>"
            "<style>body{font-family:system-ui,sans-serif;margin:1.2em 2em}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:3px 9px;text-align:right}"
            "td:first-child,th:first-child{text-align:left}"
            "img{max-width:100%}</style></head><body>"
            f"<h1>Error against run time</h1><p>{esc(title)}</p>"
            f"<p>Equal time: {table['equal_time_s']:.3g} s per render (the longest every configuration reached); "
            f"equal error: {esc(base)}'s final relMSE {table['equal_error_rel_mse']:.3g}. Both are read from each "
            f"configuration's fitted line (dashed), marked on the relMSE plot (x: error at equal time, +: time to "
            f"equal error); * = read outside the rendered times (never beyond {MAX_EXTRAPOLATION:g}×), n/a = no "
            f"trustworthy read.</p><img src=\"convergence.png\" alt=\"error against run time\">"
            f"<table>{head}{''.join(rows)}</table><ul>{''.join(notes)}</ul>"
            "<p><a href=\"convergence.csv\">convergence.csv</a> · <a href=\"convergence.json\">convergence.json</a>"
            "</p></body></html>\n")


def write_outputs(out: Path, configs: list[Config], doc: dict, table_md: str, title: str) -> None:
    """The output folder, written whole (atomic.atomic_folder: the folder's files are one run's)."""
    with atomic.atomic_folder(out, OUTPUT_MARKER) as tmp:
        atomic.write_text(tmp / "convergence.csv", csv_text(configs))
        atomic.write_bytes(tmp / "convergence.png", plot_png(configs, title, doc["table"]))
        atomic.write_text(tmp / "convergence.md", f"# Error against run time\n\n{title}\n\n{table_md}")
        atomic.write_text(tmp / "convergence.html", html_page(configs, doc["table"], title))
        atomic.write_text(tmp / OUTPUT_MARKER, json.dumps(doc, indent=1))


# -- the command ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConvergeSettings:
    """One `layerbvh converge` run (the command's options; the sweep's converge points)."""

    scene: str | Path
    budget: float                     # seconds of rendering per configuration
    out: str | Path
    configs: str = "stock,embree,per_ray,layer_sorted"  # parse_configs' list
    ref_spp: int = 4096
    max_spp: int | None = None        # None: ref spp / 16
    res: tuple[int, int] | None = None
    leaf_size: int | None = None
    branching: int = layerbvh.DEFAULT_BRANCHING
    cache: str | Path | None = None   # None: cache_dir("references")
    as_path: bool = False
    progress: bool = True


def settings_from_args(args) -> ConvergeSettings:
    return ConvergeSettings(scene=args.scene, budget=args.budget, out=args.out, configs=args.configs,
                            ref_spp=args.ref_spp, max_spp=args.max_spp, res=tuple(args.res) if args.res else None,
                            leaf_size=args.leaf_size, branching=args.branching, cache=args.cache,
                            as_path=args.as_path, progress=not args.no_progress)


def run(mi, s: ConvergeSettings) -> dict:
    """`layerbvh converge`: returns the JSON document it writes."""
    configs = parse_configs(s.configs)
    if s.budget <= 0:
        raise ConvergeError(f"--budget must be > 0 seconds, got {s.budget}")
    if s.ref_spp < 16:
        raise ConvergeError(f"--ref-spp must be >= 16, got {s.ref_spp}")
    max_spp = s.max_spp or max(1, s.ref_spp // 16)
    if max_spp > s.ref_spp // 4:
        raise ConvergeError(f"--max-spp {max_spp} is too close to --ref-spp {s.ref_spp}: the reference's own "
                            f"noise would bias the error (keep max spp <= ref spp / 4)")
    scene_path = Path(s.scene)
    t0 = time.perf_counter()
    scene = load_scene(mi, str(scene_path), s.res)
    load_s = time.perf_counter() - t0
    path = path_settings(mi, scene, s.as_path, scene_path)
    if path.wrapper is not None:  # the wrapper adds channels, not error: its inner estimator is scored
        path.note = (f"the scene's integrator is {path.scene_integrator}; its radiance (the {path.estimator} inside) "
                     f"is scored, its other channels are not")
    props = path.props
    size = [int(x) for x in scene.sensors()[0].film().crop_size()]
    settings = {"ref_spp": s.ref_spp, "resolution": size, "variant": mi.variant(), "mitsuba": mi.__version__,
                "integrator": props, "seed": REFERENCE_SEED,
                **({"stock": path.stock_inner()} if path.estimator != "path" else {})}
    progress = s.progress
    ref, ref_info = reference(mi, scene, scene_path, settings, Path(s.cache or cache_dir("references")), progress)
    if progress:
        print(f"reference: {'reused' if ref_info['cached'] else 'rendered'} {ref_info['path']}", file=sys.stderr)
    renders = len(configs) * (int(math.log2(max_spp)) + 1)
    with tqdm(total=renders, desc="converge", unit="render", disable=not progress, file=sys.stderr) as bar:
        for i, cfg in enumerate(configs):
            run_config(mi, scene, cfg, i, path, ref, s.budget, max_spp,
                       {"branching": s.branching, **({} if s.leaf_size is None else {"leaf_size": s.leaf_size})},
                       bar)
            cfg.fit = fits(cfg)
            bar.total = bar.n + (len(configs) - i - 1) * (int(math.log2(max_spp)) + 1)
    table = equal_time_error_table(configs)
    title = (f"{scene_path.name}: {size[0]}x{size[1]}, budget {s.budget:g} s per configuration, "
             f"reference stock {path.estimator} at {s.ref_spp} spp, {mi.variant()}"
             + (f"; {path.note}" if path.note else ""))
    doc = {
        "scene": str(scene_path), "resolution": size, "variant": mi.variant(), "budget_s": s.budget,
        "max_spp": max_spp, "scene_load_s": load_s, "integrator": props,
        "scene_integrator": path.scene_integrator,
        "compared_as": path.estimator + (" (--as-path)" if path.as_path else " (the wrapper's radiance)" if path.wrapper
                                         else ""),
        "reference": {k: ref_info[k] for k in ("path", "key", "cached", "render_s")} | {"spp": s.ref_spp},
        "configs": [{"name": c.name, "traversal": c.traversal or "stock (Embree)", "treelet_height":
                     None if c.stock or c.traversal == "per_ray" else c.treelet_height,
                     "build_s": c.build_s, "first_render_s": c.first_render_s, "compile_s": c.compile_s,
                     "calibration_s": c.calibration_s,
                     "fit": c.fit, "points": c.points} for c in configs],
        "table": table,
    }
    table_md = table_markdown(configs, table)
    write_outputs(Path(s.out), configs, doc, table_md, title)
    print(table_md)
    return doc
