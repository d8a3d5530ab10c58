"""What Mitsuba's float32 surface code loses at extreme scales, repaired for our tracer (runtime/extreme_scale.py):
the face-normal table against Mitsuba's own normals where they are whole, and shadow rays rebuilt where they are
lost. (End to end: the stability suite's extreme_scales case.)"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

import layerbvh_mitsuba  # noqa: F401  (sets the variant, registers the integrator)
from layerbvh_mitsuba.runtime import extreme_scale
from layerbvh_mitsuba.runtime.adapter import SceneTracer
from layerbvh_mitsuba.runtime.scene_geometry import collect_geometry


def _scene(scale: float = 1.0):
    """Meshes of every kind the table must orient (a cube with vertex normals, a flipped
    rectangle, a flat-shaded cube, a flipped flat one) and an analytic sphere it must leave out."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "cube": {"type": "cube", "to_world": T().scale(scale).translate([-2, 0, 0])},
        "flat": {"type": "cube", "face_normals": True, "to_world": T().scale(scale).translate([2, 0, 0])},
        "flat_flipped": {"type": "cube", "face_normals": True, "flip_normals": True,
                         "to_world": T().scale(scale).translate([0, 2.5, 0]).scale(0.5)},
        "ball": {"type": "sphere", "to_world": T().scale(scale).translate([0, -2.5, 0])},
        "floor": {"type": "rectangle", "flip_normals": True,
                  "to_world": T().scale(scale).translate([0, 0, -2]).scale(6)},
    })


def _camera_rays(scale: float, n: int = 8192):
    """Rays from 8 scale-units in front of the scene towards points all over it."""
    rng = np.random.default_rng(5)
    target = np.stack([rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(-2, 1, n)])
    origin = np.array([[1.0], [2.0], [8.0]])
    d = target - origin
    d /= np.linalg.norm(d, axis=0)
    return mi.Ray3f(mi.Point3f(*(origin * scale).astype(np.float32)), mi.Vector3f(*d.astype(np.float32)))


def test_the_face_normal_table_is_mitsubas_normal_where_mitsubas_is_whole():
    """At scale 1 every mesh hit's row of the table (first[shape_index] + prim_index) is the normal
    Mitsuba computed, flipped shapes included; the sphere has no row. A table the repair reads at
    the wrong row, or with the wrong sign, fails here (at 1e12 Mitsuba's normal is lost: nothing to
    compare with)."""
    scene = _scene()
    table = extreme_scale.FaceNormals.build(scene, collect_geometry(scene).groups[0])
    ray = _camera_rays(1.0)
    pi = scene.ray_intersect_preliminary(ray)
    si = pi.compute_surface_interaction(ray)
    valid = np.array(si.is_valid())
    shapes = np.where(valid, np.array(pi.shape_index), 0)
    first = np.array(table.first)[shapes]
    rows = np.array(table.table).reshape(-1, 3)
    mesh = valid & (first != extreme_scale.NO_MESH)
    assert 0.5 < mesh.mean() < valid.mean(), "the rays must hit meshes and the sphere"
    got = rows[(first + np.array(si.prim_index))[mesh]]
    want = np.array(si.n).T[mesh]
    assert np.abs(got - want).max() < 1e-5
    flipped = [i for i, s in enumerate(scene.shapes()) if s.is_mesh() and s.has_flipped_normals()]
    assert np.isin(shapes[mesh], flipped).sum() > 100, "hits on the flipped shapes"


