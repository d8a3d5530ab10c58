"""What one inverse-rendering iteration costs through our traversal against stock `prb`: a primal
render, and a render with the gradient of a reflectance followed by `dr.backward` (what an
optimisation step runs), side by side in one process (issue 43).

Each scene of `--scenes` (project scenes, default cbox, bunny_box, paper_mix) is rendered with
stock `prb` and with `layerbvh_prb` in each `--traversals` mode at the scene's own max_depth, at
`--res` and `--spp`; every timing is the median of `--reps` runs after one warm-up run (which
compiles the kernels: Dr.Jit's kernel cache then serves them; Python still records each render's
kernels, which is the part that small films pay for). The differentiated parameter is the
scene's first `*.reflectance.value` in `mi.traverse` order.

    .venv/bin/python scripts/bench_prb.py [--scenes cbox bunny_box paper_mix] [--res 128 128] [--spp 16]
        [--reps 5] [--traversals per_ray layer_sorted auto] [--integrator prb|prb_basic]

Prints the CPU, the vector width and one row per scene and side: seconds and ours over stock.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import time

import drjit as dr
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import layerbvh  # noqa: E402
import layerbvh_mitsuba  # noqa: E402,F401  (registers our integrators)
from layerbvh_mitsuba.repo import SCENES  # noqa: E402


def _timed(fn, reps: int) -> float:
    fn()  # warm-up: compiles (or loads from the kernel cache)
    dr.sync_thread()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()  # (Dr.Jit's LLVM backend launches kernels asynchronously)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _iteration(scene, params, key: str, integrator, spp: int):
    """A render with the parameter's gradient on, then dr.backward of the image's sum: the
    gradient an optimiser would step with (evaluated)."""
    def run():
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, integrator=integrator, spp=spp, seed=1)
        dr.backward(dr.sum(image, axis=None))
        g = dr.grad(params[key])
        dr.eval(g)
        dr.disable_grad(params[key])
        params.update()
    return run


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=["cbox", "bunny_box", "paper_mix"])
    p.add_argument("--res", type=int, nargs=2, default=[128, 128], metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--traversals", nargs="+", default=["per_ray", "layer_sorted", "auto"])
    p.add_argument("--integrator", default="prb", choices=["prb", "prb_basic", "path"],
                   help="path: the primal column only, for reference (ours is then `layerbvh`)")
    a = p.parse_args()
    cpu = subprocess.run(["sh", "-c", "lscpu | grep 'Model name'"], capture_output=True, text=True).stdout.strip()
    print(f"{cpu}; Dr.Jit LLVM vector width {layerbvh.llvm_vector_width()} lanes, "
          f"{dr.thread_count()} threads; {a.integrator}, {a.res[0]}x{a.res[1]}, {a.spp} spp, median of {a.reps}")
    print(f"{'scene':<11} {'side':<24} {'primal s':>9} {'x stock':>8} {'iteration s':>12} {'x stock':>8}")
    for name in a.scenes:
        scene = mi.load_file(str(SCENES / f"{name}.xml"), resx=a.res[0], resy=a.res[1])
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("reflectance.value"))
        depth = scene.integrator().max_depth if hasattr(scene.integrator(), "max_depth") else 8
        sides = [("stock " + a.integrator, {"type": a.integrator, "max_depth": depth})]
        ours = "layerbvh" if a.integrator == "path" else f"layerbvh_{a.integrator}"
        sides += [(f"ours {t}", {"type": ours, "max_depth": depth, "traversal": t}) for t in a.traversals]
        base = None
        for label, d in sides:
            integ = mi.load_dict(d)
            primal = _timed(lambda: dr.eval(mi.render(scene, integrator=integ, spp=a.spp, seed=1)), a.reps)
            it = (float("nan") if a.integrator == "path"
                  else _timed(_iteration(scene, params, key, integ, a.spp), a.reps))
            base = base or (primal, it)
            print(f"{name:<11} {label:<24} {primal:9.3f} {primal / base[0]:8.2f} {it:12.3f} {it / base[1]:8.2f}",
                  flush=True)
        print(f"{'':<11} (gradient of {key}, max_depth {depth})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
