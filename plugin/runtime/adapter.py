"""Scene adapter: a Mitsuba scene's mesh triangles in world space, its analytic shapes, and the map from our hits back to Mitsuba shapes."""
from __future__ import annotations

import hashlib
import json
import re
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh
from layerbvh import from_numpy
from layerbvh_mitsuba.runtime.queries import RayQueries

# Per-ray work kept per sample for the traversal-cost heat maps (state.WORK names).
HEATMAP_WORK = ("inner_nodes", "triangles", "steps")
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
WORLD = layerbvh.MISS


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
    objects = []

    class Objects(mi.TraversalCallback):  # made here: the class exists only once a variant is set
        def put(self, name, value, flags, cpptype=None):
            if isinstance(value, mi.Object):
                objects.append((name, value))

    obj.traverse(Objects())
    return objects


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


def _mesh_digest(v: np.ndarray, f: np.ndarray) -> bytes:
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
    order = sorted(range(len(parts)), key=lambda i: (_mesh_digest(parts[i][0], parts[i][1]), ids[i]))
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
        placements.append(Placement(group_of[gid], m, i))
        if group_tests[gid]:
            to_object = mi.traverse(inst)["to_world"].inverse()
            analytic += [AnalyticTest(t.shape, t.shape_index, t.prim, i, to_object) for t in group_tests[gid]]
    pairs = sum(t.instance is not None for t in analytic)
    if pairs > MAX_PER_SHAPE_TESTS:
        raise UnsupportedShapeError(
            f"the scene's instances place {pairs} analytic shapes (spheres, disks, cylinders, ellipsoids in shapegroups); "
            f"the layerbvh backend tests each placement per ray and takes at most {MAX_PER_SHAPE_TESTS}: "
            f"give the shapegroups meshes instead")
    if placements and len(groups[0].faces):
        # The scene's own meshes: one more group, placed once as they are (instance index 0,
        # so they win ties against instances).
        placements.insert(0, Placement(0, np.eye(4), None))
    return SceneGeometry(groups=groups, placements=placements, analytic=analytic, shape_names=names)


def _analytic_descriptor(test: AnalyticTest, geometry: SceneGeometry) -> str:
    """An analytic shape's content for the auto key: its type, bounding box, primitive and the
    placement of the instance it sits in (not its index in scene.shapes(): load order)."""
    b = test.shape.bbox()
    box = [list(map(float, b.min)), list(map(float, b.max))]
    place = None
    if test.instance is not None:
        place = next(p.to_world.tolist() for p in geometry.placements if p.instance == test.instance)
    return json.dumps([test.shape.class_name(), box, test.prim, place])


@dataclass
class PerSampleWork:
    """Traversal work per sample of the last counted render, for the heat maps: per name of
    HEATMAP_WORK, the work of the sample's camera ray (`camera`) and of its whole path (`path`),
    as UInt32 arrays of one entry per sample (the wavefront loop traces at the pass's width)."""

    camera: dict = field(default_factory=dict)
    path: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.path)


