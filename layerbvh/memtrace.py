"""The exact memory trace of a traversal: walk.py's loop replayed in the kernels' schedule, fed to the cache model."""
from __future__ import annotations

# Why a replay and not an instrumented kernel: the trace has to be read in schedule order (warp by
# warp, iteration by iteration, across resident warps and SMs), and a Dr.Jit kernel can only append
# its reads to a buffer in an order the threads race for, tens of bytes per lane-iteration. The
# replay is the same loop as walk.walk, statement for statement, in float32 arithmetic that Dr.Jit's
# LLVM backend reproduces bit for bit (measured: dr.rcp is an exact division there and products are
# not contracted into FMAs), so its visit order is the kernel's. locality.check_trace proves it per
# ray: hits (prim, t bits) and the work counters (inner nodes, leaves, triangles, iterations, steps)
# equal what the kernel returned. On CUDA, rcp is approximate: rare rays may take another order (counted).
#
# What one lane-iteration can read, in walk's order (each a separate load instruction, "site"):
# a triangle record, its local entry-stack slot, a global entry-stack entry (two arrays), a node's
# treelet (bounded steps), an exit's treelet root, a node record, and it writes its local stack
# (every iteration: walk keeps local accesses outside branches, a lane that pushes nothing writes
# the spare slot). At a warp's first iteration each lane also loads its ray (and, in a wavefront
# step, its state). A wide node (branching 4 or 8) is one record load of its format's size; a
# lane that pushes writes its K - 1 push slots (a branch: on a GPU, lanes that push nothing are
# predicated off); a lane that ends stores its outputs (memstores.py). Instances: flattened.
import numba
import numpy as np

from . import cachesim, geometry, layout, memsites, memstores, numba_cache
from .layout import TRI_FACE
from .cachesim import cache_access, coalesce
from .memsites import (BY_LANE, BY_LINK_NODE, BY_SLOT, F_D, F_INV, F_O, F_SX, F_SY, F_SZ, F_T, F_U, F_V, I_ACTIVE,
                       I_DONE, I_HITS, I_HITW, I_INNER, I_ITER, I_KX, I_KY, I_KZ, I_LEAF, I_LINK, I_NEXT, I_NL,
                       I_PRIM, I_SP, I_SPILL, I_STEPS, I_TRELET, I_TRI, I_TRI_CUR, I_TRI_END, MAX_PUSH, NO_READ, SITES,
                       STORE_SITES, S_LOC_R_LINK, S_LOC_R_T, S_LOC_W_LINK, S_LOC_W_T, S_NODE, S_NODE_TRELET, S_PUSH,
                       S_STACK_LINK, S_STACK_T, S_START, S_TF, S_TRI, _EDGE, _EXIT, _FAR, _FAR_COORD, _FAR_UNIT,
                       _FIRST, _FLT_MAX, _HI0, _HI1, _LEAF, _LK0, _LK1, _LO0, _LO1, _MIN_RCP, _NRM, _PAYLOAD, _POP,
                       _SHIFT, _V0, _V1, _V2, BY_PREVIOUS_LANE)


@numba.njit(cache=True, inline="always")
def _pick(a0, a1, a2, k):
    return a0 if k == 0 else (a1 if k == 1 else a2)


@numba.njit(cache=True, nogil=True)
def setup_rays(o, d, fst, ist, tmax):
    """geometry.setup_ray for every ray (origin, reciprocal direction, Woop's shear), t = tmax."""
    for i in range(len(o)):
        for c in range(3):
            fst[i, F_O + c] = o[i, c]
            fst[i, F_D + c] = d[i, c]
            x = d[i, c]
            if abs(x) < _MIN_RCP:
                x = _MIN_RCP if x >= 0 else -_MIN_RCP
            fst[i, F_INV + c] = np.float32(1.0) / x
        ax, ay, az = abs(d[i, 0]), abs(d[i, 1]), abs(d[i, 2])
        kz = 0 if (ax >= ay and ax >= az) else (1 if ay >= az else 2)
        kx = 0 if kz == 2 else kz + 1
        ky = 0 if kx == 2 else kx + 1
        dz = d[i, kz]
        if dz < 0:
            kx, ky = ky, kx
        sz = np.float32(1.0) / dz
        ist[i, I_KX], ist[i, I_KY], ist[i, I_KZ] = kx, ky, kz
        fst[i, F_SX] = d[i, kx] * sz
        fst[i, F_SY] = d[i, ky] * sz
        fst[i, F_SZ] = sz
        fst[i, F_T] = tmax[i]
        fst[i, F_U] = 0
        fst[i, F_V] = 0
        ist[i, I_PRIM] = _POP  # MISS has the same bits
        ist[i, I_LINK] = 0
        ist[i, I_SP] = 0
        ist[i, I_TRELET] = 0
        ist[i, I_DONE] = 0
        for c in range(I_INNER, I_HITW + 1):  # the work counters
            ist[i, c] = 0


