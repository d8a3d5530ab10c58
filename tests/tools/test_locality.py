"""The locality model: the replayed trace against the kernel, transactions on a hand-built case, and where sorting
must and cannot cut transactions."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import layerbvh
from layerbvh import locality as L
from layerbvh import memsites as ms
from layerbvh.memmodel import CacheLevel, Preset, preset
from layerbvh import meshes
from layerbvh_mitsuba.repo import SCENES

N_RAYS = 6000


def _rays(v, kind, n=N_RAYS, seed=5):
    o, d = meshes.camera_rays(v, n, seed) if kind == "camera" else meshes.incoherent_rays(v, n, seed)
    return o, d, np.full(n, np.inf, np.float32)


def test_the_replay_follows_the_kernels_step_cap(procedural):
    """tail_steps = 2, not the default (two sorted steps, then the tail; the rays-left rule off): the
    replay takes the kernel's schedule, so every ray's hit, work counts (its three kernel calls
    included) and loads equal the kernel's."""
    v, f = procedural
    o, d, tmax = _rays(v, "incoherent")
    bvh = layerbvh.build(v, f, branching=4, treelet_height=4, batch_rays=len(o), tail_rays=0, tail_fraction=1e-6,
                         tail_steps=2)
    rep = L.replay_tree(bvh, o, d, tmax, "layer_sorted", False, 32, preset("gtx965m"))
    chk = L.check_trace(bvh, o, d, tmax, False, rep)
    assert chk.exact, (chk.hit_mismatches, chk.work_mismatches, chk.load_mismatches)
    assert rep.kernels == 3 and rep.tail_steps == 2 and rep.work["steps"].max() == 3
    assert L.row("incoherent", rep, 4).tail_steps == 2


