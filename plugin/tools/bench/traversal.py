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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

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

DEFAULT_MESH = SCENES / "meshes" / "bunny.ply"
RAY_KINDS = ("coherent", "incoherent")
LAYER_MODES = ("layer_sorted", "layer_unsorted")
AUTO_HEIGHT = layerbvh.DEFAULT_TREELET_HEIGHT  # the integrator's default
MIB = 1 << 20


@dataclass
class Config:
    """One timed configuration: `run(stats)` traces every ray once and returns (seconds, prim, stats).

    The warm-up run counts work (stats=True); the timed runs do not, as a renderer would not:
    `stats` keeps the warm-up's work counts, `time_stats` a timed run's steps and time split."""

    mode: str
    height: int | None
    run: Callable
    branching: int | None = None  # children per node of the layerbvh layout (None: Embree)
    build_s: float | None = None
    bvh_bytes: int | None = None
    times: list = field(default_factory=list)
    prim: np.ndarray | None = None
    stats: object = None
    time_stats: object = None
    rss_peak: int | None = None
    rss_extra: int | None = None

    @property
    def label(self) -> str:
        return self.mode if self.height is None else layout_label(self.mode, self.branching, self.height)


def layout_label(mode: str, branching: int, height: int) -> str:
    """How a configuration is named in tables: its mode, its layout's branching and treelet height."""
    return f"{mode} K={branching} h={height}"


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


# -- figures ----------------------------------------------------------------------------------------


def prim_mismatches(configs: list[Config]) -> dict:
    """Per config label: how many rays' prim differs from per_ray's."""
    ref = next(c for c in configs if c.mode == "per_ray")
    return {c.label: int((c.prim != ref.prim).sum()) for c in configs}


def print_agreement(diff: dict, n: int, any_hit: bool = False) -> None:
    what = "occlusion answer" if any_hit else "prim"
    for label, k in diff.items():
        if k and label != "embree":  # layer modes walk the same tree in the same order: must agree exactly
            print(f"WARNING: {label} returns a different {what} than per_ray on {k:,} of {n:,} rays")
    if diff["embree"] and any_hit:
        print(f"note: Embree's occlusion answer differs from per_ray on {diff['embree']:,} of {n:,} rays "
              f"({1e6 * diff['embree'] / n:.1f} ppm; shared edges and hits at tmax)")
    elif diff["embree"]:
        # Embree may pick the other triangle of a shared edge, so this is a note, not a failure.
        print(f"note: Embree's prim differs from per_ray on {diff['embree']:,} of {n:,} rays "
              f"({1e6 * diff['embree'] / n:.1f} ppm)")
    if not any(k for label, k in diff.items() if label != "embree"):
        print(f"all layerbvh modes and heights return the same {what} for every ray")


def result_rows(mesh: str, tris: int, kind: str, configs: list[Config], n: int, diff: dict,
                any_hit: bool = False, source: str = "generated") -> list[dict]:
    mrays = {c.label: [n / t / 1e6 for t in c.times] for c in configs}
    med = {k: float(np.median(v)) for k, v in mrays.items()}
    # The baseline is the fastest per_ray over the layouts benched (the strongest one).
    per_ray = max(med[c.label] for c in configs if c.mode == "per_ray")
    rows = []
    for c in configs:
        s = c.stats
        # auto against the faster (by median) of the two modes it chooses between, same layout:
        # the median of per-round ratios, since auto runs next to both in every round and a
        # round's neighbours share the machine's state of the moment
        best_of = None
        if c.mode == "auto":
            faster = max((layout_label("per_ray", c.branching, c.height), layout_label("layer_sorted", c.branching, c.height)),
                         key=lambda k: med[k])
            best_of = float(np.median([a / b for a, b in zip(mrays[c.label], mrays[faster])]))
        rows.append({
            "mesh": mesh, "triangles": tris, "rays": kind, "mode": c.mode, "treelet_height": c.height,
            "branching": c.branching,
            "mrays_s": med[c.label], "runs": mrays[c.label], "build_s": c.build_s,
            "bvh_bytes": c.bvh_bytes, "work_bytes": s.work_bytes if s else None,
            "ratio_per_ray": med[c.label] / per_ray, "ratio_embree": med[c.label] / med["embree"],
            "ratio_per_ray_same_h": med[c.label] / med[layout_label("per_ray", c.branching, c.height)] if c.height else None,
            "inner_per_ray": s.inner_nodes_per_ray if s else None,
            "leaves_per_ray": s.leaves_per_ray if s else None,
            "tris_per_ray": s.triangles_per_ray if s else None,
            "iterations_per_ray": s.per_ray("iterations") if s else None,
            # each inner-node visit slab-tests all of the node's child slots: box tests go up with
            # the branching while iterations and dependent node loads (= inner visits) go down
            "box_tests_per_ray": s.inner_nodes_per_ray * c.branching if s else None,
            "steps": s.steps if s else None,
            "ray_count": n, "query": "any_hit" if any_hit else "closest_hit", "source": source,
            "hit_fraction": float(np.mean(c.prim != (0 if any_hit else layerbvh.MISS))),
            "prim_mismatch_vs_per_ray": diff[c.label],
            "rss_peak_bytes": c.rss_peak, "rss_extra_bytes": c.rss_extra,
            "auto_choice": s.mode if c.mode == "auto" and s else None,
            "ratio_best_of_two": best_of,
            "time_split_s": time_split(s, c.time_stats),
        })
    return rows