def test_a_scene_at_1e12_gets_mitsubas_unit_scale_surfaces_back():
    """At 1e12 Mitsuba's normals are lost (squared norms overflow); the repaired surface
    interaction equals the one at scale 1 (normal, shading frame, wi) on every hit, and a scene at
    scale 1 gets no table (it traces as before, kernel for kernel)."""
    out = {}
    for scale in (1.0, 1e12):
        scene = _scene(scale)
        tr = SceneTracer(scene, traversal="per_ray", count_work=False)
        assert (tr.normals is None) == (scale == 1.0)
        ray = _camera_rays(scale)
        pi = tr.intersect(ray, mi.Bool(True))
        lost = np.array(pi.compute_surface_interaction(ray, mi.RayFlags.All).n)
        si = tr.surface(pi, ray, mi.RayFlags.All)
        out[scale] = (np.array(pi.is_valid()), np.array(si.n), np.array(si.sh_frame.s), np.array(si.wi), lost)
    (v1, n1, s1, w1, _), (v12, n12, s12, w12, lost12) = out[1.0], out[1e12]
    assert (v1 == v12).all() and v1.mean() > 0.5
    mesh = v1 & (np.abs(np.linalg.norm(lost12, axis=0) - 1) > 0.5)
    assert mesh.sum() > 1000, "Mitsuba's normal must be lost at 1e12 (else this tests nothing)"
    for a, b in ((n1, n12), (s1, s12), (w1, w12)):
        assert np.abs(a[:, v1] - b[:, v1]).max() < 1e-4


def test_a_shadow_ray_past_float32_range_is_rebuilt():
    """Mitsuba's spawn_ray_to a point 4e19 away has no direction (the squared norm overflows);
    the rebuilt ray points at it with its length, and a ray Mitsuba gets whole is kept bit for bit."""
    si = mi.SurfaceInteraction3f()
    si.p, si.n = mi.Point3f(1e18, 2e18, -3e18), mi.Normal3f(0, 0, 1)
    target = mi.Point3f(4e19, -1e19, 2e19)
    assert not np.isfinite(np.array(si.spawn_ray_to(target).maxt)).all()
    ray = extreme_scale.spawn_ray_to(si, target)
    d = np.array(target, np.float64).ravel() - np.array(ray.o, np.float64).ravel()
    assert np.allclose(np.array(ray.d).ravel(), d / np.linalg.norm(d), atol=1e-6)
    assert np.isclose(float(np.array(ray.maxt).ravel()[0]), np.linalg.norm(d) * (1 - mi.math.ShadowEpsilon), rtol=1e-5)
    si.p = mi.Point3f(1, 2, -3)
    near = mi.Point3f(4, -1, 2)
    whole, again = si.spawn_ray_to(near), extreme_scale.spawn_ray_to(si, near)
    assert np.array_equal(np.array(whole.d), np.array(again.d))
    assert np.array_equal(np.array(whole.maxt), np.array(again.maxt))


def test_a_tiny_scene_offsets_its_rays_as_the_scene_at_unit_size():
    """Stock offsets a spawned ray by (1 + max|p|) x RayEpsilon, 9e-5 near the origin whatever the
    scene's size. In a scene under TINY_EXTENT ours offsets by (unit + max|p|) x RayEpsilon: the
    unit-size scene's ray, scaled by the power of two `unit`, bit for bit (origins and the shadow
    ray's length); a scene at unit size keeps stock's."""
    unit = 2.0 ** -40
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 1, (3, 64)).astype(np.float32)
    n = rng.normal(size=(3, 64))
    n = (n / np.linalg.norm(n, axis=0)).astype(np.float32)
    d = rng.normal(size=(3, 64))
    d = (d / np.linalg.norm(d, axis=0)).astype(np.float32)
    target = rng.uniform(-3, 3, (3, 64)).astype(np.float32)

    def interaction(k):
        si = mi.SurfaceInteraction3f()
        si.p, si.n = mi.Point3f(*(p * k)), mi.Normal3f(*n)
        return si
    big, small = interaction(1.0), interaction(unit)
    assert extreme_scale.tiny_unit(_scene(unit)) is not None and extreme_scale.tiny_unit(_scene()) is None
    want, got = big.spawn_ray(mi.Vector3f(*d)), extreme_scale.spawn_ray(small, mi.Vector3f(*d), unit)
    assert np.array_equal(np.array(got.o) / unit, np.array(want.o))
    want = big.spawn_ray_to(mi.Point3f(*target))
    got = extreme_scale.spawn_ray_to(small, mi.Point3f(*(target * unit)), unit)
    assert np.array_equal(np.array(got.o) / unit, np.array(want.o))
    assert np.allclose(np.array(got.maxt) / unit, np.array(want.maxt), rtol=1e-6)
    assert not np.allclose(np.array(small.spawn_ray(mi.Vector3f(*d)).o) / unit, np.array(want.o), atol=1e-3)
