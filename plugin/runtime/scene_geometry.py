"""The scene's geometry as our traversal takes it: Mitsuba's shapes walked once (meshes merged per group, instances
and their placements, analytic shapes tested per shape), refused by name where we cannot trace them."""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np

import layerbvh


# Shapes traced by Mitsuba's own per-shape routine and merged with the BVH's closest hit.
ANALYTIC = ("Sphere", "Disk", "Cylinder")
# Ellipsoid clouds: Mitsuba's routine tests one ellipsoid (primitive) per call, so each ellipsoid
# is one more test per ray.
ELLIPSOIDS = "Ellipsoids"
# Per-shape tests run for every ray, unrolled into the traversal's kernel: at most this many
# ellipsoids per `ellipsoids` shape, and at most this many (instance, analytic shape) pairs per
# scene; beyond that a scene is refused by name rather than compiled into a kernel of
# thousands of tests.
MAX_PER_SHAPE_TESTS = 64
# The engine's "no instance" (a hit on the scene's own meshes).

class UnsupportedShapeError(ValueError):
    """A scene holds a shape type this backend cannot trace (never traced wrongly: refused)."""


@dataclass
class MeshGroup:
    """Triangles traced as one BVH: the scene's own meshes (world space) or the meshes of one
    shapegroup (its object space), in one index space.

    tri_shape  uint32 (F,): per triangle, what Mitsuba's hit record calls its shape_index: the
               index into scene.shapes() (own meshes) or into the shapegroup's shapes
    tri_local  uint32 (F,): the triangle's index inside its own mesh
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    tri_shape: np.ndarray
    tri_local: np.ndarray


@dataclass
class Placement:
    """One engine instance: group `group` placed by `to_world` (4x4, float64); `instance` is the
    index into scene.shapes() of Mitsuba's Instance, None for the scene's own meshes."""

    group: int
    to_world: np.ndarray
    instance: int | None


@dataclass
class AnalyticTest:
    """One per-shape intersection run next to the BVH: Mitsuba's own routine for primitive
    `prim` of `shape`, in world space or (`to_object` set) in the object space of the Instance
    at scene.shapes()[`instance`]. `shape_index` is what Mitsuba's hit record holds: the index
    into scene.shapes(), or into the shapegroup's shapes."""

    shape: object
    shape_index: int
    prim: int = 0
    instance: int | None = None
    to_object: object = None


