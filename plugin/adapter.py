"""Scene adapter: a Mitsuba scene's mesh triangles in world space, its analytic shapes, and the map from our hits back to Mitsuba shapes."""
from __future__ import annotations

import hashlib
import json
import platform
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh

# Per-ray work kept per sample for the traversal-cost heat maps (state.WORK names).
HEATMAP_WORK = ("inner_nodes", "triangles", "steps")
# Shapes traced by Mitsuba's own per-shape routine and merged with the BVH's closest hit.
ANALYTIC = ("Sphere", "Disk", "Cylinder")


class UnsupportedShapeError(ValueError):
    """A scene holds a shape type this backend cannot trace (never traced wrongly: refused)."""


@dataclass
class SceneGeometry:
    """Everything the traversal needs from a scene, gathered once.

    vertices/faces  all mesh triangles in world space, one global index space
    tri_shape       uint32 (F,): index into scene.shapes() of each global triangle
    tri_local       uint32 (F,): the triangle's index inside its own mesh
    analytic        [(shape index, shape)] for spheres, disks and cylinders
    """

    vertices: np.ndarray
    faces: np.ndarray
    tri_shape: np.ndarray
    tri_local: np.ndarray
    analytic: list = field(default_factory=list)
    shape_names: list = field(default_factory=list)

    @property
    def triangle_count(self) -> int:
        return len(self.faces)


def describe(shape, index=None) -> str:
    sid = shape.id()
    name = f"'{sid}'" if sid else "(no id)"
    return f"{shape.class_name()} {name}" + (f" (shape #{index})" if index is not None and not sid else "")


def collect_geometry(scene) -> SceneGeometry:
    """World-space triangles of every mesh shape plus the analytic shapes; refuse anything else."""
    verts, faces, tri_shape, tri_local, analytic, names = [], [], [], [], [], []
    offset = 0
    for i, shape in enumerate(scene.shapes()):
        names.append(describe(shape, i))
        if shape.is_mesh():
            v, f = layerbvh.check_mesh(np.array(shape.vertex_positions_buffer()).reshape(-1, 3),
                                       np.array(shape.faces_buffer(), np.int64).reshape(-1, 3),
                                       name=f"shape {describe(shape)}")
            verts.append(v)
            faces.append(f + offset)
            tri_shape.append(np.full(len(f), i, np.uint32))
            tri_local.append(np.arange(len(f), dtype=np.uint32))
            offset += len(v)
        elif shape.class_name() in ANALYTIC:
            analytic.append((i, shape))
        else:
            raise UnsupportedShapeError(
                f"shape {describe(shape, i)} (plugin type '{shape.class_name().lower()}') is not supported by the "
                f"layerbvh backend: it traces triangle meshes (incl. rectangle, cube, ply, obj, serialized) "
                f"and {', '.join(a.lower() for a in ANALYTIC)}; instances/shapegroups, curves, SDF grids and "
                f"ellipsoids are refused rather than traced wrongly")
    cat = (lambda xs, shape, dt: np.concatenate(xs) if xs else np.zeros(shape, dt))
    return SceneGeometry(vertices=cat(verts, (0, 3), np.float32), faces=cat(faces, (0, 3), np.int64),
                         tri_shape=cat(tri_shape, (0,), np.uint32), tri_local=cat(tri_local, (0,), np.uint32),
                         analytic=analytic, shape_names=names)


