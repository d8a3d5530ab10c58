"""Reusable pytest helpers: check that the layerbvh integrator renders a scene (and, for prb and its kin, its
derivatives) like stock Mitsuba (same seed, and statistically), each an `ab.compare.compare` run."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from layerbvh_mitsuba.ab import hypotheses, metrics
from layerbvh_mitsuba.ab.compare import CompareSettings, Comparison, compare, ours_props as ours_props_of
from layerbvh_mitsuba.ab.metrics import SAME_SEED_MAX_MEAN_REL, SAME_SEED_MIN_FRAC, SAME_SEED_TOL, same_seed_verdict
from layerbvh_mitsuba.ab.render import load_scene, use_variant, write_exr
from layerbvh_mitsuba.ab.scene_integrator import path_settings
from layerbvh_mitsuba.ab.report import write_comparison
from layerbvh_mitsuba.ab.verdict import StatisticalStep, Verdict, independent_seed_test
from layerbvh_mitsuba.runtime.cache import cache_dir
from layerbvh_mitsuba.runtime.settings import Traversal
from layerbvh_mitsuba.runtime.stats import RenderStats

# Integrator properties that are fields of CompareSettings (the rest stay ours_props).
_SETTING_PROPS = ("treelet_height", "branching", "leaf_size")


def settings(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", ours_props=None, params=None,
             **kw) -> CompareSettings:
    """CompareSettings for the helpers' arguments: `ours_props` are layerbvh integrator properties
    (treelet_height, branching and leaf_size go to their fields), `params` the scene's
    $parameters, `kw` more CompareSettings fields."""
    props = dict(ours_props or {})
    fields = {k: props.pop(k) for k in _SETTING_PROPS if k in props}
    return CompareSettings(scene=Path(scene_path), spp=spp, res=tuple(res) if res is not None else None, seed=seed,
                           traversal=Traversal.parse(traversal), ours_props=props, params=dict(params or {}),
                           **fields, **kw)


@dataclass
class SameSeedResult:
    frac_within: float      # share of pixels within the same-seed tolerance in every channel
    mean_abs: float
    mean_ref: float
    max_abs: float
    stock: np.ndarray
    ours: np.ndarray
    ours_stats: RenderStats  # the layerbvh integrator's last_stats
    passed: bool = False     # the criterion held
    compared_as: str = ""    # what both sides rendered (PathSettings.compared_as: "path", "moment(volpath)", ...)

    def summary(self) -> str:
        return (f"{100 * self.frac_within:.3f}% of pixels within tolerance, mean |diff| {self.mean_abs:.3g} "
                f"(mean pixel {self.mean_ref:.3g}), max |diff| {self.max_abs:.3g}")


def scaled_reflectances(factor: float):
    """A negative control's `modify(params)`: every reflectance of the scene (every key ending in
    `reflectance.value`) times `factor`, the bias the verdict's controls and power study use."""
    def modify(params):
        for key in [k for k in params.keys() if k.endswith("reflectance.value")]:
            params[key] = params[key] * factor
    return modify


def load(scene_path, res=None, **params):
    """Load an XML scene with optional $parameters and a film resolution override."""
    return load_scene(use_variant(), str(scene_path), res, **params)


def same_seed(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", tol=SAME_SEED_TOL, ours_props=None,
              min_frac=SAME_SEED_MIN_FRAC, max_mean_rel=SAME_SEED_MAX_MEAN_REL, ours_modify=None,
              **params) -> SameSeedResult:
    """Same-seed stock and layerbvh renders of an XML scene (`params`: its $parameters;
    `ours_props`: extra layerbvh integrator properties such as treelet_height, batch_rays;
    `ours_modify(params)`: a change to ours' copy of the scene, a negative control's),
    measured by the same-seed criterion (metrics.same_seed_verdict)."""
    c = compare(use_variant(), settings(scene_path, spp, res, seed, traversal, ours_props, params,
                                        statistical_step=False, ours_modify=ours_modify))
    v = same_seed_verdict(c.stock, c.ours, tol, min_frac, max_mean_rel)
    return SameSeedResult(stock=c.stock, ours=c.ours, ours_stats=c.stats, passed=v["passed"],
                          compared_as=c.path.compared_as, **v["values"])


