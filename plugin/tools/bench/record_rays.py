"""Record the rays a layerbvh render of a Mitsuba scene traces (camera, bounces by lobe, shadow; or a particle
tracer's light rays) into an .npz for the benchmark."""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from layerbvh_mitsuba.ab.render import UserError, load_scene, use_variant
from layerbvh_mitsuba.ab.scene_integrator import path_settings
from layerbvh_mitsuba.ab.stock_cache import reference_key
from layerbvh_mitsuba.runtime import record
from layerbvh_mitsuba.runtime.cache import cache_dir


@dataclass
class Recording:
    """The rays one render traced, with the scene's triangles in world space (every placement of
    an instanced shapegroup flattened: benchmarks on a recording trace a one-level BVH)."""

    recorder: record.RayRecorder
    vertices: np.ndarray
    faces: np.ndarray
    meta: dict  # what RayRecorder.save stores beside the rays
    render_s: float

    def save(self, path) -> None:
        self.recorder.save(path, self.vertices, self.faces, self.meta)


def record_scene(mi, scene_path, res, spp: int, seed: int, cap: int, light: bool = False) -> Recording:
    """Render the scene with the layerbvh integrator (per_ray) and keep the rays it traces; with
    `light`, or where the scene's integrator is `ptracer`, its particle tracer (`layerbvh_ptracer`,
    the scene's depths): light rays from the emitters and their bounces ("light"), and each
    vertex's visibility from the sensor ("shadow"). Raises UserError when the scene cannot be
    loaded."""
    scene = load_scene(mi, str(scene_path), tuple(res))
    path = path_settings(mi, scene, as_path=True)
    light = light or path.estimator == "ptracer"
    props = {k: v for k, v in path.props.items()
             if k in ("max_depth", "rr_depth", "hide_emitters", "samples_per_pass")} if light else path.props
    integ = mi.load_dict({"type": "layerbvh_ptracer" if light else "layerbvh", "traversal": "per_ray", **props})
    tracer = integ.tracer(scene)
    if tracer.geometry.analytic:
        print(f"record_rays: note: {len(tracer.geometry.analytic)} analytic shape(s) are not in the recorded "
              f"triangles; rays that hit them are benchmarked against the triangles only", file=sys.stderr)
    if tracer.geometry.instanced:
        print("record_rays: note: the scene has instances; the recording holds every placed triangle in world "
              "space (flattened), so benchmarks on it trace a one-level BVH", file=sys.stderr)
    recorder = record.RayRecorder(cap)
    t0 = time.perf_counter()
    integ.render_recorded(scene, recorder, spp, seed)
    secs = time.perf_counter() - t0
    vertices, faces, _ = tracer.geometry.world_triangles()
    meta = {"scene": Path(scene_path).name, "resolution": list(res), "spp": spp, "seed": seed,
            "triangles": len(faces), "integrator": {"type": "ptracer" if light else "path", **props}}
    return Recording(recorder, vertices, faces, meta, secs)


def cached_recording(mi, scene_path, res, spp: int, seed: int, cap: int):
    """(vertices, faces, {kind: (o, d, tmax)}, meta) of the scene's recording at these settings,
    kept in the cache ($XDG_CACHE_HOME/layerbvh/rays, keyed like converge's references: the scene,
    every file it references, the settings and Mitsuba's version), so tools that replay the same
    rays record them once."""
    what = {"record": {"res": list(res), "spp": spp, "seed": seed, "cap": cap}, "variant": mi.variant(),
            "mitsuba": mi.__version__}
    path = cache_dir("rays") / f"{reference_key(Path(scene_path), what)[:24]}.npz"
    if not path.is_file():
        record_scene(mi, scene_path, res, spp, seed, cap).save(path)
    return record.load(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("scene", help="Mitsuba 3 XML scene")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), default=(512, 512))
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--cap", type=int, default=1_000_000, help="rays kept per kind (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--light", action="store_true",
                   help="trace light paths from the emitters (layerbvh_ptracer, the scene's depths) instead of camera "
                        "paths: records the 'light' kind and the sensor connections' 'shadow' rays")
    args = p.parse_args(argv)
    mi = use_variant()
    try:
        rec = record_scene(mi, args.scene, args.res, args.spp, args.seed, args.cap, args.light)
    except UserError as e:
        print(f"record_rays: error: {e}", file=sys.stderr)
        return 2
    rec.save(args.out)
    print(f"{args.out}: {len(rec.faces):,} triangles, render {rec.render_s:.1f} s; rays kept/traced: "
          + ", ".join(f"{k} {rec.recorder.count[k]:,}/{rec.recorder.seen[k]:,}" for k in record.KINDS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
