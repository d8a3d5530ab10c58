"""The tail's step cap (issue 57 items 1 and 3): after k sorted wavefront steps, one per-ray kernel finishes the
rays left in the order the last step sorted them. For each k, the locality model's DRAM bytes and steps per ray on
a GPU preset, and layer_sorted's CPU time against per_ray's, on a scene's recorded rays or a mesh's; resumable
JSON (a point already in the file is not measured again)."""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

import layerbvh
from layerbvh import meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT

DEFAULT_STEPS = (1, 2, 3, 4, 8, 32)  # (32: the cap before entry 61, where the rays-left rule ends most batches)
SECTION = "tail_cutoff"  # BENCHMARKS.md's section, generated from the JSON (--benchmarks)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scene", action="append", default=[], help="Mitsuba 3 XML scene: its recorded rays")
    p.add_argument("--mesh", action="append", default=[], help=".ply/.obj or procedural:TRIANGLES: incoherent rays")
    p.add_argument("--out", required=True, help="the JSON file (read first: points in it are kept)")
    p.add_argument("--kinds", default="diffuse,shadow", help="a scene's kinds of rays (default %(default)s)")
    p.add_argument("--res", type=int, nargs=2, default=(1024, 1024), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=1)
    p.add_argument("--rays", type=int, default=1 << 20, help="a mesh's incoherent rays (default %(default)s)")
    p.add_argument("--sample", type=int, help="replay and time at most N rays per kind (default: all)")
    p.add_argument("--steps", default=",".join(map(str, DEFAULT_STEPS)),
                   help="the step caps k to measure (default %(default)s)")
    p.add_argument("--heights", default=str(layerbvh.DEFAULT_TREELET_HEIGHT), help="treelet heights (default 8)")
    p.add_argument("--branching", type=int, default=layerbvh.DEFAULT_BRANCHING, choices=layerbvh.BRANCHINGS)
    p.add_argument("--preset", default="gtx965m")
    p.add_argument("--warp", type=int, default=32)
    p.add_argument("--runs", type=int, default=3, help="timed runs of each configuration, interleaved")
    p.add_argument("--no-model", action="store_true", help="CPU timings only")
    p.add_argument("--no-time", action="store_true", help="the model only")
    p.add_argument("--quick", action="store_true", help="65,536 rays, k = 1 and 32, one run")
    p.add_argument("--benchmarks", action="store_true",
                   help="measure nothing: write BENCHMARKS.md's section from the JSON (--out)")
    return p.parse_args(argv)


def ray_sources(args):
    """(name, vertices, faces, [RaySet]) per --scene and --mesh."""
    for spec in args.mesh:
        v, f = (meshes.procedural_mesh(int(spec.split(":", 1)[1])) if spec.startswith("procedural:")
                else meshes.load_mesh(spec))
        o, d = meshes.incoherent_rays(v, args.rays, seed=1)
        yield spec, v, f, [layerbvh.RaySet("incoherent", o, d, np.full(len(o), np.inf, np.float32))]
    if args.scene:
        from layerbvh_mitsuba.ab.render import use_variant  # local: Mitsuba only where a scene is recorded
        from layerbvh_mitsuba.tools.bench.locality import ANY_HIT_KINDS, DEFAULT_CAP  # local: as above
        from layerbvh_mitsuba.tools.bench.record_rays import cached_recording  # local: as above
        mi = use_variant("llvm_ad_rgb")
        kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
        for scene in args.scene:
            v, f, rays, _ = cached_recording(mi, scene, tuple(args.res), args.spp, 0, DEFAULT_CAP)
            sets = [layerbvh.RaySet(k, *rays[k], any_hit=k in ANY_HIT_KINDS) for k in kinds if k in rays]
            yield Path(scene).parent.name if Path(scene).name == "scene.xml" else Path(scene).stem, v, f, sets


def _model(bvh, rs, o, d, t, mode, k, pre, warp, h):
    bvh.tail_steps = k  # (the replay and the kernel it is checked against both follow it)
    rep = layerbvh.replay_tree(bvh, o, d, t, mode, rs.any_hit, warp, pre)
    chk = layerbvh.check_trace(bvh, o, d, t, rs.any_hit, rep)
    return layerbvh.locality_row(rs.kind, rep, h, check=chk)