class SceneTracer:
    """Closest-hit and occlusion queries over a whole Mitsuba scene with the Layer BVH.

    Built once per scene; every query returns Mitsuba types (PreliminaryIntersection3f, Bool)."""

    def __init__(self, scene, traversal: str = "auto", treelet_height: int = layerbvh.DEFAULT_TREELET_HEIGHT,
                 leaf_size: int = layerbvh.DEFAULT_LEAF_SIZE,
                 count_work: bool = True, batch_rays: int = layerbvh.BATCH_RAYS):
        t0 = time.perf_counter()
        self.scene = scene
        self.geometry = collect_geometry(scene)
        self.traversal = traversal
        self.count_work = count_work
        self.bvh = layerbvh.build(self.geometry.vertices, self.geometry.faces, treelet_height=treelet_height,
                                  leaf_size=leaf_size, backend="cuda" if mi.variant().startswith("cuda") else "llvm",
                                  batch_rays=batch_rays)
        self.tri_shape = mi.UInt32(self.geometry.tri_shape)
        self.tri_local = mi.UInt32(self.geometry.tri_local)
        # numba's one-time kernel load is not build time (bvh.stats.kernel_load_s reports it).
        self.build_s = time.perf_counter() - t0 - self.bvh.stats.kernel_load_s
        self.trace_s = 0.0
        self.trace_stats = []
        self.recorder = None  # a record.RayRecorder to capture every traced ray by kind

    def device_key(self) -> str:
        """What `auto`'s decisions depend on besides the rays: the scene's triangles, the BVH's
        parameters, the backend and the device. A SHA-256, so any change gives a new key."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.geometry.vertices).tobytes())
        h.update(np.ascontiguousarray(self.geometry.faces).tobytes())
        st = self.bvh.stats
        cpu = platform.processor() or platform.machine()
        try:
            with open("/proc/cpuinfo") as fh:
                cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), cpu)
        except OSError:
            pass
        h.update(json.dumps({"treelet_height": st.treelet_height, "leaf_size": st.leaf_size,
                             "batch_rays": self.bvh.batch_rays, "backend": self.bvh.backend, "cpu": cpu,
                             "threads": dr.thread_count(), "layerbvh": layerbvh.__version__}).encode())
        return h.hexdigest()

    def reset_counters(self):
        self.trace_s = 0.0
        self.trace_stats = []
        self.work = {}  # with counting: per sample, work summed over the camera query / the whole path

    def _count(self, out, hint: str) -> None:
        """Add a query's per-ray work (one ray per sample: the wavefront loop runs at full width)."""
        if out.work is None:
            return
        for name in HEATMAP_WORK:
            w = mi.UInt32(out.work[name])
            keys = ("path", "camera") if hint == "camera" else ("path",)
            for k in keys:
                key = f"{k}_{name}"
                self.work[key] = self.work[key] + w if key in self.work else w

    def _query(self, fn, hint: str):
        t0 = time.perf_counter()
        out = fn()
        self.trace_s += time.perf_counter() - t0
        self.trace_stats.append(out.stats)
        self._count(out, hint)
        return out

    # -- between kernels: traced in batches (any mode), statistics and recording possible ----------
    symbolic = False

    def intersect(self, ray: mi.Ray3f, active, hint: str = "camera", kind=None) -> mi.PreliminaryIntersection3f:
        """Closest hit over meshes (our traversal) and analytic shapes (Mitsuba's per-shape test).
        `hint` ('camera' or 'bounce') names the kind of batch for auto's decision; `kind` (an
        array of record.KINDS codes, default: the hint) labels the rays for a recorder."""
        active = mi.Bool(active)
        if self.recorder is not None:
            self.recorder.add(hint if kind is None else kind, ray, active)
        hits = self._query(lambda: self.bvh.trace(ray.o, ray.d, ray.maxt, mode=self.traversal, stats=self.count_work,
                                                  hint=hint, active=active), hint)
        return self._preliminary(ray, active, hits)

    def occluded(self, ray: mi.Ray3f, active) -> mi.Bool:
        """Any hit in (0, ray.maxt): our any-hit traversal, then the analytic shapes."""
        active = mi.Bool(active)
        if self.recorder is not None:
            self.recorder.add("shadow", ray, active)
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
        """A Mitsuba PreliminaryIntersection3f from our closest hits, merged with the analytic shapes'."""
        hit = active & (mi.UInt32(hits.prim) != layerbvh.MISS)
        pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(ray.o))
        pi.t = dr.select(hit, mi.Float(hits.t), dr.inf)
        pi.prim_uv = mi.Point2f(mi.Float(hits.u), mi.Float(hits.v))
        if self.geometry.triangle_count:  # (Dr.Jit refuses to gather from an empty array)
            gid = dr.select(hit, mi.UInt32(hits.prim), 0)
            pi.prim_index = dr.gather(mi.UInt32, self.tri_local, gid, hit)
            pi.shape_index = dr.gather(mi.UInt32, self.tri_shape, gid, hit)
        for index, shape in self.geometry.analytic:
            api = shape.ray_intersect_preliminary(ray, 0, active)
            closer = active & api.is_valid() & (api.t < pi.t)
            pi.t = dr.select(closer, api.t, pi.t)
            pi.prim_uv = dr.select(closer, api.prim_uv, pi.prim_uv)
            pi.prim_index = dr.select(closer, api.prim_index, pi.prim_index)
            pi.shape_index = dr.select(closer, index, pi.shape_index)
            hit |= closer
        if self.scene.shapes():
            pi.shape = dr.gather(mi.ShapePtr, self.scene.shapes_dr(), pi.shape_index, hit)
        pi.t = dr.select(hit, pi.t, dr.inf)
        if hasattr(pi, "valid"):
            pi.valid = hit
        return pi

    def _or_analytic(self, ray, active, occ) -> mi.Bool:
        occ = occ & active
        for _, shape in self.geometry.analytic:
            occ |= active & shape.ray_test(ray, active)
        return occ


class InlineQueries:
    """The bounce loop's queries as per_ray traversal inside its kernel (the megakernel path)."""

    symbolic = True

    def __init__(self, tracer: SceneTracer):
        self.tracer = tracer

    def intersect(self, ray, active, hint: str = "camera", kind=None):
        return self.tracer.intersect_inline(ray, active)

    def occluded(self, ray, active):
        return self.tracer.occluded_inline(ray, active)


class EmbreeQueries:
    """The bounce loop's queries answered by stock Mitsuba (Embree): the control that isolates
    the traversal's cost (same loop, another traversal)."""

    symbolic = True

    def __init__(self, scene):
        self.scene = scene

    def intersect(self, ray, active, hint: str = "camera", kind=None):
        return self.scene.ray_intersect_preliminary(ray, coherent=hint == "camera", active=active)

    def occluded(self, ray, active):
        return self.scene.ray_test(ray, active)