@numba.njit(cache=True)
def _hit_triangle(tris_f, tris_u, tris_d, tri, fst, ist, s):
    """geometry.hit_triangle for ray s: (hit, t, u, v, prim), the same float32/float64 steps."""
    kx, ky, kz = ist[s, I_KX], ist[s, I_KY], ist[s, I_KZ]
    sx, sy = fst[s, F_SX], fst[s, F_SY]
    o0, o1, o2 = fst[s, F_O], fst[s, F_O + 1], fst[s, F_O + 2]
    a0, a1, a2 = tris_f[tri, _V0] - o0, tris_f[tri, _V0 + 1] - o1, tris_f[tri, _V0 + 2] - o2
    b0, b1, b2 = tris_f[tri, _V1] - o0, tris_f[tri, _V1 + 1] - o1, tris_f[tri, _V1 + 2] - o2
    c0, c1, c2 = tris_f[tri, _V2] - o0, tris_f[tri, _V2 + 1] - o1, tris_f[tri, _V2 + 2] - o2
    # geometry.far_unit: taken here for every triangle (a layout without far coordinates never
    # passes FAR_COORD, where the kernel leaves the check out, so both decide alike)
    big = max(abs(a0), abs(a1), abs(a2), abs(b0), abs(b1), abs(b2), abs(c0), abs(c1), abs(c2))
    unit = _FAR_UNIT if big > _FAR_COORD else np.float32(1.0)
    a0, a1, a2, b0, b1, b2 = a0 * unit, a1 * unit, a2 * unit, b0 * unit, b1 * unit, b2 * unit
    c0, c1, c2 = c0 * unit, c1 * unit, c2 * unit
    az_, bz_, cz_ = _pick(a0, a1, a2, kz), _pick(b0, b1, b2, kz), _pick(c0, c1, c2, kz)
    ax_, ay_ = _pick(a0, a1, a2, kx) - sx * az_, _pick(a0, a1, a2, ky) - sy * az_
    bx_, by_ = _pick(b0, b1, b2, kx) - sx * bz_, _pick(b0, b1, b2, ky) - sy * bz_
    cx_, cy_ = _pick(c0, c1, c2, kx) - sx * cz_, _pick(c0, c1, c2, ky) - sy * cz_
    U = cx_ * by_ - cy_ * bx_
    V = ax_ * cy_ - ay_ * cx_
    W = bx_ * ay_ - by_ * ax_
    shear = abs(sx) + abs(sy)
    mA = abs(_pick(a0, a1, a2, kx)) + abs(_pick(a0, a1, a2, ky)) + abs(az_) * shear
    mB = abs(_pick(b0, b1, b2, kx)) + abs(_pick(b0, b1, b2, ky)) + abs(bz_) * shear
    mC = abs(_pick(c0, c1, c2, kx)) + abs(_pick(c0, c1, c2, ky)) + abs(cz_) * shear
    unsure_u = abs(U) <= _EDGE * (mB * mC)
    unsure_v = abs(V) <= _EDGE * (mC * mA)
    unsure_w = abs(W) <= _EDGE * (mA * mB)
    if unsure_u or unsure_v or unsure_w:
        p0, p1, p2 = np.float64(o0), np.float64(o1), np.float64(o2)
        d0, d1, d2 = np.float64(fst[s, F_D]), np.float64(fst[s, F_D + 1]), np.float64(fst[s, F_D + 2])
        dz64 = _pick(d0, d1, d2, kz)
        sx64, sy64 = _pick(d0, d1, d2, kx) / dz64, _pick(d0, d1, d2, ky) / dz64
        q = np.empty(6, np.float64)
        for j in range(3):
            base = (_V0, _V1, _V2)[j]
            e0 = np.float64(tris_f[tri, base]) - p0
            e1 = np.float64(tris_f[tri, base + 1]) - p1
            e2 = np.float64(tris_f[tri, base + 2]) - p2
            e0, e1, e2 = e0 * np.float64(unit), e1 * np.float64(unit), e2 * np.float64(unit)
            ez = _pick(e0, e1, e2, kz)
            q[2 * j] = _pick(e0, e1, e2, kx) - sx64 * ez
            q[2 * j + 1] = _pick(e0, e1, e2, ky) - sy64 * ez
        ax, ay, bx, by, cx, cy = q[0], q[1], q[2], q[3], q[4], q[5]
        if unsure_u:
            U = np.float32(cx * by - cy * bx)
        if unsure_v:
            V = np.float32(ax * cy - ay * cx)
        if unsure_w:
            W = np.float32(bx * ay - by * ax)
    outside = (U < 0 or V < 0 or W < 0) and (U > 0 or V > 0 or W > 0)
    det = U + V + W
    rcp = np.float32(1.0) / det if det != 0 else np.float32(np.inf)
    t = np.float32(np.inf)
    inside = (not outside) and det != 0
    if inside:
        n0, n1, n2 = tris_d[tri, _NRM], tris_d[tri, _NRM + 1], tris_d[tri, _NRM + 2]
        nv = n0 * (np.float64(tris_f[tri, _V0]) - np.float64(o0))
        nv = nv + n1 * (np.float64(tris_f[tri, _V0 + 1]) - np.float64(o1))
        nv = nv + n2 * (np.float64(tris_f[tri, _V0 + 2]) - np.float64(o2))
        nd = n0 * np.float64(fst[s, F_D]) + n1 * np.float64(fst[s, F_D + 1])
        nd = nd + n2 * np.float64(fst[s, F_D + 2])
        if nd != 0:
            t = np.float32(nv / nd)
    hit = inside and t > 0 and t < np.inf
    return hit, t, V * rcp, W * rcp, np.int64(tris_u[tri, TRI_FACE])


