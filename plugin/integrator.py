"""The `layerbvh` integrator: Mitsuba's path tracer with every ray query answered by the Layer BVH traversal."""
from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

import layerbvh

from .adapter import SceneTracer
from .features import Features, plan_features
from .record import bounce_kind


def mis_weight(pdf_a, pdf_b):
    """Power heuristic, as in Mitsuba's path tracers."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


def check_settings(max_depth: int, rr_depth: int, traversal: str, treelet_height: int, leaf_size: int,
                   batch_rays: int) -> None:
    """The integrator's rules for its properties (the CLI and converge check the same way):
    a ValueError naming the property and what it must be."""
    if max_depth < -1:
        raise ValueError(f"max_depth must be -1 (infinite) or >= 0, got {max_depth}")
    if rr_depth <= 0:
        raise ValueError(f"rr_depth must be > 0, got {rr_depth}")
    if traversal not in layerbvh.TRACE_MODES:
        raise ValueError(f"traversal must be one of {', '.join(layerbvh.TRACE_MODES)}; got {traversal!r}")
    layerbvh.check_param("treelet_height", treelet_height)
    layerbvh.check_param("leaf_size", leaf_size)
    layerbvh.check_param("batch_rays", batch_rays)


@dataclass
class SceneState:
    """What the integrator keeps per scene: its traversal (BVH built once) and feature plan."""

    scene: object
    tracer: SceneTracer
    features: Features


class LayerBVHPathTracer:
    r"""Unidirectional path tracer (same estimator as stock ``path``) tracing with layerbvh.

    Algorithm, per bounce (the primal path of ``prb``/stock ``path``): compute the surface
    interaction of the current hit, add emission with the power-heuristic MIS weight, sample an
    emitter (``next_2d``, always drawn) and test its visibility with our any-hit traversal, sample
    the BSDF (``next_1d``, ``next_2d``), apply Russian roulette (``next_1d``, always drawn), and
    find the next hit with our closest-hit traversal. Sampler use is in exactly this order, so a
    same-seed render matches stock ``path`` up to floating-point noise.

    Our traversal sorts and compacts rays between wavefront steps, which needs host
    synchronisation, so the bounce loop runs in evaluated mode (a Python loop, one step per
    bounce) instead of a symbolic loop. Everything a bounce carries to the next (the path state
    and the sampler's state) is evaluated at its end, so every bounce launches the same kernels.

    The scene is inspected once (``features.plan_features``) and only what it needs runs: no
    emitter sampling or shadow rays when it has no emitter, no emission lookups at hits when
    nothing in it can be hit and emits, no analytic-shape tests without analytic shapes, no sort
    when the BVH is one treelet, no work counters unless ``stats`` is set. Samples are still drawn
    in the same order, so leaving a feature out never changes the image.

    Properties: ``max_depth`` (default -1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false)
    as in ``path``; ``traversal`` (``auto`` | ``per_ray`` | ``layer_sorted`` | ``layer_unsorted``,
    default ``auto``: per ray batch, the faster of per_ray and layer_sorted, timed once per kind
    of batch), ``treelet_height`` (4), ``leaf_size`` (4), ``stats`` (false: collect
    traversal work counts), ``adaptive`` (true: leave out what the scene does not need),
    ``batch_rays`` (2^20: rays traced per batch; bounds the traversal's work memory).

    ``integrator_class`` makes the subclass of the active variant's ``mi.SamplingIntegrator``
    with these methods (Mitsuba's base classes exist once per variant, and nanobind classes take
    a single base); ``_base`` is that variant's ``SamplingIntegrator``.
    """

    _base = None

    def __init__(self, props: mi.Properties):
        self._base.__init__(self, props)
        self.max_depth = props.get("max_depth", -1)
        self.rr_depth = props.get("rr_depth", 5)
        self.hide_emitters = props.get("hide_emitters", False)
        self.traversal = props.get("traversal", "auto")
        self.treelet_height = props.get("treelet_height", 4)
        self.leaf_size = props.get("leaf_size", 4)
        self.stats = props.get("stats", False)
        self.adaptive = props.get("adaptive", True)
        self.batch_rays = props.get("batch_rays", layerbvh.BATCH_RAYS)
        try:
            check_settings(self.max_depth, self.rr_depth, self.traversal, self.treelet_height, self.leaf_size,
                           self.batch_rays)
        except ValueError as e:
            raise ValueError(f"layerbvh integrator: {e}") from None
        self._state: SceneState | None = None
        self._bounces = 0
        self.last_stats = {}

    # -- the BVH and the feature plan, made once per scene ---------------------------------------
    def scene_state(self, scene) -> SceneState:
        if self._state is None or self._state.scene is not scene:
            tracer = SceneTracer(scene, self.traversal, self.treelet_height, self.leaf_size, count_work=self.stats,
                                 batch_rays=self.batch_rays)
            features = plan_features(scene, len(tracer.geometry.analytic), tracer.bvh.stats.treelets,
                                     self.traversal, self.stats, self.adaptive)
            self._state = SceneState(scene, tracer, features)
        return self._state

    def tracer(self, scene) -> SceneTracer:
        """The scene's traversal: builds the BVH (and refuses unsupported shapes) on first use."""
        return self.scene_state(scene).tracer

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        state = self.scene_state(scene)
        tracer = state.tracer
        tracer.reset_counters()
        self._bounces = 0
        t0 = time.perf_counter()
        img = self._base.render(self, scene, sensor, seed, spp, develop, evaluate)
        dr.eval(img)
        total = time.perf_counter() - t0
        steps = tracer.trace_stats
        self.last_stats = {
            "build_s": tracer.build_s, "render_s": total, "trace_s": tracer.trace_s,
            "shading_s": max(total - tracer.trace_s, 0.0), "queries": len(steps),
            "traversal": self.traversal, "treelet_height": self.treelet_height,
            "bvh": {k: v for k, v in vars(tracer.bvh.stats).items() if k != "treelet_node_counts"},
            "rays": sum(s.rays for s in steps),
            "wavefront_steps": sum(s.steps for s in steps),
            "inner_nodes": sum(s.inner_nodes for s in steps),
            "leaves": sum(s.leaves for s in steps),
            "triangles": sum(s.triangles for s in steps),
            "time_sort_s": sum(s.time_sort_s for s in steps),
            "time_traverse_s": sum(s.time_traverse_s for s in steps),
            "peak_work_bytes": max((s.work_bytes for s in steps), default=0),
            "bounces": self._bounces,
            "modes_used": dict(Counter(s.mode for s in steps)),
            "auto_choices": {"/".join(map(str, k)): v for k, v in tracer.bvh.auto_choices.items()},
            "features": state.features.as_dict(),
        }
        return img

    # -- one ray per sample: the path tracer ----------------------------------------------------
    def sample(self, scene, sampler, ray, medium=None, active=True):
        state = self.scene_state(scene)
        tracer, use = state.tracer, state.features
        bsdf_ctx = mi.BSDFContext()
        ray = mi.Ray3f(ray)
        n = dr.width(ray.o)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        depth = mi.UInt32(0)
        L = mi.Spectrum(0)
        beta = mi.Spectrum(1)
        eta = mi.Float(1)
        prev_si = dr.zeros(mi.SurfaceInteraction3f, n)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        # As in stock `path`: a path that only sees the environment is a valid sample.
        valid_ray = mi.Bool((not self.hide_emitters) and scene.environment() is not None)
        if self.max_depth == 0:
            return mi.Spectrum(0), mi.Bool(False), []

        pi = tracer.intersect(ray, active, hint="camera")
        if self.hide_emitters:
            pi = self._skip_area_emitters(tracer, ray, pi, active)

        bounce = 0
        while True:
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
            bsdf = si.bsdf(ray)
            active_next = mi.Bool(active)
            if self.hide_emitters:
                active_next &= ~((depth == 0) & ~si.is_valid())

            # Emission reached by the previous BSDF sample, MIS-weighted against emitter sampling.
            Le = mi.Spectrum(0)
            if use.emitter_hits.on:
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                mis = mis_weight(prev_bsdf_pdf, scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta))
                Le = beta * mis * ds.emitter.eval(si, active_next & (prev_bsdf_pdf > 0))

            if self.max_depth >= 0:
                active_next &= depth + 1 < self.max_depth
            active_next &= si.is_valid()

            # Emitter sampling; Mitsuba's own visibility test would trace with Embree, so it is
            # switched off and the shadow ray goes through our any-hit traversal.
            # The sample is drawn even when emitter sampling is left out: the sequence stays stock's.
            em_sample = sampler.next_2d()
            Lr_dir = mi.Spectrum(0)
            if use.emitter_sampling.on:
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                ds, em_weight = scene.sample_emitter_direction(si, em_sample, False, active_em)
                active_em &= ds.pdf != 0.0
                shadow_ray = si.spawn_ray_to(ds.p)
                active_em &= ~tracer.occluded(shadow_ray, active_em)
                wo = si.to_local(ds.d)
                bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
                mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
                Lr_dir = dr.select(active_em, beta * mis_em * bsdf_value_em * em_weight, 0)

            bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            kind = None if tracer.recorder is None else bounce_kind(mi, dr, bsdf_sample.sampled_type, depth)

            L = dr.select(active, L + Le + Lr_dir, L)
            ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
            eta = dr.select(active, eta * bsdf_sample.eta, eta)
            beta = dr.select(active, beta * bsdf_weight, beta)
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Null)
            prev_si = si
            prev_bsdf_pdf = bsdf_sample.pdf
            prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            # Stock `path` counts the vertex before deciding Russian roulette on the new depth.
            depth = dr.select(active & si.is_valid(), depth + 1, depth)
            beta_max = dr.max(mi.unpolarized_spectrum(beta))
            rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            beta = dr.select(active & rr_active, beta * dr.rcp(rr_prob), beta)
            rr_continue = sampler.next_1d() < rr_prob
            active = active_next & (~rr_active | rr_continue) & (beta_max != 0)
            # The next bounce starts from evaluated arrays only (the sampler's state included),
            # so it compiles to the same kernels as this one.
            sampler.schedule_state()
            dr.eval(L, beta, eta, depth, active, valid_ray, ray, prev_si, prev_bsdf_pdf, prev_bsdf_delta)
            bounce += 1
            self._bounces = max(self._bounces, bounce)
            if not dr.any(active)[0] if dr.is_array_v(dr.any(active)) else not dr.any(active):
                break
            pi = tracer.intersect(ray, active, hint="bounce", kind=kind)

        return dr.select(valid_ray, L, 0), valid_ray, []

    def _skip_area_emitters(self, tracer, ray, pi, active):
        """hide_emitters: a camera ray that hits an area emitter continues behind it (as in prb)."""
        for _ in range(16):
            hit_em = active & pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711
            if not dr.any(hit_em)[0] if dr.is_array_v(dr.any(hit_em)) else not dr.any(hit_em):
                break
            si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, hit_em)
            ray = mi.Ray3f(dr.select(hit_em, si.spawn_ray(ray.d).o, ray.o), ray.d)
            pi2 = tracer.intersect(ray, hit_em, hint="camera")
            pi = dr.select(hit_em, pi2, pi)
        return pi

    def aov_names(self):
        return []

    def to_string(self):
        return (f"LayerBVHIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"traversal={self.traversal}, treelet_height={self.treelet_height}]")


