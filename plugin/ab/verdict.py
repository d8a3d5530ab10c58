"""The verdict of an A/B comparison: the same-seed criterion (same paths), the paired same-seed tests and, where
paths diverged, the independent-seed renders and tests (hypotheses.py), judged as one family (agrees within Monte
Carlo noise, or differs beyond it)."""
from __future__ import annotations

import time
from pathlib import Path
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from layerbvh_mitsuba.ab import hypotheses, metrics
from layerbvh_mitsuba.ab.hypotheses import Moments
from layerbvh_mitsuba.ab.render import load_integrator, load_scene
from layerbvh_mitsuba.runtime.scene_geometry import sensor_medium
from layerbvh_mitsuba.runtime.stats import RenderStats

# Seeds of the statistical step's two renders at compare seed 0: apart, so stock's and ours'
# samples are independent; compare seed s moves both by SEED_STRIDE x s (mod 2^32, `independent_seeds`),
# so the verdicts of different compare seeds are independent too (scripts/verdict_power.py).
STOCK_SEED, OURS_SEED = 1000, 5000
SEED_STRIDE = 10_000
# Where a pixel's samples cannot be read one by one, its moments come from this many independent
# renders, each a sample of the pixel's mean: an adjoint integrator (ptracer) splats its light
# paths anywhere on the film, and a gradient image (ab/gradient.py) is only what a render returns.
MOMENT_RENDERS = 16


@dataclass
class StatisticalStep:
    """What the independent-seed renders ran and found: their tests (hypotheses.independent)."""

    resolution: tuple[int, int]  # its film (W, H), per panel
    spp: int                     # samples per pixel, one render per side
    tests: list = field(repr=False)  # [hypotheses.Tests] at each level
    seconds: float
    panels: tuple[str, ...] = ("",)
    ours_stats: RenderStats | None = field(default=None, repr=False)  # ours' integrator's last_stats

    @property
    def family(self) -> hypotheses.Family:
        """These tests alone under the verdict's correction (where no paired test joins them)."""
        return hypotheses.Family(self.tests, self.panels)

    @property
    def passed(self) -> bool:
        return not self.family.rejected

    @property
    def pixels(self) -> int:
        return self.resolution[0] * self.resolution[1] * len(self.panels)

    @property
    def failing_pixels(self) -> int:
        return self.family.failing_pixels()

    def as_dict(self, family: hypotheses.Family | None = None) -> dict:
        f = family or self.family
        return {"resolution": list(self.resolution), "spp": self.spp, "pixels": self.pixels,
                "failing_pixels": f.failing_pixels(), "panels": list(self.panels), "seconds": self.seconds,
                "test": "Welch test of equal means per pixel, per tile and over the image (per-sample variances; "
                        "over repeated renders where the samples are renders)"}


@dataclass
class Verdict:
    """The verdict of one comparison (report.json's "verdict" is `as_dict`): step 1's same-seed
    criterion and the family of tests (hypotheses.Family) that decides where it fails and states
    the power (MDE) of every verdict."""

    label: str                         # metrics.SAME_PATHS | AGREES | DIFFERS | SAME_SEED_DIFFERS
    same_seed: dict                    # metrics.same_seed_verdict
    statistical: StatisticalStep | None = None
    family: hypotheses.Family | None = None

    @property
    def passed(self) -> bool:
        return metrics.verdict_passed(self.label)

    def mde(self) -> dict | None:
        """hypotheses.Family.power: the relative bias caught with 95% probability (None: no family ran)."""
        return None if self.family is None else self.family.power()

    def summary(self) -> str:
        v = self.same_seed["values"]
        within = f"{100 * v['frac_within']:.2f}% of pixels within {metrics.SAME_SEED_TOL:g}"
        # (No test in the family: an adjoint integrator's same paths, judged by step 1 alone.)
        tail = "" if self.family is None or not self.family.tests else f"; {self.family.summary()}"
        if self.same_seed["passed"]:
            return f"same seed: {within}, mean |diff| {v['mean_abs']:.3g} (mean pixel {v['mean_ref']:.3g}){tail}"
        diverged = f"same-seed paths diverged: {within}"
        z = self.statistical
        if z is not None:
            w, h = z.resolution
            tail += f" (independent seeds: {w}x{h}, {z.spp} spp per side, {z.seconds:.1f} s)"
        elif self.family is not None and self.family.planned and self.family.rejected:
            tail += " (the paired tests decided: no independent-seed renders were needed)"
        return diverged + tail

    def as_dict(self) -> dict:
        v = self.same_seed
        return {"label": self.label, "passed": self.passed, "summary": self.summary(),
                "mde": self.mde(),
                "criterion": (f"1. {v['criterion']}; 2. otherwise no test of the family rejects equal means "
                              f"(paired same-seed and independent-seed tests of the image, its tiles and pixels, "
                              f"equivalence margin {hypotheses.MARGIN:g} of |stock|, family-wise alpha "
                              f"{hypotheses.ALPHA:g}, weighted Bonferroni)"),
                "same_seed": {"passed": v["passed"], **v["values"]}, "values": v["values"],
                "hypotheses": None if self.family is None else self.family.as_dict(),
                "statistical": None if self.statistical is None else self.statistical.as_dict(self.family)}


