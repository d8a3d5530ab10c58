"""The sweep's one table (results.csv, results.json, summary.md, index.html) and the documents merged from its points
(converge per scene, bench.json)."""
from __future__ import annotations

import csv
import html
import io
import json
from pathlib import Path

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.tools import converge


def short_name(name: str) -> str:
    """A scene's short name: the file's stem, or its folder's name for the common `scene.xml`."""
    p = Path(name)
    return p.parent.name if p.stem == "scene" and p.parent.name else p.stem


# Every row: the point, how it ended, where and how long it ran; then the job's figures.
COMMON = ("scene", "config", "spp", "resolution", "status", "error", "triangles", "host", "wall_s", "peak_rss_mib",
          "ran", "started", "key", "dir", "report")
FIGURES = {
    "compare": ("verdict", "mde_image", "within_1e-3", "rmse", "rel_mse", "flip_mean", "delta_e2000_mean",
                "delta_e2000_p95", "max_abs", "mean_abs", "stock_s", "control_s", "ours_s", "ours_over_stock",
                "traversal_s", "loop_s", "build_s", "compile_s", "calibration_s"),
    "converge": ("spp_reached", "seconds", "rel_mse", "flip", "delta_e2000", "slope_rel_mse_vs_spp",
                 "slope_rel_mse_vs_seconds", "rel_mse_at_equal_time", "error_vs_base", "seconds_to_equal_error",
                 "time_vs_base", "build_s", "compile_s", "calibration_s", "reference_s"),
    "bench": ("rays", "query", "ray_count", "embree_mrays_s", "per_ray_mrays_s", "per_ray_h", "sorted_mrays_s",
              "sorted_h", "sorted_vs_per_ray", "sorted_vs_embree", "per_ray_vs_embree", "memory_vs_per_ray",
              "auto_mrays_s", "auto_choice", "auto_vs_best_of_two"),
    "locality": ("rays", "preset", "warp", "per_ray_transactions", "sorted_transactions", "per_ray_dram_bytes",
                 "sorted_dram_bytes", "sorted_sort_bytes", "sorted_total_vs_per_ray", "trace_exact"),
    "third_party": ("result", "within_1e-3", "mean_abs", "max_abs", "flip_mean", "rel_mse", "rays_other_prim",
                    "ray_ties", "stock_s", "ours_s", "notes"),
}
# What summary.md and index.html show (results.csv/.json have every column).
SHOWN = {
    "compare": ("verdict", "mde_image", "within_1e-3", "rel_mse", "flip_mean", "stock_s", "ours_s", "ours_over_stock",
                "build_s"),
    "converge": ("spp_reached", "seconds", "rel_mse", "slope_rel_mse_vs_spp", "rel_mse_at_equal_time", "error_vs_base",
                 "time_vs_base", "build_s"),
    "bench": ("rays", "ray_count", "embree_mrays_s", "per_ray_mrays_s", "per_ray_h", "sorted_mrays_s", "sorted_h",
              "sorted_vs_per_ray", "sorted_vs_embree", "auto_choice"),
    "third_party": ("result", "within_1e-3", "flip_mean", "rays_other_prim", "stock_s", "ours_s"),
    "locality": ("rays", "preset", "warp", "per_ray_transactions", "sorted_transactions", "per_ray_dram_bytes",
                 "sorted_dram_bytes", "sorted_sort_bytes", "sorted_total_vs_per_ray", "trace_exact"),
}
SHOWN_COMMON = ("scene", "config", "spp", "resolution", "triangles", "status")
SHOWN_TAIL = ("host", "wall_s", "ran", "error")
MIB = 1 << 20


def _third_party_figures(rec: dict) -> dict:
    ss, m, rc = rec.get("same_seed") or {}, rec.get("metrics") or {}, rec.get("ray_check") or {}
    return {"result": rec.get("result"), "triangles": rec.get("triangles"), "resolution": rec.get("resolution"),
            "within_1e-3": ss.get("frac_within_1e-3"), "mean_abs": ss.get("mean_abs"), "max_abs": ss.get("max_abs"),
            "flip_mean": m.get("flip_mean"), "rel_mse": m.get("rel_mse"), "rays_other_prim": rc.get("other_prim"),
            "ray_ties": rc.get("ties"), "stock_s": rec.get("stock_s"), "ours_s": rec.get("ours_s"),
            "notes": "; ".join(rec.get("notes") or []) or None, "report": None}


def row(point, stored: dict | None, ran: set, extra: dict) -> dict:
    """One point's row (every column of COMMON and its job's FIGURES; missing figures are None)."""
    s = point.settings
    r = dict.fromkeys(COMMON + FIGURES[point.job])
    r.update(scene=point.name, config=point.label, key=point.key, dir=f"points/{point.dirname}", spp=s.get("spp"),
             resolution=s.get("res"), status="not run")
    if stored is None:
        return r
    fig = stored.get("figures") or {}
    if point.job == "third_party" and fig:
        fig = _third_party_figures(fig)
    r.update({k: v for k, v in fig.items() if k in r})
    report = fig.get("report") if stored["status"] == "ok" else None
    r.update(status=stored["status"], error=stored.get("error"), host=stored.get("host"), wall_s=stored.get("wall_s"),
             started=stored.get("started"), ran="this run" if point.key in ran else "reused",
             peak_rss_mib=stored["peak_rss_bytes"] / MIB if stored.get("peak_rss_bytes") else None,
             report=f"{r['dir']}/{report or 'log.txt'}")
    r.update(extra.get(point.key, {}))
    return r


