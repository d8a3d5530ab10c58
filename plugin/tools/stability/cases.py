"""The stability suite's cases: extreme geometry against Embree (ray level) and stiff light transport against stock Mitsuba (image level).

Every case is a function `case(scale) -> CaseResult` registered in CASES; `scale` multiplies the
ray count or the image size (the tests run scale 1, `scripts/stability_report.py` more). A case
measures, then decides `passed` by the rule it states in `criterion` with the measured numbers;
`tests/tools/test_stability.py` asserts it and `scripts/stability_report.py` turns the results into
STABILITY.md.

Ray level. Our closest hits (all three traversal modes, which must agree bit for bit) against
Embree in its default and robust (`embree_use_robust_intersections`) modes. A *disagreement* is a
ray where one side hits and the other misses, or where the two hit different triangles at
different distances; rays that hit two triangles at the same distance (shared edges, coplanar
faces: either answer is right) are ties and counted apart (`embree.disagreements`).

Image level. Our `layerbvh` integrator in layer_sorted (treelets of LAYER_HEIGHT levels, so that
the wavefront path runs) against stock `path` on the scenes in scenes/stability/: same seed
(pixels differing by more than 1e-3 x max(1, |stock|) from Embree in default and robust mode),
NaN/Inf pixels, and a negative control: the same rule must fail on stock with one material's
albedo x 1.02 (see image_case).
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

import layerbvh
from layerbvh import MAX_DEPTH, MISS, from_numpy, meshes
from layerbvh_mitsuba.ab import embree, metrics
from layerbvh_mitsuba.ab.compare import CompareSettings, compare
from layerbvh_mitsuba.ab.render import load_scene, use_variant
from layerbvh_mitsuba.repo import SCENES
from layerbvh_mitsuba.runtime.adapter import SceneTracer, collect_geometry
from layerbvh_mitsuba.runtime.settings import Traversal
from layerbvh_mitsuba.runtime.stats import RenderStats

STIFF = SCENES / "stability"
RAYS = 40_000          # rays per ray-level case at scale 1
# Allowed rate of rays on which we are wrong by the exact float64 check. Measured: 0 rays in every
# case at scale 1 and 5; with the double-precision edge refinement switched off, 3 (slivers), 288
# (edges and vertices) and 2,315 (grazing) at scale 1. (Until this was written the rule also let us
# be as wrong as robust Embree, 12 / 473 / 3,231 rays there, which hid that.)
REAL_RATE = 1e-4


@dataclass
class CaseResult:
    case: str
    level: str                 # "rays" or "image"
    tried: int                 # rays (ray level) or pixels (image level)
    vs_default: int | None     # disagreements with Embree in its default mode
    vs_robust: int | None      # ... with embree_use_robust_intersections
    nonfinite: int             # NaN/Inf values among our hits or pixels
    passed: bool
    criterion: str             # the pass rule with the measured numbers
    notes: str = ""
    figures: dict = field(default_factory=dict)


@dataclass
class Case:
    name: str
    level: str
    what: str
    run: Callable[[float], CaseResult]


CASES: dict[str, Case] = {}


def case(name: str, level: str, what: str):
    def register(fn):
        CASES[name] = Case(name, level, what, fn)
        return fn
    return register


def run_case(name: str, scale: float = 1.0) -> CaseResult:
    return CASES[name].run(scale)


def _mi():
    return use_variant()


# -- ray level: shared machinery ---------------------------------------------------------------------


def _rng(name: str) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32(name.encode()))


def scene_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of a project XML scene (every mesh, as the integrator sees them)."""
    mi = _mi()
    v, f, _ = collect_geometry(mi.load_file(str(path), resx=8, resy=8)).world_triangles()
    return v.astype(np.float64), f


def bunny() -> tuple[np.ndarray, np.ndarray]:
    v, f = meshes.load_mesh(SCENES / "meshes" / "bunny.ply")
    return v.astype(np.float64), f


