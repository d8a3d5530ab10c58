"""The render driver: one Mitsuba integrator per estimator it is given (runtime/estimators/), owning what a render
needs around sampling: the scene's BVH and feature plan, auto's pre-pass and kept decisions, the loop mode,
statistics, ray recording and heat maps."""
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
from layerbvh_mitsuba.runtime.estimators.common import Tracing
from layerbvh_mitsuba.runtime.features import Features, plan_features
from layerbvh_mitsuba.runtime.held_instances import instances_held
from layerbvh_mitsuba.runtime.queries import EmbreeQueries, InlineQueries, RayQueries
from layerbvh_mitsuba.runtime.record import RayRecorder, RecordingQueries
from layerbvh_mitsuba.runtime.settings import Traversal, check_traversal_settings
from layerbvh_mitsuba.runtime.stats import RenderStats


@dataclass
class SceneState:
    """What the integrator keeps per scene: its traversal (BVH built once; None for the embree
    control), its feature plan, and where auto's decisions for it are kept between runs."""

    scene: object
    tracer: SceneTracer | None
    features: Features
    auto_file: Path | None = None
    prepass_s: float = 0.0  # auto's pre-passes, less compilation and the policy's own timing


# Mitsuba's integrator base classes exist once per variant (SamplingIntegrator, AdjointIntegrator,
# and the Python RBIntegrator, reloaded per variant), and a nanobind class takes no second base: a
# mixin beside the bound base is refused ("nb_type_init(): invalid number of bases", measured). So
# the driver is a class statement over its base, made once per base class.
_drivers: dict[type, type] = {}


def driver_class(base: type) -> type:
    """The render driver (LayerBVHIntegrator) as a subclass of `base`, one of a JIT variant's
    integrator base classes, made once per base."""
    cls = _drivers.get(base)
    if cls is None:
        cls = _drivers[base] = _driver_over(base)
    return cls


