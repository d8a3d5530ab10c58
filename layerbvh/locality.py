"""The locality model: a traversal's exact memory trace (memtrace) per mode, run through the coalescing and cache
model (memmodel) for a warp width and a hardware preset, checked against the kernel, reduced to one row of numbers."""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

import numpy as np

from . import memsites as ms, memstores as ms_store, memtrace as mt
from .bvh import build
from .inputs import DEFAULT_BRANCHING, DEFAULT_TREELET_HEIGHT
from .cachesim import C_WRITE_MISSES
from .layout import LayerLayout, node_format, treelet_levels
from .locality_verdict import preset_verdict, verdict
from .memmodel import Caches, Preset, preset as named_preset, with_segment
from .state import COMPACT_RECORD_WORDS, MISS, StateRecords
from .steptraffic import limits, result_traffic, sort_traffic
from .tracecheck import TraceCheck, check_trace, same_as
from .walk import SORT_NETWORKS
from .wavefront import MODES, TAIL_FRACTION, TAIL_RAYS, TAIL_STEPS, stack_rows, takes_tail

RAY_RECORD_BYTES = 32       # state.RayRecords: one 32-byte record per ray (the layer modes)
PER_RAY_LOADS = 7           # per_ray reads o, d (six arrays) and tmax by slot: 4 bytes each
REGION_ALIGN = 4096
# The results (state.Results: t, prim, u, v by slot), each an array of its own: store site, region.
RESULT_REGIONS = ((ms.S_RES_T, "results_t"), (ms.S_RES_PRIM, "results_prim"), (ms.S_RES_U, "results_u"),
                  (ms.S_RES_V, "results_v"))


@dataclass
class ReplayResult:
    """One mode's replay under one schedule: per-ray hits and work (for the check against the
    kernel) and the memory model's tallies."""

    mode: str
    warp: int
    preset: Preset
    rays: int                       # rays traced (valid rays of the set)
    prim: np.ndarray                # per ray of the input (MISS: none / not occluded)
    t: np.ndarray                   # float32, inf on a miss
    work: dict                      # per ray: inner_nodes, leaves, triangles, iterations, steps
    branching: int
    tally: np.ndarray               # [site, (transactions, lane requests)]
    levels_hit: np.ndarray          # [site, level]: transactions served by each level (last: DRAM)
    warp_iterations: int
    lane_iterations: int
    kernels: int                    # kernel launches (wavefront steps, the tail)
    sort_bytes: int                 # bytes moved between steps (see sort_traffic)
    ray_steps: int                  # rays summed over the steps (not the tail): what sort_bytes is spread over
    pushed: int                     # entries the rays that went on pushed in the steps (written back)
    seconds: float
    carried: int = 0                # rays summed over the wavefront steps they went on from (a state record each)
    result_bytes: int = 0           # bytes written to the results (steptraffic.result_traffic)
    setup_bytes: int = 0            # bytes the trace call's passes before its first kernel read and write
    loads: dict = None              # per ray and load kind (memtrace.LOAD_KINDS): the loads fed to the cache model
    write_misses: tuple = ()        # per level: the replay's stores (memsites.STORE_SITES) that missed it
    write_back_bytes: int = 0       # dirty lines the last level wrote back into DRAM, in bytes
    tail_steps: int = TAIL_STEPS    # the step cap of the tail rule replayed (wavefront.takes_tail)


