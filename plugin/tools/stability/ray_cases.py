"""Stability cases at the ray level on float precision: scaled and moved scenes, sliver and degenerate triangles,
coplanar overlap, axis-aligned and grazing rays, each against Embree and an exact float64 referee."""
from __future__ import annotations


import numpy as np

from layerbvh import MISS, meshes
from layerbvh_mitsuba.tools.stability.machinery import (CaseResult, _n, _rng, against_embree, box_bunny, bunny, case,
                                                        embree_hits, random_rays, trace_modes)


# -- ray level: the cases ------------------------------------------------------------------------------


def _transformed(name: str, scale: float, mul: float, add: float) -> CaseResult:
    v, f = box_bunny()
    v = v * mul + add
    o, d = random_rays(v, _n(scale), _rng(name))
    return against_embree(name, v, f, o, d, notes=f"default scene's {len(f):,} triangles x {mul:g} + {add:g}")


@case("scale_1e-4", "rays", "the default scene (box + bunny) scaled by 1e-4, random rays")
def scale_small(scale):
    return _transformed("scale_1e-4", scale, 1e-4, 0.0)


@case("scale_1e4", "rays", "the default scene scaled by 1e4, random rays")
def scale_large(scale):
    return _transformed("scale_1e4", scale, 1e4, 0.0)


@case("translate_1e5", "rays", "the default scene moved to (1e5, 1e5, 1e5), random rays")
def translate_1e5(scale):
    return _transformed("translate_1e5", scale, 1.0, 1e5)


@case("translate_1e6", "rays", "the default scene moved to (1e6, 1e6, 1e6) (float spacing 0.0625 there), random rays")
def translate_1e6(scale):
    return _transformed("translate_1e6", scale, 1.0, 1e6)


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def aimed_rays(targets: np.ndarray, normals: np.ndarray, dist, rng, spread: float = 0.8):
    """Rays from outside (along the normal, tilted by up to `spread` radians) aimed exactly at
    float64 targets; returns float32 (o, d) and the intended hit distance."""
    n = len(targets)
    tilt = rng.normal(size=(n, 3))
    tilt -= (tilt * normals).sum(1, keepdims=True) * normals
    tilt /= np.maximum(np.linalg.norm(tilt, axis=1, keepdims=True), 1e-30)
    ang = rng.uniform(0, spread, (n, 1))
    out = normals * np.cos(ang) + tilt * np.sin(ang)
    o = targets + out * np.reshape(dist, (-1, 1))
    d = targets - o
    t = np.linalg.norm(d, axis=1)
    return o.astype(np.float32), (d / t[:, None]).astype(np.float32), t


@case("sliver_triangles", "rays",
      "a flat strip of 2,000 slivers (1e-3 x 1000, aspect 1e6), turned at random; rays aimed inside it")
def sliver_triangles(scale):
    rng = _rng("sliver")
    cols, width, length = 1000, 1e-3, 1000.0
    x = np.arange(cols + 1) * width
    bottom = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    top = bottom + [0.0, length, 0.0]
    v = np.concatenate([bottom, top])
    i = np.arange(cols)
    f = np.concatenate([np.stack([i, i + 1, cols + 1 + i], 1), np.stack([i + 1, cols + 2 + i, cols + 1 + i], 1)])
    rot = random_rotation(rng)
    v = (v - [cols * width / 2, length / 2, 0]) @ rot.T
    n = _n(scale, 10_000)  # turned slivers have huge boxes: every ray visits most of the tree
    # Targets strictly inside the strip; origins 1..100 away on either side.
    local = np.stack([rng.uniform(-0.49, 0.49, n) * cols * width, rng.uniform(-0.49, 0.49, n) * length,
                      np.zeros(n)], 1)
    side = np.where(rng.random(n) < 0.5, 1.0, -1.0)[:, None]
    o, d, t = aimed_rays(local @ rot.T, side * rot[:, 2], rng.uniform(1, 100, n), rng, spread=1.2)
    traced = trace_modes(v.astype(np.float32), f, o, d)
    h = traced[1]
    emb = embree_hits(v, f, o, d)
    leaks = int((h.prim == MISS).sum())
    return against_embree("sliver_triangles", v, f, o, d, traced=traced, embree_ref=emb,
                          extra={"leaks": (leaks, True), "Embree leaks": (int((emb[False] == MISS).sum()), False),
                                 "robust leaks": (int((emb[True] == MISS).sum()), False)},
                          notes="a leak: a ray aimed inside the strip that misses it")


