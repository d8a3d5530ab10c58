"""Cost of one walk-kernel iteration per branching: LLVM IR instructions by branch, packet iterations, SIMD use and
ns per packet-iteration."""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import shlex
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import drjit as dr
import numpy as np

import layerbvh
from layerbvh import meshes
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.tools.bench.traversal import timed

# Lines of Dr.Jit's LLVM IR that are not work: labels, branches, and the broadcast of a
# constant (insertelement into undef + shufflevector), which LLVM folds into the operand.
_NOT_WORK = re.compile(r"^\s*(br |ret |[A-Za-z_0-9]+:|;|}|$)|insertelement <\d+ x [a-z0-9]+> undef|"
                       r"shufflevector <\d+ x [a-z0-9]+> %\S+, <\d+ x [a-z0-9]+> undef, <\d+ x i32> zeroinitializer")
_LABEL = re.compile(r"^(l_(\d+)_(start|end|body|done|cond|before)):")


@dataclass
class IRCount:
    """Instructions of the walk kernel's loop: all of it, and the parts inside its top-level
    branches (a packet runs a branch only when one of its lanes takes it)."""

    loop: int
    triangle_branch: int
    node_branch: int
    leaf_branch: int

    @property
    def always(self) -> int:
        """Instructions every packet-iteration runs (outside the three branches)."""
        return self.loop - self.triangle_branch - self.node_branch - self.leaf_branch


_HELPER = re.compile(r"^internal fastcc [^@]*@([A-Za-z_0-9]+)\(")
_CALL = re.compile(r"call fastcc [^@]*@([A-Za-z_0-9]+)\(")


def count_ir(ir: str) -> IRCount:
    """IRCount of the walk kernel: the kernel whose loop body is the largest in `ir`. A call of
    one of Dr.Jit's internal helpers (the packet gather `gather_8xf32`: 16 loads, their merge
    and a transpose) counts as the helper's own instructions, since it runs them inline."""
    parts = ir.split("\ndefine ")
    helpers = {}
    for part in parts:
        m = _HELPER.match(part)
        if m:
            helpers[m.group(1)] = sum(0 if _NOT_WORK.search(line) else 1 for line in part.splitlines()[1:])
    kernels = [k for k in parts if "_body:" in k]
    if not kernels:
        raise ValueError("no kernel with a loop in the IR")
    best = None
    for k in kernels:
        lines = k.splitlines()
        spans, open_at = {}, {}
        for i, line in enumerate(lines):
            m = _LABEL.match(line)
            if not m:
                continue
            label_id, kind = m.group(2), m.group(3)
            if kind in ("start", "before"):
                open_at.setdefault(label_id, i)
            elif kind == "end" and label_id in open_at:
                spans[label_id] = (open_at[label_id], i)
        work = np.array([0 if _NOT_WORK.search(line) else
                         1 + helpers.get((_CALL.search(line) or [None, None])[1], 0) for line in lines])
        loops = [lid for lid, (a, b) in spans.items()
                 if any(lines[j].startswith(f"l_{lid}_body:") for j in range(a, b))]
        if not loops:
            continue
        lid = max(loops, key=lambda x: spans[x][1] - spans[x][0])
        a, b = spans[lid]
        inner = sorted((s for x, s in spans.items() if x != lid and a < s[0] and s[1] < b), key=lambda s: s[0])
        top, last_end = [], -1
        for s in inner:  # top-level branches of the loop body, in program order
            if s[0] > last_end:
                top.append(s)
                last_end = s[1]
        size = [int(work[s[0]:s[1]].sum()) for s in top]
        total = int(work[a:b].sum())
        if best is None or total > best.loop:
            # First branch: a triangle; last: entering a leaf; the largest of the rest: the node.
            node = max(size[1:-1]) if len(size) > 2 else 0
            best = IRCount(loop=total, triangle_branch=size[0] if size else 0, node_branch=node,
                           leaf_branch=size[-1] if len(size) > 1 else 0)
    return best


