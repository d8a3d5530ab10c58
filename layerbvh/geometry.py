"""Ray set-up (world and instance object space), the conservative two-child slab test and the watertight ray/triangle
test (Dr.Jit)."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .layout import (FAR_COORD, INST_FLOATS, INST_ROOT, INST_TO_OBJECT, NODE_BOX_HI, NODE_BOX_LO, NODE_FLOATS,
                     NODE_LINK, TRI_FACE, TRI_FLOATS, TRI_NORMAL, TRI_VERTEX, NodeFormat)

# Ize 2013: scaling a box's far distance by 1 + 2*gamma(3) makes the float slab test conservative.
_GAMMA3 = 3 * 2.0 ** -24 / (1 - 3 * 2.0 ** -24)
FAR_SCALE = 1.0 + 2.0 * _GAMMA3
# Direction components below this are replaced by it (sign kept), so (lo - o) * inv_d is never
# 0 * inf = NaN for a ray whose origin lies in a slab plane (Embree does the same).
MIN_RCP_INPUT = 1e-18
# Bound on a float edge function's error in units of m(P) m(Q) (see hit_triangle): 16 ulps.
EDGE_ERR = 16 * 2.0 ** -24
# An edge function multiplies two vertex coordinates taken relative to the ray origin: past ~2^63
# the product overflows float32 (FLT_MAX ~ 2^128) and the triangle is lost (a scene scaled by 1e18
# has its floor's corners at 1e19: issue 56). Where a triangle's relative coordinates pass
# layout.FAR_COORD they are taken in units of 1 / FAR_UNIT, a power of two: every product keeps its
# bits, so the test decides as it would in a float with more exponent. Only a layout holding a
# coordinate beyond FAR_COORD compiles the check (DeviceLayout.far); the others test as before.
FAR_UNIT = 2.0 ** -80


@dataclass
class Ray:
    """Per-ray constants of one traversal: origin, reciprocal direction, Woop's shear (made by
    `setup_ray`; a dataclass, so a kernel can switch a ray between world and object space
    inside its loop)."""

    o: list
    d: list
    inv: list
    kx: object
    ky: object
    kz: object
    sx: object
    sy: object
    sz: object


def setup_ray(m, o, d) -> Ray:
    """The Ray of origin o and direction d (three Floats each)."""
    inv = []
    for c in d:
        c_safe = dr.select(dr.abs(c) < MIN_RCP_INPUT, dr.copysign(MIN_RCP_INPUT, c), c)
        inv.append(dr.rcp(c_safe))
    # Woop, Benthin, Wald 2013: kz is the dominant axis; kx, ky are swapped when d[kz] < 0
    # to keep the winding (and so the sign of U, V, W) consistent.
    ax, ay, az = dr.abs(d[0]), dr.abs(d[1]), dr.abs(d[2])
    kz = dr.select((ax >= ay) & (ax >= az), m.UInt32(0), dr.select(ay >= az, m.UInt32(1), m.UInt32(2)))
    kx = dr.select(kz == 2, m.UInt32(0), kz + 1)
    ky = dr.select(kx == 2, m.UInt32(0), kx + 1)
    dz = pick(d, kz)
    flip = dz < 0
    kx, ky = dr.select(flip, ky, kx), dr.select(flip, kx, ky)
    sz = dr.rcp(dz)
    return Ray(o=list(o), d=list(d), inv=inv, kx=kx, ky=ky, kz=kz, sx=pick(d, kx) * sz, sy=pick(d, ky) * sz, sz=sz)


@dataclass
class ObjectRay:
    """A world ray mapped into the object space of an instance (`to_object_space`), and the
    link to the root of that instance's group."""

    o: list
    d: list
    root: object


def to_object_space(m, instances, k, o, d, active) -> ObjectRay:
    """World ray (o, d) in the object space of instance `k` (its INST_TO_OBJECT record).

    The direction is mapped without renormalising, so a point at distance t along the object
    ray is the image of the point at t along the world ray: hit distances need no mapping back
    (up to the float32 rounding of the mapped ray). Fused multiply-adds in one fixed order give
    the same bits wherever a kernel maps the ray (on entering an instance, or at the start of a
    wavefront step), so every mode sees the same object ray."""
    rec = dr.gather(m.ArrayXf, instances, k, active, shape=(INST_FLOATS, dr.width(k)))

    def row(r, x, w):
        at = INST_TO_OBJECT + 4 * r
        return dr.fma(rec[at], x[0], dr.fma(rec[at + 1], x[1], dr.fma(rec[at + 2], x[2], w)))
    return ObjectRay(o=[row(r, o, rec[INST_TO_OBJECT + 4 * r + 3]) for r in range(3)],
                     d=[row(r, d, m.Float(0)) for r in range(3)],
                     root=dr.reinterpret_array(m.UInt32, rec[INST_ROOT]))