@numba.njit(cache=True, inline="always")
def _slab(rec, lo, hi, fst, s):
    tn, tf = np.float32(0.0), np.float32(np.inf)
    for c in range(3):
        o, inv = fst[s, F_O + c], fst[s, F_INV + c]
        t0 = (rec[lo + c] - o) * inv
        t1 = (rec[hi + c] - o) * inv
        tn = max(tn, min(t0, t1))
        tf = min(tf, max(t0, t1))
    return tn, tf


@numba.njit(cache=True, inline="always")
def _wide_node(rec, rec_u, k, net, fst, s, keys, links):
    """walk._wide_node for ray s: every child's slab test (hit_children_wide: the exit distance
    starts from t_best), entry distances clamped below FLT_MAX (misses inf), sorted with the
    network; keys/links[0] is the nearest. Returns (entries to push, link to go on with)."""
    t_best = fst[s, F_T]
    n_hit = 0
    for c in range(k):
        tn, tf = np.float32(0.0), t_best
        for a in range(3):
            o, inv = fst[s, F_O + a], fst[s, F_INV + a]
            t0 = (rec[a * k + c] - o) * inv
            t1 = (rec[(3 + a) * k + c] - o) * inv
            tn = max(tn, min(t0, t1))
            tf = min(tf, max(t0, t1))
        links[c] = np.int64(rec_u[6 * k + c])
        if tn <= tf * _FAR:
            keys[c] = min(tn, _FLT_MAX)
            n_hit += 1
        else:
            keys[c] = np.float32(np.inf)
    for p in range(net.shape[0]):
        a, b = net[p, 0], net[p, 1]
        if keys[b] < keys[a]:
            keys[a], keys[b] = keys[b], keys[a]
            links[a], links[b] = links[b], links[a]
    return (n_hit - 1 if n_hit > 1 else 0), (links[0] if n_hit > 0 else np.int64(_POP))