def capture_ir(fn) -> str:
    """Run `fn` with Dr.Jit printing the IR of every kernel it compiles (on file descriptors 1
    and 2, whichever its log goes to), and return that text."""
    import ctypes  # local: the C library is opened only to flush its stdio buffers here
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    sys.stderr.flush()
    # Dr.Jit prints the IR of a kernel it compiles or loads from its disk cache, not of one it
    # already holds in memory (a kernel this process ran before): drop those first.
    dr.flush_kernel_cache()
    saved = [os.dup(1), os.dup(2)]
    # Where the log lands depends on who set Dr.Jit up: the process's descriptors, or Python's
    # sys.stdout / sys.stderr (replaced by pytest's capture, for one). Both are caught.
    py = io.StringIO()
    with tempfile.TemporaryFile("w+") as tmp, contextlib.redirect_stdout(py), contextlib.redirect_stderr(py):
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        dr.set_flag(dr.JitFlag.PrintIR, True)
        try:
            fn()
        finally:
            dr.set_flag(dr.JitFlag.PrintIR, False)
            libc.fflush(None)  # the C library's buffers, before the descriptors go back
            for fd, old in zip((1, 2), saved):
                os.dup2(old, fd)
                os.close(old)
        tmp.seek(0)
        return tmp.read() + py.getvalue()


@dataclass
class KernelCost:
    branching: int
    rays: str
    mrays_s: float
    speedup_vs_first: float    # median over rounds of (first branching's time / this one's)
    ir: dict
    iterations_per_ray: float
    packet_iterations_per_ray: float
    simd_use: float            # lane-iterations / (lanes x packet-iterations)
    ns_per_packet_iteration: float  # per core: wall time x threads / packet-iterations
    inner_per_ray: float
    box_tests_per_ray: float
    tris_per_ray: float


def packet_iterations(iters: np.ndarray, lanes: int) -> int:
    """Iterations of the packets that per_ray runs: W consecutive rays per packet, each packet
    looping until its slowest lane is done."""
    pad = -len(iters) % lanes
    return int(np.concatenate([iters, np.zeros(pad, iters.dtype)]).reshape(-1, lanes).max(1).sum())


class _Setup:
    """One branching's BVH, its rays on the device, IR and counted work (before any timing)."""

    def __init__(self, v, f, o, d, branching: int, height: int, leaf_size: int | None = None):
        self.branching = branching
        self.bvh = bvh = layerbvh.build(v, f, branching=branching, treelet_height=height, leaf_size=leaf_size)
        self.o, self.d = meshes.device_rays(bvh.m, o, d)
        self.ir = count_ir(capture_ir(lambda: dr.eval(bvh.trace(self.o, self.d, mode="per_ray", stats=False).t)))
        self.counted = bvh.trace(self.o, self.d, mode="per_ray", stats=True)
        self.iters = np.asarray(self.counted.work["iterations"].numpy(), np.int64)
        self.times = []

    def run(self) -> None:
        def trace():
            h = self.bvh.trace(self.o, self.d, mode="per_ray", stats=False)
            dr.eval(h.t, h.prim)
        self.times.append(timed(trace)[0])