def pick(v, k):
    return dr.select(k == 0, v[0], dr.select(k == 1, v[1], v[2]))


def _slab(m, rec, lo, hi, ray: Ray, tf):
    """(entry, exit) distances of `ray` through the box whose bounds are rec[lo[axis]] and
    rec[hi[axis]], the exit distance starting from `tf` (the one slab test of every branching)."""
    tn, tf = m.Float(0.0), m.Float(tf)
    for c in range(3):
        t0 = (rec[lo[c]] - ray.o[c]) * ray.inv[c]
        t1 = (rec[hi[c]] - ray.o[c]) * ray.inv[c]
        tn = dr.maximum(tn, dr.minimum(t0, t1))
        tf = dr.minimum(tf, dr.maximum(t0, t1))
    return tn, tf


def hit_children(m, nodes, node, ray: Ray, t_best, active):
    """Slab-test both child boxes of `node`: (hit_left, hit_right, t_left, t_right, link_left, link_right).

    A box counts as hit when its entry distance is <= t_best up to the slab test's rounding
    (FAR_SCALE), so a box that could hold a triangle at exactly t_best (a tie decided by
    primitive id, e.g. coplanar faces) is never culled."""
    rec = dr.gather(m.ArrayXf, nodes, node, active, shape=(NODE_FLOATS, dr.width(node)))
    out = []
    for side in (0, 1):
        lo, hi = NODE_BOX_LO[side], NODE_BOX_HI[side]
        tn, tf = _slab(m, rec, range(lo, lo + 3), range(hi, hi + 3), ray, dr.inf)
        hit = active & (tn <= tf * FAR_SCALE) & (tn <= t_best * FAR_SCALE)
        out.append((hit, tn))
    links = [dr.reinterpret_array(m.UInt32, rec[NODE_LINK[side]]) for side in (0, 1)]
    return out[0][0], out[1][0], out[0][1], out[1][1], links[0], links[1]


def hit_children_wide(m, nodes, node, ray: Ray, t_best, active, fmt: NodeFormat):
    """Slab-test all child boxes of a wide `node` (record layout `fmt`): per child (hit, entry
    distance, link), as three lists. The same test as hit_children, so a box is hit (and at the
    same distance) whatever the branching: tn <= min(tf, t_best) * FAR_SCALE is exactly
    (tn <= tf * FAR_SCALE) & (tn <= t_best * FAR_SCALE), rounding being monotone. Empty slots
    hold EMPTY_BOX, which no ray aims at (and whose link is an empty leaf)."""
    rec = dr.gather(m.ArrayXf, nodes, node, active, shape=(fmt.floats, dr.width(node)))
    hits, ts, links = [], [], []
    for c in range(fmt.branching):
        # far distance from t_best: min(tf, t_best) * FAR_SCALE rounds as the two tests of hit_children
        tn, tf = _slab(m, rec, fmt.lo[c], fmt.hi[c], ray, t_best)
        # (no `active &`: the caller runs this inside its node branch and reads only its lanes)
        hits.append(tn <= tf * FAR_SCALE)
        ts.append(tn)
        links.append(dr.reinterpret_array(m.UInt32, rec[fmt.link[c]]))
    return hits, ts, links


def f64_from_halves(m, lo, hi):
    """A float64 stored as two float32 slots (low word first)."""
    bits = m.UInt64(dr.reinterpret_array(m.UInt32, lo)) | (m.UInt64(dr.reinterpret_array(m.UInt32, hi)) << 32)
    return dr.reinterpret_array(m.Float64, bits)


def far_unit(m, relative):
    """Per lane, the unit (1 or FAR_UNIT) in which a triangle's origin-relative coordinates
    (`relative`: A, B, C, three Floats each) are tested (see FAR_COORD)."""
    big = dr.abs(relative[0][0])
    for point in relative:
        for c in point:
            big = dr.maximum(big, dr.abs(c))
    return dr.select(big > FAR_COORD, m.Float(FAR_UNIT), m.Float(1.0))


