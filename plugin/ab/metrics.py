"""Image metrics for the stock-vs-ours A/B comparison: error norms, ꟻLIP, ΔE2000 and the per-pixel Z-test."""
from __future__ import annotations

import functools
import json
import math
import os
import warnings

import numpy as np

# Tone-mapped values are compared as LDR, so anything brighter than white is one colour.
_SRGB_LINEAR_CUTOFF = 0.0031308
_REL_MSE_EPS = 1e-2
_DIFF_THRESHOLD = 1e-3
# The same-seed criterion (every A/B comparison's first step: compare, the pytest helpers, the
# third-party table, the stability suite): at least SAME_SEED_MIN_FRAC of the pixels within
# SAME_SEED_TOL x max(1, |stock|) in every channel, and the mean |diff| at most
# SAME_SEED_MAX_MEAN_REL of the mean pixel value. The tolerance is absolute up to 1 and relative
# above it: a pixel of radiance 1e6 (a tiny bright emitter seen directly) carries float32 rounding
# of ~0.06, which no absolute 1e-3 can hold.
SAME_SEED_TOL = 1e-3
SAME_SEED_MIN_FRAC = 0.999
SAME_SEED_MAX_MEAN_REL = 1e-4
_EQUAL_MEANS_TOL = 1e-6


def as_rgb(img, name: str = "image") -> np.ndarray:
    """Return `img` as a finite float32 (H, W, 3) array: grey is repeated, channels past 3 are dropped."""
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] in (0, 2):
        raise ValueError(f"{name}: expected (H, W), (H, W, 1) or (H, W, >=3), got shape {np.shape(img)}")
    a = np.repeat(a, 3, axis=2) if a.shape[2] == 1 else a[:, :, :3]
    a = np.ascontiguousarray(a, dtype=np.float32)
    bad = int(np.count_nonzero(~np.isfinite(a).all(axis=2)))
    if bad:
        raise ValueError(f"{name} image has {bad} pixel(s) with NaN or Inf values")
    return a


STOKES_PANELS = ("RGB", "S0", "S1", "S2", "S3")  # a `stokes` render's channels, in threes


def stokes_panels(img) -> np.ndarray:
    """A `stokes` render, (H, W, 15): RGB, then the Stokes vector's S0-S3 each in RGB (Mitsuba's
    stokes integrator), as its five RGB images side by side, (H, 5W, 3), so that every image metric
    and test judges S1-S3 (the polarization) as it judges RGB."""
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 * len(STOKES_PANELS):
        raise ValueError(f"a stokes image has {3 * len(STOKES_PANELS)} channels, got shape {a.shape}")
    return np.concatenate([a[..., 3 * i:3 * i + 3] for i in range(len(STOKES_PANELS))], axis=1)


def _pair(ref, test) -> tuple[np.ndarray, np.ndarray]:
    r, t = as_rgb(ref, "ref"), as_rgb(test, "test")
    if r.shape != t.shape:
        raise ValueError(f"shape mismatch: ref {np.shape(ref)} vs test {np.shape(test)}")
    return r, t


