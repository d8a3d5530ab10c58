"""The walk kernels' hashes and IR op counts in every mode (per_ray, layer_sorted), branching (2, 4,
8), query (closest, closest with statistics, any hit) and an instanced layout: run it before and
after a change to the kernel's Python, and diff. The same hash is the same LLVM IR, so the same
speed.

    .venv/bin/python scripts/kernel_hashes.py > before.txt   # (then again after the change; diff)
"""
import argparse
import re
import subprocess
import sys

CHILD = r'''
import sys
import numpy as np
import drjit as dr
import layerbvh
from layerbvh import meshes

v, f = meshes.procedural_mesh(20000, seed=1)
o, d = meshes.incoherent_rays(v, 4096, seed=2)


def run(label, fn):
    print(f"### {label}", flush=True)
    fn()
    dr.sync_thread()
    sys.stdout.flush()


dr.set_log_level(dr.LogLevel.Info)
for K in (2, 4, 8):
    bvh = layerbvh.build(v, f, treelet_height=3, branching=K)
    for mode in ("per_ray", "layer_sorted"):
        run(f"K={K} {mode} closest", lambda: dr.eval(bvh.trace(o, d, mode=mode, stats=False).prim))
        run(f"K={K} {mode} closest stats", lambda: dr.eval(bvh.trace(o, d, mode=mode, stats=True).prim))
        run(f"K={K} {mode} any", lambda: dr.eval(bvh.occluded(o, d, mode=mode, stats=False).occluded))
shift = [np.eye(4) + np.pad([[0, 0, 0, x]], ((0, 3), (0, 0))) for x in range(0, 8, 2)]
ib = layerbvh.build_instanced([layerbvh.Group(*meshes.uv_sphere(24, 12))], [layerbvh.Instance(0, m) for m in shift],
                              treelet_height=2, branching=4)
for mode in ("per_ray", "layer_sorted"):
    run(f"instanced K=4 {mode}", lambda: dr.eval(ib.trace(o, d, mode=mode, stats=True).prim))
'''
MIN_OPS = 300  # the walk kernels; smaller ones are set-up, sort and moves


def main(argv=None) -> int:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args(argv)
    # Dr.Jit logs from C++ onto the process's own streams: read them from a child.
    p = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True)
    if p.returncode:
        print(p.stderr[-2000:], file=sys.stderr)
        return p.returncode
    label, kernels = None, {}
    for line in (p.stdout + p.stderr).splitlines():
        if line.startswith("### "):
            label = line[4:]
            kernels[label] = set()
        elif label and (m := re.search(r"launching ([0-9a-f]{16}) \(.*?ops=(\d+)", line)) and int(m.group(2)) > MIN_OPS:
            kernels[label].add((m.group(1), int(m.group(2))))
    for label, ks in kernels.items():
        print(f"{label}: " + ", ".join(f"{h} ({ops} ops)" for h, ops in sorted(ks)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