@numba.njit(cache=True)
def iterate(s, ls, bounded, use_global, cap, any_hit, cap_g, nodes_f, nodes_u, tris_f, tris_u, tris_d, treelet_first,
            node_treelet, fst, ist, loc_link, loc_t, g_link, g_t, req, branching, net, wkeys, wlinks):
    """One iteration of walk.walk's loop for the ray in slot s (active on entry), whose local entry
    stack is row `ls` of loc_link/loc_t (the lane it runs in). Writes the element index each load
    site read (req[site], NO_READ for none) and updates the ray's state. Returns the sites it read
    as a bit mask (bit k: site k). A wide tree (`branching` > 2) orders a node's children with the
    sorting network `net` (walk.SORT_NETWORKS, (pairs, 2)) in the scratch rows wkeys, wlinks."""
    for k in range(S_START):
        req[k] = NO_READ
    used = (1 << S_LOC_R_LINK) | (1 << S_LOC_R_T) | (1 << S_LOC_W_LINK) | (1 << S_LOC_W_T)
    ist[s, I_ITER] += 1
    active = True
    link = ist[s, I_LINK]
    # -- a triangle of the current leaf --
    if ist[s, I_TRI_CUR] < ist[s, I_TRI_END]:
        tri = ist[s, I_TRI_CUR]
        req[S_TRI] = tri
        used |= 1 << S_TRI
        hit, t, u, v, prim = _hit_triangle(tris_f, tris_u, tris_d, tri, fst, ist, s)
        t_best = fst[s, F_T]
        closer = hit and (t < t_best or (t == t_best and prim < ist[s, I_PRIM]))
        if closer:
            fst[s, F_T], fst[s, F_U], fst[s, F_V] = t, u, v
            ist[s, I_PRIM] = prim
            ist[s, I_HITS] += 1  # (a layer step writes each closer hit to the results at once)
            if use_global:  # (so does the tail: the layer modes' kernels, never per_ray's)
                ist[s, I_HITW] += 1
        ist[s, I_TRI_CUR] = tri + 1
        ist[s, I_TRI] += 1
        if any_hit and closer:
            ist[s, I_DONE] = 1
            active = False
    # -- the next entry --
    want = active and ist[s, I_TRI_CUR] >= ist[s, I_TRI_END] and link == _POP
    nl = ist[s, I_NL]
    from_local = want and nl > 0
    if from_local:
        nl -= 1
    req[S_LOC_R_LINK] = nl   # walk reads the local slot nl in every iteration (outside branches)
    req[S_LOC_R_T] = nl
    e_link, e_t = loc_link[ls, nl], loc_t[ls, nl]
    from_global = False
    sp = ist[s, I_SP]
    if use_global:
        from_global = want and not from_local and sp > 0
        if from_global:
            sp -= 1
            req[S_STACK_LINK] = s * cap_g + sp
            req[S_STACK_T] = s * cap_g + sp
            used |= (1 << S_STACK_LINK) | (1 << S_STACK_T)
            e_link, e_t = np.int64(g_link[s, sp]), g_t[s, sp]
    empty = want and not from_local and not from_global
    if empty:
        ist[s, I_DONE] = 1
        active = False
    if want:
        link = e_link if (active and e_t <= fst[s, F_T] * _FAR) else _POP
    if bounded and want and active and link != _POP and (link & _LEAF) == 0:
        is_exit = (link & _EXIT) != 0
        tre = (link & _PAYLOAD) if is_exit else ist[s, I_TRELET]
        if from_global and not is_exit:
            req[S_NODE_TRELET] = link & _PAYLOAD
            used |= 1 << S_NODE_TRELET
            tre = node_treelet[link & _PAYLOAD]
        if tre != ist[s, I_TRELET]:
            ist[s, I_NEXT] = tre
            active = False
    # -- a node: all children; on with the nearest, push the others (binary: the farther) --
    push = False
    far_link, far_t = np.int64(0), np.float32(0.0)
    n_push = 0
    if active and ist[s, I_TRI_CUR] >= ist[s, I_TRI_END] and link != _POP and (link & _LEAF) == 0 and branching > 2:
        payload = link & _PAYLOAD
        node = payload
        if (link & _EXIT) != 0:
            req[S_TF] = payload
            used |= 1 << S_TF
            node = treelet_first[payload]
        req[S_NODE] = node
        used |= 1 << S_NODE
        n_push, link = _wide_node(nodes_f[node], nodes_u[node], branching, net, fst, s, wkeys, wlinks)
        ist[s, I_INNER] += 1
        if bounded and link != _POP and (link & _LEAF) == 0 and (link & _EXIT) != 0:
            ist[s, I_NEXT] = link & _PAYLOAD
            active = False
    elif active and ist[s, I_TRI_CUR] >= ist[s, I_TRI_END] and link != _POP and (link & _LEAF) == 0:
        payload = link & _PAYLOAD
        node = payload
        if (link & _EXIT) != 0:
            req[S_TF] = payload
            used |= 1 << S_TF
            node = treelet_first[payload]
        req[S_NODE] = node
        used |= 1 << S_NODE
        rec = nodes_f[node]
        t_best = fst[s, F_T]
        tn_l, tf_l = _slab(rec, _LO0, _HI0, fst, s)
        tn_r, tf_r = _slab(rec, _LO1, _HI1, fst, s)
        hit_l = tn_l <= tf_l * _FAR and tn_l <= t_best * _FAR
        hit_r = tn_r <= tf_r * _FAR and tn_r <= t_best * _FAR
        link_l, link_r = np.int64(nodes_u[node, _LK0]), np.int64(nodes_u[node, _LK1])
        ist[s, I_INNER] += 1
        right_first = hit_r and ((not hit_l) or tn_r < tn_l)
        push = hit_l and hit_r
        far_link, far_t = (link_l, tn_l) if right_first else (link_r, tn_r)
        link = (link_r if right_first else link_l) if (hit_l or hit_r) else _POP
        if bounded and link != _POP and (link & _LEAF) == 0 and (link & _EXIT) != 0:
            ist[s, I_NEXT] = link & _PAYLOAD
            active = False
    if branching > 2:
        if n_push > 0:  # (walk: push j goes to slot nl + n_push - 1 - j, the nearest on top)
            for j in range(branching - 1):
                slot = nl + n_push - (j + 1) if j < n_push else cap
                site_link = S_LOC_W_LINK if j == 0 else S_PUSH + 2 * (j - 1)
                site_t = S_LOC_W_T if j == 0 else S_PUSH + 2 * (j - 1) + 1
                req[site_link] = slot
                req[site_t] = slot
                used |= (1 << site_link) | (1 << site_t)
                loc_link[ls, slot] = wlinks[j + 1]
                loc_t[ls, slot] = wkeys[j + 1]
            nl += n_push
    else:
        slot = nl if push else cap
        req[S_LOC_W_LINK] = slot
        req[S_LOC_W_T] = slot
        loc_link[ls, slot] = far_link
        loc_t[ls, slot] = far_t
        if push:
            nl += 1
    # -- a leaf: its triangles from the next iteration on --
    if active and link != _POP and (link & _LEAF) != 0:
        ist[s, I_TRI_CUR] = link & _FIRST
        ist[s, I_TRI_END] = (link & _FIRST) + ((link & 0x7FFFFFFF) >> _SHIFT)
        link = _POP
        ist[s, I_LEAF] += 1
    ist[s, I_LINK] = link
    ist[s, I_SP] = sp
    ist[s, I_NL] = nl
    ist[s, I_ACTIVE] = 1 if active else 0
    return used


