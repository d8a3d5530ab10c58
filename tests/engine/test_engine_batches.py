"""Ray batches: tracing in batches of any size returns bit-identical hits and bounds the work memory by the batch."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh import meshes


@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_batches_change_nothing_but_memory(procedural, mode):
    v, f = procedural
    o, d = meshes.incoherent_rays(v, 20_000, seed=11)
    whole = layerbvh.build(v, f, treelet_height=3, backend="llvm")
    batched = layerbvh.build(v, f, treelet_height=3, backend="llvm", batch_rays=3_000)
    a, b = whole.trace(o, d, mode=mode), batched.trace(o, d, mode=mode)
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert b.stats.batches == 7 and a.stats.batches == 1 and b.stats.rays == 20_000
    assert (b.stats.inner_nodes, b.stats.leaves, b.stats.triangles) == (a.stats.inner_nodes, a.stats.leaves,
                                                                        a.stats.triangles)
    if mode != "per_ray":  # the entry stacks and queues scale with the batch
        assert b.stats.work_bytes < a.stats.work_bytes / 3
    tmax = np.where(np.isfinite(a.t), a.t * 0.5, 10.0).astype(np.float32)
    assert np.array_equal(whole.occluded(o, d, tmax, mode=mode).occluded,
                          batched.occluded(o, d, tmax, mode=mode).occluded)


def test_batch_size_is_checked(bunny):
    with pytest.raises(ValueError, match="batch_rays"):
        layerbvh.build(*bunny, batch_rays=0)


def test_auto_returns_the_same_hits_and_records_its_choice(procedural):
    v, f = procedural
    policy = layerbvh.AutoPolicy(min_rays=1 << 16)  # the CPU rule times only from 2^19 rays
    bvh = layerbvh.build(v, f, treelet_height=3, backend="llvm", auto_policy=policy)
    o, d = meshes.incoherent_rays(v, 70_000, seed=5)
    ref = bvh.trace(o, d, mode="per_ray")
    a = bvh.trace(o, d, mode="auto", hint="bounce")
    assert np.array_equal(a.prim, ref.prim) and np.array_equal(a.t, ref.t)
    (key, choice), = bvh.auto_choices.items()
    assert key == f"closest_hit/bounce/{(70_000).bit_length()}"
    assert choice["mode"] in ("per_ray", "layer_sorted") and a.stats.mode == f"auto:{choice['mode']}"
    sec = choice["seconds"]  # layer_sorted only when clearly faster (it needs more memory)
    assert choice["mode"] == ("layer_sorted" if sec["layer_sorted"] < 0.95 * sec["per_ray"] else "per_ray")
    assert policy.calibration_s > 0
    bvh.trace(o, d, mode="auto", hint="bounce")
    assert len(bvh.auto_choices) == 1, "decided once per kind and size class"
    small = bvh.trace(o[:1000], d[:1000], mode="auto", hint="bounce")
    assert small.stats.mode == "auto:per_ray" and bvh.auto_choices["closest_hit/bounce/10"]["seconds"] is None, \
        "small batches never calibrate"
    camera = bvh.trace(o, d, mode="auto", hint="camera")
    assert camera.stats.mode == "auto:per_ray" and "camera rays" in bvh.auto_choices["closest_hit/camera/17"]["reason"]
    # Decisions kept from an earlier run are adopted and not timed again.
    again = layerbvh.AutoPolicy(min_rays=1 << 16)
    again.load(policy.choices)
    assert again.known(False, "bounce", 70_000, bvh.stats.treelets) == choice["mode"]
    # ... and saved and loaded again, each run: the reason says "kept" once (it grew a prefix a run).
    third = layerbvh.AutoPolicy(min_rays=1 << 16)
    third.load(again.choices)
    assert all(c["reason"].count("kept from an earlier run") == 1 for c in third.choices.values()), third.choices
    assert layerbvh.AutoPolicy().known(False, "bounce", 70_000, bvh.stats.treelets) == "per_ray", \
        "the CPU rule: below 2^19 rays per_ray"


@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_active_mask_makes_misses_and_leaves_the_rest_alone(procedural, mode):
    v, f = procedural
    o, d = meshes.incoherent_rays(v, 5_000, seed=12)
    bvh = layerbvh.build(v, f, treelet_height=3, backend="llvm", batch_rays=2_000)
    active = np.random.default_rng(1).random(len(o)) < 0.6
    ref = bvh.trace(o, d, mode="per_ray")
    h = bvh.trace(o, d, mode=mode, active=active)
    assert np.array_equal(h.prim[active], ref.prim[active]) and np.array_equal(h.t[active], ref.t[active])
    assert np.all(h.prim[~active] == layerbvh.MISS) and np.all(np.isinf(h.t[~active]))
    assert (ref.prim[~active] != layerbvh.MISS).sum() > 100, "masked rays would have hit"
    # The work counts only the active rays.
    assert h.stats.inner_nodes < ref.stats.inner_nodes * 0.75
    tmax = np.where(np.isfinite(ref.t), ref.t * 2, 10.0).astype(np.float32)
    occ = bvh.occluded(o, d, tmax, mode=mode, active=active)
    assert isinstance(occ, layerbvh.Occlusion) and occ.stats.rays == len(o) and occ.stats.batches == 3
    assert np.array_equal(occ.occluded, active & (ref.prim != layerbvh.MISS))
    with pytest.raises(ValueError, match=r"active has 3 entries, origins has 5000"):
        bvh.trace(o, d, mode=mode, active=np.ones(3, bool))


def test_auto_runs_the_mode_it_reports(procedural):
    """auto's reported mode is the one that ran, told apart by what only the traversal itself
    shows: per_ray is one kernel over every ray (steps 1, all rays active in it), layer_sorted
    takes the same steps as layer_sorted traced directly (a sorted step, then the tail)."""
    v, f = procedural
    o, d = meshes.incoherent_rays(v, 20_000, seed=6)
    bvh = layerbvh.build(v, f, treelet_height=3, backend="llvm")
    sorted_steps = bvh.trace(o, d, mode="layer_sorted").stats.steps
    assert sorted_steps > 1
    small = bvh.trace(o, d, mode="auto", hint="bounce")  # below the CPU rule's 2^19 rays: per_ray, untimed
    assert small.stats.mode == "auto:per_ray"
    assert small.stats.steps == 1 and small.stats.active_per_step == [20_000], small.stats.active_per_step
    # A decision kept from an earlier run (as the integrator loads them): layer_sorted for this kind.
    (key,) = bvh.auto_choices  # the kind just decided
    bvh.auto.choices.clear()
    bvh.auto.load({key: {"mode": "layer_sorted", "reason": "timed in an earlier run"}})
    kept = bvh.trace(o, d, mode="auto", hint="bounce")
    assert kept.stats.mode == "auto:layer_sorted" and kept.stats.steps == sorted_steps
