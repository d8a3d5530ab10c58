"""The two-step verdict of an A/B comparison: same seed within tolerance (same paths), else an independent-seed per-pixel test on a downsampled film (agrees within Monte Carlo noise, or differs beyond it)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.render import load_integrator, load_scene
from layerbvh_mitsuba.runtime.scene_geometry import sensor_medium
from layerbvh_mitsuba.runtime.stats import RenderStats

# Seeds of the statistical step's two renders: apart, so stock's and ours' samples are independent.
STOCK_SEED, OURS_SEED = 1000, 5000
# Where a pixel's samples cannot be read one by one, its moments come from this many independent
# renders, each a sample of the pixel's mean: an adjoint integrator (ptracer) splats its light
# paths anywhere on the film, and a gradient image (ab/gradient.py) is only what a render returns.
MOMENT_RENDERS = 16


@dataclass
class StatisticalStep:
    """What step 2 ran and found."""

    resolution: tuple[int, int]  # its film (W, H)
    spp: int                     # samples per pixel, one render per side
    pass_fraction: float
    pixels: int
    min_p: float
    threshold: float             # per-pixel p-value threshold (Šidák)
    seconds: float
    passing: np.ndarray = field(repr=False)  # (H, W) bool
    ours_stats: RenderStats | None = field(default=None, repr=False)  # ours' integrator's last_stats

    @property
    def failing_pixels(self) -> int:
        return int(self.pixels - round(self.pass_fraction * self.pixels))

    def as_dict(self) -> dict:
        return {"resolution": list(self.resolution), "spp": self.spp, "pass_fraction": self.pass_fraction,
                "failing_pixels": self.failing_pixels, "pixels": self.pixels, "min_p": self.min_p,
                "threshold": self.threshold, "alpha": metrics.Z_ALPHA, "max_fail_frac": metrics.Z_MAX_FAIL_FRAC,
                "seconds": self.seconds,
                "test": "per-pixel Welch t-test of equal means (per-sample variances), Šidák-corrected over the pixels"}


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
                f"({w}x{h}, {z.spp} spp per side, {z.seconds:.1f} s)")

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
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    p = mi.traverse(scene)
    modify(p)
    p.update()
    return scene


def pixel_moments(mi, scene, integrator, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-pixel mean, the variance of one sample, and the samples per pixel: for an adjoint
    integrator from MOMENT_RENDERS renders of spp / MOMENT_RENDERS each (`_render_moments`),
    else of `integrator`'s estimate over `spp` samples per pixel,
    from one call of its `sample` on all of them: camera rays through uniform positions
    in each pixel (a box filter) from the scene's first sensor, with an independent sampler
    seeded `seed`. One render instead of repeated ones: the variance comes from the samples, and
    the layer modes' per-render kernel launches are paid once, not once per repeat. Both sides
    go through this same estimator, so it compares the integrators, not two films."""
    if isinstance(integrator, mi.AdjointIntegrator) or _stokes(integrator):
        return _render_moments(mi, scene, integrator, spp, seed)
    differentiable = isinstance(integrator, mi.CppADIntegrator)  # (prb and its kin: `sample` takes an AD mode first)
    sensor = scene.sensors()[0]
    w, h = (int(x) for x in sensor.film().crop_size())
    n = w * h * spp
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    pixel = dr.arange(mi.UInt32, n) // spp
    pos = mi.Vector2f(mi.Float(pixel % w), mi.Float(pixel // w)) + sampler.next_2d()
    ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), pos / mi.Vector2f(w, h), sampler.next_2d())
    if differentiable:
        with dr.suspend_grad():
            L = integrator.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, mi.Bool(True))[0]
    else:
        L, _, _ = integrator.sample(scene, sampler, ray, sensor_medium(sensor), True)  # (volpath: a camera in a medium)
    value = weight * L
    dr.eval(value)
    v = np.stack([np.asarray(value[c], np.float64) for c in range(3)], -1).reshape(h, w, spp, 3)
    return v.mean(2), v.var(2, ddof=1), spp


def _stokes(integrator) -> bool:
    """Mitsuba's stokes wrapper: its `sample` needs the sensor that only its `render` sets, and
    its result is judged on all five RGB panels (metrics.stokes_panels)."""
    return integrator.class_name() == "StokesIntegrator"


