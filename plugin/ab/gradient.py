"""Gradients in an A/B comparison: the derivatives of stock's and ours' renders with respect to one scene parameter
(a mi.traverse key), forward (an image) and backward (the parameter's gradient of the image's sum), judged with the
image verdict's two steps."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from layerbvh_mitsuba.ab import hypotheses, metrics
from layerbvh_mitsuba.ab.render import UserError, load_integrator, load_scene
from layerbvh_mitsuba.ab.verdict import MOMENT_RENDERS, STOCK_SEED, load_modified
from layerbvh_mitsuba.runtime.registry import differentiation


@dataclass
class Gradients:
    """One side's derivatives at one seed: `forward`, the (H, W, 3) derivative of the image when
    every component of the parameter moves by 1 (None: the integrator has no forward mode), and
    `backward`, the gradient of the image's sum (every pixel and channel weighted 1) with respect
    to each of the parameter's components, flattened. Non-finite values are 0 (`nonfinite` counts them)."""

    forward: np.ndarray | None = field(repr=False)
    backward: np.ndarray = field(repr=False)
    nonfinite: int = 0


def _finite(a: np.ndarray) -> tuple[np.ndarray, int]:
    bad = ~np.isfinite(a)
    return np.where(bad, 0.0, a), int(bad.sum())


def check_gradient(mi, estimator: str, scene, key: str) -> None:
    """Refuse (UserError, one line) a gradient comparison that cannot run: an integrator that
    does not differentiate, or a key that is not a differentiable parameter of the scene."""
    if not differentiation(estimator)[0]:
        raise UserError(f"--grad needs a differentiable integrator (prb, prb_basic, prbvolpath); the scene's is "
                        f"{estimator}")
    params = mi.traverse(scene)
    if key not in params:
        some = ", ".join(k for k in params.keys() if not k.endswith(("to_world", "faces", "vertex_positions",
                                                                       "vertex_normals", "vertex_texcoords")))[:300]
        raise UserError(f"--grad {key}: the scene has no parameter {key} (mi.traverse lists: {some})")
    if not dr.is_diff_v(params[key]) or not dr.is_float_v(params[key]):
        raise UserError(f"--grad {key}: the parameter is not differentiable (a {type(params[key]).__name__})")


def gradients(mi, scene, integrator, key: str, spp: int, seed: int, forward: bool) -> Gradients:
    """`integrator`'s derivatives of its render of `scene` at `seed` with respect to the
    parameter `key`, through `mi.render` as a user calls it (the forward pass and the backward
    pass each render once in primal mode and once replaying)."""
    params = mi.traverse(scene)
    fwd = None
    try:
        if forward:
            dr.enable_grad(params[key])
            params.update()
            image = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
            dr.forward(params[key])
            fwd = np.array(dr.grad(image), np.float64)[..., :3]
            dr.disable_grad(params[key])
            params.update()
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, integrator=integrator, spp=spp, seed=seed)
        dr.backward(image)
        bwd = np.array(dr.grad(params[key]), np.float64).ravel()
    finally:
        dr.disable_grad(params[key])
        params.update()
    bwd, bad = _finite(bwd)
    if fwd is not None:
        fwd, bad_f = _finite(fwd)
        bad += bad_f
    return Gradients(fwd, bwd, bad)


def _row(v: np.ndarray) -> np.ndarray:
    """A backward gradient as a one-row grey image, for the image criteria."""
    return v.reshape(1, -1)


def same_seed(stock: Gradients, ours: Gradients) -> dict:
    """Step 1 on each derivative the sides have (metrics.same_seed_verdict's criterion): {passed,
    forward, backward}."""
    parts = {"backward": metrics.same_seed_verdict(_row(stock.backward), _row(ours.backward))}
    if stock.forward is not None:
        parts["forward"] = metrics.same_seed_verdict(stock.forward, ours.forward)
    return {"passed": all(p["passed"] for p in parts.values()), **parts}