@numba.njit(cache=True)
def _start_lane(s, ist):
    """What walk sets up per call: an empty local stack, no leaf at hand, the step's treelet."""
    ist[s, I_TRI_CUR] = 0
    ist[s, I_TRI_END] = 0
    ist[s, I_NL] = 0
    ist[s, I_ACTIVE] = 1
    ist[s, I_NEXT] = ist[s, I_TRELET]
    ist[s, I_STEPS] += 1
    ist[s, I_HITS] = 0


@numba.njit(cache=True, inline="always")
def _write_back(s, ls, ist, loc_link, loc_t, g_link, g_t):
    """walk's spill for one ray whose step ended and that goes on: the entries it still holds go
    above its global stack as its lane ends, as the step kernel writes them (so the local stacks
    are per lane, not per ray). Returns how many."""
    nl = ist[s, I_NL]
    sp = ist[s, I_SP]
    for k in range(nl):
        g_link[s, sp + k] = np.uint32(loc_link[ls, k])
        g_t[s, sp + k] = loc_t[ls, k]
    ist[s, I_SP] = sp + nl
    ist[s, I_SPILL] += nl
    return nl


@numba.njit(cache=True, inline="always")
def _start_index(by, s, lane, prev_pos, ist, bounded):
    if by == BY_LINK_NODE:
        link = ist[s, I_LINK]
        return link & _PAYLOAD if bounded and (link & _EXIT) == 0 else NO_READ
    return s if by == BY_SLOT else (lane if by == BY_LANE else (prev_pos[s] if by == BY_PREVIOUS_LANE else NO_READ))