def _render_moments(mi, scene, integrator, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-pixel mean and variance over MOMENT_RENDERS independent renders (seeds `seed` x
    MOMENT_RENDERS + r) of spp / MOMENT_RENDERS samples per pixel each; each render's pixel is
    one sample of its mean. RGB; a stokes render's five panels side by side."""
    per = max(1, spp // MOMENT_RENDERS)
    judged = metrics.stokes_panels if _stokes(integrator) else (lambda img: img[..., :3])
    v = np.stack([judged(np.array(mi.render(scene, integrator=integrator, spp=per, seed=seed * MOMENT_RENDERS + r),
                                  np.float64)) for r in range(MOMENT_RENDERS)])
    return v.mean(0), v.var(0, ddof=1), MOMENT_RENDERS


def independent_seed_test(mi, scene_path, res: tuple[int, int], spp: int, stock: dict, ours: dict,
                          params: dict | None = None, ours_modify=None, wrap=None) -> StatisticalStep:
    """Stock's estimator and ours (integrator dicts: `path` and `layerbvh`, or `direct` and
    `layerbvh_direct`) at independent seeds (STOCK_SEED, OURS_SEED) on the scene at film
    `res`, `spp` camera samples per pixel a side (`pixel_moments`), then metrics.pixel_test
    (Welch, Šidák-corrected at metrics.Z_ALPHA). `ours_modify(params)` changes ours' copy of the
    scene (negative controls). `wrap(integrator)`: the scene's wrapper around each side where it
    changes what is judged (stokes: scene_integrator.PathSettings.integrator)."""
    t0 = time.perf_counter()
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    ours_scene = scene if ours_modify is None else load_modified(mi, scene_path, res, params, ours_modify)
    stock = load_integrator(mi, stock)
    ours = load_integrator(mi, ours)
    wrapped = (lambda integ: integ) if wrap is None else (lambda integ: load_integrator(mi, wrap(integ)))
    ref_mean, ref_var, n_ref = pixel_moments(mi, scene, wrapped(stock), spp, STOCK_SEED)
    mean, var, n = pixel_moments(mi, ours_scene, wrapped(ours), spp, OURS_SEED)
    summary, passing = metrics.pixel_test(ref_mean, ref_var, mean, var, n_ref, n, alpha=metrics.Z_ALPHA, student=True)
    return StatisticalStep(resolution=tuple(res), spp=spp, pass_fraction=summary["pass_fraction"],
                           pixels=summary["pixels"], min_p=summary["min_p"], threshold=summary["threshold"],
                           seconds=time.perf_counter() - t0, passing=passing, ours_stats=ours.last_stats)


def statistical_step(mi, scene_path, size: tuple[int, int], samples: int, stock: dict, ours: dict,
                     params: dict | None = None, ours_modify=None, wrap=None) -> StatisticalStep:
    """Step 2: `independent_seed_test` on the scene's film shrunk to metrics.z_test_film(size),
    about Z_SAMPLE_SHARE x `samples` camera samples per side (metrics.z_test_spp)."""
    return independent_seed_test(mi, scene_path, metrics.z_test_film(*size), metrics.z_test_spp(*size, samples),
                                 stock, ours, params, ours_modify, wrap)


def judge(mi, scene_path, stock_img: np.ndarray, ours_img: np.ndarray, spp: int, stock: dict,
          ours: dict, params: dict | None = None, ours_modify=None, film: tuple[int, int] | None = None,
          wrap=None) -> Verdict:
    """Both steps for same-seed images of `scene_path` (film of their size, or `film` (W, H)
    where the images are panels of it, `spp` spp): step 2 runs only where step 1 fails, at about
    the same number of samples per side (`wrap`: independent_seed_test)."""
    s = metrics.same_seed_verdict(stock_img, ours_img)
    if s["passed"]:
        return Verdict(metrics.SAME_PATHS, s)
    w, h = film or stock_img.shape[1::-1]
    z = statistical_step(mi, scene_path, (w, h), w * h * spp, stock, ours, params, ours_modify, wrap)
    return Verdict(metrics.verdict_label(False, z.pass_fraction), s, z)
