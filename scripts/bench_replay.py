#!/usr/bin/env python3
"""Seconds the locality replay (layerbvh.locality.replay: the trace through the cache model) takes per
mode and preset, for this checkout or another (a worktree of an earlier commit), to time a change
of the model side by side: run it once per checkout, alternating.

    .venv/bin/python scripts/bench_replay.py [--checkout PATH] [--rays 20000] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkout", default=str(ROOT), help="the checkout whose layerbvh is timed (default: this one)")
    p.add_argument("--rays", type=int, default=20000)
    p.add_argument("--json", help="write the seconds here")
    args = p.parse_args()
    sys.path.insert(0, args.checkout)
    import layerbvh
    from layerbvh import locality, meshes
    from layerbvh.memmodel import preset
    v, f = meshes.load_mesh(str(ROOT / "scenes" / "meshes" / "bunny.ply"))
    o, d = meshes.incoherent_rays(v, args.rays, seed=0)
    tmax = np.full(len(o), np.inf, np.float32)
    bvh = layerbvh.build(v, f, branching=4, treelet_height=8, batch_rays=len(o))
    out = {}
    for name in ("gtx965m", "cpu"):
        pre = preset(name)
        for mode in ("per_ray", "layer_sorted"):
            # (a checkout from before PERFORMANCE.md entry 61 has no step cap to pass)
            tail = (bvh.tail_rays, bvh.tail_fraction) + ((bvh.tail_steps,) if hasattr(bvh, "tail_steps") else ())

            def run(k):
                return locality.replay(bvh.layout, o[:k], d[:k], tmax[:k], mode, False, pre.warp, pre, *tail)
            run(500)  # (numba's compile or cache load)
            times = []
            for _ in range(3):
                t = time.perf_counter()
                run(len(o))
                times.append(time.perf_counter() - t)
            out[f"{name} {mode}"] = min(times)
    print(f"{Path(layerbvh.__file__).parent.parent}: "
          + ", ".join(f"{k} {s:.3f} s" for k, s in out.items()) + f" ({args.rays:,} bunny rays, best of 3)")
    if args.json:
        Path(args.json).write_text(json.dumps({"checkout": args.checkout, "rays": args.rays, "seconds": out,
                                               "command": " ".join(sys.argv)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