def time_split(work, timed) -> dict | None:
    """Seconds per stage of a timed run; its kernel time is split into treelet and leaf work by
    the warm-up's share of loop iterations spent on triangles (the timed run counts no work)."""
    if work is None:
        return None
    t = timed or work
    share = work.triangles / work.iterations if work.iterations else 0.0
    return {"sort": t.time_sort_s, "treelet": t.time_traverse_s * (1 - share), "leaf": t.time_traverse_s * share,
            "other": t.time_other_s, "total": t.time_total_s}


def mode_label(r: dict) -> str:
    """The mode, and for auto what it chose (e.g. `auto (per_ray)`)."""
    if r["mode"] == "auto" and r.get("auto_choice"):
        return f"auto ({r['auto_choice'].split(':', 1)[-1]})"
    return r["mode"]


def _fmt(x, spec):
    return "–" if x is None else format(x, spec)


def print_table(rows: list[dict]) -> None:
    r0 = next(r for r in rows if r["mode"] == "per_ray")
    query = "any-hit" if r0["query"] == "any_hit" else "closest-hit"
    print(f"\n## {r0['mesh']} ({r0['triangles']:,} triangles), {r0['rays']} rays, {query} "
          f"({r0['ray_count']:,}, {100 * r0['hit_fraction']:.1f}% hit per per_ray)\n")
    print("| mode | K | h | Mrays/s | runs min–max | × per_ray | × Embree | inner/ray | box tests/ray | iters/ray "
          "| leaves/ray | tris/ray | steps | build s | build Mtris/s | BVH MiB | work MiB | peak RSS +MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        build_rate = r["triangles"] / r["build_s"] / 1e6 if r["build_s"] else None
        print(f"| {mode_label(r)} | {_fmt(r['branching'], 'd')} | {_fmt(r['treelet_height'], 'd')} | {r['mrays_s']:.2f} "
              f"| {min(r['runs']):.2f}–{max(r['runs']):.2f} | {r['ratio_per_ray']:.2f} | {r['ratio_embree']:.2f} "
              f"| {_fmt(r['inner_per_ray'], '.1f')} | {_fmt(r['box_tests_per_ray'], '.1f')} "
              f"| {_fmt(r['iterations_per_ray'], '.1f')} | {_fmt(r['leaves_per_ray'], '.2f')} "
              f"| {_fmt(r['tris_per_ray'], '.1f')} | {_fmt(r['steps'], 'd')} | {_fmt(r['build_s'], '.2f')} "
              f"| {_fmt(build_rate, '.2f')} | {_fmt(r['bvh_bytes'] and r['bvh_bytes'] / MIB, '.1f')} "
              f"| {_fmt(r['work_bytes'] and r['work_bytes'] / MIB, '.1f')} "
              f"| {_fmt(r['rss_extra_bytes'] and r['rss_extra_bytes'] / MIB, '.0f')} |")


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