# -- merged documents -------------------------------------------------------------------------------


def _converge_configs(out: Path, points, results) -> dict:
    """Per scene: [(point, its convergence.json)] of its successful converge points."""
    by_scene = {}
    for p, r in zip(points, results):
        if p.job == "converge" and r is not None and r["status"] == "ok":
            doc = json.loads((out / "points" / p.dirname / "converge" / "convergence.json").read_text())
            by_scene.setdefault(p.scene, []).append((p, doc))
    return by_scene


def merge_converge(out: Path, points, results) -> dict:
    """converge/<scene>/convergence.* from the scene's configurations (one sweep point each), as
    `layerbvh converge` writes them for one run; returns the equal-time columns per point key."""
    extra = {}
    for scene, items in _converge_configs(out, points, results).items():
        configs = []
        for p, doc in items:
            c = doc["configs"][0]
            cfg = converge.Config(c["name"], traversal=None if c["name"] == "stock" else c["traversal"],
                                  treelet_height=c["treelet_height"] or 0, build_s=c["build_s"],
                                  first_render_s=c["first_render_s"], compile_s=c["compile_s"],
                                  calibration_s=c["calibration_s"], points=c["points"], fit=c["fit"])
            configs.append(cfg)
        table = converge.equal_time_error_table(configs)
        for p, _ in items:
            t = table["rows"][p.settings["config"]]
            extra[p.key] = {k: t.get(k) for k in ("rel_mse_at_equal_time", "error_vs_base", "seconds_to_equal_error",
                                                 "time_vs_base")}
        first = items[0][1]
        size = first["resolution"]
        title = (f"{Path(scene).name}: {size[0]}x{size[1]}, budget {first['budget_s']:g} s per configuration, "
                 f"reference stock path at {first['reference']['spp']} spp, {first['variant']}; each configuration "
                 f"a sweep point (its own `layerbvh converge` process, seeds of a first configuration)")
        doc = {k: first[k] for k in ("scene", "resolution", "variant", "budget_s", "max_spp", "integrator",
                                     "reference")}
        doc["configs"] = [d["configs"][0] for _, d in items]
        doc["table"] = table
        doc["sweep_points"] = [p.key for p, _ in items]
        converge.write_outputs(out / "converge" / short_name(items[0][0].name), configs, doc,
                               converge.table_markdown(configs, table), title)
    return extra


def merge_bench(out: Path, points, results, command: str) -> None:
    """bench.json in bench_traversal's format (every point's rows, each with its host), for scripts/report.py."""
    docs = []
    for p, r in zip(points, results):
        if p.job == "bench" and r is not None and r["status"] == "ok":
            doc = json.loads((out / "points" / p.dirname / "bench.json").read_text())
            docs.append((r.get("host"), doc))
    if not docs:
        return
    rows = [{**row, "host": host} for host, d in docs for row in d["results"]]
    first = docs[0][1]
    merged = {"machine": first["machine"], "versions": first["versions"], "command": command,
              "runs": first["runs"], "hosts": sorted({h for h, _ in docs if h}), "results": rows}
    atomic.write_text(out / "bench.json", json.dumps(merged, indent=1))


def merge_locality(out: Path, points, results, command: str) -> None:
    """locality.json: every point's rows (each with its scene), checks and verdict sentences, for
    scripts/report.py's locality section."""
    docs = []
    for p, r in zip(points, results):
        if p.job == "locality" and r is not None and r["status"] == "ok":
            doc = json.loads((out / "points" / p.dirname / "locality" / "locality.json").read_text())
            docs.append((p, doc))
    if not docs:
        return
    scene = (lambda p: short_name(p.name))
    merged = {"command": command,
              "results": [{**row, "scene": scene(p), "triangles": d["triangles"]}
                          for p, d in docs for row in d["results"]],
              "checks": [{**c, "scene": scene(p)} for p, d in docs for c in d["checks"]],
              "verdict": [f"{scene(p)}: {v}" for p, d in docs for v in d["verdict"]],
              "presets": {k: v for _, d in docs for k, v in d["presets"].items()},
              "preset_lines": list(dict.fromkeys(line for _, d in docs for line in d["preset_lines"])),
              "scenes": {}, "machine": docs[0][1].get("machine")}
    for p, d in docs:  # one point per kind: a scene's kinds come from several points
        info = merged["scenes"].setdefault(scene(p), {k: d[k] for k in ("resolution", "spp", "triangles", "sampled")}
                                           | ({"tail_steps": d["tail_steps"]} if "tail_steps" in d else {}))
        info.setdefault("kinds", {}).update(d["kinds"])
    atomic.write_text(out / "locality.json", json.dumps(merged, indent=1))