def tonemap_srgb(img) -> np.ndarray:
    """Clip linear RGB to [0, 1] and apply the piecewise sRGB OETF."""
    x = np.clip(np.asarray(img, dtype=np.float32), 0.0, 1.0)
    # np.where evaluates both branches; the power of the tiny-value branch is harmless.
    return np.where(x <= _SRGB_LINEAR_CUTOFF, 12.92 * x,
                    1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def _flip_on_srgb(ref_srgb: np.ndarray, test_srgb: np.ndarray) -> tuple[np.ndarray, float]:
    import flip_evaluator as flip  # local: loaded for ꟻLIP only

    # flip-evaluator 1.7: evaluate(ref, test, "LDR", inputsRGB=True, applyMagma=True, ...) returns
    # (error map, mean, params). Without magma the map is (H, W, 1); LDR inputs are sRGB-encoded.
    err, mean, _params = flip.evaluate(np.ascontiguousarray(ref_srgb), np.ascontiguousarray(test_srgb),
                                       "LDR", inputsRGB=True, applyMagma=False, computeMeanError=True)
    return np.asarray(err, dtype=np.float32).reshape(ref_srgb.shape[:2]), float(mean)


def flip_error_map(ref, test) -> tuple[np.ndarray, float]:
    """LDR ꟻLIP error map (H, W) in [0, 1] and its mean, on the tone-mapped sRGB images."""
    r, t = _pair(ref, test)
    return _flip_on_srgb(tonemap_srgb(r), tonemap_srgb(t))


@functools.cache
def _colour():
    # colour-science warns on import when SciPy is missing; nothing used here needs SciPy.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour  # local: colour-science takes about a second to import; loaded for ΔE2000 only
    return colour


def _srgb_to_lab(srgb: np.ndarray) -> np.ndarray:
    colour = _colour()
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    xyz = colour.sRGB_to_XYZ(srgb.astype(np.float64), apply_cctf_decoding=True)
    return colour.XYZ_to_Lab(xyz, d65)


def delta_e2000(ref_srgb: np.ndarray, test_srgb: np.ndarray) -> np.ndarray:
    """Per-pixel CIEDE2000 between two sRGB-encoded images in [0, 1]."""
    return np.asarray(_colour().delta_E(_srgb_to_lab(ref_srgb), _srgb_to_lab(test_srgb),
                                        method="CIE 2000"))


def _error_norms(r: np.ndarray, t: np.ndarray) -> dict:
    r64, t64 = r.astype(np.float64), t.astype(np.float64)
    d = t64 - r64
    ad = np.abs(d)
    return {
        "rmse": float(np.sqrt(np.mean(d * d))),
        "rel_mse": float(np.mean(d * d / (r64 * r64 + _REL_MSE_EPS))),
        "max_abs": float(ad.max()),
        "frac_pixels_over_1e-3": float(np.mean(ad.max(axis=2) > _DIFF_THRESHOLD)),
        "mean_abs": float(ad.mean()),
        "mean_ref": float(r64.mean()),
        "pixels": int(r.shape[0] * r.shape[1]),
    }


def same_seed_verdict(ref, test, tol: float = SAME_SEED_TOL, min_frac: float = SAME_SEED_MIN_FRAC,
                      max_mean_rel: float = SAME_SEED_MAX_MEAN_REL) -> dict:
    """Does a same-seed render equal the reference up to floating-point noise? {passed,
    criterion, values}: the share of pixels whose every channel is within `tol`, and the mean
    |diff| against the mean |pixel value|."""
    r, t = _pair(ref, test)
    d = np.abs(t.astype(np.float64) - r)
    within = d.max(-1) <= tol * np.maximum(1.0, np.abs(r.astype(np.float64)).max(-1))
    # (The mean |stock|: a gradient image is signed.)
    frac, mean_abs, mean_ref = float(np.mean(within)), float(d.mean()), float(np.abs(r.astype(np.float64)).mean())
    out = {"passed": frac >= min_frac and mean_abs <= max_mean_rel * mean_ref,
           "criterion": f"same seed: >= {100 * min_frac:g}% of pixels within {tol:g} x max(1, |stock|) in every "
                        f"channel and mean |diff| <= {max_mean_rel:g} x mean pixel",
           "values": {"frac_within": frac, "mean_abs": mean_abs, "mean_ref": mean_ref, "max_abs": float(d.max())}}
    _log("same_seed", passed=bool(out["passed"]), min_frac=min_frac, max_mean_rel=max_mean_rel, **out["values"])
    return out


VERDICT_LOG_ENV = "LAYERBVH_VERDICT_LOG"


def _log(kind: str, **values) -> None:
    """With LAYERBVH_VERDICT_LOG set, append `values` and the test that asked
    (PYTEST_CURRENT_TEST, inherited by a test's subprocesses) to that file as a JSON line:
    scripts/cpu_margins.py reads it to show how near its threshold each same-seed check and
    verdict of the suite sits on this CPU (issue 64). One O_APPEND write per line, so processes
    may share the file."""
    log = os.environ.get(VERDICT_LOG_ENV)
    if log:
        rec = {"kind": kind, "test": os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0], **values}
        with open(log, "a") as fh:
            fh.write(json.dumps(rec) + "\n")


def compare_images_with_flip_map(ref, test) -> tuple[dict, np.ndarray]:
    """`compare_images` plus the ꟻLIP error map, so reports need not run ꟻLIP twice."""
    r, t = _pair(ref, test)
    rs, ts = tonemap_srgb(r), tonemap_srgb(t)
    flip_map, flip_mean = _flip_on_srgb(rs, ts)
    de = delta_e2000(rs, ts)
    m = _error_norms(r, t)
    m.update(flip_mean=flip_mean, delta_e2000_mean=float(de.mean()),
             delta_e2000_p95=float(np.percentile(de, 95)))
    keys = ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs",
            "frac_pixels_over_1e-3", "mean_abs", "mean_ref", "pixels")
    return {k: m[k] for k in keys}, flip_map