def same_seed_only(stock: np.ndarray, ours: np.ndarray) -> Verdict:
    """Step 1 alone (no scene at hand to render step 2 from)."""
    s = metrics.same_seed_verdict(stock, ours)
    return Verdict(metrics.verdict_label(s["passed"], None), s)


def independent_seeds(seed: int) -> tuple[int, int]:
    """(stock, ours) seeds of the independent-seed renders of a compare at `seed`, each with room
    for MOMENT_RENDERS consecutive render seeds below 2^32."""
    room = (1 << 32) // MOMENT_RENDERS
    return tuple((base + SEED_STRIDE * int(seed)) % room for base in (STOCK_SEED, OURS_SEED))


def load_modified(mi, scene_path, res, params: dict | None, modify):
    """A fresh copy of the scene at film `res` with `modify(mi.traverse(copy))` applied: what a
    negative control renders on ours' side."""
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    p = mi.traverse(scene)
    modify(p)
    p.update()
    return scene


def pixel_moments(mi, scene, integrator, spp: int, seed: int) -> Moments:
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
    return Moments(v.mean(2), v.var(2, ddof=1), spp)


def _stokes(integrator) -> bool:
    """Mitsuba's stokes wrapper: its `sample` needs the sensor that only its `render` sets, and
    its result is judged on all five RGB panels (metrics.stokes_panels)."""
    return integrator.class_name() == "StokesIntegrator"


