"""Binned SAH builder: triangles in, a binary BVH in level (breadth-first) order out."""
from __future__ import annotations

from dataclasses import dataclass

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


def _segment_ids(counts: np.ndarray) -> np.ndarray:
    return np.repeat(np.arange(len(counts)), counts)


def _gather_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Indices start[i] .. start[i]+count[i]-1 for every i, concatenated."""
    total = int(counts.sum())
    offs = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(offs - starts, counts)


def _half_area(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Half surface area of boxes stored component-major: lo, hi of shape (3, ...)."""
    e = np.maximum(hi - lo, 0.0)
    return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]


def _best_binned_split(cen, tlo, thi, seg, offs, counts):
    """For each node (segment), the SAH-best (axis, bin) split; cost inf where none exists."""
    k = len(counts)
    # Bin tables cost O(k * BINS): deep levels of small nodes get fewer bins, so a level's
    # tables never outgrow its triangle count by much.
    mean = cen.shape[1] / k
    BINS = int(min(MAX_BINS, max(4, 2 ** np.ceil(np.log2(mean)))))
    cmin = np.minimum.reduceat(cen, offs, axis=1)
    cmax = np.maximum.reduceat(cen, offs, axis=1)
    ext = cmax - cmin
    best_cost = np.full(k, np.inf)
    best_axis = np.zeros(k, np.int64)
    best_bin = np.zeros(k, np.int64)
    bins_of = np.empty((3, cen.shape[1]), np.int64)
    for axis in range(3):
        e = ext[axis]
        scale = np.where(e > 0, np.float32(BINS) / np.where(e > 0, e, 1.0), 0.0).astype(np.float32)
        b = ((cen[axis] - cmin[axis][seg]) * scale[seg]).astype(np.int64)
        np.clip(b, 0, BINS - 1, out=b)
        bins_of[axis] = b
        # Bin-major tables (BINS, k): prefix scans over bins then run over contiguous rows.
        key = b * k + seg
        n = np.bincount(key, minlength=k * BINS).reshape(BINS, k)
        blo = np.full((3, BINS * k), np.inf, np.float32)
        bhi = np.full((3, BINS * k), -np.inf, np.float32)
        for c in range(3):
            np.minimum.at(blo[c], key, tlo[c])
            np.maximum.at(bhi[c], key, thi[c])
        blo = blo.reshape(3, BINS, k)
        bhi = bhi.reshape(3, BINS, k)
        # Split after bin i: left = bins 0..i, right = bins i+1..BINS-1.
        lcount = np.cumsum(n, axis=0)[:-1]
        rcount = n.sum(axis=0) - lcount
        larea = _half_area(np.minimum.accumulate(blo, axis=1), np.maximum.accumulate(bhi, axis=1))[:-1]
        rarea = _half_area(np.minimum.accumulate(blo[:, ::-1], axis=1),
                           np.maximum.accumulate(bhi[:, ::-1], axis=1))[::-1][1:]
        with np.errstate(invalid="ignore"):
            cost = lcount * larea + rcount * rarea
        cost = np.where((lcount > 0) & (rcount > 0), cost, np.inf)
        i = np.argmin(cost, axis=0)
        c = cost[i, np.arange(k)]
        better = c < best_cost
        best_cost = np.where(better, c, best_cost)
        best_axis = np.where(better, axis, best_axis)
        best_bin = np.where(better, i, best_bin)
    return best_cost, best_axis, best_bin, bins_of


def build_binned_sah(tri_lo: np.ndarray, tri_hi: np.ndarray, leaf_size: int) -> BinaryBVH:
    """Level-synchronous binned SAH: every level splits all its open nodes with whole-array numpy ops.

    Every node with more than `leaf_size` triangles is split. Where the binned SAH finds no split
    (all centroids in one bin) or the node is close to MAX_DEPTH, the split halves the node's
    triangle range instead, so depth stays below MAX_DEPTH on any input.
    """
    f = len(tri_lo)
    # Component-major (3, F) copies kept in `perm` order, so each level reads node ranges
    # sequentially instead of gathering triangles from all over memory.
    lo_p = np.ascontiguousarray(tri_lo.T, np.float32)
    hi_p = np.ascontiguousarray(tri_hi.T, np.float32)
    cen_p = (lo_p + hi_p) * np.float32(0.5)
    perm = np.arange(f, dtype=np.int64)

    lo_parts, hi_parts, left_parts, start_parts, count_parts, depth_parts = [], [], [], [], [], []
    n_nodes = 1
    level_start = np.zeros(1, np.int64)
    level_count = np.full(1, f, np.int64)
    depth = 0
    while len(level_start):
        idx = _gather_ranges(level_start, level_count)
        offs = np.cumsum(level_count) - level_count
        lo_parts.append(np.minimum.reduceat(lo_p[:, idx], offs, axis=1).T)
        hi_parts.append(np.maximum.reduceat(hi_p[:, idx], offs, axis=1).T)
        split = level_count > leaf_size
        left = np.full(len(level_start), -1, np.int64)
        start_parts.append(level_start)
        count_parts.append(level_count)
        depth_parts.append(np.full(len(level_start), depth, np.int64))
        left_parts.append(left)
        if not split.any():
            break
        # Work only on the triangles of nodes being split.
        s_start, s_count = level_start[split], level_count[split]
        s_idx = _gather_ranges(s_start, s_count)
        s_offs = np.cumsum(s_count) - s_count
        seg = _segment_ids(s_count)
        s_lo, s_hi, s_cen, s_tris = lo_p[:, s_idx], hi_p[:, s_idx], cen_p[:, s_idx], perm[s_idx]
        cost, axis, sbin, bins_of = _best_binned_split(s_cen, s_lo, s_hi, seg, s_offs, s_count)
        levels_needed = np.ceil(np.log2(np.maximum(s_count / leaf_size, 1.0))).astype(np.int64)
        median = ~np.isfinite(cost) | (depth + 1 + levels_needed >= MAX_DEPTH - 1)
        rank = np.arange(len(s_idx)) - s_offs[seg]
        goes_left = np.where(median[seg], rank < (s_count // 2)[seg],
                             bins_of[axis[seg], np.arange(len(s_idx))] <= sbin[seg])
        # Stable partition of each node's range: left triangles first.
        gl = goes_left.astype(np.int64)
        excl_l = np.cumsum(gl) - gl
        rank_l = excl_l - excl_l[s_offs][seg]
        n_left = np.add.reduceat(gl, s_offs)
        pos = s_start[seg] + np.where(goes_left, rank_l, n_left[seg] + (rank - rank_l))
        perm[pos] = s_tris
        lo_p[:, pos] = s_lo
        hi_p[:, pos] = s_hi
        cen_p[:, pos] = s_cen
        # Children of this level's split nodes, in order, form the next level.
        n_split = len(s_start)
        left[split] = n_nodes + 2 * np.arange(n_split)
        n_nodes += 2 * n_split
        level_start = np.stack([s_start, s_start + n_left], 1).reshape(-1)
        level_count = np.stack([n_left, s_count - n_left], 1).reshape(-1)
        depth += 1

    return BinaryBVH(lo=np.concatenate(lo_parts), hi=np.concatenate(hi_parts),
                     left=np.concatenate(left_parts), start=np.concatenate(start_parts),
                     count=np.concatenate(count_parts), depth=np.concatenate(depth_parts), perm=perm)