def trace_modes(v, f, o, d, tmax=None, **build):
    """Our hits in every mode on every branching (the default BVH and its per_ray hits returned)
    and how many rays any other mode or branching answers differently (bits of prim, t, u, v)."""
    v32 = np.asarray(v, np.float32)
    bvhs = {k: layerbvh.build(v32, f, **{**build, "branching": k}) for k in layerbvh.BRANCHINGS}
    bvh = bvhs[build.get("branching", layerbvh.DEFAULT_BRANCHING)]
    ref = bvh.trace(o, d, tmax, mode="per_ray", stats=False)
    hits = [b.trace(o, d, tmax, mode=m, stats=False) for b in bvhs.values() for m in layerbvh.MODES]
    differ = np.zeros(len(o), bool)
    for h in hits:
        for a, b in ((h.prim, ref.prim), (h.t, ref.t), (h.u, ref.u), (h.v, ref.v)):
            differ |= ~((a == b) | (np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f" else (a == b))
    return bvh, ref, int(differ.sum())


def nonfinite_hits(h) -> int:
    hit = h.prim != MISS
    return int((hit & ~(np.isfinite(h.t) & np.isfinite(h.u) & np.isfinite(h.v))).sum())


def embree_hits(v, f, o, d, tmax=None, with_t: bool = False) -> dict:
    """Embree's closest-hit prims (or (t, prim) with `with_t`), default and robust mode."""
    _mi()
    v32 = np.asarray(v, np.float32)
    out = {robust: embree.intersect(embree.scene_from_mesh(v32, f, robust), o, d, tmax) for robust in (False, True)}
    return out if with_t else {r: tp[1] for r, tp in out.items()}


def against_embree(name: str, v, f, o, d, tmax=None, extra: dict | None = None, notes: str = "",
                   traced: tuple | None = None, embree_ref: dict | None = None, **build) -> CaseResult:
    """The standard ray-level verdict. Where ours and Embree (default or robust) disagree, an exact
    float64 test of the triangles each side names decides who is wrong (`embree.wrong_answers`).
    Pass: the modes agree bit for bit, no NaN/Inf hit, and we are wrong on at most REAL_RATE x
    rays. `extra` adds {label: (value, must_be_zero)} figures. `traced` and `embree_ref`: what
    the case already has from `trace_modes` and `embree_hits` for these rays (not traced again)."""
    v32 = np.asarray(v, np.float32)
    o, d = np.asarray(o, np.float32), np.asarray(d, np.float32)
    _, h, mode_diff = traced if traced is not None else trace_modes(v32, f, o, d, tmax, **build)
    ref = embree_ref if embree_ref is not None else embree_hits(v32, f, o, d, tmax)
    dis = {r: embree.disagreements(v32, f, o, d, h.prim, p) for r, p in ref.items()}
    own = embree.disagreements(v32, f, o, d, ref[False], ref[True])
    rays = np.unique(np.concatenate([dis[False]["real_idx"], dis[True]["real_idx"], own["real_idx"]]))
    wrong = embree.wrong_answers(v32, f, o, d, {"ours": h.prim, "default": ref[False], "robust": ref[True]}, rays)
    n = len(o)
    allowed = int(REAL_RATE * n)
    bad = nonfinite_hits(h)
    extra = extra or {}
    hard = {k: val for k, (val, zero) in extra.items() if zero}
    passed = mode_diff == 0 and bad == 0 and wrong["ours"] <= allowed and all(val == 0 for val in hard.values())
    crit = (f"modes identical ({mode_diff} rays differ), NaN/Inf {bad}, wrong by exact check {wrong['ours']} <= "
            f"{allowed} ({REAL_RATE:g} x rays; Embree default / robust: {wrong['default']} / {wrong['robust']})")
    if hard:
        crit += "; " + ", ".join(f"{k} {val} = 0" for k, val in hard.items())
    soft = [f"{k} {val}" for k, (val, zero) in extra.items() if not zero]
    hit_rate = float(np.mean(h.prim != MISS))
    return CaseResult(name, "rays", n, dis[False]["real"], dis[True]["real"], bad, passed, crit,
                      "; ".join(x for x in [f"{100 * hit_rate:.1f}% hit", f"ties {dis[False]['ties']} / {dis[True]['ties']}",
                                            *soft, notes] if x),
                      {"mode_diff": mode_diff, "wrong": wrong, "embree_default_vs_robust": own["real"],
                       "ties_default": dis[False]["ties"], "ties_robust": dis[True]["ties"], "hit_rate": hit_rate,
                       **{k: val for k, (val, _) in extra.items()}})


def _n(scale: float, base: int = RAYS) -> int:
    return max(1000, int(base * scale))


def box_bunny() -> tuple[np.ndarray, np.ndarray]:
    """The default scene's triangles: the paper's closed box with the bunny and the ceiling light."""
    return scene_triangles(SCENES / "bunny_box.xml")


def random_rays(v, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    return meshes.incoherent_rays(v, n, seed=int(rng.integers(2**31)))


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


@case("sliver_triangles", "rays", "a flat strip of 2,000 slivers (1e-3 x 1000, aspect 1e6), turned at random; rays aimed inside it")
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
    pts[np.arange(len(line))[:, None], np.arange(3)[None, :], axis[:, None]] += np.array([0.0, 0.3, 1.0])[None] * span[:, None]
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


@case("degenerate_triangles", "rays", "the bunny with 30% zero-area triangles mixed in (repeated vertices, single points, collinear); random rays")
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
    orient = np.sign((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))
    e = e * orient
    inside = np.all(e > eps, axis=0)
    touching = np.all(e > -eps, axis=0)
    ids = np.arange(len(f))[None, :]
    first_touch = np.where(touching, ids, len(f)).min(1)
    first_in = np.where(inside, ids, len(f)).min(1)
    return np.where(first_touch < first_in, -1, np.where(first_in < len(f), first_in, MISS))


@case("coplanar_overlap", "rays", "duplicated bunny (every triangle twice) and 62 overlapping coplanar triangles in z = 0: the lower id must win; the same set turned at random (ties decided by rounding)")
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


@case("axis_aligned_rays", "rays", "rays along +-x, +-y, +-z with the other components +0 or -0, origins in the default scene, many on vertex coordinates (slab and triangle planes)")
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


@case("grazing_rays", "rays", "an exactly planar 10 x 10 sheet of 51,200 triangles (z = y / 2); rays within 1e-7..1e-6 rad of it, descending onto its middle (must hit) or rising from it (must miss)")
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


def closed_meshes():
    """Closed test meshes: a UV sphere (pole fans) and a tessellated cube, float64."""
    sv, sf = meshes.uv_sphere(48, 25)
    k = 6
    g = np.linspace(-1, 1, k + 1)
    verts, faces, index = [], [], {}

    def vid(p):
        key = tuple(np.round(p, 12))
        if key not in index:
            index[key] = len(verts)
            verts.append(p)
        return index[key]
    for axis in range(3):
        for sgn in (-1.0, 1.0):
            u, w = [a for a in range(3) if a != axis]
            for i in range(k):
                for j in range(k):
                    quad = []
                    for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = np.zeros(3)
                        p[axis], p[u], p[w] = sgn, g[i + di], g[j + dj]
                        quad.append(vid(p))
                    a, b, c, d = quad
                    faces += [[a, b, c], [a, c, d]]
    return [("sphere", sv, outward(sv, sf)), ("cube", np.array(verts), outward(np.array(verts), np.array(faces)))]


def outward(v, f):
    """Faces of a convex mesh around the origin, wound so that their normals point outwards."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    flip = (n * v[f].mean(1)).sum(1) < 0
    return np.where(flip[:, None], f[:, ::-1], f)


def edge_and_vertex_targets(v, f):
    """Every undirected edge's midpoint and every vertex, the outward direction there (mean of the
    adjacent faces' normals), and (target, face) pairs of the faces meeting at each target."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    face_of_half_edge = np.tile(np.arange(len(f)), 3)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.ravel()
    pairs = np.concatenate([np.stack([inv, face_of_half_edge], 1),
                            np.stack([len(edges) + f.ravel(), np.repeat(np.arange(len(f)), 3)], 1)])
    nrm = np.zeros((len(edges) + len(v), 3))
    np.add.at(nrm, pairs[:, 0], fn[pairs[:, 1]])
    pts = np.concatenate([(v[edges[:, 0]] + v[edges[:, 1]]) / 2, v])
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True), pairs, fn


def facing_all(d, target, pairs, fn) -> np.ndarray:
    """Per ray: the smallest cosine between -d and the normals of the faces meeting at its target."""
    out = np.full(len(d), np.inf)
    by_target = np.argsort(pairs[:, 0], kind="stable")
    pairs = pairs[by_target]
    start = np.searchsorted(pairs[:, 0], target, "left")
    stop = np.searchsorted(pairs[:, 0], target, "right")
    for k in range(int((stop - start).max())):
        has = start + k < stop
        face = pairs[np.minimum(start + k, len(pairs) - 1), 1]
        cos = -(d * fn[face]).sum(1)
        out = np.where(has, np.minimum(out, cos), out)
    return out


@case("watertight_edges_vertices", "rays", "rays aimed exactly at the shared edges and vertices of a closed sphere and cube, near the origin and (x100) moved to 1e5; a leak passes through")
def watertight(scale):
    rng = _rng("watertight")
    per_target = max(1, int(2 * scale))
    rows = []
    for k, (name, v, f) in enumerate(closed_meshes()):
        # Near the origin and (x100) at 1e5; the meshes sit 5 sizes apart, so that the combined
        # check against Embree below sees every mesh alone.
        for size, offset in ((1.0, 5.0 * k), (100.0, 1e5 + 500.0 * k)):
            vv = (v * size + offset).astype(np.float32).astype(np.float64)
            o, d, dist = edge_rays(v, f, size, offset, per_target, rng)
            _, h, _ = trace_modes(vv.astype(np.float32), f, o, d)
            emb = embree_hits(vv, f, o, d, with_t=True)
            rows.append((f"{name}@{offset:g}", vv, f, o, d, leaks(h.prim, h.t, dist, size),
                         leaks(emb[False][1], emb[False][0], dist, size), leaks(emb[True][1], emb[True][0], dist, size)))
    v_all = np.concatenate([r[1] for r in rows])
    offs = np.cumsum([0] + [len(r[1]) for r in rows[:-1]])
    f_all = np.concatenate([r[2] + k for r, k in zip(rows, offs)])
    o_all, d_all = np.concatenate([r[3] for r in rows]), np.concatenate([r[4] for r in rows])
    ours, e_def, e_rob = (sum(r[k] for r in rows) for k in (5, 6, 7))
    res = against_embree("watertight_edges_vertices", v_all, f_all, o_all, d_all,
                         extra={"leaks": (ours, True), "Embree leaks": (e_def, False), "robust leaks": (e_rob, False)},
                         notes="; ".join(f"{r[0]}: ours {r[5]}, Embree {r[6]}/{r[7]}" for r in rows))
    res.figures["per_mesh"] = [{"mesh": r[0], "rays": len(r[3]), "ours": r[5], "embree": r[6], "robust": r[7]} for r in rows]
    return res


def edge_rays(v, f, size: float, offset: float, per_target: int, rng):
    """Rays aimed exactly at every edge midpoint and vertex of a closed mesh (scaled by `size`,
    moved by `offset`), from outside, each meeting every face at its target from the front (at a
    corner of the cube a tilted ray may touch the solid in that one point and rightly miss).
    Returns float32 (o, d) and the distance to the aim point."""
    pts, nrm, pairs, fn = edge_and_vertex_targets(v, f)
    target = np.repeat(np.arange(len(pts)), per_target)
    pts, nrm = pts[target] * size + offset, nrm[target]
    o, d, dist = aimed_rays(pts, nrm, rng.uniform(0.5, 3.0, len(pts)) * size, rng, spread=0.5)
    keep = facing_all(d.astype(np.float64), target, pairs, fn) > 0.05
    return o[keep], d[keep], dist[keep]


def leaks(prim, t, dist, size: float) -> int:
    """Rays that missed, or hit beyond their aim point: through the front surface to the back."""
    return int(((prim == MISS) | (t > dist * (1 + 1e-3) + 1e-3 * size)).sum())


@case("spawn_ray_self_hits", "rays", "rays leaving the default scene's surfaces (Mitsuba's spawn_ray, both hemispheres), also with the scene moved to 1e5: none may hit its own triangle")
def spawn_ray_self_hits(scale):
    mi = _mi()
    rng = _rng("spawn")
    n = _n(scale)
    v0, f = box_bunny()
    counts, tried, notes = {}, 0, []
    for offset in (0.0, 1e5):
        # One mesh holding the scene's triangles (face i = prim i), so Mitsuba computes the
        # surface interaction and spawns the ray, and Embree and we trace the same triangles.
        v = (v0 + offset).astype(np.float32)
        scene = embree.scene_from_mesh(v, f)
        tracer = SceneTracer(scene, "layer_sorted", count_work=False)
        o, d = random_rays(v, n, rng)
        ray = embree.rays(o, d)
        pi = tracer.intersect(ray, True)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, pi.is_valid())
        hit0 = np.array(pi.is_valid())
        own = np.array(pi.prim_index)[hit0]
        out = rng.normal(size=(n, 3)).astype(np.float32)
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        ray2 = si.spawn_ray(mi.Vector3f(*(from_numpy(mi.Float, out[:, c]) for c in range(3))))
        o2 = np.stack([np.array(ray2.o[c]) for c in range(3)], 1)[hit0]
        d2 = np.stack([np.array(ray2.d[c]) for c in range(3)], 1)[hit0]
        h = tracer.bvh.trace(o2, d2, mode="layer_sorted", stats=False)
        self_ours = int((h.prim == own).sum())
        emb = embree_hits(v, f, o2, d2)
        self_emb = [int((p == own).sum()) for p in (emb[False], emb[True])]
        counts[offset] = (self_ours, *self_emb)
        tried += len(o2)
        notes.append(f"at {offset:g}: ours {self_ours}, Embree {self_emb[0]}/{self_emb[1]} of {len(o2):,}")
    ours = sum(c[0] for c in counts.values())
    return CaseResult("spawn_ray_self_hits", "rays", tried, sum(c[1] for c in counts.values()),
                      sum(c[2] for c in counts.values()), 0, ours == 0,
                      f"self-hits (a spawned ray hitting its own triangle) {ours} = 0; columns give Embree's self-hits",
                      "; ".join(notes), {"per_offset": {str(k): v for k, v in counts.items()}})


@case("tiny_meshes", "rays", "all triangles at one point (1,000), one triangle, no triangles: bounded build depth, correct hits")
def tiny_meshes(scale):
    rng = _rng("tiny")
    n = _n(scale, 10_000)
    notes, ok, tried, real, real_r, depth_max = [], True, 0, 0, 0, 0
    point = np.tile([[0.3, -0.2, 0.7]], (3000, 1))
    one_v, one_f = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]])
    for name, v, f in (("one point", point, np.arange(3000).reshape(-1, 3)), ("one triangle", one_v, one_f)):
        bvh = layerbvh.build(v.astype(np.float32), f)
        bvh.check()
        depth_max = max(depth_max, bvh.stats.depth)
        # Half the rays aimed at the geometry (the point / inside the triangle), half at random.
        tgt = v[f].mean(1)[rng.integers(0, len(f), n)] + (0 if name == "one point" else rng.uniform(-0.3, 0.3, (n, 3)) * [1, 1, 0])
        o, d, _ = aimed_rays(tgt, np.tile([0.0, 0.0, 1.0], (n, 1)), rng.uniform(0.5, 2, n), rng, spread=1.0)
        r = against_embree(f"tiny:{name}", v, f, o, d)
        tried += r.tried
        real, real_r = real + r.vs_default, real_r + r.vs_robust
        ok &= r.passed
        notes.append(f"{name}: depth {bvh.stats.depth}, {100 * r.figures['hit_rate']:.0f}% hit")
        if name == "one point":
            ok &= r.figures["hit_rate"] == 0
    empty = layerbvh.build(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    o, d = rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32)
    empty_hits = sum(int((empty.trace(o, d, mode=m).prim != MISS).sum()) for m in layerbvh.MODES)
    tried += n
    ok &= empty_hits == 0 and depth_max < MAX_DEPTH
    notes.append(f"no triangles: {empty_hits} hits")
    return CaseResult("tiny_meshes", "rays", tried, real, real_r, 0, ok,
                      f"all-at-one-point mesh never hit, empty mesh never hit ({empty_hits}), build depth {depth_max} < "
                      f"{MAX_DEPTH}, one triangle within the Embree rule", "; ".join(notes), {"depth_max": depth_max})


