"""BENCHMARKS.md's GPU section: the tables of a GPU check's folder (scripts/gpu_check.sh's device half:
measured_<backend>.json, model.json and its --kernels listings)."""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT

GPU_SECTION = "gpu"  # BENCHMARKS.md's markers around the section
DEFAULT_FOLDER = ROOT / "docs" / "bench" / "gpu_h200"  # the one GPU lent so far
_HEAD = re.compile(r"K=(\d+) H=(\d+) (\S+): ([\d,]+) rays, (\d+) launches, kernels ([\d.]+) ms of ([\d.]+) ms wall")
_LAUNCH = re.compile(r"\s+KernelType\.(\S+)\s+width\s+([\d,]+) ops\s+(\d+) in\s+(\d+) out\s+(\d+)\s+([\d.]+) ms")
# The traversal kernel (walk's loop: several hundred IR operations) is the only launch that large;
# the next largest, state setup and gathers (and the held-entry move of the listings made before
# PERFORMANCE.md entry 45), have under 40.
TRAVERSAL_OPS = 300


def kernel_split(text: str) -> list[dict]:
    """Per (branching, height, mode) of a `gpu_check_device.py --kernels` listing: the GPU's time in
    the traversal kernels, in kernels between a step and its sort (the first JIT kernel after each
    step's traversal kernel: until PERFORMANCE.md entry 45 the move of the entries each ray still
    held, over the step's (lane, entry) pairs, as in the H200 listings of docs/bench/gpu_h200;
    since then the step kernel writes them itself and nothing runs there), in the sort (MkPerm,
    and argsort's prefix sums between its MkPerm passes) and in the rest (state set-up, gathers,
    memsets), and the wall time the launches leave idle."""
    out, cur, prev = [], None, ""
    for line in text.splitlines():
        if m := _HEAD.match(line):
            k, h, mode, n, launches, total, wall = m.groups()
            cur = {"branching": int(k), "treelet_height": int(h), "mode": mode, "rays": int(n.replace(",", "")),
                   "launches": int(launches), "kernels_ms": float(total), "wall_ms": float(wall),
                   "traversal_ms": 0.0, "steps": 0, "between_ms": 0.0, "sort_ms": 0.0, "rest_ms": 0.0}
            out.append(cur)
            prev = ""
        elif (m := _LAUNCH.match(line)) and cur is not None:
            typ, _, ops, _, _, ms = m.groups()
            ms, ops = float(ms), int(ops)
            if typ == "JIT" and ops >= TRAVERSAL_OPS:
                cur["traversal_ms"] += ms
                cur["steps"] += 1
                prev = "traversal"
                continue
            if typ == "JIT" and prev == "traversal":
                cur["between_ms"] += ms
                prev = typ
            elif typ == "MkPerm" or (typ == "BlockPrefixReduce" and prev == "MkPerm"):
                cur["sort_ms"] += ms  # (a prefix sum between two MkPerm passes is argsort's; one
                prev = typ            # after a Compress is the ray batch's compaction: set-up)
            else:
                cur["rest_ms"] += ms
                prev = typ if typ == "JIT" else prev  # (the step's two counts: reductions and copies on LLVM)
    for r in out:
        r["host_gaps_ms"] = r["wall_ms"] - r["kernels_ms"]
    return out


def _md(head: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows])


def check_table(measured: dict) -> str:
    """paper_mix's recorded rays: both modes' throughput, the measured ratio beside the model's."""
    rows = [[r["branching"], r["treelet_height"], r["kind"], f"{r['rays']:,}",
             f"{r['rays'] / r['seconds']['per_ray'] / 1e6:.1f}",
             f"{r['rays'] / r['seconds']['layer_sorted'] / 1e6:.1f}",
             f"{r['measured_sorted_over_per_ray']:.2f}x", f"{r['model_dram_per_ray_over_sorted']:.2f}x",
             f"{r['model_total_per_ray_over_sorted']:.2f}x",
             f"{r['hits_differing_from_replay']['per_ray']} / {r['hits_differing_from_replay']['layer_sorted']}"]
            for r in measured["kinds"]]
    return _md(["K", "H", "rays", "count", "per_ray Mrays/s", "layer_sorted Mrays/s", "measured speed-up",
                "model: per_ray ÷ sorted DRAM bytes", "... with the steps' own traffic", "hits ≠ LLVM replay"], rows)


