"""The two-step verdict of an A/B comparison: same seed within tolerance (same paths), else an independent-seed per-pixel test on a downsampled film (agrees within Monte Carlo noise, or differs beyond it)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import metrics

# Seeds of the statistical step's repeats, apart for the two sides (stock's repeat k and ours'
# never share a seed; render.pass_seed keeps multi-pass repeats apart too, within 32 bits).
STOCK_SEED0, OURS_SEED0 = 1000, 5000


@dataclass
class StatisticalStep:
    """What step 2 ran and found."""

    resolution: tuple[int, int]  # its film (W, H)
    spp: int                     # per repeat
    repeats: int                 # per side
    pass_fraction: float
    pixels: int
    min_p: float
    threshold: float             # per-pixel p-value threshold (Šidák)
    seconds: float
    passing: np.ndarray = field(repr=False)  # (H, W) bool

    @property
    def failing_pixels(self) -> int:
        return int(self.pixels - round(self.pass_fraction * self.pixels))

    def as_dict(self) -> dict:
        return {"resolution": list(self.resolution), "spp": self.spp, "repeats": self.repeats,
                "pass_fraction": self.pass_fraction, "failing_pixels": self.failing_pixels, "pixels": self.pixels,
                "min_p": self.min_p, "threshold": self.threshold, "alpha": metrics.Z_ALPHA,
                "max_fail_frac": metrics.Z_MAX_FAIL_FRAC, "seconds": self.seconds,
                "test": "per-pixel Welch t-test of equal means, Šidák-corrected over the pixels"}


@dataclass
class Verdict:
    """The verdict of one comparison (report.json's "verdict" is `as_dict`)."""

    label: str                         # metrics.SAME_PATHS | AGREES | DIFFERS | SAME_SEED_DIFFERS
    same_seed: dict                    # metrics.same_seed_verdict
    statistical: StatisticalStep | None = None

    @property
    def passed(self) -> bool:
        return metrics.verdict_passed(self.label)

    def summary(self) -> str:
        v = self.same_seed["values"]
        within = f"{100 * v['frac_within']:.2f}% of pixels within {metrics.SAME_SEED_TOL:g}"
        if self.label == metrics.SAME_PATHS:
            return f"same seed: {within}, mean |diff| {v['mean_abs']:.3g} (mean pixel {v['mean_ref']:.3g})"
        diverged = f"same-seed paths diverged: {within}"
        z = self.statistical
        if z is None:
            return diverged
        w, h = z.resolution
        return (f"{diverged}; independent seeds: {z.failing_pixels} of {z.pixels} pixels differ beyond noise "
                f"({w}x{h}, {z.repeats} x {z.spp} spp per side, {z.seconds:.1f} s)")

    def as_dict(self) -> dict:
        v = self.same_seed
        return {"label": self.label, "passed": self.passed, "summary": self.summary(),
                "criterion": (f"1. {v['criterion']}; 2. otherwise independent seeds agree: at most "
                              f"{100 * metrics.Z_MAX_FAIL_FRAC:g}% of pixels fail a per-pixel Welch t-test at "
                              f"family-wise alpha {metrics.Z_ALPHA:g} (Šidák)"),
                "same_seed": {"passed": v["passed"], **v["values"]}, "values": v["values"],
                "statistical": None if self.statistical is None else self.statistical.as_dict()}


def same_seed_only(stock: np.ndarray, ours: np.ndarray) -> Verdict:
    """Step 1 alone (no scene at hand to render step 2 from)."""
    s = metrics.same_seed_verdict(stock, ours)
    return Verdict(metrics.verdict_label(s["passed"], None), s)


def load_modified(mi, scene_path, res, params: dict | None, modify):
    """A fresh copy of the scene at film `res` with `modify(mi.traverse(copy))` applied: what a
    negative control renders on ours' side."""
    from .render import load_scene
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    p = mi.traverse(scene)
    modify(p)
    p.update()
    return scene


def repeated_moments(mi, scene, integrator, spp: int, repeats: int, seed0: int):
    """Per-pixel mean and variance (of one repeat's mean) over `repeats` independent renders."""
    from .render import render_passes
    imgs = np.stack([render_passes(mi, scene, integrator, spp, seed0 + k, "", False)[0].astype(np.float64)
                     for k in range(repeats)])
    return imgs.mean(0), imgs.var(0, ddof=1)


def statistical_step(mi, scene_path, size: tuple[int, int], samples: int, stock_props: dict, ours_props: dict,
                     params: dict | None = None, ours_modify=None) -> StatisticalStep:
    """Step 2: stock `path` and layerbvh at independent seeds on the scene's film shrunk to
    metrics.z_test_film(size), about `samples` camera samples per side, then metrics.pixel_test
    (Welch). `ours_modify(params)` changes ours' copy of the scene (negative controls)."""
    from .render import load_integrator, load_scene
    t0 = time.perf_counter()
    res = metrics.z_test_film(*size)
    spp = metrics.z_test_spp(*size, samples)
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    ours_scene = scene if ours_modify is None else load_modified(mi, scene_path, res, params, ours_modify)
    stock = load_integrator(mi, {"type": "path", **stock_props})
    ours = load_integrator(mi, {"type": "layerbvh", **ours_props})
    r = metrics.Z_REPEATS
    ref_mean, ref_var = repeated_moments(mi, scene, stock, spp, r, STOCK_SEED0)
    mean, var = repeated_moments(mi, ours_scene, ours, spp, r, OURS_SEED0)
    summary, passing = metrics.pixel_test(ref_mean, ref_var, mean, var, r, r, alpha=metrics.Z_ALPHA, student=True)
    return StatisticalStep(resolution=res, spp=spp, repeats=r, pass_fraction=summary["pass_fraction"],
                           pixels=summary["pixels"], min_p=summary["min_p"], threshold=summary["threshold"],
                           seconds=time.perf_counter() - t0, passing=passing)


def judge(mi, scene_path, stock_img: np.ndarray, ours_img: np.ndarray, spp: int, stock_props: dict,
          ours_props: dict, params: dict | None = None, ours_modify=None) -> Verdict:
    """Both steps for same-seed images of `scene_path` (film of their size, `spp` spp): step 2
    runs only where step 1 fails, at about the same number of samples per side."""
    s = metrics.same_seed_verdict(stock_img, ours_img)
    if s["passed"]:
        return Verdict(metrics.SAME_PATHS, s)
    h, w = stock_img.shape[:2]
    z = statistical_step(mi, scene_path, (w, h), w * h * spp, stock_props, ours_props, params, ours_modify)
    return Verdict(metrics.verdict_label(False, z.pass_fraction), s, z)
