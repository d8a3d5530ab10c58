#!/usr/bin/env python3
"""The stack frame of each traversal kernel on this CPU: its LLVM IR (as Dr.Jit hands it to LLVM)
compiled by llc at -O2 for the host, with the frame's bytes, the local entry stacks' share and the
register spills (stores) and reloads llc marks. Why: at an 8 KiB D1 valgrind counts several write
misses per ray that the locality model's loads and stores do not explain (docs/guide.md); a
frame of kilobytes that every iteration touches would compete with the node traffic there.

    .venv/bin/python scripts/kernel_frame.py [--mesh scenes/meshes/bunny.ply] [--rays 4000] [--json OUT]

Needs llc (Debian: apt-get install llvm-19; Dr.Jit's IR uses intrinsics older llc versions cannot
select). Not a test: which registers spill is LLVM's and the CPU's choice.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
LLC = ("llc-19", "/usr/lib/llvm-19/bin/llc")


def frame(ir: str, llc: str, cpu: str) -> dict:
    """llc's assembly of one kernel's IR: frame bytes (the largest `sub $N, %rsp`), alloca bytes
    (the local arrays), spill stores and reloads (llc's `Spill` / `Reload` comments)."""
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "k.ll", Path(tmp) / "k.s"
        src.write_text(ir)
        run = subprocess.run([llc, "-O2", f"-mcpu={cpu}", str(src), "-o", str(out)], capture_output=True, text=True)
        if run.returncode:
            said = run.stderr.strip()
            return {"error": said.splitlines()[-1] if said else f"llc exit {run.returncode}"}
        asm = out.read_text()
    subs = [int(x) for x in re.findall(r"subq\s+\$(\d+),\s*%rsp", asm)]
    allocas = sum(int(n) * (4 if t in ("float", "i32") else 8)
                  for t, n in re.findall(r"alloca (float|i32|i64|double), i32 (\d+)", ir))
    # The frame's 64-byte lines that spills and reloads touch (`N(%rsp)` operands on llc's Spill and
    # Reload lines, each access of the marked width): what a packet iteration reads and writes
    # there besides the local arrays (the locality model's `frame_bytes`, memsites.S_FRAME_READ).
    lines = set()
    for m in re.finditer(r"(-?\d*)\(%rsp\)[^\n]*# (\d+)-byte (?:Folded )?(?:Spill|Reload)", asm):
        off, size = int(m.group(1) or 0), int(m.group(2))
        lines.update(range(off // 64, (off + size - 1) // 64 + 1))
    return {"frame_bytes": max(subs, default=0), "local_array_bytes": allocas,
            "spill_stores": asm.count("Spill"), "reloads": asm.count("Reload"), "spill_line_bytes": 64 * len(lines)}


def find_llc() -> str | None:
    return next((x for x in LLC if shutil.which(x)), None)


def kernel_rows(bvh, o, d, modes, llc: str, cpu: str = "native") -> list[dict]:
    """One row per traversal kernel (ops >= 200, each once) that tracing `o`, `d` runs in each mode."""
    import drjit as dr

    from layerbvh import backend as be, meshes, wavefront
    from layerbvh.inputs import ray_batch
    m = be.module("llvm")
    dev = bvh.layout.to_device(m)
    rows = []
    for mode in modes:
        oo, dd = meshes.device_rays(m, o, d)
        batch = ray_batch(m, "llvm", oo, dd, m.Float(np.full(len(o), np.inf, np.float32)))
        dr.eval(*batch.o, *batch.d, batch.tmax, batch.valid)
        was = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        try:
            res, _ = wavefront.trace(m, dev, batch, mode=mode, any_hit=False, count_work=False,
                                     tail_rays=bvh.tail_rays, tail_fraction=bvh.tail_fraction,
                                     tail_steps=bvh.tail_steps)
            dr.eval(res.t, res.prim)
            dr.sync_thread()
            kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, was)
        seen = set()
        for k in kernels:
            if k["hash"] in seen or k["operation_count"] < 200:  # (the traversal kernels, once each)
                continue
            seen.add(k["hash"])
            rows.append({"mode": mode, "hash": k["hash"], "ops": k["operation_count"], "lanes": k["size"],
                         **frame(k["ir"].getvalue(), llc, cpu)})
    return rows


def spill_bytes_by_mode(rows: list[dict]) -> dict:
    """Per mode, the most spill-line bytes of its kernels (the locality model's `frame_bytes`)."""
    out: dict = {}
    for r in rows:
        out[r["mode"]] = max(out.get(r["mode"], 0), r.get("spill_line_bytes", 0))
    return out


def main() -> int:
    import layerbvh
    from layerbvh import meshes
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", default="scenes/meshes/bunny.ply")
    p.add_argument("--rays", type=int, default=4000)
    p.add_argument("--cpu", default="native", help="llc's -mcpu (default: the host)")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args()
    llc = find_llc()
    if llc is None:
        print("kernel_frame: llc 19 is not installed (Debian: apt-get install llvm-19)", file=sys.stderr)
        return 2
    v, f = meshes.load_mesh(args.mesh)
    bvh = layerbvh.build(v, f, backend="llvm")
    o, d = meshes.incoherent_rays(v, args.rays, seed=0)
    rows = kernel_rows(bvh, o, d, ("per_ray", "layer_sorted"), llc, args.cpu)
    for row in rows:
        print(f"{row['mode']:13} kernel {row['hash'][:8]} ({row['ops']} ops): "
              + (row["error"] if "error" in row else
                 f"frame {row['frame_bytes']:,} B ({row['local_array_bytes']:,} B local entry stacks), "
                 f"{row['spill_stores']} spill stores, {row['reloads']} reloads, "
                 f"{row['spill_line_bytes']:,} B of spill lines"))
    if args.json:
        Path(args.json).write_text(json.dumps({"mesh": args.mesh, "rays": args.rays, "llc": llc, "cpu": args.cpu,
                                               "machine": layerbvh.cpu_model(), "command": " ".join(sys.argv),
                                               "kernels": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
