"""One sweep point in its own process: runs the job (compare, converge, bench, third-party check)
and writes its figures to result.json.

    python -m layerbvh_mitsuba.tools.sweep.point POINT.json OUT_DIR

POINT.json is a `sweep.Point` as a dict. Files the job writes go under OUT_DIR; result.json
(`status`, `figures` or `error`, `point_s`, `peak_rss_bytes`) is written last. The sweep's task
starts this process, enforces the time and memory limits and sends everything back.
"""
from __future__ import annotations

import json
import os
import resource
import signal
import sys
import time
import traceback
from pathlib import Path
from types import SimpleNamespace

import layerbvh
from layerbvh import meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.compare import CompareSettings, ComparisonFailed, compare
from layerbvh_mitsuba.ab.render import UserError, load_scene, use_variant
from layerbvh_mitsuba.ab.report import json_safe, write_comparison
from layerbvh_mitsuba.runtime.scene_geometry import UnsupportedShapeError, collect_geometry
from layerbvh_mitsuba.runtime.settings import Traversal
from layerbvh_mitsuba.tools import converge
from layerbvh_mitsuba.tools.bench import report as bench_report, traversal
from layerbvh_mitsuba.tools.bench.locality import LocalityRequest, headline, measure_scene, write_outputs
from layerbvh_mitsuba.tools.bench.record_rays import cached_recording
from layerbvh_mitsuba.tools.sweep.table import short_name
from layerbvh_mitsuba.tools.third_party import one_line, run_worker

GENERATED_SEED_OFFSET = {"coherent": 1, "incoherent": 2}  # bench_traversal's seeds of its generated ray sets


class PointError(Exception):
    """The job reported a problem with this point (one line, for the table)."""


def _die_with_parent() -> None:
    """Linux: be killed when the sweep's worker goes (Ctrl-C, cluster shut down), never left running."""
    parent = int(os.environ.get("LAYERBVH_SWEEP_PARENT", "0"))
    try:
        import ctypes  # local: Linux only, tried where it runs
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent and os.getppid() != parent:  # the parent went before the line above
        os._exit(1)


# -- jobs -------------------------------------------------------------------------------------------


def run_compare(point: dict, out: Path) -> dict:
    """The A/B comparison (ab.compare.compare, as `layerbvh compare` runs it: with the Embree
    control and the statistics pass) on the point's scene and configuration; its report folder,
    metrics, times and verdict."""
    s = point["settings"]
    mi = use_variant(s["variant"])
    c = compare(mi, CompareSettings(
        scene=point["scene"], spp=s.get("spp"), res=tuple(s["res"]) if s.get("res") else None, seed=s["seed"],
        traversal=Traversal.parse(s["traversal"]), treelet_height=s["treelet_height"],
        branching=s.get("branching") or layerbvh.DEFAULT_BRANCHING, control=True, statistics_pass=True))
    write_comparison(out / "compare", c)
    m, split = c.metrics, c.split() or {}
    return {"report": "compare/index.html", "spp": c.spp, "resolution": list(c.resolution),
            "triangles": c.counted.bvh.triangles if c.counted and c.counted.bvh else None,
            "verdict": c.verdict.label, "mde_image": (c.verdict.mde() or {}).get("image"),
            "within_1e-3": 1.0 - m["frac_pixels_over_1e-3"],
            **{k: m[k] for k in ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs",
                                 "mean_abs")},
            "stock_s": c.stock_time.render_s, "control_s": c.control_time.render_s if c.control_time else None,
            "ours_s": c.ours_time.render_s, "ours_over_stock": split.get("ours_over_stock"),
            "traversal_s": split.get("traversal_s"), "loop_s": split.get("loop_s"), "build_s": c.stats.build_s,
            "compile_s": c.ours_time.compile_s, "calibration_s": c.ours_time.calibration_s}


def _triangles(point: dict) -> int:
    """Mesh triangles of the point's scene (a load of its own: converge does not report them)."""
    mi = use_variant(point["settings"]["variant"])
    return sum(int(sh.face_count()) for sh in load_scene(mi, point["scene"]).shapes() if sh.is_mesh())


def run_converge(point: dict, out: Path) -> dict:
    """`converge` for one configuration; its last point, slopes and the separate costs."""
    s = point["settings"]
    mi = use_variant(s["variant"])
    doc = converge.run(mi, converge.ConvergeSettings(
        scene=point["scene"], budget=s["budget"], out=out / "converge", configs=s["config"], ref_spp=s["ref_spp"],
        max_spp=s.get("max_spp"), res=tuple(s["res"]) if s.get("res") else None, progress=False))
    c = doc["configs"][0]
    last, fit = c["points"][-1], c["fit"]

    def slope(name):
        return fit[name] and fit[name]["slope"]
    return {"report": "converge/convergence.png", "resolution": doc["resolution"], "spp": last["spp"],
            "triangles": _triangles(point),
            "spp_reached": last["spp"], "seconds": last["seconds"], "rel_mse": last["rel_mse"], "flip": last["flip"],
            "delta_e2000": last["delta_e2000"], "slope_rel_mse_vs_spp": slope("rel_mse_vs_spp"),
            "slope_rel_mse_vs_seconds": slope("rel_mse_vs_seconds"), "build_s": c["build_s"],
            "compile_s": c["compile_s"], "calibration_s": c["calibration_s"],
            "reference_s": doc["reference"]["render_s"], "reference_cached": doc["reference"]["cached"]}