def _time(bvh, rs, o, d, t, ks, runs) -> dict:
    """Median seconds of per_ray and of layer_sorted at each k, the runs interleaved (a slow spell
    of the machine hits every configuration alike); the hits of every configuration must equal."""
    configs = [("per_ray", layerbvh.TAIL_STEPS)] + [("layer_sorted", k) for k in ks]
    seconds = {c: [] for c in configs}
    ref = None
    for r in range(runs + 1):  # (the first round compiles: not timed)
        for mode, k in configs:
            bvh.tail_steps = k
            t0 = time.perf_counter()
            q = bvh.occluded(o, d, t, mode=mode) if rs.any_hit else bvh.trace(o, d, t, mode=mode)
            hit = np.asarray(q.occluded if rs.any_hit else q.prim)
            if r:
                seconds[(mode, k)].append(time.perf_counter() - t0)
            if ref is None:
                ref = hit
            elif not np.array_equal(hit, ref):
                raise AssertionError(f"{rs.kind}: layer_sorted with tail_steps {k} changed the hits")
    med = {f"{m}" if m == "per_ray" else f"k{k}": float(np.median(s)) for (m, k), s in seconds.items()}
    return {"seconds": med, "sorted_speed_over_per_ray": {c: med["per_ray"] / s for c, s in med.items()
                                                          if c != "per_ray"}}


def measure(args, doc: dict, save) -> None:
    ks = [int(x) for x in args.steps.split(",")]
    pre = layerbvh.preset(args.preset)
    for name, v, f, sets in ray_sources(args):
        for h in (int(x) for x in args.heights.split(",")):
            bvh = None
            for rs in sets:
                o, d, t, _ = layerbvh.sample_rays(rs.o, rs.d, rs.tmax, args.sample, 0)
                base = f"{name}|{rs.kind}|K{args.branching}|H{h}"
                todo = [] if args.no_model else [k for k in [None, *ks] if f"{base}|{k or 'per_ray'}" not in doc]
                if not todo and (args.no_time or f"{base}|cpu" in doc):
                    continue
                if bvh is None:
                    bvh = layerbvh.build(v, f, treelet_height=h, branching=args.branching,
                                         batch_rays=max(len(s.o) for s in sets))
                per = None
                for k in todo:
                    mode = "per_ray" if k is None else "layer_sorted"
                    row = _model(bvh, rs, o, d, t, mode, k or layerbvh.TAIL_STEPS, pre, args.warp, h)
                    if k is None:
                        per = row
                    else:
                        per = per or layerbvh.LocalityRow(**doc[f"{base}|per_ray"]["row"])
                        layerbvh.step_limits([per, row])
                    doc[f"{base}|{k or 'per_ray'}"] = {"source": name, "kind": rs.kind, "treelet_height": h,
                                                       "branching": args.branching, "tail_steps": k,
                                                       "triangles": int(len(f)), "row": row.as_dict()}
                    save(doc)
                    print(f"{base}|{k or 'per_ray'}: total DRAM {row.total_dram_bytes_per_ray:.1f} B/ray, "
                          f"steps/ray {row.steps_per_ray:.2f}, exact {row.trace_exact}", flush=True)
                if not args.no_time and f"{base}|cpu" not in doc:
                    doc[f"{base}|cpu"] = {"source": name, "kind": rs.kind, "treelet_height": h, "rays": len(o),
                                          **_time(bvh, rs, o, d, t, ks, args.runs)}
                    save(doc)
                    print(f"{base}|cpu: {doc[f'{base}|cpu']['sorted_speed_over_per_ray']}", flush=True)


