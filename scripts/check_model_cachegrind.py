"""Check the locality model against valgrind's cache simulator: first-level and last-level read and
write misses per ray of the real LLVM kernels, beside the model's replay of the same rays on the
same cache geometry.

    .venv/bin/python scripts/check_model_cachegrind.py --mesh scenes/meshes/bunny.ply --rays 20000 \\
        [--d1 32 --d1 8] [--ll 1024] [--modes per_ray,layer_sorted,layer_unsorted] --json OUT
    .venv/bin/python scripts/check_model_cachegrind.py --report OUT [OUT ...]   # BENCHMARKS.md's section

How (issue 41):
- The rays are incoherent (layerbvh.meshes.incoherent_rays, as the benchmarks make them); the tree
  is built here (numba) and handed to a child process as arrays, so nothing is built under
  valgrind. Valgrind's CPU has no AVX-512 and another model name, so Dr.Jit's kernels cached for
  the host do not apply: the first child compiles them into Dr.Jit's cache (uninstrumented, see
  below), the others load them from there.
- The measured children run under valgrind's callgrind with its cache simulator
  (`--cache-sim=yes`, the same simulator as cachegrind's, with the D1 and LL geometry set: 8-way
  D1, 16-way LL, 64-byte lines) and one Dr.Jit thread. Cachegrind 3.19 has no instrumentation
  toggles; callgrind's can be driven while the process runs (`callgrind_control`): the child
  starts uninstrumented (it runs at near native speed), traces each mode once on rays of its
  own (compiling or loading the kernels), and then the parent switches instrumentation on
  (`--instr=on`), zeroes the counters just before each mode's trace call (`-z`) and dumps them
  just after (`-d`). Start-up, imports, compiling and loading are never counted or simulated.
- Per D1 size, one child traces the first N rays in each mode, one the first 2N; the difference
  of their regions' read and write misses, over N, is what a ray costs (the constant per-call
  work, Python tracing the kernels and the launches, cancels). The model replays the same N and 2N rays on a
  preset of the same geometry (one core, the child's SIMD width, Dr.Jit's packet schedule), and
  the same difference is taken.
What each side leaves out is printed with the table (BLIND_SPOTS).
Exit status: 0 when the model's sorted / per_ray ratio and verdict agree with valgrind's at every D1
size, level and kind of miss (reads, writes), 3 when one does not (the JSON is written all the same),
1 on a measurement that stayed disturbed, 2 without valgrind.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the checkout's layerbvh, also in the child

MODES = ("per_ray", "layer_sorted", "layer_unsorted")
# Each child first traces as many rays as it measures, rays of their own past the first 2N (4N in
# all), so that every kernel its measured call runs (a first wavefront step, the later steps, the
# tail) is compiled or loaded before the region: with 4,096 warm rays a 2N-ray call took steps the
# warm-up had not, and compiled their kernel inside the region (measured: 324,000 instructions per
# ray counted for layer_sorted, where the kernels were not yet in the disk cache).
LINE = 64
D1_WAYS, LL_WAYS = 8, 16
SECTION = "cachegrind"  # BENCHMARKS.md's markers around the section
# The agreement issue 41 asks for.
RATIO_TOLERANCE, ABSOLUTE_TOLERANCE = 0.15, 0.30
DISAGREES_EXIT = 3  # (1: a disturbed measurement, 2: no valgrind)
BLIND_SPOTS = (
    "The model simulates the traversal kernels' loads and stores (the local entry stack; as a lane ends, "
    "its hit, and in a step its sort key, state record and held entries, in the first step its ray record; "
    "write-allocate, write-back) "
    "and the trace call's passes before its first kernel (the valid rays' compaction, the results' fill; "
    "before PERFORMANCE.md entries 62 and 63 also the packing of every ray's state and ray records): the "
    "sort and compaction between steps and the "
    "host's work are not in its misses (the layer modes' `sort_bytes` stand for them elsewhere). The "
    "kernels' stack frames (register spills) are, where llc 19 is installed: each packet iteration "
    "writes, then reads, the frame lines its kernel's spills and reloads touch (scripts/kernel_frame.py; "
    "in the kernel they interleave with the loads); valgrind counts every "
    "read and write the trace call makes. Valgrind's own simplifications: an inclusive LL, LRU "
    "everywhere, no prefetching, no TLB, and one cache for all threads (the children run one Dr.Jit "
    "thread). Read misses (D1mr, DLmr) are held against the model's loads that miss L1 and L2, write "
    "misses (D1mw, DLmw) against its stores that do.")


# -- the child: engine only, runs under valgrind ------------------------------------------------------
def child(work: Path, n: int, modes: list[str], out: Path) -> None:
    import gc

    import drjit as dr

    from layerbvh import backend as be
    from layerbvh import meshes, wavefront
    from layerbvh.inputs import ray_batch
    from layerbvh.layout import LayerLayout

    gc.disable()  # (a collection inside the region would be noise of its own)
    dr.set_thread_count(0)  # kernels on this thread: one cache hierarchy, the model's one core, and in the region
    z = np.load(work / "layout.npz")
    lay = LayerLayout(nodes=z["nodes"], leaves=z["leaves"], tris=z["tris"], treelet_first=z["treelet_first"],
                      node_treelet=z["node_treelet"], leaf_treelet=z["leaf_treelet"], depth=int(z["depth"]),
                      height=int(z["height"]), branching=int(z["branching"]))
    m = be.module("llvm")
    dev = lay.to_device(m)
    r = np.load(work / "rays.npz")
    tail = dict(tail_rays=int(z["tail_rays"]), tail_fraction=float(z["tail_fraction"]),
                tail_steps=int(z["tail_steps"]))

    def rays(lo, hi):  # (made outside the measured region: numpy's copies are not the traversal's)
        o, d = meshes.device_rays(m, r["o"][lo:hi], r["d"][lo:hi])
        batch = ray_batch(m, "llvm", o, d, m.Float(np.full(hi - lo, np.inf, np.float32)))
        dr.eval(*batch.o, *batch.d, batch.tmax, batch.valid)
        return batch

    def trace(batch, mode):
        res, _ = wavefront.trace(m, dev, batch, mode=mode, any_hit=False, count_work=False, **tail)
        dr.eval(res.t, res.prim)
        return res
    # One trace per mode on as many rays of their own first: it compiles (once, into Dr.Jit's cache: the
    # kernels cached for the host do not apply under valgrind's CPU) or loads every kernel of
    # the mode, still uninstrumented. Then the parent switches instrumentation on.
    for mode in modes:
        trace(rays(len(r["o"]) - n, len(r["o"])), mode)
    dr.sync_thread()
    print("loaded", flush=True)
    sys.stdin.readline()
    prims = {}
    for mode in modes:
        batch = rays(0, n)
        dr.sync_thread()
        # The region: the parent zeroes callgrind's counters (callgrind_control -z) when this says
        # "ready", and dumps them (-d) when it says "done".
        print("ready", flush=True)
        sys.stdin.readline()
        res = trace(batch, mode)
        dr.sync_thread()
        print("done", flush=True)
        sys.stdin.readline()
        prims[mode] = np.asarray(res.prim).astype(np.int64)
    np.savez(out, lanes=be.llvm_vector_width(), **prims)


# -- the parent -------------------------------------------------------------------------------------------
def _run_child(work: Path, n: int, modes: list[str], tool: list[str], tag: str, between=None) -> dict:
    """One child under valgrind tracing n rays per mode; `between(pid, i, say)` is called once the
    child has loaded everything (-1, "loaded"), and when mode i's region starts (i, "ready") and
    ends (i, "done")."""
    out = work / f"{tag}.npz"
    cmd = ["valgrind", "-q", *tool, sys.executable, __file__, "--child", str(work), str(n), ",".join(modes), str(out)]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONHASHSEED": "0"})
    for i, say in [(-1, "loaded")] + [(i, say) for i in range(len(modes)) for say in ("ready", "done")]:
        line = proc.stdout.readline().strip()
        if line != say:
            break
        if between:
            between(proc.pid, i, say)
        proc.stdin.write("go\n")
        proc.stdin.flush()
    _, err = proc.communicate()
    if proc.returncode != 0 or not out.exists():
        raise SystemExit(f"check_model_cachegrind: the child under valgrind failed ({' '.join(tool[:1])}): "
                         f"{err.strip().splitlines()[-1] if err.strip() else proc.returncode}")
    return dict(np.load(out))


def read_callgrind(path: Path) -> dict:
    """A callgrind dump's event counters since they were zeroed ('summary:' over 'events:'). (Not
    the sum of its cost lines, 'totals:': the functions still running when the counters were
    zeroed, the interpreter's frames around the region, keep their earlier costs there.)"""
    events, summary = [], None
    for line in path.read_text().splitlines():
        if line.startswith("events:"):
            events = line.split()[1:]
        elif line.startswith("summary:"):
            summary = [int(x) for x in line.split()[1:]]
    if summary is None:
        raise ValueError(f"{path}: no summary line")
    return dict(zip(events, summary + [0] * (len(events) - len(summary))))


