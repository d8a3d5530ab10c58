"""Layer BVH layout: the byte layout of treelets stored treelet by treelet (nodes, triangles, leaves, instances), and
its invariant check (relayout.py builds it)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .backend import from_numpy

# Child links (uint32). Bit 31: BVH leaf, carrying its triangle range (leaf_link), so reaching a
# leaf reads no leaf record. Else bit 30: exit into a child treelet, payload = treelet id (its
# root is `treelet_first[id]`). Neither: inner node of the same treelet, payload = node index.
LEAF_BIT = np.uint32(1 << 31)
EXIT_BIT = np.uint32(1 << 30)
PAYLOAD_MASK = np.uint32((1 << 30) - 1)
LEAF_COUNT_SHIFT = 26   # leaf link: bits 26..30 the triangle count, bits 0..25 the first triangle
LEAF_FIRST_MASK = np.uint32((1 << LEAF_COUNT_SHIFT) - 1)
MAX_TRIANGLES = 1 << LEAF_COUNT_SHIFT  # 67,108,864: what a leaf link can address
# A link value no node, leaf or exit has: "take the next entry from the stack". It is not the
# MISS of a result (state.MISS), only equal to it in bits.
POP = 0xFFFFFFFF

# Instanced layouts (layerbvh.instances): leaf links whose count field is INSTANCE_COUNT (no
# triangle leaf has it: leaf_size <= 16) are top-level leaves, one instance each, payload = the
# instance's index. LEAVE, the marker a ray pushes under the entries of the instance it enters,
# sends it back to world space when popped. POP carries the same tag, so by value:
# triangle leaves < INSTANCE_TAG <= instance links < LEAVE < POP.
INSTANCE_COUNT = 31
INSTANCE_TAG = np.uint32(LEAF_BIT | (INSTANCE_COUNT << LEAF_COUNT_SHIFT))
LEAVE = 0xFFFFFFFE
MAX_INSTANCES = int(LEAVE & LEAF_FIRST_MASK)  # instance indices 0 .. MAX_INSTANCES - 1

# Instance record, float32 slots (uint32 bits where noted), one per instance.
INST_TO_OBJECT = 0      # 12 floats: world -> object affine map, row-major 3x4 (x' = M[:, :3] x + M[:, 3])
INST_ROOT = 12          # uint32: exit link into the root treelet of the instance's group
INST_GROUP = 13         # uint32: the instance's group (for tools and checks)
INST_FLOATS = 16        # slots 14, 15 unused; total: 64 bytes, one cache line

# Binary inner-node record (branching 2, the paper's), float32 slots (uint32 bits where noted).
# Index [side] = left (0), right (1).
NODE_BOX_LO = (0, 6)    # 3 floats: child box minimum (x, y, z)
NODE_BOX_HI = (3, 9)    # 3 floats: child box maximum
NODE_LINK = (12, 13)    # uint32: child link (LEAF_BIT / EXIT_BIT / node index)
NODE_DEPTH = 14         # float: depth of the node in the BVH (read by the invariant check only)
NODE_CHILDREN = 15      # float: number of children (2; read by the invariant check only)
NODE_FLOATS = 16        # total: 64 bytes, one cache line

# Wide inner-node record (branching K = 4 or 8), float32 slots, structure of arrays so that one
# packet gather brings each bound of all K children as K consecutive floats:
#   [0, K)        child box xmin[k]           [3K, 4K)   xmax[k]
#   [K, 2K)       ymin[k]                     [4K, 5K)   ymax[k]
#   [2K, 3K)      zmin[k]                     [5K, 6K)   zmax[k]
#   [6K, 7K)      uint32 child link[k] (as NODE_LINK)
#   7K            float: depth of the node (invariant check only)
#   7K + 1        float: number of children c (invariant check only); slots c .. K-1 are empty
#   up to a multiple of 16 floats: unused
# total: 128 bytes (K = 4, two cache lines), 256 bytes (K = 8, four cache lines)
BRANCHINGS = (2, 4, 8)
# An empty child slot: an empty leaf (so reaching it, should a ray ever hit its box, tests no
# triangle) whose box is a point far outside any scene, hit only by a ray aimed at it exactly.
EMPTY_LINK = np.uint32(LEAF_BIT)
EMPTY_BOX = (3.0e38, -3.0e38, 2.0e38)


def treelet_levels(height: int, branching: int) -> int:
    """Levels of the `branching`-wide tree a treelet of height `height` holds. The height counts
    levels of the binary tree, whatever the branching: a wide level stands for log2(branching)
    binary levels, so a treelet spans about the same depth, and about the same bytes (height 8:
    up to 255 binary nodes, 16 KiB; 85 nodes of 4, 11 KiB; 73 nodes of 8, 18 KiB), and the
    same height means the same thing in every setting (PERFORMANCE.md entry 27)."""
    return max(1, -(-height // (branching.bit_length() - 1)))


@dataclass(frozen=True)
class NodeFormat:
    """Where each field of an inner-node record of one branching sits (float32 slot indices)."""

    branching: int
    lo: tuple     # lo[k][axis]: child k's box minimum on axis
    hi: tuple     # hi[k][axis]
    link: tuple   # link[k]: child k's link
    depth: int
    children: int
    floats: int   # record size in float32 slots (a multiple of 16: whole cache lines)

    @property
    def bytes(self) -> int:
        return 4 * self.floats


def node_format(branching: int) -> NodeFormat:
    """The record layout of inner nodes with `branching` children (BRANCHINGS)."""
    k = branching
    if k == 2:
        return NodeFormat(2, tuple(tuple(NODE_BOX_LO[s] + a for a in range(3)) for s in (0, 1)),
                          tuple(tuple(NODE_BOX_HI[s] + a for a in range(3)) for s in (0, 1)),
                          NODE_LINK, NODE_DEPTH, NODE_CHILDREN, NODE_FLOATS)
    if k not in BRANCHINGS:
        raise ValueError(f"branching must be one of {BRANCHINGS}, got {k}")
    return NodeFormat(k, tuple(tuple(a * k + c for a in range(3)) for c in range(k)),
                      tuple(tuple((3 + a) * k + c for a in range(3)) for c in range(k)),
                      tuple(6 * k + c for c in range(k)), 7 * k, 7 * k + 1, -(-(7 * k + 2) // 16) * 16)

# Triangle record, float32 slots, one per triangle in leaf order.
TRI_VERTEX = (0, 3, 6)  # 3 floats each: v0, v1, v2 (x, y, z)
TRI_FACE = 9            # uint32: the caller's face index
TRI_NORMAL = 10         # 3 float64 in slots 10..15 (low word first): (v1 - v0) x (v2 - v0)
TRI_FLOATS = 16         # total: 64 bytes, one cache line
# A layout with a vertex coordinate beyond this tests triangles in far units (geometry.hit_triangle,
# DeviceLayout.far): 2^50, far under 2^63, where an edge function's product overflows float32.
FAR_COORD = 2.0 ** 50

# Leaf record, uint32 slots.
LEAF_FIRST = 0          # first triangle (leaf order)
LEAF_COUNT = 1          # number of triangles
LEAF_UINTS = 2          # total: 8 bytes


def leaf_link(first, count):
    """The link of a leaf holding triangles first .. first+count-1 (leaf order); numpy or Dr.Jit."""
    return LEAF_BIT | (count << LEAF_COUNT_SHIFT) | first


def leaf_range(link):
    """(first triangle, count) of a leaf link; numpy or Dr.Jit."""
    return link & LEAF_FIRST_MASK, (link & ~LEAF_BIT) >> LEAF_COUNT_SHIFT


def instance_link(index):
    """The top-level leaf link of instance `index`; numpy or Dr.Jit."""
    return INSTANCE_TAG | index


@dataclass
class LayerLayout:
    """The arrays the traversal kernels read, all flat and contiguous.

    nodes           float32 (N*F): one record per inner node (node_format(branching): 64 bytes
                    binary, 128 or 256 bytes wide), treelet 0's nodes first, each treelet's nodes
                    breadth-first
    leaves          uint32 (L*2): per BVH leaf (first triangle, triangle count: LEAF_*), grouped
                    by the treelet of the leaf's parent, in that treelet's breadth-first order (the
                    kernels read the range from the leaf link; this record is for checks and tools)
    tris            float32 (F*16): per triangle in leaf order, one 64-byte record (fields TRI_*):
                    vertices, the caller's face index, the float64 geometric normal
    treelet_first   uint32 (T+1): first node of each treelet, plus the node count at the end
    node_treelet    uint32 (N): treelet of each inner node
    leaf_treelet    uint32 (L): treelet of each leaf's parent
    depth           number of inner-node levels (the longest root-to-leaf path has depth inner nodes)
    height          treelet height H the layout was cut with, in binary levels: each treelet
                    holds `levels` = treelet_levels(H, branching) levels of this tree
    branching       children per inner node: 2 (the binary BVH) or 4, 8 (collapsed from it)
    instances       float32 (I*16) or None: per instance one 64-byte record (fields INST_*), in an
                    instanced layout (layerbvh.instances), whose first treelets are the top level
    """

    nodes: np.ndarray
    leaves: np.ndarray
    tris: np.ndarray
    treelet_first: np.ndarray
    node_treelet: np.ndarray
    leaf_treelet: np.ndarray
    depth: int
    height: int
    branching: int = 2
    instances: np.ndarray | None = None

    @property
    def format(self) -> NodeFormat:
        return node_format(self.branching)

    @property
    def levels(self) -> int:
        """Levels of this layout's tree per treelet (treelet_levels)."""
        return treelet_levels(self.height, self.branching)

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

    def records(self) -> np.ndarray:
        """The node records as an (N, node_format(branching).floats) float32 view."""
        return self.nodes.reshape(-1, self.format.floats)

    def links(self) -> np.ndarray:
        """(N, branching) uint32 view of the child links (empty slots hold EMPTY_LINK)."""
        fmt = self.format
        return self.records()[:, fmt.link[0]:fmt.link[-1] + 1].view(np.uint32)

    def children(self) -> np.ndarray:
        """(N,) number of children of each node (the others are empty slots)."""
        return self.records()[:, self.format.children].astype(np.int64)

    def to_device(self, m) -> "DeviceLayout":
        """The arrays on Dr.Jit array module `m` (backend.module)."""
        # Dr.Jit maps numpy memory as it is; an array that is not 64-byte aligned cannot be read
        # with packet gathers (8-float loads plus a transpose) and falls back to one vpgatherdd
        # per float, so the arrays go to the device from aligned memory (backend.from_numpy).
        return DeviceLayout(
            nodes=from_numpy(m.Float, self.nodes), tris=from_numpy(m.Float, self.tris),
            treelet_first=from_numpy(m.UInt32, self.treelet_first),
            node_treelet=from_numpy(m.UInt32, self.node_treelet),
            depth=self.depth, height=self.height, treelet_count=self.treelet_count, branching=self.branching,
            instances=None if self.instances is None else from_numpy(m.Float, self.instances), far=self.far)

    @property
    def far(self) -> bool:
        """Whether a vertex coordinate lies beyond FAR_COORD (geometry.hit_triangle's far units)."""
        corners = self.tris.reshape(-1, TRI_FLOATS)[:, TRI_VERTEX[0]:TRI_VERTEX[2] + 3]
        return bool(corners.size) and bool(np.abs(corners).max() > FAR_COORD)

    def array_bytes(self) -> dict:
        """Bytes of each array the traversal keeps on the device (see DeviceLayout)."""
        names = ("nodes", "tris", "treelet_first", "node_treelet")
        names += ("instances",) if self.instances is not None else ()
        return {name: int(getattr(self, name).nbytes) for name in names}