class SceneTracer(RayQueries):
    """Closest-hit and occlusion queries over a whole Mitsuba scene with the Layer BVH, between
    kernels (traced in batches in any engine mode; statistics possible).

    Built once per scene; every query returns Mitsuba types (PreliminaryIntersection3f, Bool).
    `traversal` is the engine mode (settings.Traversal.mode)."""

    def __init__(self, scene, traversal: str = "auto", treelet_height: int = layerbvh.DEFAULT_TREELET_HEIGHT,
                 leaf_size: int | None = None,
                 count_work: bool = True, batch_rays: int = layerbvh.BATCH_RAYS,
                 branching: int = layerbvh.DEFAULT_BRANCHING):
        t0 = time.perf_counter()
        self.scene = scene
        self.geometry = collect_geometry(scene)
        self.traversal = traversal
        self.count_work = count_work
        g = self.geometry
        backend = "cuda" if mi.variant().startswith("cuda") else "llvm"
        params = dict(treelet_height=treelet_height, leaf_size=leaf_size, backend=backend, batch_rays=batch_rays,
                      branching=branching)
        if g.instanced:
            # Each shapegroup's triangles once; the scene's own meshes are one more placement.
            self.bvh = layerbvh.build_instanced(g.engine_groups(), g.engine_instances(), **params)
            first = np.cumsum([0] + [len(gr.faces) for gr in g.groups])
            # Per engine instance: its group's first triangle in the tables below, and the
            # Mitsuba Instance it is (WORLD for the scene's own meshes).
            self.place_first = from_numpy(mi.UInt32, np.array([first[p.group] for p in g.placements], np.uint32))
            self.place_shape = from_numpy(mi.UInt32, np.array([WORLD if p.instance is None else p.instance
                                                                for p in g.placements], np.uint32))
            self.tri_shape = from_numpy(mi.UInt32, np.concatenate([gr.tri_shape for gr in g.groups]))
            self.tri_local = from_numpy(mi.UInt32, np.concatenate([gr.tri_local for gr in g.groups]))
        else:
            self.bvh = layerbvh.build(g.vertices, g.faces, **params)
            self.tri_shape = from_numpy(mi.UInt32, g.tri_shape)
            self.tri_local = from_numpy(mi.UInt32, g.tri_local)
        # numba's one-time kernel load is not build time (bvh.stats.kernel_load_s reports it).
        self.build_s = time.perf_counter() - t0 - self.bvh.stats.kernel_load_s
        self.reset_counters()

    def device_key(self) -> str:
        """What `auto`'s decisions depend on besides the rays: the scene's content (triangles,
        placements, analytic shapes), the BVH's parameters, the backend and the device. A
        SHA-256, so any change gives a new key; independent of the order in which Mitsuba
        loaded the shapes (each group's meshes are in content order, see `_group`, and groups,
        placements and analytic shapes are hashed as sorted lists)."""
        g = self.geometry
        group_digest = []
        for gr in g.groups:
            group_digest.append(_mesh_digest(gr.vertices, gr.faces).hex())
        h = hashlib.sha256()
        content = {
            "groups": sorted(group_digest),
            "placements": sorted(json.dumps([group_digest[p.group], p.to_world.tolist()]) for p in g.placements),
            "analytic": sorted(_analytic_descriptor(t, g) for t in g.analytic),
        }
        h.update(json.dumps(content).encode())
        st = self.bvh.stats
        h.update(json.dumps({"treelet_height": st.treelet_height, "leaf_size": st.leaf_size, "branching": st.branching,
                             "batch_rays": self.bvh.batch_rays, "backend": self.bvh.backend,
                             "cpu": layerbvh.cpu_model(),
                             "threads": dr.thread_count(), "layerbvh": layerbvh.__version__}).encode())
        return h.hexdigest()

    def reset_counters(self):
        self.trace_s = 0.0
        self.trace_stats = []
        self.work = PerSampleWork()  # with counting

    def _count(self, out, hint: str) -> None:
        """Add a query's per-ray work (one ray per sample: the wavefront loop runs at full width)."""
        if out.work is None:
            return
        for name in HEATMAP_WORK:
            w = mi.UInt32(out.work[name])
            for scope in (self.work.path, self.work.camera) if hint == "camera" else (self.work.path,):
                scope[name] = scope[name] + w if name in scope else w

    def _query(self, fn, hint: str):
        t0 = time.perf_counter()
        out = fn()
        self.trace_s += time.perf_counter() - t0
        self.trace_stats.append(out.stats)
        self._count(out, hint)
        return out

    # -- between kernels: traced in batches (any mode), statistics possible -----------------------
    symbolic = False

    def intersect(self, ray: mi.Ray3f, active, hint: str = "camera", kind=None) -> mi.PreliminaryIntersection3f:
        """Closest hit over meshes (our traversal) and analytic shapes (Mitsuba's per-shape test).
        `hint` ('camera' or 'bounce') names the kind of batch for auto's decision."""
        active = mi.Bool(active)
        hits = self._query(lambda: self.bvh.trace(ray.o, ray.d, ray.maxt, mode=self.traversal, stats=self.count_work,
                                                  hint=hint, active=active), hint)
        return self._preliminary(ray, active, hits)

    def occluded(self, ray: mi.Ray3f, active) -> mi.Bool:
        """Any hit in (0, ray.maxt): our any-hit traversal, then the analytic shapes."""
        active = mi.Bool(active)
        occ = self._query(lambda: self.bvh.occluded(ray.o, ray.d, ray.maxt, mode=self.traversal,
                                                    stats=self.count_work, hint="shadow", active=active), "shadow")
        return self._or_analytic(ray, active, mi.Bool(occ.occluded))

    # -- inside the caller's kernel: per_ray, no host synchronisation --------------------------------
    def intersect_inline(self, ray: mi.Ray3f, active) -> mi.PreliminaryIntersection3f:
        """As `intersect`, traced inline (usable in a symbolic loop)."""
        active = mi.Bool(active)
        return self._preliminary(ray, active, self.bvh.trace_inline(ray.o, ray.d, ray.maxt, active))

    def occluded_inline(self, ray: mi.Ray3f, active) -> mi.Bool:
        """As `occluded`, traced inline (usable in a symbolic loop)."""
        active = mi.Bool(active)
        hits = self.bvh.trace_inline(ray.o, ray.d, ray.maxt, active, any_hit=True)
        return self._or_analytic(ray, active, mi.UInt32(hits.prim) != layerbvh.MISS)

    # -- our hits as Mitsuba's ---------------------------------------------------------------------
    def _preliminary(self, ray, active, hits) -> mi.PreliminaryIntersection3f:
        """A Mitsuba PreliminaryIntersection3f from our closest hits, merged with the per-shape
        tests', filled as Mitsuba's Embree path fills it: a hit on the scene's own shapes sets
        `shape` and shape_index = its index in scene.shapes(); a hit inside an instance sets
        `instance` (shape stays null) and shape_index = the shape's index in its shapegroup."""
        hit = active & (mi.UInt32(hits.prim) != layerbvh.MISS)
        pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(ray.o))
        pi.t = dr.select(hit, mi.Float(hits.t), dr.inf)
        pi.prim_uv = mi.Point2f(mi.Float(hits.u), mi.Float(hits.v))
        instanced = self.geometry.instanced
        inst_shape = mi.UInt32(WORLD)  # the Mitsuba Instance hit (index into scene.shapes()), or WORLD
        if self.geometry.triangle_count:  # (Dr.Jit refuses to gather from an empty array)
            gid = dr.select(hit, mi.UInt32(hits.prim), 0)
            if instanced:
                place = dr.select(hit, mi.UInt32(hits.instance), 0)
                gid += dr.gather(mi.UInt32, self.place_first, place, hit)
                inst_shape = dr.select(hit, dr.gather(mi.UInt32, self.place_shape, place, hit), WORLD)
            pi.prim_index = dr.gather(mi.UInt32, self.tri_local, gid, hit)
            pi.shape_index = dr.gather(mi.UInt32, self.tri_shape, gid, hit)
        for test in self.geometry.analytic:
            api = test.shape.ray_intersect_preliminary(self._local(ray, test), test.prim, active)
            closer = active & api.is_valid() & (api.t < pi.t)
            pi.t = dr.select(closer, api.t, pi.t)
            pi.prim_uv = dr.select(closer, api.prim_uv, pi.prim_uv)
            pi.prim_index = dr.select(closer, api.prim_index, pi.prim_index)
            pi.shape_index = dr.select(closer, test.shape_index, pi.shape_index)
            if instanced:
                inst_shape = dr.select(closer, WORLD if test.instance is None else test.instance, inst_shape)
            hit |= closer
        if self.scene.shapes():
            in_instance = hit & (inst_shape != WORLD) if instanced else mi.Bool(False)
            pi.shape = dr.gather(mi.ShapePtr, self.scene.shapes_dr(), pi.shape_index, hit & ~in_instance)
            if instanced:
                pi.instance = dr.gather(mi.ShapePtr, self.scene.shapes_dr(), inst_shape, in_instance)
        pi.t = dr.select(hit, pi.t, dr.inf)
        if hasattr(pi, "valid"):
            pi.valid = hit
        return pi

    @staticmethod
    def _local(ray, test: AnalyticTest):
        """The ray in the space of a per-shape test (an instance's object space: Mitsuba's own
        to_object map, as Instance.compute_surface_interaction applies it)."""
        return ray if test.to_object is None else test.to_object @ ray

    def _or_analytic(self, ray, active, occ) -> mi.Bool:
        occ = occ & active
        for test in self.geometry.analytic:
            local = self._local(ray, test)
            if test.shape.class_name() == ELLIPSOIDS:  # its ray_test takes no primitive index
                occ |= active & test.shape.ray_intersect_preliminary(local, test.prim, active).is_valid()
            else:
                occ |= active & test.shape.ray_test(local, active)
        return occ