@numba.njit(cache=True, nogil=True)
def run_kernel(order, W, units, resident, block_warps, bounded, use_global, cap, any_hit, cap_g, branching, net,
               nodes_f, nodes_u, tris_f, tris_u, tris_d, treelet_first, node_treelet,
               fst, ist, loc_link, loc_t, g_link, g_t,
               site_base, site_bytes, site_local, start_sites, start_by_pos, prev_pos, seg_bytes,
               tags, stamps, dirty, params, counts, clock, tally, levels_hit, lanes_out, loads):
    """One kernel launch over the rays `order` (slots, in the launch's order), lane j in warp j // W.
    Warps go to units (SMs, cores) a block of `block_warps` at a time, round-robin; each unit keeps
    `resident` warps and runs them round-robin, one loop iteration per turn; units take turns too, so
    the shared cache level sees their requests interleaved. Every warp-iteration's loads are coalesced
    per site into segments (transactions), each one access to the cache model (then, on a CPU, its
    stack frame: memstores.frame_pass). tally[site] += (transactions, lane requests); levels_hit[site,
    level] += transactions served by that level (last column: DRAM); lanes_out += (warp-iterations,
    active lane-iterations, entries written back, closer hits found). In a bounded step the entries a
    ray that goes on still holds go to its global stack when its lane ends (walk's spill)."""
    n = len(order)
    n_warps = (n + W - 1) // W
    # Each unit's warps, in launch order.
    unit_of = np.empty(n_warps, np.int64)
    for w in range(n_warps):
        unit_of[w] = (w // block_warps) % units
    queue = np.argsort(unit_of, kind="mergesort")
    q_start = np.zeros(units + 1, np.int64)
    for w in range(n_warps):
        q_start[unit_of[w] + 1] += 1
    for u in range(units):
        q_start[u + 1] += q_start[u]
    q_next = q_start[:-1].copy()
    res_warp = np.full((units, resident), -1, np.int64)
    req = np.empty((W, SITES), np.int64)
    lane = np.empty(W, np.int64)
    every = np.ones(W, np.bool_)
    addr = np.empty(W, np.int64)
    segs = np.empty(W * (max(site_bytes.max() // seg_bytes, 6) + 2), np.int64)  # (coalesce's bound)
    wkeys = np.empty(MAX_PUSH + 1, np.float32)
    wlinks = np.empty(MAX_PUSH + 1, np.int64)
    n_levels = levels_hit.shape[1] - 1
    n_start = len(start_sites)
    remaining = n_warps
    while remaining > 0:
        for u in range(units):
            for r in range(resident):
                w = res_warp[u, r]
                fresh = False
                if w < 0:
                    if q_next[u] >= q_start[u + 1]:
                        continue
                    w = queue[q_next[u]]
                    q_next[u] += 1
                    res_warp[u, r] = w
                    fresh = True
                slot_id = u * resident + r   # local memory is reused by the warp that takes the slot next
                lo = w * W
                hi = min(n, lo + W)
                live = 0        # lanes that run this iteration: lane[0 .. live)
                going = 0       # ... and are still active after it
                used = 0
                for j in range(hi - lo):
                    s = order[lo + j]
                    if fresh:
                        _start_lane(s, ist)
                    if ist[s, I_ACTIVE] == 0:
                        continue
                    lane[live] = j
                    live += 1
                    ls = slot_id * W + j
                    for k in range(S_START, S_START + n_start):  # iterate() resets the others
                        req[j, k] = NO_READ
                    memstores.reset(req[j])
                    if fresh:
                        for k in range(n_start):  # the ray (and its state) at the kernel's start
                            req[j, S_START + k] = _start_index(start_by_pos[k], s, lo + j, prev_pos, ist, bounded)
                            used |= 1 << (S_START + k)
                    used |= iterate(s, ls, bounded, use_global, cap, any_hit, cap_g, nodes_f, nodes_u, tris_f, tris_u,
                                    tris_d, treelet_first, node_treelet, fst, ist, loc_link, loc_t, g_link, g_t, req[j],
                                    branching, net, wkeys, wlinks)
                    if ist[s, I_ACTIVE] != 0:
                        going += 1
                    else:
                        lanes_out[3] += ist[s, I_HITS]
                        used |= memstores.lane_end(s, lo + j, bounded, use_global, ist, req[j])
                        if bounded and ist[s, I_DONE] == 0:  # (the spill's stores before the write-back moves sp)
                            memstores.spill_stores(s, ist, cap_g, site_base, seg_bytes, u, tags, stamps, dirty, params,
                                                   counts, clock, tally, levels_hit, loads, addr, every, segs)
                            lanes_out[2] += _write_back(s, ls, ist, loc_link, loc_t, g_link, g_t)
                lanes_out[0] += 1
                lanes_out[1] += live
                for k in range(SITES):
                    if (used >> k) & 1 == 0:
                        continue
                    size = site_bytes[k]
                    n_req = 0
                    for i in range(live):
                        j = lane[i]
                        e = req[j, k]
                        if e < 0:
                            continue
                        loads[order[lo + j], k] += 1  # (per ray: locality.check_trace holds it against the kernel)
                        if site_local[k]:   # interleaved per warp: lane j's word e
                            addr[n_req] = site_base[k] + ((slot_id * (cap + 1) + e) * W + j) * size
                        else:
                            addr[n_req] = site_base[k] + e * size
                        n_req += 1
                    if n_req == 0:
                        continue
                    tally[k, 1] += n_req
                    m, store = coalesce(addr, every, n_req, size, seg_bytes, segs), k in STORE_SITES
                    tally[k, 0] += m
                    for i in range(m):
                        # cache_access answers -1 only for a negative address or a unit out of range,
                        # which this loop never makes; replay() checks the counts add up.
                        lvl = cache_access(tags, stamps, dirty, params, counts, clock, u, segs[i] * seg_bytes,
                                           store)
                        levels_hit[k, min(lvl, n_levels)] += 1
                memstores.frame_pass(slot_id, site_base, site_bytes, seg_bytes, u, tags, stamps, dirty, params, counts,
                                     clock, tally, levels_hit)
                still = going > 0
                if not still:
                    res_warp[u, r] = -1
                    remaining -= 1


@numba.njit(cache=True)
def next_treelets(order, ist, finished):
    """The sort key of each ray after a step: the treelet it enters next, `finished` when done."""
    keys = np.empty(len(order), np.int64)
    for j in range(len(order)):
        s = order[j]
        if ist[s, I_DONE] != 0:
            keys[j] = finished
        else:
            keys[j] = ist[s, I_NEXT]
            ist[s, I_TRELET] = ist[s, I_NEXT]
    return keys


numba_cache.follow(globals(), cachesim, memsites, memstores, layout, geometry)  # what the replay compiles in
