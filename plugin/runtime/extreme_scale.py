"""What Mitsuba's float32 surface code loses at extreme scales, repaired for our tracer (issue 56 item 2): geometric
normals (a table of the scene's mesh face normals), the shadow rays of emitter samples whose distance overflows, and
spawned rays' offsets in a tiny scene."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from layerbvh import from_numpy

# Mitsuba's mesh surface interaction takes n = normalize(cross(p1 - p0, p2 - p0)) in float32. The
# squared norm of the cross product grows as |edge|^4: past FLT_MAX (3.4e38) once edges pass ~4e9,
# under the smallest normal float (1.2e-38) once they fall under ~1e-10. Either way the normal
# comes out (0, 0, 0) or NaN, a spawned ray gets no offset and hits the surface it leaves
# (measured on scenes/stability/scaled.xml: 67% of the floor's hits at scale 1e9, all at 1e10;
# stock loses 8-14% of the image there, tools/stability/scale_cases.py). A scene whose triangles
# come within SQUARED_MARGIN of either end gets the table; every other scene traces as before,
# kernel for kernel (the switch is taken in Python).
SQUARED_MARGIN = 1e3
# Likewise a shadow ray (Interaction::spawn_ray_to) normalises the vector to its target: past ~1.8e19
# its squared norm overflows and the ray comes out with no direction (a constant sky's samples lie
# 2 bounding-sphere radii away: scaled.xml at 1e18). A scene whose bounding box reaches FAR_EXTENT
# (or fits in 1 / FAR_EXTENT) gets robust shadow rays.
FAR_EXTENT = 2.0 ** 55
# A spawned ray leaves its surface offset by (1 + max|p|) x RayEpsilon (Interaction::offset_p): an
# absolute 9e-5 near the origin, which in a scene smaller than TINY_EXTENT passes a tenth of the
# scene's size (scaled.xml at 1e-6: 47% of the pixels off its unit-scale render, the same on both
# sides). There ours offsets by (unit + max|p|) x RayEpsilon, `unit` the power of two nearest the
# scene's extent: exactly the offset of the scene rescaled to unit size, so its paths are the
# unit-scale scene's (ab/referee.py renders that scene with stock).
TINY_EXTENT = 1e-3
NO_MESH = 0xFFFFFFFF  # `first` of a scene shape that is not one of the world's meshes


def _face_cross(group) -> np.ndarray:
    """(p1 - p0) x (p2 - p0) of every face of `group`, in float64 from its float32 vertices."""
    v, f = group.vertices.astype(np.float64), group.faces
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]) if len(f) else np.zeros((0, 3))


def _lost_in_float32(cross64: np.ndarray) -> bool:
    """Whether some triangle's squared cross product leaves float32's normal range (with margin)."""
    sq = np.einsum("ij,ij->i", cross64, cross64)
    sq = sq[sq > 0]  # degenerate triangles have no normal on either side
    info = np.finfo(np.float32)
    return bool(sq.size) and bool((sq.max() > float(info.max) / SQUARED_MARGIN)
                                  or (sq.min() < float(info.tiny) * SQUARED_MARGIN))


def _unit(v):
    """A power of two that brings the largest component of `v` near 1 where its squared norm
    would leave float32's range (exact: the direction keeps its bits)."""
    big = dr.maximum(dr.maximum(dr.abs(v.x), dr.abs(v.y)), dr.abs(v.z))
    return dr.select(big > 2.0 ** 60, 2.0 ** -64, dr.select(big < 2.0 ** -60, 2.0 ** 64, 1.0))


def scene_box(scene) -> tuple[float, float] | None:
    """(largest |coordinate|, diagonal) of `scene`'s bounding box; None for an empty or infinite one."""
    box = scene.bbox()
    lo, hi = np.array(box.min, np.float64).ravel(), np.array(box.max, np.float64).ravel()
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(hi < lo):
        return None
    return float(max(np.abs(lo).max(), np.abs(hi).max())), float(np.linalg.norm(hi - lo))


def far_scene(scene) -> bool:
    """Whether `scene`'s bounding box reaches FAR_EXTENT, or its diagonal is under 1 / FAR_EXTENT."""
    box = scene_box(scene)
    return box is not None and (box[0] >= FAR_EXTENT or box[1] <= 1 / FAR_EXTENT)


def unit_of(extent: float) -> float:
    """The power of two nearest `extent` (in log scale): a scene's length unit, exact to scale by."""
    return 2.0 ** round(np.log2(extent))


def tiny_unit(scene) -> float | None:
    """unit_of `scene`'s bounding-box diagonal where it is under TINY_EXTENT."""
    box = scene_box(scene)
    return unit_of(box[1]) if box is not None and 0 < box[1] < TINY_EXTENT else None


def _offset(ref, d, unit: float):
    """Interaction::offset_p with the offset's floor `unit` instead of 1."""
    p = ref.p
    mag = (unit + dr.maximum(dr.maximum(dr.abs(p.x), dr.abs(p.y)), dr.abs(p.z))) * mi.math.RayEpsilon
    return dr.fma(dr.mulsign(mag, dr.dot(ref.n, d)), ref.n, p)


def spawn_ray(ref, d, unit: float):
    """`ref.spawn_ray(d)` with the offset of a scene `unit` times unit size (tiny_unit)."""
    return mi.Ray3f(_offset(ref, d, unit), d, dr.largest(mi.Float), ref.time, ref.wavelengths)


