"""The GPU check of the locality model: measured layer_sorted x per_ray on the GPU beside what the model predicts for its preset, from one ray recording and one traversal benchmark (scripts/gpu_check.sh)."""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import layerbvh
from layerbvh.locality import LocalitySettings, RaySet, measure

from .. import record
from .locality import rows_of

MODEL_RAYS = 200_000  # rays per kind the model replays (sampled, and said): the check must fit in minutes


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--rays", required=True, help="ray recording (.npz, scripts/record_rays.py)")
    p.add_argument("--bench", required=True, help="bench_traversal.py --json output on the same recording")
    p.add_argument("--preset", default="h200", help="the GPU's preset (default %(default)s)")
    p.add_argument("--height", type=int, default=layerbvh.DEFAULT_TREELET_HEIGHT)
    p.add_argument("--json", help="write the comparison here")
    args = p.parse_args(argv)
    v, f, rays, _ = record.load(args.rays)
    bench = json.loads(open(args.bench).read())
    measured = {}
    for r in bench["results"]:
        if r["mode"] in ("per_ray", "layer_sorted") and r["treelet_height"] == args.height:
            measured[(r["rays"], r["mode"])] = r["mrays_s"]
    kinds = sorted({k for k, _ in measured} & set(rays))
    sets = [RaySet(k, *rays[k], any_hit=k == "shadow") for k in kinds]
    run = measure(v, f, sets, LocalitySettings(modes=("per_ray", "layer_sorted"), presets=(args.preset,),
                                               treelet_heights=(args.height,), sample=MODEL_RAYS), 4)
    rows = rows_of(run.as_dict())
    out = []
    print(f"{'kind':22} {'measured sorted x per_ray':>26} {'model: DRAM bytes':>18} {'model: +between steps':>22} "
          f"{'model: node tx':>15}   (model: per_ray / sorted; >1 means sorted predicted faster)")
    for k in kinds:
        pr = next(r for r in rows if r.kind == k and r.mode == "per_ray")
        so = next(r for r in rows if r.kind == k and r.mode == "layer_sorted")
        speed = measured[(k, "layer_sorted")] / measured[(k, "per_ray")]
        pred = {"dram": pr.dram_bytes_per_ray / so.dram_bytes_per_ray,
                "total": pr.dram_bytes_per_ray / so.total_dram_bytes_per_ray,
                "node_tx": pr.node_transactions_per_ray / so.node_transactions_per_ray}
        out.append({"kind": k, "measured_sorted_over_per_ray": speed, "model": pred, "rays_modelled": so.rays,
                    "sampled_from": so.sampled_from})
        print(f"{k:22} {speed:26.2f} {pred['dram']:18.2f} {pred['total']:22.2f} {pred['node_tx']:15.2f}")
    if not all(c["exact"] for c in run.checks):
        print("warning: the trace differs from the kernel on some rays", file=sys.stderr)
    if args.json:
        from .. import atomic
        atomic.write_text(args.json, json.dumps({"preset": args.preset, "height": args.height, "kinds": out,
                                                 "checks": run.checks}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
