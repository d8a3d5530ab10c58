"""Re-laying a binary BVH out as a Layer BVH (layout.py's byte layout): treelets cut by height, collapsed to the
branching, written breadth-first treelet after treelet, with the triangle, leaf and instance records."""
from __future__ import annotations

import time

import numba
import numpy as np

from . import layout, numba_cache
from .collapse import collapse
from .layout import (EMPTY_BOX, EMPTY_LINK, EXIT_BIT, INSTANCE_COUNT, LEAF_COUNT, LEAF_FIRST, LEAF_UINTS, TRI_FACE,
                     TRI_FLOATS, TRI_NORMAL, TRI_VERTEX, LayerLayout, instance_link, leaf_link, node_format,
                     treelet_levels)
from .sah import BinaryBVH, build_binned_sah, triangle_bounds


def _wrap_leaf_root(b: BinaryBVH) -> BinaryBVH:
    """A BVH whose root is a leaf gets an inner root over (that leaf, an empty leaf),
    so every traversal starts at an inner node."""
    lo = np.concatenate([b.lo[:1], b.lo[:1], b.lo[:1]])
    hi = np.concatenate([b.hi[:1], b.hi[:1], b.lo[:1]])
    n = int(b.count[0])
    return BinaryBVH(lo=lo, hi=hi, left=np.array([1, -1, -1]), start=np.array([0, 0, n]),
                     count=np.array([n, n, 0]), depth=np.array([0, 1, 1]), perm=b.perm)


