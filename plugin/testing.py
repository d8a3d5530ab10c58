"""Reusable pytest helpers: check that the layerbvh integrator renders a scene like stock Mitsuba (same seed, and statistically)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .metrics import SAME_SEED_MAX_MEAN_REL, SAME_SEED_MIN_FRAC, SAME_SEED_TOL, same_seed_verdict
from .verdict import load_modified


@dataclass
class SameSeedResult:
    frac_within: float      # share of pixels whose every channel differs by <= tol
    mean_abs: float
    mean_ref: float
    max_abs: float
    stock: np.ndarray
    ours: np.ndarray
    ours_stats: dict  # the layerbvh integrator's last_stats (loop, rays, wavefront_steps, modes_used, ...)

    def summary(self) -> str:
        return (f"{100 * self.frac_within:.3f}% of pixels within tolerance, mean |diff| {self.mean_abs:.3g} "
                f"(mean pixel {self.mean_ref:.3g}), max |diff| {self.max_abs:.3g}")


def _mi():
    from .render import use_variant
    return use_variant()


def load(scene_path, res=None, **params):
    """Load an XML scene with optional $parameters and a film resolution override."""
    from .render import load_scene
    return load_scene(_mi(), scene_path, res, **params)


def render_pair(scene, spp: int, seed: int = 0, traversal: str = "per_ray", ours_scene=None, stats_out=None,
                **ours_props):
    """Stock `path` (with the scene's own settings) and `layerbvh` images of one scene, same seed.
    `ours_props` go to the layerbvh integrator (e.g. treelet_height); `stats_out` (a dict), if
    given, receives the integrator's last_stats."""
    mi = _mi()
    from .render import path_props
    props = path_props(mi, scene)
    stock = mi.load_dict({"type": "path", **props})
    ours = mi.load_dict({"type": "layerbvh", "traversal": traversal, **props, **ours_props})
    a = np.array(mi.render(scene, integrator=stock, spp=spp, seed=seed), np.float32)
    b = np.array(mi.render(ours_scene or scene, integrator=ours, spp=spp, seed=seed), np.float32)
    if stats_out is not None:
        stats_out.update(ours.last_stats)
    return a, b


def same_seed(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", tol=SAME_SEED_TOL, ours_props=None,
              **params) -> SameSeedResult:
    """Same-seed stock and layerbvh renders of an XML scene (`params`: its $parameters;
    `ours_props`: extra layerbvh integrator properties such as treelet_height)."""
    scene = load(scene_path, res, **params)
    stats: dict = {}
    a, b = render_pair(scene, spp, seed, traversal, stats_out=stats, **(ours_props or {}))
    v = same_seed_verdict(a, b, tol)["values"]
    return SameSeedResult(frac_within=v["frac_within"], mean_abs=v["mean_abs"], mean_ref=v["mean_ref"],
                          max_abs=v["max_abs"], stock=a, ours=b, ours_stats=stats)


def assert_matches_stock(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", tol=SAME_SEED_TOL,
                         min_frac=SAME_SEED_MIN_FRAC, max_mean_rel=SAME_SEED_MAX_MEAN_REL, diff_dir=None,
                         ours_props=None, **params) -> SameSeedResult:
    """Same seed: the layerbvh render must equal stock `path` (metrics.same_seed_verdict): within
    `tol` in `min_frac` of the pixels, with mean |diff| <= max_mean_rel * mean pixel value. On
    failure the message gives the numbers and, with `diff_dir`, the stock/ours/diff images are
    saved there as EXR."""
    r = same_seed(scene_path, spp, res, seed, traversal, tol, ours_props, **params)
    ok = r.frac_within >= min_frac and r.mean_abs <= max_mean_rel * r.mean_ref
    if not ok:
        where = ""
        if diff_dir is not None:
            from .render import write_exr
            out = Path(diff_dir)
            for name, img in (("stock", r.stock), ("ours", r.ours), ("diff", np.abs(r.stock - r.ours))):
                write_exr(out / f"{Path(scene_path).stem}_{name}.exr", img)
            where = f"; images saved in {out}"
        raise AssertionError(f"{scene_path}: layerbvh differs from stock path: {r.summary()} "
                             f"(need >= {100 * min_frac:.2f}% within {tol} and mean |diff| <= "
                             f"{max_mean_rel} x mean){where}")
    return r


def repeated_moments(scene, integrator, spp: int, repeats: int, seed0: int):
    """Per-pixel mean and variance of `repeats` independent renders (the estimator's variance)."""
    mi = _mi()
    imgs = np.stack([np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed0 + k), np.float64)
                     for k in range(repeats)])
    return imgs.mean(0), imgs.var(0, ddof=1)


def zscore_vs_stock(scene_path, spp=64, res=(8, 8), repeats=8, traversal="per_ray", alpha=0.01,
                    modify=None, ours_props=None, **params) -> dict:
    """Independent seeds: per-pixel Z-test (Šidák-corrected) of layerbvh against stock `path`.
    `modify(params)` may change the scene for the layerbvh render (a negative control);
    `ours_props`: extra layerbvh integrator properties. The result also holds `ours_stats`, the
    integrator's last_stats of its last repeat."""
    mi = _mi()
    from .render import path_props
    from .metrics import zscore_test
    scene = load(scene_path, res, **params)
    props = path_props(mi, scene)
    stock = mi.load_dict({"type": "path", **props})
    ref_mean, ref_var = repeated_moments(scene, stock, spp, repeats, seed0=1000)
    ours_scene = scene if modify is None else load_modified(mi, scene_path, res, params, modify)
    ours = mi.load_dict({"type": "layerbvh", "traversal": traversal, **props, **(ours_props or {})})
    mean, var = repeated_moments(ours_scene, ours, spp, repeats, seed0=5000)
    # Variance of a repeat's mean; zscore_test divides by the repeat count.
    return {**zscore_test(ref_mean, ref_var, mean, var, repeats, repeats, alpha=alpha),
            "ours_stats": dict(ours.last_stats)}