@case("bad_data", "rays", "NaN/Inf vertex positions (clear error naming the shape), NaN/Inf/zero rays (misses)")
def bad_data(scale):
    mi = _mi()
    notes, ok = [], True
    for bad in (np.nan, np.inf):
        scene = mi.load_string(f"""<scene version="3.0.0">
            <shape type="ply" id="bunny_{'nan' if np.isnan(bad) else 'inf'}">
              <string name="filename" value="{SCENES / 'meshes' / 'bunny.ply'}"/></shape></scene>""")
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("vertex_positions"))
        pos = np.array(params[key])
        pos[3 * 17 + 1] = bad
        params[key] = from_numpy(mi.Float, pos)
        params.update()
        try:
            SceneTracer(scene)
            msg = "no error"
        except ValueError as e:
            msg = str(e)
        named = "bunny_" in msg and "vertices[17]" in msg
        ok &= named
        notes.append(f"{'NaN' if np.isnan(bad) else 'Inf'} vertex: {msg!r}")
    v, f = bunny()
    n = _n(scale, 10_000)
    rng = _rng("bad")
    o, d = random_rays(v, n, rng)
    o, d = o.copy(), d.copy()
    kinds = rng.integers(0, 5, n)
    col = rng.integers(0, 3, n)
    vals = np.array([np.nan, np.inf, -np.inf], np.float32)[rng.integers(0, 3, n)]
    o[kinds == 0, col[kinds == 0]] = vals[kinds == 0]
    d[kinds == 1, col[kinds == 1]] = vals[kinds == 1]
    d[kinds == 2] = 0.0
    bad_rays = kinds <= 2
    bvh = layerbvh.build(v.astype(np.float32), f)
    hits_on_bad, nonfinite = 0, 0
    for m in layerbvh.MODES:
        h = bvh.trace(o, d, mode=m)
        hits_on_bad += int((h.prim[bad_rays] != MISS).sum() + np.isfinite(h.t[bad_rays]).sum())
        nonfinite += nonfinite_hits(h)
        occ = bvh.occluded(o, d, 1.0, mode=m).occluded
        hits_on_bad += int(occ[bad_rays].sum())
    ok &= hits_on_bad == 0 and nonfinite == 0
    notes.append(f"{int(bad_rays.sum()):,} NaN/Inf/zero rays of {n:,}")
    return CaseResult("bad_data", "rays", n, None, None, nonfinite, ok,
                      f"NaN and Inf vertices refused naming shape and vertex; bad rays reported as hits {hits_on_bad} = 0 "
                      f"in every mode (closest and any hit)", "; ".join(notes))


