"""What `auto`'s untimed rules (layerbvh/auto.py RULES) rest on, measured again with the tail after one sorted step
(PERFORMANCE.md entry 61): layer_sorted's speed against per_ray's per kind of rays and batch size, on one build,
interleaved (each round alternates the order), median of the timed rounds; resumable JSON (a point already in the
file is not measured again).

    .venv/bin/python scripts/bench_auto_rules.py [--mesh procedural:600000] [--kinds incoherent,camera]
        [--sizes 65536,131072,262144,524288,1048576] [--runs 5] [--out docs/bench/auto_rules.json] [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import layerbvh
from layerbvh import meshes
from layerbvh_mitsuba import atomic

MODES = ("per_ray", "layer_sorted")


def _mesh(spec: str):
    if spec.startswith("procedural:"):
        return meshes.procedural_mesh(int(spec.split(":", 1)[1]))
    return meshes.load_mesh(spec)


def _rays(v, kind: str, n: int):
    if kind == "camera":
        return meshes.camera_rays(v, n, 1)
    if kind == "incoherent":
        return meshes.incoherent_rays(v, n, seed=1)
    raise SystemExit(f"bench_auto_rules: unknown kind of rays {kind!r} (camera, incoherent)")


def _time(bvh, o, d, runs: int) -> dict:
    """Median seconds per mode over `runs` rounds after one untimed round, alternating the order."""
    seconds = {m: [] for m in MODES}
    for r in range(runs + 1):
        for m in MODES if r % 2 == 0 else MODES[::-1]:
            t0 = time.perf_counter()
            np.asarray(bvh.trace(o, d, mode=m, stats=False).prim)
            if r:
                seconds[m].append(time.perf_counter() - t0)
    med = {m: float(np.median(s)) for m, s in seconds.items()}
    return {"seconds": med, "sorted_speed_over_per_ray": med["per_ray"] / med["layer_sorted"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="procedural:600000", help=".ply/.obj or procedural:TRIANGLES")
    ap.add_argument("--kinds", default="incoherent,camera")
    ap.add_argument("--sizes", default="65536,131072,262144,524288,1048576", help="rays per batch")
    ap.add_argument("--runs", type=int, default=5, help="timed rounds after the first")
    ap.add_argument("--out", default="docs/bench/auto_rules.json")
    ap.add_argument("--quick", action="store_true", help="sizes 65536 and 524288, 3 rounds")
    a = ap.parse_args()
    sizes = [65536, 524288] if a.quick else [int(x) for x in a.sizes.split(",")]
    runs = 3 if a.quick else a.runs
    out = Path(a.out)
    doc = json.loads(out.read_text()) if out.exists() else {"points": {}}
    doc["machine"] = {"cpu": layerbvh.cpu_model(), "cores": os.cpu_count(),
                      "llvm_vector_width": layerbvh.llvm_vector_width(), "tail_steps": layerbvh.TAIL_STEPS}
    todo = [(k, n) for k in a.kinds.split(",") for n in sizes if f"{a.mesh}|{k}|{n}" not in doc["points"]]
    if todo:
        v, f = _mesh(a.mesh)
        bvh = layerbvh.build(v, f, batch_rays=max(sizes))
        for kind, n in todo:
            o, d = _rays(v, kind, n)
            doc["points"][f"{a.mesh}|{kind}|{n}"] = {"mesh": a.mesh, "triangles": int(len(f)), "kind": kind,
                                                     "rays": n, "runs": runs, **_time(bvh, o, d, runs)}
            atomic.write_text(out, json.dumps(doc, indent=1) + "\n")
    print(f"{doc['machine']['cpu']}, Dr.Jit LLVM {doc['machine']['llvm_vector_width']} lanes, "
          f"tail_steps {doc['machine']['tail_steps']}")
    print("| mesh | kind | rays | per_ray s | layer_sorted s | layer_sorted speed ÷ per_ray |\n"
          "|---|---|---:|---:|---:|---:|")
    for p in doc["points"].values():
        s = p["seconds"]
        print(f"| {p['mesh']} | {p['kind']} | {p['rays']:,} | {s['per_ray']:.3f} | {s['layer_sorted']:.3f} | "
              f"{p['sorted_speed_over_per_ray']:.2f} |")


if __name__ == "__main__":
    main()
