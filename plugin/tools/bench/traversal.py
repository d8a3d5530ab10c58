"""Traversal benchmark: Mrays/s, work per ray, build time and memory of every layerbvh mode against Embree."""
from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh
from layerbvh import from_numpy, meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab import embree
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.repo import ROOT, SCENES
from layerbvh_mitsuba.runtime import record
from layerbvh_mitsuba.tools.bench.traversal_figures import (Config, prim_mismatches, print_agreement, print_table,
    result_rows)

DEFAULT_MESH = SCENES / "meshes" / "bunny.ply"
RAY_KINDS = ("coherent", "incoherent")
LAYER_MODES = ("layer_sorted", "layer_unsorted")
AUTO_HEIGHT = layerbvh.DEFAULT_TREELET_HEIGHT  # the integrator's default


# -- setup ------------------------------------------------------------------------------------------


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--mesh", action="append", default=None,
                   help="PLY/OBJ mesh to bench (repeatable, or a comma list); default: scenes/meshes/bunny.ply")
    p.add_argument("--rays", type=int, default=1_000_000, help="rays per batch (default 1,000,000)")
    p.add_argument("--procedural-tris", type=int, default=600_000,
                   help="triangles of the procedural sphere soup (default 600,000; 0 skips it)")
    p.add_argument("--heights", default="3,4,6,8", help="treelet heights, comma list (default 3,4,6,8)")
    p.add_argument("--branchings", default=str(layerbvh.DEFAULT_BRANCHING),
                   help=f"children per BVH node, comma list of {', '.join(map(str, layerbvh.BRANCHINGS))} "
                        f"(default {layerbvh.DEFAULT_BRANCHING})")
    p.add_argument("--runs", type=int, default=5, help="timed runs per configuration after one warm-up (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural mesh and the rays")
    p.add_argument("--backend", choices=("llvm", "cuda"), default="llvm",
                   help="layerbvh backend (default llvm: the same CPU threads Embree runs on)")
    p.add_argument("--rays-file", action="append", default=[],
                   help="ray recording (.npz from scripts/record_rays.py) to bench: its triangles and every "
                        "recorded ray kind (repeatable)")
    p.add_argument("--kinds", help="comma list of recorded ray kinds to bench (default: all in the file)")
    p.add_argument("--batch-rays", type=int, default=layerbvh.BATCH_RAYS,
                   help="rays per trace batch of the layerbvh modes (default %(default)s; bounds work memory)")
    p.add_argument("--vector-widths", default="",
                   help="comma list of LLVM packet widths (lanes per SIMD packet: 4, 8, 16, 32): the benchmark once "
                        "per width, one process each, merged (default: the CPU's own, 8 with AVX2)")
    p.add_argument("--vector-width", type=int, help=argparse.SUPPRESS)
    p.add_argument("--json", metavar="OUT", help="write every figure to this JSON file")
    args = p.parse_args(argv)
    try:
        args.vector_widths = [int(w) for w in args.vector_widths.split(",") if w.strip()]
    except ValueError:
        p.error(f"--vector-widths must be a comma list of integers, got {args.vector_widths!r}")
    if (args.vector_widths or args.vector_width) and args.backend != "llvm":
        p.error("--vector-widths applies to the llvm backend only")
    try:
        args.heights = [int(h) for h in args.heights.split(",") if h.strip()]
    except ValueError:
        p.error(f"--heights must be a comma list of integers, got {args.heights!r}")
    if not args.heights:
        p.error("--heights is empty")
    try:
        args.branchings = [layerbvh.check_param("branching", int(k)) for k in args.branchings.split(",") if k.strip()]
    except ValueError as e:
        p.error(f"--branchings: {e}")
    if not args.branchings:
        p.error("--branchings is empty")
    if args.rays < 1 or args.runs < 1 or args.procedural_tris < 0 or args.batch_rays < 1:
        p.error("--rays, --runs and --batch-rays must be >= 1, --procedural-tris >= 0")
    args.mesh = [m.strip() for arg in args.mesh for m in arg.split(",") if m.strip()] if args.mesh else None
    args.kinds = [k.strip() for k in args.kinds.split(",") if k.strip()] if args.kinds else None
    return args