@dr.syntax
def hit_triangle(m, tris, tri, ray: Ray, active, far: bool = False):
    """Watertight test against triangle `tri` (leaf order): (hit, t, u, v, original face id).

    Hits are 0 < t; p = (1-u-v)*v0 + u*v1 + v*v2. Degenerate triangles (det = 0) never hit.
    `far`: the layout holds coordinates beyond FAR_COORD (DeviceLayout.far)."""
    rec = dr.gather(m.ArrayXf, tris, tri, active, shape=(TRI_FLOATS, dr.width(tri)))
    A, B, C = ([rec[at + c] - ray.o[c] for c in range(3)] for at in TRI_VERTEX)
    unit = far_unit(m, (A, B, C)) if far else None
    if far:
        A, B, C = ([c * unit for c in P] for P in (A, B, C))
    Az, Bz, Cz = pick(A, ray.kz), pick(B, ray.kz), pick(C, ray.kz)
    Ax, Ay = pick(A, ray.kx) - ray.sx * Az, pick(A, ray.ky) - ray.sy * Az
    Bx, By = pick(B, ray.kx) - ray.sx * Bz, pick(B, ray.ky) - ray.sy * Bz
    Cx, Cy = pick(C, ray.kx) - ray.sx * Cz, pick(C, ray.ky) - ray.sy * Cz
    U = Cx * By - Cy * Bx
    V = Ax * Cy - Ay * Cx
    W = Bx * Ay - By * Ax
    # A float edge function is off by at most ~8 eps m(P) m(Q), with P, Q the edge's vertices and
    # m their magnitude before the shear cancels. Below that its sign is unreliable (hits near an
    # edge, rays grazing the triangle), so it is recomputed from the unrounded shear in double
    # precision. Decision and value depend only on the edge and the ray, so the two triangles of a
    # shared edge see the same value (opposite sign): the test stays watertight.
    shear = dr.abs(ray.sx) + dr.abs(ray.sy)
    mA = dr.abs(pick(A, ray.kx)) + dr.abs(pick(A, ray.ky)) + dr.abs(Az) * shear
    mB = dr.abs(pick(B, ray.kx)) + dr.abs(pick(B, ray.ky)) + dr.abs(Bz) * shear
    mC = dr.abs(pick(C, ray.kx)) + dr.abs(pick(C, ray.ky)) + dr.abs(Cz) * shear
    unsure_u = dr.abs(U) <= EDGE_ERR * (mB * mC)
    unsure_v = dr.abs(V) <= EDGE_ERR * (mC * mA)
    unsure_w = dr.abs(W) <= EDGE_ERR * (mA * mB)
    F64 = m.Float64
    if active & (unsure_u | unsure_v | unsure_w):
        o64 = [F64(ray.o[c]) for c in range(3)]
        d64 = [F64(ray.d[c]) for c in range(3)]
        dz64 = pick(d64, ray.kz)
        sx64, sy64 = pick(d64, ray.kx) / dz64, pick(d64, ray.ky) / dz64

        unit64 = F64(unit) if far else None

        def sheared(base):
            p = [F64(rec[base + c]) - o64[c] for c in range(3)]
            if far:
                p = [c * unit64 for c in p]
            pz = pick(p, ray.kz)
            return pick(p, ray.kx) - sx64 * pz, pick(p, ray.ky) - sy64 * pz
        (ax, ay), (bx, by), (cx, cy) = (sheared(at) for at in TRI_VERTEX)
        U = dr.select(unsure_u, m.Float(cx * by - cy * bx), U)
        V = dr.select(unsure_v, m.Float(ax * cy - ay * cx), V)
        W = dr.select(unsure_w, m.Float(bx * ay - by * ax), W)
    outside = ((U < 0) | (V < 0) | (W < 0)) & ((U > 0) | (V > 0) | (W > 0))
    det = U + V + W
    rcp = dr.rcp(det)
    # Distance to the triangle's plane, t = n.(v0 - o) / n.d in double precision with the stored
    # normal, rounded once: the sheared float formula (T / det) loses up to 1e-2 relative at short
    # range, this is within an ulp, and it gives identical t for duplicated triangles and for
    # coplanar faces on axis-aligned planes, so such ties go by primitive id, not by rounding.
    # Only for rays inside the triangle: a packet with no such lane skips the float64 work.
    inside = active & ~outside & (det != 0)
    t = m.Float(dr.inf)
    if inside:
        n = [f64_from_halves(m, rec[TRI_NORMAL + 2 * c], rec[TRI_NORMAL + 2 * c + 1]) for c in range(3)]
        n_to_v0 = sum(n[c] * (F64(rec[TRI_VERTEX[0] + c]) - F64(ray.o[c])) for c in range(3))
        n_dot_d = sum(n[c] * F64(ray.d[c]) for c in range(3))
        t = dr.select(n_dot_d != 0, m.Float(n_to_v0 / n_dot_d), dr.inf)
    hit = inside & (t > 0) & (t < dr.inf)
    prim = dr.reinterpret_array(m.UInt32, rec[TRI_FACE])
    return hit, t, V * rcp, W * rcp, prim
