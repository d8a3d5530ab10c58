"""Stability cases at the ray level on whole meshes and inputs: watertight edges and vertices of closed meshes,
self-hits of spawned rays, tiny meshes and bad data."""
from __future__ import annotations


import numpy as np

import layerbvh
from layerbvh import MAX_DEPTH, MISS, from_numpy, meshes
from layerbvh_mitsuba.ab import embree
from layerbvh_mitsuba.repo import SCENES
from layerbvh_mitsuba.runtime.adapter import SceneTracer
from layerbvh_mitsuba.tools.stability.machinery import (CaseResult, _mi, _n, _rng, against_embree, box_bunny, bunny,
                                                        case, embree_hits, nonfinite_hits, random_rays, trace_modes)
from layerbvh_mitsuba.tools.stability.ray_cases import aimed_rays


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


@case("watertight_edges_vertices", "rays", "rays aimed exactly at the shared edges and vertices of a closed sphere "
      "and cube, near the origin and (x100) moved to 1e5; a leak passes through")
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
                         leaks(emb[False][1], emb[False][0], dist, size),
                         leaks(emb[True][1], emb[True][0], dist, size)))
    v_all = np.concatenate([r[1] for r in rows])
    offs = np.cumsum([0] + [len(r[1]) for r in rows[:-1]])
    f_all = np.concatenate([r[2] + k for r, k in zip(rows, offs)])
    o_all, d_all = np.concatenate([r[3] for r in rows]), np.concatenate([r[4] for r in rows])
    ours, e_def, e_rob = (sum(r[k] for r in rows) for k in (5, 6, 7))
    res = against_embree("watertight_edges_vertices", v_all, f_all, o_all, d_all,
                         extra={"leaks": (ours, True), "Embree leaks": (e_def, False), "robust leaks": (e_rob, False)},
                         notes="; ".join(f"{r[0]}: ours {r[5]}, Embree {r[6]}/{r[7]}" for r in rows))
    res.figures["per_mesh"] = [{"mesh": r[0], "rays": len(r[3]), "ours": r[5], "embree": r[6], "robust": r[7]}
                               for r in rows]
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


@case("spawn_ray_self_hits", "rays", "rays leaving the default scene's surfaces (Mitsuba's spawn_ray, both "
      "hemispheres), also with the scene moved to 1e5: none may hit its own triangle")
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


@case("tiny_meshes", "rays",
      "all triangles at one point (1,000), one triangle, no triangles: bounded build depth, correct hits")
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
        tgt = v[f].mean(1)[rng.integers(0, len(f), n)] + (
            0 if name == "one point" else rng.uniform(-0.3, 0.3, (n, 3)) * [1, 1, 0])
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
                      f"all-at-one-point mesh never hit, empty mesh never hit ({empty_hits}), "
                      f"build depth {depth_max} < {MAX_DEPTH}, one triangle within the Embree rule", "; ".join(notes),
                      {"depth_max": depth_max})


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
                      "NaN and Inf vertices refused naming shape and vertex; "
                      f"bad rays reported as hits {hits_on_bad} = 0 "
                      f"in every mode (closest and any hit)", "; ".join(notes))