@dataclass
class GradientStatistical:
    """Step 2 for gradients: MOMENT_RENDERS pairs of renders, stock and ours at the same seed in
    each pair and independent seeds between pairs; each pixel of the forward derivative, each
    component of the backward one and each of their sums tested for a zero mean difference
    (`paired_over_renders`)."""

    resolution: tuple[int, int]
    spp: int                    # per render
    renders: int                # pairs
    forward: dict | None        # paired_over_renders' summary on the forward derivative
    backward: dict              # ... on the backward gradient's components
    seconds: float
    stock_side: tuple | None = field(default=None, repr=False)  # stock's renders (_moments), for reuse

    @property
    def passed(self) -> bool:
        return all(t["pass_fraction"] == 1.0 for t in (self.forward, self.backward) if t is not None)

    def as_dict(self) -> dict:
        return {"resolution": list(self.resolution), "spp": self.spp, "renders": self.renders,
                "forward": self.forward, "backward": self.backward, "seconds": self.seconds,
                "alpha": hypotheses.ALPHA, "margin": hypotheses.MARGIN,
                "test": "paired t-test over same-seed render pairs (ours - stock) per pixel and per component, "
                        "and of their sums, beyond the equivalence margin; Bonferroni over them"}


def _moments(runs: list[Gradients]) -> tuple:
    fwd = None if runs[0].forward is None else np.stack([r.forward for r in runs])
    bwd = np.stack([_row(r.backward) for r in runs])
    return fwd, bwd


def paired_over_renders(stock: np.ndarray, ours: np.ndarray, alpha: float) -> dict:
    """Paired test of equal means on renders (n, H, W, C) of both sides, render i of each at the
    same seed and the pairs at independent seeds: per pixel and channel, and over the whole
    (summed) image per channel, Student's t with n - 1 degrees of freedom on the n differences.

    Valid whatever the paths do (hypotheses' paired test, over whole renders): the pairs are
    independent, and E[ours - stock] = 0 in each pair where both estimators are unbiased. Where
    same-seed paths mostly agree the differences have tiny variance, so a 2% error is seen at a
    small fraction of the samples an independent-seed (Welch) test needs; where they diverge the
    difference's variance is at most the two sides' together, Welch's. A test rejects only beyond
    hypotheses.MARGIN of its region's mean |stock| (float rounding of same-seed renders does not
    average out); Bonferroni over every test at `alpha`. Summary: {pass_fraction, pixels, min_p,
    threshold, rejected, sum_relative}."""
    s, o = np.asarray(stock, np.float64), np.asarray(ours, np.float64)
    if s.ndim == 3:  # a backward gradient's row (n, 1, K): one channel
        s, o = s[..., None], o[..., None]
    n = len(s)
    d_pix, s_pix = o - s, np.abs(s.mean(0))
    d_sum, s_sum = (o - s).sum((1, 2)), np.abs(s.sum((1, 2)).mean(0))
    pixels = int(np.prod(s.shape[1:3]))
    count = d_pix[0].size + d_sum[0].size
    threshold = alpha / count

    def test(d, scale, cells):  # (the verdict's statistic and margin: hypotheses.statistics)
        t = hypotheses.Tests(hypotheses.PAIRED, "pixel", d.mean(0), d.std(0, ddof=1) / np.sqrt(n), scale,
                             np.full(scale.shape, cells), df=n - 1)
        excess, _, p = hypotheses.statistics(t)
        return p, (excess > 0) & (p < threshold)
    p_pix, bad_pix = test(d_pix, s_pix, 1)
    p_sum, bad_sum = test(d_sum, s_sum, pixels)
    passed = ~bad_pix.any(axis=-1) & ~bad_sum.any()
    return {"pass_fraction": float(passed.mean()), "pixels": pixels, "min_p": float(min(p_pix.min(), p_sum.min())),
            "threshold": float(threshold), "rejected": int(bad_pix.sum() + bad_sum.sum()),
            "sum_relative": [float(x) for x in d_sum.mean(0) / np.maximum(s_sum, 1e-300)]}


# Camera samples a side in step 2, spread over MOMENT_RENDERS render pairs. Not tied to the
# compare's own spp as the image's step is: a backward gradient sums the whole image, and it must
# see a parameter 2% off (the negative control). Measured on the Cornell box (prb, 8x8):
# with Welch's test over independent seeds 2^20 samples a side were needed (2^17: p = 0.003
# against a threshold of 0.0033); the paired test sees the light 2% brighter and every
# reflectance 2% higher at 2^14 (tests/runtime/test_prb.py prints the margins).
GRAD_SAMPLES = 1 << 15
PAIR_SEED = STOCK_SEED  # the pairs' seeds: PAIR_SEED x MOMENT_RENDERS + r


