"""auto: the timing policy that picks per_ray or layer_sorted for each kind of ray batch."""
from __future__ import annotations

import time
from typing import Callable

import drjit as dr
import numpy as np

from .inputs import RayBatch

AUTO = "auto"
# Below this many rays a batch goes per_ray without asking (a few rays per treelet cannot repay
# a sort and a launch per step); above it the first batch of each size class is timed both ways
# on a whole batch (up to batch_rays of its rays: sorting pays off with the number of rays per
# treelet, so a smaller sample would favour per_ray) and the faster mode is kept.
AUTO_MIN_RAYS = 1 << 16
AUTO_WARMUP_RAYS = 4096  # compiles both modes' kernels before anything is timed
AUTO_ROUNDS = 3  # timed rounds, alternating which mode goes first; the median decides
AUTO_MARGIN = 0.05  # layer_sorted must be this much faster: it also needs far more memory


class AutoPolicy:
    """The faster of per_ray and layer_sorted, measured once per kind of batch: (closest/any hit,
    the caller's hint such as 'camera', size class = bit length of the ray count).

    Timing both on real rays captures what a rule cannot: scene size against the caches, ray
    coherence, CPU or GPU. Hits do not depend on the choice (every mode is exact and breaks ties
    by primitive id), only the time does. `choices` maps each kind to its decision."""

    def __init__(self):
        self.choices = {}  # (query, hint, size class) -> {"mode", "seconds", "sample_rays"}

    def decide(self, trace: Callable[[RayBatch, str], object], batch: RayBatch, batch_rays: int, any_hit: bool,
               hint: str, treelets: int) -> str:
        """The mode for `batch`; `trace(sample, mode)` traces a sub-batch (its results evaluated)."""
        k = min(batch.n, batch_rays)  # what one traced batch holds
        if k < AUTO_MIN_RAYS or treelets <= 1:
            return "per_ray"
        key = ("any_hit" if any_hit else "closest_hit", hint, k.bit_length())
        known = self.choices.get(key)
        if known is not None:
            return known["mode"]

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
        runs = {"per_ray": [], "layer_sorted": []}
        for rep in range(AUTO_ROUNDS):  # alternate the order so drifts hit both alike
            for mode in (("per_ray", "layer_sorted") if rep % 2 == 0 else ("layer_sorted", "per_ray")):
                runs[mode].append(timed(sample, mode))
        seconds = {mode: float(np.median(t)) for mode, t in runs.items()}
        choice = "layer_sorted" if seconds["layer_sorted"] < (1 - AUTO_MARGIN) * seconds["per_ray"] else "per_ray"
        self.choices[key] = {"mode": choice, "seconds": seconds, "sample_rays": k}
        return choice
