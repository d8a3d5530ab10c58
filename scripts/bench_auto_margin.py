"""`auto` against the mode it chose, traced directly: per_ray, layer_sorted and auto on one build,
interleaved (each round alternates the order), median of the timed rounds; auto decides on the
first round (its calibration is not timed). Prints each mode's time, what auto chose and the
ratios (PERFORMANCE.md entry 61: auto must stay within 5% of the faster mode).

    .venv/bin/python scripts/bench_auto_margin.py [--triangles 600000] [--rays 1000000] [--runs 7]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import layerbvh
from layerbvh import meshes

MODES = ("per_ray", "layer_sorted", "auto")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=600_000, help="procedural mesh size")
    ap.add_argument("--rays", type=int, default=1_000_000, help="incoherent rays")
    ap.add_argument("--runs", type=int, default=7, help="timed rounds after the first")
    a = ap.parse_args()
    print(f"{layerbvh.cpu_model()}; Dr.Jit LLVM lanes {layerbvh.llvm_vector_width()}; "
          f"tail_steps {layerbvh.TAIL_STEPS}")
    v, f = meshes.procedural_mesh(a.triangles)
    o, d = meshes.incoherent_rays(v, a.rays, seed=1)
    bvh = layerbvh.build(v, f)
    seconds = {m: [] for m in MODES}
    for r in range(a.runs + 1):
        for m in MODES if r % 2 == 0 else MODES[::-1]:
            t0 = time.perf_counter()
            h = bvh.trace(o, d, mode=m, stats=False, hint="bounce")
            np.asarray(h.prim)
            if r:
                seconds[m].append(time.perf_counter() - t0)
            elif m == "auto":
                print(f"auto chose {h.stats.mode}: {next(iter(bvh.auto_choices.values()))['reason']}")
    med = {m: float(np.median(s)) for m, s in seconds.items()}
    for m in MODES:
        print(f"{m:13s} median {med[m]:.3f} s (min {min(seconds[m]):.3f}, max {max(seconds[m]):.3f})")
    faster = min(med["per_ray"], med["layer_sorted"])
    print(f"layer_sorted speed / per_ray {med['per_ray'] / med['layer_sorted']:.2f}; "
          f"auto time / the faster mode's {med['auto'] / faster:.2f}")


if __name__ == "__main__":
    main()
