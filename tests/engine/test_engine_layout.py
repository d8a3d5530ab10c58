"""Layer BVH layout invariants, build bounds on degenerate input, statistics and input errors."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh.layout import EXIT_BIT, LEAF_BIT, NODE_DEPTH, NODE_FLOATS, NODE_LINK, check_layout
from layerbvh.sah import MAX_DEPTH, triangle_bounds
from layerbvh import meshes


def _soup(n, seed=0, size=0.05):
    rng = np.random.default_rng(seed)
    v = (rng.random((n, 1, 3)) + rng.random((n, 3, 3)) * size).astype(np.float32).reshape(-1, 3)
    return v, np.arange(3 * n).reshape(-1, 3)


def _degenerate_cases():
    one_point = (np.zeros((3000, 3), np.float32), np.arange(3000).reshape(-1, 3))
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    duplicated = (np.tile(tri, (500, 1)), np.arange(1500).reshape(-1, 3))
    collinear = (np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]] * 50, np.float32), np.arange(150).reshape(-1, 3))
    single = (tri, np.array([[0, 1, 2]]))
    return {"one_point": one_point, "duplicated": duplicated, "collinear": collinear, "single": single}


@pytest.mark.parametrize("height", [1, 2, 3, 4, 8])
def test_layout_invariants_bunny(bunny, height):
    v, f = bunny
    bvh = layerbvh.build(v, f, branching=2, treelet_height=height)
    bvh.check()
    s = bvh.stats
    counts = np.array(s.treelet_node_counts)
    assert counts.sum() == s.nodes and len(counts) == s.treelets
    assert counts.max() <= 2 ** height - 1, "a treelet of height H holds at most 2^H - 1 nodes"
    assert s.leaves == s.nodes + 1, "a binary tree has one more leaf than inner nodes"
    # Treelet roots are exactly the inner nodes at depths 0, H, 2H, ...
    depth = bvh.layout.nodes.reshape(-1, NODE_FLOATS)[:, NODE_DEPTH].astype(int)
    assert s.treelets == int(np.sum(depth % height == 0))
    assert s.bytes["nodes"] == 64 * s.nodes and s.bytes["tris"] == 64 * s.triangles
    assert set(s.bytes) == {"nodes", "tris", "treelet_first", "node_treelet"}, "what the device holds"


@pytest.mark.parametrize("leaf_size", [1, 4, 16])
def test_layout_invariants_random_and_procedural(procedural, leaf_size):
    for v, f in (_soup(5000, seed=leaf_size), procedural):
        bvh = layerbvh.build(v, f, branching=2, treelet_height=3, leaf_size=leaf_size)
        bvh.check()
        lv = bvh.layout.leaves.reshape(-1, 2)
        assert lv[:, 1].max() <= leaf_size


@pytest.mark.parametrize("case", list(_degenerate_cases()))
def test_degenerate_meshes_build_and_trace(case):
    v, f = _degenerate_cases()[case]
    bvh = layerbvh.build(v, f, treelet_height=2, leaf_size=2)
    bvh.check()
    assert bvh.stats.depth < MAX_DEPTH
    o = np.array([[0.25, 0.25, 1.0], [0.0, 0.0, 1.0], [5, 5, 5]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1], [1, 0, 0]], np.float32)
    hits = {m: bvh.trace(o, d, mode=m) for m in layerbvh.MODES}
    for m in layerbvh.MODES:
        assert np.array_equal(hits[m].prim, hits["per_ray"].prim)
    h = hits["per_ray"]
    if case in ("duplicated", "single"):
        # Ties in t go to the smallest primitive id, in every mode.
        assert h.prim[0] == 0 and h.t[0] == pytest.approx(1.0)
        assert h.u[0] == pytest.approx(0.25) and h.v[0] == pytest.approx(0.25)
    else:
        # Zero-area triangles are never hit.
        assert np.all(h.prim == layerbvh.MISS) and np.all(np.isinf(h.t))


def test_empty_mesh_misses_everything():
    bvh = layerbvh.build(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    h = bvh.trace(np.zeros((4, 3), np.float32), np.ones((4, 3), np.float32))
    assert np.all(h.prim == layerbvh.MISS) and np.all(np.isinf(h.t))
    assert not bvh.occluded(np.zeros((4, 3), np.float32), np.ones((4, 3), np.float32), 10.0).occluded.any()


@pytest.mark.parametrize("branching", [2, 4])
def test_check_layout_catches_corruption(bunny, branching):
    v, f = bunny
    lay = layerbvh.build(v, f, branching=branching, treelet_height=3).layout
    links, rec, fmt = lay.links(), lay.records(), lay.format
    inner = np.nonzero((links[:, 0] & (LEAF_BIT | EXIT_BIT)) == 0)[0]
    assert len(inner) >= 2
    saved = links[inner[0], 0]
    links[inner[0], 0] = links[inner[1], 0]  # one node referenced twice, another never
    with pytest.raises(AssertionError, match="referenced"):
        check_layout(lay, len(f))
    links[inner[0], 0] = saved
    check_layout(lay, len(f))
    rec[0, list(fmt.hi[0])] = rec[0, list(fmt.lo[0])]  # shrink the root's first child box to a point
    with pytest.raises(AssertionError, match="box"):
        check_layout(lay, len(f))


def test_build_rate_is_reported(procedural):
    """Build and layout times are reported apart from loading the builder's kernels, which
    happens once per process: the first build here may load them (it is the first in the process
    when this file runs alone: 5.9 s on a cold numba cache), a second build must not."""
    v, f = procedural
    first = layerbvh.build(v, f).stats
    again = layerbvh.build(v, f).stats
    for s in (first, again):
        assert s.build_s > 0 and s.layout_s > 0 and s.kernel_load_s >= 0
    assert again.kernel_load_s == 0.0, "the builder's kernels load once per process, not per build"


def test_compiled_records_match_numpy(bunny):
    """The numba kernels compute what the plain numpy expressions do, bit for bit."""
    v, f = bunny
    lo, hi = triangle_bounds(v, f)
    assert np.array_equal(lo, v[f].min(1)) and np.array_equal(hi, v[f].max(1))
    lay = layerbvh.build(v, f, branching=2).layout
    rec = lay.tris.reshape(-1, 16)
    ids = rec[:, 9].view(np.uint32)
    p = v[f[ids]].astype(np.float64)
    assert np.array_equal(rec[:, :9], v[f[ids]].reshape(-1, 9))
    assert np.array_equal(rec[:, 10:16].view(np.float64), np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))


def test_sah_split_quality(bunny):
    """The builder's SAH cost (inner node area + leaf area x triangles, over the root's area)
    stays at a binned SAH's level; a median or random split scores far worse on the bunny."""
    v, f = bunny
    b = layerbvh.build(v, f, branching=2).binary
    e = np.maximum(b.hi.astype(np.float64) - b.lo, 0)
    area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
    inner = b.left >= 0
    cost = (area[inner].sum() + (area[~inner] * b.count[~inner]).sum()) / area[0]
    assert cost < 35.0, f"SAH cost {cost:.1f}: the numpy binned SAH reached 32.8"
    # every node's triangles lie in its box (the partition moved bounds with the ids)
    tri = v[f[b.perm]]
    for i in np.random.default_rng(0).choice(len(b.left), 500, replace=False):
        t = tri[b.start[i]:b.start[i] + b.count[i]]
        assert np.all(t.min((0, 1)) >= b.lo[i]) and np.all(t.max((0, 1)) <= b.hi[i])