def mesh_inputs(args) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, vertices, faces) of every mesh to bench, all loaded up front so a bad file fails at once."""
    out = []
    if args.procedural_tris:
        v, f = meshes.procedural_mesh(args.procedural_tris, seed=args.seed)
        out.append((f"procedural_{args.procedural_tris // 1000}k", v, f))
    paths = args.mesh
    if paths is None:
        if DEFAULT_MESH.exists():
            paths = [str(DEFAULT_MESH)]
        else:
            print(f"(skipping the bunny: {DEFAULT_MESH.relative_to(ROOT)} not found; pass --mesh PATH)")
            paths = []
    for path in paths:
        v, f = meshes.load_mesh(path)
        out.append((Path(path).stem, v, f))
    return out


def embree_scene(v: np.ndarray, f: np.ndarray):
    """A Mitsuba scene holding exactly these triangles (face i = prim i), and its build seconds."""
    t0 = time.perf_counter()
    scene = embree.scene_from_mesh(v, f)
    return scene, time.perf_counter() - t0


# -- timed configurations ---------------------------------------------------------------------------


def timed(fn):
    """(seconds, result) of fn(), with Dr.Jit's queue drained before and after."""
    dr.sync_thread()  # nothing queued from before may be billed to this run
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return time.perf_counter() - t0, out


def embree_config(scene, o: np.ndarray, d: np.ndarray, tmax, any_hit: bool, build_s: float) -> Config:
    ray = embree.rays(o, d, tmax)
    dr.eval(ray)

    def trace():
        if any_hit:
            occ = scene.ray_test(ray)
            dr.eval(occ)
            return occ
        pi = scene.ray_intersect_preliminary(ray)
        dr.eval(pi.t, pi.prim_index, pi.prim_uv, pi.shape)
        return pi

    def run(stats=True):
        secs, pi = timed(trace)
        if any_hit:
            return secs, lambda: pi.numpy().astype(np.uint32), None
        return secs, lambda: dr.select(pi.is_valid(), pi.prim_index, mi.UInt32(layerbvh.MISS)).numpy(), None
    return Config("embree", None, run, build_s=build_s)


def layer_config(bvh, mode: str, height: int, o_dev, d_dev, tmax_dev, any_hit: bool, hint: str = "") -> Config:
    def trace(stats):
        if any_hit:
            occ = bvh.occluded(o_dev, d_dev, tmax_dev, mode=mode, hint=hint, stats=stats)
            dr.eval(occ.occluded)
            return occ.occluded, occ.stats
        h = bvh.trace(o_dev, d_dev, tmax_dev, mode=mode, hint=hint, stats=stats)
        dr.eval(h.t, h.prim, h.u, h.v)
        return h, h.stats

    def run(stats=True):
        secs, (h, stats) = timed(lambda: trace(stats))
        if any_hit:
            return secs, lambda: h.numpy().astype(np.uint32), stats
        return secs, h.prim.numpy, stats
    s = bvh.stats
    return Config(mode, height, run, branching=s.branching, build_s=s.build_s + s.layout_s, bvh_bytes=s.total_bytes)


def make_configs(scene, embree_build_s, bvhs: dict, o, d, tmax, any_hit: bool, backend: str,
                 kind: str = "") -> list[Config]:
    # Rays go to the device once, outside the timing, for Embree and layerbvh alike.
    m = getattr(dr, backend)
    o_dev, d_dev = meshes.device_rays(m, o, d)
    tmax_dev = from_numpy(m.Float, np.asarray(tmax, np.float32)) if tmax is not None else None
    dr.eval(tmax_dev)
    first = next(iter(bvhs))
    configs = [embree_config(scene, o, d, tmax, any_hit, embree_build_s)]
    # per_ray on every layout too: the treelet layout orders its nodes, so it is part of the baseline.
    # auto on the default height (its warm-up run is where it times per_ray against layer_sorted),
    # placed between the two modes it picks from so that every round runs the three back to back
    auto_key = (layerbvh.DEFAULT_BRANCHING, AUTO_HEIGHT) if (layerbvh.DEFAULT_BRANCHING, AUTO_HEIGHT) in bvhs else first
    for (k, h), bvh in bvhs.items():
        configs.append(layer_config(bvh, "per_ray", h, o_dev, d_dev, tmax_dev, any_hit))
        if (k, h) == auto_key:
            configs.append(layer_config(bvh, "auto", h, o_dev, d_dev, tmax_dev, any_hit, hint=kind))
        configs += [layer_config(bvh, mode, h, o_dev, d_dev, tmax_dev, any_hit) for mode in LAYER_MODES]
    return configs


