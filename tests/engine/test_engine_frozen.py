"""Frozen wavefront steps (wavefront.FROZEN_STACK_BYTES: dr.freeze replays the step and tail kernels) return what the unfrozen steps return, at every width they are replayed at, and are replayed, not recorded again."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh import meshes, wavefront

WORK = ("steps", "inner_nodes", "leaves", "triangles", "iterations", "ray_steps")
# Widths in an order that replays a recording at a larger width than it was made at (an array
# allocated inside a frozen function keeps its recorded size: state.StateRecords.write's `into`).
WIDTHS = (512, 16_384, 65_536, 3_000)


@pytest.fixture(scope="module", params=[1.0, 1e18], ids=["unit", "far"])
def scaled(request, bunny):
    """The bunny at scale 1 and at 1e18 (a layout in far units, layout.FAR_COORD: its `far` True
    is the shared Python object that hid a changed any_hit from drjit's own key)."""
    v, f = bunny
    v = (v.astype(np.float64) * request.param).astype(np.float32)
    return v, layerbvh.build(v, f)


def _trace(tree, o, d, mode, any_hit):
    h = (tree.occluded if any_hit else tree.trace)(o, d, mode=mode)
    return h, ("occluded",) if any_hit else ("t", "prim", "u", "v")


@pytest.mark.parametrize("mode", ["layer_sorted", "layer_unsorted"])
def test_frozen_steps_return_the_unfrozen_hits_and_work_at_every_width(scaled, mode, monkeypatch):
    v, tree = scaled
    recordings = []
    for rnd in range(3):
        for n in WIDTHS:
            o, d = meshes.incoherent_rays(v, n, seed=11 + n)
            # Any-hit first: a closest-hit query that replayed the any-hit kernels (drjit's key
            # missed `any_hit`: wavefront._configuration) returns wrong hits; the reverse does not show.
            for any_hit in (True, False):
                monkeypatch.setattr(wavefront, "FROZEN_BACKENDS", ())
                ref, keys = _trace(tree, o, d, mode, any_hit)
                monkeypatch.setattr(wavefront, "FROZEN_BACKENDS", ("llvm",))
                got, _ = _trace(tree, o, d, mode, any_hit)
                assert got.stats.frozen and not ref.stats.frozen, n
                for k in keys:
                    assert np.array_equal(np.asarray(getattr(ref, k)), np.asarray(getattr(got, k))), (n, any_hit, k)
                assert [getattr(got.stats, w) for w in WORK] == [getattr(ref.stats, w) for w in WORK], (n, any_hit)
                assert ref.stats.steps >= 2  # (at least one wavefront step before the tail)
        recordings.append((wavefront._STEP.n_recordings, wavefront._TAIL.n_recordings))
    # The last round is all replays: the kernels were recorded once per shape. (The second round
    # may record once more: measured, the 512-ray trace after a larger one records again once.)
    assert recordings[2] == recordings[1], recordings


def test_large_traces_are_not_frozen(scaled):
    """Above FROZEN_STACK_BYTES a step would copy the whole entry stack (it spills into the array
    it reads): the unfrozen step, with its alias and no copy, is taken there."""
    tree = scaled[1]
    rows = wavefront.stack_rows(tree.device)
    n = wavefront.FROZEN_STACK_BYTES // (rows * wavefront.ENTRY_BYTES) + 1
    assert not wavefront.frozen_steps(tree.device, n, rows) and wavefront.frozen_steps(tree.device, n - 1, rows)