# -- image level -------------------------------------------------------------------------------------


# Image cases build treelets of 2 levels: at the default height 8 four of the five scenes are one
# treelet, where layer_sorted cannot differ from per_ray (at 2: 3-6 treelets, infinite_mirrors
# 14,602; measured 1.3-3.3 wavefront steps per query). Each case checks that the wavefront path ran.
LAYER_HEIGHT = 2
CONTROL_FACTOR = 1.02  # the negative control: one material's albedo x 1.02
GREY = "grey.reflectance.value"  # box.xml's walls, floor and ceiling


def layer_path_ran(st: RenderStats) -> tuple[bool, float]:
    """Whether a layer_sorted render's last_stats show the layer path: the wavefront loop, only
    layer_sorted queries, several treelets and more than one wavefront step per query (per_ray, or
    one treelet, takes at most one); and the steps per query."""
    per_query = st.wavefront_steps / max(1, st.queries)
    ok = (st.loop == "wavefront" and set(st.modes_used) == {"layer_sorted"}
          and st.bvh.treelets > 1 and per_query > 1)
    return ok, per_query


def _within(ref: np.ndarray, img: np.ndarray) -> float:
    """The share of pixels the same-seed criterion (metrics.same_seed_verdict) counts as within."""
    return metrics.same_seed_verdict(ref, img)["values"]["frac_within"]


