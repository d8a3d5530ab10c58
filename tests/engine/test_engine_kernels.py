"""One compiled kernel serves every tree and every input alignment: what the suite's and a user's first-run time rest
on (issue 39: most of it is LLVM compiling kernels)."""
from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

import layerbvh
from layerbvh import backend as be
from layerbvh import meshes
from layerbvh.loopstate import body_traces


def _history(fn) -> list[dict]:
    """Dr.Jit's kernel history of what `fn` launches."""
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # what came before is not ours
    try:
        fn()
        return dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)


def _launched(fn) -> set[str]:
    """Hashes of the compiled (JIT) kernels `fn` launches."""
    return {k["hash"] for k in _history(fn) if k.get("hash")}


def _misaligned(a: np.ndarray) -> np.ndarray:
    """A copy of `a` whose data starts 4 bytes past a 64-byte boundary."""
    buf = np.empty(a.nbytes + 128, np.uint8)
    start = -buf.ctypes.data % 64 + 4
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def test_numpy_inputs_compile_one_kernel_whatever_their_alignment():
    """Dr.Jit maps numpy memory as it is and compiles a kernel reading an unaligned array with
    other loads (another kernel): from_numpy hands it aligned memory, so the same code over an
    aligned and a misaligned array is one kernel."""
    m = be.module("llvm")
    x = np.arange(1000, dtype=np.float32)
    kernels = []
    for a in (be.aligned(x), _misaligned(x)):
        kernels.append(_launched(lambda a=a: dr.eval(be.from_numpy(m.Float, a) * 3 + 1)))
    assert kernels[0] == kernels[1]
    assert int(be.from_numpy(m.Float, _misaligned(x))[999]) == 999


@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_a_second_tree_compiles_no_new_kernel(mode):
    """Two meshes whose trees differ in depth, treelet count and size: tracing the second, in the
    same mode with the same options, launches only kernels the first compiled (per-tree numbers
    are kernel parameters; local stacks are rounded up to a power of two, here 32 slots for both; the two
    trees take as many steps, so the same kernels run)."""
    small, large = meshes.procedural_mesh(3000, seed=5), meshes.procedural_mesh(5000, seed=3)
    bvhs = [layerbvh.build(v, f) for v, f in (small, large)]
    assert bvhs[0].stats.depth != bvhs[1].stats.depth and bvhs[0].stats.treelets != bvhs[1].stats.treelets
    seen = []
    for (v, _), bvh in zip((small, large), bvhs):
        o, d = meshes.incoherent_rays(v, 4000, seed=1)
        seen.append(_launched(lambda: bvh.trace(o, d, mode=mode, stats=True)))
    assert seen[1] <= seen[0], f"{len(seen[1] - seen[0])} kernels compiled again for the second tree"


@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_lazy_rays_are_computed_in_one_kernel(mode):
    """A renderer hands the traversal rays it has not evaluated (its shading): they are computed
    once, in one kernel, not once per column the traversal gathers (each a kernel to compile)."""
    v, f = meshes.procedural_mesh(3000, seed=5)
    bvh = layerbvh.build(v, f)
    o, d = meshes.incoherent_rays(v, 4000, seed=2)
    m = be.module("llvm")
    cols = [be.from_numpy(m.Float, np.ascontiguousarray(a[:, c])) for a in (o, d) for c in range(3)]
    dr.eval(cols)
    evaluated = _launched(lambda: bvh.trace(m.Array3f(*cols[:3]), m.Array3f(*cols[3:]), mode=mode, stats=False))
    lazy_o = m.Array3f(*(c * 1.0001 - 0.0001 * c for c in cols[:3]))  # lazy, and the same rays up to rounding
    lazy_d = m.Array3f(*(-(-c) for c in cols[3:]))
    lazy = _launched(lambda: bvh.trace(lazy_o, lazy_d, mode=mode, stats=False))
    assert len(lazy - evaluated) <= 1, f"{len(lazy - evaluated)} kernels more for lazy rays (one computes them)"