@dataclass
class DeviceLayout:
    """A LayerLayout's arrays on the Dr.Jit device (same byte layout, see LayerLayout); made by
    LayerLayout.to_device."""

    nodes: object
    tris: object
    treelet_first: object
    node_treelet: object
    depth: int
    height: int
    treelet_count: int
    branching: int = 2
    instances: object = None  # instance records (INST_*), None for a layout without instances
    far: bool = False         # a vertex coordinate lies beyond FAR_COORD (geometry.hit_triangle's units)


def check_layout(lay: LayerLayout, n_faces: int, instance_ids: np.ndarray | None = None) -> None:
    """Raise AssertionError naming the first broken invariant of a Layer BVH layout.

    With `instance_ids`, `lay` is a top level over these instances (to_layer_layout with no
    triangles): each must sit in exactly one leaf, in place of the triangle checks."""
    n, nl, nt, h, k = lay.node_count, lay.leaf_count, lay.treelet_count, lay.levels, lay.branching
    fmt = lay.format
    rec = lay.records()
    links = lay.links()
    assert n >= 1, "layout has no root node"
    tf = lay.treelet_first.astype(np.int64)
    assert tf[0] == 0 and tf[-1] == n and np.all(np.diff(tf) >= 1), "treelet_first is not a partition of the nodes"
    assert np.array_equal(lay.node_treelet, np.repeat(np.arange(nt), np.diff(tf))), \
        "nodes of a treelet are not contiguous, or treelets are out of order"
    nchild = lay.children()
    assert np.all((nchild >= 2) & (nchild <= k)), f"a node has fewer than 2 or more than {k} children"
    used = np.arange(k)[None, :] < nchild[:, None]  # child slots in use; the rest are empty
    boxes_lo = np.stack([rec[:, list(fmt.lo[c])] for c in range(k)], 1)  # (N, K, 3)
    boxes_hi = np.stack([rec[:, list(fmt.hi[c])] for c in range(k)], 1)
    assert np.all(links[~used] == EMPTY_LINK) and np.all(boxes_lo[~used] == np.float32(EMPTY_BOX)) and \
        np.all(boxes_hi[~used] == np.float32(EMPTY_BOX)), "an empty child slot is not EMPTY_LINK with EMPTY_BOX"

    is_leaf = used & ((links & LEAF_BIT) != 0)
    is_exit = used & ~is_leaf & ((links & EXIT_BIT) != 0)
    payload = (links & PAYLOAD_MASK).astype(np.int64)
    lv = lay.leaves.reshape(-1, LEAF_UINTS).astype(np.int64)
    first, count = lv[:, LEAF_FIRST], lv[:, LEAF_COUNT]
    # A leaf link carries (first, count); its leaf is the record with that range (leaves are
    # contiguous in triangle order, so first + the count tell them apart, even an empty one).
    l_first, l_count = (x.astype(np.int64) for x in leaf_range(links))
    leaf_key = first * (MAX_TRIANGLES + 1) + count
    order = np.argsort(leaf_key, kind="stable")
    pos = np.searchsorted(leaf_key[order], l_first * (MAX_TRIANGLES + 1) + l_count)
    pos = np.minimum(pos, nl - 1)
    found = is_leaf & (leaf_key[order][pos] == l_first * (MAX_TRIANGLES + 1) + l_count)
    assert np.all(found[is_leaf]), "a leaf link's triangle range is no leaf's"
    payload = np.where(is_leaf, order[pos], payload)
    assert np.all(payload[is_exit] < nt), "an exit link points past the treelet array"
    inner = used & ~is_leaf & ~is_exit
    assert np.all(payload[inner] < n), "a node link points past the node array"
    # Every node and leaf is reached exactly once from the root (node 0).
    child_node = np.where(is_exit, tf[np.minimum(payload, nt)], payload)
    node_refs = np.bincount(child_node[used & ~is_leaf], minlength=n)
    assert node_refs[0] == 0 and np.all(node_refs[1:] == 1), "some node is referenced not exactly once"
    assert np.all(np.bincount(payload[is_leaf], minlength=nl) == 1), "some leaf is referenced not exactly once"
    # Links inside a treelet stay inside it; exits go to another treelet's root.
    owner = np.repeat(lay.node_treelet[:, None], k, 1).astype(np.int64)
    assert np.all(lay.node_treelet[payload[inner]] == owner[inner]), "a node link crosses a treelet without an exit"
    assert np.all(payload[is_exit] != owner[is_exit]), "an exit link points to its own treelet"
    assert np.all(lay.leaf_treelet[payload[is_leaf]] == owner[is_leaf]), \
        "a leaf is not stored with its parent's treelet"
    # Breadth-first inside each treelet: children come after parents; height is respected.
    parents = np.repeat(np.arange(n)[:, None], k, 1)
    assert np.all(payload[inner] > parents[inner]), "a child node precedes its parent"
    depth = rec[:, fmt.depth].astype(np.int64)
    assert np.all(depth[payload[inner]] == depth[parents[inner]] + 1), "child depth is not parent depth + 1"
    root_depth = depth[tf[:-1]]
    assert np.all(depth - root_depth[lay.node_treelet] < h), "a treelet is taller than its height"
    assert np.all(np.diff(depth[tf[:-1]]) >= 0) or nt == 1, "treelets are not in breadth-first order"
    assert lay.depth == int(depth.max()) + 1, "the layout's depth is not its number of node levels"
    if instance_ids is not None:
        held = count == INSTANCE_COUNT
        assert np.all(held | (count == 0)), "a top-level leaf holds something else than one instance"
        assert np.array_equal(np.sort(first[held]), np.sort(instance_ids)), \
            "top-level leaves do not hold every instance exactly once"
        assert len(lay.tris) == 0, "a top level over instances has triangle records"
    else:
        # Every triangle in exactly one leaf, leaves contiguous in triangle order.
        assert first.tolist() == (np.cumsum(count) - count).tolist(), "leaf triangle ranges are not contiguous"
        assert count.sum() == n_faces, "leaves do not cover every triangle exactly once"
        ids = lay.tris.reshape(-1, TRI_FLOATS)[:, TRI_FACE].view(np.uint32)
        assert np.array_equal(np.sort(ids), np.arange(n_faces, dtype=np.uint32)), "triangle ids are not a permutation"
    # Child boxes bound what is below them (an instance's box: see instances.check_instanced).
    tri = lay.tris.reshape(-1, TRI_FLOATS)[:, TRI_VERTEX[0]:TRI_VERTEX[2] + 3].reshape(-1, 3, 3)
    for c in range(k):
        box_lo, box_hi = boxes_lo[:, c], boxes_hi[:, c]
        lk = is_leaf[:, c]
        tri_leaves = np.nonzero(lk)[0] if instance_ids is None else np.zeros(0, np.int64)
        for i in tri_leaves[:: max(1, len(tri_leaves) // 2000)]:  # a sample keeps the check fast
            s, cnt = first[payload[i, c]], count[payload[i, c]]
            if cnt:
                t = tri[s:s + cnt]
                assert np.all(t.min((0, 1)) >= box_lo[i]) and np.all(t.max((0, 1)) <= box_hi[i]), \
                    f"node {i} child {c}: leaf triangles outside the child box"
        nk = used[:, c] & ~lk
        kid = child_node[nk, c]
        kid_used = used[kid][:, :, None]
        enclose_lo = np.where(kid_used, boxes_lo[kid], np.inf).min(1)
        enclose_hi = np.where(kid_used, boxes_hi[kid], -np.inf).max(1)
        assert np.all(box_lo[nk] <= enclose_lo) and np.all(box_hi[nk] >= enclose_hi), \
            f"a child box (slot {c}) does not contain its node's children"