def spawn_ray_to(ref, p, unit: float | None = None):
    """Mitsuba's `ref.spawn_ray_to(p)` (its origin, offset off the surface; with `unit`, the offset
    of a tiny scene, see spawn_ray), with the direction and length taken in a power-of-two unit
    wherever Mitsuba's came out lost (no direction, or an infinite length): the same ray where
    Mitsuba's is whole."""
    ray = ref.spawn_ray_to(p)
    if unit is not None:
        o = _offset(ref, p - ref.p, unit)
        d = p - o
        dist = dr.norm(d)
        ray = mi.Ray3f(o, d / dist, dist * (1 - mi.math.ShadowEpsilon), ref.time, ref.wavelengths)
    lost = ~(dr.isfinite(ray.maxt) & (dr.squared_norm(ray.d) > 0.5))
    d = p - ray.o
    unit = _unit(d)
    dist = dr.norm(d * unit)
    ray.d = dr.select(lost, d * unit / dist, ray.d)
    ray.maxt = dr.select(lost, dist / unit * (1 - mi.math.ShadowEpsilon), ray.maxt)
    return ray


class FaceNormals:
    """Unit geometric normals of the world's mesh faces, as Mitsuba orients them (its vertex order,
    negated for a shape with flip_normals), computed in float64.

    first   UInt32 per scene shape (scene.shapes() order): its first row in `table`, NO_MESH for a
            shape that is not among the world's meshes (analytic shapes, instances)
    table   Float, 3 per face: row first[shape] + face is that face's normal
    Instanced meshes are left as Mitsuba computes them (in their group's object space, whose scale
    is the group's own)."""

    def __init__(self, first: np.ndarray, table: np.ndarray):
        self.first = from_numpy(mi.UInt32, first.astype(np.uint32))
        self.table = from_numpy(mi.Float, table.astype(np.float32).ravel())

    @classmethod
    def needed(cls, scene, group) -> "FaceNormals | None":
        """The table for `group` (the scene's own meshes, scene_geometry.MeshGroup), or None where
        every face's float32 normal is in range."""
        cross = _face_cross(group)
        return cls.build(scene, group, cross) if len(cross) and _lost_in_float32(cross) else None

    @classmethod
    def build(cls, scene, group, cross=None) -> "FaceNormals":
        """The table for `group`, whether needed or not (`cross`: its faces' cross products)."""
        cross = _face_cross(group) if cross is None else cross
        shapes = scene.shapes()
        counts = np.zeros(len(shapes), np.int64)
        np.maximum.at(counts, group.tri_shape.astype(np.int64), group.tri_local.astype(np.int64) + 1)
        first = np.where(counts > 0, np.cumsum(counts) - counts, NO_MESH)
        norm = np.linalg.norm(cross, axis=1, keepdims=True)
        unit = np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)
        flip = np.array([-1.0 if s.is_mesh() and s.has_flipped_normals() else 1.0 for s in shapes])
        table = np.zeros((int(counts.sum()), 3))
        table[first[group.tri_shape] + group.tri_local] = unit * flip[group.tri_shape, None]
        return cls(first, table)

    def repair(self, si, pi, ray, active):
        """`si` with a geometric normal (and the shading frame, wi and the surface's tangents where
        Mitsuba derived them from it) wherever Mitsuba's came out without one."""
        lost = active & si.is_valid() & ~(dr.squared_norm(si.n) > 0.5)  # (0, 0, 0) or NaN
        if hasattr(pi, "instance"):
            lost &= pi.instance == None  # noqa: E711  (object space: the group's own scale)
        first = dr.gather(mi.UInt32, self.first, pi.shape_index, lost)
        lost &= first != NO_MESH
        n = dr.gather(mi.Vector3f, self.table, first + pi.prim_index, lost)
        si.n = dr.select(lost, n, si.n)
        # Tangents: Mitsuba takes coordinate_system(n) for a mesh without UVs, lost with n.
        tangents_lost = lost & ~(dr.all(dr.isfinite(si.dp_du) & dr.isfinite(si.dp_dv)) & dr.any(si.dp_du != 0))
        frame = mi.Frame3f(n)
        si.dp_du = dr.select(tangents_lost, frame.s, si.dp_du)
        si.dp_dv = dr.select(tangents_lost, frame.t, si.dp_dv)
        # Shading frame: the interpolated vertex normal where the mesh has one (in range), else n;
        # s by Gram-Schmidt of dp_du against it, as SurfaceInteraction::initialize_sh_frame, with
        # dp_du in a power-of-two unit (its squared norm overflows where n's did: edges of 1e19).
        sh_n = dr.select(~(dr.squared_norm(si.sh_frame.n) > 0.5), n, si.sh_frame.n)
        frame_lost = lost & ~((dr.abs(dr.squared_norm(si.sh_frame.s) - 1) < 1e-3)
                              & (dr.abs(dr.dot(si.sh_frame.n, sh_n) - 1) < 1e-3))
        du = si.dp_du * _unit(si.dp_du)
        s = dr.normalize(du - sh_n * dr.dot(sh_n, du))
        si.sh_frame = dr.select(frame_lost, mi.Frame3f(s, dr.cross(sh_n, s), sh_n), si.sh_frame)
        si.wi = dr.select(lost, si.to_local(-ray.d), si.wi)
        return si