def assert_statistically_matches_stock(scene_path, min_pass=0.975, **kw) -> dict:
    r = zscore_vs_stock(scene_path, **kw)
    assert r["pass_fraction"] >= min_pass, \
        f"{scene_path}: only {100 * r['pass_fraction']:.1f}% of pixels pass the Z-test (need {100 * min_pass}%): {r}"
    return r


@dataclass
class ABResult:
    """What a `layerbvh_ab` check found (returned when it passes)."""

    scene: str
    traversal: str
    verdict: object            # verdict.Verdict
    metrics: dict              # metrics.compare_images
    stock_s: float             # stock's render (0 when it came from the cache)
    ours_s: float
    stock_cached: bool
    page: str | None = None    # index.html of its compare page, where one was kept
    stock: object = field(default=None, repr=False)
    ours: object = field(default=None, repr=False)

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    def message(self) -> str:
        """One readable paragraph: the verdict, its numbers, where the page is."""
        m = self.metrics
        where = f" Page: {self.page}" if self.page else " (run with --layerbvh-results DIR to keep its page)"
        return (f"{self.scene} ({self.traversal}): {self.verdict.label}. {self.verdict.summary()}. "
                f"RMSE {m['rmse']:.3g}, relMSE {m['rel_mse']:.3g}, pixels over 1e-3 "
                f"{100 * m['frac_pixels_over_1e-3']:.2f}%; stock {self.stock_s:.2f} s"
                f"{' (cached)' if self.stock_cached else ''}, ours {self.ours_s:.2f} s.{where}")


def run_check(scene, spp=16, res=(64, 64), traversal="auto", seed=0, ours=None, variant=None, use_cache=True,
              keep_dir: Path | None = None, keep_all=False, ours_modify=None, **params) -> ABResult:
    """The A/B check of the pytest plugin and `verdict_vs_stock`: stock `path` (the scene's own
    path settings; with `use_cache`, cached by scene content and settings) against layerbvh with
    `ours` integrator properties on top (and `ours_modify(params)` applied to its copy of the
    scene: negative controls), same seed, then the two-step verdict; the compare page is
    written to `keep_dir` when the check fails (or always with `keep_all`)."""
    import mitsuba
    import layerbvh
    from . import metrics
    from .converge import cached_stock
    from .render import cache_dir, load_integrator, load_scene, path_props, render_passes, use_variant
    from .report import write_report
    from .verdict import judge
    mi = use_variant(variant)
    scene_path = Path(scene).resolve()
    sc = load_scene(mi, str(scene_path), tuple(res), **params)
    props = path_props(mi, sc)
    settings = {"resolution": list(res), "integrator": props, "variant": mi.variant(), "params": params,
                "versions": {"mitsuba": mitsuba.__version__, "layerbvh": layerbvh.__version__}}
    t0 = time.perf_counter()
    if use_cache:
        stock, info = cached_stock(mi, sc, scene_path, settings, spp, seed, cache_dir("pytest"), "stock", False)
        cached = bool(info.get("cached"))
    else:
        stock = render_passes(mi, sc, load_integrator(mi, {"type": "path", **props}), spp, seed, "stock", False)[0]
        cached = False
    stock_s = 0.0 if cached else time.perf_counter() - t0
    ours_props = {"traversal": traversal, **props, **(ours or {})}
    integ = load_integrator(mi, {"type": "layerbvh", **ours_props})
    ours_scene = sc if ours_modify is None else load_modified(mi, scene_path, tuple(res), params, ours_modify)
    img, ours_s = render_passes(mi, ours_scene, integ, spp, seed, "layerbvh", False)
    judged = judge(mi, scene_path, stock, img, spp, props, ours_props, params, ours_modify)
    result = ABResult(scene=str(scene), traversal=traversal, verdict=judged, metrics=metrics.compare_images(stock, img),
                      stock_s=stock_s, ours_s=ours_s, stock_cached=cached, stock=stock, ours=img)
    if keep_dir is not None and (keep_all or not judged.passed):
        info = {"scene": str(scene_path), "spp": spp, "resolution": list(res), "seed": seed, "variant": mi.variant(),
                "integrator": props, "ours": {"traversal": traversal, "render_s": ours_s, **(ours or {})},
                "stock": {"render_s": stock_s, "cached": cached}}
        write_report(keep_dir, stock, img, info, judged=judged)
        result.page = str(keep_dir / "index.html")
    return result


def verdict_vs_stock(scene_path, spp=16, res=(32, 32), seed=0, traversal="per_ray", ours_props=None, ours_modify=None,
                     **params):
    """The two-step verdict (plugin/verdict.py, as `layerbvh compare` gives it) of layerbvh
    against stock `path` on an XML scene (`run_check`, stock rendered afresh): same seed, and
    where same-seed paths diverged, independent seeds on a downsampled film. `ours_modify(params)`
    changes ours' copy of the scene (a negative control). Returns verdict.Verdict."""
    return run_check(scene_path, spp=spp, res=res, traversal=traversal, seed=seed, ours=ours_props, use_cache=False,
                     ours_modify=ours_modify, **params).verdict


def assert_agrees_with_stock(scene_path, **kw):
    """`verdict_vs_stock` must say "same paths" or "agrees within Monte Carlo noise"."""
    v = verdict_vs_stock(scene_path, **kw)
    assert v.passed, f"{scene_path}: {v.label}: {v.summary()}"
    return v