def _driver_over(base: type) -> type:
    class LayerBVHIntegrator(base):
        r"""A Mitsuba sampling integrator whose every ray query our traversal answers: the driver of
        one estimator (``ESTIMATOR``, a class of runtime/estimators/, made from the same properties),
        as Mitsuba's ``common.py`` drives ``prb.py``.

        Per render (``sample``: JIT variants trace all of a pass's samples at once): make the scene's
        BVH and feature plan once per scene (``scene_state``); with ``traversal`` auto, decide every
        kind of batch the estimator traces before the render (``_plan_auto``, timing what is open in
        a pre-pass); choose the loop mode; hand the estimator its queries (``Tracing``); then keep
        the render's statistics (``last_stats``).

        The loop runs in one of two modes:

        - *megakernel* (a symbolic loop): ``per_ray`` and ``embree`` traversal, no statistics, no ray
          recording. The traversal is traced inline (``SceneTracer.intersect_inline``), so a render
          is one kernel, as stock's is.
        - *wavefront* (a Python loop, see ``estimators.common.loop``): the layer modes (their sort
          needs the host between wavefront steps), ``auto``, statistics and recording. Queries trace
          only the paths still alive (the traversal compacts its active rays), and every iteration
          launches the same kernels.

        The scene is inspected once (``features.plan_features``) and only what it needs runs: no
        emitter sampling or shadow rays when it has no emitter, no emission lookups at hits when
        nothing in it can be hit and emits, no analytic-shape tests without analytic shapes, no sort
        when the BVH is one treelet, no work counters unless ``stats`` is set. Samples are still drawn
        in the same order, so leaving a feature out never changes the image.

        Properties (besides the estimator's): ``traversal`` (``auto`` | ``per_ray`` | ``layer_sorted``
        | ``layer_unsorted`` | ``embree``, default ``auto``: per ray batch, the faster of per_ray and
        layer_sorted, timed once per kind of batch; ``embree``: this loop with Mitsuba's own queries,
        the control that isolates the traversal), ``branching`` (children per BVH node: 2, 4 or 8;
        default layerbvh.DEFAULT_BRANCHING), ``treelet_height`` (8, levels of that tree),
        ``leaf_size`` (default 4 binary, 2 wide: layerbvh.default_leaf_size), ``stats`` (false:
        collect traversal work counts), ``adaptive`` (true: leave out what the scene does not need),
        ``batch_rays`` (2^20: rays traced per batch; bounds the traversal's work memory), ``tail_steps``
        (1: sorted wavefront steps before the per-ray tail finishes a batch; layerbvh.TAIL_STEPS).

        ``registry.integrator_class`` makes, per variant and estimator, a subclass naming its
        estimator (``ESTIMATOR``) and plugin (``PLUGIN``); ``_base`` is the Mitsuba base class.
        """

        _base = base
        ESTIMATOR = None  # the estimator class (registry.PLUGINS)
        PLUGIN = "layerbvh"

        def __init__(self, props: mi.Properties):
            super().__init__(props)
            traversal = props.get("traversal", layerbvh.AUTO)
            self.treelet_height = props.get("treelet_height", layerbvh.DEFAULT_TREELET_HEIGHT)
            self.leaf_size = props.get("leaf_size", None)
            self.branching = props.get("branching", layerbvh.DEFAULT_BRANCHING)
            self.stats = props.get("stats", False)
            self.adaptive = props.get("adaptive", True)
            self.batch_rays = props.get("batch_rays", layerbvh.BATCH_RAYS)
            self.tail_steps = props.get("tail_steps", layerbvh.TAIL_STEPS)
            try:
                self.traversal = Traversal.parse(traversal)
                check_traversal_settings(self.treelet_height, self.leaf_size, self.batch_rays, self.branching,
                                         self.tail_steps)
                self.estimator = self.ESTIMATOR(props)
            except ValueError as e:
                raise ValueError(f"{self.PLUGIN} integrator: {e}") from None
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
                                         count_work=self.stats, batch_rays=self.batch_rays, branching=self.branching,
                                         tail_steps=self.tail_steps)
                    treelets, analytic = tracer.bvh.stats.treelets, len(tracer.geometry.analytic)
                features = plan_features(scene, analytic, treelets, self.traversal.name, self.stats, self.adaptive,
                                         volumetric=self.estimator.VOLUMETRIC)
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

        def _plan_auto(self, state: SceneState, width: int, prepass) -> bool:
            """auto: decide every kind of batch this render traces before it starts. All of a
            render's batches of one kind have the pass's width (paths keep their lanes; the
            traversal compacts the live ones), so one decision per kind covers the render. What no
            rule or kept decision settles is timed in a pre-pass on this scene's rays
            (`_prepass`). True when every kind goes per_ray: the render is then one megakernel, the
            same kernel `per_ray` runs."""
            tracer = state.tracer
            policy, treelets = tracer.bvh.auto, tracer.bvh.stats.treelets
            k = min(width, self.batch_rays)  # what one traced batch holds
            reason = self.estimator.auto_rule(state.features)
            if reason is not None:
                for any_hit, hint in self.estimator.kinds(state.features):
                    policy.choices.setdefault(layerbvh.choice_key(any_hit, hint, k),
                                              {"mode": "per_ray", "reason": reason, "seconds": None, "sample_rays": 0})
                return True

            def modes():
                return [policy.settle(any_hit, hint, k, treelets)
                        for any_hit, hint in self.estimator.kinds(state.features)]
            if None in modes():
                self._prepass(state, k, prepass)
            return all(mode == "per_ray" for mode in modes())

        def _prepass(self, state: SceneState, k: int, prepass) -> None:
            """Time auto's open decisions on rays of this scene, before the render: `prepass(sampler,
            k, tracing)` runs the estimator's pre-pass on one batch of `k` rays (as the render traces
            them; a sampling estimator's on the pass's first camera rays), doing what reaches every
            kind of batch it traces (a path vertex, say) with a sampler of its own (PREPASS_SEED),
            so each kind reaches the traversal with mode auto, which times it on this batch
            (AutoPolicy.decide). The render's sampler is not touched: the image is the same with or
            without a pre-pass. Its wall time less kernel compilation is calibration."""
            tracer = state.tracer
            policy_s = tracer.bvh.auto.calibration_s
            t0 = time.perf_counter()
            with CompileClock() as clock:
                sampler = mi.load_dict({"type": "independent"})
                sampler.seed(self.PREPASS_SEED, k)
                prepass(sampler, k, Tracing(state.tracer, state.features, megakernel=False))
            state.prepass_s += (time.perf_counter() - t0 - clock.seconds
                                - (tracer.bvh.auto.calibration_s - policy_s))

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

        def _begin(self, state: SceneState, width: int, prepass) -> dict:
            """A render of `width` lanes starts: auto decides first (`prepass`: see _prepass)."""
            start = {"calibration_s": self.calibration_s()}
            if self.traversal.auto:
                self._auto_per_ray = self._plan_auto(state, width, prepass)
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

        # -- one render ---------------------------------------------------------------------------
        def _render(self, scene, width: int, prepass, run):
            """One render of `width` lanes, bracketed for statistics: auto decides (`prepass`: see
            _prepass), the loop mode is chosen, `run(tracing)` samples, `last_stats` is kept.
            Returns what `run` returns."""
            state = self.scene_state(scene)
            start = self._begin(state, width, prepass)
            megakernel = self.megakernel()
            tracing = Tracing(self._queries(scene, state.tracer, megakernel), state.features, megakernel)
            out = run(tracing)
            self._vertices = tracing.iterations
            self._finish(state, start, megakernel)
            return out

        def _camera_prepass(self, scene, ray):
            """auto's pre-pass of an estimator that starts at camera rays: on the pass's first k of `ray`."""
            def prepass(sampler, k, tracing):
                idx = dr.arange(mi.UInt32, k)
                take = (lambda x: x if dr.width(x) <= 1 else dr.gather(type(x), x, idx))
                cam = mi.Ray3f(take(ray.o), take(ray.d), take(ray.maxt), take(ray.time), take(ray.wavelengths))
                self.estimator.prepass(scene, sampler, cam, tracing)
            return prepass

        @instances_held()
        def sample(self, scene, sampler, ray, medium=None, active=True):
            """A sampling estimator's render: every lane's camera ray `ray` (Mitsuba's SamplingIntegrator)."""
            def run(tracing):
                lanes = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray.o))
                return self.estimator.sample(scene, sampler, mi.Ray3f(ray), medium, lanes, tracing)
            L, valid = self._render(scene, dr.width(ray.o), self._camera_prepass(scene, ray), run)
            return L, valid, []

        @instances_held()
        def sample_differentiable(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
            """A differentiable estimator's pass (Mitsuba's RBIntegrator: registry.integrator_class
            makes this the class's `sample`): every lane's camera ray `ray` in AD `mode` (primal;
            forward or backward, replaying the primal pass's paths from its radiance `state_in`).
            Returns (L or δL, valid, aovs, L), as ADIntegrator.sample does."""
            def run(tracing):
                lanes = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray.o))
                return self.estimator.sample(mode, scene, sampler, mi.Ray3f(ray), δL, state_in, lanes, tracing)
            return self._render(scene, dr.width(ray.o), self._camera_prepass(scene, ray), run)

        @instances_held()
        def sample_adjoint(self, scene, sensor, sampler, block, sample_scale):
            """An adjoint estimator's render pass (Mitsuba's AdjointIntegrator: registry.integrator_class
            makes this the class's `sample`): every lane of `sampler` splats into `block`."""
            self._render(scene, sampler.wavefront_size(),
                         lambda sampler, k, tracing: self.estimator.prepass(scene, sensor, sampler, tracing),
                         lambda tracing: self.estimator.sample(scene, sensor, sampler, block, sample_scale, tracing))

        # A differentiable render (Mitsuba's RBIntegrator, registry.integrator_class) calls `sample`
        # twice, primal then replaying, and records both into one kernel with the splatting around
        # them: the collector stays paused across the whole of it (held_instances), not only inside
        # each `sample`. Measured: prb's gradient test after two other renders in one process
        # aborted ("Fatal Python error: Aborted") with the pause on `sample` alone.
        # (These are Mitsuba's Python methods, so wrapping them nests no SIGINT handler.)
        def render_differentiable(self, *args, **kwargs):
            with instances_held():
                return super().render(*args, **kwargs)

        def render_forward_held(self, *args, **kwargs):
            with instances_held():
                return super().render_forward(*args, **kwargs)

        def render_backward_held(self, *args, **kwargs):
            with instances_held():
                return super().render_backward(*args, **kwargs)

        def _queries(self, scene, tracer: SceneTracer | None, megakernel: bool) -> RayQueries:
            """Who answers this render's queries: Embree (the control), our traversal inline (the
            megakernel) or between kernels, and, when recording, a recorder in front."""
            if self.traversal.control:
                queries = EmbreeQueries(scene)
            else:
                queries = InlineQueries(tracer) if megakernel else tracer
            return queries if self._recorder is None else RecordingQueries(queries, self._recorder)

        def aov_names(self):
            return []

        def to_string(self):
            return (f"{type(self).__name__}[{self.estimator.describe()}, traversal={self.traversal}, "
                    f"branching={self.branching}, treelet_height={self.treelet_height}]")

    return LayerBVHIntegrator