# -- the table --------------------------------------------------------------------------------------


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "x".join(map(str, v))
    return str(v)


def csv_text(rows: list[dict], columns) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("x".join(map(str, r[k])) if isinstance(r[k], list) else r[k]) for k in columns})
    return buf.getvalue()


def _counts(res) -> dict:
    done = [r for r in res.results if r is not None]
    return {"points": len(res.points), "ok": sum(r["status"] == "ok" for r in done),
            "failed": sum(r["status"] != "ok" for r in done), "not_run": len(res.points) - len(done),
            "ran": len(res.ran), "reused": len(done) - len(res.ran)}


def _headline(res, job: str, command: str) -> list[str]:
    n = _counts(res)
    c = res.cluster
    where = (f"Dask scheduler {c['scheduler']}, {c['workers']} workers on {', '.join(c['hosts'])}"
             if c else "nothing to run (every point reused)")
    return [f"`{command}`" if command else "",
            f"{n['points']} points of job `{job}`: {n['ok']} ok, {n['failed']} failed, {n['not_run']} not run. "
            f"This run ran {n['ran']} and reused {n['reused']} in {res.wall_s:.1f} s ({where})"
            + ("; interrupted." if res.interrupted else ".")]


def summary_md(res, rows: list[dict], job: str, command: str) -> str:
    cols = SHOWN_COMMON + SHOWN[job] + SHOWN_TAIL
    lines = [f"# Sweep: {job}", "", *_headline(res, job, command), "",
             "| " + " | ".join(cols) + " | report |", "|" + "---|" * (len(cols) + 1)]
    for r in rows:
        cells = [_cell(r[k]).replace("|", "\\|") for k in cols]
        link = f"[{Path(r['report']).name}]({r['report']})" if r["report"] else ""
        lines.append("| " + " | ".join(cells) + f" | {link} |")
    failed = [r for r in rows if r["status"] not in ("ok", "not run")]
    if failed:
        lines += ["", "Failed points (run again by the next sweep with the same arguments):", ""]
        lines += [f"- `{r['scene']}` [{r['config']}]: {r['error']}" for r in failed]
    return "\n".join(lines) + "\n"


def index_html(res, rows: list[dict], job: str, command: str) -> str:
    esc = html.escape
    cols = SHOWN_COMMON + SHOWN[job] + SHOWN_TAIL
    head = "".join(f"<th>{esc(k)}</th>" for k in cols) + "<th>report</th><th>log</th>"
    body = []
    for r in rows:
        style = "" if r["status"] == "ok" else ' class="bad"'
        cells = "".join(f"<td>{esc(_cell(r[k]))}</td>" for k in cols)
        rep = f'<a href="{esc(r["report"])}">{esc(Path(r["report"]).name)}</a>' if r["report"] else ""
        log = f'<a href="{esc(r["dir"])}/log.txt">log</a>' if r["status"] != "not run" else ""
        body.append(f"<tr{style}>{cells}<td>{rep}</td><td>{log}</td></tr>")
    info = (f"<p><code>{esc(command)}</code></p>" if command else "") + f"<p>{esc(_headline(res, job, command)[1])}</p>"
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>sweep: {esc(job)}</title>\n<style>body{{font-family:sans-serif;margin:1.5em}}"
            "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:2px 6px;text-align:left}"
            "tr.bad{background:#fdd}</style>\n</head>\n<body>\n"
            f"<h1>Sweep: {esc(job)}</h1>\n{info}\n<table>\n<tr>{head}</tr>\n" + "\n".join(body)
            + "\n</table>\n<p>Every column: results.csv, results.json.</p>\n</body>\n</html>\n")


def write_tables(res, command: str) -> list[dict]:
    """Every table file of the sweep folder, each written whole (results.json last); returns the rows."""
    if not res.points:
        return []
    out, job = res.out, res.points[0].job
    extra = merge_converge(out, res.points, res.results) if job == "converge" else {}
    if job == "bench":
        merge_bench(out, res.points, res.results, command)
    if job == "locality":
        merge_locality(out, res.points, res.results, command)
    ran = set(res.ran)
    rows = [row(p, r, ran, extra) for p, r in zip(res.points, res.results)]
    columns = COMMON + FIGURES[job]
    atomic.write_text(out / "results.csv", csv_text(rows, columns))
    atomic.write_text(out / "summary.md", summary_md(res, rows, job, command))
    atomic.write_text(out / "index.html", index_html(res, rows, job, command))
    doc = {"command": command, "job": job, **_counts(res), "wall_s": res.wall_s, "interrupted": res.interrupted,
           "cluster": res.cluster, "columns": list(columns), "rows": rows}
    atomic.write_text(out / "results.json", json.dumps(doc, indent=1))
    return rows