def table(doc: dict) -> str:
    """Markdown: per source, kind and height, each k's total DRAM bytes over per_ray's, node and
    triangle bytes over per_ray's, steps per ray, bytes per step against break-even and lower
    bound, and the CPU's layer_sorted speed over per_ray's."""
    lines = ["| source | rays | H | k | total DRAM ÷ per_ray | node+tri ÷ per_ray | steps/ray "
             "| between steps B/ray·step (break-even, bound) | CPU speed ÷ per_ray |",
             "|---|---|---:|---:|---:|---:|---:|---|---:|"]
    points = doc["points"]
    for key, p in points.items():
        if p.get("tail_steps") is None or "row" not in p:
            continue
        per = points.get(key.rsplit("|", 1)[0] + "|per_ray")
        cpu = points.get(key.rsplit("|", 1)[0] + "|cpu")
        if per is None:
            continue
        r, q = p["row"], per["row"]
        nt = ((r["node_dram_bytes_per_ray"] + r["triangle_dram_bytes_per_ray"])
              / (q["node_dram_bytes_per_ray"] + q["triangle_dram_bytes_per_ray"]))
        be, lb = r.get("break_even_bytes_per_ray_step"), r.get("lower_bound_bytes_per_ray_step")
        speed = cpu and cpu["sorted_speed_over_per_ray"].get(f"k{p['tail_steps']}")
        lines.append(f"| {p['source']} ({p['triangles']:,} tris) | {p['kind']} ({r['rays']:,}) | "
                     f"{p['treelet_height']} | {p['tail_steps']} | "
                     f"{r['total_dram_bytes_per_ray'] / q['total_dram_bytes_per_ray']:.2f} | {nt:.2f} | "
                     f"{r['steps_per_ray']:.2f} | {r['sort_bytes_per_ray_step']:.0f} "
                     f"({'–' if be is None else f'{be:.0f}'}, {'–' if lb is None else f'{lb:.0f}'}) | "
                     f"{'–' if not speed else f'{speed:.2f}'} |")
    return "\n".join(lines)


def best(doc: dict) -> list[str]:
    """Per source, kind and height: the k with the least total DRAM bytes in the model and the
    fastest k on the CPU, each against per_ray."""
    points, out = doc["points"], []
    bases = dict.fromkeys(k.rsplit("|", 1)[0] for k in points)
    for base in bases:
        per, cpu = points.get(base + "|per_ray"), points.get(base + "|cpu")
        caps = {p["tail_steps"]: p["row"] for k, p in points.items()
                if k.rsplit("|", 1)[0] == base and p.get("tail_steps") is not None}
        if per is None or not caps:
            continue
        total = per["row"]["total_dram_bytes_per_ray"]
        k_model = min(caps, key=lambda k: caps[k]["total_dram_bytes_per_ray"])
        line = (f"{base}: least DRAM at k = {k_model} ({caps[k_model]['total_dram_bytes_per_ray'] / total:.2f}x "
                f"per_ray, {caps[k_model]['steps_per_ray']:.2f} steps per ray)")
        if cpu:
            speed = cpu["sorted_speed_over_per_ray"]
            k_cpu = max(speed, key=speed.get)
            line += f"; fastest on the CPU at k = {k_cpu.removeprefix('k')} ({speed[k_cpu]:.2f}x per_ray's speed)"
        out.append(line)
    return out


def section(doc: dict) -> str:
    """BENCHMARKS.md's section: the commands, the machine, the table and each set's best k."""
    m = doc.get("machine", {})
    return "\n".join(["## The tail's step cap (`scripts/tail_cutoff.py`, docs/bench/tail_cutoff.json)", "",
                      "After k sorted wavefront steps one per-ray kernel finishes the rays left, in the order the "
                      "last step sorted them. Model: `gtx965m`, W = 32, total DRAM bytes with the traffic between "
                      "steps and the hits written; CPU: layer_sorted's median time against per_ray's, interleaved "
                      f"({m.get('cpu')}, Dr.Jit LLVM {m.get('llvm_vector_width')} lanes). Every replay was checked "
                      "against the kernel ray by ray; every timed configuration returned the same hits.", "",
                      *[f"`{c}`  " for c in doc.get("commands", [])], "", table(doc), "",
                      *[f"- {line}" for line in best(doc)], ""])


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.benchmarks:
        atomic.splice_section(ROOT / "BENCHMARKS.md", SECTION, section(json.loads(Path(args.out).read_text())))
        print(f"replaced the {SECTION} section of BENCHMARKS.md")
        return 0
    if args.quick:
        args.sample, args.steps, args.runs = 1 << 16, "1,32", 1
    out = Path(args.out)
    doc = json.loads(out.read_text()) if out.is_file() else {}
    doc.setdefault("points", {})
    doc["machine"] = {"cpu": layerbvh.cpu_model(), "llvm_vector_width": layerbvh.llvm_vector_width()}
    doc.setdefault("commands", [])
    command = "python scripts/tail_cutoff.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    if command not in doc["commands"]:
        doc["commands"].append(command)

    def save(d):
        atomic.write_text(out, json.dumps(d, indent=1) + "\n")
    measure(args, doc["points"], lambda _: save(doc))
    save(doc)
    print(table(doc))
    return 0
