"""auto against per_ray on whole renders of multi-shape scenes at their own depth: first run (empty
caches) and later run, each in a fresh process.

    .venv/bin/python scripts/bench_auto.py [--scenes S.xml ...] [--res W H] [--spp N] [--rounds R]
        [--code DIR] [--json OUT]

For each scene, `--rounds` rounds of: `per_ray`, then `auto` with an empty decision cache
($XDG_CACHE_HOME, a first run), then `auto` again with that cache (a later run). Every render
is a fresh process (what a user's command is), loads the scene, builds the BVH and renders
through render.timed_render: `render_s` is the render less kernel compilation and auto's
calibration (both reported apart), `total_s` is everything from loading the scene to the
image. The table's ratios: auto first run / per_ray on render_s (calibration apart), auto
later run / per_ray on total_s (everything counted), of the medians over the rounds and of the
minima (robust where another process shares the cores: it only ever slows a run). `--code DIR`
runs the renders with the packages of another checkout (a before/after comparison).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from layerbvh import cpu_model, llvm_vector_width
from layerbvh_mitsuba.ab.render import load_integrator, load_scene, timed_render, use_variant
from layerbvh_mitsuba.ab.scene_integrator import path_settings

DEFAULT_SCENES = ("scenes/staircase2/scene.xml", "scenes/paper_mix.xml", "scenes/bunny_box.xml",
                  "scenes/paper_glass.xml")


def point(scene: str, traversal: str, res, spp: int) -> dict:
    """One render in this process (the child's side): times and auto's decisions."""
    t0 = time.perf_counter()
    mi = use_variant("llvm_ad_rgb")
    sc = load_scene(mi, scene, res)
    props = path_settings(mi, sc).props
    integ = load_integrator(mi, {"type": "layerbvh", "traversal": traversal, **props})
    integ.tracer(sc)  # the BVH (as compare builds it before rendering)
    r = timed_render(mi, sc, integ, spp, 0)
    st = integ.last_stats
    choices = {k: c.get("mode") for k, c in st.get("auto_choices", {}).items()}
    return {"render_s": r.seconds, "compile_s": r.compile_s, "calibration_s": r.calibration_s,
            "wall_s": r.wall_s, "total_s": time.perf_counter() - t0, "loop": st.get("loop"),
            "max_depth": props.get("max_depth"), "treelets": st.get("bvh", {}).get("treelets"),
            "auto_choices": choices}


def _child(scene, traversal, res, spp, cache: str, code: str | None) -> dict:
    env = dict(os.environ, XDG_CACHE_HOME=cache)
    if code:
        env["PYTHONPATH"] = code
    cmd = [sys.executable, __file__, "--point", scene, traversal, str(res[0]), str(res[1]), str(spp)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"bench_auto: {traversal} on {scene} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES))
    p.add_argument("--res", type=int, nargs=2, default=[320, 180], metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--code", help="run the renders with this checkout's packages (PYTHONPATH)")
    p.add_argument("--json", help="write every point here")
    p.add_argument("--point", nargs=5, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.point:
        scene, traversal, w, h, spp = args.point
        print(json.dumps(point(scene, traversal, (int(w), int(h)), int(spp))))
        return 0
    print(f"# CPU: {cpu_model()}; {platform.machine()}; Dr.Jit LLVM vector width {llvm_vector_width()} lanes; "
          f"{args.res[0]}x{args.res[1]}, {args.spp} spp; {args.rounds} rounds; code: {args.code or 'this checkout'}")
    rows, points = [], []
    for scene in args.scenes:
        runs = {"per_ray": [], "auto_first": [], "auto_later": []}
        for _ in range(args.rounds):
            with tempfile.TemporaryDirectory(prefix="bench_auto_") as cache:
                runs["per_ray"].append(_child(scene, "per_ray", args.res, args.spp, cache, args.code))
                runs["auto_first"].append(_child(scene, "auto", args.res, args.spp, cache, args.code))
                runs["auto_later"].append(_child(scene, "auto", args.res, args.spp, cache, args.code))
        med = {k: {f: statistics.median(r[f] for r in v) for f in ("render_s", "total_s", "calibration_s",
                                                                     "compile_s")} for k, v in runs.items()}
        def low(kind, f):
            return min(r[f] for r in runs[kind])
        row = {"scene": scene, "max_depth": runs["per_ray"][0]["max_depth"],
               "treelets": runs["per_ray"][0]["treelets"],
               **{f"{k}_{f}": v for k, m in med.items() for f, v in m.items()},
               "loops": {k: sorted({r["loop"] for r in v}) for k, v in runs.items()},
               "first_over_per_ray_render": med["auto_first"]["render_s"] / med["per_ray"]["render_s"],
               "later_over_per_ray_total": med["auto_later"]["total_s"] / med["per_ray"]["total_s"],
               # Minima too: another process taking a core slows a run, never speeds it up.
               "first_over_per_ray_render_min": low("auto_first", "render_s") / low("per_ray", "render_s"),
               "later_over_per_ray_total_min": low("auto_later", "total_s") / low("per_ray", "total_s"),
               "auto_choices": runs["auto_first"][-1]["auto_choices"]}
        rows.append(row)
        points.append({"scene": scene, "runs": runs})
        print(f"{scene}: max_depth {row['max_depth']}, {row['treelets']} treelets | per_ray render "
              f"{med['per_ray']['render_s']:.2f} s, total {med['per_ray']['total_s']:.2f} s | auto first run render "
              f"{med['auto_first']['render_s']:.2f} s (calibration {med['auto_first']['calibration_s']:.2f} s, loop "
              f"{'/'.join(row['loops']['auto_first'])}) = {row['first_over_per_ray_render']:.3f}x | auto later run "
              f"total {med['auto_later']['total_s']:.2f} s (loop {'/'.join(row['loops']['auto_later'])}) = "
              f"{row['later_over_per_ray_total']:.3f}x | minima over rounds: "
              f"{row['first_over_per_ray_render_min']:.3f}x, "
              f"{row['later_over_per_ray_total_min']:.3f}x", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "points": points, "args": vars(args)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
