"""Layer BVH layout: the binary BVH cut into treelets, stored treelet by treelet, and its invariant check."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .sah import BinaryBVH

# Child links (uint32). Bit 31: BVH leaf, payload = leaf index. Bit 30: exit into a child
# treelet, payload = treelet id (its root is `treelet_first[id]`). Neither: inner node of the
# same treelet, payload = node index.
LEAF_BIT = np.uint32(1 << 31)
EXIT_BIT = np.uint32(1 << 30)
PAYLOAD_MASK = np.uint32((1 << 30) - 1)
NODE_FLOATS = 16
TRI_FLOATS = 16


@dataclass
class LayerLayout:
    """The arrays the traversal kernels read, all flat and contiguous.

    nodes           float32 (N*16): one 64-byte record per inner node, treelet 0's nodes first,
                    each treelet's nodes breadth-first:
                      [0:3] left child box lo, [3:6] left hi, [6:9] right lo, [9:12] right hi,
                      [12] left link, [13] right link (uint32 bits, see LEAF_BIT/EXIT_BIT),
                      [14] depth of the node in the BVH, [15] unused (0)
    leaves          uint32 (L*2): per BVH leaf (first triangle, triangle count), grouped by the
                    treelet of the leaf's parent, in that treelet's breadth-first order
    tris            float32 (F*16): per triangle in leaf order, one 64-byte record (a cache line):
                    [0:9] v0, v1, v2 (xyz each), [9] original face index (uint32 bits),
                    [10:16] geometric normal (v1 - v0) x (v2 - v0) as three float64 (the bits of
                    each in two consecutive slots, little-endian)
    treelet_first   uint32 (T+1): first node of each treelet, plus the node count at the end
    node_treelet    uint32 (N): treelet of each inner node
    leaf_treelet    uint32 (L): treelet of each leaf's parent
    depth           number of inner-node levels (the longest root-to-leaf path has depth inner nodes)
    height          treelet height H the layout was cut with
    """

    nodes: np.ndarray
    leaves: np.ndarray
    tris: np.ndarray
    treelet_first: np.ndarray
    node_treelet: np.ndarray
    leaf_treelet: np.ndarray
    depth: int
    height: int

    @property
    def node_count(self) -> int:
        return len(self.node_treelet)

    @property
    def treelet_count(self) -> int:
        return len(self.treelet_first) - 1

    @property
    def leaf_count(self) -> int:
        return len(self.leaf_treelet)

    @property
    def treelet_node_counts(self) -> np.ndarray:
        return np.diff(self.treelet_first)

    def links(self) -> np.ndarray:
        return self.nodes.reshape(-1, NODE_FLOATS)[:, 12:14].view(np.uint32)

    def array_bytes(self) -> dict:
        return {name: int(getattr(self, name).nbytes)
                for name in ("nodes", "leaves", "tris", "treelet_first", "node_treelet", "leaf_treelet")}


@dataclass
class DeviceLayout:
    """A LayerLayout's arrays on the Dr.Jit device (same byte layout, see layout.LayerLayout)."""

    nodes: object
    leaves: object
    tris: object
    treelet_first: object
    node_treelet: object
    leaf_treelet: object
    depth: int
    height: int
    treelet_count: int


def _wrap_leaf_root(b: BinaryBVH) -> BinaryBVH:
    """A BVH whose root is a leaf gets an inner root over (that leaf, an empty leaf),
    so every traversal starts at an inner node."""
    lo = np.concatenate([b.lo[:1], b.lo[:1], b.lo[:1]])
    hi = np.concatenate([b.hi[:1], b.hi[:1], b.lo[:1]])
    n = int(b.count[0])
    return BinaryBVH(lo=lo, hi=hi, left=np.array([1, -1, -1]), start=np.array([0, 0, n]),
                     count=np.array([n, n, 0]), depth=np.array([0, 1, 1]), perm=b.perm)


