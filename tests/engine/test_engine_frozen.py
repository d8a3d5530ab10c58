"""Frozen wavefront steps (wavefront.FROZEN_STACK_BYTES: dr.freeze replays the step and tail kernels; opt-in,
LAYERBVH_FROZEN_STEPS=1, on here) return what the unfrozen steps return, at every width they are replayed at, and are
replayed, not recorded again."""
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
    # (tail_steps 32: several steps per trace, so a step recorded at one width is replayed at others)
    return v, layerbvh.build(v, f, tail_steps=32)


def _trace(tree, o, d, mode, any_hit):
    h = (tree.occluded if any_hit else tree.trace)(o, d, mode=mode)
    return h, ("occluded",) if any_hit else ("t", "prim", "u", "v")


@pytest.mark.parametrize("mode", ["layer_sorted", "layer_unsorted"])
def test_frozen_steps_return_the_unfrozen_hits_and_work_at_every_width(scaled, mode, monkeypatch):
    v, tree = scaled
    recordings = []
    for rnd in range(4):
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
    # The last round is all replays: the kernels were recorded once per shape. (The second and
    # third rounds may record again: measured, the 512-ray trace after a larger one records once
    # more, and since the first step reads no records, issue 57 item 2, a 16,384-ray trace's steps too.)
    assert recordings[3] == recordings[2], recordings


def test_large_traces_are_not_frozen(scaled, monkeypatch):
    """Above FROZEN_STACK_BYTES a step would copy the whole entry stack (it spills into the array
    it reads): the unfrozen step, with its alias and no copy, is taken there."""
    tree = scaled[1]
    monkeypatch.setattr(wavefront, "FROZEN_BACKENDS", ("llvm",))
    rows = wavefront.stack_rows(tree.device)
    n = wavefront.FROZEN_STACK_BYTES // (rows * wavefront.ENTRY_BYTES) + 1
    assert not wavefront.frozen_steps(tree.device, n, rows) and wavefront.frozen_steps(tree.device, n - 1, rows)


@pytest.mark.parametrize("n", [3_000, 100_000])  # frozen, and too large to freeze
def test_every_step_has_its_time_split(scaled, n, monkeypatch):
    """stats.step_times (issue 57 item 4; scripts/gpu_check_device.py prints it): one entry per
    step in order, the tail last, each with the rays it walked, and their times adding up to the
    trace's kernel and sort totals."""
    v, tree = scaled
    monkeypatch.setattr(wavefront, "FROZEN_BACKENDS", ("llvm",))
    o, d = meshes.incoherent_rays(v, n, seed=3)
    st = tree.trace(o, d, mode="layer_sorted").stats
    assert st.frozen == (n == 3_000)
    assert len(st.step_times) == st.steps >= 2
    assert [t.rays for t in st.step_times] == st.active_per_step
    assert [t.tail for t in st.step_times] == [False] * (st.steps - 1) + [st.tail_rays > 0]
    assert all(t.trace_s >= 0 and t.kernel_s > 0 and t.sort_s >= 0 for t in st.step_times)
    assert sum(t.trace_s + t.kernel_s for t in st.step_times) == pytest.approx(st.time_traverse_s, rel=1e-9)
    assert sum(t.sort_s for t in st.step_times) == pytest.approx(st.time_sort_s, rel=1e-9, abs=1e-12)
