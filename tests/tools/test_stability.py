"""The stability suite (layerbvh_mitsuba.tools.stability.cases): every case passes its stated rule, and the checks
catch what they are meant to catch."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh_mitsuba.tools.stability import cases as sc, mesh_cases, scale_cases


@pytest.mark.parametrize("name", list(sc.CASES))
def test_case(name):
    r = sc.run_case(name)
    assert r.nonfinite == 0, f"{name}: {r.nonfinite} NaN/Inf values; {r.criterion}"
    assert r.passed, f"{name}: {r.criterion} ({r.notes})"
    # A case that tried nothing would pass its rule: ray cases trace at least 1,000 rays (the
    # floor of _n), image cases render at least 8x8 pixels.
    assert r.tried >= (1000 if r.level == "rays" else 64), f"{name}: tried only {r.tried}"
    if name == "extreme_scales":  # its rule's parts (scale_cases.extreme_scales)
        assert r.figures["steps_per_query"] > 1, r.criterion
        assert abs(r.figures["control_rel"]) > scale_cases.TOLERANCE, f"the negative control passed: {r.criterion}"
    elif r.level == "image":  # the image rule's parts, as measured (the rule itself is in r.passed)
        assert r.figures["steps_per_query"] > 1 and r.figures["treelets"] > 1, r.criterion
        assert r.figures["control_frac"] < 0.99, f"{name}: the negative control passed: {r.criterion}"


def test_leak_count_catches_cracks():
    """Negative control for the watertightness case: shrink every triangle of the closed cube by
    1e-4 about its centroid (cracks along every edge) and the same rays must leak."""
    rng = np.random.default_rng(0)
    _, v, f = mesh_cases.closed_meshes()[1]
    o, d, dist = mesh_cases.edge_rays(v, f, 1.0, 0.0, 1, rng)
    tri = v[f]
    shrunk = (tri - tri.mean(1, keepdims=True)) * (1 - 1e-4) + tri.mean(1, keepdims=True)
    cracked_v, cracked_f = shrunk.reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3)
    whole = layerbvh.build(v.astype(np.float32), f).trace(o, d)
    cracked = layerbvh.build(cracked_v.astype(np.float32), cracked_f).trace(o, d)
    assert mesh_cases.leaks(whole.prim, whole.t, dist, 1.0) == 0
    assert mesh_cases.leaks(cracked.prim, cracked.t, dist, 1.0) > 0.3 * len(o)


def test_exact_check_names_the_wrong_side():
    """embree.wrong_answers: an answer naming a triangle the ray misses, or a farther one, is wrong."""
    from layerbvh_mitsuba.ab import embree
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float64)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    o = np.array([[0.2, 0.2, 2.0], [0.9, 0.9, 2.0]], np.float32)
    d = np.array([[0, 0, -1], [0, 0, -1]], np.float32)
    near, far, miss = np.uint32(1), np.uint32(0), np.uint32(layerbvh.MISS)
    answers = {"right": np.array([near, miss]), "farther": np.array([far, miss]), "fake": np.array([near, near])}
    wrong = embree.wrong_answers(v, f, o, d, answers, np.array([0, 1]))
    assert wrong == {"right": 0, "farther": 1, "fake": 1}


def test_the_scale_referee_names_the_side_that_matches():
    """scale_cases.which_matches: within the tolerance of the referee's mean, finite, is a match."""
    row = {"ours_rel": 0.004, "stock_rel": -0.13, "ours_nonfinite": 0, "stock_nonfinite": 0}
    assert scale_cases.which_matches(row) == "ours"
    assert scale_cases.which_matches({**row, "ours_rel": -0.011}) == "neither"
    assert scale_cases.which_matches({**row, "stock_rel": 0.009}) == "both"
    assert scale_cases.which_matches({**row, "ours_nonfinite": 1, "stock_rel": 0.0}) == "stock"