def to_layer_layout(b: BinaryBVH, vertices: np.ndarray, faces: np.ndarray, height: int) -> LayerLayout:
    """Cut `b` into treelets of at most `height` levels and lay it out for traversal."""
    if b.left[0] < 0:
        b = _wrap_leaf_root(b)
    m = len(b.left)
    inner = b.left >= 0
    # Treelet roots are the inner nodes at depths 0, H, 2H, ...; nodes are in level order, so
    # numbering roots in node order numbers treelets breadth-first, and a stable sort by
    # treelet keeps each treelet's nodes breadth-first.
    parent = np.full(m, -1, np.int64)
    kids = b.left[inner]
    parent[kids] = np.nonzero(inner)[0]
    parent[kids + 1] = np.nonzero(inner)[0]
    is_root = inner & (b.depth % height == 0)
    root_id = np.cumsum(is_root) - 1
    tre = np.full(m, -1, np.int64)
    for d in range(int(b.depth.max()) + 1):  # one vectorized pass per level
        at = np.nonzero(b.depth == d)[0]
        from_parent = tre[parent[at]] if d > 0 else np.zeros(len(at), np.int64)
        tre[at] = np.where(is_root[at], root_id[at], from_parent)
    # Leaves belong to their parent's treelet (a leaf at a treelet boundary stays with its parent).
    leaf = ~inner
    tre[leaf] = tre[parent[leaf]] if m > 1 else 0

    inner_ids = np.nonzero(inner)[0]
    order = inner_ids[np.argsort(tre[inner_ids], kind="stable")]
    new_idx = np.full(m, -1, np.int64)
    new_idx[order] = np.arange(len(order))
    leaf_ids = np.nonzero(leaf)[0]
    leaf_order = leaf_ids[np.argsort(tre[leaf_ids], kind="stable")]
    new_leaf = np.full(m, -1, np.int64)
    new_leaf[leaf_order] = np.arange(len(leaf_order))
    n_treelets = int(is_root.sum())

    def link(child, par):
        out = np.where(leaf[child], LEAF_BIT | new_leaf[child].astype(np.uint32),
                       np.where(tre[child] != tre[par], EXIT_BIT | tre[child].astype(np.uint32),
                                new_idx[child].astype(np.uint32)))
        return out.astype(np.uint32)

    l, r = b.left[order], b.left[order] + 1
    rec = np.zeros((len(order), NODE_FLOATS), np.float32)
    rec[:, 0:3], rec[:, 3:6] = b.lo[l], b.hi[l]
    rec[:, 6:9], rec[:, 9:12] = b.lo[r], b.hi[r]
    rec[:, 12] = link(l, order).view(np.float32)
    rec[:, 13] = link(r, order).view(np.float32)
    rec[:, 14] = b.depth[order]

    # Triangles in leaf order: leaf i covers tris[first_i : first_i + count_i].
    counts = b.count[leaf_order]
    first = np.cumsum(counts) - counts
    tri_ids = b.perm[_ranges(b.start[leaf_order], counts)]
    tri = np.zeros((len(tri_ids), TRI_FLOATS), np.float32)
    _triangle_records(vertices, faces, tri_ids, tri, tri.view(np.uint32), tri.view(np.float64))

    tre_first = np.searchsorted(tre[order], np.arange(n_treelets + 1)).astype(np.uint32)
    return LayerLayout(
        nodes=rec.reshape(-1),
        leaves=np.stack([first, counts], 1).astype(np.uint32).reshape(-1),
        tris=tri.reshape(-1),
        treelet_first=tre_first,
        node_treelet=tre[order].astype(np.uint32),
        leaf_treelet=tre[leaf_order].astype(np.uint32),
        depth=int(b.depth[inner].max()) + 1,
        height=height,
    )


@numba.njit(cache=True)
def _triangle_records(vertices, faces, tri_ids, out, out_u32, out_f64):
    """Fill the 64-byte triangle records (see LayerLayout.tris) of tri_ids, in that order.
    out, out_u32, out_f64 are float32, uint32 and float64 views of the same (F, 16) array."""
    for j in range(len(tri_ids)):
        fid = tri_ids[j]
        for k in range(3):
            for a in range(3):
                out[j, 3 * k + a] = vertices[faces[fid, k], a]
        out_u32[j, 9] = np.uint32(fid)
        p0x, p0y, p0z = np.float64(out[j, 0]), np.float64(out[j, 1]), np.float64(out[j, 2])
        e1x, e1y, e1z = out[j, 3] - p0x, out[j, 4] - p0y, out[j, 5] - p0z
        e2x, e2y, e2z = out[j, 6] - p0x, out[j, 7] - p0y, out[j, 8] - p0z
        # float64 slots 5, 6, 7 are float32 slots 10..15
        out_f64[j, 5] = e1y * e2z - e1z * e2y
        out_f64[j, 6] = e1z * e2x - e1x * e2z
        out_f64[j, 7] = e1x * e2y - e1y * e2x


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    offs = np.cumsum(counts) - counts
    return np.arange(int(counts.sum())) - np.repeat(offs - starts, counts)


