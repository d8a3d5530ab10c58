"""Kernels compiled and LLVM seconds, with an empty Dr.Jit kernel cache: what a fresh clone's test
suite and a user's first run pay (issue 39).

Each measurement runs in a fresh process with its own empty HOME (so an empty ~/.drjit):
- `counted SCENE MODE`: a counted render (stats on: the wavefront loop, what every `compare`'s
  statistics pass runs) at 64x64, 4 spp;
- `cases A B`: two stability ray cases in one process; the second case's new kernels say whether
  kernels are shared between trees (they should be: per-tree numbers are kernel parameters).

    .venv/bin/python scripts/bench_compile.py            # all rows
Prints the CPU, the vector width and one line per measurement.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

ROWS = [("counted", "cbox", "per_ray"), ("counted", "cbox", "layer_sorted"),
        ("cases", "scale_1e-4", "scale_1e4")]

CHILD = r"""
import json, sys, drjit as dr
from layerbvh_mitsuba.runtime.compile_clock import compile_seconds
def compiled(h):
    h = [k for k in h if k.get("hash")]
    return h, [k for k in h if not k.get("cache_hit")]
kind, a, b = sys.argv[1:4]
dr.set_flag(dr.JitFlag.KernelHistory, True)
out = {}
if kind == "counted":
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from layerbvh_mitsuba.ab.render import load_integrator
    from layerbvh_mitsuba.repo import SCENES
    scene = mi.load_file(str(SCENES / f"{a}.xml"), resx=64, resy=64)
    integ = load_integrator(mi, {"type": "layerbvh", "traversal": b, "stats": True})
    dr.kernel_history()
    mi.render(scene, integrator=integ, spp=4)
    h, c = compiled(dr.kernel_history())
    out = {"launches": len(h), "distinct": len({k["hash"] for k in h}), "compiled": len(c),
           "compile_s": compile_seconds(c)}
else:
    from layerbvh_mitsuba.tools.stability import cases as sc
    seen = set()
    for name in (a, b):
        dr.kernel_history()
        sc.run_case(name)
        h, c = compiled(dr.kernel_history())
        new = [k for k in c if k["hash"] not in seen]
        seen |= {k["hash"] for k in h}
        out[name] = {"new_kernels": len(new), "compile_s": compile_seconds(new)}
print(json.dumps(out))
"""


def main() -> int:
    py = sys.executable
    cpu = subprocess.run(["sh", "-c", "lscpu | grep 'Model name'"], capture_output=True, text=True).stdout.strip()
    lanes = subprocess.run([py, "-c", "import layerbvh; print(layerbvh.llvm_vector_width())"],
                           capture_output=True, text=True).stdout.strip()
    print(f"{cpu}; Dr.Jit LLVM lanes {lanes}")
    for row in ROWS:
        with tempfile.TemporaryDirectory() as home:
            env = {**os.environ, "HOME": home, "XDG_CACHE_HOME": os.path.join(home, ".cache")}
            r = subprocess.run([py, "-c", CHILD, *row], capture_output=True, text=True, env=env)
        if r.returncode != 0:
            print(f"{' '.join(row)}: failed: {r.stderr.strip().splitlines()[-1:]}")
            return 1
        res = json.loads(r.stdout.strip().splitlines()[-1])
        if row[0] == "counted":
            print(f"counted render {row[1]} {row[2]}: {res['distinct']} distinct kernels in "
                  f"{res['launches']} launches, {res['compiled']} compiled, {res['compile_s']:.1f} s of LLVM")
        else:
            print("stability cases in one process: " + "; ".join(
                f"{n} {v['new_kernels']} new kernels, {v['compile_s']:.1f} s" for n, v in res.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