def to_layer_layout(b: BinaryBVH, vertices: np.ndarray | None, faces: np.ndarray | None, height: int,
                    branching: int = 2) -> LayerLayout:
    """Collapse `b` to `branching` children per node (collapse.collapse; 2 keeps it binary), cut
    it into treelets of at most treelet_levels(height, branching) levels of that tree (height
    counts binary levels) and lay it out for traversal.

    With vertices and faces None, `b` is a top level over instances (built with leaf size 1):
    each leaf's link is the instance link of its one primitive (an empty leaf keeps an empty
    triangle range) and there are no triangle records."""
    over_instances = vertices is None
    fmt = node_format(branching)
    if b.left[0] < 0:
        b = _wrap_leaf_root(b)
    m = len(b.left)
    wide = collapse(b, branching)
    kids, is_node = wide.kids, wide.is_node
    # Breadth-first over the wide tree, one vectorized pass per level: `bfs` lists its inner
    # nodes, `leaf_bfs` its leaves, each in the order a breadth-first walk meets them.
    depth = np.full(m, -1, np.int64)
    parent = np.full(m, -1, np.int64)
    frontier, levels, leaf_levels, d = np.zeros(1, np.int64), [], [], 0
    while len(frontier):
        depth[frontier] = d
        levels.append(frontier)
        ch = kids[frontier].reshape(-1)
        par = np.repeat(frontier, branching)
        real = ch >= 0
        ch, par = ch[real], par[real]
        parent[ch] = par
        depth[ch] = d + 1
        leaf_levels.append(ch[~is_node[ch]])
        frontier = ch[is_node[ch]]
        d += 1
    bfs = np.concatenate(levels)
    leaf_bfs = np.concatenate(leaf_levels)
    # Treelet roots are the inner nodes at depths 0, L, 2L, ... (L levels per treelet);
    # numbering them in breadth-first order numbers treelets breadth-first, and a stable sort by
    # treelet keeps each treelet's nodes breadth-first. Leaves belong to their parent's treelet
    # (a leaf at a treelet boundary stays with its parent).
    is_root = np.zeros(m, np.bool_)
    is_root[bfs] = depth[bfs] % treelet_levels(height, branching) == 0
    root_rank = np.full(m, -1, np.int64)
    root_rank[bfs[is_root[bfs]]] = np.arange(int(is_root.sum()))
    tre = np.full(m, -1, np.int64)
    for lev in levels:  # parents' levels come first (the root is its own treelet 0)
        tre[lev] = np.where(is_root[lev], root_rank[lev], tre[np.maximum(parent[lev], 0)])
    tre[leaf_bfs] = tre[parent[leaf_bfs]]

    order = bfs[np.argsort(tre[bfs], kind="stable")]
    new_idx = np.full(m, -1, np.int64)
    new_idx[order] = np.arange(len(order))
    leaf_order = leaf_bfs[np.argsort(tre[leaf_bfs], kind="stable")]
    n_treelets = int(is_root.sum())

    # Triangles in leaf order: leaf i covers tris[first_i : first_i + count_i].
    counts = b.count[leaf_order]
    first = np.cumsum(counts) - counts
    leaf_first = np.zeros(m, np.int64)
    leaf_first[leaf_order] = first
    is_leaf = np.zeros(m, np.bool_)
    is_leaf[leaf_bfs] = True

    # The link each node of the wide tree is reached by, from its one parent.
    in_tree = np.zeros(m, np.bool_)
    in_tree[bfs[1:]] = True
    in_tree[leaf_bfs] = True
    nodes_in = np.nonzero(in_tree)[0]
    if over_instances:
        one = b.perm[np.minimum(b.start[nodes_in], max(len(b.perm) - 1, 0))].astype(np.uint32)
        as_leaf = np.where(b.count[nodes_in] == 1, instance_link(one), leaf_link(np.uint32(0), np.uint32(0)))
    else:
        as_leaf = leaf_link(leaf_first[nodes_in].astype(np.uint32), b.count[nodes_in].astype(np.uint32))
    child_link = np.zeros(m, np.uint32)
    child_link[nodes_in] = np.where(
        is_leaf[nodes_in], as_leaf,
        np.where(tre[nodes_in] != tre[parent[nodes_in]], EXIT_BIT | tre[nodes_in].astype(np.uint32),
                 new_idx[nodes_in].astype(np.uint32))).astype(np.uint32)

    rec = np.zeros((len(order), fmt.floats), np.float32)
    # Child boxes are stored one float step larger on every side. A ray with a zero direction
    # component that lies exactly in a box's face plane gets (hi - o) * inv = 0 there (inv is
    # finite, geometry.MIN_RCP_INPUT), an empty slab interval, and would miss the closed box
    # and the triangles touching that face: a tie (a hit on a shared edge) would then go to
    # whichever triangle's box happens not to end there, so the answer would depend on the
    # tree. One step out, such a ray is strictly inside the slab; a ray in the widened face
    # plane lies outside the true box and can hit nothing in it.
    lo_out = np.nextafter(b.lo, np.float32(-np.inf))
    hi_out = np.nextafter(b.hi, np.float32(np.inf))
    _node_records(order, kids, lo_out, hi_out, child_link, np.array(fmt.lo), np.array(fmt.hi), np.array(fmt.link),
                  np.float32(EMPTY_BOX), EMPTY_LINK, rec, rec.view(np.uint32))
    real = kids[order] >= 0
    rec[:, fmt.depth] = depth[order]
    rec[:, fmt.children] = real.sum(1)

    tri_ids = b.perm[_ranges(b.start[leaf_order], counts)]
    tri = np.zeros((0 if over_instances else len(tri_ids), TRI_FLOATS), np.float32)
    if not over_instances:
        _triangle_records(vertices, faces, tri_ids, tri, tri.view(np.uint32), tri.view(np.float64))

    tre_first = np.searchsorted(tre[order], np.arange(n_treelets + 1)).astype(np.uint32)
    return LayerLayout(
        nodes=rec.reshape(-1),
        leaves=_instance_leaf_records(b, leaf_order) if over_instances else _leaf_records(first, counts),
        tris=tri.reshape(-1),
        treelet_first=tre_first,
        node_treelet=tre[order].astype(np.uint32),
        leaf_treelet=tre[leaf_order].astype(np.uint32),
        depth=int(depth[bfs].max()) + 1,
        height=height,
        branching=branching,
    )