def check_layout(lay: LayerLayout, n_faces: int) -> None:
    """Raise AssertionError naming the first broken invariant of a Layer BVH layout."""
    n, nl, nt, h = lay.node_count, lay.leaf_count, lay.treelet_count, lay.height
    rec = lay.nodes.reshape(-1, NODE_FLOATS)
    links = lay.links()
    assert n >= 1, "layout has no root node"
    tf = lay.treelet_first.astype(np.int64)
    assert tf[0] == 0 and tf[-1] == n and np.all(np.diff(tf) >= 1), "treelet_first is not a partition of the nodes"
    assert np.array_equal(lay.node_treelet, np.repeat(np.arange(nt), np.diff(tf))), \
        "nodes of a treelet are not contiguous, or treelets are out of order"

    is_leaf = (links & LEAF_BIT) != 0
    is_exit = ~is_leaf & ((links & EXIT_BIT) != 0)
    payload = (links & PAYLOAD_MASK).astype(np.int64)
    assert np.all(payload[is_leaf] < nl), "a leaf link points past the leaf array"
    assert np.all(payload[is_exit] < nt), "an exit link points past the treelet array"
    inner = ~is_leaf & ~is_exit
    assert np.all(payload[inner] < n), "a node link points past the node array"
    # Every node and leaf is reached exactly once from the root (node 0).
    child_node = np.where(is_exit, tf[np.minimum(payload, nt)], payload)
    node_refs = np.bincount(child_node[~is_leaf], minlength=n)
    assert node_refs[0] == 0 and np.all(node_refs[1:] == 1), "some node is referenced not exactly once"
    assert np.all(np.bincount(payload[is_leaf], minlength=nl) == 1), "some leaf is referenced not exactly once"
    # Links inside a treelet stay inside it; exits go to another treelet's root.
    owner = np.repeat(lay.node_treelet[:, None], 2, 1).astype(np.int64)
    assert np.all(lay.node_treelet[payload[inner]] == owner[inner]), "a node link crosses a treelet without an exit"
    assert np.all(payload[is_exit] != owner[is_exit]), "an exit link points to its own treelet"
    assert np.all(lay.leaf_treelet[payload[is_leaf]] == owner[is_leaf]), "a leaf is not stored with its parent's treelet"
    # Breadth-first inside each treelet: children come after parents; height is respected.
    parents = np.repeat(np.arange(n)[:, None], 2, 1)
    assert np.all(payload[inner] > parents[inner]), "a child node precedes its parent"
    depth = rec[:, 14].astype(np.int64)
    assert np.all(depth[payload[inner]] == depth[parents[inner]] + 1), "child depth is not parent depth + 1"
    root_depth = depth[tf[:-1]]
    assert np.all(depth - root_depth[lay.node_treelet] < h), "a treelet is taller than its height"
    assert np.all(np.diff(depth[tf[:-1]]) >= 0) or nt == 1, "treelets are not in breadth-first order"
    # Every triangle in exactly one leaf, leaves contiguous in triangle order.
    lv = lay.leaves.reshape(-1, 2).astype(np.int64)
    assert lv[:, 0].tolist() == (np.cumsum(lv[:, 1]) - lv[:, 1]).tolist(), "leaf triangle ranges are not contiguous"
    assert lv[:, 1].sum() == n_faces, "leaves do not cover every triangle exactly once"
    ids = lay.tris.reshape(-1, TRI_FLOATS)[:, 9].view(np.uint32)
    assert np.array_equal(np.sort(ids), np.arange(n_faces, dtype=np.uint32)), "triangle ids are not a permutation"
    # Child boxes bound what is below them.
    tri = lay.tris.reshape(-1, TRI_FLOATS)[:, :9].reshape(-1, 3, 3)
    for side in (0, 1):
        box_lo, box_hi = rec[:, 6 * side:6 * side + 3], rec[:, 6 * side + 3:6 * side + 6]
        lk = is_leaf[:, side]
        for i in np.nonzero(lk)[0][:: max(1, lk.sum() // 2000)]:  # a sample keeps the check fast
            s, c = lv[payload[i, side]]
            if c:
                t = tri[s:s + c]
                assert np.all(t.min((0, 1)) >= box_lo[i]) and np.all(t.max((0, 1)) <= box_hi[i]), \
                    f"node {i} child {side}: leaf triangles outside the child box"
        nk = ~lk
        kid = child_node[nk, side]
        kid_box = rec[kid]
        enclose_lo = np.minimum(kid_box[:, 0:3], kid_box[:, 6:9])
        enclose_hi = np.maximum(kid_box[:, 3:6], kid_box[:, 9:12])
        assert np.all(box_lo[nk] <= enclose_lo) and np.all(box_hi[nk] >= enclose_hi), \
            f"a child box (side {side}) does not contain its node's children"