def _regions(sizes: dict) -> dict:
    """Byte base of each named array in one address space, each on its own 4 KiB page (arrays
    never share a line, as separate allocations never do)."""
    base, out = 0, {}
    for name, nbytes in sizes.items():
        out[name] = base
        base += -(-max(int(nbytes), 1) // REGION_ALIGN) * REGION_ALIGN + REGION_ALIGN
    return out


def valid_rays(o: np.ndarray, d: np.ndarray, tmax: np.ndarray) -> np.ndarray:
    """inputs.ray_batch's validity: finite origin and direction, nonzero direction, tmax > 0."""
    ok = np.isfinite(o).all(1) & np.isfinite(d).all(1) & (d != 0).any(1)
    return ok & ~np.isnan(tmax) & (tmax > 0)


def replay(lay: LayerLayout, o, d, tmax, mode: str, any_hit: bool, warp: int, preset: Preset,
           tail_rays: int = TAIL_RAYS, tail_fraction: float = TAIL_FRACTION,
           tail_steps: int = TAIL_STEPS, frame_bytes: int = 0) -> ReplayResult:
    """Trace the rays (numpy (N, 3), (N, 3), (N,)) in `mode` as wavefront.trace schedules them,
    with `warp` lanes per warp (packet) on `preset`'s units and caches (and, on a CPU, each packet
    iteration reading and writing a stack frame of `frame_bytes`: memsites.S_FRAME_READ)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    t0 = time.perf_counter()
    o = np.ascontiguousarray(o, np.float32)
    d = np.ascontiguousarray(d, np.float32)
    tmax = np.ascontiguousarray(np.broadcast_to(np.asarray(tmax, np.float32), (len(o),)))
    n_all = len(o)
    valid = valid_rays(o, d, tmax)
    order = np.flatnonzero(valid).astype(np.int64)
    n = len(order)
    nodes_f, nodes_u, tris_f, tris_u, tris_d, tf, nt = ms.layout_views(lay)
    fst = np.zeros((n_all, ms.F_COLS), np.float32)
    ist = np.zeros((n_all, ms.I_COLS), np.int64)
    mt.setup_rays(o, d, fst, ist, tmax)
    layer = mode != "per_ray"
    # Entry stacks as wavefront.trace sizes them: a node pushes at most branching - 1 entries.
    cap_g = stack_rows(lay)
    levels = min(treelet_levels(lay.height, lay.branching), lay.depth)
    cap_local = max(1, (lay.branching - 1) * levels) if layer else cap_g
    cap_max = max(cap_local, cap_g)
    lanes_held = ms.local_stack_rows(preset.units, preset.resident_warps, warp)
    loc_link = np.zeros((lanes_held, cap_max + 1), np.int64)
    loc_t = np.zeros((lanes_held, cap_max + 1), np.float32)
    # Entry stacks in global memory, as wavefront.trace allocates them (only the layer modes have them).
    g_link = np.zeros((n_all if layer else 1, cap_g), np.uint32)
    g_t = np.zeros((n_all if layer else 1, cap_g), np.float32)

    local_words = lanes_held * (cap_max + 1)
    sizes = {"nodes": lay.nodes.nbytes, "tris": lay.tris.nbytes, "treelet_first": lay.treelet_first.nbytes,
             "node_treelet": lay.node_treelet.nbytes, "stack_link": n_all * cap_g * 4, "stack_t": n_all * cap_g * 4,
             "local_link": local_words * 4, "local_t": local_words * 4,
             **{region: n_all * 4 for _, region in RESULT_REGIONS}, "valid": n_all, "idx": n_all * 4}
    # The state record's format, as wavefront.trace picks it (the replay flattens instances).
    record_bytes = 4 * StateRecords.words(False, cap_g, n_all)
    compact = record_bytes == 4 * COMPACT_RECORD_WORDS
    if layer:
        sizes["ray_records"] = n_all * RAY_RECORD_BYTES
        # A step reads its ray's record by slot and its state record where the step before wrote it
        # (state.StateRecords: in that step's lane order), through the sort's permutation; from a
        # compact record, the treelet of a node link (walk._record_treelet).
        sizes["state_records"] = n_all * record_bytes
        # A step writes its keys and records (lane order) into arrays of their own: the records
        # the next step reads are the ones this step wrote (ping-pong, as Dr.Jit's allocator
        # hands the freed array of the step before to the one after).
        sizes["state_records_out"], sizes["keys"] = n_all * record_bytes, n_all * 4
        sizes.update({f"ray_{k}": n_all * 4 for k in range(6)})  # the batch's origins and directions
        sizes["tmax"] = n_all * 4
        start = [("ray_records", RAY_RECORD_BYTES, ms.BY_SLOT), ("state_records", record_bytes, ms.BY_PREVIOUS_LANE)] \
            + ([("node_treelet", 4, ms.BY_LINK_NODE)] if compact else [])
        # The first step reads no records: its kernel starts each ray at the root from its slot (the
        # valid rays' indices, by lane: its "state" load) and its tmax, and reads its origin and
        # direction from the batch's six arrays (by slot, so in order: ray_0 is its "ray" load);
        # it writes the ray record of each ray that goes on (state.RayRecords.write).
        first_start = [("ray_0", 4, ms.BY_SLOT), ("idx", 4, ms.BY_LANE), ("node_treelet", 4, ms.BY_NONE),
                       ("tmax", 4, ms.BY_SLOT)] + [(f"ray_{k}", 4, ms.BY_SLOT) for k in range(1, 6)]
    else:
        # per_ray's kernel reads each lane's slot (the valid rays' indices: its "state" load), then o, d, tmax by slot.
        sizes.update({f"ray_{k}": n_all * 4 for k in range(PER_RAY_LOADS)})
        start = [(f"ray_{k}", 4, ms.BY_SLOT) for k in range(PER_RAY_LOADS)] + [("idx", 4, ms.BY_LANE)]
    # A CPU kernel's stack frames, one per packet slot, last (with none, every region stays where it was).
    sizes.update({"frame": preset.units * preset.resident_warps * frame_bytes} if frame_bytes else {})
    base = _regions(sizes)
    site_base = np.zeros(ms.SITES, np.int64)
    site_bytes = np.ones(ms.SITES, np.int64)
    site_local = np.zeros(ms.SITES, np.bool_)
    for site, region, nbytes, local in (
            (ms.S_TRI, "tris", 64, False), (ms.S_LOC_R_LINK, "local_link", 4, True),
            (ms.S_LOC_R_T, "local_t", 4, True), (ms.S_STACK_LINK, "stack_link", 4, False),
            (ms.S_STACK_T, "stack_t", 4, False), (ms.S_NODE_TRELET, "node_treelet", 4, False),
            (ms.S_TF, "treelet_first", 4, False), (ms.S_NODE, "nodes", node_format(lay.branching).bytes, False),
            (ms.S_LOC_W_LINK, "local_link", 4, True), (ms.S_LOC_W_T, "local_t", 4, True)):
        site_base[site], site_bytes[site], site_local[site] = base[region], nbytes, local
    site_base[ms.S_FRAME_READ], site_bytes[ms.S_FRAME_READ] = base.get("frame", 0), frame_bytes
    for j in range(1, ms.MAX_PUSH):  # a wide node's further pushes (local, like the first)
        for site, region in zip((ms.S_PUSH + 2 * (j - 1), ms.S_PUSH + 2 * (j - 1) + 1), ("local_link", "local_t")):
            site_base[site], site_bytes[site], site_local[site] = base[region], 4, True

    def use(starts):
        """The start loads of the next launches (StartLoads): their sites' regions, and (sites, by)."""
        for k, (region, nbytes, _) in enumerate(starts):
            site_base[ms.S_START + k], site_bytes[ms.S_START + k] = base[region], nbytes
        return np.arange(len(starts), dtype=np.int64), np.array([by for _, _, by in starts], np.int64)

    later = use(start)
    first = use(first_start) if layer else later
    outputs = RESULT_REGIONS
    if layer:
        outputs = [*outputs, (ms.S_KEY_OUT, "keys"), (ms.S_SPILL_LINK, "stack_link"), (ms.S_SPILL_T, "stack_t")]
    for site, region in outputs:
        site_base[site], site_bytes[site] = base[region], 4
    if layer:
        site_base[ms.S_STATE_OUT], site_bytes[ms.S_STATE_OUT] = base["state_records_out"], record_bytes
        site_base[ms.S_RAY_OUT], site_bytes[ms.S_RAY_OUT] = base["ray_records"], RAY_RECORD_BYTES
    prev_pos = np.zeros(n_all, np.int64)

    caches = Caches(preset)
    tags, stamps, dirty, params, counts, clock = caches.arrays
    n_levels = len(preset.levels)
    tally = np.zeros((ms.SITES, 2), np.int64)
    levels_hit = np.zeros((ms.SITES, n_levels + 1), np.int64)
    lanes = np.zeros(4, np.int64)
    loads = np.zeros((n_all, ms.SITES), np.int32)
    views = (nodes_f, nodes_u, tris_f, tris_u, tris_d, tf, nt)
    state = (fst, ist, loc_link, loc_t, g_link, g_t)
    model = (tags, stamps, dirty, params, counts, clock, tally, levels_hit, lanes, loads)
    net = np.array(SORT_NETWORKS.get(lay.branching, ()), np.int64).reshape(-1, 2)

    def launch(rays, bounded, use_global, cap, starts):
        if preset.flush_private_each_kernel:
            caches.flush_private()
        mt.run_kernel(rays, warp, preset.units, preset.resident_warps, preset.block_warps, bounded, use_global, cap,
                      any_hit, cap_g, lay.branching, net, *views, *state, site_base, site_bytes, site_local, *starts,
                      prev_pos, preset.segment_bytes, *model)

    # The trace call's passes before its first kernel (wavefront.trace; Dr.Jit launches each as a
    # kernel, a memset or a compaction): the valid rays' indices; the results filled. (The layer
    # modes' ray records are written by their first step, for the rays that go on: PERFORMANCE.md
    # entry 63; before it, a pass packed every ray's.)
    passes = [("valid", n_all, False), ("idx", 4 * n, True)]
    passes += [(region, 4 * n_all, True) for _, region in RESULT_REGIONS]
    passes = passes if n else []
    for region, nbytes, write in passes:
        ms_store.setup_pass(ms.S_SETUP_STORE if write else ms.S_SETUP_LOAD, base[region], nbytes, write,
                            preset.segment_bytes, 0, tags, stamps, dirty, params, counts, clock, tally, levels_hit)
    kernels, sort_bytes, ray_steps, carried = 0, 0, 0, 0
    if n and not layer:
        launch(order, ms.WHOLE, False, cap_g, later)
        kernels = 1
    elif n:
        sort = mode == "layer_sorted"
        finished = lay.treelet_count
        n0 = n_active = n
        while n_active > 0:
            if takes_tail(n_active, n0, kernels, tail_rays, tail_fraction, tail_steps):
                launch(order, ms.WHOLE, True, cap_g, later)
                kernels += 1
                break
            before = lanes.copy()
            launch(order, ms.FIRST_STEP if kernels == 0 else ms.STEP, True, cap_local, first if kernels == 0 else later)
            if kernels == 0:  # (later steps read the records a step wrote: ping-pong from here)
                use(start)
            kernels += 1
            ray_steps += n_active
            pushed = int(lanes[2] - before[2])
            keys = mt.next_treelets(order, ist, finished)
            prev_pos[order] = np.arange(len(order))  # (each ray's record, where this step wrote it)
            state_in = ms.S_START + 1
            site_base[state_in], site_base[ms.S_STATE_OUT] = site_base[ms.S_STATE_OUT], site_base[state_in]
            done = int(np.count_nonzero(keys == finished))
            last = done == n_active
            sort_bytes += sort_traffic(n_active, pushed, done, sort, last, record_bytes,
                                       RAY_RECORD_BYTES if kernels == 1 else 0)
            carried += n_active - done
            if last:
                break
            # block_mkperm is a stable counting sort; finished rays go last and are dropped.
            keep = np.argsort(keys, kind="stable")[:n_active - done] if sort else np.flatnonzero(keys != finished)
            order = order[keep]
            n_active -= done

    # Every transaction reached L1 once: a cache_access that refused its input (-1) would not count.
    assert counts[0, :2].sum() == tally[:, 0].sum() == levels_hit.sum(), "the cache model lost transactions"
    prim = np.full(n_all, MISS, np.int64)
    t = np.full(n_all, np.inf, np.float32)
    prim[valid] = ist[valid, ms.I_PRIM]
    hit = prim != MISS
    t[hit] = fst[hit, ms.F_T]
    work = {name: np.where(valid, ist[:, col], 0) for name, col in (
        ("inner_nodes", ms.I_INNER), ("leaves", ms.I_LEAF), ("triangles", ms.I_TRI), ("iterations", ms.I_ITER),
        ("steps", ms.I_STEPS), ("entries_written", ms.I_SPILL), ("hits_written", ms.I_HITW))}
    kinds = {kind: sites for kind, (sites, _) in ms.LOAD_KINDS.items()}
    kinds["ray"] = tuple(ms.S_START + k for k in ((0,) if layer else range(PER_RAY_LOADS)))
    kinds["state"] = (ms.S_START + (1 if layer else PER_RAY_LOADS),)
    per_kind = {kind: [loads[:, k] for k in sites] for kind, sites in kinds.items() if sites}
    # (a kind's sites are loaded together, so each counts its loads once; replay() checks they agree)
    assert all((c == cs[0]).all() for cs in per_kind.values() for c in cs), "a load kind's sites disagree"
    per_ray_loads = {kind: cs[0] for kind, cs in per_kind.items()}  # (+ a step's lookup, as the kernel counts:)
    lookups = loads[:, ms.S_START + 2] if layer and compact else 0
    per_ray_loads["node_treelet"] = per_ray_loads["node_treelet"] + lookups
    return ReplayResult(mode=mode, warp=warp, preset=preset, rays=n, prim=prim, t=t, work=work,
                        loads={kind: np.where(valid, c, 0) for kind, c in per_ray_loads.items()},
                        branching=lay.branching, tally=tally,
                        levels_hit=levels_hit, warp_iterations=int(lanes[0]), lane_iterations=int(lanes[1]),
                        kernels=kernels, sort_bytes=sort_bytes, ray_steps=ray_steps, tail_steps=tail_steps,
                        pushed=int(lanes[2]), carried=carried, seconds=time.perf_counter() - t0,
                        result_bytes=result_traffic(not layer, n, int(work["hits_written"].sum())),
                        setup_bytes=sum(nbytes for _, nbytes, _ in passes),
                        write_misses=tuple(int(x) for x in counts[:-1, C_WRITE_MISSES]),
                        write_back_bytes=caches.dram_write_bytes())


# -- one row of numbers ------------------------------------------------------------------------------
@dataclass
class LocalityRow:
    """What one kind of rays costs in one mode, warp width and preset, per ray (docs/guide.md,
    locality: 'What the numbers mean'). Transactions and cache figures are of the traversal kernels'
    loads; sort_bytes_per_ray is what the layer modes move between steps (0 for per_ray)."""

    kind: str
    mode: str
    warp: int
    preset: str
    treelet_height: int
    rays: int
    inner_per_ray: float
    leaves_per_ray: float
    tris_per_ray: float
    iterations_per_ray: float
    kernels: int
    transactions_per_ray: float
    node_transactions_per_ray: float
    triangle_transactions_per_ray: float
    stack_transactions_per_ray: float
    local_transactions_per_ray: float
    ray_transactions_per_ray: float
    requests_per_transaction: float     # lane loads served per transaction (1 = none coalesced)
    simd_efficiency: float
    l1_hit_rate: float
    l2_hit_rate: float
    l3_hit_rate: float | None
    l2_bytes_per_ray: float             # bytes into L1 from below (L1 misses x L1 line)
    dram_bytes_per_ray: float           # bytes from DRAM (last level's misses x its line)
    node_dram_bytes_per_ray: float
    triangle_dram_bytes_per_ray: float
    sort_bytes_per_ray: float
    total_dram_bytes_per_ray: float     # dram + sort + result + set-up: what the mode costs the memory bus
    branching: int = 2                  # children per node of the replayed tree
    result_bytes_per_ray: float = 0.0   # hits written to the results (steptraffic.result_traffic)
    steps_per_ray: float = 0.0          # kernel calls a ray took part in (wavefront steps and the tail)
    # wavefront steps after which the tail finishes the rays left; rows of documents written before
    # it was recorded (PERFORMANCE.md entry 61) were replayed with the cap of then, 32
    tail_steps: int = 32
    sort_bytes_per_ray_step: float = 0.0  # sort_bytes over the rays of every wavefront step
    pushed_per_ray_step: float = 0.0    # entries pushed and written back, per ray and wavefront step
    carried_per_ray_step: float = 0.0   # the share of a step's rays that go on (write a state record)
    # The limits of a step design on layer rows (steptraffic.limits; None on per_ray rows).
    break_even_bytes_per_ray_step: float | None = None
    lower_bound_bytes_per_ray_step: float | None = None
    sampled_from: int | None = None     # rays the kind had before sampling (None: not sampled)
    seconds: float = 0.0
    trace_exact: bool | None = None     # the trace matched the kernel on every ray (None: not checked)
    l1_write_misses_per_ray: float = 0.0  # the replay's stores (memsites.STORE_SITES) that missed L1
    write_back_bytes_per_ray: float = 0.0  # dirty lines written back into DRAM (the stores' bytes: counted in the
    #                                        between-step and result bytes, so not again in total_dram_bytes_per_ray)
    preset_params: dict = field(default_factory=dict)
    # The trace call's passes before its first kernel, each byte read or written once (streams: the
    # valid rays' compaction, in the layer modes the ray records' packing, the results' fill). None:
    # a row of a document written before PERFORMANCE.md entry 62, whose total left them out.
    setup_bytes_per_ray: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def replay_tree(bvh, o, d, tmax, mode: str, any_hit: bool, warp: int, preset: Preset, frame_bytes=0) -> ReplayResult:
    """`replay` over a LayerBVH's layout with its own tail rule (tail_rays, tail_fraction,
    tail_steps): the schedule its kernels run."""
    return replay(bvh.layout, o, d, tmax, mode, any_hit, warp, preset, bvh.tail_rays, bvh.tail_fraction,
                  bvh.tail_steps, frame_bytes)


def row(kind: str, rep: ReplayResult, treelet_height: int, sampled_from: int | None = None,
        check: TraceCheck | None = None) -> LocalityRow:
    """The row of one replay: its transactions, hit rates and DRAM bytes are the traversal's (the
    sites before memsites.S_END); what the kernels write out is in the between-step and result
    bytes (steptraffic), its stores' misses in the cache state and l1_write_misses_per_ray."""
    n = max(rep.rays, 1)
    levels = rep.preset.levels
    traversal = range(ms.S_END)
    tx = rep.tally[:ms.S_END, 0]
    lh = rep.levels_hit[:ms.S_END]
    total = int(tx.sum())

    def per_ray(sites):
        return float(tx[list(sites)].sum()) / n

    def rate(k):  # hits at level k over the transactions that reached it
        reached = int(lh[:, k:].sum())
        return float(lh[:, k].sum()) / reached if reached else 0.0

    def dram(sites):
        return float(lh[list(sites), -1].sum()) * levels[-1].line_bytes / n
    start_sites = range(ms.S_START, ms.S_END)
    return LocalityRow(
        kind=kind, mode=rep.mode, warp=rep.warp, preset=rep.preset.name, treelet_height=treelet_height, rays=rep.rays,
        inner_per_ray=rep.work["inner_nodes"].sum() / n, leaves_per_ray=rep.work["leaves"].sum() / n,
        tris_per_ray=rep.work["triangles"].sum() / n, iterations_per_ray=rep.work["iterations"].sum() / n,
        kernels=rep.kernels, transactions_per_ray=total / n,
        node_transactions_per_ray=per_ray(ms.CATEGORY["node"]),
        triangle_transactions_per_ray=per_ray(ms.CATEGORY["triangle"]),
        stack_transactions_per_ray=per_ray(ms.CATEGORY["stack"]),
        local_transactions_per_ray=per_ray(ms.CATEGORY["local"]),
        ray_transactions_per_ray=per_ray(start_sites),
        requests_per_transaction=float(rep.tally[:ms.S_END, 1].sum()) / total if total else 0.0,
        simd_efficiency=rep.lane_iterations / (rep.warp_iterations * rep.warp) if rep.warp_iterations else 0.0,
        l1_hit_rate=rate(0), l2_hit_rate=rate(1) if len(levels) > 1 else 0.0,
        l3_hit_rate=rate(2) if len(levels) > 2 else None,
        l2_bytes_per_ray=float(total - lh[:, 0].sum()) * levels[0].line_bytes / n,
        dram_bytes_per_ray=dram(traversal),
        node_dram_bytes_per_ray=dram(ms.CATEGORY["node"]), triangle_dram_bytes_per_ray=dram(ms.CATEGORY["triangle"]),
        sort_bytes_per_ray=rep.sort_bytes / n,
        total_dram_bytes_per_ray=dram(traversal) + (rep.sort_bytes + rep.result_bytes + rep.setup_bytes) / n,
        setup_bytes_per_ray=rep.setup_bytes / n,
        branching=rep.branching, result_bytes_per_ray=rep.result_bytes / n,
        steps_per_ray=float(rep.work["steps"].sum()) / n, tail_steps=rep.tail_steps,
        sort_bytes_per_ray_step=rep.sort_bytes / rep.ray_steps if rep.ray_steps else 0.0,
        pushed_per_ray_step=rep.pushed / rep.ray_steps if rep.ray_steps else 0.0,
        carried_per_ray_step=rep.carried / rep.ray_steps if rep.ray_steps else 0.0,
        sampled_from=sampled_from, seconds=rep.seconds, trace_exact=None if check is None else check.exact,
        preset_params=rep.preset.as_dict(),
        l1_write_misses_per_ray=rep.write_misses[0] / n if rep.write_misses else 0.0,
        write_back_bytes_per_ray=rep.write_back_bytes / n)


def sample_rays(o, d, tmax, limit: int | None, seed: int = 0):
    """At most `limit` of the rays, drawn uniformly without replacement and kept in their
    original order (the order is part of the schedule); (o, d, tmax, rays before sampling or None)."""
    n = len(o)
    if limit is None or n <= limit:
        return o, d, tmax, None
    keep = np.sort(np.random.default_rng(seed).choice(n, limit, replace=False))
    return o[keep], d[keep], np.asarray(tmax)[keep], n


@dataclass(frozen=True)
class LocalitySettings:
    """What `measure` runs: every mode x warp width x preset x treelet height on each kind of rays."""

    modes: tuple = MODES
    warps: tuple | None = None      # None: each preset's own width (its `warp`)
    presets: tuple = ("gtx965m", "h200", "cpu")
    treelet_heights: tuple = (DEFAULT_TREELET_HEIGHT,)
    sample: int | None = None       # at most this many rays per kind (uniform; None: all)
    seed: int = 0
    check: bool = True              # compare each mode's trace with the kernel (once per kind, height)
    threads: int | None = None      # replays run at once (numba releases the GIL); None: the CPU count
    segments: tuple | None = None   # transaction sizes in bytes (memmodel.with_segment); None: each preset's own
    branching: int = DEFAULT_BRANCHING  # children per node of the tree replayed (a render's default)
    tail_steps: int = TAIL_STEPS    # the layer modes' step cap: after this many steps the tail finishes the rays


@dataclass
class RaySet:
    """One kind of rays to replay: numpy origins (N, 3), directions (N, 3), tmax (N,), and whether
    they are any-hit queries (shadow rays)."""

    kind: str
    o: np.ndarray
    d: np.ndarray
    tmax: np.ndarray
    any_hit: bool = False


@dataclass
class LocalityRun:
    """What `measure` gives: the rows, the trace checks and the build of each treelet height."""

    rows: list
    checks: list                     # TraceCheck per (kind, height, mode), as dicts with kind and height
    bvh: dict                        # treelet height -> BVHStats as a dict
    seconds: float

    def as_dict(self) -> dict:
        return {"results": [r.as_dict() for r in self.rows], "checks": self.checks, "bvh": self.bvh,
                "verdict": verdict(self.rows), "preset_verdict": preset_verdict(self.rows), "seconds": self.seconds}


def measure(vertices, faces, ray_sets: list[RaySet], settings: LocalitySettings, leaf_size: int | None,
            backend: str = "llvm", progress=None) -> LocalityRun:
    """Every kind x treelet height x mode x warp x preset of `settings`, each replayed once; each
    mode's trace checked against the kernel once per kind and height (settings.check).
    `progress(done, total, label)` is called after each replay."""
    t0 = time.perf_counter()
    presets = [with_segment(named_preset(p), seg) if seg else named_preset(p)
               for p in settings.presets for seg in (settings.segments or (None,))]
    sets = []
    for rs in ray_sets:
        o, d, tmax, before = sample_rays(rs.o, rs.d, rs.tmax, settings.sample, settings.seed)
        sets.append((rs, o, d, tmax, before))
    widths = [(pre, w) for pre in presets for w in (settings.warps or (pre.warp,))]
    total = len(sets) * len(settings.treelet_heights) * len(settings.modes) * len(widths)
    rows, checks, bvh_stats, done = [], [], {}, 0
    for h in settings.treelet_heights:
        most = max([len(s[1]) for s in sets] + [1])
        bvh = build(vertices, faces, treelet_height=h, leaf_size=leaf_size, backend=backend, batch_rays=most,
                    branching=settings.branching, tail_steps=settings.tail_steps)
        bvh_stats[h] = asdict(bvh.stats)
        for rs, o, d, tmax, before in sets:
            configs = [(mode, pre, warp) for mode in settings.modes for pre, warp in widths]

            def one(config, rs=rs, o=o, d=d, tmax=tmax):
                mode, pre, warp = config
                return replay_tree(bvh, o, d, tmax, mode, rs.any_hit, warp, pre)
            with ThreadPoolExecutor(max_workers=settings.threads or os.cpu_count() or 1) as pool:
                reps = []
                for config, rep in zip(configs, pool.map(one, configs)):
                    reps.append(rep)
                    done += 1
                    if progress is not None:
                        progress(done, total, f"{rs.kind} h={h} {config[0]} W={config[2]} {config[1].name}")
            checked, check = {}, None
            for rep in reps:  # the kernel traces each mode once; every other schedule of that mode
                # must give the same hits and work per ray (a lane's state leaking into another would not)
                if settings.check and rep.mode not in checked:
                    checked[rep.mode] = (check_trace(bvh, o, d, tmax, rs.any_hit, rep), rep)
                    check = checked[rep.mode][0]
                    checks.append({"kind": rs.kind, "treelet_height": h, **asdict(check), "exact": check.exact})
                elif settings.check:
                    check = same_as(rep, *checked[rep.mode])
                    if not check.exact:
                        checks.append({"kind": rs.kind, "treelet_height": h, **asdict(check), "exact": False,
                                       "schedule": f"W={rep.warp} {rep.preset.name}"})
                rows.append(row(rs.kind, rep, h, before, check if settings.check else None))
    limits(rows)
    return LocalityRun(rows=rows, checks=checks, bvh=bvh_stats, seconds=time.perf_counter() - t0)
