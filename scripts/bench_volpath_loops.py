"""Time layerbvh_volpath's and layerbvh_volpathmis's two loop forms on Mitsuba's media test scenes:
the megakernel (per_ray) against the wavefront loop (layer_sorted), and stock beside them, side by
side in one run, warm kernels.

    .venv/bin/python scripts/bench_volpath_loops.py [--res 48] [--spp 16]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

MEDIA = Path(__file__).resolve().parents[1] / "scenes" / "media"
SCENES = ["test_homo_emitter_inside_medium_volpath", "test_hetero_sigmat_volpath", "test_surf_area_light_volpath",
          "test_homo_spectral_sigmat_volpathmis", "test_hetero_spectral_sigmat_volpathmis"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    mi.set_variant("llvm_ad_rgb")
    import layerbvh
    import layerbvh_mitsuba  # noqa: F401  (registers the integrators)
    print(f"CPU: {layerbvh.cpu_model()}; Dr.Jit LLVM lanes: {layerbvh.llvm_vector_width()}; "
          f"{args.res}x{args.res}, {args.spp} spp, warm kernels (second render timed)")
    print("| scene | integrator | stock s | per_ray s | layer_sorted s | per_ray / stock | layer_sorted / per_ray |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name in SCENES:
        kind = name.rsplit("_", 1)[-1]  # the integrator the scene states
        scene = mi.load_file(str(MEDIA / f"{name}.xml"), res=args.res)
        row = {}
        for label, props in (("stock", {"type": kind, "max_depth": 6}),
                             ("per_ray", {"type": f"layerbvh_{kind}", "max_depth": 6, "traversal": "per_ray"}),
                             ("layer_sorted", {"type": f"layerbvh_{kind}", "max_depth": 6,
                                               "traversal": "layer_sorted"})):
            integ = mi.load_dict(props)
            for _ in range(2):
                t0 = time.perf_counter()
                dr.eval(mi.render(scene, integrator=integ, spp=args.spp, seed=1))
                dr.sync_thread()
                row[label] = time.perf_counter() - t0
        print(f"| {name} | {kind} | {row['stock']:.2f} | {row['per_ray']:.2f} | {row['layer_sorted']:.2f} | "
              f"{row['per_ray'] / row['stock']:.1f}x | {row['layer_sorted'] / row['per_ray']:.1f}x |", flush=True)


if __name__ == "__main__":
    main()
