"""Scene adapter: a Mitsuba scene's mesh triangles in world space, its analytic shapes, and the map from our hits
back to Mitsuba shapes."""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh
from layerbvh import from_numpy
from layerbvh_mitsuba.runtime import extreme_scale
from layerbvh_mitsuba.runtime.queries import RayQueries
from layerbvh_mitsuba.runtime.scene_geometry import (AnalyticTest, ELLIPSOIDS, SceneGeometry, mesh_digest,
    collect_geometry)

# Per-ray work kept per sample for the traversal-cost heat maps (state.WORK names).
HEATMAP_WORK = ("inner_nodes", "triangles", "steps")
WORLD = layerbvh.MISS


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
                 branching: int = layerbvh.DEFAULT_BRANCHING, tail_steps: int = layerbvh.TAIL_STEPS):
        t0 = time.perf_counter()
        self.scene = scene
        self.geometry = collect_geometry(scene)
        self.traversal = traversal
        self.count_work = count_work
        g = self.geometry
        backend = "cuda" if mi.variant().startswith("cuda") else "llvm"
        params = dict(treelet_height=treelet_height, leaf_size=leaf_size, backend=backend, batch_rays=batch_rays,
                      branching=branching, tail_steps=tail_steps)
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
        self.normals = extreme_scale.FaceNormals.needed(scene, g.groups[0])
        self.far = extreme_scale.far_scene(scene)
        self.tiny = extreme_scale.tiny_unit(scene)
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
            group_digest.append(mesh_digest(gr.vertices, gr.faces).hex())
        h = hashlib.sha256()
        content = {
            "groups": sorted(group_digest),
            "placements": sorted(json.dumps([group_digest[p.group], p.to_world.tolist()]) for p in g.placements),
            "analytic": sorted(_analytic_descriptor(t, g) for t in g.analytic),
        }
        h.update(json.dumps(content).encode())
        st = self.bvh.stats
        h.update(json.dumps({"treelet_height": st.treelet_height, "leaf_size": st.leaf_size, "branching": st.branching,
                             "batch_rays": self.bvh.batch_rays, "tail_steps": self.bvh.tail_steps,
                             "backend": self.bvh.backend,
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
    def surface(self, pi, ray, flags, active=True):
        """Mitsuba's surface interaction, its normals repaired where float32 lost them (extreme_scale)."""
        si = pi.compute_surface_interaction(ray, flags, active)
        return si if self.normals is None else self.normals.repair(si, pi, ray, active)

    def shadow_ray(self, ref, p):
        """Mitsuba's ray from `ref` to `p`, rebuilt where float32 lost it, offset as at unit size in
        a tiny scene (extreme_scale)."""
        if self.far or self.tiny:
            return extreme_scale.spawn_ray_to(ref, p, self.tiny)
        return ref.spawn_ray_to(p)

    def spawn(self, si, d):
        """Mitsuba's ray leaving `si` along `d`, offset as at unit size in a tiny scene (extreme_scale)."""
        return extreme_scale.spawn_ray(si, d, self.tiny) if self.tiny else si.spawn_ray(d)

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
