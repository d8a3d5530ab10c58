"""Trace drivers: one kernel per batch (per_ray) and sorted/unsorted wavefront steps over treelets."""
from __future__ import annotations

import os
import time

import drjit as dr

from .collector import collector_held
from .inputs import RayBatch
from .layout import DeviceLayout, treelet_levels
from .state import DirectRays, EntryStack, RayRecords, RayState, Results, SlotRays, StateRecords, work_fields
from .stats import StepTime, TraceStats
from .walk import walk

MODES = ("per_ray", "layer_sorted", "layer_unsorted")
ENTRY_BYTES = 8  # one entry-stack slot: link (uint32) + entry distance (float32)
# When this few rays are left, one per-ray kernel finishes them from their entry stacks: a
# long tail of nearly empty wavefront steps costs host time per step and buys no locality.
TAIL_RAYS = 2048
# ... and so does it once this share of a batch is left: the first steps, with many rays per
# treelet, are where sorting pays (PERFORMANCE.md entry 20).
TAIL_FRACTION = 0.25
# ... and so does it after this many steps, however many rays are left (a LayerBVH's `tail_steps`).
# The tail walks the rays in the order the last step sorted them (by the treelet each enters next),
# so it keeps that sort's coherence without a step's per-ray reads and writes, its sort and its host
# time; and a tree whose boxes all overlap (the stability suite's turned slivers) cannot take
# hundreds of steps. One step: on every ray set of scripts/tail_cutoff.py (docs/bench/tail_cutoff.json,
# PERFORMANCE.md entry 61) the least total DRAM bytes in the model of the paper's GPU (gtx965m,
# W = 32) and the fastest layer_sorted on the CPU. A larger k keeps the rays in sorted steps longer.
TAIL_STEPS = 1
# Where a trace's entry stacks are at most this many bytes, its step and tail kernels are frozen
# (dr.freeze): recorded once per tree and batch shape, then replayed without tracing the walk in
# Python again (PERFORMANCE.md entry 54: 47 ms -> 2 ms per 10-step trace of 512 rays). A frozen
# step cannot take the spill's second array over the stack's memory (drjit 1.5.0 crashes on it,
# and cannot record the alias made inside), so Dr.Jit copies the stack it scatters into once a
# step: cheap below this size, and above it the unfrozen step (no copy) is taken. Backends whose
# frozen steps a run has checked against the unfrozen ones (CUDA: not yet, issue 57 item 4).
# Off unless LAYERBVH_FROZEN_STEPS=1: a run of the suite with them on aborted inside a frozen
# step's recording. Cause (PERFORMANCE.md entry 55): Python's cycle collector ran there and freed
# a Mitsuba scene, whose release drjit cannot record; the steps now hold the collector off
# (collector.collector_held). tests/engine/test_engine_frozen.py runs them on, against the
# unfrozen steps.
FROZEN_STACK_BYTES = 16 << 20
FROZEN_BACKENDS = ("llvm",) if os.environ.get("LAYERBVH_FROZEN_STEPS") == "1" else ()


def takes_tail(n_active: int, n0: int, steps: int, tail_rays: int, tail_fraction: float,
               tail_steps: int = TAIL_STEPS) -> bool:
    """Whether the rays still active after `steps` wavefront steps (of n0) are finished by one
    per-ray kernel (the tail) instead of more steps: the rule `trace` runs and the locality replay
    follows. tail_rays = 0 and tail_fraction = 0 turn the tail off, the step cap (tail_steps) with it."""
    if steps == 0 or (tail_rays == 0 and tail_fraction == 0):
        return False
    return n_active <= max(tail_rays, int(tail_fraction * n0)) or steps >= tail_steps


def stack_rows(lay: DeviceLayout) -> int:
    """Entry-stack slots a per-ray walk can need: each node level pushes at most branching - 1
    entries (the nearest hit child is taken, not pushed)."""
    return max(1, (lay.branching - 1) * lay.depth)