def image_case(name: str, scene: str, scale: float, spp: int = 16, control: str = GREY, **params) -> CaseResult:
    """Stock `path` (Embree default and robust) against `layerbvh` in layer_sorted (treelet height
    LAYER_HEIGHT) on scenes/stability/SCENE.xml, same seed (ab.compare.compare, its first step:
    the same-seed criterion of every comparison), NaN/Inf pixels, and whether the wavefront path
    ran.

    Negative control: the same criterion, stock against stock with `control` (a material's albedo,
    or the light's radiance where no albedo is seen) x CONTROL_FACTOR, must fail: the criterion
    can see a 2% change on this scene at this size (measured at scale 1 with the earlier 99%
    rule: 3.1% of the pixels over at max_depth 1, where only the light's own pixels change, 14% at
    max_depth 2, 81-100% on the others).
    (Until this was written the verdict also held a per-pixel Z-test over independent seeds, 8x8
    pixels, 64 spp, 8 seeds, which passed with a 5% albedo change. Sized to see 2% on these scenes
    (36 pixels, 2048 spp and more) its layer_sorted side took 6-22 s a case: the same-seed rule is
    the stronger check for the price; the Z-tests with shown power are in tests/runtime/.)"""
    mi = use_variant()
    res = max(8, int(round(16 * math.sqrt(scale))))
    path = STIFF / f"{scene}.xml"
    scene_params = {"resx": res, "resy": res, **params}
    c = compare(mi, CompareSettings(scene=path, spp=spp, seed=3, traversal=Traversal.parse("layer_sorted"),
                                    treelet_height=LAYER_HEIGHT, params={**scene_params, "robust": False},
                                    statistical_step=False))
    st = c.stats
    stock = mi.load_dict(c.path.stock_inner())  # (the scene's estimator: path, or volpath in the media cases)
    robust_scene = load_scene(mi, str(path), **scene_params, robust=True)
    robust = np.array(mi.render(robust_scene, integrator=stock, spp=spp, seed=3), np.float32)
    changed_params = mi.traverse(c.scene)
    changed_params[control] = changed_params[control] * CONTROL_FACTOR
    changed_params.update()
    changed = np.array(mi.render(c.scene, integrator=stock, spp=spp, seed=3), np.float32)
    nonfinite = c.nonfinite[1]
    pixels = res * res
    frac, frac_robust = _within(c.stock, c.ours), _within(robust, c.ours)
    control_verdict = metrics.same_seed_verdict(c.stock, changed)
    control_frac = control_verdict["values"]["frac_within"]
    layer_ok, per_query = layer_path_ran(st)
    passed = nonfinite == 0 and c.verdict.same_seed["passed"] and layer_ok and not control_verdict["passed"]
    crit = (f"NaN/Inf pixels {nonfinite} = 0; {c.verdict.same_seed['criterion']}: {100 * frac:.2f}% within; "
            f"wavefront steps per query {per_query:.2f} > 1 ({st.bvh.treelets} treelets); control ({control} x "
            f"{CONTROL_FACTOR:g}) fails it: {100 * control_frac:.2f}% within")
    return CaseResult(name, "image", pixels, round((1 - frac) * pixels), round((1 - frac_robust) * pixels), nonfinite,
                      passed, crit,
                      f"{res}x{res}, {spp} spp same seed, layer_sorted at treelet height {LAYER_HEIGHT}; up to "
                      f"{st.bounces} bounces; mean pixel {c.stock.mean():.3g}",
                      {"same_seed_frac": frac, "control_frac": control_frac, "steps_per_query": per_query,
                       "treelets": st.bvh.treelets, "bounces": st.bounces})


