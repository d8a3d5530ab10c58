"""Instanced scenes: groups of unique geometry placed by affine instances, the top-level BVH over the instances'
world boxes, and the one combined layout the kernels walk."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .inputs import check_mesh
from .layout import (EXIT_BIT, INST_FLOATS, INST_GROUP, INST_ROOT, INST_TO_OBJECT, INSTANCE_TAG, LEAF_BIT,
                     LEAF_FIRST, LEAF_FIRST_MASK, LEAF_UINTS, LEAVE, MAX_INSTANCES, MAX_TRIANGLES,
                     PAYLOAD_MASK, TRI_FLOATS, LayerLayout, check_layout)
from .relayout import to_layer_layout
from .sah import build_binned_sah, triangle_bounds

# An instance whose linear part has a larger condition number than this is refused: its
# float32 world -> object map (what the kernels apply to rays) would lose most of its digits.
MAX_CONDITION = 1e6
# Top-level boxes are the group's box mapped to world space, widened by this share of their
# coordinates' magnitude: a hit is found with the float32 object-space ray, so the world point it
# stands for lies off the world ray by a few float32 roundings of the transform.
BOX_PAD = 2.0 ** -18


@dataclass
class Group:
    """Unique geometry: a triangle mesh in its own (object) space, stored once however often it is placed."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass
class Instance:
    """One placement of group `group`: `to_world` (4x4 with last row 0 0 0 1, or 3x4) maps the
    group's object space to world space."""

    group: int
    to_world: np.ndarray


def check_instances(groups, instances) -> tuple[list[Group], list[Instance]]:
    """Groups with checked meshes (check_mesh) and instances with a float64 (3, 4) `to_world`;
    a ValueError naming the group or instance and what is wrong with it."""
    groups = list(groups)
    instances = list(instances)
    out_groups = []
    for g, grp in enumerate(groups):
        if not isinstance(grp, Group):
            raise ValueError(f"groups[{g}] must be a layerbvh.Group(vertices, faces), got {type(grp).__name__}")
        v, f = check_mesh(grp.vertices, grp.faces, name=f"group {g}")
        out_groups.append(Group(v, f))
    if len(instances) > MAX_INSTANCES:
        raise ValueError(f"{len(instances):,} instances; an instanced layout addresses at most {MAX_INSTANCES:,}")
    out_inst = []
    for k, inst in enumerate(instances):
        if not isinstance(inst, Instance):
            raise ValueError(f"instances[{k}] must be a layerbvh.Instance(group, to_world), got {type(inst).__name__}")
        g = inst.group
        if isinstance(g, bool) or not isinstance(g, (int, np.integer)) or not 0 <= g < len(groups):
            raise ValueError(f"instance {k}: group {g!r} is not one of the {len(groups)} groups")
        m = np.asarray(inst.to_world, np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"instance {k}: to_world must have shape (4, 4) or (3, 4), got {m.shape}")
        if not np.isfinite(m).all():
            raise ValueError(f"instance {k}: to_world has non-finite entries")
        if m.shape == (4, 4) and not np.array_equal(m[3], [0, 0, 0, 1]):
            raise ValueError(f"instance {k}: to_world is not affine (last row {m[3].tolist()}, must be [0, 0, 0, 1])")
        lin = m[:3, :3]
        if np.linalg.det(lin) == 0 or np.linalg.cond(lin) > MAX_CONDITION:
            raise ValueError(f"instance {k}: to_world is singular or too ill-conditioned for a float32 inverse "
                             f"(condition number {np.linalg.cond(lin):.3g}, at most {MAX_CONDITION:g})")
        out_inst.append(Instance(int(g), m[:3].copy()))
    total = sum(len(grp.faces) for grp in out_groups)
    if total > MAX_TRIANGLES:
        raise ValueError(f"groups hold {total:,} triangles; a Layer BVH addresses at most {MAX_TRIANGLES:,}")
    return out_groups, out_inst