def soup_table(measured: dict) -> str:
    """The sphere soup's incoherent rays at the GPU's scale, with the sorted path's host-timed split."""
    rows = []
    for r in measured.get("soup", []):
        sp = r["split"]["layer_sorted"]
        rows.append([r["branching"], r["treelet_height"], r["query"], f"{r['rays']:,}",
                     f"{r['rays'] / r['seconds']['per_ray'] / 1e6:.0f}",
                     f"{r['rays'] / r['seconds']['layer_sorted'] / 1e6:.0f}",
                     f"{r['measured_sorted_over_per_ray']:.2f}x",
                     sp["steps"], r["modes_disagree"]])
    return _md(["K", "H", "query", "rays", "per_ray Mrays/s", "layer_sorted Mrays/s", "speed-up", "steps",
                "hits differing"], rows)


def kernel_table(splits: list[dict]) -> str:
    rows = []
    for r in splits:
        rows.append([r["branching"], r["treelet_height"], r["mode"], f"{r['rays']:,}", r["launches"],
                     f"{r['traversal_ms']:.1f} ({r['steps']})", f"{r['between_ms']:.1f}", f"{r['sort_ms']:.1f}",
                     f"{r['rest_ms']:.1f}", f"{r['host_gaps_ms']:.1f}", f"{r['wall_ms']:.1f}"])
    return _md(["K", "H", "mode", "rays", "launches", "traversal kernels ms (launches)", "between-step kernels ms",
                "sort ms", "set-up, gathers ms", "host gaps ms", "wall ms"], rows)


def section(folder: Path) -> str:
    measured = json.loads(next(folder.glob("measured_*.json")).read_text())
    model = json.loads((folder / "model.json").read_text())
    device = (folder / "device.txt").read_text().strip() if (folder / "device.txt").exists() else "the lent GPU"
    parts = ["## GPU: measured against the model (`scripts/gpu_check.sh`)", "",
             f"Measured on {device} with Dr.Jit's `{measured['backend']}` backend; "
             f"the model's preset `{model['preset']['name']}`; rays recorded from {model['scene']} at "
             f"{model['recording']['resolution'][0]}×{model['recording']['resolution'][1]}, "
             f"{model['recording']['rays_per_kind']:,} per kind. Command: `bash scripts/gpu_check.sh`, then "
             "`python3 scripts/gpu_check_device.py out/gpu_check --backend cuda` on the device (its output is in "
             f"`{folder.relative_to(ROOT) if folder.resolve().is_relative_to(ROOT) else folder}`). Speed-up is "
             "per_ray's median time over layer_sorted's (above 1: sorting wins).", "",
             check_table(measured), "",
             "### Incoherent rays at the GPU's own scale", "",
             "A sphere soup (`layerbvh.meshes.sphere_soup`) and `meshes.incoherent_rays`, as the benchmarks make "
             "them; no model row (its replay of millions of rays does not fit this check's time).", "",
             soup_table(measured), ""]
    for log in sorted(folder.glob("kernels_*.log")):
        text = log.read_text()
        parts += [f"### Where the GPU's time goes: `{log.name}`", "",
                  f"`python3 scripts/gpu_check_device.py out/gpu_check --backend cuda --kernels RAYS --soup TRIS`; "
                  "each launch's execution time from Dr.Jit's kernel history. Host gaps: wall time with no kernel "
                  "running (tracing the step's kernel in Python, the counts read back each step: two in these "
                  "listings, one since PERFORMANCE.md entry 45; the launches).", "",
                  kernel_table(kernel_split(text)), ""]
    return "\n".join(parts)


def block(folder: Path) -> list[str]:
    """The section between its markers, for report.py's whole document."""
    return atomic.marked_lines(GPU_SECTION, section(folder))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("folder", nargs="?", default=str(DEFAULT_FOLDER))
    p.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    args = p.parse_args(argv)
    atomic.splice_section(Path(args.out), GPU_SECTION, section(Path(args.folder)))
    print(f"replaced the GPU section of {args.out} from {args.folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
