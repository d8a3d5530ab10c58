"""Render passes and trace calls larger than one ray batch: inputs of width 1 broadcast to every
ray, batches return what one unbatched call returns, and renders above 2^20 rays per pass match
stock Mitsuba (the sizes users render, not only 32x32)."""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import layerbvh
from layerbvh.backend import from_numpy
from layerbvh_mitsuba import testing

SCENES = Path(__file__).resolve().parents[2] / "scenes"
N_RAYS = 10_000
SMALL_BATCH = 4096  # 3 batches for N_RAYS


@pytest.fixture(scope="module")
def bunny_bvhs(bunny):
    v, f = bunny
    whole = layerbvh.build(v, f, treelet_height=4, backend="llvm")
    batched = layerbvh.build(v, f, treelet_height=4, backend="llvm", batch_rays=SMALL_BATCH)
    return v, whole, batched


def _columns(a: np.ndarray):
    return mi.Vector3f(*(from_numpy(mi.Float, a[:, c]) for c in range(3)))  # (aligned: backend.ALIGN)


def _camera_like(v):
    """Rays from one eye point (as a pinhole camera's), toward random points of the mesh's box."""
    rng = np.random.default_rng(4)
    lo, hi = v.min(0), v.max(0)
    eye = ((lo + hi) / 2 + np.array([0, 0, 2.5]) * (hi - lo).max()).astype(np.float32)
    target = rng.uniform(lo, hi, (N_RAYS, 3)).astype(np.float32)
    return eye, (target - eye).astype(np.float32)


# Each case: (origins, directions, tmax) as the caller passes them, built from eye/d/tmax arrays.
INPUTS = {
    "drjit, tmax width 1": lambda eye, d, t: (_columns(np.broadcast_to(eye, d.shape)), _columns(d), mi.Float(t[0])),
    "drjit, origin width 1": lambda eye, d, t: (mi.Point3f(*(mi.Float(x) for x in eye)), _columns(d),
                                                from_numpy(mi.Float, t)),
    "drjit, all width n": lambda eye, d, t: (_columns(np.broadcast_to(eye, d.shape)), _columns(d),
                                             from_numpy(mi.Float, t)),
    "mixed widths": lambda eye, d, t: (mi.Point3f(mi.Float(eye[0]),
                                                  from_numpy(mi.Float, np.full(len(d), eye[1], np.float32)),
                                                  mi.Float(eye[2])),
                                       _columns(d), mi.Float(t[0])),
    "numpy point, python tmax": lambda eye, d, t: (eye, d, float(t[0])),
}


@pytest.mark.parametrize("mode", layerbvh.MODES)
@pytest.mark.parametrize("case", sorted(INPUTS))
def test_broadcast_inputs_in_batches_match_one_unbatched_call(bunny_bvhs, mode, case):
    v, whole, batched = bunny_bvhs
    eye, d = _camera_like(v)
    # One finite tmax for every ray (what the width-1 inputs carry), short enough to cut some hits
    # (t is in units of |d|, eye to target: hits lie at t = 0.73..1.27).
    tmax = np.full(N_RAYS, 0.9, np.float32)
    ref = whole.trace(np.broadcast_to(eye, d.shape), d, tmax, mode="per_ray")
    assert 0.2 < np.mean(ref.prim != layerbvh.MISS) < 0.9, "the rays should both hit and miss"
    o_in, d_in, t_in = INPUTS[case](eye, d, tmax)
    hits = batched.trace(o_in, d_in, t_in, mode=mode)
    assert hits.stats.batches == 3
    for name in ("t", "prim", "u", "v"):
        got = getattr(hits, name)
        got = got.numpy() if dr.is_array_v(got) else got
        assert np.array_equal(got, getattr(ref, name)), f"{case}: {name} differs from the unbatched trace"
    # Any hit, with a tmax that ends before some hits: the same answer as unbatched, full width.
    occ_ref = whole.occluded(np.broadcast_to(eye, d.shape), d, tmax, mode="per_ray").occluded
    occ = batched.occluded(o_in, d_in, t_in, mode=mode).occluded
    occ = occ.numpy() if dr.is_array_v(occ) else occ
    assert occ.shape == (N_RAYS,) and np.array_equal(occ, occ_ref), f"{case}: occlusion differs"


def test_an_input_of_another_width_is_refused_by_name(bunny_bvhs):
    v, _, batched = bunny_bvhs
    eye, d = _camera_like(v)
    with pytest.raises(ValueError, match=r"tmax has 7 entries, origins\[0\] has 10000"):
        batched.trace(_columns(np.broadcast_to(eye, d.shape)), _columns(d),
                      from_numpy(mi.Float, np.ones(7, np.float32)))
    with pytest.raises(ValueError, match=r"origins\[1\] has 3 entries, directions\[0\] has 10000"):
        batched.occluded(mi.Point3f(mi.Float(0), mi.Float([0, 1, 2]), mi.Float(0)), _columns(d)).occluded
    with pytest.raises(ValueError, match=r"directions must have shape \(N, 3\), got \(4, 2\)"):
        batched.trace(np.zeros((4, 3)), np.ones((4, 2)))


@pytest.mark.parametrize("traversal", ["per_ray", "layer_sorted"])
def test_integrator_with_passes_larger_than_a_batch_matches_stock(traversal, layer_path_ran):
    # 64x64 at 4 spp = 16,384 camera rays per pass: four batches of 4,096. The layer mode at
    # treelet height 3 (cbox: 6 treelets; one at the default 8, where it could not differ from per_ray).
    layer = {"treelet_height": 3} if traversal == "layer_sorted" else {}
    r = testing.assert_matches_stock(SCENES / "cbox.xml", spp=4, res=(64, 64), seed=2, traversal=traversal,
                                     ours_props={"batch_rays": SMALL_BATCH, **layer})
    if layer:
        layer_path_ran(r.ours_stats, traversal)


def test_a_real_size_render_matches_stock(layer_path_ran):
    """512x512 at 8 spp in layer_sorted: 2,097,152 camera rays per pass, two batches of the default
    size (2^20) per query, at treelet height 3 (cbox: 6 treelets). (per_ray renders in one
    megakernel, which traces inline and has no batches: its 64x64 case above covers it.)
    Measured over seeds 1-3: 0-3 pixels of 262,144 over 1e-3, mean |diff| <= 6.9e-7 x mean."""
    assert 512 * 512 * 8 > layerbvh.BATCH_RAYS, "more than one batch per pass"
    r = testing.assert_matches_stock(SCENES / "cbox.xml", spp=8, res=(512, 512), seed=1, traversal="layer_sorted",
                                     ours_props={"treelet_height": 3}, max_depth=4)
    layer_path_ran(r.ours_stats, "layer_sorted")
    assert r.ours_stats.rays >= 512 * 512 * 8
