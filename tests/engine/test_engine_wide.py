"""Wide Layer BVHs (branching 4 and 8): the collapse, the layout's invariants, and hits bit-identical to the binary
per_ray walk in every mode."""
from __future__ import annotations

import math

import numpy as np
import pytest

import layerbvh
from layerbvh.collapse import collapse, surface_areas
from layerbvh.layout import EMPTY_LINK, check_layout
from layerbvh.walk import SORT_NETWORKS
from layerbvh import meshes

N_RAYS = 40_000
WIDE = (4, 8)


def _rays(v, kind, n=N_RAYS, seed=7):
    return meshes.camera_rays(v, n, seed) if kind == "camera" else meshes.incoherent_rays(v, n, seed)


def _bits(x):
    return np.asarray(x, np.float32).view(np.uint32)


def test_sorting_networks_sort_every_input():
    """By the 0-1 principle a comparator network sorts everything iff it sorts every 0/1 input."""
    for k, net in SORT_NETWORKS.items():
        for bits in range(1 << k):
            x = [(bits >> i) & 1 for i in range(k)]
            for a, b in net:
                if x[b] < x[a]:
                    x[a], x[b] = x[b], x[a]
            assert x == sorted(x), f"the {k}-input network leaves {bits:0{k}b} unsorted"


@pytest.mark.parametrize("branching", WIDE)
def test_collapse_pulls_up_the_largest_children(procedural, branching):
    """Every wide node is full or has only leaves below its slots, and every binary node it
    opened is at least as large (surface area) as any inner child it kept: the greedy rule."""
    v, f = procedural
    b = layerbvh.build(v, f, branching=2).binary
    wide = collapse(b, branching)
    area = surface_areas(b)
    inner = b.left >= 0
    held = np.zeros(len(b.left), np.int64)
    for n in np.nonzero(wide.is_node)[0]:
        kids = wide.kids[n][wide.kids[n] >= 0]
        held[kids] += 1
        assert 2 <= len(kids) <= branching
        kept_inner = kids[inner[kids]]
        assert len(kids) == branching or len(kept_inner) == 0, f"node {n} could have opened a child"
        opened, todo = [], [n]
        while todo:  # the binary nodes between n and its wide children
            x = todo.pop()
            for c in (b.left[x], b.left[x] + 1):
                if c not in kids:
                    opened.append(c)
                    todo.append(c)
        assert len(opened) == len(kids) - 2
        if opened and len(kept_inner):
            assert area[opened].min() >= area[kept_inner].max(), f"node {n} opened a smaller child first"
    assert np.all(held[~inner] == 1), "every binary leaf is the child of exactly one wide node"
    assert np.all(held[wide.is_node][1:] == 1) and held[0] == 0


@pytest.mark.parametrize("branching", WIDE)
@pytest.mark.parametrize("height", [1, 2, 3, 8])
def test_wide_layout_invariants(bunny, branching, height):
    v, f = bunny
    wide = layerbvh.build(v, f, treelet_height=height, branching=branching, leaf_size=4)  # the binary's leaves
    wide.check()
    binary = layerbvh.build(v, f, treelet_height=height, branching=2)
    lay, bl = wide.layout, binary.layout
    assert lay.records().shape[1] * 4 == {4: 128, 8: 256}[branching]
    assert lay.node_count < bl.node_count / (0.8 * math.log2(branching))
    assert math.ceil(bl.depth / math.log2(branching)) <= lay.depth < bl.depth
    assert lay.children().max() == branching and lay.children().mean() > 0.55 * branching
    assert wide.stats.branching == branching and wide.stats.depth == lay.depth
    # The same leaves and triangles, so the same triangle and leaf records.
    assert lay.leaf_count == bl.leaf_count and len(lay.tris) == len(bl.tris)


def test_check_layout_catches_a_used_empty_slot(bunny):
    """(References and boxes on a wide tree: test_engine_layout.test_check_layout_catches_corruption.)"""
    v, f = bunny
    lay = layerbvh.build(v, f, treelet_height=8, branching=4).layout
    links = lay.links()
    part = np.nonzero(lay.children() < 4)[0]
    assert len(part), "the bunny's BVH4 should have a node with an empty slot"
    n = part[0]
    links[n, 3] = links[n, 0]  # an empty slot used again
    with pytest.raises(AssertionError, match="empty child slot"):
        check_layout(lay, len(f))
    links[n, 3] = EMPTY_LINK
    check_layout(lay, len(f))


