#!/usr/bin/env python3
"""How long packing the layer modes' ray records takes (state.RayRecords, PERFORMANCE.md entry 59):
the one-kernel packing against the six-scatter packing it replaced, interleaved in one process.

    .venv/bin/python scripts/bench_ray_records.py [--rays 1048576] [--repeats 15] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    import drjit as dr

    import layerbvh
    from layerbvh import backend as be
    from layerbvh.state import RayRecords
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rays", type=int, default=1 << 20)
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--json", help="write the medians here")
    args = p.parse_args()
    m = be.module("llvm")
    n = args.rays
    rng = np.random.default_rng(0)
    o = [m.Float(rng.random(n, dtype=np.float32)) for _ in range(3)]
    d = [m.Float(rng.random(n, dtype=np.float32)) for _ in range(3)]
    dr.eval(*o, *d)

    def six_scatters():  # (the packing before entry 59: a memset, then one kernel per component)
        rec = dr.zeros(m.Float, n * RayRecords.STRIDE)
        idx = dr.arange(m.UInt32, n) * RayRecords.STRIDE
        for c, x in enumerate(tuple(o) + tuple(d)):
            dr.scatter(rec, x, idx + c)
        dr.eval(rec)
        return rec

    def one_kernel():
        return RayRecords(m, o, d).rec
    sides = {"six_scatters": six_scatters, "one_kernel": one_kernel}
    assert np.array_equal(np.asarray(six_scatters()), np.asarray(one_kernel())), "the packings differ"
    times = {k: [] for k in sides}
    for _ in range(args.repeats):
        for name, f in sides.items():
            dr.sync_thread()
            t = time.perf_counter()
            f()
            dr.sync_thread()
            times[name].append(time.perf_counter() - t)
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"{n:,} rays, {be.llvm_vector_width()} lanes ({layerbvh.cpu_model()}): "
          + ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in med.items())
          + f"; {med['six_scatters'] / med['one_kernel']:.1f}x")
    if args.json:
        Path(args.json).write_text(json.dumps({"rays": n, "lanes": be.llvm_vector_width(), "cpu": layerbvh.cpu_model(),
                                               "median_s": med, "command": " ".join(sys.argv)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