def degenerate_mix(v: np.ndarray, f: np.ndarray, rng, share: float = 0.3):
    """`f` with zero-area triangles mixed in (repeated vertices, all three equal, exactly collinear
    points on axis-parallel lines), original triangles kept in their order. Returns
    (vertices, faces, is_degenerate, original index of each face or -1)."""
    k = int(len(f) * share)
    kind = rng.integers(0, 3, k)
    # a, b: the ends of a mesh edge. Degenerate triangles in real meshes are local; ones spanning
    # the mesh would have huge boxes and only measure how a BVH copes with long diagonal slivers.
    edge = f[rng.integers(0, len(f), k)]
    a, b = edge[:, 0], edge[:, 1]
    deg = np.stack([a, a, np.where(kind == 0, b, a)], 1)  # kinds 0 and 1: (a, a, b) and (a, a, a)
    # Kind 2: three points that differ in one coordinate only, so exactly collinear in float32.
    line = np.nonzero(kind == 2)[0]
    axis = rng.integers(0, 3, len(line))
    pts = np.repeat(v[a[line]][:, None, :], 3, 1)
    span = v[b[line], axis] - v[a[line], axis] + 1e-3
    step = np.array([0.0, 0.3, 1.0])[None] * span[:, None]
    pts[np.arange(len(line))[:, None], np.arange(3)[None, :], axis[:, None]] += step
    pts = pts.astype(np.float32).astype(np.float64)
    deg[line] = len(v) + np.arange(3 * len(line)).reshape(-1, 3)
    v2 = np.concatenate([v, pts.reshape(-1, 3)])
    slots = np.sort(rng.choice(len(f) + k, k, replace=False))
    is_deg = np.zeros(len(f) + k, bool)
    is_deg[slots] = True
    f2 = np.empty((len(f) + k, 3), np.int64)
    f2[is_deg] = deg
    f2[~is_deg] = f
    orig = np.full(len(f2), -1)
    orig[~is_deg] = np.arange(len(f))
    return v2, f2, is_deg, orig


@case("degenerate_triangles", "rays", "the bunny with 30% zero-area triangles mixed in (repeated vertices, "
      "single points, collinear); random rays")
def degenerate_triangles(scale):
    rng = _rng("degenerate")
    v, f = bunny()
    v2, f2, is_deg, orig = degenerate_mix(v, f, rng)
    o, d = random_rays(v, _n(scale), rng)
    _, clean, _ = trace_modes(v.astype(np.float32), f, o, d)
    traced = trace_modes(v2.astype(np.float32), f2, o, d)
    h = traced[1]
    hit = h.prim != MISS
    on_degenerate = int(is_deg[h.prim[hit]].sum())
    mapped = np.where(hit, orig[np.where(hit, h.prim, 0)], -1)
    want = np.where(clean.prim != MISS, clean.prim.astype(np.int64), -1)
    changed = int(((mapped != want) | (h.t != clean.t) | (h.u != clean.u) | (h.v != clean.v)).sum())
    emb = embree_hits(v2, f2, o, d)
    emb_deg = int(sum(is_deg[p[p != MISS]].sum() for p in emb.values()))
    return against_embree("degenerate_triangles", v2, f2, o, d, traced=traced, embree_ref=emb,
                          extra={"hits on degenerate triangles": (on_degenerate, True),
                                 "rays whose hit differs from the clean mesh's": (changed, True),
                                 "Embree hits on degenerate triangles": (emb_deg, False)},
                          notes=f"{int(is_deg.sum()):,} degenerate of {len(f2):,} triangles")


def _overlap_plane(rng, n_small: int = 60):
    """A 2 x 2 square (two triangles) in z = 0 and `n_small` random triangles inside it, all coplanar."""
    v = [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]
    f = [[0, 1, 2], [0, 2, 3]]
    for _ in range(n_small):
        c = rng.uniform(-0.7, 0.7, 2)
        p = c + rng.uniform(-0.3, 0.3, (3, 2))
        base = len(v)
        v += [[x, y, 0.0] for x, y in p]
        f.append([base, base + 1, base + 2])
    order = rng.permutation(len(f))  # the big square gets random ids among the small ones
    return np.array(v, np.float64), np.array(f)[order]


