#!/usr/bin/env python3
"""Host time of a walk: milliseconds per trace call and per wavefront step on few rays (where
tracing the walk in Python, not the kernel, is the cost), and how many times each walk's loop body
was traced.

    .venv/bin/python scripts/bench_walk_trace.py [--rays 2000] [--reps 40] [--json OUT]

Before/after a change, as PERFORMANCE.md entry 58 ran it (a worktree of REV ahead on PYTHONPATH,
interleaved): `git worktree add /tmp/before REV; mkdir /tmp/pp; ln -s /tmp/before/layerbvh /tmp/pp/;
cd /tmp && for i in 1 2; do PYTHONPATH=/tmp/pp python SCRIPT; python SCRIPT; done` (from /tmp, so
that the working tree's layerbvh is not the one imported first).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.append(str(ROOT))  # after PYTHONPATH: a "before" tree wins
import layerbvh  # noqa: E402
from layerbvh import meshes  # noqa: E402


def _this_checkouts_loopstate():
    """layerbvh/loopstate.py of this script's checkout, loaded by path: its body_traces counts the
    traces of any tree's walk, also one from before the module existed."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("bench_loopstate", ROOT / "layerbvh" / "loopstate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


body_traces = _this_checkouts_loopstate().body_traces

BUNNY = ROOT / "scenes" / "meshes" / "bunny.ply"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=40)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    v, f = meshes.load_mesh(BUNNY)
    bvh = layerbvh.build(v, f, treelet_height=4)
    o, d = meshes.incoherent_rays(v, a.rays, seed=1)
    rows = []
    for mode in ("per_ray", "layer_sorted"):
        for stats in (False, True):
            run = lambda: bvh.trace(o, d, mode=mode, stats=stats)  # noqa: E731
            hits = run()  # kernels compiled (or loaded) here, not timed
            traces = body_traces(run)
            times = []
            for _ in range(a.reps):
                t0 = time.perf_counter()
                hits = run()
                times.append(time.perf_counter() - t0)
            steps = hits.stats.steps if stats else None
            ms = statistics.median(times) * 1e3
            rows.append({"mode": mode, "stats": stats, "ms_per_trace": ms, "steps": steps,
                         "body_traces_per_walk": traces})
            print(f"{mode:13s} stats={'on ' if stats else 'off'} {ms:6.2f} ms per trace call"
                  + (f" ({steps} steps)" if steps else "") + f"; loop body traced {traces} times per walk")
    doc = {"layerbvh": str(Path(layerbvh.__file__).parent), "rays": a.rays, "reps": a.reps,
           "cpu": layerbvh.cpu_model(), "lanes": layerbvh.llvm_vector_width(), "rows": rows}
    print(f"({doc['layerbvh']}; {doc['cpu']}, Dr.Jit LLVM {doc['lanes']} lanes; median of {a.reps})")
    if a.json:
        tmp = Path(a.json).with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