# -- statistics against theory ------------------------------------------------------------------

def test_single_treelet_takes_one_step(bunny):
    """When one treelet holds the whole BVH, no ray ever leaves it: one wavefront step."""
    v, f = bunny
    o, d = meshes.incoherent_rays(v, 5000, 1)
    bvh = layerbvh.build(v, f, branching=2, treelet_height=64)
    assert bvh.stats.treelets == 1
    for mode in ("layer_sorted", "layer_unsorted"):
        h = bvh.trace(o, d, mode=mode)
        assert h.stats.steps == 1 and h.stats.active_per_step == [5000]


def test_step_statistics(bunny):
    v, f = bunny
    o, d = meshes.incoherent_rays(v, 5000, 2)
    bvh = layerbvh.build(v, f, branching=2, treelet_height=3)
    h = bvh.trace(o, d, mode="layer_sorted")
    st = h.stats
    a = st.active_per_step
    assert a[0] == 5000 and all(x >= y for x, y in zip(a, a[1:])), "rays only ever leave the wavefront"
    assert st.steps == len(a) > 1
    # Every ray starts at the root, so it visits at least one inner node; hits need a triangle test.
    assert st.inner_nodes >= 5000
    assert st.triangles >= int(np.sum(h.prim != layerbvh.MISS))
    assert st.leaves <= st.inner_nodes + 5000
    # The kernel's per-ray step counter against the host's count of active rays per step: each
    # ray active in a step (the per-ray tail included) runs that step's kernel once, so a ray
    # dropped from the wavefront or counted twice shows here. More than one step per ray.
    assert st.ray_steps == sum(a) > 5000
    assert h.work["steps"].min() >= 1 and h.work["steps"].max() == st.steps
    # (time_treelet_s is time_traverse_s minus the estimated time_leaf_s: their sum is not checked,
    # it holds by construction.)
    assert st.work_bytes >= 5000 * bvh.stats.depth * 8, "entry stacks are part of the work memory"


