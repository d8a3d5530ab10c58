"""The `layerbvh` integrator: Mitsuba's path tracer with every ray query answered by the Layer BVH traversal."""
from __future__ import annotations

import json
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.runtime.adapter import SceneTracer
from layerbvh_mitsuba.runtime.cache import cache_dir
from layerbvh_mitsuba.runtime.compile_clock import CompileClock
from layerbvh_mitsuba.runtime.features import Features, plan_features
from layerbvh_mitsuba.runtime.held_instances import instances_held
from layerbvh_mitsuba.runtime.queries import EmbreeQueries, InlineQueries, RayQueries
from layerbvh_mitsuba.runtime.record import RayRecorder, RecordingQueries, bounce_kind
from layerbvh_mitsuba.runtime.settings import Traversal, check_settings
from layerbvh_mitsuba.runtime.stats import RenderStats


def mis_weight(pdf_a, pdf_b):
    """Power heuristic, as in Mitsuba's path tracers."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


def loop(state: tuple, cond, body, symbolic: bool, label: str) -> tuple:
    """`while cond(*state): state = body(*state)`, per lane. Symbolic: one Dr.Jit loop compiled
    into the caller's kernel. Otherwise a Python loop whose body may synchronise with the host
    (our sorted traversal does); its state (a sampler's included) is evaluated after every
    iteration, so every iteration compiles to the same kernels. (Dr.Jit's own evaluated mode
    applies the loop's mask to everything in the body, which arrays of another width, such as
    the traversal's compacted rays, cannot take.)"""
    if symbolic:
        return dr.while_loop(state, cond, body, label=label, mode="symbolic")
    # The first iteration's state too: a literal in it (dr.zeros, a constant) would be compiled
    # into that iteration's kernels, which the second iteration (evaluated arrays) then compiles
    # again (measured: a volpath case of the stability suite compiled 149 kernels, 3 of most).
    dr.make_opaque(*(x for x in state if not isinstance(x, mi.Sampler)))
    while bool(dr.any(cond(*state), axis=None)):
        state = body(*state)
        for x in state:
            if isinstance(x, mi.Sampler):
                x.schedule_state()
        dr.eval(*(x for x in state if not isinstance(x, mi.Sampler)))
    return state


@dataclass
class SceneState:
    """What the integrator keeps per scene: its traversal (BVH built once; None for the embree
    control), its feature plan, and where auto's decisions for it are kept between runs."""

    scene: object
    tracer: SceneTracer | None
    features: Features
    auto_file: Path | None = None
    prepass_s: float = 0.0  # auto's pre-passes, less compilation and the policy's own timing


@dataclass
class PathState:
    """What a path carries from one vertex to the next: the bounce loop's state."""

    ray: mi.Ray3f                      # the ray that found `pi`
    pi: mi.PreliminaryIntersection3f   # the vertex to shade next
    active: mi.Bool
    depth: mi.UInt32
    L: mi.Spectrum                     # radiance so far
    beta: mi.Spectrum                  # throughput
    eta: mi.Float                      # relative index of refraction so far (Russian roulette)
    valid: mi.Bool                     # the sample counts (stock path's valid_ray)
    prev_si: mi.SurfaceInteraction3f   # for the MIS weight of emission found by the BSDF sample
    prev_bsdf_pdf: mi.Float
    prev_bsdf_delta: mi.Bool


class LayerBVHPathTracer:
    r"""Unidirectional path tracer (same estimator as stock ``path``) tracing with layerbvh.

    Algorithm, per vertex (the primal path of ``prb``/stock ``path``; ``_vertex``): compute the
    surface interaction of the current hit, add emission with the power-heuristic MIS weight,
    sample an emitter (``next_2d``, always drawn) and test its visibility with our any-hit
    traversal, sample the BSDF (``next_1d``, ``next_2d``), apply Russian roulette (``next_1d``,
    always drawn), and find the next hit with our closest-hit traversal. Sampler use is in
    exactly this order, so a same-seed render matches stock ``path`` up to floating-point noise.

    The bounce loop runs in one of two modes (``dr.while_loop``):

    - *megakernel* (symbolic loop): ``per_ray`` and ``embree`` traversal, no statistics, no ray
      recording. The traversal is traced inline (``SceneTracer.intersect_inline``), so a render
      is one kernel, as stock ``path`` is.
    - *wavefront* (a Python loop, see ``loop``): the layer modes (their sort needs the host
      between wavefront steps), ``auto``, statistics and recording. Queries trace only the paths
      still alive (the traversal compacts its active rays), and every vertex launches the same
      kernels.

    The scene is inspected once (``features.plan_features``) and only what it needs runs: no
    emitter sampling or shadow rays when it has no emitter, no emission lookups at hits when
    nothing in it can be hit and emits, no analytic-shape tests without analytic shapes, no sort
    when the BVH is one treelet, no work counters unless ``stats`` is set. Samples are still drawn
    in the same order, so leaving a feature out never changes the image.

    Properties: ``max_depth`` (default -1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false)
    as in ``path``; ``traversal`` (``auto`` | ``per_ray`` | ``layer_sorted`` | ``layer_unsorted``
    | ``embree``, default ``auto``: per ray batch, the faster of per_ray and layer_sorted, timed
    once per kind of batch; ``embree``: this loop with Mitsuba's own queries, the control that
    isolates the traversal), ``branching`` (children per BVH node: 2, 4 or 8; default
    layerbvh.DEFAULT_BRANCHING), ``treelet_height`` (8, levels of that tree), ``leaf_size``
    (default 4 binary, 2 wide: layerbvh.default_leaf_size), ``stats`` (false:
    collect traversal work counts), ``adaptive`` (true: leave out what the scene does not need),
    ``batch_rays`` (2^20: rays traced per batch; bounds the traversal's work memory).

    ``integrator_class`` makes the subclass of the active variant's ``mi.SamplingIntegrator``
    with these methods (Mitsuba's base classes exist once per variant, and nanobind classes take
    a single base); ``_base`` is that variant's ``SamplingIntegrator``.
    """

    _base = None
    VOLUMETRIC = False  # the estimator handles participating media (features.plan_features)

    def __init__(self, props: mi.Properties):
        self._base.__init__(self, props)
        self.max_depth = props.get("max_depth", -1)
        self.rr_depth = props.get("rr_depth", 5)
        self.hide_emitters = props.get("hide_emitters", False)
        traversal = props.get("traversal", layerbvh.AUTO)
        self.treelet_height = props.get("treelet_height", layerbvh.DEFAULT_TREELET_HEIGHT)
        self.leaf_size = props.get("leaf_size", None)
        self.branching = props.get("branching", layerbvh.DEFAULT_BRANCHING)
        self.stats = props.get("stats", False)
        self.adaptive = props.get("adaptive", True)
        self.batch_rays = props.get("batch_rays", layerbvh.BATCH_RAYS)
        try:
            self.traversal = Traversal.parse(traversal)
            check_settings(self.max_depth, self.rr_depth, self.treelet_height, self.leaf_size, self.batch_rays,
                           self.branching)
        except ValueError as e:
            raise ValueError(f"layerbvh integrator: {e}") from None
        self._state: SceneState | None = None
        self._vertices = 0  # loop iterations of the last render (wavefront mode)
        self._auto_per_ray = False  # auto settled every kind of batch of this render on per_ray
        self._recorder: RayRecorder | None = None  # set by `render_recorded` for one render
        self.last_stats: RenderStats | None = None

    # -- the BVH and the feature plan, made once per scene ---------------------------------------
    def scene_state(self, scene) -> SceneState:
        if self._state is None or self._state.scene is not scene:
            if self.traversal.control:
                tracer, treelets = None, 1
                analytic = sum(not s.is_mesh() for s in scene.shapes())
            else:
                tracer = SceneTracer(scene, self.traversal.mode, self.treelet_height, self.leaf_size,
                                     count_work=self.stats, batch_rays=self.batch_rays, branching=self.branching)
                treelets, analytic = tracer.bvh.stats.treelets, len(tracer.geometry.analytic)
            features = plan_features(scene, analytic, treelets, self.traversal.name, self.stats, self.adaptive,
                                     volumetric=self.VOLUMETRIC)
            self._state = SceneState(scene, tracer, features)
            if self.traversal.auto:
                self._state.auto_file = cache_dir("auto") / f"{tracer.device_key()[:32]}.json"
                try:
                    tracer.bvh.auto.load(json.loads(self._state.auto_file.read_text()))
                except (OSError, ValueError):
                    pass  # nothing kept yet (or unreadable): decide again
        return self._state

    def heatmaps(self, scene) -> dict:
        """Traversal cost per pixel of the last counted render (`stats` true, wavefront loop): the
        mean over each pixel's samples of the work of its camera ray and of its whole path (inner
        nodes, triangles; wavefront steps in the layer modes), as (H, W) float64 arrays. Mitsuba
        orders a pass's samples pixel by pixel, sample i belonging to pixel i // spp."""
        tracer = self.scene_state(scene).tracer
        if tracer is None or not tracer.work:
            return {}
        w, h = (int(x) for x in scene.sensors()[0].film().crop_size())
        out = {}
        for scope, work in (("camera", tracer.work.camera), ("path", tracer.work.path)):
            for name, arr in work.items():
                if name == "steps" and (scope == "camera" or self.traversal.mode == "per_ray"):
                    continue  # per_ray: one kernel per query; not a map worth drawing
                per_sample = np.asarray(arr, np.float64)
                spp = len(per_sample) // (w * h)
                out[f"{scope}_{name.replace('inner_nodes', 'inner')}"] = \
                    per_sample[: w * h * spp].reshape(h, w, spp).mean(-1)
        return out

    def calibration_s(self) -> float:
        """Seconds auto has spent deciding for the current scene, all renders together: its
        pre-passes and timing runs, without kernel compilation (which timed_render reports)."""
        state = self._state
        if state is None or state.tracer is None:
            return 0.0
        return state.tracer.bvh.auto.calibration_s + state.prepass_s

    # -- auto: decided before the render -------------------------------------------------------
    PREPASS_SEED = 0x5EED  # the pre-pass's own sampler; the render's sampler is never touched

    def _auto_kinds(self, state: SceneState) -> list[tuple[bool, str]]:
        """(any_hit, hint) of every kind of batch this render traces."""
        if self.max_depth == 0:
            return []  # nothing is traced
        kinds = [(False, "camera")]
        if self.max_depth < 0 or self.max_depth > 1:
            kinds.append((False, "bounce"))
        if state.features.emitter_sampling.on:
            kinds.append((True, "shadow"))
        return kinds

    def _plan_auto(self, scene, state: SceneState, ray: mi.Ray3f) -> bool:
        """auto: decide every kind of batch this render traces before it starts. All of a
        render's batches of one kind have the pass's width (paths keep their lanes; the
        traversal compacts the live ones), so one decision per kind covers the render. What no
        rule or kept decision settles is timed in a pre-pass on this scene's rays
        (`_prepass`). True when every kind goes per_ray: the render is then one megakernel, the
        same kernel `per_ray` runs."""
        tracer = state.tracer
        policy, treelets = tracer.bvh.auto, tracer.bvh.stats.treelets
        k = min(dr.width(ray.o), self.batch_rays)  # what one traced batch holds
        reason = self._auto_rule(state)
        if reason is not None:
            for any_hit, hint in self._auto_kinds(state):
                policy.choices.setdefault(layerbvh.choice_key(any_hit, hint, k),
                                          {"mode": "per_ray", "reason": reason, "seconds": None, "sample_rays": 0})
            return True

        def modes():
            return [policy.settle(any_hit, hint, k, treelets) for any_hit, hint in self._auto_kinds(state)]
        if None in modes():
            self._prepass(scene, state, ray, k)
        return all(mode == "per_ray" for mode in modes())

    def _auto_rule(self, state: SceneState) -> str | None:
        """Why this integrator runs every batch of this scene per_ray (the megakernel) whatever
        timing would say, or None: the path tracer times its open decisions."""
        return None

    def _prepass(self, scene, state: SceneState, ray: mi.Ray3f, k: int) -> None:
        """Time auto's open decisions on rays of this scene, before the render: the pass's first
        `k` camera rays (one batch, as the render traces it) and one path vertex on them, shaded
        with a sampler of its own (PREPASS_SEED), so its camera hits, shadow rays and first
        bounce rays reach the traversal with mode auto, which times each open kind on this
        batch (AutoPolicy.decide). The render's sampler is not touched: the image is the same
        with or without a pre-pass. Its wall time less kernel compilation is calibration."""
        tracer = state.tracer
        policy_s = tracer.bvh.auto.calibration_s
        t0 = time.perf_counter()
        with CompileClock() as clock:
            idx = dr.arange(mi.UInt32, k)
            take = (lambda x: x if dr.width(x) <= 1 else dr.gather(type(x), x, idx))
            cam = mi.Ray3f(take(ray.o), take(ray.d), take(ray.maxt), take(ray.time), take(ray.wavelengths))
            sampler = mi.load_dict({"type": "independent"})
            sampler.seed(self.PREPASS_SEED, k)
            self._prepass_paths(scene, state, cam, sampler)
        state.prepass_s += (time.perf_counter() - t0 - clock.seconds
                            - (tracer.bvh.auto.calibration_s - policy_s))

    def _prepass_paths(self, scene, state: SceneState, cam: mi.Ray3f, sampler) -> None:
        """The pre-pass's work on its camera rays: their hits and one path vertex (the kinds of
        batch a render of this integrator traces)."""
        active = dr.full(mi.Bool, True, dr.width(cam.o))
        path = self._start_path(scene, cam, state.tracer.intersect(cam, active, hint="camera"), active)
        self._vertex(scene, sampler, state.features, state.tracer, path, megakernel=False)

    def _keep_auto_choices(self, state: SceneState) -> None:
        """Persist auto's timed decisions, so later runs on this scene, BVH and device skip timing."""
        timed = {k: c for k, c in state.tracer.bvh.auto_choices.items() if c.get("seconds")}
        if timed:
            try:
                atomic.write_text(state.auto_file, json.dumps(timed, indent=1))
            except OSError:
                pass  # a read-only cache costs only the timing next time

    def tracer(self, scene) -> SceneTracer | None:
        """The scene's traversal: builds the BVH (and refuses unsupported shapes) on first use;
        None for the embree control."""
        return self.scene_state(scene).tracer

    def megakernel(self) -> bool:
        """Whether the bounce loop compiles into one kernel (see the class docstring)."""
        if self._recorder is not None:
            return False  # recording reads the rays on the host
        if self.traversal.control:
            return True  # Embree's queries have no counters of ours
        if self.stats:
            return False  # counters are read on the host
        return self.traversal.mode == "per_ray" or (self.traversal.auto and self._auto_per_ray)

    def render_recorded(self, scene, recorder: RayRecorder, spp: int, seed: int = 0):
        """`mi.render` with every ray this render traces kept in `recorder` by kind (camera,
        bounces by sampled lobe, shadow): RecordingQueries in front of the render's queries, in
        the wavefront loop. Returns the image."""
        self._recorder = recorder
        try:
            return mi.render(scene, integrator=self, spp=spp, seed=seed)
        finally:
            self._recorder = None

    # -- statistics of a render -----------------------------------------------------------------
    # No `render` override: Mitsuba guards its render with a SIGINT handler, and a Python render
    # calling the base render again would nest two of them, which loses Ctrl-C. `sample` runs
    # once per render (JIT variants trace all of a pass's samples at once), so it brackets it.

    def _begin(self, scene, state: SceneState, ray: mi.Ray3f) -> dict:
        start = {"calibration_s": self.calibration_s()}
        if self.traversal.auto:
            self._auto_per_ray = self._plan_auto(scene, state, ray)
        start["t0"] = time.perf_counter()  # the render's own time starts after the pre-pass
        if state.tracer is not None:
            state.tracer.reset_counters()  # (the pre-pass's queries are not the render's)
        self._vertices = 0
        return start

    def _finish(self, state: SceneState, start: dict, megakernel: bool) -> None:
        """`last_stats` of this render (in the megakernel the work runs after `sample` returns, so
        its times say nothing there and are None)."""
        tracer = state.tracer
        total = time.perf_counter() - start["t0"]
        if self.traversal.auto:
            self._keep_auto_choices(state)
        steps = tracer.trace_stats if tracer is not None else []
        trace_s = None if megakernel or tracer is None else tracer.trace_s
        self.last_stats = RenderStats(
            loop="megakernel" if megakernel else "wavefront", traversal=self.traversal.name,
            treelet_height=self.treelet_height, branching=self.branching, features=state.features,
            bvh=None if tracer is None else tracer.bvh.stats,
            build_s=tracer.build_s if tracer is not None else 0.0, trace_s=trace_s,
            shading_s=None if trace_s is None else max(total - trace_s, 0.0), queries=len(steps),
            rays=sum(s.rays for s in steps), wavefront_steps=sum(s.steps for s in steps),
            ray_steps=sum(s.ray_steps for s in steps), inner_nodes=sum(s.inner_nodes for s in steps),
            leaves=sum(s.leaves for s in steps), triangles=sum(s.triangles for s in steps),
            time_sort_s=sum(s.time_sort_s for s in steps), time_traverse_s=sum(s.time_traverse_s for s in steps),
            peak_work_bytes=max((s.work_bytes for s in steps), default=0),
            bounces=None if megakernel else self._vertices, modes_used=dict(Counter(s.mode for s in steps)),
            auto_choices={} if tracer is None else dict(tracer.bvh.auto_choices),
            calibration_s=self.calibration_s() - start["calibration_s"])

    # -- one ray per sample: the path tracer ----------------------------------------------------
    @instances_held()
    def sample(self, scene, sampler, ray, medium=None, active=True):
        state = self.scene_state(scene)
        tracer = state.tracer
        start = self._begin(scene, state, ray)
        megakernel = self.megakernel()
        queries = self._queries(scene, tracer, megakernel)
        n = dr.width(ray.o)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        if self.max_depth == 0:
            self._finish(state, start, megakernel)
            return mi.Spectrum(0), mi.Bool(False), []
        ray = mi.Ray3f(ray)
        pi = queries.intersect(ray, active, hint="camera")
        if self.hide_emitters:
            pi = self._skip_area_emitters(queries, ray, pi, active, megakernel)
        path = self._start_path(scene, ray, pi, active)
        sampler, path = loop(
            (sampler, path), cond=lambda sampler, path: path.active,
            body=lambda sampler, path: self._vertex(scene, sampler, state.features, queries, path, megakernel),
            symbolic=megakernel, label="layerbvh path tracer")
        self._finish(state, start, megakernel)
        return dr.select(path.valid, path.L, 0), path.valid, []

    def _queries(self, scene, tracer: SceneTracer | None, megakernel: bool) -> RayQueries:
        """Who answers this render's queries: Embree (the control), our traversal inline (the
        megakernel) or between kernels, and, when recording, a recorder in front."""
        if self.traversal.control:
            queries = EmbreeQueries(scene)
        else:
            queries = InlineQueries(tracer) if megakernel else tracer
        return queries if self._recorder is None else RecordingQueries(queries, self._recorder)

    def _start_path(self, scene, ray: mi.Ray3f, pi, active) -> PathState:
        """The state of paths whose camera rays `ray` found `pi`."""
        n = dr.width(active)
        return PathState(
            ray=ray, pi=pi, active=active, depth=dr.zeros(mi.UInt32, n), L=dr.zeros(mi.Spectrum, n),
            beta=dr.full(mi.Spectrum, 1, n), eta=dr.full(mi.Float, 1, n),
            # As in stock `path`: a path that only sees the environment is a valid sample.
            valid=dr.full(mi.Bool, (not self.hide_emitters) and scene.environment() is not None, n),
            prev_si=dr.zeros(mi.SurfaceInteraction3f, n), prev_bsdf_pdf=dr.full(mi.Float, 1, n),
            prev_bsdf_delta=dr.full(mi.Bool, True, n))

    def _vertex(self, scene, sampler, use: Features, queries, p: PathState, megakernel: bool):
        """One loop iteration: shade the vertex `p.pi`, then find the next one."""
        if not megakernel:
            self._vertices += 1
        bsdf_ctx = mi.BSDFContext()
        active, depth, beta, eta = p.active, p.depth, p.beta, p.eta
        si = p.pi.compute_surface_interaction(p.ray, mi.RayFlags.All, active)
        bsdf = si.bsdf(p.ray)
        active_next = mi.Bool(active)
        if self.hide_emitters:
            active_next &= ~((depth == 0) & ~si.is_valid())

        # Emission reached by the previous BSDF sample, MIS-weighted against emitter sampling.
        Le = mi.Spectrum(0)
        if use.emitter_hits.on:
            ds = mi.DirectionSample3f(scene, si=si, ref=p.prev_si)
            mis = mis_weight(p.prev_bsdf_pdf, scene.pdf_emitter_direction(p.prev_si, ds, ~p.prev_bsdf_delta))
            Le = beta * mis * ds.emitter.eval(si, active_next & (p.prev_bsdf_pdf > 0))

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
            active_em &= ~queries.occluded(si.spawn_ray_to(ds.p), active_em)
            wo = si.to_local(ds.d)
            bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
            mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
            Lr_dir = dr.select(active_em, beta * mis_em * bsdf_value_em * em_weight, 0)

        bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)

        # (Without either emission term L stays p.L itself: Dr.Jit's loop optimisation re-records
        # a loop whose state comes back unchanged, and `select(active, 0 + 0, 0)` on the literal
        # it then substitutes is a new variable, which it refuses.)
        L = dr.select(active, p.L + Le + Lr_dir, p.L) if use.emitter_hits.on or use.emitter_sampling.on else p.L
        ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
        eta = dr.select(active, eta * bsdf_sample.eta, eta)
        beta = dr.select(active, beta * bsdf_weight, beta)
        valid = p.valid | (active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Null))

        # Stock `path` counts the vertex before deciding Russian roulette on the new depth.
        depth = dr.select(active & si.is_valid(), depth + 1, depth)
        beta_max = dr.max(mi.unpolarized_spectrum(beta))
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = depth >= self.rr_depth
        beta = dr.select(active & rr_active, beta * dr.rcp(rr_prob), beta)
        rr_continue = sampler.next_1d() < rr_prob
        active = active_next & (~rr_active | rr_continue) & (beta_max != 0)

        kind = None
        if isinstance(queries, RecordingQueries):
            kind = bounce_kind(mi, dr, bsdf_sample.sampled_type, p.depth)
        pi = queries.intersect(ray, active, hint="bounce", kind=kind)
        return sampler, PathState(ray=ray, pi=pi, active=active, depth=depth, L=L, beta=beta, eta=eta, valid=valid,
                                  prev_si=si, prev_bsdf_pdf=bsdf_sample.pdf,
                                  prev_bsdf_delta=mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta))

    def _skip_area_emitters(self, queries, ray, pi, active, megakernel: bool):
        """hide_emitters: a camera ray that hits an area emitter continues behind it (as in prb)."""
        def hits_emitter(ray, pi):
            return active & pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711

        def step(ray, pi):
            hit_em = hits_emitter(ray, pi)
            si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, hit_em)
            ray = mi.Ray3f(dr.select(hit_em, si.spawn_ray(ray.d).o, ray.o), ray.d)
            return ray, dr.select(hit_em, queries.intersect(ray, hit_em, hint="camera"), pi)
        _, pi = loop((ray, pi), cond=hits_emitter, body=step, symbolic=megakernel, label="layerbvh hide_emitters")
        return pi

    def aov_names(self):
        return []

    def to_string(self):
        return (f"LayerBVHIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"traversal={self.traversal}, branching={self.branching}, treelet_height={self.treelet_height}]")