# -- registration, once per variant ------------------------------------------------------------------

_classes: dict[str, type] = {}


def is_jit_variant(variant: str | None) -> bool:
    return bool(variant) and variant.split("_", 1)[0] in ("llvm", "cuda")


def integrator_class() -> type:
    """The LayerBVHIntegrator class of the active variant: that variant's mi.SamplingIntegrator
    with LayerBVHPathTracer's methods."""
    variant = mi.variant()
    if not is_jit_variant(variant):
        raise ValueError(f"the layerbvh integrator needs a JIT variant (llvm_* or cuda_*); the active variant is "
                         f"{variant}")
    cls = _classes.get(variant)
    if cls is None:
        methods = {k: v for k, v in vars(LayerBVHPathTracer).items() if k not in ("__dict__", "__weakref__")}
        base = mi.SamplingIntegrator
        cls = _classes[variant] = type("LayerBVHIntegrator", (base,), {**methods, "_base": base})
    return cls


def _make(props):
    return integrator_class()(props)


def register(variant: str | None = None) -> None:
    """Register `layerbvh` with the active Mitsuba variant (a scalar variant gets a factory that
    refuses by name: our traversal runs on Dr.Jit's JIT backends only)."""
    if (variant or mi.variant()) is not None:
        mi.register_integrator("layerbvh", _make)
