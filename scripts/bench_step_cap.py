"""The wavefront tail's step cap (a LayerBVH's tail_steps, default wavefront.TAIL_STEPS): steps and time
of layer_sorted with the cap and without it, side by side in one run (scripts/tail_cutoff.py compares caps).

Rows: turned slivers (meshes.turned_slivers: every ray walks most of the tree, hundreds of steps)
and incoherent rays on the bunny and on 600k procedural triangles (typical batches: the cap
should not apply). Without the cap means the tail rule as before it: tail_rays and tail_fraction
only (`--rays` rays; the cap is the only difference).

    .venv/bin/python scripts/bench_step_cap.py [--rays N] [--runs 3]
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import time

import numpy as np

import layerbvh
from layerbvh import meshes, wavefront
from layerbvh_mitsuba.repo import SCENES


def timed(bvh, o, d, runs: int):
    bvh.trace(o, d, mode="layer_sorted")  # (compiles)
    times, h = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        h = bvh.trace(o, d, mode="layer_sorted")
        times.append(time.perf_counter() - t0)
    return h, statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1 << 20, help="incoherent rays per mesh row")
    ap.add_argument("--runs", type=int, default=3)
    a = ap.parse_args()
    cpu = subprocess.run(["sh", "-c", "lscpu | grep 'Model name'"], capture_output=True, text=True).stdout.strip()
    print(f"{cpu}; Dr.Jit LLVM lanes {layerbvh.llvm_vector_width()}; TAIL_STEPS {wavefront.TAIL_STEPS}")
    bunny = meshes.load_mesh(SCENES / "meshes" / "bunny.ply")
    proc = meshes.procedural_mesh(600_000, seed=3)
    sv, sf, so, sd = meshes.turned_slivers()
    rows = [("turned slivers (2,000 tris, 3,000 rays)", sv, sf, so, sd)]
    for name, (v, f) in (("bunny incoherent", bunny), ("600k procedural incoherent", proc)):
        o, d = meshes.incoherent_rays(v, a.rays, seed=1)
        rows.append((name, np.asarray(v, np.float32), f, o, d))
    for name, v, f, o, d in rows:
        bvh = layerbvh.build(v, f)
        capped, t_capped = timed(bvh, o, d, a.runs)
        bvh.tail_steps = 1 << 16  # (the cap off: the rays-left rule alone)
        uncapped, t_uncapped = timed(bvh, o, d, a.runs)
        bvh.tail_steps = wavefront.TAIL_STEPS
        same = bool((capped.prim == uncapped.prim).all() and (capped.t == uncapped.t).all())
        print(f"{name}: steps {uncapped.stats.steps} -> {capped.stats.steps} (tail rays {uncapped.stats.tail_rays} -> "
              f"{capped.stats.tail_rays}), {t_uncapped:.3f} -> {t_capped:.3f} s ({t_uncapped / t_capped:.2f}x), "
              f"same hits {same}")


if __name__ == "__main__":
    main()
