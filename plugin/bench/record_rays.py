"""Record the rays a layerbvh render of a Mitsuba scene traces (camera, bounces by lobe, shadow) into an .npz for the benchmark."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path



def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("scene", help="Mitsuba 3 XML scene")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), default=(512, 512))
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--cap", type=int, default=1_000_000, help="rays kept per kind (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    import mitsuba as mi
    from layerbvh_mitsuba.render import use_variant
    mi = use_variant()
    from layerbvh_mitsuba import record
    from layerbvh_mitsuba.render import UserError, load_scene, path_props
    try:
        scene = load_scene(mi, args.scene, args.res)
    except UserError as e:
        print(f"record_rays: error: {e}", file=sys.stderr)
        return 2
    integ = mi.load_dict({"type": "layerbvh", "traversal": "per_ray", **path_props(mi, scene)})
    tracer = integ.tracer(scene)
    if tracer.geometry.analytic:
        print(f"record_rays: note: {len(tracer.geometry.analytic)} analytic shape(s) are not in the recorded "
              f"triangles; rays that hit them are benchmarked against the triangles only", file=sys.stderr)
    if tracer.geometry.instanced:
        print("record_rays: note: the scene has instances; the recording holds every placed triangle in world "
              "space (flattened), so benchmarks on it trace a one-level BVH", file=sys.stderr)
    tracer.recorder = record.RayRecorder(args.cap)
    t0 = time.perf_counter()
    mi.render(scene, integrator=integ, spp=args.spp, seed=args.seed)
    secs = time.perf_counter() - t0
    vertices, faces, _ = tracer.geometry.world_triangles()
    meta = {"scene": Path(args.scene).name, "resolution": list(args.res), "spp": args.spp, "seed": args.seed,
            "triangles": len(faces), "integrator": path_props(mi, scene)}
    tracer.recorder.save(args.out, vertices, faces, meta)
    rec = tracer.recorder
    print(f"{args.out}: {len(faces):,} triangles, render {secs:.1f} s; rays kept/traced: "
          + ", ".join(f"{k} {rec.count[k]:,}/{rec.seen[k]:,}" for k in record.KINDS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