def region_difference(a: dict, b: dict, n: int, what: str) -> dict:
    """Per ray of rays n..2n: the events of the 2n-ray region `b` less those of the n-ray region
    `a` (read misses D1, LL; write misses D1, LL; instructions). More events for n rays than for 2n
    means something else ran in the n-ray region (measured once: a kernel compiled there, -430 read
    misses per ray): a disturbed run, not a result, so it raises."""
    out = {"D1": (b["D1mr"] - a["D1mr"]) / n, "LL": (b["DLmr"] - a["DLmr"]) / n,
           "D1_writes": (b["D1mw"] - a["D1mw"]) / n, "LL_writes": (b["DLmw"] - a["DLmw"]) / n,
           "instructions": (b["Ir"] - a["Ir"]) / n}
    if min(out["D1"], out["LL"], out["instructions"]) < 0:
        raise RuntimeError(f"{what}: the {n}-ray region counted more events than the {2 * n}-ray one "
                           f"(something besides the trace ran in it); run the check again")
    return out


ATTEMPTS = 3  # measurements of a (D1, n) pair before a disturbed one stops the check


def cachegrind_misses(work: Path, n: int, modes: list[str], d1_kib: int, ll_kib: int, measure=None) -> dict:
    """`measure_pair`, again where a measurement was disturbed (region_difference: more events for
    n rays than for 2n), at most ATTEMPTS times; "attempts" says how many it took. A busy machine
    once made one such run (issue 56): callgrind_control's zero and dump land when valgrind next
    looks, which a loaded machine delays, and a kernel compiled inside a region counts there; the
    next run finds the kernels cached and the machine in another state."""
    measure = measure or measure_pair
    for attempt in range(1, ATTEMPTS + 1):
        try:
            return measure(work, n, modes, d1_kib, ll_kib) | {"attempts": attempt}
        except RuntimeError as e:
            if attempt == ATTEMPTS:
                raise RuntimeError(f"{e} ({ATTEMPTS} measurements, each disturbed)") from None
            print(f"check_model_cachegrind: measuring again: {e}", file=sys.stderr)


