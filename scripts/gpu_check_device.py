"""The device half of the GPU check (scripts/gpu_check.sh): times per_ray and layer_sorted on the recorded rays on the GPU, checks their hits against the LLVM replay's, and prints the measured layer_sorted x per_ray beside the locality model's prediction for that GPU.

Needs only the engine (layerbvh: numpy, numba, drjit), so it runs on a device image without
Mitsuba:  python scripts/gpu_check_device.py out/gpu_check [--backend cuda] [--runs 5]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's layerbvh, wherever it runs

import drjit as dr  # noqa: E402
import numpy as np  # noqa: E402

import layerbvh  # noqa: E402

MODES = ("per_ray", "layer_sorted")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="what plugin/tools/bench/gpu_check.py wrote (rays.npz, model.json)")
    p.add_argument("--backend", default="cuda")
    p.add_argument("--runs", type=int, default=5)
    args = p.parse_args(argv)
    folder = Path(args.folder)
    z = np.load(folder / "rays.npz")
    model = json.loads((folder / "model.json").read_text())
    h = model["treelet_height"]
    bvh = layerbvh.build(z["vertices"], z["faces"], treelet_height=h, backend=args.backend, branching=2)  # the model's tree
    print(f"backend {args.backend}; {len(z['faces']):,} triangles, treelet height {h}; model preset "
          f"{model['preset']['name']}")
    print(f"{'kind':22} {'rays':>8} {'per_ray Mrays/s':>16} {'sorted Mrays/s':>15} {'measured sorted x per_ray':>26} "
          f"{'model per_ray/sorted DRAM':>26} {'... + between steps':>20} {'hits != replay':>15}")
    result = []
    for kind in model["kinds"]:
        o, d, tmax = z[f"{kind}_o"], z[f"{kind}_d"], z[f"{kind}_tmax"]
        any_hit = kind == "shadow"
        m = bvh.m
        O = m.Array3f(*(m.Float(np.ascontiguousarray(o[:, c])) for c in range(3)))  # on the device, as a
        D = m.Array3f(*(m.Float(np.ascontiguousarray(d[:, c])) for c in range(3)))  # renderer passes them
        T = m.Float(tmax)

        def trace(mode):
            if any_hit:
                q = bvh.occluded(O, D, T, mode=mode, stats=False)
                dr.eval(q.occluded)
                return q.occluded
            hit = bvh.trace(O, D, T, mode=mode, stats=False)
            dr.eval(hit.prim)
            return hit.prim
        want = z[f"{kind}_prim"]
        bad = {}
        for mode in MODES:  # warm-up (compiles) and the exactness check against the LLVM replay
            got = np.asarray(trace(mode))
            bad[mode] = int(np.count_nonzero(got != (want != layerbvh.MISS))) if any_hit else \
                int(np.count_nonzero(got.astype(np.int64) != want))
        times = {mode: [] for mode in MODES}
        for _ in range(args.runs):  # interleaved rounds
            for mode in MODES:
                dr.sync_thread()
                t0 = time.perf_counter()
                trace(mode)
                dr.sync_thread()
                times[mode].append(time.perf_counter() - t0)
        med = {mode: statistics.median(t) for mode, t in times.items()}
        rows = {r["mode"]: r for r in model["rows"] if r["kind"] == kind}
        pr, so = rows["per_ray"], rows["layer_sorted"]
        pred_dram = pr["dram_bytes_per_ray"] / so["dram_bytes_per_ray"]
        pred_total = pr["dram_bytes_per_ray"] / so["total_dram_bytes_per_ray"]
        speed = med["per_ray"] / med["layer_sorted"]
        n = len(o)
        print(f"{kind:22} {n:8,} {n / med['per_ray'] / 1e6:16.2f} {n / med['layer_sorted'] / 1e6:15.2f} "
              f"{speed:26.2f} {pred_dram:26.2f} {pred_total:20.2f} {bad['per_ray']:>7}/{bad['layer_sorted']:<7}")
        result.append({"kind": kind, "rays": n, "seconds": med, "measured_sorted_over_per_ray": speed,
                       "model_dram_per_ray_over_sorted": pred_dram, "model_total_per_ray_over_sorted": pred_total,
                       "hits_differing_from_replay": bad})
    (folder / f"measured_{args.backend}.json").write_text(json.dumps({"backend": args.backend, "kinds": result},
                                                                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