@dataclass
class SceneGeometry:
    """Everything the traversal needs from a scene, gathered once.

    groups      MeshGroup per BVH group: groups[0] the scene's own meshes (world space), then
                one per shapegroup that an instance places
    placements  the engine's instances (empty for a scene without Mitsuba instances: then the
                scene's meshes are one flat BVH)
    analytic    AnalyticTest per sphere, disk, cylinder, ellipsoid, and per instance of one
    """

    groups: list
    placements: list = field(default_factory=list)
    analytic: list = field(default_factory=list)
    shape_names: list = field(default_factory=list)

    @property
    def instanced(self) -> bool:
        return bool(self.placements)

    # The scene's own meshes (all of a scene without instances).
    @property
    def vertices(self) -> np.ndarray:
        return self.groups[0].vertices

    @property
    def faces(self) -> np.ndarray:
        return self.groups[0].faces

    @property
    def tri_shape(self) -> np.ndarray:
        return self.groups[0].tri_shape

    @property
    def tri_local(self) -> np.ndarray:
        return self.groups[0].tri_local

    @property
    def triangle_count(self) -> int:
        """Unique triangles (a shapegroup's once, however often it is placed)."""
        return sum(len(g.faces) for g in self.groups)

    def engine_groups(self) -> list:
        """The groups as layerbvh.build_instanced takes them."""
        return [layerbvh.Group(g.vertices, g.faces) for g in self.groups]

    def engine_instances(self) -> list:
        """The placements as layerbvh.build_instanced takes them."""
        return [layerbvh.Instance(p.group, p.to_world) for p in self.placements]

    def world_triangles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every placed triangle in world space (tools and checks only; the traversal keeps each
        group once): (vertices, faces, first flat face of each placement). A scene without
        instances: its meshes as they are, one placement starting at 0."""
        if not self.instanced:
            return self.vertices, self.faces, np.zeros(1, np.int64)
        vs, fs, first, nv, nf = [], [], [], 0, 0
        for p in self.placements:
            g = self.groups[p.group]
            vs.append(g.vertices.astype(np.float64) @ p.to_world[:3, :3].T + p.to_world[:3, 3])
            fs.append(g.faces + nv)
            first.append(nf)
            nv += len(g.vertices)
            nf += len(g.faces)
        return (np.concatenate(vs).astype(np.float32) if vs else np.zeros((0, 3), np.float32),
                np.concatenate(fs) if fs else np.zeros((0, 3), np.int64), np.array(first, np.int64))


def describe(shape, index=None) -> str:
    sid = shape.id()
    name = f"'{sid}'" if sid else "(no id)"
    return f"{shape.class_name()} {name}" + (f" (shape #{index})" if index is not None and not sid else "")


def _children(obj) -> list:
    """(name, object) of the objects a Mitsuba object hands to its traversal callback, in order
    (a shapegroup: its shapes in the order of Mitsuba's shape_index)."""
    cb = _objects_callback()()
    obj.traverse(cb)
    return cb.objects


# One callback class per variant, kept: a class made per call is a reference cycle (class ->
# method -> closure -> class), and the Mitsuba objects its closure held were freed only by
# Python's cycle collector, at whatever moment it ran. Measured (PERFORMANCE.md entry 55): it ran
# inside a frozen wavefront step's recording, where a shapegroup freed then (its Embree scene is
# released through a host callback) aborts the process.
_OBJECTS_CALLBACK: dict[str, type] = {}


def _objects_callback() -> type:
    """The traversal callback class of the current variant (made once a variant is set)."""
    variant = mi.variant()
    if variant not in _OBJECTS_CALLBACK:
        class Objects(mi.TraversalCallback):
            def __init__(self):
                super().__init__()
                self.objects = []

            def put(self, name, value, flags, cpptype=None):
                if isinstance(value, mi.Object):
                    self.objects.append((name, value))
        _OBJECTS_CALLBACK[variant] = Objects
    return _OBJECTS_CALLBACK[variant]


def sensor_medium(sensor):
    """The medium a sensor sits in, or None (Mitsuba's Python API does not expose it; the
    sensor hands it to its traversal callback)."""
    return next((obj for name, obj in _children(sensor) if name == "medium"), None)


def _is_shapegroup(obj) -> bool:
    return obj.class_name() in ("ShapeGroupPlugin", "ShapeGroup")


def _shapegroup_of(instance, index: int, shapegroups: dict):
    """The shapegroup an Instance places. Mitsuba's Python API does not expose it: it is named in
    the Instance's description (`shapegroup = ShapeGroup[ name = "<id>", ...`), and shapegroups
    are children of the scene with that id (Mitsuba 3.9 accepts a shapegroup only there)."""
    m = re.search(r'shapegroup\s*=\s*ShapeGroup\[\s*name\s*=\s*"([^"]*)"', str(instance))
    group = shapegroups.get(m.group(1)) if m else None
    if group is None or group.primitive_count() != instance.effective_primitive_count():
        raise UnsupportedShapeError(
            f"shape {describe(instance, index)} (plugin type 'instance'): cannot tell which shapegroup it places "
            f"(the layerbvh backend finds it by the shapegroup's id among the scene's shapegroups)")
    return group


def _refusal(shape, index, where: str = "") -> UnsupportedShapeError:
    kinds = ", ".join(a.lower() for a in ANALYTIC)
    return UnsupportedShapeError(
        f"shape {describe(shape, index)}{where} (plugin type '{shape.class_name().lower()}') is not supported by the "
        f"layerbvh backend: it traces triangle meshes (incl. rectangle, cube, ply, obj, serialized), {kinds}, "
        f"ellipsoids (up to {MAX_PER_SHAPE_TESTS} per shape) and instances of shapegroups of these; ellipsoidsmesh, "
        f"curves and SDF grids are refused rather than traced wrongly")


def _analytic_tests(shape, index, shape_index: int, where: str = "") -> list[AnalyticTest]:
    """The per-shape tests of an analytic shape (ellipsoids: one per ellipsoid), or a refusal."""
    name = shape.class_name()
    if name in ANALYTIC:
        return [AnalyticTest(shape, shape_index)]
    if name == ELLIPSOIDS:
        n = int(shape.primitive_count())
        if n > MAX_PER_SHAPE_TESTS:
            raise UnsupportedShapeError(
                f"shape {describe(shape, index)}{where} (plugin type 'ellipsoids') holds {n} ellipsoids; the layerbvh "
                f"backend tests each one per ray and takes at most {MAX_PER_SHAPE_TESTS} per shape")
        return [AnalyticTest(shape, shape_index, prim=p) for p in range(n)]
    raise _refusal(shape, index, where)


def _mesh_arrays(shape, name: str, shape_index: int):
    v, f = layerbvh.check_mesh(np.array(shape.vertex_positions_buffer()).reshape(-1, 3),
                               np.array(shape.faces_buffer(), np.int64).reshape(-1, 3), name=name)
    return v, f, np.full(len(f), shape_index, np.uint32), np.arange(len(f), dtype=np.uint32)


def mesh_digest(v: np.ndarray, f: np.ndarray) -> bytes:
    """SHA-256 of one mesh's vertices and faces (its own indices)."""
    h = hashlib.sha256(np.ascontiguousarray(v, np.float32).tobytes())
    h.update(np.ascontiguousarray(f, np.int64).tobytes())
    return h.digest()


def _group(name: str, parts: list, ids: list | None = None) -> MeshGroup:
    """One MeshGroup from (vertices, faces, tri_shape, tri_local) of several meshes, in an order
    of their own: sorted by content (then by the shape's id). Mitsuba loads shapes in parallel, so
    scene.shapes() comes in another order from one load to the next; concatenated in that order,
    the same scene would build another BVH, break ties between coplanar triangles another way and
    get another `auto` key on every load (tri_shape still maps each triangle to its shape)."""
    ids = ids or [""] * len(parts)
    order = sorted(range(len(parts)), key=lambda i: (mesh_digest(parts[i][0], parts[i][1]), ids[i]))
    verts, faces, tri_shape, tri_local, offset = [], [], [], [], 0
    for v, f, ts, tl in (parts[i] for i in order):
        verts.append(v)
        faces.append(f + offset)
        tri_shape.append(ts)
        tri_local.append(tl)
        offset += len(v)
    cat = (lambda xs, shape, dt: np.concatenate(xs) if xs else np.zeros(shape, dt))
    return MeshGroup(name, cat(verts, (0, 3), np.float32), cat(faces, (0, 3), np.int64),
                     cat(tri_shape, (0,), np.uint32), cat(tri_local, (0,), np.uint32))


def _is_plain_mesh(shape) -> bool:
    # EllipsoidsMesh is a Mesh, but stock Mitsuba traces it with back faces culled.
    return shape.is_mesh() and not shape.is_ellipsoids()


def collect_geometry(scene) -> SceneGeometry:
    """World-space triangles of every mesh shape, the analytic shapes, and the shapegroups the
    scene's instances place (each once, in its object space); refuse anything else by name."""
    world, world_ids, analytic, names = [], [], [], []
    shapegroups = {obj.id(): obj for _, obj in _children(scene) if _is_shapegroup(obj)}
    group_of: dict[str, int] = {}  # shapegroup id -> index into groups
    groups: list[MeshGroup] = []
    instance_at: list[tuple[int, object]] = []  # (scene index, Instance shape)
    group_tests: dict[str, list[AnalyticTest]] = {}  # shapegroup id -> its analytic tests (object space)
    for i, shape in enumerate(scene.shapes()):
        names.append(describe(shape, i))
        if shape.class_name() == "Instance":
            instance_at.append((i, shape))
        elif _is_plain_mesh(shape):
            world.append(_mesh_arrays(shape, f"shape {describe(shape)}", i))
            world_ids.append(shape.id())
        else:
            analytic += _analytic_tests(shape, i, i)
    groups.append(_group("scene meshes", world, world_ids))
    placements = []
    for i, inst in instance_at:
        sg = _shapegroup_of(inst, i, shapegroups)
        gid = sg.id()
        if gid not in group_of:
            parts, part_ids, tests = [], [], []
            for c, (_, child) in enumerate(_children(sg)):
                where = f" in shapegroup '{gid}'"
                if child.class_name() == "Instance" or _is_shapegroup(child):  # Mitsuba 3.9 refuses these itself
                    raise UnsupportedShapeError(f"shape {describe(child)}{where}: nested instancing is not supported")
                if _is_plain_mesh(child):
                    parts.append(_mesh_arrays(child, f"shape {describe(child)}{where}", c))
                    part_ids.append(child.id())
                else:
                    tests += _analytic_tests(child, None, c, where)
            group_of[gid] = len(groups)
            groups.append(_group(f"shapegroup '{gid}'", parts, part_ids))
            group_tests[gid] = tests
        m = np.array(mi.traverse(inst)["to_world"].matrix, np.float64).reshape(4, 4)
        if np.linalg.matrix_rank(m[:3, :3]) < 3:
            # Scaled to zero along some axis (a hidden copy, or flattened onto a plane): stock's
            # Embree renders such an instance as absent, measured bit for bit (issue 56).
            # It has no inverse to trace in, so it is left out, as stock leaves it.
            continue
        placements.append(Placement(group_of[gid], m, i))
        if group_tests[gid]:
            to_object = mi.traverse(inst)["to_world"].inverse()
            analytic += [AnalyticTest(t.shape, t.shape_index, t.prim, i, to_object) for t in group_tests[gid]]
    pairs = sum(t.instance is not None for t in analytic)
    if pairs > MAX_PER_SHAPE_TESTS:
        raise UnsupportedShapeError(
            f"the scene's instances place {pairs} analytic shapes (spheres, disks, cylinders, ellipsoids in "
            f"shapegroups); "
            f"the layerbvh backend tests each placement per ray and takes at most {MAX_PER_SHAPE_TESTS}: "
            f"give the shapegroups meshes instead")
    if placements and len(groups[0].faces):
        # The scene's own meshes: one more group, placed once as they are (instance index 0,
        # so they win ties against instances).
        placements.insert(0, Placement(0, np.eye(4), None))
    return SceneGeometry(groups=groups, placements=placements, analytic=analytic, shape_names=names)