def measure_pair(work: Path, n: int, modes: list[str], d1_kib: int, ll_kib: int) -> dict:
    """Per mode: read misses per ray of tracing rays n..2n (the region of the child that traces 2n
    rays minus that of the child that traces n). The counters are zeroed when a region starts and
    dumped when it ends (callgrind_control), so only the trace call is counted; the caches are
    simulated from when instrumentation goes on, so each region starts with the caches as the
    child's earlier traces left them."""
    got = {}
    for k in (n, 2 * n):
        cg = work / f"cg_{d1_kib}_{k}.out"

        def between(pid, i, say):
            flag = {"loaded": "--instr=on", "ready": "-z", "done": "-d"}[say]
            subprocess.run(["callgrind_control", flag, str(pid)], check=True, capture_output=True)
        tool = ["--tool=callgrind", "--cache-sim=yes", "--instr-atstart=no", f"--D1={d1_kib * 1024},{D1_WAYS},{LINE}",
                f"--LL={ll_kib * 1024},{LL_WAYS},{LINE}", f"--callgrind-out-file={cg}"]
        prims = _run_child(work, k, modes, tool, f"cg_{d1_kib}_{k}", between)
        lanes = int(prims["lanes"])
        got[k] = {mode: (read_callgrind(Path(f"{cg}.{i + 1}")), prims[mode]) for i, mode in enumerate(modes)}
    out = {mode: region_difference(got[n][mode][0], got[2 * n][mode][0], n, f"{mode}, D1 {d1_kib} KiB")
           | {"prim": got[2 * n][mode][1]} for mode in modes}
    out["lanes"] = lanes
    return out