# A walk's local stack is a fixed-size array in the kernel (an alloca: its size is a literal of
# the kernel's code). Its slots are rounded up to a power of two (at least LOCAL_ROWS_MIN), so
# trees of similar depth share one compiled kernel instead of compiling one per depth (issue 39:
# the suite's time is mostly LLVM compiling). Spare slots cost thread stack, never traffic.
LOCAL_ROWS_MIN = 16


def local_rows(rows: int) -> int:
    """Local stack slots for a walk that may hold `rows` entries (LOCAL_ROWS_MIN)."""
    return max(LOCAL_ROWS_MIN, 1 << (rows - 1).bit_length())


def _sync():
    dr.sync_thread()
    return time.perf_counter()


def trace(m, lay: DeviceLayout, batch: RayBatch, *, mode: str, any_hit: bool, tail_rays: int = TAIL_RAYS,
          count_work: bool = True, tail_fraction: float = TAIL_FRACTION, tail_steps: int = TAIL_STEPS):
    """Closest hit (or any hit) of every ray of `batch`; returns (Results, TraceStats)."""
    n = batch.n
    stats = TraceStats(mode=mode, rays=n)
    instanced = lay.instances is not None
    res = Results(m, n, instanced)
    # Invalid and inactive rays are misses and never enter a kernel.
    idx = dr.compress(batch.valid)
    if dr.width(idx) == 0:  # no valid ray: Dr.Jit kernels cannot run on empty arrays
        return res, stats
    # per_ray reads the batch's arrays by slot; the layer modes' later kernels read a ray's 32-byte
    # record, which the first step writes for the rays that go on (RayRecords.write).
    rays = SlotRays(m, batch.o, batch.d) if mode == "per_ray" else RayRecords.unfilled(m, n)
    t0 = _sync()
    if mode == "per_ray":
        s = RayState.start(m, batch.tmax, count_work, instanced).take(idx)
        cap = local_rows(stack_rows(lay))
        out, done = walk(m, lay, rays, s, stack=None, cap=cap, bounded=False, any_hit=any_hit,
                         count_work=count_work)
        res.write(out, done)
        dr.eval(*res.arrays())
        t1 = _sync()
        stats.steps = 1
        stats.active_per_step = [dr.width(s.t)]
        stats.time_traverse_s = t1 - t0
        stats.work_bytes = n * 4 * 10  # ray in/out arrays
        return res, stats

    sort = mode == "layer_sorted"  # (modes are checked where they come in: LayerBVH.trace/occluded)
    # A step pushes at most branching - 1 entries per level of its treelet, plus, in an instanced
    # layout, the LEAVE marker of the instance it enters (entering ends the step).
    levels = treelet_levels(lay.height, lay.branching)
    cap_local = max(1, (lay.branching - 1) * min(levels, lay.depth)) + (1 if instanced else 0)
    cap_global = stack_rows(lay)
    # Entries are only read below a ray's stack pointer, so the stacks need no zeroing.
    st_link = dr.empty(m.UInt32, n * cap_global)
    st_t = dr.empty(m.Float, n * cap_global)
    stack = EntryStack(st_link, st_t, cap_global)
    # The same memory as a second array, which the step kernels write (walk's `spill`) while they
    # read the stack itself: Dr.Jit would copy an array a kernel both reads and writes.
    # (Not in a frozen trace: frozen_steps. The frozen kernels cannot record the alias, and an
    # alias alive beside them hides the stack's memory from the recording.)
    frozen = frozen_steps(lay, n, cap_global)
    if frozen:
        dr.eval(st_link, st_t)
    else:
        spill = EntryStack(_alias(st_link), _alias(st_t), cap_global)
    finished = lay.treelet_count  # bucket after every treelet: finished rays sort last
    # Per-tree numbers enter the kernels opaque (kernel parameters, not literals), so one
    # compiled kernel serves every tree (issue 39).
    finished_key = dr.opaque(m.UInt32, finished)
    buckets = 1 << max(1, (finished).bit_length())
    work = tuple(work_fields(instanced)) if count_work else ()  # statistics: the work counters
    # The states between steps as records (state.StateRecords, compact where they fit), each step
    # writing those its next step reads. The first step reads none: its kernel starts each ray at the
    # root from its slot and tmax (RayState.begin) and reads its origin and direction from the
    # batch's arrays, so `rec` is (slots, tmax, origin, direction) until a step wrote records.
    words = StateRecords.words(instanced, cap_global, n)
    rec = (idx, *(m.Float(x) for x in (batch.tmax, *batch.o, *batch.d)))  # (new handles: a frozen trace
    # makes them opaque, not the caller's)
    peak = 0
    n_active = n0 = dr.width(idx)
    stats.frozen = frozen
    # The state between steps: the records, the permutation the next step reads them by, and the
    # work counters (None: all zero, the first step's).
    perm, counters = dr.arange(m.UInt32, n_active), None
    kw = dict(instanced=instanced, words=words, work=work, any_hit=any_hit, count_work=count_work)
    first = True  # (the tail never comes first: takes_tail)
    if frozen:
        counters = tuple(dr.zeros(m.UInt32, n_active) for _ in work)
        # (Every input evaluated: a literal input's size is part of a recording, and one whose
        # width then changes fails the replay's dry run and is recorded again, measured.)
        dr.make_opaque(*rec)  # (dr.eval leaves a literal, the default tmax, as it is)
        dr.eval(perm, *counters, *res.arrays())
    while n_active > 0:
        stats.active_per_step.append(n_active)
        ta = _sync()
        if takes_tail(n_active, n0, stats.steps, tail_rays, tail_fraction, tail_steps):
            # Same nearest-first order as the steps, so the same hits and work counts.
            if frozen:
                with collector_held():
                    _TAIL(m, lay, rays.rec, rec, perm, counters, res.fields(), tuple(stack), local_rows(cap_global),
                          **kw)
            else:
                _tail(m, lay, rays, rec, perm, counters, res, stack, local_rows(cap_global), **kw)
            traced = time.perf_counter()
            dr.eval(*res.arrays())
            tb = _sync()
            stats.time_traverse_s += tb - ta
            stats.step_times.append(StepTime(n_active, traced - ta, tb - traced, 0.0, tail=True))
            stats.tail_rays = n_active
            stats.steps += 1
            break
        rec_out = dr.empty(m.UInt32, n_active * words)
        if frozen:  # (a frozen step's replay launches its kernels as it goes)
            with collector_held():
                rec, keys, n_done_w, counters = _STEP(m, lay, rays.rec, rec, perm, counters, res.fields(),
                                                      tuple(stack), rec_out, cap_local, finished_key, first=first,
                                                      **kw)
        else:
            rec, keys, n_done_w, counters = _step(m, lay, rays, rec, perm, counters, res, stack, spill, rec_out,
                                                  cap_local, finished_key, first=first, **kw)
        first = False
        traced = time.perf_counter()  # the step traced in Python (unfrozen: nothing launched yet)
        dr.eval(rec, keys, n_done_w, *counters, *res.arrays())
        n_step = dr.width(keys)
        n_active -= int(n_done_w[0])
        tb = _sync()
        stats.steps += 1
        stats.time_traverse_s += tb - ta
        te = tb
        if n_active > 0:
            # Only the next step's permutation is written: it gathers each ray's record through it
            # (unfrozen: lazily, inside its kernel).
            perm = _order(m, keys, n_step, n_active, buckets, finished_key, sort)
            if frozen:
                dr.eval(perm)
            te = _sync()
            stats.time_sort_s += te - tb
            # the records read and those written (both alive during a step), keys, permutation
            peak = max(peak, n_step * (2 * 4 * words + 8 + 8 * len(work)))
        stats.step_times.append(StepTime(n_step, traced - ta, tb - traced, te - tb))
    # entry stacks, ray records, ray in/out arrays
    stats.work_bytes = (peak + n * cap_global * ENTRY_BYTES + n * 4 * RayRecords.STRIDE
                        + n * 4 * 10)
    return res, stats


