"""Instanced geometry: two-level traversal in every mode against each other; ties, memory, bad
input (against a flattened copy and Embree's own instancing: tests/runtime/test_engine_vs_embree.py)."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh import MISS, Group, Instance
from layerbvh.instances import BOX_PAD
from layerbvh import meshes

from engine_helpers import forest, placements, report, rotation  # noqa: F401  (forest: a fixture)


@pytest.mark.parametrize("kind", ["incoherent", "camera"])
def test_instanced_modes_agree_exactly(forest, kind):
    o, d = forest["rays"][kind]
    # (tail_steps 32: the steps go on until the rays-left rule hands the rest to the tail)
    bvhs = {tail: layerbvh.build_instanced(forest["groups"], forest["instances"], treelet_height=4, tail_rays=tail,
                                           tail_fraction=0.25 if tail else 0.0, tail_steps=32) for tail in (0, 2048)}
    bvhs[0].check()
    ref = bvhs[0].trace(o, d, mode="per_ray")
    assert np.mean(ref.prim != MISS) > 0.2, "a good share of the test rays should hit"
    assert len(np.unique(ref.instance[ref.prim != MISS])) >= 0.8 * len(forest["instances"]), "most instances are hit"
    for mode, tail in (("layer_sorted", 0), ("layer_sorted", 2048), ("layer_unsorted", 0)):
        h = bvhs[tail].trace(o, d, mode=mode)
        assert h.stats.steps > 3 and (h.stats.tail_rays > 0) == (tail > 0)
        bad = (h.prim != ref.prim) | (h.instance != ref.instance) | (h.t != ref.t) | (h.u != ref.u) | (h.v != ref.v)
        assert not bad.any(), f"{mode} differs from per_ray on {bad.sum()} rays:\n" + report(
            bad, h.instance, ref.instance, h.prim, ref.prim, h.t, ref.t,
            names=("inst", "inst_per_ray", "prim", "prim_per_ray", "t", "t_per_ray"))
        assert h.stats.inner_nodes == ref.stats.inner_nodes and h.stats.triangles == ref.stats.triangles
        assert (h.stats.top_inner_nodes, h.stats.instance_entries) == (ref.stats.top_inner_nodes,
                                                                       ref.stats.instance_entries)
        occ = bvhs[tail].occluded(o, d, np.full(len(o), np.inf, np.float32), mode=mode).occluded
        assert np.array_equal(occ, ref.prim != MISS), \
            f"{mode}: any-hit and closest-hit disagree on {(occ != (ref.prim != MISS)).sum()} rays"
    # Small batches: the same hits again (the batching path gathers per ray, instances included).
    small = layerbvh.build_instanced(forest["groups"], forest["instances"], treelet_height=4, batch_rays=7000)
    h = small.trace(o, d, mode="layer_sorted")
    assert h.stats.batches == 5 and np.array_equal(h.instance, ref.instance) and np.array_equal(h.prim, ref.prim)


def test_ties_across_instances_go_to_the_lower_instance(bunny):
    """Two instances with the same transform put the same triangles at the same distances:
    every hit must go to the lower instance index, in every mode."""
    v, f = bunny
    rng = np.random.default_rng(4)
    m = np.eye(4)
    m[:3, :3] = rotation(rng) * 1.3
    other = np.eye(4)
    other[:3, 3] = [0.5, 0, 0]
    instances = [Instance(0, other), Instance(0, m), Instance(0, other + 0), Instance(0, m.copy())]
    bvh = layerbvh.build_instanced([Group(v, f)], instances, treelet_height=3)
    world_v = np.concatenate([v @ m[:3, :3].T, v + [0.5, 0, 0]]).astype(np.float32)
    o, d = meshes.incoherent_rays(world_v, 20_000, seed=9)
    unique = layerbvh.build_instanced([Group(v, f)], instances[:2], treelet_height=3).trace(o, d, mode="per_ray")
    for mode in layerbvh.MODES:
        h = bvh.trace(o, d, mode=mode)
        hit = h.prim != MISS
        assert hit.mean() > 0.1
        assert set(np.unique(h.instance[hit]).tolist()) == {0, 1}, f"{mode}: a duplicate instance won a tie"
        assert np.all(h.instance[~hit] == MISS)
        # ... and the duplicates change nothing else: the hits of the two unique instances alone.
        assert np.array_equal(h.instance, unique.instance) and np.array_equal(h.prim, unique.prim)
        assert np.array_equal(h.t, unique.t)


def test_memory_grows_with_unique_geometry_not_instances(bunny):
    v, f = bunny
    one = layerbvh.build_instanced([Group(v, f)], placements(1, 1, seed=1, spread=1.0))
    many = layerbvh.build_instanced([Group(v, f)], placements(200, 1, seed=1, spread=1.0))
    b1, b200 = one.stats.bytes, many.stats.bytes
    assert b200["tris"] == b1["tris"] == len(f) * 64
    # Per extra instance: one 64-byte record, about one top-level node (64 bytes) plus its
    # treelet bookkeeping; nothing that scales with the group's triangles.
    per_instance = (sum(b200.values()) - sum(b1.values())) / 199
    assert per_instance <= 160, per_instance
    assert many.stats.triangles == len(f) and many.stats.placed_triangles == 200 * len(f)
    flat_bytes = 200 * (b1["tris"] + b1["nodes"])
    assert sum(b200.values()) < flat_bytes / 50


def test_trace_inline_matches_per_ray(forest):
    """The megakernel path (trace_inline, no host sync) gives the same hits as per_ray."""
    import drjit as dr
    o, d = forest["rays"]["incoherent"]
    bvh = layerbvh.build_instanced(forest["groups"], forest["instances"])
    ref = bvh.trace(o, d, mode="per_ray")
    F = bvh.m.Float
    h = bvh.trace_inline([F(o[:, c]) for c in range(3)], [F(d[:, c]) for c in range(3)], F(np.inf), bvh.m.Bool(True))
    dr.eval(h.t, h.prim, h.instance)
    assert np.array_equal(h.prim.numpy(), ref.prim) and np.array_equal(h.instance.numpy(), ref.instance)
    assert np.array_equal(h.t.numpy(), ref.t)


def test_instances_of_empty_groups_and_no_instances_miss(bunny):
    v, f = bunny
    o, d = meshes.incoherent_rays(v, 4000, seed=1)
    empty = Group(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    for groups, instances in (([empty], [Instance(0, np.eye(4))]), ([Group(v, f)], [])):
        bvh = layerbvh.build_instanced(groups, instances)
        bvh.check()
        for mode in layerbvh.MODES:
            h = bvh.trace(o, d, mode=mode)
            assert np.all(h.prim == MISS) and np.all(h.instance == MISS) and np.all(np.isinf(h.t))
    # An empty group next to a real one: only the real one's instances are traced.
    bvh = layerbvh.build_instanced([empty, Group(v, f)], [Instance(0, np.eye(4)), Instance(1, np.eye(4))])
    bvh.check()
    h = bvh.trace(o, d, mode="layer_sorted")
    assert set(np.unique(h.instance[h.prim != MISS]).tolist()) == {1}


def test_top_level_boxes_hold_their_instances(forest):
    bvh = layerbvh.build_instanced(forest["groups"], forest["instances"], treelet_height=2)
    bvh.check()
    parts = bvh.parts
    # Corrupting one instance's transform after the build breaks the box invariant.
    inst = [Instance(i.group, i.to_world.copy()) for i in bvh.instances]
    inst[3].to_world[:, 3] += 10.0
    with pytest.raises(AssertionError, match="does not hold instance 3"):
        layerbvh.instances.check_instanced(parts, bvh.groups, inst)
    assert 0 < BOX_PAD < 1e-4


@pytest.mark.parametrize("instance,message", [
    (Instance(2, np.eye(4)), r"instance 0: group 2 is not one of the 1 groups"),
    (Instance(0, np.eye(3)), r"instance 0: to_world must have shape \(4, 4\) or \(3, 4\)"),
    (Instance(0, np.diag([1.0, 1.0, 0.0, 1.0])), r"instance 0: to_world is singular"),
    (Instance(0, np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]])),
     r"instance 0: to_world is not affine"),
    (Instance(0, np.full((4, 4), np.nan)), r"instance 0: to_world has non-finite entries"),
])
def test_bad_instances_are_refused_by_name(bunny, instance, message):
    with pytest.raises(ValueError, match=message):
        layerbvh.build_instanced([Group(*bunny)], [instance])


def test_bad_groups_and_arguments_are_refused_by_name(bunny):
    v, f = bunny
    with pytest.raises(ValueError, match=r"group 1: faces\[0\] references vertex"):
        layerbvh.build_instanced([Group(v, f), Group(v[:3], f[:2] + 100)], [Instance(0, np.eye(4))])
    with pytest.raises(ValueError, match="groups and instances"):
        layerbvh.LayerBVH(v, f, groups=[Group(v, f)], instances=[])


def test_per_level_work_is_the_flat_walk_plus_the_top_level(bunny):
    """One identity instance of the bunny against the bunny as a plain mesh: the top level is one
    node per ray, a ray enters the instance iff it meets the (padded) box, and inside it walks
    exactly the flat BVH's nodes, less the root test of the rays that never entered."""
    v, f = bunny
    o, d = meshes.incoherent_rays(v, 20_000, seed=1)
    n = len(o)
    flat = layerbvh.build(v, f, treelet_height=4)
    one = layerbvh.build_instanced([Group(v, f)], [Instance(0, np.eye(4))], treelet_height=4)
    lo, hi = v.min(0).astype(np.float64), v.max(0).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    meets = np.nanmax(np.minimum(t0, t1), 1) <= np.nanmin(np.maximum(t0, t1), 1)
    meets &= np.nanmin(np.maximum(t0, t1), 1) >= 0
    for mode in ("per_ray", "layer_sorted", "layer_unsorted"):
        a, b = flat.trace(o, d, mode=mode), one.trace(o, d, mode=mode)
        assert np.array_equal(a.prim, b.prim)
        st = b.stats
        assert st.top_inner_nodes == n, mode
        assert abs(st.instance_entries - meets.sum()) <= 1e-3 * n, (mode, st.instance_entries, meets.sum())
        assert st.inner_nodes - st.top_inner_nodes == a.stats.inner_nodes - (n - st.instance_entries), mode
        assert st.as_dict()["instance_entries_per_ray"] == st.instance_entries / n
    assert flat.trace(o, d, mode="per_ray").stats.instance_entries == 0


@pytest.mark.parametrize("branching", [4, 8])
def test_instanced_wide_trees_return_the_binary_hits(forest, branching):
    """Two-level BVHs with 4- and 8-wide nodes (top level and groups): every mode returns binary
    per_ray's instance, prim and t bits, closest and any hit."""
    o, d = forest["rays"]["incoherent"]
    ref = layerbvh.build_instanced(forest["groups"], forest["instances"], treelet_height=4,
                                   branching=2).trace(o, d, mode="per_ray")
    bvh = layerbvh.build_instanced(forest["groups"], forest["instances"], treelet_height=2, branching=branching,
                                   tail_rays=0, tail_fraction=0.0)
    bvh.check()
    for mode in layerbvh.MODES:
        h = bvh.trace(o, d, mode=mode)
        bad = (h.prim != ref.prim) | (h.instance != ref.instance) | (h.t.view(np.uint32) != ref.t.view(np.uint32))
        assert not bad.any(), f"branching {branching} {mode} differs from binary per_ray on {bad.sum()} rays"
        occ = bvh.occluded(o, d, np.full(len(o), np.inf, np.float32), mode=mode).occluded
        assert np.array_equal(occ, ref.prim != MISS)
