"""Stock Mitsuba (Embree) ray queries over a bare triangle mesh or instanced meshes: the ground truth the engine is
checked against."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from layerbvh import MISS, from_numpy
from layerbvh_mitsuba.ab.render import use_variant


def scene_from_mesh(vertices: np.ndarray, faces: np.ndarray, robust: bool = False):
    """A Mitsuba scene holding one mesh with exactly these triangles (face i = primitive i)."""
    use_variant()
    props = {"type": "scene", "mesh": _mesh("mesh", vertices, faces)}
    if robust:
        props["embree_use_robust_intersections"] = True
    return mi.load_dict(props)


def _mesh(name: str, vertices: np.ndarray, faces: np.ndarray):
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.uint32)
    mesh = mi.Mesh(name, vertex_count=len(v), face_count=len(f), has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = from_numpy(mi.Float, v.reshape(-1))
    params["faces"] = from_numpy(mi.UInt32, f.reshape(-1))
    params.update()
    return mesh


def scene_from_instances(groups, instances):
    """A Mitsuba scene with one shapegroup per layerbvh.Group (one mesh each) and one instance
    per layerbvh.Instance (id `inst_<index>`), for Embree's own two-level traversal."""
    use_variant()
    props = {"type": "scene"}
    for g, grp in enumerate(groups):
        props[f"group_{g}"] = {"type": "shapegroup", "mesh": _mesh(f"mesh_{g}", grp.vertices, grp.faces)}
    for k, inst in enumerate(instances):
        m = np.eye(4)
        m[:3] = np.asarray(inst.to_world, np.float64)[:3]
        props[f"inst_{k}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": f"group_{inst.group}"},
                              "to_world": mi.ScalarTransform4f(m.tolist())}
    return mi.load_dict(props)


def intersect_instanced(scene, o: np.ndarray, d: np.ndarray):
    """Embree closest hits through instances as numpy: (t with inf for misses, instance index
    (from the id `inst_<index>`), prim inside the group; MISS for misses)."""
    pi = scene.ray_intersect_preliminary(rays(o, d))
    valid = pi.is_valid()
    inst = dr.full(mi.UInt32, MISS, dr.width(valid))
    for shape in scene.shapes():
        if shape.id().startswith("inst_"):
            inst = dr.select(valid & (pi.instance == shape), int(shape.id()[5:]), inst)
    t = dr.select(valid, pi.t, dr.inf)
    prim = dr.select(valid, pi.prim_index, mi.UInt32(MISS))
    dr.eval(t, inst, prim)
    return t.numpy(), inst.numpy(), prim.numpy()


def rays(o: np.ndarray, d: np.ndarray, tmax=None):
    ray = mi.Ray3f(mi.Point3f(*(from_numpy(mi.Float, np.asarray(o[:, c], np.float32)) for c in range(3))),
                   mi.Vector3f(*(from_numpy(mi.Float, np.asarray(d[:, c], np.float32)) for c in range(3))))
    if tmax is not None:
        ray.maxt = from_numpy(mi.Float, np.broadcast_to(np.asarray(tmax, np.float32), (len(o),)))
    return ray


def intersect(scene, o: np.ndarray, d: np.ndarray, tmax=None):
    """Embree closest hits as numpy: (t with inf for misses, prim with MISS for misses)."""
    if len(o) == 0:  # Dr.Jit cannot run a query on empty arrays
        return np.zeros(0, np.float32), np.zeros(0, np.uint32)
    pi = scene.ray_intersect_preliminary(rays(o, d, tmax))
    valid = pi.is_valid()
    t = dr.select(valid, pi.t, dr.inf)
    prim = dr.select(valid, pi.prim_index, mi.UInt32(MISS))
    dr.eval(t, prim)
    return t.numpy(), prim.numpy()


def occluded(scene, o: np.ndarray, d: np.ndarray, tmax) -> np.ndarray:
    if len(o) == 0:
        return np.zeros(0, bool)
    return scene.ray_test(rays(o, d, tmax)).numpy()