def _rss_bytes(field: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Linux resets the process's peak RSS (VmHWM) to the current RSS on this write."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def measure(configs: list[Config], runs: int) -> None:
    """One warm-up per config (JIT compilation, hits, work counts and its peak RSS), then `runs`
    rounds of every config.

    Each round runs every configuration once, starting one further along each time, so slow
    drifts and bursts of noise on a shared machine land on all configurations alike. Peak RSS is
    taken around the warm-up after returning Dr.Jit's cached allocations to the system, so it
    counts what this configuration itself allocates (kernels, queues, stacks, hits)."""
    for c in configs:
        dr.flush_malloc_cache()
        base = _rss_bytes("VmRSS")
        ok = _reset_peak_rss()
        _, prim, c.stats = c.run()
        c.prim = prim()
        peak = _rss_bytes("VmHWM")
        c.rss_peak, c.rss_extra = (peak, peak - base) if ok and peak and base else (None, None)
    for r in range(runs):
        k = r % len(configs)
        for c in configs[k:] + configs[:k]:
            secs, _, stats = c.run(stats=False)
            c.times.append(secs)
            c.time_stats = stats  # steps and time split of a warm run without work counting


# -- run --------------------------------------------------------------------------------------------


def machine_info(backend: str) -> dict:
    return {"cpu": layerbvh.cpu_model(), "cores": os.cpu_count(), "os": platform.platform(),
            "drjit_threads": dr.thread_count(), "layerbvh_backend": backend, "embree": "mitsuba llvm_ad_rgb"}


def versions() -> dict:
    return {"python": platform.python_version(), "drjit": dr.__version__, "mitsuba": mi.__version__,
            "numpy": np.__version__, "layerbvh": layerbvh.__version__}


def write_json(path: str, doc: dict) -> None:
    """Write atomically: readers never see a half-written file, even if the run dies mid-way."""
    atomic.write_text(path, json.dumps(doc, indent=1))


def generated_ray_sets(v, args):
    """(kind, o, d, tmax, any_hit) of the synthetic ray sets: camera-like and random rays."""
    for kind in RAY_KINDS:
        gen = meshes.camera_rays if kind == "coherent" else meshes.incoherent_rays
        o, d = gen(v, args.rays, seed=args.seed + (1 if kind == "coherent" else 2))
        yield kind, o, d, None, False


def recorded_ray_sets(rays: dict, args):
    """(kind, o, d, tmax, any_hit) of each recorded kind, at most --rays of each (the first ones)."""
    for kind, (o, d, tmax) in rays.items():
        if args.kinds is None or kind in args.kinds:
            n = min(len(o), args.rays)
            yield kind, o[:n], d[:n], tmax[:n], kind == "shadow"


def bench_mesh(name: str, v, f, ray_sets, args, source: str = "generated") -> list[dict]:
    scene, embree_build_s = embree_scene(v, f)
    branchings = getattr(args, "branchings", [layerbvh.DEFAULT_BRANCHING])
    bvhs = {(k, h): layerbvh.build(v, f, treelet_height=h, backend=args.backend, branching=k,
                                   batch_rays=getattr(args, "batch_rays", layerbvh.BATCH_RAYS))
            for k in branchings for h in args.heights}
    rows = []
    width = layerbvh.llvm_vector_width() if args.backend == "llvm" else None
    for kind, o, d, tmax, any_hit in ray_sets:
        configs = make_configs(scene, embree_build_s, bvhs, o, d, tmax, any_hit, args.backend, kind)
        measure(configs, args.runs)
        diff = prim_mismatches(configs)
        kind_rows = result_rows(name, len(f), kind, configs, len(o), diff, any_hit, source)
        for r in kind_rows:
            r["vector_width"] = width
        print_table(kind_rows)
        print()
        print_agreement(diff, len(o), any_hit)
        sys.stdout.flush()
        rows += kind_rows
    return rows


def run_widths(args, argv) -> int:
    """--vector-widths: the whole benchmark once per packet width, each in its own process (Dr.Jit
    reuses compiled kernels across a width change within one process and crashes), merged into
    one JSON whose rows carry `vector_width`."""
    rest, skip = [], False
    for a in argv:  # the same arguments without --vector-widths and --json
        if skip:
            skip = False
        elif a in ("--vector-widths", "--json"):
            skip = True
        elif not a.startswith(("--vector-widths=", "--json=")):
            rest.append(a)
    doc = None
    for width in args.vector_widths:
        print(f"\n# packet width {width} lanes\n", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "bench.json"
            rc = subprocess.call([sys.executable, "-m", "layerbvh_mitsuba.tools.bench.traversal", *rest,
                                  "--vector-width", str(width), "--json", str(out)])
            if rc != 0:
                print(f"error: the run at packet width {width} failed (exit {rc})", file=sys.stderr)
                return rc
            part = json.loads(out.read_text())
        doc = part if doc is None else {**doc, "results": doc["results"] + part["results"]}
    if args.json:
        doc["command"] = shlex.join(getattr(sys, "orig_argv", [sys.executable] + sys.argv))
        write_json(args.json, doc)
        print(f"\nwrote {args.json}")
    print_width_table(doc["results"])
    return 0


def print_width_table(rows: list[dict]) -> None:
    """sorted × per_ray (best height of each) against the packet width, per ray set."""
    widths = sorted({r["vector_width"] for r in rows})
    sets = list(dict.fromkeys((r["mesh"], r["rays"]) for r in rows))
    print("\n## sorted × per_ray against packet width (best treelet height of each mode)\n")
    print("| mesh | rays | " + " | ".join(f"{w} lanes" for w in widths) + " |")
    print("|---|---|" + "---:|" * len(widths))
    for mesh, kind in sets:
        cells = []
        for w in widths:
            sel = [r for r in rows if (r["mesh"], r["rays"], r["vector_width"]) == (mesh, kind, w)]
            best = {m: max((r["mrays_s"] for r in sel if r["mode"] == m), default=None)
                    for m in ("per_ray", "layer_sorted")}
            cells.append("–" if None in best.values() else
                         f"{best['layer_sorted'] / best['per_ray']:.2f} ({best['per_ray']:.2f} / "
                         f"{best['layer_sorted']:.2f} Mr/s)")
        print(f"| {mesh} | {kind} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.vector_widths:
        return run_widths(args, list(sys.argv[1:] if argv is None else argv))
    use_variant()
    if args.vector_width is not None:
        layerbvh.set_llvm_vector_width(args.vector_width)  # before any kernel is compiled
    command = shlex.join(getattr(sys, "orig_argv", [sys.executable] + sys.argv))
    machine = machine_info(args.backend)
    print(f"# Traversal benchmark\n\n`{command}`\n")
    print(f"{machine['cpu']}, {machine['cores']} cores, {machine['os']}; "
          + ", ".join(f"{k} {v}" for k, v in versions().items()))
    print(f"median of {args.runs} runs after one warm-up; Embree = Mitsuba {mi.variant()} "
          f"ray_intersect_preliminary; layerbvh backend {args.backend}; × per_ray: against the fastest per_ray "
          f"over the layouts")
    try:
        inputs = mesh_inputs(args) if (args.mesh or not args.rays_file or args.procedural_tris) else []
        recordings = [(Path(p).stem, *record.load(p)) for p in args.rays_file]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    doc = {"machine": machine, "versions": versions(), "command": command, "runs": args.runs, "results": []}
    for name, v, f in inputs:
        doc["results"] += bench_mesh(name, v, f, generated_ray_sets(v, args), args)
        if args.json:  # after each mesh, so an interrupted run still leaves its figures
            write_json(args.json, doc)
    for name, v, f, rays, meta in recordings:
        doc["results"] += bench_mesh(name, v, f, recorded_ray_sets(rays, args), args,
                                     source=f"recorded from {meta['scene']} ({meta['resolution'][0]}x"
                                            f"{meta['resolution'][1]}, {meta['spp']} spp)")
        if args.json:
            write_json(args.json, doc)
    if args.json:
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