def _render_moments(mi, scene, integrator, spp: int, seed: int) -> Moments:
    """Per-pixel mean and variance over MOMENT_RENDERS independent renders (seeds `seed` x
    MOMENT_RENDERS + r) of spp / MOMENT_RENDERS samples per pixel each; each render's pixel is
    one sample of its mean. RGB; a stokes render's five panels side by side."""
    per = max(1, spp // MOMENT_RENDERS)
    judged = metrics.stokes_panels if _stokes(integrator) else (lambda img: img[..., :3])
    v = np.stack([judged(np.array(mi.render(scene, integrator=integrator, spp=per, seed=seed * MOMENT_RENDERS + r),
                                  np.float64)) for r in range(MOMENT_RENDERS)])
    return Moments(v.mean(0), v.var(0, ddof=1), MOMENT_RENDERS, renders=v)


def independent_seed_test(mi, scene_path, res: tuple[int, int], spp: int, stock: dict, ours: dict,
                          params: dict | None = None, ours_modify=None, wrap=None, seed: int = 0) -> StatisticalStep:
    """Stock's estimator and ours (integrator dicts: `path` and `layerbvh`, or `direct` and
    `layerbvh_direct`) at independent seeds (`independent_seeds(seed)`) on the scene at film `res`,
    `spp` camera samples per pixel a side (`pixel_moments`), and their tests of equal means over the
    image, its tiles and its pixels (hypotheses.independent). `ours_modify(params)` changes ours'
    copy of the scene (negative controls). `wrap(integrator)`: the scene's wrapper around each side
    where it changes what is judged (stokes: scene_integrator.PathSettings.integrator)."""
    t0 = time.perf_counter()
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    ours_scene = scene if ours_modify is None else load_modified(mi, scene_path, res, params, ours_modify)
    stock = load_integrator(mi, stock)
    ours = load_integrator(mi, ours)
    wrapped = (lambda integ: integ) if wrap is None else (lambda integ: load_integrator(mi, wrap(integ)))
    stock_int, ours_int = wrapped(stock), wrapped(ours)
    stock_seed, ours_seed = independent_seeds(seed)
    key = (str(scene_path), Path(scene_path).stat().st_mtime_ns, tuple(res), spp, stock_seed,
           repr(sorted((params or {}).items())), repr(stock), None if wrap is None else repr(wrap(stock)))
    a = _STOCK_MOMENTS.get(key)
    if a is None:
        a = _STOCK_MOMENTS[key] = pixel_moments(mi, scene, stock_int, spp, stock_seed)
        while len(_STOCK_MOMENTS) > _STOCK_MOMENTS_KEPT:
            _STOCK_MOMENTS.pop(next(iter(_STOCK_MOMENTS)))
    b = pixel_moments(mi, ours_scene, ours_int, spp, ours_seed)
    panels = metrics.STOKES_PANELS if _stokes(stock_int) else ("",)
    tests = hypotheses.independent(a, b, hypotheses.TILE, len(panels))
    return StatisticalStep(resolution=tuple(res), spp=spp, tests=tests, seconds=time.perf_counter() - t0, panels=panels,
                           ours_stats=ours.last_stats)


# Stock's independent-seed moments by (scene file, film, spp, seed, $parameters, integrator):
# a negative control or a power study judges many of ours' variants against the same stock
# side in one process. Stock's scene is never modified, so its moments are the same each time.
_STOCK_MOMENTS: dict = {}
_STOCK_MOMENTS_KEPT = 8


def statistical_step(mi, scene_path, size: tuple[int, int], samples: int, stock: dict, ours: dict,
                     params: dict | None = None, ours_modify=None, wrap=None, seed: int = 0) -> StatisticalStep:
    """Step 2: `independent_seed_test` on the scene's film shrunk to metrics.z_test_film(size),
    about Z_SAMPLE_SHARE x `samples` camera samples per side (metrics.z_test_spp)."""
    return independent_seed_test(mi, scene_path, metrics.z_test_film(*size), metrics.z_test_spp(*size, samples),
                                 stock, ours, params, ours_modify, wrap, seed)


def judge(mi, scene_path, stock_img: np.ndarray, ours_img: np.ndarray, spp: int, stock: dict,
          ours: dict, params: dict | None = None, ours_modify=None, film: tuple[int, int] | None = None,
          wrap=None, reach: int | None = None, seed: int = 0) -> Verdict:
    """The verdict on same-seed images of `scene_path` (film of their size, or `film` (W, H)
    where the images are panels of it, `spp` spp). Step 1, the same-seed criterion; the paired
    tests on these images (hypotheses.paired, `reach`: the film filter's, hypotheses.reach; None
    or an adjoint integrator: not run) give every verdict its power. Where step 1 fails, the
    independent-seed renders (`statistical_step`, at about the compare's samples per side;
    `wrap`: independent_seed_test) join them in one family: "agrees" iff none rejects."""
    s = metrics.same_seed_verdict(stock_img, ours_img)
    w, h = film or stock_img.shape[1::-1]
    names = metrics.STOKES_PANELS if stock_img.shape[1] == len(metrics.STOKES_PANELS) * w else ("",)
    paired = []
    if reach is not None and not isinstance(load_integrator(mi, stock), mi.AdjointIntegrator):
        zw, _ = metrics.z_test_film(w, h)
        paired = hypotheses.paired(stock_img, ours_img, reach, max(1, round(hypotheses.TILE * w / zw)), len(names))
    if s["passed"]:
        family = hypotheses.Family(paired, names)
        return Verdict(metrics.verdict_label(True, family.rejected), s, family=family)
    # The family's thresholds are fixed per level by its size (Bonferroni), so a paired test that
    # rejects with the independent-seed tests counted in rejects whatever they find: "differs"
    # without their renders (the full family would say the same, at their cost).
    planned = hypotheses.independent_counts(metrics.z_test_film(w, h), len(names), stock_img.shape[-1])
    early = hypotheses.Family(paired, names, planned=planned)
    if early.rejected:
        return Verdict(metrics.verdict_label(False, True), s, family=early)
    z = statistical_step(mi, scene_path, (w, h), w * h * spp, stock, ours, params, ours_modify, wrap, seed)
    family = hypotheses.Family(paired + z.tests, names)
    return Verdict(metrics.verdict_label(False, family.rejected), s, z, family)
