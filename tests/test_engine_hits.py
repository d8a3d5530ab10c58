"""Closest hits and occlusion: every traversal mode against each other and against Embree."""
from __future__ import annotations

import numpy as np
import pytest

import layerbvh
from layerbvh_mitsuba import embree
from layerbvh_mitsuba.bench import meshes

N_RAYS = 40_000


def _rays(v, kind, n=N_RAYS, seed=7):
    return meshes.camera_rays(v, n, seed) if kind == "camera" else meshes.incoherent_rays(v, n, seed)


def _report(mask, *cols, names=()):
    idx = np.nonzero(mask)[0][:8]
    return "\n".join(f"ray {i}: " + ", ".join(f"{n}={c[i]}" for n, c in zip(names, cols)) for i in idx)


@pytest.mark.parametrize("mesh_name", ["bunny", "procedural"])
@pytest.mark.parametrize("kind", ["camera", "incoherent"])
def test_modes_agree_exactly(request, mesh_name, kind):
    v, f = request.getfixturevalue(mesh_name)
    o, d = _rays(v, kind)
    bvhs = {tail: layerbvh.build(v, f, treelet_height=4, tail_rays=tail, tail_fraction=0.25 if tail else 0.0)
            for tail in (0, 2048)}
    ref = bvhs[0].trace(o, d, mode="per_ray")
    assert np.mean(ref.prim != layerbvh.MISS) > 0.2, "test rays should mostly hit"
    for mode, tail in (("layer_sorted", 0), ("layer_sorted", 2048), ("layer_unsorted", 0)):
        h = bvhs[tail].trace(o, d, mode=mode)  # tail 0: every ray stays in the wavefront steps to the end
        assert (h.stats.tail_rays > 0) == (tail > 0)
        bad = (h.prim != ref.prim) | (h.t != ref.t) | (h.u != ref.u) | (h.v != ref.v)
        assert not bad.any(), f"{mode} differs from per_ray on {bad.sum()} rays:\n" + \
            _report(bad, h.prim, ref.prim, h.t, ref.t, names=("prim", "prim_per_ray", "t", "t_per_ray"))
        # Same traversal order, so the same work: a check of the statistics, not only the hits.
        assert h.stats.inner_nodes == ref.stats.inner_nodes
        assert h.stats.triangles == ref.stats.triangles


@pytest.mark.parametrize("mesh_name", ["bunny", "procedural"])
@pytest.mark.parametrize("kind", ["camera", "incoherent"])
def test_closest_hit_matches_embree(request, mesh_name, kind):
    v, f = request.getfixturevalue(mesh_name)
    o, d = _rays(v, kind)
    scene = embree.scene_from_mesh(v, f)
    t_e, p_e = embree.intersect(scene, o, d)
    h = layerbvh.build(v, f, treelet_height=4).trace(o, d, mode="layer_sorted")
    hit_e, hit_o = p_e != layerbvh.MISS, h.prim != layerbvh.MISS
    n = len(o)
    disagree = hit_e != hit_o
    assert disagree.sum() <= 1e-4 * n, f"hit/miss differs on {disagree.sum()} of {n} rays:\n" + \
        _report(disagree, p_e, h.prim, t_e, h.t, names=("embree_prim", "prim", "embree_t", "t"))
    both = hit_e & hit_o
    other_tri = both & (p_e != h.prim)
    assert other_tri.sum() <= 1e-4 * both.sum(), f"different triangle on {other_tri.sum()} rays:\n" + \
        _report(other_tri, p_e, h.prim, t_e, h.t, names=("embree_prim", "prim", "embree_t", "t"))
    same = both & ~other_tri
    dt = np.abs(h.t[same] - t_e[same])
    worst = int(np.argmax(dt / t_e[same])) if same.any() else 0
    assert np.all(dt <= 1e-4 * t_e[same]), f"|dt| too large, worst ray {np.nonzero(same)[0][worst]}: " \
        f"t={h.t[same][worst]} embree={t_e[same][worst]}"
    # Barycentrics reproduce the hit point.
    tri = v[f[h.prim[same]]]
    p_bary = (1 - h.u[same] - h.v[same])[:, None] * tri[:, 0] + h.u[same][:, None] * tri[:, 1] + \
        h.v[same][:, None] * tri[:, 2]
    p_ray = o[same] + h.t[same][:, None] * d[same]
    scale = np.abs(p_ray).max() + 1
    assert np.max(np.abs(p_bary - p_ray)) <= 1e-4 * scale


@pytest.mark.parametrize("mode", layerbvh.MODES)
def test_occluded_matches_embree(bunny, mode):
    v, f = bunny
    o, d = _rays(v, "incoherent", n=20_000)
    rng = np.random.default_rng(2)
    tmax = (rng.random(len(o)) * 0.2).astype(np.float32)
    scene = embree.scene_from_mesh(v, f)
    occ_e = embree.occluded(scene, o, d, tmax)
    occ = layerbvh.build(v, f).occluded(o, d, tmax, mode=mode).occluded
    assert 0.05 < occ.mean() < 0.95, "tmax should make the test non-trivial"
    bad = occ != occ_e
    assert bad.sum() <= 1e-4 * len(o), f"occluded differs from Embree on {bad.sum()} rays"
    # Any-hit agrees with the closest hit's distance too.
    h = layerbvh.build(v, f).trace(o, d, mode=mode)
    assert np.array_equal(occ, h.t < tmax)


def test_dr_jit_arrays_in_and_out(bunny):
    """Mitsuba's llvm_ad_rgb arrays go in and come back as Dr.Jit arrays with the same hits."""
    import drjit as dr
    import mitsuba as mi
    v, f = bunny
    o, d = _rays(v, "incoherent", n=4000)
    bvh = layerbvh.build(v, f)
    ref = bvh.trace(o, d)
    oj = mi.Point3f(*(mi.Float(o[:, c]) for c in range(3)))
    dj = mi.Vector3f(*(mi.Float(d[:, c]) for c in range(3)))
    h = bvh.trace(oj, dj, mode="layer_sorted")
    assert dr.is_array_v(h.t) and dr.is_array_v(h.prim)
    assert np.array_equal(np.array(h.prim), ref.prim)
    assert np.array_equal(np.array(h.t), ref.t)
    occ = bvh.occluded(oj, dj, mi.Float(np.full(len(o), 0.1, np.float32))).occluded
    assert np.array_equal(np.array(occ), ref.t < 0.1)
