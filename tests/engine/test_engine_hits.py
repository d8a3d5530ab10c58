"""Closest hits and occlusion: every traversal mode against each other (against Embree:
tests/runtime/test_engine_vs_embree.py)."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh import meshes

from engine_helpers import rays, report


@pytest.mark.parametrize("mesh_name", ["bunny", "procedural"])
@pytest.mark.parametrize("kind", ["camera", "incoherent"])
def test_modes_agree_exactly(request, mesh_name, kind):
    v, f = request.getfixturevalue(mesh_name)
    o, d = rays(v, kind)
    bvhs = {tail: layerbvh.build(v, f, treelet_height=4, tail_rays=tail, tail_fraction=0.25 if tail else 0.0)
            for tail in (0, 2048)}
    ref = bvhs[0].trace(o, d, mode="per_ray")
    assert np.mean(ref.prim != layerbvh.MISS) > 0.2, "test rays should mostly hit"
    for mode, tail in (("layer_sorted", 0), ("layer_sorted", 2048), ("layer_unsorted", 0)):
        h = bvhs[tail].trace(o, d, mode=mode)  # tail 0: every ray stays in the wavefront steps to the end
        assert (h.stats.tail_rays > 0) == (tail > 0)
        bad = (h.prim != ref.prim) | (h.t != ref.t) | (h.u != ref.u) | (h.v != ref.v)
        assert not bad.any(), f"{mode} differs from per_ray on {bad.sum()} rays:\n" + \
            report(bad, h.prim, ref.prim, h.t, ref.t, names=("prim", "prim_per_ray", "t", "t_per_ray"))
        # Same traversal order, so the same work: a check of the statistics, not only the hits.
        assert h.stats.inner_nodes == ref.stats.inner_nodes
        assert h.stats.triangles == ref.stats.triangles


def test_the_step_cap_hands_a_long_batch_to_the_tail():
    """Rays that need hundreds of steps (turned slivers) are finished by the per-ray tail after
    wavefront.TAIL_STEPS steps, with the same hits and work; with the tail off they are not."""
    from layerbvh.wavefront import TAIL_STEPS
    v, f, o, d = meshes.turned_slivers()
    capped, uncapped = (layerbvh.build(v, f, tail_rays=t, tail_fraction=0.25 if t else 0.0) for t in (2048, 0))
    ref = capped.trace(o, d, mode="per_ray")
    assert np.mean(ref.prim != layerbvh.MISS) > 0.99  # (aimed inside the strip: every ray hits)
    long = uncapped.trace(o, d, mode="layer_sorted")
    assert long.stats.steps > 4 * TAIL_STEPS and long.stats.tail_rays == 0
    h = capped.trace(o, d, mode="layer_sorted")
    assert h.stats.steps == TAIL_STEPS + 1 and h.stats.tail_rays > 0.5 * len(o)
    for got in (long, h):
        assert (got.prim == ref.prim).all() and (got.t == ref.t).all() and (got.u == ref.u).all()
        assert got.stats.inner_nodes == ref.stats.inner_nodes and got.stats.triangles == ref.stats.triangles


@pytest.mark.parametrize("tail_steps", [1, 2])
def test_a_step_cap_of_k_takes_k_sorted_steps_then_the_tail(procedural, tail_steps):
    """tail_steps = k: k wavefront steps, then the per-ray tail finishes every ray left (in the
    order the last step sorted them), with per_ray's hits and work, closest and any hit."""
    v, f = procedural
    o, d = rays(v, "incoherent")
    bvh = layerbvh.build(v, f, treelet_height=4, tail_steps=tail_steps)
    ref = bvh.trace(o, d, mode="per_ray")
    h = bvh.trace(o, d, mode="layer_sorted")
    assert h.stats.steps == tail_steps + 1 and h.stats.tail_rays == h.stats.active_per_step[-1] > 0.25 * len(o)
    assert (h.prim == ref.prim).all() and (h.t == ref.t).all() and (h.u == ref.u).all()
    assert h.stats.inner_nodes == ref.stats.inner_nodes and h.stats.triangles == ref.stats.triangles
    occ = bvh.occluded(o, d, mode="layer_sorted").occluded
    assert (np.asarray(occ) == (np.asarray(ref.prim) != layerbvh.MISS)).all()