def to_object(to_world: np.ndarray) -> np.ndarray:
    """The world -> object map (3, 4) of an object -> world map (3, 4), in float64."""
    inv = np.linalg.inv(to_world[:, :3])
    return np.concatenate([inv, -(inv @ to_world[:, 3])[:, None]], axis=1)


def world_box(to_world: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (float32, widened by BOX_PAD) of the object-space box lo..hi mapped to world space."""
    corners = np.array([[(lo, hi)[(c >> a) & 1][a] for a in range(3)] for c in range(8)], np.float64)
    w = corners @ to_world[:, :3].T + to_world[:, 3]
    pad = BOX_PAD * (np.abs(w).max() + np.abs(w.max(0) - w.min(0)).max())
    return (np.nextafter((w.min(0) - pad).astype(np.float32), np.float32(-np.inf)),
            np.nextafter((w.max(0) + pad).astype(np.float32), np.float32(np.inf)))


@dataclass
class InstancedParts:
    """How a combined layout was put together (kept for checks and tools).

    top             the top level over instances (to_layer_layout without triangles)
    groups          each group's own layout (None for a group without triangles)
    node_offset     first node of each group's layout in the combined node array
    treelet_offset  first treelet of each group's layout
    tri_offset      first triangle record of each group
    traced          instances in the top level (those of groups with triangles)
    """

    top: LayerLayout | None
    groups: list
    node_offset: list
    treelet_offset: list
    tri_offset: list
    traced: np.ndarray


def _shifted(lay: LayerLayout, nodes: int, treelets: int, tris: int) -> tuple[np.ndarray, np.ndarray]:
    """`lay`'s node and leaf records with every link moved by the given offsets (node links by
    `nodes`, exits by `treelets`, leaf triangle ranges by `tris`)."""
    fmt = lay.format
    rec = lay.records().copy()
    links = rec[:, fmt.link[0]:fmt.link[-1] + 1].view(np.uint32)
    used = np.arange(fmt.branching)[None, :] < lay.children()[:, None]  # empty slots stay as they are
    leaf = used & ((links & LEAF_BIT) != 0)
    exit_ = used & ~leaf & ((links & EXIT_BIT) != 0)
    node = used & ~leaf & ~exit_
    links[node] += np.uint32(nodes)
    links[exit_] = EXIT_BIT | ((links[exit_] & PAYLOAD_MASK) + np.uint32(treelets))
    first = links[leaf] & LEAF_FIRST_MASK
    links[leaf] = (links[leaf] & ~LEAF_FIRST_MASK) | (first + np.uint32(tris))
    leaves = lay.leaves.reshape(-1, LEAF_UINTS).copy()
    leaves[:, LEAF_FIRST] += np.uint32(tris)
    return rec.reshape(-1), leaves.reshape(-1)


def instanced_layout(groups: list[Group], instances: list[Instance], height: int,
                     leaf_size: int, branching: int = 2) -> tuple[LayerLayout | None, InstancedParts]:
    """The combined layout of checked groups and instances (check_instances): the top level's
    treelets first (its leaves are instance links), then each group's layout once, its links
    moved into the combined arrays; one instance record per instance. None when nothing can be
    hit (no instance of a group with triangles)."""
    group_layouts, boxes = [], []
    for grp in groups:
        if len(grp.faces) == 0:
            group_layouts.append(None)
            boxes.append(None)
            continue
        lo, hi = triangle_bounds(grp.vertices, grp.faces)
        group_layouts.append(to_layer_layout(build_binned_sah(lo, hi, leaf_size), grp.vertices, grp.faces, height,
                                             branching))
        boxes.append((lo.min(0).astype(np.float64), hi.max(0).astype(np.float64)))
    traced = np.array([k for k, inst in enumerate(instances) if group_layouts[inst.group] is not None], np.int64)
    if len(traced) == 0:
        return None, InstancedParts(None, group_layouts, [], [], [], traced)
    w = [world_box(instances[k].to_world, *boxes[instances[k].group]) for k in traced]
    top_b = build_binned_sah(np.array([b[0] for b in w]), np.array([b[1] for b in w]), 1)
    top = to_layer_layout(replace(top_b, perm=traced[top_b.perm]), None, None, height, branching)

    nodes, leaves, tris = [top.nodes], [top.leaves], []
    tre_first, node_tre, leaf_tre = [top.treelet_first[:-1]], [top.node_treelet], [top.leaf_treelet]
    node_off, tre_off, tri_off = [], [], []
    n_nodes, n_tre, n_tri = top.node_count, top.treelet_count, 0
    for lay in group_layouts:
        node_off.append(n_nodes)
        tre_off.append(n_tre)
        tri_off.append(n_tri)
        if lay is None:
            continue
        rec, lv = _shifted(lay, n_nodes, n_tre, n_tri)
        nodes.append(rec)
        leaves.append(lv)
        tris.append(lay.tris)
        tre_first.append(lay.treelet_first[:-1] + np.uint32(n_nodes))
        node_tre.append(lay.node_treelet + np.uint32(n_tre))
        leaf_tre.append(lay.leaf_treelet + np.uint32(n_tre))
        n_nodes += lay.node_count
        n_tre += lay.treelet_count
        n_tri += len(lay.tris) // TRI_FLOATS

    rec = np.zeros((len(instances), INST_FLOATS), np.float32)
    bits = rec.view(np.uint32)
    for k, inst in enumerate(instances):
        rec[k, INST_TO_OBJECT:INST_TO_OBJECT + 12] = to_object(inst.to_world).reshape(-1)
        bits[k, INST_ROOT] = EXIT_BIT | np.uint32(tre_off[inst.group])
        bits[k, INST_GROUP] = inst.group
    # The deepest path: the top level down to a leaf, the LEAVE marker, then the deepest group.
    depth = top.depth + 1 + max(lay.depth for lay in group_layouts if lay is not None)
    combined = LayerLayout(
        nodes=np.concatenate(nodes), leaves=np.concatenate(leaves),
        tris=np.concatenate(tris) if tris else np.zeros(0, np.float32),
        treelet_first=np.concatenate(tre_first + [np.array([n_nodes], np.uint32)]).astype(np.uint32),
        node_treelet=np.concatenate(node_tre).astype(np.uint32),
        leaf_treelet=np.concatenate(leaf_tre).astype(np.uint32),
        depth=depth, height=height, branching=branching, instances=rec.reshape(-1))
    return combined, InstancedParts(top, group_layouts, node_off, tre_off, tri_off, traced)


def check_instanced(parts: InstancedParts, groups: list[Group], instances: list[Instance]) -> None:
    """Raise AssertionError naming the first broken invariant of an instanced layout: the top
    level and every group's layout (check_layout), and each traced instance's top-level box
    holding its group's box mapped to world space."""
    for g, lay in enumerate(parts.groups):
        if lay is not None:
            check_layout(lay, len(groups[g].faces))
    if parts.top is None:
        return
    check_layout(parts.top, 0, instance_ids=parts.traced)
    fmt = parts.top.format
    rec = parts.top.records()
    links = parts.top.links()
    used = np.arange(fmt.branching)[None, :] < parts.top.children()[:, None]
    for side in range(fmt.branching):
        held = used[:, side] & (links[:, side] >= INSTANCE_TAG) & (links[:, side] < np.uint32(LEAVE))
        for i in np.nonzero(held)[0]:
            k = int(links[i, side] & LEAF_FIRST_MASK)
            grp = groups[instances[k].group]
            lo, hi = triangle_bounds(grp.vertices, grp.faces)
            wlo, whi = world_box(instances[k].to_world, lo.min(0).astype(np.float64), hi.max(0).astype(np.float64))
            assert np.all(rec[i, list(fmt.lo[side])] <= wlo) and np.all(rec[i, list(fmt.hi[side])] >= whi), \
                f"top-level node {i} child {side}: box does not hold instance {k}"