def model_preset(d1_kib: int, ll_kib: int, lanes: int):
    from layerbvh.memmodel import DRJIT_LLVM_BLOCK_LANES, KIB, CacheLevel, Preset
    return Preset(
        name=f"cachegrind-d1-{d1_kib}k", description=f"cachegrind's D1 {d1_kib} KiB, LL {ll_kib} KiB", kind="cpu",
        units=1, resident_warps=1, block_warps=max(1, DRJIT_LLVM_BLOCK_LANES // lanes), warp=lanes, segment_bytes=LINE,
        levels=(CacheLevel("L1", d1_kib * KIB, D1_WAYS, LINE, False),
                CacheLevel("L2", ll_kib * KIB, LL_WAYS, LINE, True)),
        flush_private_each_kernel=False, source="set to the geometry given to cachegrind (check_model_cachegrind.py)")


def model_misses(bvh, o, d, n: int, mode: str, pre, frame_bytes: int = 0) -> dict:
    """The model's L1 and L2 (last-level) misses per ray of rays n..2n, as valgrind's are taken,
    in total and per kind of load (memtrace.CATEGORY: nodes, triangles, stacks, the kernels' stack
    frames of `frame_bytes` each, ray and state records)."""
    from layerbvh import memsites as ms
    from layerbvh import replay_tree
    got = {}
    for k in (n, 2 * n):
        rep = replay_tree(bvh, o[:k], d[:k], np.full(k, np.inf, np.float32), mode, False, pre.warp, pre, frame_bytes)
        lh = rep.levels_hit  # [site, level]: transactions served there (last column: below the last level)
        miss_l1 = lh.sum(axis=1) - lh[:, 0]
        got[k] = (miss_l1, lh[:, -1], rep.prim, rep.sort_bytes)
    loads = [k for k in range(ms.SITES) if k not in ms.STORE_SITES]
    stores = list(ms.STORE_SITES)

    def per_ray(level, sites):
        return float(got[2 * n][level][sites].sum() - got[n][level][sites].sum()) / n
    parts = {"D1": {}, "LL": {}}
    for cat, sites in {**ms.CATEGORY, "ray and state records": tuple(range(ms.S_START, ms.S_END))}.items():
        parts["D1"][cat] = per_ray(0, [k for k in sites if k in loads])
        parts["LL"][cat] = per_ray(1, [k for k in sites if k in loads])
    # Read misses against valgrind's D1mr/DLmr; the replay's stores (the local entry stack) that
    # missed, against its D1mw/DLmw.
    return {"D1": per_ray(0, loads), "LL": per_ray(1, loads), "D1_writes": per_ray(0, stores),
            "LL_writes": per_ray(1, stores), "parts": parts, "prim": got[2 * n][2],
            # what the model's formula (locality.sort_traffic) says the steps move between them, in lines
            "between_steps_lines": (got[2 * n][3] - got[n][3]) / n / LINE}


def kernel_frames(bvh, o, d, modes) -> tuple[dict, int | None]:
    """Per mode, the stack-frame bytes a packet iteration touches (the spill lines of its kernels,
    scripts/kernel_frame.py: llc's assembly of the IR this process compiles), and the kernels'
    lanes: the model takes them where valgrind's children run as many lanes (an AVX-512 host's
    kernels are not the ones valgrind runs). ({}, None) without llc 19 (the frames then left out)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import kernel_frame
    import layerbvh
    llc = kernel_frame.find_llc()
    if llc is None:
        print("check_model_cachegrind: llc 19 is missing (Debian: apt-get install llvm-19): the model leaves "
              "out the kernels' stack frames", flush=True)
        return {}, None
    frames = kernel_frame.spill_bytes_by_mode(kernel_frame.kernel_rows(bvh, o, d, modes, llc))
    print(f"kernel stack frames (spill lines a packet iteration touches): {frames}", flush=True)
    return frames, layerbvh.llvm_vector_width()


def load_mesh(spec: str):
    from layerbvh import meshes
    if spec.startswith("procedural:"):
        return meshes.procedural_mesh(int(spec.split(":", 1)[1]))
    return meshes.load_mesh(spec)


def check(args) -> dict:
    import layerbvh
    from layerbvh import meshes
    v, f = load_mesh(args.mesh)
    bvh = layerbvh.build(v, f, treelet_height=args.height, branching=args.branching, backend="llvm")
    n = args.rays
    o, d = meshes.incoherent_rays(v, 4 * n, seed=args.seed)  # 2N measured, the rest warm-up
    work = Path(tempfile.mkdtemp(prefix="cachegrind-"))
    lay = bvh.layout
    np.savez(work / "layout.npz", nodes=lay.nodes, leaves=lay.leaves, tris=lay.tris, treelet_first=lay.treelet_first,
             node_treelet=lay.node_treelet, leaf_treelet=lay.leaf_treelet, depth=lay.depth, height=lay.height,
             branching=lay.branching, tail_rays=bvh.tail_rays, tail_fraction=bvh.tail_fraction,
             tail_steps=bvh.tail_steps)
    np.savez(work / "rays.npz", o=o, d=d)
    print(f"{args.mesh}: {len(f):,} triangles, K={args.branching}, H={args.height}; {n:,} incoherent rays",
          flush=True)
    frames, frame_lanes = kernel_frames(bvh, o[:n], d[:n], args.modes)
    rows, lanes = [], None
    for d1 in args.d1:
        t0 = time.perf_counter()
        cgs = cachegrind_misses(work, n, args.modes, d1, args.ll)
        lanes = cgs["lanes"]  # Dr.Jit's packet width under valgrind (8: no AVX-512 there)
        pre = model_preset(d1, args.ll, lanes)
        for mode in args.modes:
            fb = frames.get(mode, 0) if frame_lanes == lanes else 0
            cg, mo = cgs[mode], model_misses(bvh, o, d, n, mode, pre, fb)
            exact = bool(np.array_equal(cg["prim"], mo["prim"]))
            for level in ("D1", "LL"):
                rows.append({"mode": mode, "level": level, "d1_kib": d1, "ll_kib": args.ll,
                             "model_misses_per_ray": mo[level], "cachegrind_misses_per_ray": cg[level],
                             "cachegrind_write_misses_per_ray": cg[f"{level}_writes"],
                             "model_write_misses_per_ray": mo[f"{level}_writes"],
                             "instructions_per_ray": cg["instructions"], "model_parts": mo["parts"][level],
                             "model_between_steps_lines_per_ray": mo["between_steps_lines"],
                             "hits_equal": exact, "attempts": cgs["attempts"], "model_frame_bytes": fb})
            print(f"  D1 {d1:3} KiB {mode:15} read misses/ray, D1: model {mo['D1']:6.2f}, valgrind {cg['D1']:6.2f} "
                  f"(write misses: model {mo['D1_writes']:.2f}, valgrind {cg['D1_writes']:.2f}; model's between-step "
                  f"estimate {mo['between_steps_lines']:.2f} lines); "
                  f"LL: model {mo['LL']:5.2f}, valgrind {cg['LL']:5.2f}; "
                  f"{cg['instructions']:.0f} instructions/ray; hits {'equal' if exact else 'DIFFER'}", flush=True)
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return {"mesh": args.mesh, "triangles": int(len(f)), "rays": n, "branching": args.branching,
            "treelet_height": args.height, "tail_steps": bvh.tail_steps, "lanes": lanes, "ll_kib": args.ll,
            "seed": args.seed,
            "command": "scripts/check_model_cachegrind.py " + " ".join(sys.argv[1:]), "rows": rows,
            "verdicts": verdicts(rows)}


def verdicts(rows: list[dict]) -> list[dict]:
    """Per D1 size, level and kind of miss (reads, and writes where the rows have the model's):
    sorted / per_ray misses in the model and in cachegrind, and whether the ratio (within
    RATIO_TOLERANCE), the absolute misses (ABSOLUTE_TOLERANCE) and the verdict (which mode misses
    less) agree."""
    out = []
    by = {(r["mode"], r["level"], r["d1_kib"]): r for r in rows}
    columns = {"reads": ("model_misses_per_ray", "cachegrind_misses_per_ray"),
               "writes": ("model_write_misses_per_ray", "cachegrind_write_misses_per_ray")}
    for (mode, level, d1), s in by.items():
        p = by.get(("per_ray", level, d1))
        if mode != "layer_sorted" or p is None:
            continue
        for misses, (model, cg) in columns.items():
            if any(r.get(model) is None or r.get(cg) is None for r in (p, s)):
                continue  # (a JSON from before the model had stores)
            rm = s[model] / p[model] if p[model] else float("nan")
            rc = s[cg] / p[cg] if p[cg] else float("nan")
            absolute = all(abs(r[model] - r[cg]) <= ABSOLUTE_TOLERANCE * r[cg] for r in (p, s))
            out.append({"level": level, "d1_kib": d1, "misses": misses, "model_ratio": rm, "cachegrind_ratio": rc,
                        "ratio_agrees": abs(rm - rc) <= RATIO_TOLERANCE * rc, "absolute_agrees": absolute,
                        "verdict_agrees": (rm < 1) == (rc < 1)})
    return out


# -- BENCHMARKS.md ------------------------------------------------------------------------------------------
def section(docs: list[dict]) -> str:
    from layerbvh import LocalityRow  # (the step cap of documents that do not record it: LocalityRow's default)
    from layerbvh_mitsuba.tools.bench.locality import steps_text
    parts = ["## The model against valgrind's cache simulator (`scripts/check_model_cachegrind.py`)", "",
             "Read misses per ray of the real LLVM kernels under valgrind's cache simulator (callgrind "
             "`--cache-sim=yes`, the simulator of cachegrind), beside the locality "
             "model's replay of the same incoherent rays on the same cache geometry (8-way D1, 16-way LL, "
             "64-byte lines, one core). Both sides difference a run of 2N rays and one of N (the script's "
             "docstring says how). ±: the targets of issue 41, sorted ÷ per_ray ratio within "
             f"{RATIO_TOLERANCE:.0%} and absolute misses within {ABSOLUTE_TOLERANCE:.0%}.", "", BLIND_SPOTS, ""]
    for doc in docs:
        parts += [f"### {Path(doc['mesh']).name} ({doc['triangles']:,} triangles), {doc['rays']:,} rays, "
                  f"K={doc['branching']}, H={doc['treelet_height']}, the layer modes' tail after "
                  f"{steps_text(doc.get('tail_steps', LocalityRow.tail_steps))} at most, {doc['lanes']} lanes", "",
                  f"`{doc['command']}`", "",
                  "| D1 | level | mode | model read misses/ray | valgrind read misses/ray | model ÷ valgrind | "
                  "model write misses/ray | valgrind write misses/ray | hits equal |",
                  "|---|---|---|---|---|---|---|---|---|"]

        def num(x):  # (a JSON written before the model had stores has no model write misses; LL none)
            return "" if x is None else f"{x:.2f}"
        for r in doc["rows"]:
            cg = r["cachegrind_misses_per_ray"]
            q = r["model_misses_per_ray"] / cg if cg else float("nan")
            parts.append(f"| {r['d1_kib']} KiB | {r['level']} | {r['mode']} | {r['model_misses_per_ray']:.2f} | "
                         f"{r['cachegrind_misses_per_ray']:.2f} | {q:.2f} "
                         f"| {num(r.get('model_write_misses_per_ray'))} | "
                         f"{num(r['cachegrind_write_misses_per_ray'])} | {'yes' if r['hits_equal'] else 'NO'} |")
        parts += ["", "| D1 | level | misses | sorted ÷ per_ray, model | sorted ÷ per_ray, valgrind "
                  "| ratio within ±15% | absolute within ±30% | same verdict |", "|---|---|---|---|---|---|---|---|"]
        for v in doc["verdicts"]:
            parts.append(f"| {v['d1_kib']} KiB | {v['level']} | {v.get('misses', 'reads')} | {v['model_ratio']:.2f} | "
                         f"{v['cachegrind_ratio']:.2f} | "
                         f"{'yes' if v['ratio_agrees'] else 'no'} | {'yes' if v['absolute_agrees'] else 'no'} | "
                         f"{'yes' if v['verdict_agrees'] else 'no'} |")
        parts += ["", *unmodelled(doc["rows"]), ""]
    return "\n".join(parts)


def unmodelled(rows: list[dict]) -> list[str]:
    """Per D1 size and layer mode, what valgrind counts beyond the model: the read misses the model
    has not, the write misses beyond per_ray's (the layer modes' own stores), beside the lines
    the model's between-step formula (locality.sort_traffic) stands for."""
    by = {(r["mode"], r["level"], r["d1_kib"]): r for r in rows}
    out = []
    for (mode, level, d1), r in by.items():
        p = by.get(("per_ray", "D1", d1))
        if level != "D1" or mode == "per_ray" or p is None:
            continue
        extra = r["cachegrind_misses_per_ray"] - r["model_misses_per_ray"]
        writes = r["cachegrind_write_misses_per_ray"] - p["cachegrind_write_misses_per_ray"]
        lines = r["model_between_steps_lines_per_ray"]
        out.append(f"- D1 {d1} KiB, {mode}: valgrind counts {extra:.1f} more read misses per ray than the model and "
                   f"{writes:.1f} write misses per ray more than per_ray's; the model's between-step formula stands "
                   f"for {lines:.1f} lines ({64 * lines:.0f} B) per ray.")
    return out


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        child(Path(argv[1]), int(argv[2]), argv[3].split(","), Path(argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", help=".ply/.obj, or procedural:TRIANGLES")
    p.add_argument("--rays", type=int, default=20000, help="N: the children trace N and 2N rays (default %(default)s)")
    p.add_argument("--d1", type=int, action="append", help="D1 size in KiB (repeatable; default 32 and 8)")
    p.add_argument("--ll", type=int, default=1024, help="LL size in KiB (default %(default)s)")
    p.add_argument("--modes", default=",".join(MODES), help="comma list (default %(default)s)")
    p.add_argument("--branching", type=int, default=4)
    p.add_argument("--height", type=int, default=8)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="write the rows here")
    p.add_argument("--keep", action="store_true", help="keep the children's folder (cachegrind.out files)")
    p.add_argument("--report", nargs="+", metavar="JSON", help="write BENCHMARKS.md's section from these and stop")
    args = p.parse_args(argv)
    if args.report:
        from layerbvh_mitsuba import atomic
        docs = [json.loads(Path(j).read_text()) for j in args.report]
        atomic.splice_section(ROOT / "BENCHMARKS.md", SECTION, section(docs))
        print(f"replaced the {SECTION} section of BENCHMARKS.md")
        return 0
    if not args.mesh:
        p.error("--mesh is required (or --report)")
    if shutil.which("valgrind") is None:
        print("check_model_cachegrind: valgrind is not installed (Debian: apt-get install valgrind)", file=sys.stderr)
        return 2
    args.modes = [m for m in args.modes.split(",") if m]
    bad = [m for m in args.modes if m not in MODES]
    if bad or args.rays < 1:
        p.error(f"modes must be among {', '.join(MODES)} and --rays positive")
    args.d1 = args.d1 or [32, 8]
    try:
        doc = check(args)
    except RuntimeError as e:  # (a disturbed measurement: region_difference)
        print(f"check_model_cachegrind: {e}", file=sys.stderr)
        return 1
    if args.json:
        tmp = Path(args.json).with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(args.json)
    for v in doc["verdicts"]:
        def word(key):
            return "agrees" if v[key] else "DISAGREES"
        print(f"D1 {v['d1_kib']} KiB {v['level']} {v.get('misses', 'reads')}: sorted / per_ray model "
              f"{v['model_ratio']:.2f}, valgrind {v['cachegrind_ratio']:.2f}: ratio {word('ratio_agrees')}, "
              f"absolute {word('absolute_agrees')}, verdict {word('verdict_agrees')}")
    return disagreement(doc["verdicts"])


def disagreement(verdicts: list[dict]) -> int:
    """The check's exit status (issue 57 item 5): DISAGREES_EXIT, with one line naming where, when
    the model's sorted / per_ray ratio or its verdict (which mode misses less) disagrees with
    valgrind's at any D1 size or level; 0 when every one agrees. The JSON is written either way,
    so BENCHMARKS.md shows the disagreement too."""
    bad = [f"{v['level']} {v.get('misses', 'reads')} (D1 {v['d1_kib']} KiB)" for v in verdicts
           if not (v["ratio_agrees"] and v["verdict_agrees"])]
    if not bad:
        return 0
    print(f"check_model_cachegrind: the model disagrees with valgrind on sorted / per_ray (ratio beyond "
          f"{RATIO_TOLERANCE:.0%} or the other verdict) at {', '.join(bad)}", file=sys.stderr)
    return DISAGREES_EXIT


if __name__ == "__main__":
    sys.exit(main())