def covering_min_id(v, f, points, eps: float = 1e-6) -> np.ndarray:
    """Per point of the z = 0 plane (float64): the lowest id of a triangle containing it, MISS if
    none does, or -1 where that triangle only touches the point within `eps` of an edge (there a
    neighbour's answer is as right)."""
    a, b, c = (v[f[:, k], :2][None] for k in range(3))
    x = points[:, None, :]

    def edge(p, q):
        return (q[..., 0] - p[..., 0]) * (x[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (x[..., 0] - p[..., 0])
    e = np.stack([edge(a, b), edge(b, c), edge(c, a)])
    orient = np.sign((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1])
                     - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))
    e = e * orient
    inside = np.all(e > eps, axis=0)
    touching = np.all(e > -eps, axis=0)
    ids = np.arange(len(f))[None, :]
    first_touch = np.where(touching, ids, len(f)).min(1)
    first_in = np.where(inside, ids, len(f)).min(1)
    return np.where(first_touch < first_in, -1, np.where(first_in < len(f), first_in, MISS))


@case("coplanar_overlap", "rays", "duplicated bunny (every triangle twice) and 62 overlapping coplanar triangles "
      "in z = 0: the lower id must win; the same set turned at random (ties decided by rounding)")
def coplanar_overlap(scale):
    rng = _rng("coplanar")
    n = _n(scale)
    # 1. Every triangle twice: identical t, so the lower id (the first copy) must win every hit.
    v, f = bunny()
    f2 = np.concatenate([f, f])
    o, d = random_rays(v, n, rng)
    _, h, _ = trace_modes(v.astype(np.float32), f2, o, d)
    dup_wrong = int(((h.prim != MISS) & (h.prim >= len(f))).sum())
    emb = embree_hits(v, f2, o, d)
    emb_second = int(((emb[False] != MISS) & (emb[False] >= len(f))).sum())
    # 2. Overlapping coplanar triangles in z = 0: t is exact, so the lowest covering id wins.
    pv, pf = _overlap_plane(rng)
    targets = np.stack([rng.uniform(-0.99, 0.99, n), rng.uniform(-0.99, 0.99, n), np.zeros(n)], 1)
    po, pd, _ = aimed_rays(targets, np.tile([0.0, 0.0, 1.0], (n, 1)), rng.uniform(0.5, 5, n), rng, spread=1.3)
    _, ph, _ = trace_modes(pv.astype(np.float32), pf, po, pd)
    # Where the ray really crosses z = 0 (the float32 ray, not the float64 target).
    t0 = -po[:, 2].astype(np.float64) / pd[:, 2]
    cross = po.astype(np.float64) + t0[:, None] * pd
    want = covering_min_id(pv, pf, cross[:, :2])
    decided = want != -1
    plane_wrong = int((decided & (ph.prim.astype(np.int64) != want)).sum())
    pemb = embree_hits(pv, pf, po, pd)
    emb_lowest = float(np.mean(pemb[False][decided] == want[decided]))
    # 3. The same set turned at random: coplanar only up to rounding; report who picks the lowest.
    rot = random_rotation(rng)
    rv, ro, rd = pv @ rot.T, po @ rot.T.astype(np.float32), pd @ rot.T.astype(np.float32)
    turned = trace_modes(rv.astype(np.float32), pf, ro, rd)
    rh = turned[1]
    res = against_embree("coplanar_overlap", rv, pf, ro, rd, traced=turned,
                         extra={"duplicate hits not on the lower copy": (dup_wrong, True),
                                "z = 0 hits not on the lowest covering id": (plane_wrong, True),
                                "Embree hits on the higher duplicate": (emb_second, False)})
    ours_lowest = float(np.mean(rh.prim[decided] == want[decided]))
    res.tried = 3 * n
    res.notes += (f"; z = 0: Embree picks the lowest id on {100 * emb_lowest:.1f}% of rays; turned plane: "
                  f"ours picks the lowest id on {100 * ours_lowest:.1f}% (the rest by rounding, as in Embree)")
    res.figures.update(turned_lowest_share=ours_lowest, embree_plane_lowest_share=emb_lowest)
    return res