def statistical_step(mi, scene_path, size: tuple[int, int], stock: dict, ours: dict, key: str,
                     forward: bool, params: dict | None = None, ours_modify=None,
                     stock_side: tuple | None = None) -> GradientStatistical:
    """Both sides' derivatives on the scene's film shrunk to metrics.z_test_film(size),
    GRAD_SAMPLES camera samples a side spread over MOMENT_RENDERS render pairs (stock and ours at
    the same seed in a pair, the pairs at independent seeds), judged by `paired_over_renders`
    (forward and backward at half the family's alpha each). `stock_side`: stock's renders from an
    earlier step with the same arguments (its `stock_side`), not rendered again (a negative
    control changes ours' side only)."""
    t0 = time.perf_counter()
    res = metrics.z_test_film(*size)
    spp = max(1, GRAD_SAMPLES // (res[0] * res[1] * MOMENT_RENDERS))
    scene = load_scene(mi, str(scene_path), res, **(params or {}))
    ours_scene = scene if ours_modify is None else load_modified(mi, scene_path, res, params, ours_modify)
    stock_int, ours_int = load_integrator(mi, stock), load_integrator(mi, ours)
    side = {} if stock_side is None else {"stock": stock_side}
    for name, sc, integ in (("stock", scene, stock_int), ("ours", ours_scene, ours_int)):
        if name not in side:
            side[name] = _moments([gradients(mi, sc, integ, key, spp, PAIR_SEED * MOMENT_RENDERS + r, forward)
                                   for r in range(MOMENT_RENDERS)])
    alpha = hypotheses.ALPHA / (2 if forward else 1)

    def test(i):
        return paired_over_renders(side["stock"][i], side["ours"][i], alpha)
    return GradientStatistical(resolution=tuple(res), spp=spp, renders=MOMENT_RENDERS,
                               forward=test(0) if forward else None, backward=test(1),
                               seconds=time.perf_counter() - t0, stock_side=side["stock"])


@dataclass
class GradientComparison:
    """Stock's and ours' derivatives with respect to `key` at the compare's seed, and their verdict."""

    key: str
    stock: Gradients = field(repr=False)
    ours: Gradients = field(repr=False)
    label: str
    same_seed: dict
    statistical: GradientStatistical | None
    seconds: float

    @property
    def passed(self) -> bool:
        return metrics.verdict_passed(self.label)

    def as_dict(self) -> dict:
        return {"key": self.key, "label": self.label, "passed": self.passed, "seconds": self.seconds,
                "forward": self.stock.forward is not None,
                "backward": {"stock": self.stock.backward[:64].tolist(), "ours": self.ours.backward[:64].tolist(),
                             "components": int(self.stock.backward.size)},
                "nonfinite": {"stock": self.stock.nonfinite, "ours": self.ours.nonfinite},
                "same_seed": self.same_seed,
                "statistical": None if self.statistical is None else self.statistical.as_dict()}

    def summary(self) -> str:
        z = self.statistical
        if z is None:
            tail = ""
        else:
            differ = z.backward['pixels'] - round(z.backward['pass_fraction'] * z.backward['pixels'])
            tail = (f"; paired over {z.renders} same-seed render pairs: backward {differ} of "
                    f"{z.backward['pixels']} components differ")
        return f"gradient d/d {self.key}: {self.label}{tail}"


def compare_gradients(mi, estimator: str, scene_path, scene, ours_scene, size: tuple[int, int], spp: int, seed: int,
                      stock: dict, ours: dict, key: str, params: dict | None = None, ours_modify=None,
                      statistical: bool = True) -> GradientComparison:
    """Stock's and ours' derivatives (integrator dicts `stock`, `ours`) with respect to `key` on
    the loaded scenes at the compare's `spp` and `seed`, then the two steps: same seed (every
    derivative within the image criterion), else, with `statistical`, the paired step over render pairs."""
    check_gradient(mi, estimator, scene, key)
    fwd_mode = differentiation(estimator)[1]
    t0 = time.perf_counter()
    s = gradients(mi, scene, load_integrator(mi, stock), key, spp, seed, fwd_mode)
    o = gradients(mi, ours_scene, load_integrator(mi, ours), key, spp, seed, fwd_mode)
    step1 = same_seed(s, o)
    z = None
    if not step1["passed"] and statistical:
        z = statistical_step(mi, scene_path, size, stock, ours, key, fwd_mode, params, ours_modify)
    label = metrics.SAME_PATHS if step1["passed"] else metrics.SAME_SEED_DIFFERS if z is None else \
        metrics.AGREES if z.passed else metrics.DIFFERS
    return GradientComparison(key, s, o, label, step1, z, time.perf_counter() - t0)