def _order(m, keys, n_step, n_active: int, buckets: int, finished_key, sort: bool):
    """The next step's permutation: by treelet (a stable counting sort; finished rays last, left
    out), or the rays that go on in their order."""
    if sort:
        perm = dr.detail.block_mkperm(keys, n_step, buckets) if buckets <= (1 << 16) else dr.argsort(keys)
        return dr.gather(m.UInt32, perm, dr.arange(m.UInt32, n_active))
    return dr.compress(keys != finished_key)  # (not ~done: an unevaluated kernel output re-runs it)


def frozen_steps(lay: DeviceLayout, n: int, rows: int) -> bool:
    """Whether a wavefront trace of `n` rays (`rows` entry-stack rows each) on `lay` runs its
    steps frozen (FROZEN_STACK_BYTES, FROZEN_BACKENDS)."""
    backend = dr.backend_v(lay.nodes)
    name = {dr.JitBackend.LLVM: "llvm", dr.JitBackend.CUDA: "cuda"}.get(backend)
    return name in FROZEN_BACKENDS and n * rows * ENTRY_BYTES <= FROZEN_STACK_BYTES


def _state(m, rec, perm, counters, instanced, words, work, first: bool = False) -> RayState:
    """The states of the records `perm` with their work counters (gathered with them; None: the
    first step's, all zero). The first step's (`first`; `rec` then (slots, tmax, ...), `perm` the
    identity) start at the root (RayState.begin)."""
    s = RayState.begin(m, rec[0], rec[1], instanced) if first else StateRecords.read(m, rec, perm, instanced, words)
    for i, f in enumerate(work):
        setattr(s, f, dr.zeros(m.UInt32, dr.width(perm)) if counters is None
                else dr.gather(m.UInt32, counters[i], perm))
    return s