def _recorded_rays(mi, point: dict, kind: str):
    """(vertices, faces, o, d, tmax, source) of one recorded kind, from the scene's cached recording at
    the point's resolution, spp and seed (record_rays.cached_recording)."""
    s = point["settings"]
    v, f, rays, meta = cached_recording(mi, point["scene"], s["res"], s["spp"], s["seed"], s["ray_count"])
    if kind not in rays:
        raise PointError(f"the render traced no {kind} rays ({s['res'][0]}x{s['res'][1]}, {s['spp']} spp)")
    o, d, tmax = rays[kind]
    return v, f, o, d, tmax, (f"recorded from {meta['scene']} ({meta['resolution'][0]}x{meta['resolution'][1]}, "
                              f"{meta['spp']} spp)")


def run_bench(point: dict, out: Path) -> dict:
    """The traversal benchmark (bench/traversal.py) on one ray set of the scene: Embree and every mode ×
    treelet height plus auto, interleaved in this process; the headline figures (best height of each)."""
    s = point["settings"]
    kind, n = s["rays"], s["ray_count"]
    mi = use_variant(s["variant"])
    if kind in GENERATED_SEED_OFFSET:
        g = collect_geometry(load_scene(mi, point["scene"]))
        v, f = g.vertices, g.faces
        if len(f) == 0:
            raise PointError("the scene has no triangles to bench")
        gen = meshes.camera_rays if kind == "coherent" else meshes.incoherent_rays
        o, d = gen(v, n, seed=s["seed"] + GENERATED_SEED_OFFSET[kind])
        ray_set, source = (kind, o, d, None, False), "generated"
    else:
        v, f, o, d, tmax, source = _recorded_rays(mi, point, kind)
        ray_set = (kind, o[:n], d[:n], tmax[:n], kind == "shadow")
    args = SimpleNamespace(heights=s["heights"], branchings=s.get("branchings", [2]), runs=s["runs"], backend="llvm",
                           batch_rays=layerbvh.BATCH_RAYS)
    rows = traversal.bench_mesh(short_name(point["name"]), v, f, [ray_set], args, source=source)
    doc = {"machine": traversal.machine_info("llvm"), "versions": traversal.versions(),
           "command": f"layerbvh sweep --job bench: {point['name']}, {kind} rays", "runs": s["runs"], "results": rows}
    atomic.write_text(out / "bench.json", json.dumps(doc, indent=1))
    head = bench_report.headline_rows(rows)[0]
    return {"report": "bench.json", "triangles": int(len(f)), "rays": kind, "query": head["query"],
            "ray_count": head["ray_count"], "embree_mrays_s": head["embree"], "per_ray_mrays_s": head["per_ray"],
            "per_ray_h": head["per_ray_h"], "sorted_mrays_s": head["sorted"], "sorted_h": head["sorted_h"],
            "sorted_vs_per_ray": head["sorted_vs_per_ray"], "sorted_vs_embree": head["sorted_vs_embree"],
            "per_ray_vs_embree": head["per_ray_vs_embree"], "memory_vs_per_ray": head["memory_vs_per_ray"],
            "auto_mrays_s": head["auto"], "auto_choice": head["auto_choice"],
            "auto_vs_best_of_two": head["auto_vs_best_of_two"]}


def run_third_party(point: dict, out: Path) -> dict:
    """third_party.run_worker: the A/B record of one third-party scene (verdict, ray check, notes)."""
    return run_worker(SimpleNamespace(worker=point["scene"], **point["settings"]))


def run_locality(point: dict, out: Path) -> dict:
    """The locality model (bench/locality.py) on one recorded kind and treelet height of the scene:
    every mode x preset x warp width; its locality.json, and the headline of the first preset."""
    s = point["settings"]
    mi = use_variant(s["variant"])
    req = LocalityRequest(scene=point["scene"], res=tuple(s["res"]) if s.get("res") else None, spp=s["spp"],
                          seed=s["seed"], kinds=(s["rays"],), warps=tuple(s["warps"]) if s.get("warps") else None,
                          presets=tuple(s["presets"]), treelet_heights=(s["treelet_height"],), modes=layerbvh.MODES,
                          leaf_size=None, sample=s.get("sample"), cap=s["ray_count"],
                          segments=tuple(s["segments"]) if s.get("segments") else None,
                          branching=s.get("branching", 2))
    try:
        doc = measure_scene(mi, req, progress=False)
    except ValueError as e:
        raise PointError(str(e)) from None
    write_outputs(out / "locality", doc, f"layerbvh sweep --job locality: {point['name']}, {s['rays']} rays")
    return {"report": "locality/summary.md", "resolution": doc["resolution"], "triangles": doc["triangles"],
            **headline(doc)}


RUNNERS = {"compare": run_compare, "converge": run_converge, "bench": run_bench, "third_party": run_third_party,
           "locality": run_locality}


def main(argv=None) -> int:
    _die_with_parent()
    point_file, out = argv or sys.argv[1:]
    point, out = json.loads(Path(point_file).read_text()), Path(out)
    t0 = time.perf_counter()
    try:
        res = {"status": "ok", "figures": RUNNERS[point["job"]](point, out)}
    except PointError as e:
        res = {"status": "error", "error": str(e)}
    except Exception as e:  # noqa: BLE001  (anything else still becomes one line in the table)
        if isinstance(e, ComparisonFailed):
            e = e.error
        traceback.print_exc()
        res = {"status": "error", "error": str(e) if isinstance(e, (UserError, UnsupportedShapeError,
                                                                    converge.ConvergeError))
               else f"{type(e).__name__}: {one_line(e)}"}
    res["point_s"] = time.perf_counter() - t0
    res["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    atomic.write_text(out / "result.json", json.dumps(json_safe(res), allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
