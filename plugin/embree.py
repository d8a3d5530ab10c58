"""Stock Mitsuba (Embree) ray queries over a bare triangle mesh: the ground truth the engine is checked against."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def ensure_variant(variant: str = "llvm_ad_rgb") -> None:
    if mi.variant() is None:
        mi.set_variant(variant)


def scene_from_mesh(vertices: np.ndarray, faces: np.ndarray, robust: bool = False):
    """A Mitsuba scene holding one mesh with exactly these triangles (face i = primitive i)."""
    ensure_variant()
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.uint32)
    mesh = mi.Mesh("mesh", vertex_count=len(v), face_count=len(f),
                   has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.reshape(-1))
    params["faces"] = mi.UInt32(f.reshape(-1))
    params.update()
    props = {"type": "scene", "mesh": mesh}
    if robust:
        props["embree_use_robust_intersections"] = True
    return mi.load_dict(props)


def rays(o: np.ndarray, d: np.ndarray, tmax=None):
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(o[:, c], np.float32)) for c in range(3))),
                   mi.Vector3f(*(mi.Float(np.ascontiguousarray(d[:, c], np.float32)) for c in range(3))))
    if tmax is not None:
        ray.maxt = mi.Float(np.broadcast_to(np.asarray(tmax, np.float32), (len(o),)).copy())
    return ray


def intersect(scene, o: np.ndarray, d: np.ndarray, tmax=None):
    """Embree closest hits as numpy: (t with inf for misses, prim with 0xFFFFFFFF for misses)."""
    pi = scene.ray_intersect_preliminary(rays(o, d, tmax))
    valid = pi.is_valid()
    t = dr.select(valid, pi.t, dr.inf)
    prim = dr.select(valid, pi.prim_index, mi.UInt32(0xFFFFFFFF))
    dr.eval(t, prim)
    return t.numpy(), prim.numpy()


def occluded(scene, o: np.ndarray, d: np.ndarray, tmax) -> np.ndarray:
    return scene.ray_test(rays(o, d, tmax)).numpy()