def exact_t(v: np.ndarray, f: np.ndarray, prim: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance along each ray to the plane of triangle `prim`, in float64 (Moeller-Trumbore)."""
    a, b, c = (v[f[prim, k]].astype(np.float64) for k in range(3))
    e1, e2, tv = b - a, c - a, o.astype(np.float64) - a
    pv = np.cross(d.astype(np.float64), e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.einsum("ij,ij->i", e2, np.cross(tv, e1)) / np.einsum("ij,ij->i", e1, pv)


def disagreements(v: np.ndarray, f: np.ndarray, o: np.ndarray, d: np.ndarray, prim_a: np.ndarray,
                  prim_b: np.ndarray) -> dict:
    """Where two closest-hit answers differ: `hit_miss` (one hits, one misses), `ties` (other
    triangle, but both at the same distance in float64 up to float32 resolution of the coordinates:
    shared edges, coplanar overlaps, where either answer is right) and `other` (another triangle at
    another distance: a real disagreement). `real` = hit_miss + other; `rays` with indices in `real_idx`."""
    differ = np.nonzero(prim_a != prim_b)[0]
    hit_a, hit_b = prim_a[differ] != MISS, prim_b[differ] != MISS
    both = differ[hit_a & hit_b]
    t_a = exact_t(v, f, prim_a[both], o[both], d[both])
    t_b = exact_t(v, f, prim_b[both], o[both], d[both])
    # Below 8 ulps of the coordinates involved, which of two (near-)coplanar triangles is nearer
    # is decided by rounding, in Embree as in ours.
    p = o[both].astype(np.float64) + t_a[:, None] * d[both]
    scale = np.maximum(np.abs(o[both]).max(1, initial=0), np.abs(p).max(1, initial=0))
    scale /= np.maximum(np.linalg.norm(d[both].astype(np.float64), axis=1), 1e-30)
    tie = np.abs(t_a - t_b) <= 8 * 2.0 ** -24 * scale
    real_idx = np.sort(np.concatenate([differ[hit_a != hit_b], both[~tie]]))
    return {"rays": len(prim_a), "hit_miss": int((hit_a != hit_b).sum()), "ties": int(tie.sum()),
            "other": int((~tie).sum()), "real": len(real_idx), "real_idx": real_idx, "tie_idx": both[tie]}


def exact_hit(v: np.ndarray, f: np.ndarray, prim: np.ndarray, o: np.ndarray, d: np.ndarray, eps: float = 1e-9):
    """Does each ray really hit triangle `prim`, for the exact float32 inputs? Float64
    Moeller-Trumbore: (status, t) with status 1 (hit), 0 (miss) or -1 (undecidable: within `eps`
    of an edge in barycentric terms, the ray lies in the triangle's plane, or starts on the
    triangle). Misses (prim = MISS) get status 0 and t = inf."""
    status = np.zeros(len(prim), np.int8)
    t = np.full(len(prim), np.inf)
    has = prim != MISS
    if not has.any():
        return status, t
    a, b, c = (v[f[prim[has], k]].astype(np.float64) for k in range(3))
    o64, d64 = o[has].astype(np.float64), d[has].astype(np.float64)
    e1, e2, tv = b - a, c - a, o64 - a
    pv = np.cross(d64, e2)
    det = np.einsum("ij,ij->i", e1, pv)
    qv = np.cross(tv, e1)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d64, axis=1)
    parallel = np.abs(det) <= 1e-12 * scale
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("ij,ij->i", tv, pv) / det
        w = np.einsum("ij,ij->i", d64, qv) / det
        tt = np.einsum("ij,ij->i", e2, qv) / det
    bary = np.stack([1 - u - w, u, w])
    # A ray starting on the triangle (t = 0 up to rounding) may be called a hit or a miss.
    size = (np.abs(tv).max(1) + np.abs(e1).max(1) + np.abs(e2).max(1)) / np.linalg.norm(d64, axis=1)
    at_origin = np.abs(tt) <= eps * size
    inside = (bary > eps).all(0) & (tt > 0) & ~at_origin
    outside = ((bary < -eps).any(0) | (tt < 0)) & ~at_origin
    # Parallel: in the plane (undecidable) or beside it (a miss).
    n = np.cross(e1, e2)
    off_plane = np.abs(np.einsum("ij,ij->i", n, tv)) > 1e-12 * np.linalg.norm(n, axis=1) * (np.abs(tv).max(1) + 1)
    st = np.where(parallel, np.where(off_plane, 0, -1), np.where(inside, 1, np.where(outside, 0, -1)))
    status[has] = st
    t[has] = np.where(st == 1, tt, np.inf)
    return status, t


def wrong_answers(v, f, o, d, answers: dict, rays: np.ndarray) -> dict:
    """For each named answer (prim per ray), how many of `rays` are wrong for the exact float32
    geometry: the triangle is not really hit, or another answer's triangle is really hit and
    nearer (by more than 1e-9 relative). Undecidable cases count for nobody."""
    sub_o, sub_d = o[rays], d[rays]
    exact = {k: exact_hit(v, f, p[rays], sub_o, sub_d) for k, p in answers.items()}
    nearest = np.min([np.where(st == 1, t, np.inf) for st, t in exact.values()], axis=0)
    out = {}
    for k, (st, t) in exact.items():
        claims_miss = answers[k][rays] == MISS
        fake = (st == 0) & ~claims_miss
        farther = np.isfinite(nearest) & (np.where(st == 1, t, np.inf) > nearest * (1 + 1e-9)) & (st != -1)
        out[k] = int((fake | farther).sum())
    return out
