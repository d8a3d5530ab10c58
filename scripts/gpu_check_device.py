"""The device half of the GPU check (scripts/gpu_check.sh): times per_ray and layer_sorted on the
recorded rays on the GPU for each (branching, treelet height) of model.json, checks their hits
against the LLVM replay, and prints the measured layer_sorted x per_ray beside the locality model's
prediction for that GPU; then the same at the GPU's own scale on a sphere soup (1M-16M incoherent
rays), at each step cap k of --tail-steps (default 1 and 32: the tail after one sorted step, the
default since PERFORMANCE.md entry 61, against many steps).

Needs only the engine (layerbvh: numpy, numba, drjit), so it runs on a device image without
Mitsuba:  python scripts/gpu_check_device.py out/gpu_check [--backend cuda] [--runs 5]
With --kernels RAYS it lists instead each launch of one trace per mode with its GPU time (Dr.Jit's
kernel history), which plugin/tools/bench/gpu_report.py splits into the sorted path's stages.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # the checkout's layerbvh, wherever it runs

import drjit as dr  # noqa: E402
import numpy as np  # noqa: E402

import layerbvh  # noqa: E402
from layerbvh import meshes  # noqa: E402

MODES = ("per_ray", "layer_sorted")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="what plugin/tools/bench/gpu_check.py wrote (rays.npz, model.json)")
    p.add_argument("--backend", default="cuda")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--soup", type=int, default=1_000_000,
                   help="also time a sphere soup of about this many triangles (0: skip); no model for it")
    p.add_argument("--soup-rays", type=int, nargs="+", default=(1_000_000, 4_000_000, 16_000_000))
    p.add_argument("--tail-steps", default="1,32",
                   help="the soup's layer_sorted at each step cap k (comma list; PERFORMANCE.md entry 61: the "
                        "default became 1 on the CPU and the GPU model; not yet timed on a GPU)")
    p.add_argument("--kernels", type=int, default=0, metavar="RAYS",
                   help="only list each launch's kernel time (Dr.Jit's kernel history) for one trace of "
                        "RAYS soup rays per mode and (branching, height), then stop")
    args = p.parse_args(argv)
    folder = Path(args.folder)
    model = json.loads((folder / "model.json").read_text())
    if args.kernels:
        return _kernel_history(model["configs"], args)
    z = np.load(folder / "rays.npz")
    print(f"backend {args.backend}; {len(z['faces']):,} triangles; model preset {model['preset']['name']}")
    print(f"{'K':>2} {'H':>3} {'kind':22} {'rays':>8} {'per_ray Mrays/s':>16} {'sorted Mrays/s':>15} "
          f"{'measured sorted x per_ray':>26} {'model per_ray/sorted DRAM':>26} {'... + between steps':>20} "
          f"{'hits != replay':>15}")
    result = []
    for k, h in model["configs"]:
        bvh = layerbvh.build(z["vertices"], z["faces"], treelet_height=h, backend=args.backend, branching=k)
        for kind in model["kinds"]:
            rows = {r["mode"]: r for r in model["rows"]
                    if (r["kind"], r["branching"], r["treelet_height"]) == (kind, k, h)}
            timed = _time_kind(bvh, z[f"{kind}_o"], z[f"{kind}_d"], z[f"{kind}_tmax"], kind == "shadow", args.runs,
                               want=z[f"{kind}_prim"], rows=rows)
            result.append(dict(branching=k, treelet_height=h, kind=kind, **timed))
            r = result[-1]
            print(f"{k:2} {h:3} {kind:22} {r['rays']:8,} {r['rays'] / r['seconds']['per_ray'] / 1e6:16.2f} "
                  f"{r['rays'] / r['seconds']['layer_sorted'] / 1e6:15.2f} {r['measured_sorted_over_per_ray']:26.2f} "
                  f"{r['model_dram_per_ray_over_sorted']:26.2f} {r['model_total_per_ray_over_sorted']:20.2f} "
                  f"{r['hits_differing_from_replay']['per_ray']:>7}/{r['hits_differing_from_replay']['layer_sorted']:<7}",
                  flush=True)
    soup = _time_soup(model["configs"], args) if args.soup else []
    (folder / f"measured_{args.backend}.json").write_text(json.dumps({"backend": args.backend, "kinds": result,
                                                                      "soup": soup}, indent=1))
    return 0


def _time_kind(bvh, o, d, tmax, any_hit: bool, runs: int, want=None, rows: dict | None = None) -> dict:
    """One set of rays on one tree: both modes' hits (against the LLVM replay's `want`, if given),
    then `runs` interleaved timing rounds; the measured speed-up, beside the model's DRAM ratios
    when its `rows` (per mode) are given."""
    m = bvh.m
    O, D = meshes.device_rays(m, o, d)  # on the device, as a renderer passes them
    T = layerbvh.from_numpy(m.Float, tmax)

    last = {}

    def trace(mode):
        q = (bvh.occluded if any_hit else bvh.trace)(O, D, T, mode=mode, stats=False)
        last[mode] = q.stats  # steps and the host's split of the time (kernels, sort)
        out = q.occluded if any_hit else q.prim
        dr.eval(out)
        return out
    bad, got = {}, {}
    for mode in MODES:  # warm-up (compiles) and the exactness check against the LLVM replay
        got[mode] = np.asarray(trace(mode))
        if want is not None:
            bad[mode] = int(np.count_nonzero(got[mode] != (want != layerbvh.MISS))) if any_hit else \
                int(np.count_nonzero(got[mode].astype(np.int64) != want))
    times = {mode: [] for mode in MODES}
    for _ in range(runs):  # interleaved rounds
        for mode in MODES:
            dr.sync_thread()
            t0 = time.perf_counter()
            trace(mode)
            dr.sync_thread()
            times[mode].append(time.perf_counter() - t0)
    med = {mode: statistics.median(t) for mode, t in times.items()}
    r = {"rays": len(o), "seconds": med, "measured_sorted_over_per_ray": med["per_ray"] / med["layer_sorted"],
         "modes_disagree": int(np.count_nonzero(got["per_ray"] != got["layer_sorted"])),
         "split": {mode: {"steps": st.steps, "traverse_s": st.time_traverse_s, "sort_s": st.time_sort_s,
                          "frozen": st.frozen, "step_times": [t.as_dict() for t in st.step_times]}
                   for mode, st in last.items()}}
    if rows is not None:
        pr, so = rows["per_ray"], rows["layer_sorted"]
        r.update(model_dram_per_ray_over_sorted=pr["dram_bytes_per_ray"] / so["dram_bytes_per_ray"],
                 model_total_per_ray_over_sorted=pr["total_dram_bytes_per_ray"] / so["total_dram_bytes_per_ray"],
                 hits_differing_from_replay=bad)
    return r


def print_steps(split: dict) -> None:
    """Each wavefront step's host-timed split (layerbvh.stats.StepTime; issue 57 item 4): the rays
    it walked, Python building it (tracing; a frozen step's replay), its kernels until the
    finished count came back, and the next step's sort."""
    for i, t in enumerate(split.get("step_times", [])):
        print(f"{'':17} step {i + 1}{' (tail)' if t['tail'] else ''}: {t['rays']:,} rays; trace "
              f"{t['trace_s'] * 1e3:.2f} ms, kernels {t['kernel_s'] * 1e3:.2f} ms, sort {t['sort_s'] * 1e3:.2f} ms",
              flush=True)


def _time_soup(configs, args) -> list[dict]:
    """The stress case at the GPU's own scale: incoherent rays (meshes.incoherent_rays, as the
    benchmarks make them) into a sphere soup, closest hit and any hit, at each batch size of
    --soup-rays, each (branching, height) and each step cap of --tail-steps (one build; the cap is
    the tree's tail_steps); a batch of 200k rays is too small to fill an H200."""
    v, f = meshes.sphere_soup(max(1, args.soup // 960), 960)
    most = max(args.soup_rays)
    o_all, d_all = meshes.incoherent_rays(v, most, seed=1)
    print(f"\nsphere soup, {len(f):,} triangles, incoherent rays (no model: timing only)")
    print(f"{'K':>2} {'H':>3} {'k':>3} {'query':8} {'rays':>10} {'per_ray Mrays/s':>16} {'sorted Mrays/s':>15} "
          f"{'measured sorted x per_ray':>26}")
    out = []
    for k, h in configs:
        bvh = layerbvh.build(v, f, treelet_height=h, backend=args.backend, branching=k, batch_rays=most)
        for cap, n, query in ((int(c), n, q) for c in args.tail_steps.split(",") for n in args.soup_rays
                              for q in ("closest", "any")):
            bvh.tail_steps = cap
            r = _time_kind(bvh, o_all[:n], d_all[:n], np.full(n, np.inf, np.float32), query == "any", args.runs)
            r.update(kind="soup", branching=k, treelet_height=h, tail_steps=cap, query=query)
            out.append(r)
            print(f"{k:2} {h:3} {cap:3} {query:8} {n:10,} {n / r['seconds']['per_ray'] / 1e6:16.2f} "
                  f"{n / r['seconds']['layer_sorted'] / 1e6:15.2f} {r['measured_sorted_over_per_ray']:26.2f}  "
                  f"(hits per_ray vs sorted differ: {r['modes_disagree']})", flush=True)
            sp = r["split"]["layer_sorted"]
            print(f"{'':15} sorted: {sp['steps']} steps; kernels {sp['traverse_s'] * 1e3:.2f} ms, "
                  f"sort {sp['sort_s'] * 1e3:.2f} ms; per_ray "
                  f"{r['split']['per_ray']['traverse_s'] * 1e3:.2f} ms", flush=True)
            print_steps(sp)
    return out


def _kernel_history(configs, args) -> int:
    """Where a trace's GPU time goes: each kernel launch of one closest-hit trace of --kernels soup
    rays, per mode and (branching, height), with its width and its execution time as Dr.Jit's
    kernel history records it (the warm-up trace first, so nothing is compiled in the listing)."""
    v, f = meshes.sphere_soup(max(1, args.soup // 960), 960)
    n = args.kernels
    o, d = meshes.incoherent_rays(v, n, seed=1)
    print(f"sphere soup, {len(f):,} triangles, {n:,} incoherent closest-hit rays ({args.backend})")
    for k, h in configs:
        bvh = layerbvh.build(v, f, treelet_height=h, backend=args.backend, branching=k, batch_rays=n)
        O, D = meshes.device_rays(bvh.m, o, d)
        for mode in MODES:
            dr.eval(bvh.trace(O, D, None, mode=mode, stats=False).prim)
            dr.sync_thread()
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()  # (clears it)
            t0 = time.perf_counter()
            dr.eval(bvh.trace(O, D, None, mode=mode, stats=False).prim)
            dr.sync_thread()
            wall = time.perf_counter() - t0
            hist = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            total = sum(float(e.get("execution_time", 0.0)) for e in hist)
            print(f"K={k} H={h} {mode}: {n:,} rays, {len(hist)} launches, kernels {total:.2f} ms of "
                  f"{wall * 1e3:.2f} ms wall")
            for e in hist:
                print(f"   {str(e.get('type', '')):22} width {e.get('size', 0):>10,} "
                      f"ops {e.get('operation_count', 0):>6} in {e.get('input_count', 0):>3} "
                      f"out {e.get('output_count', 0):>3} "
                      f"{float(e.get('execution_time', 0.0)):8.3f} ms", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