@case("axis_aligned_rays", "rays", "rays along +-x, +-y, +-z with the other components +0 or -0, origins in the "
      "default scene, many on vertex coordinates (slab and triangle planes)")
def axis_aligned_rays(scale):
    rng = _rng("axis")
    v, f = box_bunny()
    n = _n(scale)
    o, _ = meshes.incoherent_rays(v, n, seed=5)
    o = o.astype(np.float64)
    # Snap one or two coordinates of half the origins onto vertex coordinates.
    snap = rng.random((n, 3)) < 0.35
    src = v[rng.integers(0, len(v), n)]
    o = np.where(snap, src, o)
    axis = rng.integers(0, 3, n)
    d = np.zeros((n, 3))
    d[np.arange(n), axis] = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    d = np.where((d == 0) & (rng.random((n, 3)) < 0.5), -0.0, d)
    return against_embree("axis_aligned_rays", v, f, o, d.astype(np.float32),
                          notes=f"{int(np.signbit(d[d == 0]).sum()):,} -0 components")


@case("grazing_rays", "rays", "an exactly planar 10 x 10 sheet of 51,200 triangles (z = y / 2); rays within "
      "1e-7..1e-6 rad of it, descending onto its middle (must hit) or rising from it (must miss)")
def grazing_rays(scale):
    rng = _rng("grazing")
    # Grid spacing 1/16 and slope 1/2 keep every vertex exactly on the plane in float32, so the
    # float64 ground truth below is exact for the float32 rays.
    k, step = 160, 1.0 / 16
    g = (np.arange(k + 1) - k / 2) * step
    xx, yy = np.meshgrid(g, g)
    v = np.stack([xx.ravel(), yy.ravel(), 0.5 * yy.ravel()], 1)
    r, c = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    a = (r * (k + 1) + c).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + k + 2], 1), np.stack([a, a + k + 2, a + k + 1], 1)])
    normal = np.array([0.0, -0.5, 1.0]) / np.sqrt(1.25)
    tx = np.array([1.0, 0.0, 0.0])
    ty = np.cross(normal, tx)
    n = _n(scale)
    target = rng.uniform(-2, 2, (n, 1)) * tx + rng.uniform(-2, 2, (n, 1)) * ty
    ang = rng.uniform(1e-7, 1e-6, (n, 1))
    az = rng.uniform(0, 2 * np.pi, (n, 1))
    along = np.cos(az) * tx + np.sin(az) * ty
    down = along * np.cos(ang) - normal * np.sin(ang)
    rising = rng.random(n) < 0.25
    dist = rng.uniform(0.5, 2.0, (n, 1))
    o = np.where(rising[:, None], target + 1e-4 * normal, target - down * dist).astype(np.float32)
    d = np.where(rising[:, None], along * np.cos(ang) + normal * np.sin(ang), down).astype(np.float32)
    # Ground truth for the float32 rays: where they cross the plane, and whether inside the sheet.
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    height = o64 @ normal
    t_cross = -height / (d64 @ normal)
    p = o64 + t_cross[:, None] * d64
    inside = (np.abs(p @ tx) < 4.9) & (np.abs(p @ ty) < 4.9 * np.sqrt(1.25))
    # Rounding can put an origin on the plane (height ~1e-18): such rays are neither.
    must_hit = (t_cross > 0) & inside & (height > 1e-12)
    must_miss = (t_cross <= 0) & (height > 1e-12)
    traced = trace_modes(v.astype(np.float32), f, o, d)
    h = traced[1]
    emb = embree_hits(v, f, o, d)
    return against_embree("grazing_rays", v, f, o, d, traced=traced, embree_ref=emb,
                          extra={"must-hit rays that miss": (int((must_hit & (h.prim == MISS)).sum()), True),
                                 "must-miss rays that hit": (int((must_miss & (h.prim != MISS)).sum()), True),
                                 "Embree must-hit misses": (int((must_hit & (emb[False] == MISS)).sum()), False),
                                 "robust": (int((must_hit & (emb[True] == MISS)).sum()), False)},
                          notes=f"{int(must_hit.sum()):,} must hit, {int(must_miss.sum()):,} must miss")
