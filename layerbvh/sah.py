"""Binned SAH builder: triangles in, a binary BVH in level (breadth-first) order out."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

MAX_BINS = 16
MAX_DEPTH = 64  # hard bound on node depth; the builder switches to median splits near it


@dataclass
class BinaryBVH:
    """A binary BVH, one row per node, nodes in level order (root = 0, parents before children).

    lo, hi   float32 (M, 3)  node bounds
    left     int64   (M,)    left child node, -1 for a leaf; the right child is left + 1
    start    int64   (M,)    first entry of the node's triangles in `perm`
    count    int64   (M,)    number of triangles below the node
    depth    int64   (M,)    root has depth 0
    perm     int64   (F,)    triangle ids, each node's triangles contiguous
    """

    lo: np.ndarray
    hi: np.ndarray
    left: np.ndarray
    start: np.ndarray
    count: np.ndarray
    depth: np.ndarray
    perm: np.ndarray

    @property
    def is_leaf(self) -> np.ndarray:
        return self.left < 0


@numba.njit(cache=True)
def triangle_bounds(vertices, faces):
    """Per-triangle bounds (F, 3) lo and hi, float32."""
    f = len(faces)
    lo = np.empty((f, 3), np.float32)
    hi = np.empty((f, 3), np.float32)
    for i in range(f):
        for a in range(3):
            x0, x1, x2 = vertices[faces[i, 0], a], vertices[faces[i, 1], a], vertices[faces[i, 2], a]
            lo[i, a] = min(x0, min(x1, x2))
            hi[i, a] = max(x0, max(x1, x2))
    return lo, hi


@numba.njit(cache=True, inline="always")
def _bin_of(x, cmin, scale, nb):
    """Bin of centroid coordinate x; binning and partition must both use exactly this."""
    return min(max(int((x - cmin) * scale), 0), nb - 1)


@numba.njit(cache=True)
def _best_split(s, c, lo, hi, cen, cmin, cmax, blo, bhi, bcnt, rarea, rcnt):
    """SAH-best split of triangles s..s+c (centroid bounds cmin, cmax) over binned centroids.

    Returns (axis, last bin of the left side, bins, scale, left count); axis -1 if no split
    separates the centroids. Scratch arrays are the caller's: blo/bhi (3, MAX_BINS, 3),
    bcnt (3, MAX_BINS), rarea/rcnt (MAX_BINS)."""
    # Small nodes get fewer bins: the sweep is O(bins) per node and deep levels hold most nodes.
    nb = MAX_BINS if c >= MAX_BINS else max(4, c)
    scale = np.zeros(3, np.float32)
    for a in range(3):
        e = cmax[a] - cmin[a]
        if e > 0:
            scale[a] = np.float32(nb) / e
    for a in range(3):
        for b in range(nb):
            bcnt[a, b] = 0
            for k in range(3):
                blo[a, b, k] = np.inf
                bhi[a, b, k] = -np.inf
    for t in range(s, s + c):
        for a in range(3):
            b = _bin_of(cen[t, a], cmin[a], scale[a], nb)
            bcnt[a, b] += 1
            for k in range(3):
                blo[a, b, k] = min(blo[a, b, k], lo[t, k])
                bhi[a, b, k] = max(bhi[a, b, k], hi[t, k])
    best_cost, best_axis, best_bin, best_left = np.inf, -1, 0, 0
    for a in range(3):
        if scale[a] == 0:
            continue
        # Right-to-left sweep: rarea[b], rcnt[b] describe bins b..nb-1.
        x0, y0, z0, x1, y1, z1, n = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf, 0
        for b in range(nb - 1, 0, -1):
            x0, y0, z0 = min(x0, blo[a, b, 0]), min(y0, blo[a, b, 1]), min(z0, blo[a, b, 2])
            x1, y1, z1 = max(x1, bhi[a, b, 0]), max(y1, bhi[a, b, 1]), max(z1, bhi[a, b, 2])
            n += bcnt[a, b]
            ex, ey, ez = max(x1 - x0, 0.0), max(y1 - y0, 0.0), max(z1 - z0, 0.0)
            rarea[b] = ex * ey + ey * ez + ez * ex
            rcnt[b] = n
        x0, y0, z0, x1, y1, z1, n = np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf, 0
        for b in range(nb - 1):  # split after bin b: left = 0..b, right = b+1..nb-1
            x0, y0, z0 = min(x0, blo[a, b, 0]), min(y0, blo[a, b, 1]), min(z0, blo[a, b, 2])
            x1, y1, z1 = max(x1, bhi[a, b, 0]), max(y1, bhi[a, b, 1]), max(z1, bhi[a, b, 2])
            n += bcnt[a, b]
            if n == 0 or rcnt[b + 1] == 0:
                continue
            ex, ey, ez = max(x1 - x0, 0.0), max(y1 - y0, 0.0), max(z1 - z0, 0.0)
            cost = n * (ex * ey + ey * ez + ez * ex) + rcnt[b + 1] * rarea[b + 1]
            if cost < best_cost:
                best_cost, best_axis, best_bin, best_left = cost, a, b, n
    return best_axis, best_bin, nb, scale, best_left


@numba.njit(parallel=True, cache=True)
def _split_level(start, count, median, leaf_size, lo, hi, cen, perm, t_lo, t_hi, t_cen, t_perm, chunks):
    """Bounds of every node of a level, and the split of every node over `leaf_size` triangles.

    Each node's triangle range [start, start+count) of (lo, hi, cen, perm) is partitioned in
    place, stably, left child's triangles first. Returns (node lo, node hi, left count; -1 for
    leaves, -2 if the partition disagrees with the bin counts). Nodes are disjoint ranges, so
    they run in parallel; chunks own their scratch."""
    k = len(start)
    node_lo = np.empty((k, 3), np.float32)
    node_hi = np.empty((k, 3), np.float32)
    n_left = np.full(k, -1, np.int64)
    chunks = min(k, chunks)
    for ch in numba.prange(chunks):
        blo = np.empty((3, MAX_BINS, 3), np.float32)
        bhi = np.empty((3, MAX_BINS, 3), np.float32)
        bcnt = np.empty((3, MAX_BINS), np.int64)
        rarea = np.empty(MAX_BINS, np.float32)
        rcnt = np.empty(MAX_BINS, np.int64)
        cmin = np.empty(3, np.float32)
        cmax = np.empty(3, np.float32)
        for i in range(ch * k // chunks, (ch + 1) * k // chunks):
            s, c = start[i], count[i]
            for a in range(3):
                node_lo[i, a], node_hi[i, a], cmin[a], cmax[a] = np.inf, -np.inf, np.inf, -np.inf
            for t in range(s, s + c):
                for a in range(3):
                    node_lo[i, a] = min(node_lo[i, a], lo[t, a])
                    node_hi[i, a] = max(node_hi[i, a], hi[t, a])
                    cmin[a] = min(cmin[a], cen[t, a])
                    cmax[a] = max(cmax[a], cen[t, a])
            if c <= leaf_size:
                continue
            axis, sbin, nb, scale, nl = -1, 0, 0, cmax, 0  # scale unused without an axis
            if not median[i]:
                axis, sbin, nb, scale, nl = _best_split(s, c, lo, hi, cen, cmin, cmax, blo, bhi, bcnt, rarea, rcnt)
            if axis < 0:  # median split, or no SAH split separates the centroids: halve the range
                nl = c // 2
            # Stable partition through the scratch copies, then back.
            li, ri = s, s + nl
            for t in range(s, s + c):
                if axis < 0:
                    left = t - s < nl
                else:
                    left = _bin_of(cen[t, axis], cmin[axis], scale[axis], nb) <= sbin
                if left:
                    d = li
                    li += 1
                else:
                    d = ri
                    ri += 1
                t_perm[d] = perm[t]
                for a in range(3):
                    t_lo[d, a], t_hi[d, a], t_cen[d, a] = lo[t, a], hi[t, a], cen[t, a]
            if li != s + nl or ri != s + c:  # the bin counts and the partition disagree
                n_left[i] = -2
                continue
            for t in range(s, s + c):
                perm[t] = t_perm[t]
                for a in range(3):
                    lo[t, a], hi[t, a], cen[t, a] = t_lo[t, a], t_hi[t, a], t_cen[t, a]
            n_left[i] = nl
    return node_lo, node_hi, n_left


def build_binned_sah(tri_lo: np.ndarray, tri_hi: np.ndarray, leaf_size: int) -> BinaryBVH:
    """Level-synchronous binned SAH: each level's nodes are split in parallel (numba kernels).

    Every node with more than `leaf_size` triangles is split. Where the binned SAH finds no split
    (all centroids in one bin) or the node is close to MAX_DEPTH, the split halves the node's
    triangle range instead, so depth stays below MAX_DEPTH on any input.
    """
    f = len(tri_lo)
    # Triangle bounds and centroids are kept in `perm` order, so each node reads its own
    # contiguous range; the t_* arrays are the partition's scratch. Copies: the partition
    # reorders them in place and the caller's arrays must stay as they were.
    lo = np.array(tri_lo, np.float32, order="C")
    hi = np.array(tri_hi, np.float32, order="C")
    cen = (lo + hi) * np.float32(0.5)
    perm = np.arange(f, dtype=np.int64)
    t_lo, t_hi, t_cen, t_perm = np.empty_like(lo), np.empty_like(hi), np.empty_like(cen), np.empty_like(perm)

    lo_parts, hi_parts, left_parts, start_parts, count_parts, depth_parts = [], [], [], [], [], []
    n_nodes = 1
    level_start = np.zeros(1, np.int64)
    level_count = np.full(1, f, np.int64)
    depth = 0
    while len(level_start):
        levels_needed = np.ceil(np.log2(np.maximum(level_count / leaf_size, 1.0))).astype(np.int64)
        median = depth + 1 + levels_needed >= MAX_DEPTH - 1
        node_lo, node_hi, n_left = _split_level(level_start, level_count, median, leaf_size,
                                                lo, hi, cen, perm, t_lo, t_hi, t_cen, t_perm,
                                                64 * numba.get_num_threads())
        if np.any(n_left == -2):
            raise RuntimeError("binned SAH: a node's partition disagrees with its bin counts (floating-point bug)")
        split = n_left >= 0
        left = np.full(len(level_start), -1, np.int64)
        left[split] = n_nodes + 2 * np.arange(int(split.sum()))
        lo_parts.append(node_lo)
        hi_parts.append(node_hi)
        start_parts.append(level_start)
        count_parts.append(level_count)
        depth_parts.append(np.full(len(level_start), depth, np.int64))
        left_parts.append(left)
        # Children of this level's split nodes, in order, form the next level.
        s_start, s_count, s_left = level_start[split], level_count[split], n_left[split]
        n_nodes += 2 * len(s_start)
        level_start = np.stack([s_start, s_start + s_left], 1).reshape(-1)
        level_count = np.stack([s_left, s_count - s_left], 1).reshape(-1)
        depth += 1

    return BinaryBVH(lo=np.concatenate(lo_parts), hi=np.concatenate(hi_parts),
                     left=np.concatenate(left_parts), start=np.concatenate(start_parts),
                     count=np.concatenate(count_parts), depth=np.concatenate(depth_parts), perm=perm)
