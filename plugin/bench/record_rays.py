"""Record the rays a layerbvh render of a Mitsuba scene traces (camera, bounces by lobe, shadow) into an .npz for the benchmark."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path



def record_scene(mi, scene_path, res, spp: int, seed: int, cap: int):
    """Render the scene with the layerbvh integrator (per_ray) and keep the rays it traces:
    (RayRecorder, SceneGeometry, meta for RayRecorder.save, render seconds). Raises UserError
    when the scene cannot be loaded."""
    from layerbvh_mitsuba import record
    from layerbvh_mitsuba.render import load_scene, path_props
    scene = load_scene(mi, str(scene_path), tuple(res))
    integ = mi.load_dict({"type": "layerbvh", "traversal": "per_ray", **path_props(mi, scene)})
    tracer = integ.tracer(scene)
    if tracer.geometry.analytic:
        print(f"record_rays: note: {len(tracer.geometry.analytic)} analytic shape(s) are not in the recorded "
              f"triangles; rays that hit them are benchmarked against the triangles only", file=sys.stderr)
    tracer.recorder = record.RayRecorder(cap)
    t0 = time.perf_counter()
    mi.render(scene, integrator=integ, spp=spp, seed=seed)
    secs = time.perf_counter() - t0
    meta = {"scene": Path(scene_path).name, "resolution": list(res), "spp": spp, "seed": seed,
            "triangles": tracer.geometry.triangle_count, "integrator": path_props(mi, scene)}
    return tracer.recorder, tracer.geometry, meta, secs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("scene", help="Mitsuba 3 XML scene")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), default=(512, 512))
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--cap", type=int, default=1_000_000, help="rays kept per kind (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    from layerbvh_mitsuba.render import use_variant
    mi = use_variant()
    from layerbvh_mitsuba import record
    from layerbvh_mitsuba.render import UserError
    try:
        rec, geometry, meta, secs = record_scene(mi, args.scene, args.res, args.spp, args.seed, args.cap)
    except UserError as e:
        print(f"record_rays: error: {e}", file=sys.stderr)
        return 2
    rec.save(args.out, geometry.vertices, geometry.faces, meta)
    print(f"{args.out}: {geometry.triangle_count:,} triangles, render {secs:.1f} s; rays kept/traced: "
          + ", ".join(f"{k} {rec.count[k]:,}/{rec.seen[k]:,}" for k in record.KINDS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