def compare_images(ref, test) -> dict:
    """Metrics of `test` against the reference `ref` (both linear RGB)."""
    return compare_images_with_flip_map(ref, test)[0]


_erfc = np.frompyfunc(math.erfc, 1, 1)  # no SciPy here; math.erfc keeps tiny p-values accurate


def _two_sided_p(z: np.ndarray) -> np.ndarray:
    return _erfc(np.abs(z) / math.sqrt(2.0)).astype(np.float64)


def _betacf(a: np.ndarray, b: np.ndarray, x: np.ndarray, iterations: int = 300) -> np.ndarray:
    """The continued fraction of the regularized incomplete beta function (modified Lentz),
    elementwise; converges fast for x < (a + 1) / (a + b + 2)."""
    tiny = 1e-300
    c = np.ones_like(x)
    d = 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / np.where(np.abs(d) < tiny, tiny, d)
    h = d.copy()
    for m in range(1, iterations + 1):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / np.where(np.abs(d) < tiny, tiny, d)
            c = 1.0 + num / c
            c = np.where(np.abs(c) < tiny, tiny, c)
            step = c * d
            h = h * step
        if np.all(np.abs(step - 1.0) < 1e-14):
            break
    return h


def _betainc(a: np.ndarray, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Regularized incomplete beta I_x(a, b), elementwise (x in [0, 1])."""
    a, b, x = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64), np.asarray(x, np.float64))
    out = np.where(x <= 0.0, 0.0, 1.0)
    inner = (x > 0.0) & (x < 1.0)
    if inner.any():
        a_, b_, x_ = a[inner], b[inner], x[inner]
        lg = np.frompyfunc(math.lgamma, 1, 1)
        front = np.exp((lg(a_ + b_) - lg(a_) - lg(b_)).astype(np.float64) + a_ * np.log(x_) + b_ * np.log1p(-x_))
        direct = x_ < (a_ + 1.0) / (a_ + b_ + 2.0)
        val = np.empty_like(x_)
        val[direct] = front[direct] * _betacf(a_[direct], b_[direct], x_[direct]) / a_[direct]
        flip = ~direct
        val[flip] = 1.0 - front[flip] * _betacf(b_[flip], a_[flip], 1.0 - x_[flip]) / b_[flip]
        out[inner] = val
    return out


def _two_sided_p_student(t: np.ndarray, df: np.ndarray) -> np.ndarray:
    """P(|T| >= |t|) for Student's t with `df` degrees of freedom: I_{df/(df+t^2)}(df/2, 1/2)."""
    t2 = np.square(t)
    return _betainc(df / 2.0, np.full_like(df, 0.5), df / (df + t2))


def pixel_test(ref_mean, ref_var, test_mean, test_var, n_ref, n_test, alpha: float = 0.01,
               student: bool = False) -> tuple[dict, np.ndarray]:
    """Per-pixel two-sample test of equal means with Šidák correction over the pixels (the idea
    of mitsuba's RenderingRegressionTest): {pass_fraction, pixels, min_p, threshold} and the
    (H, W) map of passing pixels.

    `*_var` are variances of one of the n averaged values, so the variance of each mean is
    var / n. With `student` the variances count as estimated from n values each (repeated
    renders): Welch's t-test, Student's t with Welch-Satterthwaite degrees of freedom. A
    Z-test there would take a variance estimated from 16 renders as exact and fail pixels of
    equal estimators far more often than `alpha` (at 576 pixels and alpha 0.01, |z| must
    exceed 4.3, which t with 30 degrees of freedom does 1e4 times more often than a normal).
    Without it, a Z-test (variances known or from many samples)."""
    a, va = as_rgb(ref_mean, "ref_mean"), as_rgb(ref_var, "ref_var")
    b, vb = as_rgb(test_mean, "test_mean"), as_rgb(test_var, "test_var")
    if not (a.shape == va.shape == b.shape == vb.shape):
        raise ValueError(f"shape mismatch: ref_mean {a.shape}, ref_var {va.shape}, "
                         f"test_mean {b.shape}, test_var {vb.shape}")
    diff = a.astype(np.float64) - b
    na, nb = np.asarray(n_ref, np.float64), np.asarray(n_test, np.float64)
    sa, sb = va.astype(np.float64) / na, vb.astype(np.float64) / nb
    se2 = sa + sb
    degenerate = se2 <= 0.0
    safe = np.where(degenerate, 1.0, se2)
    z = np.divide(diff, np.sqrt(safe))
    if student:
        df = np.square(safe) / np.maximum(np.square(sa) / np.maximum(na - 1, 1) + np.square(sb) / np.maximum(nb - 1, 1),
                                          1e-300)
        p = _two_sided_p_student(z, np.maximum(df, 1.0))
    else:
        p = _two_sided_p(z)
    # With no noise at all the estimators are deterministic: equal means is the only pass.
    p = np.where(degenerate, np.where(np.abs(diff) <= _EQUAL_MEANS_TOL, 1.0, 0.0), p)
    pixels = a.shape[0] * a.shape[1]
    threshold = -math.expm1(math.log1p(-alpha) / pixels)  # = 1 - (1-alpha)^(1/pixels), precisely
    passed = (p > threshold).all(axis=2)
    return ({"pass_fraction": float(passed.mean()), "pixels": int(pixels),
             "min_p": float(p.min()), "threshold": float(threshold)}, passed)


# -- the two-step verdict ---------------------------------------------------------------------------
# Wherever a verdict is given (report.json and the page, the sweep table, the pytest helpers, the
# third-party table): 1. the same-seed criterion above; where it holds, the traversal left every
# path as stock's ("same paths"). 2. Otherwise same-seed paths diverged somewhere (after many
# bounces a 1e-4 relative difference in t, or the other of two coplanar triangles, moves a path)
# and the estimators are judged by a family of tests of equal means: paired tests on the
# same-seed images and independent-seed tests on a downsampled film, over the image, its tiles
# and its pixels, under one correction (plugin/ab/hypotheses.py says why each is valid;
# plugin/ab/verdict.py renders them). Every verdict states the bias its tests would catch (MDE).
SAME_PATHS = "same paths"
AGREES = "agrees within Monte Carlo noise"
DIFFERS = "differs beyond noise"
SAME_SEED_DIFFERS = "differs (same seed; no independent-seed test run)"
Z_ALPHA = 0.01        # family-wise false-alarm rate of one verdict (hypotheses.ALPHA)
Z_MAX_SIDE = 32       # the independent-seed film: the scene's aspect, its longer side at most this many pixels
# Samples per pixel of the test's one render per side (each pixel's mean and per-sample variance).
Z_MIN_SPP = 16  # (Welch with ~30 degrees of freedom at the least; the compare's own budget first)
Z_MAX_SAMPLES = 1 << 20  # camera samples per side at most: one traced batch (batch_rays' default)
# Camera samples per side against one of the compare's renders: the compare renders stock, the
# embree control, ours and a counted pass; the test renders stock and ours once each at half as
# many samples, so it takes well under the compare's own time.
Z_SAMPLE_SHARE = 0.5


def z_test_film(width: int, height: int) -> tuple[int, int]:
    """The statistical step's film: the scene's aspect, longer side at most Z_MAX_SIDE."""
    scale = max(1.0, max(width, height) / Z_MAX_SIDE)
    return max(1, round(width / scale)), max(1, round(height / scale))


def z_test_spp(width: int, height: int, samples: int) -> int:
    """Samples per pixel of the test's film so that one side traces about Z_SAMPLE_SHARE x
    `samples` camera samples (`samples`: one render of the compare), within Z_MIN_SPP and
    Z_MAX_SAMPLES."""
    zw, zh = z_test_film(width, height)
    return int(max(Z_MIN_SPP, min(Z_MAX_SAMPLES // (zw * zh), round(Z_SAMPLE_SHARE * samples / (zw * zh)))))


def verdict_label(same_seed_passed: bool, rejected: bool | None) -> str:
    """The verdict's label: `rejected`, whether a test of the family rejected equal means (None:
    no family decided, step 1 alone)."""
    label = (DIFFERS if rejected else SAME_PATHS if same_seed_passed
             else SAME_SEED_DIFFERS if rejected is None else AGREES)
    _log("verdict", label=label, same_seed_passed=same_seed_passed, rejected=rejected)
    return label


def verdict_passed(label: str) -> bool:
    return label in (SAME_PATHS, AGREES)