@pytest.mark.parametrize("instanced", [False, True])
@pytest.mark.parametrize("branching", [2, 4])
@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_a_walk_traces_its_loop_once(mode, branching, instanced, bunny):
    """Every walk (per_ray's, each wavefront step's, the tail's, and the renderer's inline one)
    traces its loop body once, with and without work counters: a loop state variable that the
    body leaves unchanged (an input it only reads, a counter this walk does not keep) makes
    Dr.Jit trace the whole body a second time to drop it, twice the host time of each walk
    (PERFORMANCE.md entry 58)."""
    v, f = meshes.procedural_mesh(3000, seed=5)
    if instanced:
        groups = [layerbvh.Group(v, f), layerbvh.Group(*bunny)]
        shifted = [np.hstack([np.eye(3), [[0.1 * k], [0], [0]]]) for k in range(3)]
        inst = [layerbvh.Instance(g, m) for g, m in zip((0, 1, 0), shifted)]
        bvh = layerbvh.build_instanced(groups, inst, treelet_height=3, branching=branching)
    else:
        bvh = layerbvh.build(v, f, treelet_height=3, branching=branching)
    o, d = meshes.incoherent_rays(v, 3000, seed=1)
    for stats in (False, True):
        counts = body_traces(lambda: bvh.trace(o, d, mode=mode, stats=stats))
        assert counts and counts == [1] * len(counts), (stats, counts)
        counts = body_traces(lambda: bvh.occluded(o, d, mode=mode, stats=stats))
        assert counts and counts == [1] * len(counts), ("occluded", stats, counts)
    if mode == "per_ray":
        F = bvh.m.Float
        counts = body_traces(lambda: dr.eval(bvh.trace_inline([be.from_numpy(F, np.ascontiguousarray(o[:, c]))
                                                                for c in range(3)],
                                                               [be.from_numpy(F, np.ascontiguousarray(d[:, c]))
                                                                for c in range(3)], F(np.inf), bvh.m.Bool(True)).t))
        assert counts == [1], ("inline", counts)


def test_ray_records_are_packed_by_one_kernel():
    """RayRecords packs each ray's origin and direction into one 32-byte record with one kernel
    that writes the records whole (RayRecords.write: a layer trace's first step writes those of
    the rays that go on the same way, PERFORMANCE.md entry 63), nothing filled first: six scatters of a
    component each were six kernels, each passing over every record, and a memset (PERFORMANCE.md,
    entry 59: 3 of valgrind's 6.9 write misses per ray)."""
    from layerbvh.state import RayRecords
    m = be.module("llvm")
    rng = np.random.default_rng(3)
    n = 1000
    cols = [rng.normal(size=n).astype(np.float32) for _ in range(6)]
    o, d = [m.Float(c) for c in cols[:3]], [m.Float(c) for c in cols[3:]]
    dr.eval(*o, *d)
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        rec = RayRecords(m, o, d).rec
        dr.sync_thread()
        kinds = [k["type"] for k in dr.kernel_history()]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert kinds == [dr.KernelType.JIT], kinds
    assert np.array_equal(np.asarray(rec).reshape(n, 8), np.stack(cols + [np.zeros(n, np.float32)] * 2, 1))


@pytest.mark.parametrize("mode", ["per_ray", "layer_sorted"])
def test_the_walks_local_stacks_are_never_filled(bunny, mode):
    """A walk reads its local entry stack only where it pushed (below `nl`, or a pop's select that
    other lanes discard), so the stack is left uninitialized: zero-filled, every packet first wrote
    all of it (an LLVM memset of 4 KiB per 8-lane packet on a deep tree, ~20% of per_ray's time on
    1M incoherent rays: PERFORMANCE.md entry 69), traffic the locality model does not have. The
    traversal kernels of both modes hold their local arrays and fill none of them."""
    v, f = bunny
    o, d = meshes.incoherent_rays(v, 4000, seed=0)
    bvh = layerbvh.build(v, f)
    irs = [k["ir"].getvalue() for k in _history(lambda: np.asarray(bvh.trace(o, d, mode=mode, stats=False).prim))
           if k["type"] == dr.KernelType.JIT]
    walks = [ir for ir in irs if "alloca" in ir]
    assert len(walks) == (1 if mode == "per_ray" else 2), len(walks)
    assert not any("memset" in ir for ir in walks)