@numba.njit(cache=True)
def _node_records(order, kids, lo, hi, child_link, lo_slot, hi_slot, link_slot, empty_box, empty_link, out, out_u32):
    """Fill the child slots of the node records (node_format: slots lo_slot[k, axis],
    hi_slot[k, axis], link_slot[k]) of the wide nodes `order`, from their children `kids`
    (binary ids, -1: empty), the children's boxes and the links they are reached by."""
    for i in range(len(order)):
        n = order[i]
        for k in range(kids.shape[1]):
            c = kids[n, k]
            for a in range(3):
                out[i, lo_slot[k, a]] = lo[c, a] if c >= 0 else empty_box[a]
                out[i, hi_slot[k, a]] = hi[c, a] if c >= 0 else empty_box[a]
            out_u32[i, link_slot[k]] = child_link[c] if c >= 0 else empty_link


@numba.njit(cache=True)
def _triangle_records(vertices, faces, tri_ids, out, out_u32, out_f64):
    """Fill the 64-byte triangle records (see LayerLayout.tris) of tri_ids, in that order.
    out, out_u32, out_f64 are float32, uint32 and float64 views of the same (F, 16) array."""
    for j in range(len(tri_ids)):
        fid = tri_ids[j]
        for k in range(3):
            for a in range(3):
                out[j, TRI_VERTEX[k] + a] = vertices[faces[fid, k], a]
        out_u32[j, TRI_FACE] = np.uint32(fid)
        v0, v1, v2 = TRI_VERTEX
        p0x, p0y, p0z = np.float64(out[j, v0]), np.float64(out[j, v0 + 1]), np.float64(out[j, v0 + 2])
        e1x, e1y, e1z = out[j, v1] - p0x, out[j, v1 + 1] - p0y, out[j, v1 + 2] - p0z
        e2x, e2y, e2z = out[j, v2] - p0x, out[j, v2 + 1] - p0y, out[j, v2 + 2] - p0z
        n = TRI_NORMAL // 2  # the normal's float64 slots
        out_f64[j, n] = e1y * e2z - e1z * e2y
        out_f64[j, n + 1] = e1z * e2x - e1x * e2z
        out_f64[j, n + 2] = e1x * e2y - e1y * e2x


def _leaf_records(first: np.ndarray, counts: np.ndarray) -> np.ndarray:
    rec = np.zeros((len(first), LEAF_UINTS), np.uint32)
    rec[:, LEAF_FIRST], rec[:, LEAF_COUNT] = first, counts
    return rec.reshape(-1)


def _instance_leaf_records(b: BinaryBVH, leaf_order: np.ndarray) -> np.ndarray:
    """Leaf records of a top level over instances: (instance, INSTANCE_COUNT) for a leaf holding
    one, (0, 0) for an empty one, so that leaf_range of each leaf link is its record."""
    one = b.count[leaf_order] == 1
    rec = np.zeros((len(leaf_order), LEAF_UINTS), np.uint32)
    rec[one, LEAF_FIRST] = b.perm[b.start[leaf_order][one]]
    rec[one, LEAF_COUNT] = INSTANCE_COUNT
    return rec.reshape(-1)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    offs = np.cumsum(counts) - counts
    return np.arange(int(counts.sum())) - np.repeat(offs - starts, counts)

_builder_kernels_loaded = False


def load_builder_kernels() -> float:
    """Compile the builder's and the layout's numba kernels (or load them from numba's on-disk
    cache) by building a tiny mesh; the seconds it took, 0.0 once done in this process. Kept
    out of the build time, as Dr.Jit's kernel compilation is kept out of trace times."""
    global _builder_kernels_loaded
    if _builder_kernels_loaded:
        return 0.0
    t0 = time.perf_counter()
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3], [0, 1, 2], [0, 2, 3]], np.int64)
    tiny = build_binned_sah(*triangle_bounds(v, f), 1)
    to_layer_layout(tiny, v, f, 1)
    to_layer_layout(tiny, v, f, 1, 4)  # the collapse's kernel too
    _builder_kernels_loaded = True
    return time.perf_counter() - t0


numba_cache.follow(globals(), layout)  # the record writers fold layout's slots in (numba_cache)
