"""Scaling benchmark: trace time, build time and memory of every mode as the stress scene grows from 10k to 5M
triangles."""
from __future__ import annotations

import argparse
import shlex
import sys

import numpy as np

from layerbvh import meshes
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.tools.bench import stress as gen_stress, traversal as bt

DEFAULT_SIZES = "10k,30k,100k,300k,1M,3M,5M"


def parse_size(text: str) -> int:
    t = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(t[-1:], 1)
    return int(float(t[:-1] if mult > 1 else t) * mult)


def stress_mesh(triangles: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The `spheres` stress scene's triangles (gen_stress), merged into one mesh."""
    parts = gen_stress.sphere_meshes(gen_stress.plan_spheres(triangles), np.random.default_rng(seed))
    vs, fs, off = [], [], 0
    for v, f in parts.values():
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs).astype(np.float32), np.concatenate(fs).astype(np.int64)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sizes", default=DEFAULT_SIZES, help="triangle counts, comma list (default %(default)s)")
    p.add_argument("--rays", type=int, default=500_000, help="random (incoherent) rays per size")
    p.add_argument("--heights", default="4", help="treelet heights of the layer modes (default 4)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="OUT", help="write every figure to this JSON file")
    args = p.parse_args(argv)
    try:
        sizes = [parse_size(s) for s in args.sizes.split(",") if s.strip()]
        heights = [int(h) for h in args.heights.split(",")]
    except ValueError:
        p.error("--sizes and --heights must be comma lists of numbers (sizes may end in k or M)")
    use_variant()
    command = shlex.join(getattr(sys, "orig_argv", [sys.executable] + sys.argv))
    print(f"# Scaling benchmark\n\n`{command}`\n")
    doc = {"machine": bt.machine_info("llvm"), "versions": bt.versions(), "command": command,
           "runs": args.runs, "results": []}
    bargs = argparse.Namespace(heights=heights, runs=args.runs, backend="llvm")
    for n in sizes:
        need = gen_stress.estimate_bytes(n)["total"]
        avail = gen_stress.available_bytes()
        if avail is not None and need > avail:
            print(f"skipping {n:,} triangles: needs about {gen_stress.human(need)}, "
                  f"{gen_stress.human(avail)} available")
            continue
        v, f = stress_mesh(n, args.seed)
        o, d = meshes.incoherent_rays(v, args.rays, seed=args.seed + 2)
        rows = bt.bench_mesh(f"spheres_{len(f)}", v, f, [("incoherent", o, d, None, False)], bargs)
        doc["results"] += rows
        if args.json:
            bt.write_json(args.json, doc)
    if args.json:
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
