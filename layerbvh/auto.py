"""auto: the timing policy that picks per_ray or layer_sorted for each kind of ray batch."""
from __future__ import annotations

import time
from typing import Callable

import drjit as dr
import numpy as np

from .inputs import RayBatch

AUTO = "auto"
AUTO_WARMUP_RAYS = 4096  # compiles both modes' kernels before anything is timed
AUTO_ROUNDS = 3  # timed rounds, alternating which mode goes first; the median decides
KEPT = "kept from an earlier run: "  # how a loaded decision's reason begins
AUTO_MARGIN = 0.05  # layer_sorted must be this much faster: it also needs far more memory
# What is decided without timing, per backend. On the CPU (BENCHMARKS.md: 2-core Zen 3, AVX2)
# sorting lost on every camera and shadow ray set (0.59-0.84x per_ray) and on every set below
# 500k rays (0.62-0.80x), and won or tied only on incoherent batches of 0.85-1M rays (up to
# 1.11x); a few rays per treelet cannot repay a sort and a launch per step. Timed again with the
# tail after one sorted step (scripts/bench_auto_rules.py, docs/bench/auto_rules.json, PERFORMANCE.md
# entry 64, AMD EPYC AVX2): camera rays still lose at every size (0.72-0.79x), shadow rays too
# (0.76-0.87x, entry 61); incoherent rays win from 2^17 rays over 600k triangles (1.07-1.16x) but
# on the bunny (69k) only tie from 2^19 (0.88-0.93x below it). The threshold stays 2^19: below it
# the gain is scene-dependent and small, and timing would compile and run the sorted kernels in
# every small render. Nothing has been measured on a GPU yet, so there every kind from 2^16 rays is timed.
RULES = {
    "llvm": {"min_rays": 1 << 19, "per_ray_hints": ("camera", "shadow")},
    "cuda": {"min_rays": 1 << 16, "per_ray_hints": ()},
}


def choice_key(any_hit: bool, hint: str, rays: int) -> str:
    """The kind of batch a decision holds for: query, hint, size class (bit length of the count)."""
    return f"{'any_hit' if any_hit else 'closest_hit'}/{hint}/{int(rays).bit_length()}"