def assert_matches_stock(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", tol=SAME_SEED_TOL,
                         min_frac=SAME_SEED_MIN_FRAC, max_mean_rel=SAME_SEED_MAX_MEAN_REL, diff_dir=None,
                         ours_props=None, **params) -> SameSeedResult:
    """Same seed: the layerbvh render must equal stock `path` (metrics.same_seed_verdict): within
    `tol` (x max(1, |stock|)) in `min_frac` of the pixels, with mean |diff| <= max_mean_rel x mean
    pixel value. On failure the message gives the numbers and, with `diff_dir`, the
    stock/ours/diff images are saved there as EXR."""
    r = same_seed(scene_path, spp, res, seed, traversal, tol, ours_props, min_frac, max_mean_rel, **params)
    if not r.passed:
        where = ""
        if diff_dir is not None:
            out = Path(diff_dir)
            for name, img in (("stock", r.stock), ("ours", r.ours), ("diff", np.abs(r.stock - r.ours))):
                write_exr(out / f"{Path(scene_path).stem}_{name}.exr", img)
            where = f"; images saved in {out}"
        raise AssertionError(f"{scene_path}: layerbvh differs from stock path: {r.summary()} "
                             f"(need >= {100 * min_frac:.2f}% within {tol} and mean |diff| <= "
                             f"{max_mean_rel} x mean){where}")
    return r


def independent_seeds_vs_stock(scene_path, spp=4096, res=(6, 6), traversal="per_ray", modify=None, ours_props=None,
                               **params) -> StatisticalStep:
    """The verdict's second step (verdict.independent_seed_test: independent seeds, a per-pixel
    Welch t-test, Šidák-corrected) of layerbvh against stock `path` at film `res` with `spp`
    camera samples per pixel a side. `modify(params)` changes the scene for the layerbvh side (a
    negative control); `ours_props`: extra layerbvh integrator properties. The result's
    `ours_stats` is ours' last_stats."""
    mi = use_variant()
    s = settings(scene_path, spp, res, 0, traversal, ours_props, params)
    path = path_settings(mi, load(scene_path, res, **params), True, scene_path, params)
    return independent_seed_test(mi, scene_path, tuple(res), spp, path.stock_inner(), ours_props_of(s, path),
                                 dict(params), modify)


def assert_statistically_matches_stock(scene_path, **kw) -> StatisticalStep:
    """`independent_seeds_vs_stock` must pass: no test of its family (hypotheses.Family) rejects."""
    r = independent_seeds_vs_stock(scene_path, **kw)
    assert r.passed, f"{scene_path}: {r.family.summary()}"
    return r


@dataclass
class ABResult:
    """What a `layerbvh_ab` check found (returned when it passes)."""

    scene: str
    traversal: str
    comparison: Comparison = field(repr=False)
    page: str | None = None    # index.html of its compare page, where one was kept
    mde_target: float | None = None  # the MDE the check asked for (run_check's `mde`)
    mde_unreached: str | None = None  # why the verdict's MDE stayed above it, where it did

    @property
    def verdict(self) -> Verdict:
        return self.comparison.verdict

    @property
    def metrics(self) -> dict:
        return self.comparison.metrics

    @property
    def stock_s(self) -> float:  # stock's render (0 when it came from the cache)
        return self.comparison.stock_time.render_s

    @property
    def ours_s(self) -> float:
        return self.comparison.ours_time.render_s

    @property
    def stock(self) -> np.ndarray:
        return self.comparison.stock

    @property
    def ours(self) -> np.ndarray:
        return self.comparison.ours

    @property
    def stock_cached(self) -> bool:
        return self.comparison.stock_time.cached

    @property
    def gradient(self):
        """The derivatives' comparison (ab.gradient.GradientComparison) of a check with `grad`, else None."""
        return self.comparison.gradient

    @property
    def passed(self) -> bool:
        return (self.verdict.passed and (self.gradient is None or self.gradient.passed)
                and self.mde_unreached is None)

    def message(self) -> str:
        """One readable paragraph: the verdict, its numbers, where the page is."""
        m = self.metrics
        where = f" Page: {self.page}" if self.page else " (run with --layerbvh-results DIR to keep its page)"
        grad = "" if self.gradient is None else f" {self.gradient.summary()}."
        if self.mde_unreached:
            grad += f" {self.mde_unreached}."
        return (f"{self.scene} ({self.traversal}): {self.verdict.label}. {self.verdict.summary()}.{grad} "
                f"RMSE {m['rmse']:.3g}, relMSE {m['rel_mse']:.3g}, pixels over 1e-3 "
                f"{100 * m['frac_pixels_over_1e-3']:.2f}%; stock {self.stock_s:.2f} s"
                f"{' (cached)' if self.stock_cached else ''}, ours {self.ours_s:.2f} s.{where}")


