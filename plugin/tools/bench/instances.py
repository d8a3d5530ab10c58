"""Instancing benchmark: the two-level BVH against the same scene flattened into world-space
triangles, and Embree both ways: speed, agreement and memory.

    .venv/bin/python scripts/bench_instances.py [--scene scenes/instanced_bunnies.xml] [--rays N]
        [--runs R] [--height H] [--json OUT]

The scene's meshes (its own and each shapegroup's, as `adapter.collect_geometry` gathers them;
analytic shapes are left out) are traced by: `layerbvh.build_instanced` in every mode, a
one-level `layerbvh.build` over every placed triangle in world space (what tracing without
instances costs), Embree through Mitsuba's own instancing and Embree over the flattened
triangles. Two ray sets: camera rays from the scene's first sensor position through the
bounds of what the instances place, and incoherent rays (origins uniform in those bounds,
directions uniform). Every configuration runs once to warm up, then `--runs` interleaved
rounds; the table gives the median.
"""
from __future__ import annotations

import argparse
import json
import time

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh
from layerbvh import meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab import embree
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.runtime.scene_geometry import collect_geometry
from layerbvh_mitsuba.tools.bench.traversal import timed

MIB = 1 << 20


def _camera_rays(origin, lo, hi, n: int, seed: int):
    rng = np.random.default_rng(seed)
    d = rng.uniform(lo, hi, (n, 3)) - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(origin, (n, 3)).astype(np.float32), d.astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="scenes/instanced_bunnies.xml")
    p.add_argument("--rays", type=int, default=1_000_000)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--height", type=int, default=layerbvh.DEFAULT_TREELET_HEIGHT)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write every figure here")
    args = p.parse_args(argv)
    use_variant()
    scene = mi.load_file(args.scene)
    g = collect_geometry(scene)
    if not g.instanced:
        print(f"bench_instances: {args.scene} has no instances", flush=True)
        return 2
    groups, insts = g.engine_groups(), g.engine_instances()
    world_v, world_f, _ = g.world_triangles()

    builds = {}
    t0 = time.perf_counter()
    builds["instanced"] = layerbvh.build_instanced(groups, insts, treelet_height=args.height)
    t1 = time.perf_counter()
    builds["flattened"] = layerbvh.build(world_v, world_f, treelet_height=args.height)
    t2 = time.perf_counter()
    e_inst = embree.scene_from_instances(groups, insts)
    t3 = time.perf_counter()
    e_flat = embree.scene_from_mesh(world_v, world_f)
    t4 = time.perf_counter()
    build_s = {"instanced": t1 - t0, "flattened": t2 - t1, "embree instanced": t3 - t2, "embree flattened": t4 - t3}

    # Rays aim at what the instances place (not at the scene's own walls): camera rays from the
    # first sensor's position towards points in the instances' bounds, incoherent rays with
    # origins in those bounds.
    placed = np.concatenate([np.asarray(groups[pl.group].vertices, np.float64) @ pl.to_world[:3, :3].T
                             + pl.to_world[:3, 3] for pl in g.placements if pl.instance is not None])
    lo, hi = placed.min(0), placed.max(0)
    eye = np.array(scene.sensors()[0].world_transform().matrix, np.float64).reshape(4, 4)[:3, 3]
    ray_sets = {"camera": _camera_rays(eye, lo, hi, args.rays, args.seed),
                "incoherent": meshes.incoherent_rays(placed, args.rays, args.seed + 1)}
    rows, work = [], []
    for kind, (o, d) in ray_sets.items():
        m = builds["instanced"].m
        o_dev, d_dev = meshes.device_rays(m, o, d)
        ray = embree.rays(o, d)
        dr.eval(ray)
        out = {}

        def ours(name, mode):
            def run():
                h = builds[name].trace(o_dev, d_dev, mode=mode, stats=False)
                dr.eval(h.t, h.prim)
                out[(name, mode)] = h
            return run

        def stock(sc, label):
            def run():
                pi = sc.ray_intersect_preliminary(ray)
                dr.eval(pi.t, pi.prim_index, pi.shape, pi.instance)
                out[(label, "embree")] = pi
            return run
        configs = {("instanced", mode): ours("instanced", mode) for mode in layerbvh.MODES}
        configs.update({("flattened", mode): ours("flattened", mode) for mode in ("per_ray", "layer_sorted")})
        configs[("embree instanced", "embree")] = stock(e_inst, "embree instanced")
        configs[("embree flattened", "embree")] = stock(e_flat, "embree flattened")
        times = {k: [] for k in configs}
        for fn in configs.values():
            fn()  # warm-up: compiles
        keys = list(configs)
        for r in range(args.runs):
            for k in keys[r % len(keys):] + keys[:r % len(keys)]:
                times[k].append(timed(configs[k])[0])
        ref = out[("instanced", "per_ray")]
        hit_frac = float(np.mean(ref.prim.numpy() != layerbvh.MISS))
        for (name, mode), ts in times.items():
            med = float(np.median(ts))
            bvh = builds.get(name)
            row = {"rays": kind, "n": args.rays, "structure": name, "mode": mode, "seconds": med,
                   "mrays_s": args.rays / med / 1e6, "build_s": build_s[name],
                   "bvh_bytes": bvh.stats.total_bytes if bvh is not None else None, "hit_fraction": hit_frac}
            if name == "instanced":
                h = out[(name, mode)]
                row["same_hits_as_per_ray"] = bool(np.array_equal(h.prim.numpy(), ref.prim.numpy())
                                                   and np.array_equal(h.instance.numpy(), ref.instance.numpy())
                                                   and np.array_equal(h.t.numpy(), ref.t.numpy()))
            rows.append(row)
        # Per-level work, from one counted (untimed) pass per structure and mode.
        for name in ("instanced", "flattened"):
            for mode in ("per_ray", "layer_sorted"):
                c = builds[name].trace(o_dev, d_dev, mode=mode, stats=True).stats
                work.append({"rays": kind, "structure": name, "mode": mode, "steps": c.steps,
                             **{k: c.per_ray(k) for k in ("inner_nodes", "top_inner_nodes", "instance_entries",
                                                           "leaves", "triangles")}})
    st = builds["instanced"].stats
    doc = {"scene": args.scene, "height": args.height, "runs": args.runs, "unique_triangles": st.triangles,
           "placed_triangles": st.placed_triangles, "instances": st.instances, "rows": rows, "work": work,
           "threads": dr.thread_count()}
    print(f"{args.scene}: {st.triangles:,} triangles stored, {st.placed_triangles:,} placed by {st.instances} "
          f"instances; h={args.height}, {args.rays:,} rays per set, median of {args.runs} interleaved runs")
    print("| rays | structure | mode | Mrays/s | x embree instanced | BVH MiB | build s | same hits as per_ray |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for kind in ray_sets:
        base = next(r for r in rows if r["rays"] == kind and r["structure"] == "embree instanced")["mrays_s"]
        for r in (r for r in rows if r["rays"] == kind):
            mib = "-" if r["bvh_bytes"] is None else f"{r['bvh_bytes'] / MIB:.1f}"
            same = {True: "yes", False: "NO"}.get(r.get("same_hits_as_per_ray"), "-")
            print(f"| {kind} | {r['structure']} | {r['mode']} | {r['mrays_s']:.2f} | {r['mrays_s'] / base:.2f} | {mib} "
                  f"| {r['build_s']:.2f} | {same} |")
    print("\nWork per ray by level (one counted pass): inner nodes of the top level and inside instances, "
          "instances entered, leaves, triangles; wavefront steps")
    print("| rays | structure | mode | top-level nodes | nodes in instances | instances entered | leaves | triangles "
          "| steps |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for w in work:
        if w["structure"] == "flattened":  # one level: every node is the top level's
            levels = f"{w['inner_nodes']:.1f} | - | -"
        else:
            levels = (f"{w['top_inner_nodes']:.1f} | {w['inner_nodes'] - w['top_inner_nodes']:.1f} "
                      f"| {w['instance_entries']:.2f}")
        print(f"| {w['rays']} | {w['structure']} | {w['mode']} | {levels} | {w['leaves']:.1f} "
              f"| {w['triangles']:.1f} | {w['steps']} |")
    if args.json:
        atomic.write_text(args.json, json.dumps(doc, indent=1) + "\n")
    return 0
