"""auto: the timing policy that picks per_ray or layer_sorted for each kind of ray batch."""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from .wavefront import trace as _trace

# auto: below this many rays a batch goes per_ray without asking (a few rays per treelet cannot
# repay a sort and a launch per step); above it the first batch of each size class is timed both
# ways on a whole batch (up to batch_rays of its rays: sorting pays off with the number of rays
# per treelet, so a smaller sample would favour per_ray) and the faster mode is kept.
AUTO_MIN_RAYS = 1 << 16
AUTO_WARMUP_RAYS = 4096  # compiles both modes' kernels before anything is timed
AUTO_ROUNDS = 3  # timed rounds, alternating which mode goes first; the median decides
AUTO_MARGIN = 0.05  # layer_sorted must be this much faster: it also needs far more memory


def auto_mode(bvh, oj, dj, tm, valid, n, any_hit, hint) -> str:
    """The faster of per_ray and layer_sorted for this kind of batch, measured once per
    (closest/any hit, caller's hint such as 'camera', size class = bit length of the ray count).

    Timing both on real rays captures what a rule cannot: scene size against the caches,
    ray coherence, CPU or GPU. Hits do not depend on the choice (every mode is exact and
    breaks ties by primitive id), only the time does."""
    k = min(n, bvh.batch_rays)  # what one traced batch holds
    if bvh.device is None or k < AUTO_MIN_RAYS or bvh.stats.treelets <= 1:
        return "per_ray"
    key = ("any_hit" if any_hit else "closest_hit", hint, k.bit_length())
    known = bvh.auto_choices.get(key)
    if known is not None:
        return known["mode"]

    def leading(count):  # the first rays: neighbours, as in the batch itself
        idx = dr.arange(bvh.m.UInt32, count)
        take = (lambda x: dr.gather(type(x), x, idx))
        return [take(c) for c in oj], [take(c) for c in dj], take(tm), take(valid)

    def timed(sample, mode):
        dr.sync_thread()
        t0 = time.perf_counter()
        res, _ = _trace(bvh.m, bvh.device, *sample, mode, any_hit, bvh.tail_rays, count_work=False)
        dr.eval(res.t, res.tri)
        dr.sync_thread()
        return time.perf_counter() - t0

    warm, batch = leading(min(k, AUTO_WARMUP_RAYS)), leading(k)
    for mode in ("per_ray", "layer_sorted"):  # compiles the kernels; not counted
        timed(warm, mode)
    runs = {"per_ray": [], "layer_sorted": []}
    for rep in range(AUTO_ROUNDS):  # alternate the order so drifts hit both alike
        for mode in (("per_ray", "layer_sorted") if rep % 2 == 0 else ("layer_sorted", "per_ray")):
            runs[mode].append(timed(batch, mode))
    seconds = {mode: float(np.median(t)) for mode, t in runs.items()}
    choice = "layer_sorted" if seconds["layer_sorted"] < (1 - AUTO_MARGIN) * seconds["per_ray"] else "per_ray"
    bvh.auto_choices[key] = {"mode": choice, "seconds": seconds, "sample_rays": k}
    return choice