class AutoPolicy:
    """The faster of per_ray and layer_sorted, decided once per kind of batch (`choice_key`).

    Kinds covered by the backend's RULES go per_ray without timing. Any other kind is timed on
    its first batch (up to batch_rays of its rays: sorting pays off with the rays per treelet,
    so a smaller sample would favour per_ray), both modes AUTO_ROUNDS times in alternating
    order, and layer_sorted is kept only if its median time is AUTO_MARGIN below per_ray's.
    Timing real rays captures what a rule cannot: scene size against the caches, ray coherence,
    CPU or GPU. Hits never depend on the choice (every mode is exact and breaks ties by
    primitive id), only the time does.

    `choices` maps each kind to {"mode", "reason", "seconds" (per mode, when timed),
    "sample_rays"}; `calibration_s` is the time spent timing. `load` takes decisions kept
    from an earlier run (the caller persists `choices`; the engine writes no files)."""

    def __init__(self, backend: str = "llvm", min_rays: int | None = None, per_ray_hints=None):
        rules = RULES[backend]
        self.min_rays = rules["min_rays"] if min_rays is None else int(min_rays)
        self.per_ray_hints = tuple(rules["per_ray_hints"] if per_ray_hints is None else per_ray_hints)
        self.choices: dict[str, dict] = {}
        self.calibration_s = 0.0

    def load(self, choices: dict) -> None:
        """Adopt timed decisions from an earlier run (same scene, BVH, device: the caller's key).
        Their reason says so once, however often the decision was kept, saved and loaded again."""
        for key, c in choices.items():
            if c.get("mode") in ("per_ray", "layer_sorted"):
                timed = c.get("reason", "")
                while timed.startswith(KEPT):  # files kept before this fix may carry it many times
                    timed = timed[len(KEPT):]
                self.choices.setdefault(key, {**c, "reason": KEPT + timed})

    def rule(self, any_hit: bool, hint: str, rays: int, treelets: int) -> dict | None:
        """The untimed decision for this kind of batch, or None when it must be timed."""
        if treelets <= 1:
            return {"mode": "per_ray", "reason": "the BVH is one treelet: nothing to sort"}
        if hint in self.per_ray_hints:
            return {"mode": "per_ray", "reason": f"{hint} rays: sorting never won on this backend's benchmark"}
        if rays < self.min_rays:
            return {"mode": "per_ray", "reason": f"{rays:,} rays per batch, below the {self.min_rays:,} where "
                                                 f"sorting can pay off on this backend"}
        return None

    def known(self, any_hit: bool, hint: str, rays: int, treelets: int) -> str | None:
        """The mode for this kind of batch if it is decided without tracing (a rule or an
        earlier decision), else None."""
        rule = self.rule(any_hit, hint, rays, treelets)
        if rule is not None:
            return rule["mode"]
        c = self.choices.get(choice_key(any_hit, hint, rays))
        return c["mode"] if c else None

    def settle(self, any_hit: bool, hint: str, rays: int, treelets: int) -> str | None:
        """As `known`, and a rule's decision is recorded in `choices` (with its reason)."""
        key = choice_key(any_hit, hint, rays)
        rule = self.rule(any_hit, hint, rays, treelets)
        if rule is not None and key not in self.choices:
            self.choices[key] = {**rule, "seconds": None, "sample_rays": 0}
        return self.known(any_hit, hint, rays, treelets)

    def decide(self, trace: Callable[[RayBatch, str], object], batch: RayBatch, batch_rays: int, any_hit: bool,
               hint: str, treelets: int) -> str:
        """The mode for `batch`; `trace(sample, mode)` traces a sub-batch (its results evaluated)."""
        k = min(batch.n, batch_rays)  # what one traced batch holds
        key = choice_key(any_hit, hint, k)
        known = self.choices.get(key)
        if known is not None:
            return known["mode"]
        rule = self.rule(any_hit, hint, k, treelets)
        if rule is not None:
            self.choices[key] = {**rule, "seconds": None, "sample_rays": 0}
            return rule["mode"]

        def leading(count):  # the first rays: neighbours, as in the batch itself
            return batch.take(dr.arange(dr.uint32_array_t(type(batch.tmax)), count))

        def timed(sample, mode):
            dr.sync_thread()
            t0 = time.perf_counter()
            trace(sample, mode)
            dr.sync_thread()
            return time.perf_counter() - t0

        warm, sample = leading(min(k, AUTO_WARMUP_RAYS)), leading(k)
        for mode in ("per_ray", "layer_sorted"):  # compiles the kernels; not counted
            timed(warm, mode)
        # The timing starts after the warm-up: compiling is not calibration (callers report
        # compile time apart, and would otherwise count it twice).
        t_start = time.perf_counter()
        runs = {"per_ray": [], "layer_sorted": []}
        for rep in range(AUTO_ROUNDS):  # alternate the order so drifts hit both alike
            for mode in (("per_ray", "layer_sorted") if rep % 2 == 0 else ("layer_sorted", "per_ray")):
                runs[mode].append(timed(sample, mode))
        seconds = {mode: float(np.median(t)) for mode, t in runs.items()}
        faster = seconds["layer_sorted"] < (1 - AUTO_MARGIN) * seconds["per_ray"]
        choice = "layer_sorted" if faster else "per_ray"
        self.choices[key] = {"mode": choice, "seconds": seconds, "sample_rays": k,
                             "reason": f"timed: layer_sorted {seconds['layer_sorted']:.3g} s, per_ray "
                                       f"{seconds['per_ray']:.3g} s on {k:,} rays"}
        self.calibration_s += time.perf_counter() - t_start
        return choice