def measure(v, f, o, d, branchings: list[int], kind: str, runs: int, height: int,
            leaf_size: int | None = None) -> list[KernelCost]:
    """KernelCost of each branching on the same rays; the timed runs go round-robin over the
    branchings (one of each per round), so drifts of a shared machine hit all alike."""
    setups = [_Setup(v, f, o, d, k, height, leaf_size) for k in branchings]
    for r in range(runs):
        for s in setups[r % len(setups):] + setups[:r % len(setups)]:
            s.run()
    lanes = layerbvh.llvm_vector_width() if setups[0].bvh.backend == "llvm" else 32
    base = setups[0].times
    out = []
    for s in setups:
        secs = float(np.median(s.times))
        p_iter = packet_iterations(s.iters, lanes)
        st, n = s.counted.stats, len(o)
        out.append(KernelCost(
            branching=s.branching, rays=kind, mrays_s=n / secs / 1e6,
            speedup_vs_first=float(np.median([b / t for b, t in zip(base, s.times)])),
            ir=asdict(s.ir) | {"always": s.ir.always},
            iterations_per_ray=float(s.iters.mean()), packet_iterations_per_ray=p_iter / n,
            simd_use=float(s.iters.sum()) / (lanes * p_iter),
            ns_per_packet_iteration=secs * dr.thread_count() / p_iter * 1e9,
            inner_per_ray=st.inner_nodes_per_ray, box_tests_per_ray=st.inner_nodes_per_ray * s.branching,
            tris_per_ray=st.triangles_per_ray))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--mesh", default=None, help="a .ply/.obj mesh (default: a procedural mesh of --procedural-tris)")
    p.add_argument("--procedural-tris", type=int, default=600_000)
    p.add_argument("--rays", type=int, default=1_000_000)
    p.add_argument("--branchings", default=",".join(map(str, layerbvh.BRANCHINGS)))
    p.add_argument("--height", type=int, default=layerbvh.DEFAULT_TREELET_HEIGHT)
    p.add_argument("--leaf-size", type=int, help="triangles per leaf for every branching (default: each "
                                                   "branching's own, layerbvh.default_leaf_size)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="OUT")
    args = p.parse_args(argv)
    try:
        branchings = [layerbvh.check_param("branching", int(k)) for k in args.branchings.split(",")]
    except ValueError as e:
        p.error(f"--branchings: {e}")
    use_variant()
    if args.mesh:
        v, f = meshes.load_mesh(args.mesh)
        name = Path(args.mesh).stem
    else:
        v, f = meshes.procedural_mesh(args.procedural_tris, seed=args.seed)
        name = f"procedural_{args.procedural_tris // 1000}k"
    command = shlex.join(getattr(sys, "orig_argv", [sys.executable] + sys.argv))
    cpu = layerbvh.cpu_model()
    lanes = layerbvh.llvm_vector_width()
    print(f"# Walk-kernel cost per branching\n\n`{command}`\n\n{cpu}, {os.cpu_count()} cores, {lanes} lanes; "
          f"{name} ({len(f):,} triangles), {args.rays:,} rays, per_ray, median of {args.runs} interleaved rounds; "
          f"× first K: median per-round speed-up over the first branching listed\n")
    print("| rays | K | Mrays/s | × first K | IR loop | always | node branch | triangle branch | iters/ray "
          "| packet iters/ray | SIMD use | ns/packet-iter (per core) | inner/ray | box tests/ray | tris/ray |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for kind, gen, seed in (("incoherent", meshes.incoherent_rays, 2), ("camera", meshes.camera_rays, 1)):
        o, d = gen(v, args.rays, seed=args.seed + seed)
        for c in measure(v, f, o, d, branchings, kind, args.runs, args.height, args.leaf_size):
            k = c.branching
            rows.append(asdict(c))
            print(f"| {kind} | {k} | {c.mrays_s:.2f} | {c.speedup_vs_first:.2f} | {c.ir['loop']} | {c.ir['always']} "
                  f"| {c.ir['node_branch']} | {c.ir['triangle_branch']} | {c.iterations_per_ray:.1f} "
                  f"| {c.packet_iterations_per_ray:.2f} "
                  f"| {c.simd_use:.2f} | {c.ns_per_packet_iteration:.0f} | {c.inner_per_ray:.1f} "
                  f"| {c.box_tests_per_ray:.1f} | {c.tris_per_ray:.1f} |", flush=True)
    if args.json:
        atomic.write_text(args.json, json.dumps({"command": command, "cpu": cpu, "lanes": lanes, "mesh": name,
                                                 "triangles": int(len(f)), "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