def test_missing_the_root_box_costs_one_node(bunny):
    v, f = bunny
    far = v.max(0) + 10
    o = np.tile(far, (100, 1)).astype(np.float32)
    d = np.tile([1, 0, 0], (100, 1)).astype(np.float32)
    for mode in layerbvh.MODES:
        h = layerbvh.build(v, f).trace(o, d, mode=mode)
        assert h.stats.inner_nodes == 100 and h.stats.triangles == 0


# -- bad input ----------------------------------------------------------------------------------

def test_bad_mesh_errors():
    v, f = _soup(10)
    with pytest.raises(ValueError, match=r"vertices must have shape \(V, 3\)"):
        layerbvh.build(v[:, :2], f)
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        layerbvh.build(v, f[:, :2])
    bad = v.copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"vertices\[7\].*not finite"):
        layerbvh.build(bad, f)
    bad[7, 1] = np.inf
    with pytest.raises(ValueError, match=r"vertices\[7\]"):
        layerbvh.build(bad, f)
    ff = f.copy()
    ff[4, 2] = -1
    with pytest.raises(ValueError, match=r"faces\[4\].*negative"):
        layerbvh.build(v, ff)
    ff[4, 2] = 30
    with pytest.raises(ValueError, match=r"faces\[4\] references vertex 30, only 30 vertices"):
        layerbvh.build(v, ff)
    with pytest.raises(ValueError, match="treelet_height must be in"):
        layerbvh.build(v, f, treelet_height=0)
    with pytest.raises(ValueError, match="leaf_size"):
        layerbvh.build(v, f, leaf_size=0)


def test_bad_ray_errors_and_invalid_rays_miss():
    v, f = _soup(100)
    bvh = layerbvh.build(v, f)
    with pytest.raises(ValueError, match=r"origins must have shape \(N, 3\)"):
        bvh.trace(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"origins has 4 entries, directions has 5"):
        bvh.trace(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="mode must be one of"):
        bvh.trace(np.zeros((4, 3)), np.ones((4, 3)), mode="fast")
    c = v.mean(0)
    o = np.array([c + [0, 0, 2]] * 5, np.float32)
    d = np.array([[0, 0, -1]] * 5, np.float32)
    o[1, 0] = np.nan
    d[2, 1] = np.inf
    d[3] = 0
    o[4, 2] = -np.inf
    for mode in layerbvh.MODES:
        h = bvh.trace(o, d, mode=mode)
        assert np.all(h.prim[1:] == layerbvh.MISS) and np.all(np.isinf(h.t[1:]))
        assert not bvh.occluded(o, d, 10.0, mode=mode).occluded[1:].any()


def test_all_rays_invalid_is_fine():
    v, f = _soup(50)
    bvh = layerbvh.build(v, f)
    o = np.full((8, 3), np.nan, np.float32)
    for mode in layerbvh.MODES:
        assert np.all(bvh.trace(o, o, mode=mode).prim == layerbvh.MISS)
        assert not bvh.occluded(o, o, 1.0, mode=mode).occluded.any()


def test_no_rays_is_fine():
    v, f = _soup(50)
    bvh = layerbvh.build(v, f)
    none = np.zeros((0, 3), np.float32)
    for mode in layerbvh.MODES:
        h = bvh.trace(none, none, mode=mode)
        assert h.prim.shape == (0,) and h.t.shape == (0,)
        assert bvh.occluded(none, none, 1.0, mode=mode).occluded.shape == (0,)