# `mde`: a check may ask its verdict to rule out every bias of the image mean above a share; the
# samples per pixel grow (at most MDE_SPP_BUDGET x the asked spp) until the verdict's MDE
# (hypotheses.Family.power) reaches it, else the check fails saying where it stopped. The MDE
# falls about as 1/sqrt(spp) towards the equivalence margin (hypotheses.MARGIN), below which no
# spp can take it.
MDE_SPP_BUDGET = 64


def run_check(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, variant=None, use_cache=True,
              keep_dir: Path | None = None, keep_all=False, ours_modify=None, grad=None, mde=None, mde_max_spp=None,
              **params) -> ABResult:
    """`run_one` at `spp`, or with `mde` (a relative bias of the image mean, e.g. 0.01) again at
    more samples per pixel until the verdict's MDE is at most `mde` (up to `mde_max_spp`,
    default MDE_SPP_BUDGET x spp); the result fails with the reason where it never is."""
    if mde is None:
        return run_one(scene, spp, res, traversal, seed, ours, variant, use_cache, keep_dir, keep_all, ours_modify,
                       grad, **params)
    if not hypotheses.MARGIN < mde < 1:
        raise ValueError(f"mde={mde!r}: must lie between the verdict's equivalence margin {hypotheses.MARGIN:g} "
                         f"(float rounding, which no number of samples removes) and 1")
    cap = int(mde_max_spp or MDE_SPP_BUDGET * spp)
    while True:
        result = run_one(scene, spp, res, traversal, seed, ours, variant, use_cache, None, False, ours_modify, grad,
                         **params)
        got = (result.verdict.mde() or {}).get("image")
        if not result.verdict.passed or (got is not None and got <= mde) or spp >= cap or got is None:
            break
        # MDE ~ MARGIN + k / sqrt(spp): the spp that reaches `mde`, at least twice and at most 16x this one.
        need = spp * ((got - hypotheses.MARGIN) / (mde - hypotheses.MARGIN)) ** 2 * 1.2
        spp = int(min(cap, max(2 * spp, min(16 * spp, math.ceil(need)))))
    result.mde_target = mde
    if result.verdict.passed and (got is None or got > mde):
        result.mde_unreached = (f"asked to rule out a bias above {100 * mde:.2g}% of the image mean: "
                                + ("this verdict states no MDE (no test of equal means ran)" if got is None else
                                   f"its MDE is {100 * got:.2g}% at {spp} spp, the most this check may take "
                                   f"(mde_max_spp {cap})"))
    if keep_dir is not None and (keep_all or not result.passed):
        write_comparison(keep_dir, result.comparison)
        result.page = str(Path(keep_dir) / "index.html")
    return result


def run_one(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, variant=None, use_cache=True,
            keep_dir: Path | None = None, keep_all=False, ours_modify=None, grad=None, **params) -> ABResult:
    """The A/B check of the pytest plugin and `verdict_vs_stock`: `compare` of stock `path` (the
    scene's own path settings; with `use_cache`, cached by scene content and settings) against
    layerbvh with `ours` integrator properties on top (and `ours_modify(params)` applied to its
    copy of the scene: negative controls), same seed, then the two-step verdict, and with `grad`
    (a mi.traverse key; prb, prb_basic, prbvolpath) the derivatives' verdict too (`compare
    --grad`); the compare page is written to `keep_dir` when the check fails (or always with
    `keep_all`)."""
    mi = use_variant(variant)
    c = compare(mi, settings(Path(scene).resolve(), spp, res, seed, traversal, ours, params, ours_modify=ours_modify,
                             stock_cache=cache_dir("pytest") if use_cache else None, grad=grad))
    result = ABResult(scene=str(scene), traversal=traversal, comparison=c)
    if keep_dir is not None and (keep_all or not c.passed):
        write_comparison(keep_dir, c)
        result.page = str(Path(keep_dir) / "index.html")
    return result


def verdict_vs_stock(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", ours_props=None, ours_modify=None,
                     **params) -> Verdict:
    """The two-step verdict (ab/verdict.py, as `layerbvh compare` gives it) of layerbvh against
    stock `path` on an XML scene (`run_check`, stock rendered afresh): same seed, and where
    same-seed paths diverged, independent seeds on a downsampled film. `ours_modify(params)`
    changes ours' copy of the scene (a negative control)."""
    return run_check(scene_path, spp=spp, res=res, traversal=traversal, seed=seed, ours=ours_props, use_cache=False,
                     ours_modify=ours_modify, **params).verdict


def assert_agrees_with_stock(scene_path, **kw) -> Verdict:
    """`verdict_vs_stock` must say "same paths" or "agrees within Monte Carlo noise"."""
    v = verdict_vs_stock(scene_path, **kw)
    assert v.passed, f"{scene_path}: {v.label}: {v.summary()}"
    return v