def _tail(m, lay, rays, rec, perm, counters, res, stack, cap, *, instanced, words, work, any_hit, count_work) -> None:
    """The tail: the rays left walk to their end, per ray, from their entry stacks."""
    s = _state(m, rec, perm, counters, instanced, words, work)
    out, done = walk(m, lay, rays, s, stack=stack, cap=cap, bounded=False, any_hit=any_hit, count_work=count_work,
                     results=res)
    res.write(out, done)  # (the work counters: the kernel wrote the hits)


def _step(m, lay, rays, rec, perm, counters, res, stack, spill, rec_out, cap, finished_key, *, instanced, words, work,
          any_hit, count_work, first: bool = False):
    """One wavefront step's kernel: it gathers each ray's state record by the last sort's
    permutation, walks, writes the hits it improved (by slot) as it goes, and at its end, in lane
    order, every lane's sort key, the record of each ray that goes on (into `rec_out`, the step's
    lanes x words) and, above that ray's global stack, the entries it still holds (through
    `spill`; a finished ray writes no record: on paper_mix most rays finish in step 1). Nothing
    else moves between steps but the sort. Returns the records, the keys, the count of rays that
    finished (one word, counted by an atomic in the kernel, not another pass over the keys) and
    the work counters. The first step (`first`) reads no records: it takes its rays' states from
    _state and their origins and directions from the batch's arrays (in slot order, where they
    coalesce), and writes the ray record of each ray that goes on, for the kernels after it."""
    s = _state(m, rec, perm, counters, instanced, words, work, first)
    walked = DirectRays(*SlotRays(m, rec[2:5], rec[5:8]).load(s.slot)) if first else rays
    out, done = walk(m, lay, walked, s, stack=stack, cap=cap, bounded=True, any_hit=any_hit, count_work=count_work,
                     results=res, spill=spill)
    if first:
        rays.write(walked.o, walked.d, s.slot, ~done)
    keys = dr.select(done, finished_key, out.treelet)
    rec_out = StateRecords.write(m, out, ~done, words, into=rec_out)
    n_done_w = dr.zeros(m.UInt32, 1)
    dr.scatter_reduce(dr.ReduceOp.Add, n_done_w, m.UInt32(1), m.UInt32(0), done)
    if count_work:
        res.write(out, done)
    return rec_out, keys, n_done_w, tuple(getattr(out, f) for f in work)