@pytest.mark.parametrize("branching", WIDE)
@pytest.mark.parametrize("kind", ["camera", "incoherent"])
def test_every_mode_returns_the_binary_per_ray_bits(procedural, branching, kind):
    """Closest hits (prim, t, u, v bits) and any-hit answers of every mode on the wide tree equal
    binary per_ray's; with treelets of 2 levels the layer modes take many wavefront steps."""
    v, f = procedural
    o, d = _rays(v, kind)
    binary = layerbvh.build(v, f, treelet_height=4, branching=2)
    ref = binary.trace(o, d, mode="per_ray")
    ref_occ = binary.occluded(o, d, np.full(len(o), np.inf, np.float32), mode="per_ray").occluded
    assert np.mean(ref.prim != layerbvh.MISS) > 0.2, "test rays should mostly hit"
    wide = {tail: layerbvh.build(v, f, treelet_height=2, branching=branching, tail_rays=tail,  # (many steps)
                                 tail_fraction=0.25 if tail else 0.0, tail_steps=32) for tail in (0, 2048)}
    for mode, tail in (("per_ray", 0), ("layer_sorted", 0), ("layer_sorted", 2048), ("layer_unsorted", 0)):
        h = wide[tail].trace(o, d, mode=mode)
        if mode != "per_ray":
            assert h.stats.steps > 3 and (h.stats.tail_rays > 0) == (tail > 0)
        for name in ("prim", "t", "u", "v"):
            a, b = getattr(h, name), getattr(ref, name)
            bad = (a != b) if name == "prim" else (_bits(a) != _bits(b))
            assert not bad.any(), (f"branching {branching} {mode}: {name} differs from binary per_ray on "
                                   f"{bad.sum()} rays")
        occ = wide[tail].occluded(o, d, np.full(len(o), np.inf, np.float32), mode=mode).occluded
        assert np.array_equal(occ, ref_occ), f"branching {branching} {mode}: any-hit differs"
    # Work shown both ways: fewer node visits and loop iterations, more box tests.
    w = wide[0].trace(o, d, mode="per_ray").stats
    assert w.inner_nodes < 0.75 * ref.stats.inner_nodes and w.iterations < ref.stats.iterations
    assert w.inner_nodes * branching > ref.stats.inner_nodes * 2
    assert w.triangles == ref.stats.triangles or branching > 2  # visit order may differ: counts may too


def test_ties_go_to_the_lowest_primitive_whatever_the_branching():
    """Three identical copies of every triangle of a plane, ids shuffled: the closest hit must be
    the lowest id of the three, whatever the visit order (branching, mode)."""
    rng = np.random.default_rng(4)
    g = 24
    xs, ys = np.meshgrid(np.arange(g + 1, dtype=np.float32), np.arange(g + 1, dtype=np.float32))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size, np.float32)], 1)
    q = (np.arange(g)[:, None] * (g + 1) + np.arange(g)[None, :]).ravel()
    tris = np.concatenate([np.stack([q, q + 1, q + g + 2], 1), np.stack([q, q + g + 2, q + g + 1], 1)])
    perm = rng.permutation(3 * len(tris))
    faces = np.concatenate([tris] * 3)[np.argsort(perm)]  # face i is copy perm-order
    n = 20_000
    o = np.stack([rng.uniform(0, g, n), rng.uniform(0, g, n), rng.uniform(1, 5, n)], 1).astype(np.float32)
    d = np.stack([rng.normal(0, 0.2, n), rng.normal(0, 0.2, n), -np.ones(n)], 1).astype(np.float32)
    ref = layerbvh.build(v, faces, leaf_size=1, branching=2).trace(o, d, mode="per_ray")
    hit = ref.prim != layerbvh.MISS
    assert hit.mean() > 0.9
    copies = {}
    for i, tri in enumerate(faces):
        copies.setdefault(tuple(tri), []).append(i)
    lowest = {i: min(c) for c in copies.values() for i in c}
    assert all(lowest[p] == p for p in ref.prim[hit]), "binary per_ray must already pick the lowest id"
    for k in layerbvh.BRANCHINGS:
        bvh = layerbvh.build(v, faces, treelet_height=1, leaf_size=1, branching=k, tail_fraction=0.0, tail_rays=0)
        for mode in layerbvh.MODES:
            h = bvh.trace(o, d, mode=mode)
            assert np.array_equal(h.prim, ref.prim) and np.array_equal(_bits(h.t), _bits(ref.t)), f"K={k} {mode}"


@pytest.mark.parametrize("branching", WIDE)
def test_trace_inline_on_a_wide_tree(procedural, branching):
    import drjit as dr
    v, f = procedural
    o, d = _rays(v, "incoherent", 20_000)
    ref = layerbvh.build(v, f, branching=2).trace(o, d, mode="per_ray")
    bvh = layerbvh.build(v, f, branching=branching)
    F = bvh.m.Float
    h = bvh.trace_inline([F(o[:, c]) for c in range(3)], [F(d[:, c]) for c in range(3)], F(np.inf), bvh.m.Bool(True))
    dr.eval(h.t, h.prim)
    assert np.array_equal(h.prim.numpy(), ref.prim) and np.array_equal(_bits(h.t.numpy()), _bits(ref.t))


def test_bad_branching_is_refused_by_name(bunny):
    v, f = bunny
    for bad in (3, 16, 1, "4"):
        with pytest.raises(ValueError, match="branching must be"):
            layerbvh.build(v, f, branching=bad)