@case("tiny_bright_emitter", "image", "a 1e-4 area emitter of radiance 1e6 (the only light) over a diffuse block")
def tiny_bright_emitter(scale):
    return image_case("tiny_bright_emitter", "tiny_emitter", scale)


@case("near_specular", "image", "GGX alpha 1e-4: rough gold block, rough glass sphere (analytic), rough plastic block")
def near_specular(scale):
    return image_case("near_specular", "near_specular", scale)


for _ior in ("1.0001", "1.5", "0.9", "0.7"):
    case(f"dielectric_ior_{_ior}", "image", f"smooth dielectric block, int_ior {_ior} in air")(
        lambda scale, _ior=_ior: image_case(f"dielectric_ior_{_ior}", "dielectric", scale, ior=_ior))

case("total_internal_reflection", "image", "dielectric block of int_ior 2.4: total internal reflection beyond 24.6 degrees")(
    lambda scale: image_case("total_internal_reflection", "dielectric", scale, ior="2.4"))

case("facing_mirrors", "image", "two facing perfect mirrors 1.98 apart with a diffuse block between, max_depth 64")(
    lambda scale: image_case("facing_mirrors", "facing_mirrors", scale))

case("infinite_mirrors", "image", "Mitsuba's infinite_mirrors test scene: three chrome sphere meshes under an environment map")(
    lambda scale: image_case("infinite_mirrors", "infinite_mirrors", scale, control="chrome.specular_reflectance.value"))

for _medium, _what, _params in (
        ("medium_dense", "a homogeneous medium of density 200 (albedo 0.9) in a null-BSDF block, volpath",
         {"density": "200"}),
        ("medium_thin", "a homogeneous medium of density 1e-4 (nearly transparent) in a null-BSDF block, volpath",
         {"density": "0.0001"}),
        ("medium_back_faces", "the block's normals flipped and the medium its exterior: rays enter through back "
         "faces, volpath", {"flip": "true", "side": "exterior"})):
    case(_medium, "image", _what)(
        # (max_depth 4, 8 spp: between kernels each collision is a loop iteration; the suite's time)
        lambda scale, _medium=_medium, _params=_params: image_case(_medium, "medium", scale, spp=8, max_depth="4",
                                                                   **_params))

for _depth in (1, 2, 64):
    case(f"max_depth_{_depth}", "image", f"the glass block scene (int_ior 1.5) with max_depth {_depth}")(
        lambda scale, _depth=_depth: image_case(f"max_depth_{_depth}", "dielectric", scale, max_depth=str(_depth),
                                                # at max_depth 1 only emitters are seen: the light's radiance
                                                **({"control": "ceiling_light.emitter.radiance.value"} if _depth == 1 else {})))