def _frozen_tail(m, lay, rays_rec, rec, perm, counters, res, stack, cap, **kw) -> None:
    """`_tail` with its arrays as dr.freeze traverses them (frozen: _TAIL): the ray records'
    array, Results.fields(), and the EntryStack as a plain tuple (dr.freeze does not look into a
    NamedTuple for its arrays)."""
    _tail(m, lay, RayRecords.over(m, rays_rec), rec, perm, counters, Results.over(res), EntryStack(*stack), cap, **kw)


def _frozen_step(m, lay, rays_rec, rec, perm, counters, res, stack, rec_out, cap, finished_key, **kw):
    """`_step` as _frozen_tail takes its arrays (frozen: _STEP). It spills into the stack itself:
    a frozen function cannot take the alias (see FROZEN_STACK_BYTES). `rec_out` comes from the
    caller because no allocation inside a frozen function may depend on its call's widths
    (drjit 1.5.0's dr.freeze replays it at the recorded size)."""
    stack = EntryStack(*stack)
    return _step(m, lay, RayRecords.over(m, rays_rec), rec, perm, counters, Results.over(res), stack, stack, rec_out,
                 cap, finished_key, **kw)


# drjit warns on stderr once a frozen function has been recorded this often; ours are recorded
# again wherever a batch's shape is new (a render's bounces: measured up to hundreds of times in
# one test), which is expected, not a fault a user could act on.
_NO_WARNING = 1 << 30
# Recorded per tree shape and batch configuration (a few per trace: the first step's widths
# differ from the later ones'); the LRU bound keeps a session over many scenes from holding them all.
def _configuration(m, lay, *args, **kw) -> tuple:
    """What a frozen kernel's code depends on besides its arrays (the plain-Python arguments and
    the layout's shape), as one string: dr.freeze's key (state_fn). drjit 1.5.0's traversal of
    the arguments visits each Python object once by identity, and True, False and small ints are
    shared objects: measured, a call that changed only `any_hit` matched the other query's
    recording and replayed its kernels (wrong closest hits: tests/engine/test_engine_frozen.py).
    A string built here is a new object every call, compared by value."""
    plain = [repr(a) for a in args if isinstance(a, (bool, int, float, str))]
    plain += [repr(a) for a in args if isinstance(a, tuple) and all(isinstance(x, (bool, int, str)) for x in a)]
    return (f"{lay.depth}/{lay.height}/{lay.treelet_count}/{lay.branching}/{lay.far}/{lay.instances is not None}/"
            + "/".join(plain) + "/" + "/".join(f"{k}={v!r}" for k, v in sorted(kw.items())),)


_STEP = dr.freeze(_frozen_step, limit=32, warn_after=_NO_WARNING, state_fn=_configuration)
_TAIL = dr.freeze(_frozen_tail, limit=32, warn_after=_NO_WARNING, state_fn=_configuration)


def _alias(a):
    """A second Dr.Jit array over the memory of the evaluated array `a` (zero-copy). Dr.Jit does
    not know they share it: use it only where a kernel's reads through `a` and writes through the
    alias cannot meet (walk's spill)."""
    return dr.detail.import_tensor(a, False).array


def trace_inline(m, lay: DeviceLayout, o, d, tmax, active, *, any_hit: bool) -> RayState:
    """per_ray traversal of the caller's rays, one per lane, with no host synchronisation, so it
    can run inside the caller's symbolic loop (a bounce loop compiled into one kernel). Rays
    where `active` is False keep prim = MISS. Returns the final state (t, u, v, prim)."""
    n = max(dr.width(x) for x in (*o, *d, tmax, active))
    s = RayState.start(m, dr.zeros(m.Float, n) + m.Float(tmax), count_work=False,  # one tmax per lane
                       instanced=lay.instances is not None)
    out, _ = walk(m, lay, DirectRays(o, d), s, stack=None, cap=local_rows(stack_rows(lay)), bounded=False,
                  any_hit=any_hit, count_work=False, active=active)
    return out