def test_first_step_reads_no_state_record(procedural):
    """The first wavefront step starts each ray at the root from its slot and tmax (issue 57 item 2)
    and reads its origin and direction from the batch's arrays: in the replay the set-up writes
    the valid rays' indices and the results' fill, no state records and no ray records (each pass
    one transaction per segment, regions page-aligned); each ray reads its tmax and its six
    components once, in the first step, which writes the ray record of every ray that goes on (by
    slot, for the kernels after it: PERFORMANCE.md entry 63); the kernel agrees ray by ray (hits
    with a finite tmax, and loads: no treelet lookup for the root). The set-up's bytes (each read
    and write once) are in every mode's total: the compaction and the fill, 21 B a ray."""
    v, f = procedural
    o, d, _ = _rays(v, "incoherent")
    n = len(o)
    tmax = np.random.default_rng(3).uniform(0.0, 1.0, n).astype(np.float32) * np.ptp(v, 0).max()
    bvh = layerbvh.build(v, f, branching=4, treelet_height=4, batch_rays=n, tail_rays=0, tail_fraction=1e-6,
                         tail_steps=2)
    seg, got = preset("gtx965m").segment_bytes, {}
    for mode in ("layer_sorted", "layer_unsorted"):
        rep = L.replay_tree(bvh, o, d, tmax, mode, False, 32, preset("gtx965m"))
        chk = L.check_trace(bvh, o, d, tmax, False, rep)
        assert chk.exact, (mode, chk.hit_mismatches, chk.work_mismatches, chk.load_mismatches)
        assert 0 < (rep.prim != layerbvh.MISS).mean() < 0.9, "tmax should stop some rays short"
        passes = [4 * n] + [4 * n] * len(L.RESULT_REGIONS)
        assert rep.tally[ms.S_SETUP_STORE, 0] == sum(-(-b // seg) for b in passes)
        req = rep.tally[:, 1]
        assert req[ms.S_START + 3] == rep.rays == n and all(req[ms.S_START + k] == n for k in range(4, 9))
        went_on = int(np.count_nonzero(rep.work["steps"] >= 2))
        assert 0 < went_on < n and req[ms.S_RAY_OUT] == went_on
        assert rep.kernels == 3
        assert rep.setup_bytes == (1 + 4 + 16) * n
        r = L.row("incoherent", rep, 4)
        parts = r.dram_bytes_per_ray + r.sort_bytes_per_ray + r.result_bytes_per_ray + r.setup_bytes_per_ray
        assert r.setup_bytes_per_ray == 21 and r.total_dram_bytes_per_ray == pytest.approx(parts, rel=1e-12)
        got[mode] = r
    per_rep = L.replay_tree(bvh, o, d, tmax, "per_ray", False, 32, preset("gtx965m"))
    # per_ray's kernel reads each lane's slot too (the valid rays' indices): one load a ray, as the first step's.
    assert per_rep.tally[ms.S_START + L.PER_RAY_LOADS, 1] == n and per_rep.loads["state"].sum() == n
    per = L.row("incoherent", per_rep, 4)
    assert per.setup_bytes_per_ray == 21
    (sentence,) = L.verdict([per, got["layer_sorted"]])  # (the total it states counts the set-up, and says so)
    assert "moved between steps, the hits written and the set-up's passes (21 B/ray against per_ray's 21)" in sentence


@pytest.mark.parametrize("mesh_name", ["bunny", "procedural"])
@pytest.mark.parametrize("kind", ["camera", "incoherent"])
@pytest.mark.parametrize("any_hit", [False, True], ids=["closest", "any"])
def test_trace_follows_the_kernel(request, mesh_name, kind, any_hit):
    """Per ray, the replay's hit (prim, t bits), work counts (inner nodes, leaves, triangles,
    iterations, kernel calls) and loads of each kind (node records, triangles, entry-stack entries,
    node-treelet lookups, exit roots, ray and state records: what it fed to the cache model) equal
    what the kernel returned and counted, in every mode; the layer modes run many wavefront steps
    (treelet height 3) and the per-ray tail."""
    v, f = request.getfixturevalue(mesh_name)
    o, d, tmax = _rays(v, kind)
    if any_hit:  # shadow-like: finite tmax, some rays stop short of the mesh
        tmax = np.random.default_rng(1).uniform(0.0, 2.0, len(o)).astype(np.float32) * np.ptp(v, 0).max()
    bvh = layerbvh.build(v, f, branching=2, treelet_height=3, batch_rays=len(o), tail_rays=256, tail_fraction=0.05,
                         tail_steps=32)  # (many steps before the tail)
    for mode in layerbvh.MODES:
        rep = L.replay_tree(bvh, o, d, tmax, mode, any_hit, 32, preset("gtx965m"))
        chk = L.check_trace(bvh, o, d, tmax, any_hit, rep)
        assert chk.exact, (f"{mode}: {chk.hit_mismatches} hits, {chk.work_mismatches} work counts and "
                           f"{chk.load_mismatches} loads differ")
        if mode != "per_ray":  # (the check covers the loads and stores the layer steps make)
            assert all(rep.loads[k].sum() > 0 for k in ("stack", "node_treelet", "exit_root", "state")), rep.loads
            assert rep.work["entries_written"].sum() > 0 and rep.work["hits_written"].sum() > 0
        assert (rep.prim != layerbvh.MISS).mean() > (0.05 if any_hit else 0.2), "test rays should hit"
        if mode != "per_ray":
            assert rep.kernels > (1 if any_hit else 3), f"{mode} ran {rep.kernels} kernels: no wavefront steps"
        # The model's own accounting: every transaction was served by exactly one level.
        assert rep.levels_hit.sum() == rep.tally[:, 0].sum()
        # The kernels' stores as lanes end (memstores): per_ray every ray's hit by slot; a step's
        # sort key per lane, a state record per ray it carries on, the entries those still hold.
        req = rep.tally[:, 1]
        if mode == "per_ray":
            assert req[ms.S_RES_T] == rep.rays and req[ms.S_KEY_OUT:ms.S_SETUP_LOAD].sum() == 0
        else:
            assert req[ms.S_KEY_OUT] == rep.ray_steps and req[ms.S_STATE_OUT] == rep.carried > 0
            assert req[ms.S_SPILL_LINK] == req[ms.S_SPILL_T] == rep.pushed


@pytest.mark.parametrize("branching", [4, 8])
def test_trace_follows_the_kernel_on_wide_trees(bunny, branching):
    """The same per-ray check on the wide trees (4 is what a render gets): a node's children
    sorted by entry distance, K - 1 pushes, records of the wide format; closest and any hit."""
    v, f = bunny
    o, d, tmax = _rays(v, "incoherent")
    bvh = layerbvh.build(v, f, branching=branching, treelet_height=3, batch_rays=len(o), tail_rays=256,
                         tail_fraction=0.05, tail_steps=32)
    short = np.random.default_rng(1).uniform(0.0, 2.0, len(o)).astype(np.float32) * np.ptp(v, 0).max()
    for any_hit, t in ((False, tmax), (True, short)):
        for mode in layerbvh.MODES:
            rep = L.replay_tree(bvh, o, d, t, mode, any_hit, 32, preset("gtx965m"))
            chk = L.check_trace(bvh, o, d, t, any_hit, rep)
            assert chk.exact, (f"K={branching} {mode}: {chk.hit_mismatches} hits, {chk.work_mismatches} work counts "
                               f"and {chk.load_mismatches} loads differ")
            assert rep.branching == branching and (rep.prim != layerbvh.MISS).mean() > 0.05
            if mode != "per_ray":
                assert rep.kernels > 3 and rep.pushed > 0
                # every push j of a wide node writes its own local sites: the farthest ones too
                far = ms.S_PUSH + 2 * (branching - 3)
                assert rep.tally[far, 1] > 0 and rep.tally[far + 2:ms.S_START, 1].sum() == 0

@pytest.mark.parametrize("mode", ["layer_sorted", "layer_unsorted"])
def test_between_step_bytes_are_what_the_kernel_stored(bunny, mode):
    """The replay's between-step bytes (steptraffic.sort_traffic) and results' bytes from what the
    kernel itself reports: the rays of each step (stats.active_per_step), and per ray the held
    entries it wrote above its global stack and the closer hits it wrote by slot (its store
    counters). Per step: every lane's 4-byte key, a state record per ray that goes on (the bunny's
    tree takes the compact 16-byte one: state.StateRecords), and in the first step its 32-byte ray
    record (state.RayRecords.write); between steps the sort (keys read,
    permutation written; compaction: keys read, survivors written) and the permutation read by
    the next step; 8 bytes per entry. Results: 16 bytes per hit written (per_ray: per ray). No
    tail: every ray finishes in the steps, so every entry counted is a step's."""
    v, f = bunny
    o, d, tmax = _rays(v, "incoherent")
    bvh = layerbvh.build(v, f, branching=4, treelet_height=3, batch_rays=len(o), tail_rays=0, tail_fraction=0)
    h = bvh.trace(o, d, tmax, mode=mode, stats=True)
    n = h.stats.active_per_step
    assert len(n) > 3 and h.stats.tail_rays == 0
    want = 8 * int(np.sum(h.work["entries_written"]))
    for s, n_s in enumerate(n):
        left = n[s + 1] if s + 1 < len(n) else 0
        want += 4 * n_s + (16 + (32 if s == 0 else 0)) * left
        if left:
            want += (8 * n_s if mode == "layer_sorted" else 4 * n_s + 4 * left) + 4 * left
    rep = L.replay_tree(bvh, o, d, tmax, mode, False, 32, preset("gtx965m"))
    assert int(np.sum(h.work["entries_written"])) > len(o) // 4
    assert rep.sort_bytes == want
    assert rep.result_bytes == 16 * int(np.sum(h.work["hits_written"])) > 0
    per = L.replay_tree(bvh, o, d, tmax, "per_ray", False, 32, preset("gtx965m"))
    assert per.sort_bytes == 0 and per.result_bytes == 16 * len(o)


def _two_triangles():
    """Two triangles far apart (x < 0 and x > 0) in the plane z = 0, each its own leaf."""
    v = np.array([[-2, -1, 0], [-1, -1, 0], [-1.5, 1, 0], [1, -1, 0], [2, -1, 0], [1.5, 1, 0]], np.float32)
    return v, np.array([[0, 1, 2], [3, 4, 5]], np.int64)


def test_two_warps_transactions_by_hand():
    """Two warps of 4 lanes on one unit, one at a time, fully associative caches: warp 0's rays
    hit triangle A, warp 1's triangle B, so each lane reads the root (iteration 1) and its triangle
    (iteration 2). Counted by hand per warp: 7 ray loads (o, d, tmax: 16 consecutive bytes, one
    32-byte sector each), its lanes' slots (the valid rays' indices: one sector, which the set-up
    wrote, so in L1), the root record (64 bytes: 2 sectors), the triangle record (2), and the
    local entry stack's read and write (link and t) in both iterations (4 lanes x 4 bytes: one
    sector each; 8). Warp 1 finds its rays, the root and the local stack in L1."""
    v, f = _two_triangles()
    bvh = layerbvh.build(v, f, branching=2, treelet_height=8, leaf_size=1, batch_rays=8)
    x = np.array([-1.6, -1.5, -1.4, -1.5, 1.4, 1.5, 1.6, 1.5], np.float32)
    o = np.stack([x, np.zeros(8, np.float32), np.ones(8, np.float32)], 1)
    d = np.tile(np.array([[0, 0, -1]], np.float32), (8, 1))
    tmax = np.full(8, np.inf, np.float32)
    hand = Preset(name="hand", description="one unit, one warp at a time", kind="gpu", units=1, resident_warps=1,
                  block_warps=1, warp=4, segment_bytes=32,
                  levels=(CacheLevel("L1", 1024, 32, 32, shared=False), CacheLevel("L2", 4096, 128, 32, shared=True)),
                  flush_private_each_kernel=False, source="test")
    rep = L.replay(bvh.layout, o, d, tmax, "per_ray", False, 4, hand)
    assert L.check_trace(bvh, o, d, tmax, False, rep).exact
    assert (rep.prim[:4] == rep.prim[0]).all() and (rep.prim[4:] == rep.prim[4]).all() and rep.prim[0] != rep.prim[4]
    tx = rep.tally[:, 0]
    assert tx[ms.S_NODE] == 4 and tx[ms.S_TRI] == 4
    assert sum(tx[s] for s in ms.CATEGORY["local"]) == 16
    assert tx[ms.S_START:ms.S_END].sum() == 16 and list(rep.levels_hit[ms.S_START + L.PER_RAY_LOADS]) == [2, 0, 0]
    assert tx[:ms.S_END].sum() == 40
    assert rep.warp_iterations == 4 and rep.lane_iterations == 16
    # Warp 0 brings in 13 sectors (7 ray, 2 node, 2 local, 2 triangle) and re-reads the local ones
    # (6 L1 hits, and its slots: 7); warp 1 misses only on triangle B (2) and hits the other 18.
    lh = rep.levels_hit[:ms.S_END]
    assert lh[:, 0].sum() == 25 and lh[:, 1].sum() == 0 and lh[:, 2].sum() == 15
    # Before the kernel, the trace call reads the valid mask (8 bytes: one sector) and writes the
    # valid rays' indices (32 bytes: one) and fills the four result arrays (one sector each): six
    # set-up transactions, every one a miss in both levels (its stores write misses). As its rays
    # end, each warp stores their hits by slot (t, prim, u, v: 4 lanes x 4 bytes, one sector of
    # each array; both warps' slots share it), all in L1 since the fill. The local stack's stores
    # hit too (its pops read them in).
    assert (tx[ms.S_SETUP_LOAD], tx[ms.S_SETUP_STORE]) == (1, 5)
    assert list(rep.levels_hit[[ms.S_SETUP_LOAD, ms.S_SETUP_STORE]].sum(axis=0)) == [0, 0, 6]
    results = [ms.S_RES_T, ms.S_RES_PRIM, ms.S_RES_U, ms.S_RES_V]
    assert list(tx[results]) == [2, 2, 2, 2] and tx[ms.S_END:ms.S_SETUP_LOAD].sum() == 8
    assert list(rep.levels_hit[results].sum(axis=0)) == [8, 0, 0] and rep.write_misses == (5, 5)
    r = L.row("hand", rep, 8)
    assert r.simd_efficiency == 1.0 and r.transactions_per_ray == 40 / 8
    assert r.dram_bytes_per_ray == 15 * 32 / 8 and r.l1_hit_rate == 25 / 40


def test_a_cpu_kernels_stack_frame_is_written_and_read_each_packet_iteration(bunny):
    """On a CPU a kernel's spilled registers are memory (scripts/kernel_frame.py measures the frame
    lines its spills and reloads touch): with `frame_bytes`, each packet iteration writes, then reads,
    every segment of its packet slot's frame (memsites.S_FRAME_WRITE, S_FRAME_READ). A 64 KiB L1
    keeps it (its first writes miss, nothing after); an 8 KiB L1 under node traffic loses lines
    between iterations. The traversal's own requests and hits do not change; without a frame
    nothing is accessed."""
    v, f = bunny
    o, d, tmax = _rays(v, "incoherent")
    o, d, tmax = o[:2000], d[:2000], tmax[:2000]
    bvh = layerbvh.build(v, f, branching=4, batch_rays=len(o))

    def cpu(l1_kib):
        return Preset(name="cpu", description="one core", kind="cpu", units=1, resident_warps=1, block_warps=2048,
                      warp=8, segment_bytes=64, levels=(CacheLevel("L1", l1_kib << 10, 8, 64, shared=False),
                                                        CacheLevel("L2", 1 << 20, 16, 64, shared=True)),
                      flush_private_each_kernel=False, source="test")
    lines = 1024 // 64
    for mode in ("per_ray", "layer_sorted"):
        plain = L.replay_tree(bvh, o, d, tmax, mode, False, 8, cpu(64))
        rep = L.replay_tree(bvh, o, d, tmax, mode, False, 8, cpu(64), frame_bytes=1024)
        assert plain.tally[[ms.S_FRAME_READ, ms.S_FRAME_WRITE]].sum() == 0
        assert (rep.prim == plain.prim).all() and (rep.tally[:ms.S_END, 1] == plain.tally[:ms.S_END, 1]).all()
        for site in (ms.S_FRAME_WRITE, ms.S_FRAME_READ):
            assert rep.tally[site, 0] == rep.tally[site, 1] == rep.warp_iterations * lines, (mode, site)
        assert rep.levels_hit[ms.S_FRAME_WRITE, 1:].sum() == lines and rep.levels_hit[ms.S_FRAME_READ, 1:].sum() == 0
        small = L.replay_tree(bvh, o, d, tmax, mode, False, 8, cpu(8), frame_bytes=1024)
        assert small.levels_hit[[ms.S_FRAME_WRITE, ms.S_FRAME_READ], 1:].sum() > 10 * lines, mode


def test_the_replays_stores_are_the_cache_models_write_misses(bunny):
    """The replay's stores (the local entry stack, the kernels' outputs: memsites.STORE_SITES) go to the cache model as
    stores: every store transaction that L1 did not hold is counted a write miss, and no load is.
    On an 8 KiB L1 under node traffic some stores miss (a wide node's pushes reach slots that no
    pop brought in), per_ray and sorted."""
    v, f = bunny
    o, d, tmax = _rays(v, "incoherent", n=4000)
    bvh = layerbvh.build(v, f, branching=4, treelet_height=8, batch_rays=len(o))
    small = Preset(name="small", description="8 KiB L1 over 1 MiB", kind="cpu", units=1, resident_warps=1,
                   block_warps=2048, warp=8, segment_bytes=64,
                   levels=(CacheLevel("L1", 8 * 1024, 8, 64, shared=False),
                           CacheLevel("L2", 1024 * 1024, 16, 64, shared=True)),
                   flush_private_each_kernel=False, source="test")
    stores = list(ms.STORE_SITES)
    for mode in ("per_ray", "layer_sorted"):
        rep = L.replay_tree(bvh, o, d, tmax, mode, False, 8, small)
        missed = rep.levels_hit[stores, 1:].sum(axis=0)  # store transactions served by L2, DRAM
        assert rep.write_misses == (int(missed.sum()), int(missed[1:].sum())), (mode, rep.write_misses)
        assert missed.sum() > 0, mode
        assert L.row("incoherent", rep, 8).l1_write_misses_per_ray == missed.sum() / len(o)


def _soup():
    v, f = meshes.sphere_soup(60, 240, seed=4)
    return v, f


def test_sorting_must_cut_transactions():
    """Rays from one point in every direction, in random order: a warp of per_ray or of unsorted
    steps holds rays bound for different parts of the tree, a sorted step's warps rays bound for
    one treelet. Sorting must cut the node transactions per ray (measured: 6.9 against 37.5 unsorted
    and 51.2 per_ray; 15k triangles, treelet height 4, W = 32)."""
    v, f = _soup()
    n = 8192
    rng = np.random.default_rng(2)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile(((v.min(0) + v.max(0)) / 2)[None].astype(np.float32), (n, 1))
    tmax = np.full(n, np.inf, np.float32)
    bvh = layerbvh.build(v, f, branching=2, treelet_height=4, batch_rays=n, tail_steps=32)  # (steps to the end)
    rows = {m: L.row("fan", L.replay_tree(bvh, o, d, tmax, m, False, 32, preset("h200")), 4) for m in layerbvh.MODES}
    s, u, p = rows["layer_sorted"], rows["layer_unsorted"], rows["per_ray"]
    assert s.node_transactions_per_ray < 0.5 * u.node_transactions_per_ray, (s, u)
    assert s.node_transactions_per_ray < 0.5 * p.node_transactions_per_ray, (s, p)
    assert s.simd_efficiency > u.simd_efficiency
    # Same rays, same tree: the work per ray does not depend on the order.
    assert s.inner_per_ray == u.inner_per_ray and s.tris_per_ray == p.tris_per_ray


def test_sorting_cannot_cut_transactions_of_identical_rays():
    """Every lane of every warp carries the same ray: each warp-iteration already reads one node
    (2 sectors), so no order can do better; sorted, unsorted and per_ray issue the same node
    transactions and keep every lane busy."""
    v, f = _soup()
    n = 4096
    o = np.tile(np.array([[v[:, 0].min() - 1, 0.1, 0.2]], np.float32), (n, 1))
    d = np.tile(np.array([[1, 0.05, 0.02]], np.float32), (n, 1))
    tmax = np.full(n, np.inf, np.float32)
    bvh = layerbvh.build(v, f, branching=2, treelet_height=4, batch_rays=n)
    reps = {m: L.replay(bvh.layout, o, d, tmax, m, False, 32, preset("h200")) for m in layerbvh.MODES}
    rows = {m: L.row("same", rep, 4) for m, rep in reps.items()}
    for m, rep in reps.items():  # each node a ray visits: one 64-byte record, 2 sectors, for the whole warp
        assert rep.tally[ms.S_NODE, 0] * 32 == 2 * rep.work["inner_nodes"].sum(), m
        assert rows[m].simd_efficiency == 1.0
        assert rows[m].node_transactions_per_ray == rows["per_ray"].node_transactions_per_ray
    assert rows["per_ray"].sort_bytes_per_ray == 0 and rows["layer_sorted"].sort_bytes_per_ray > 0


def test_sampling_is_said_and_keeps_order():
    o = np.arange(30, dtype=np.float32).reshape(10, 3)
    d = np.ones((10, 3), np.float32)
    so, sd, st, before = L.sample_rays(o, d, np.arange(10, dtype=np.float32), 4, seed=1)
    assert before == 10 and len(so) == 4 and np.all(np.diff(st) > 0)
    assert L.sample_rays(o, d, np.zeros(10), 20)[3] is None


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "layerbvh_mitsuba.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def test_locality_command(tmp_path):
    """`layerbvh locality` on a real scene: a row per kind x mode with the documented fields, the
    trace checked, the plot and the summary written; bad options get one line."""
    out = tmp_path / "loc"
    r = _cli("locality", str(SCENES / "cbox.xml"), "--res", "24", "24", "--rays", "camera,shadow",
             "--preset", "h200,cpu", "--warp", "8,32", "--treelet-heights", "2", "--tail-steps", "1", "--out", str(out),
             "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "locality.json").read_text())
    rows = doc["results"]
    assert len(rows) == 2 * 3 * 2 * 2  # kinds x modes x presets x warps
    # With no tree options it models the tree a render gets (issue 40): the default branching.
    assert doc["branching"] == layerbvh.DEFAULT_BRANCHING and {r["branching"] for r in rows} == {doc["branching"]}
    assert doc["leaf_size"] == layerbvh.default_leaf_size(layerbvh.DEFAULT_BRANCHING)
    # --tail-steps reaches the build the kernel check traces and the replay (one step, then the tail).
    assert doc["tail_steps"] == 1 and {r["tail_steps"] for r in rows} == {1}
    assert max(r["kernels"] for r in rows) <= 2
    from layerbvh_mitsuba.tools.bench.locality import benchmarks_section, merge_documents
    assert "the layer modes' tail after 1 step at most." in benchmarks_section(merge_documents([doc]), "figs")
    need = ("kind", "mode", "warp", "preset", "rays", "inner_per_ray", "tris_per_ray", "transactions_per_ray",
            "simd_efficiency", "l1_hit_rate", "l2_hit_rate", "l2_bytes_per_ray", "dram_bytes_per_ray",
            "sort_bytes_per_ray")
    for row in rows:
        assert all(k in row for k in need), sorted(set(need) - set(row))
        assert row["rays"] > 0 and 0 < row["simd_efficiency"] <= 1
        assert (row["sort_bytes_per_ray"] == 0) == (row["mode"] == "per_ray")
    assert doc["checks"] and all(c["exact"] for c in doc["checks"])
    assert (out / "locality.png").stat().st_size > 10_000 and "## Verdict" in (out / "summary.md").read_text()
    assert any("cbox" in line or "camera" in line for line in doc["verdict"])
    # Every conclusion printed says what its model was checked against (issue 57 item 5): the GPU
    # preset's is unchecked, the CPU's checked against valgrind where the committed checks say.
    printed = [line for line in r.stdout.splitlines() if line.startswith(("h200", "cpu"))]
    assert len(printed) == 2 and all("[model " in line for line in printed), r.stdout
    assert "model unchecked" in printed[0] and "checked against valgrind" in printed[1], printed
    assert set(doc["model_checked"]) == {"h200", "cpu"} and "[model " in (out / "summary.md").read_text()
    for bad, says in ((["--preset", "nope"], "--preset: unknown 'nope'"), (["--rays", "bogus"], "--rays: unknown"),
                      (["--warp", "0"], "--warp")):
        r = _cli("locality", str(SCENES / "cbox.xml"), "--out", str(tmp_path / "x"), *bad, cwd=tmp_path)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and says in lines[0], r.stderr


def test_height_table_sets_sorted_against_per_ray_per_height():
    """BENCHMARKS.md's table against the treelet height: per kind and height, layer_sorted's total
    bytes over per_ray's and its steps per ray, at the headline warp and branching only."""
    import dataclasses
    from layerbvh_mitsuba.tools.bench.locality import height_table
    names = [f.name for f in dataclasses.fields(L.LocalityRow) if f.default is dataclasses.MISSING
             and f.default_factory is dataclasses.MISSING]
    base = L.LocalityRow(**{n: 0 for n in names})
    rows = []
    for h, sorted_total, steps in ((8, 120.0, 5.0), (12, 82.0, 3.0)):
        for k in (2, 4):  # the binary rows must not leak into the default tree's table
            rows += [dataclasses.replace(base, kind="shadow", mode="per_ray", preset="gtx965m", warp=32,
                                         treelet_height=h, branching=k, dram_bytes_per_ray=100.0,
                                         total_dram_bytes_per_ray=100.0),
                     dataclasses.replace(base, kind="shadow", mode="layer_sorted", preset="gtx965m", warp=32,
                                         treelet_height=h, branching=k, total_dram_bytes_per_ray=sorted_total * k / 4,
                                         steps_per_ray=steps)]
    table = height_table(rows)
    assert "| shadow | 1.20×, 5.00 | 0.82×, 3.00 |" in table, table
    assert height_table([r for r in rows if r.treelet_height == 8]) == ""


def test_a_verdict_says_what_its_model_was_checked_against(tmp_path):
    """model_checked.note: a GPU preset's model is unchecked; a CPU preset's names where the
    committed valgrind checks agree (ratio within tolerance and the same verdict) and where they
    do not, counting meshes; no committed check says so."""
    from layerbvh_mitsuba.tools.bench import model_checked as mc
    assert mc.note("gpu", tmp_path) == mc.GPU_NOTE and "unchecked" in mc.GPU_NOTE
    assert "no committed valgrind check" in mc.note("cpu", tmp_path)
    v = lambda level, kib, ratio=True, verdict=True: {"level": level, "d1_kib": kib, "ratio_agrees": ratio,  # noqa: E731
                                                     "verdict_agrees": verdict}
    (tmp_path / "cachegrind_a.json").write_text(json.dumps(
        {"mesh": "a.ply", "triangles": 10, "verdicts": [v("D1", 32), v("LL", 32), v("D1", 8)]}))
    assert "DISAGREES" not in mc.note("cpu", tmp_path) and "agrees at D1 32 KiB" in mc.note("cpu", tmp_path)
    # the ratio within tolerance, the verdict the other one: a disagreement all the same
    (tmp_path / "cachegrind_b.json").write_text(json.dumps(
        {"mesh": "b.ply", "triangles": 20, "verdicts": [v("D1", 32), v("LL", 32), v("D1", 8, verdict=False)]}))
    text = mc.note("cpu", tmp_path)
    assert "a.ply (10 triangles), b.ply (20 triangles)" in text, text
    assert "DISAGREES at D1 8 KiB, 1 of 2 meshes agreeing" in text, text
    assert "agrees at D1 32 KiB, LL beside D1 32" in text, text
    assert "reads only" in text
    # With write verdicts (the model's stores), each is named by its kind of miss.
    (tmp_path / "cachegrind_c.json").write_text(json.dumps(
        {"mesh": "c.ply", "triangles": 30,
         "verdicts": [v("D1", 32), {**v("D1", 32, ratio=False), "misses": "writes"}]}))
    text = mc.note("cpu", tmp_path)
    assert "reads and writes:" in text and "D1 32 KiB (writes), 0 of 1 meshes agreeing" in text, text
    (tmp_path / "cachegrind_c.json").unlink()
    noted = mc.with_note({"cpu": "cpu: sorting wins.", "x": "x: sorting loses."}, mc.notes({"cpu": "cpu"}, tmp_path))
    assert noted["cpu"].startswith("cpu: sorting wins. [model checked") and mc.GPU_NOTE in noted["x"]
