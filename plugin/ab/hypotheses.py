"""The verdict's family of tests of equal means (paired same-seed and independent-seed, over the
image, its tiles and its pixels), its one correction and its power (the minimum detectable effect,
MDE).

Why each test is valid (docs/verdict.md says the same for users):

* **Paired, same seed** (`paired`). Stock and ours render with the same sampler seed, and every
  camera sample draws its own random stream (Mitsuba's independent sampler: one PCG32 stream per
  sample), so the per-sample differences ours - stock are independent across samples, and
  E[ours - stock] = 0 in every pixel whenever both estimators are unbiased for the same
  integral -- also where their paths diverge. A film pixel mixes the samples within the
  reconstruction filter's radius r, so two pixels up to ``reach = ceil(2 r) - 1`` apart share
  samples (a box filter: none). The variance of a region's summed difference is therefore
  estimated from the products of differences at offsets within the reach (a
  heteroskedasticity-and-autocorrelation-consistent sum, no smaller than the sum of squares).
  Where most paths agree, the difference has tiny variance: this test sees a 1% bias that an
  independent-seed test at the same samples cannot. It does not hold for an adjoint integrator
  (ptracer): its light paths splat anywhere on the film, so the pixels' correlation has no reach.
* **Independent seeds** (verdict.independent_seed_test): the pixels' means and per-sample
  variances from one render per side at independent seeds; pixels are independent, so a region's
  variance is the sum of its pixels'. Where the moments come from repeated renders (an adjoint
  integrator, stokes), a region's mean is taken in each render and compared by Welch's test over
  the renders (the pixels of one render are correlated there).
* **Equivalence margin.** Same-seed renders of equal estimators differ by float rounding that
  does not average out (Embree's and our t differ by ~1e-7 relative, which moves a few paths the
  same way): the unmodified staircase2 at depth 65 shows a systematic 2e-4 in its image mean at
  z up to 4.7. A test rejects only where |difference| exceeds MARGIN of the region's mean |stock|
  by more than its critical value times its standard error; errors of MARGIN or less are below
  what the verdict claims to see.
* **One correction.** Every test of a verdict (both kinds, all levels, every channel and stokes
  panel) shares the family-wise false-alarm rate ALPHA: each level gets its SHARES of it,
  divided evenly over its tests (weighted Bonferroni, valid under any dependence between tests).
  The measured false-alarm rate is in docs/verdict_power/table.md (scripts/verdict_power.py).

The MDE of a test is the relative bias (ours = stock x (1 + b) over its region) that it rejects
with probability POWER: (MARGIN x scale + (c + q_POWER) x se) / scale.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from layerbvh_mitsuba.ab import metrics

ALPHA = metrics.Z_ALPHA  # family-wise false-alarm rate of one verdict
POWER = 0.95             # the MDE is the relative bias caught with this probability
MARGIN = 1e-3            # equivalence margin, relative to the region's mean |stock| (see above)
SCALE_FLOOR = metrics.SAME_SEED_TOL  # a pixel's scale is at least this (black regions: the same-seed tolerance)
TILE = 8                 # a tile: TILE x TILE pixels of the independent-seed test's film
SHARES = {"image": 0.5, "tile": 0.25, "pixel": 0.25}  # of ALPHA, by level
LEVELS = tuple(SHARES)
PAIRED, INDEPENDENT = "paired same-seed", "independent-seed"
CHANNELS = "RGB"
# Where a tile's MDE is reported: tiles at least this share of the image's mean |stock| per pixel.
LIT_TILE = 1e-3
# A channel (or stokes panel) counts towards the headline MDE where its mean |stock| is at least
# this share of the brightest's: a red-lit scene's blue, a linear polarizer's S3, are near zero
# and their relative MDE says nothing (they are still tested, and listed).
LIT_CHANNEL = 1e-2


@dataclass
class Tests:
    """One kind of test at one level: a test per (panel, region, channel). `estimate` is the
    summed (or mean) difference ours - stock over the region, `se` its standard error, `scale` the
    region's summed |stock| (same units as estimate), `df` the degrees of freedom (inf: normal)."""

    kind: str
    level: str
    estimate: np.ndarray  # (panels, regions, channels)
    se: np.ndarray
    scale: np.ndarray
    pixels: np.ndarray    # (panels, regions, 1): the region's pixel count
    df: np.ndarray | float = math.inf
    regions: int = 1      # (per panel)
    grid: tuple[int, int] = (1, 1)  # the regions' (columns, rows): tiles, or pixels
    film: tuple[int, int] = (1, 1)  # the tested film's (W, H) per panel
    tile: int = 1                   # a region's side in pixels of that film (tile and pixel levels)

    @property
    def count(self) -> int:
        return int(self.estimate.size)

    def margin(self) -> np.ndarray:
        """What the test tolerates: MARGIN of the region's |stock|, at least of SCALE_FLOOR per pixel."""
        return MARGIN * (self.scale + SCALE_FLOOR * self.pixels)


def normal_upper(q: float) -> float:
    """z with P(Z > z) = q for a standard normal (bisection on erfc: no SciPy here)."""
    lo, hi = -40.0, 40.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(mid / math.sqrt(2.0)) > q:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


T_MAX = 1e12         # t_upper's bracket
T_ITERATIONS = 100   # t_upper's cap on Newton/bisection steps (bisection alone: 70 from T_MAX to 1e-9)


def t_upper(q: float, df: np.ndarray | float) -> np.ndarray:
    """t with P(T > t) = q (q < 0.5) for Student's t with `df` degrees of freedom, elementwise
    (inf: the normal's): the Cornish-Fisher expansion (Abramowitz & Stegun 26.7.5) as a start,
    then Newton steps on the tail probability, kept inside a bisection bracket (at df near 1 the
    expansion can start far off). About 5 tail evaluations per element instead of bisection's
    80. Each element stops at its own convergence: over a tile grid's thousands of degrees of
    freedom, iterating the whole array until all had converged ran it to the cap (40 tail
    evaluations of every element), and converged elements stepped out of their bracket again."""
    df = np.asarray(df, np.float64)
    z = normal_upper(q)
    out = np.full(df.shape, z)
    finite = np.isfinite(df)
    if finite.any():
        d = df[finite]
        g = ((z ** 3 + z) / 4, (5 * z ** 5 + 16 * z ** 3 + 3 * z) / 96,
             (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / 384,
             (79 * z ** 9 + 776 * z ** 7 + 1482 * z ** 5 - 1920 * z ** 3 - 945 * z) / 92160)
        t = z + sum(gi / d ** (i + 1) for i, gi in enumerate(g))
        # (The bracket's top: at df 1, P(T > t) ~ 1 / (pi t), so q = 1e-9, a Bonferroni share of
        # alpha over a large film, needs t ~ 3e8; a top of 1e4 returned 1e4 there.)
        lo, hi = np.zeros_like(d), np.full_like(d, T_MAX)
        t = np.clip(t, 1e-6, T_MAX / 2)
        lg = np.frompyfunc(math.lgamma, 1, 1)
        log_c = (lg((d + 1) / 2) - lg(d / 2)).astype(np.float64) - 0.5 * np.log(d * math.pi)
        go = np.arange(d.size)  # the elements not converged yet
        for _ in range(T_ITERATIONS):
            tg, dg = t[go], d[go]
            f = 0.5 * metrics._two_sided_p_student(tg, dg) - q  # decreasing in t
            lo_g, hi_g = np.where(f > 0, tg, lo[go]), np.where(f > 0, hi[go], tg)
            lo[go], hi[go] = lo_g, hi_g
            pdf = np.exp(log_c[go] - (dg + 1) / 2 * np.log1p(tg * tg / dg))
            step = np.where(pdf > 0, f / np.maximum(pdf, 1e-300), 0.0)
            nxt = tg + step
            nxt = np.where((nxt > lo_g) & (nxt < hi_g), nxt, 0.5 * (lo_g + hi_g))
            # (Or its tail is q to 1e-12 of q, and it stays: far in the tail the tail's rounding
            # over the pdf keeps the steps above the step tolerance, and the loop ran to its cap.)
            solved = np.abs(f) <= 1e-12 * q
            done = (np.abs(nxt - tg) <= 1e-10 * np.maximum(1.0, tg)) | solved
            t[go] = np.where(solved, tg, nxt)
            go = go[~done]
            if go.size == 0:
                break
        out[finite] = t
    return out


def _tail_p(t: np.ndarray, df: np.ndarray | float) -> np.ndarray:
    """Two-sided p of statistic t (>= 0 where it matters) at `df` (inf: normal)."""
    df = np.broadcast_to(np.asarray(df, np.float64), t.shape)
    p = np.empty(t.shape)
    normal = ~np.isfinite(df)
    p[normal] = metrics._two_sided_p(t[normal]) if normal.any() else p[normal]
    if (~normal).any():
        p[~normal] = metrics._two_sided_p_student(t[~normal], df[~normal])
    return p


# -- regions -------------------------------------------------------------------------------------------

def tile_labels(h: int, w: int, tile: int) -> tuple[np.ndarray, tuple[int, int]]:
    """(H, W) tile index of each pixel for square tiles of `tile` pixels, and the (columns, rows)."""
    cols, rows = -(-w // tile), -(-h // tile)
    return (np.arange(h)[:, None] // tile) * cols + np.arange(w)[None, :] // tile, (cols, rows)


def _region_sums(x: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """(k, C) sums of (H, W, C) `x` over each label."""
    flat = labels.ravel()
    return np.stack([np.bincount(flat, x[..., c].ravel(), k) for c in range(x.shape[-1])], -1)


def _split(img: np.ndarray, panels: int) -> list[np.ndarray]:
    w = img.shape[1] // panels
    return [img[:, i * w:(i + 1) * w] for i in range(panels)]


def _hac(d: np.ndarray, labels: np.ndarray, k: int, reach: int) -> np.ndarray:
    """(k, C) variance of each region's summed `d` from the products at pixel offsets within
    `reach` inside the region, no smaller than the sum of squares (the estimate under the null
    mean 0)."""
    h, w = labels.shape
    square = _region_sums(d * d, labels, k)
    v = np.zeros_like(square)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            a = (slice(max(0, dy), h + min(0, dy)), slice(max(0, dx), w + min(0, dx)))
            b = (slice(max(0, -dy), h + min(0, -dy)), slice(max(0, -dx), w + min(0, -dx)))
            same = labels[a] == labels[b]
            prod = d[a] * d[b]
            v += np.stack([np.bincount(labels[a][same], prod[..., c][same], k) for c in range(d.shape[-1])], -1)
    return np.maximum(v, square)


def _scale(ref: np.ndarray, labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(k, C) summed |ref| over each region and (k, 1) its pixel count."""
    return _region_sums(np.abs(ref), labels, k), np.bincount(labels.ravel(), minlength=k)[:, None].astype(np.float64)


def paired(stock: np.ndarray, ours: np.ndarray, reach: int, tile: int, panels: int = 1) -> list[Tests]:
    """The paired same-seed tests on the compare's own images (H, W, 3; `panels` side by side):
    each panel's image mean and its tiles of `tile` pixels, per channel."""
    out = []
    for level in ("image", "tile"):
        est, se, scale, pixels = [], [], [], []
        for s, o in zip(_split(np.asarray(stock, np.float64), panels), _split(np.asarray(ours, np.float64), panels)):
            h, w = s.shape[:2]
            labels, grid = (np.zeros((h, w), np.int64), (1, 1)) if level == "image" else tile_labels(h, w, tile)
            side = max(h, w) if level == "image" else tile
            k = int(labels.max()) + 1
            d = o - s
            est.append(_region_sums(d, labels, k))
            se.append(np.sqrt(_hac(d, labels, k, reach)))
            sc, n = _scale(s, labels, k)
            scale.append(sc)
            pixels.append(n)
        out.append(Tests(PAIRED, level, np.stack(est), np.stack(se), np.stack(scale), np.stack(pixels),
                         regions=k, grid=grid, film=(w, h), tile=side))
    return out


@dataclass
class Moments:
    """One side's pixels on the independent-seed film: mean and per-sample variance (H, W, 3)
    over `n` samples each; `renders` (K, H, W, 3) where the samples are whole renders."""

    mean: np.ndarray
    var: np.ndarray
    n: int
    renders: np.ndarray | None = field(default=None, repr=False)


def independent(a: Moments, b: Moments, tile: int = TILE, panels: int = 1) -> list[Tests]:
    """The independent-seed tests of stock's moments `a` against ours' `b`: image, tiles of
    `tile` pixels and pixels, per channel and panel."""
    out = []
    for level in LEVELS:
        est, se, scale, pixels, df = [], [], [], [], []
        for p in range(panels):
            ma, mb = _split(a.mean, panels)[p], _split(b.mean, panels)[p]
            h, w = ma.shape[:2]
            if level == "pixel":
                labels, grid, side = np.arange(h * w).reshape(h, w), (w, h), 1
            elif level == "image":
                labels, grid, side = np.zeros((h, w), np.int64), (1, 1), max(h, w)
            else:
                (labels, grid), side = tile_labels(h, w, tile), tile
            k = int(labels.max()) + 1
            sc, n = _scale(ma, labels, k)
            scale.append(sc)
            pixels.append(n)
            if a.renders is None or b.renders is None:
                est.append(_region_sums(mb - ma, labels, k))
                va = _region_sums(_split(a.var, panels)[p] / a.n, labels, k)
                vb = _region_sums(_split(b.var, panels)[p] / b.n, labels, k)
                n_a, n_b = a.n, b.n
            else:  # a region's mean in each render, Welch over the renders
                ra = np.stack([_region_sums(_split(r, panels)[p], labels, k) for r in a.renders])
                rb = np.stack([_region_sums(_split(r, panels)[p], labels, k) for r in b.renders])
                est.append(rb.mean(0) - ra.mean(0))
                n_a, n_b = len(ra), len(rb)
                va, vb = ra.var(0, ddof=1) / n_a, rb.var(0, ddof=1) / n_b
            se.append(np.sqrt(va + vb))
            df.append(_welch_df(va, vb, n_a, n_b))
        out.append(Tests(INDEPENDENT, level, np.stack(est), np.stack(se), np.stack(scale), np.stack(pixels),
                         np.stack(df), regions=k, grid=grid, film=(w, h), tile=side))
    return out


def independent_counts(film: tuple[int, int], panels: int = 1, channels: int = 3, tile: int = TILE) -> dict:
    """Tests per level that `independent` makes on a film of `film` (W, H) per panel: what the
    family counts before the independent-seed renders exist (Family.planned)."""
    w, h = film
    cols, rows = -(-w // tile), -(-h // tile)
    return {"image": panels * channels, "tile": panels * cols * rows * channels, "pixel": panels * w * h * channels}


def _welch_df(va: np.ndarray, vb: np.ndarray, na: int, nb: int) -> np.ndarray:
    """Welch-Satterthwaite degrees of freedom of var-of-mean estimates va, vb from na, nb values."""
    num = np.square(va + vb)
    den = np.square(va) / max(na - 1, 1) + np.square(vb) / max(nb - 1, 1)
    return np.where(den > 0, num / np.maximum(den, 1e-300), math.inf).clip(1.0)


def statistics(t: Tests) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per test: the excess |estimate| - margin, the statistic excess / se (a zero se: inf where
    the excess is positive) and its two-sided p (1 within the margin)."""
    excess = np.abs(t.estimate) - t.margin()
    safe = np.where(t.se > 0, t.se, 1.0)
    stat = np.where(t.se > 0, excess / safe, np.where(excess > 0, np.inf, 0.0))
    return excess, stat, _tail_p(np.maximum(stat, 0.0), t.df)


# -- the family ------------------------------------------------------------------------------------------

@dataclass
class Rejection:
    """One test that rejected equal means."""

    kind: str
    level: str
    panel: str
    region: tuple[int, int] | None  # (column, row) of a tile or pixel
    channel: str
    relative: float                 # (ours - stock) / |stock| over the region
    z: float                        # (|difference| - margin) / se
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0)  # (x0, y0, x1, y1) in the panel, 0..1

    def describe(self) -> str:
        where = {"image": "image mean", "tile": f"tile {self.region}", "pixel": f"pixel {self.region}"}[self.level]
        panel = f"{self.panel} " if self.panel else ""
        return (f"{self.kind} test, {panel}{where} {self.channel}: ours {100 * self.relative:+.3g}% of stock "
                f"(z {self.z:.3g})")


@dataclass
class Family:
    """Every test of one verdict under one correction (ALPHA over SHARES of the levels), which
    rejected, and the power of those that did not (the MDE). `panels`: the images' panel names
    (a stokes render's five, else one unnamed)."""

    tests: list[Tests]
    panels: tuple[str, ...] = ("",)
    # Tests per level counted in but not run (yet): each level's threshold is that of the whole
    # family, so a test that rejects here rejects there too, whatever the others find.
    planned: dict = field(default_factory=dict)
    rejections: list[Rejection] = field(init=False)
    counts: dict = field(init=False)

    def __post_init__(self):
        self.counts = {lv: sum(t.count for t in self.tests if t.level == lv) + self.planned.get(lv, 0) for lv in LEVELS}
        self.rejections = []
        for t in self.tests:
            stat, reject = self._decide(t)
            w, h = t.film
            for p, r, c in zip(*np.nonzero(reject)):
                col, row = int(r % t.grid[0]), int(r // t.grid[0])
                bounds = (col * t.tile / w, row * t.tile / h,
                          min(1.0, (col + 1) * t.tile / w), min(1.0, (row + 1) * t.tile / h))
                self.rejections.append(Rejection(
                    t.kind, t.level, self.panels[p], None if t.level == "image" else (col, row),
                    CHANNELS[c], float(t.estimate[p, r, c] / max(t.scale[p, r, c], 1e-300)), float(stat[p, r, c]),
                    bounds))
        self.rejections.sort(key=lambda x: -x.z)

    def alpha_each(self, level: str) -> float:
        """The two-sided false-alarm rate of each test at `level`."""
        return ALPHA * SHARES[level] / max(1, self.counts[level])

    def _decide(self, t: Tests) -> tuple[np.ndarray, np.ndarray]:
        excess, stat, p = statistics(t)
        return stat, (excess > 0) & (p < self.alpha_each(t.level))

    @property
    def rejected(self) -> bool:
        return bool(self.rejections)

    def rejection_map(self, h: int, w: int) -> np.ndarray:
        """(h, w) map of an image of the panels side by side: 0 where no test rejects, 1 inside a
        rejected tile, 2 inside a rejected pixel test's pixel (a rejected image mean: 1 everywhere)."""
        out = np.zeros((h, w), np.uint8)
        pw = w // len(self.panels)
        for level, mark in (("image", 1), ("tile", 1), ("pixel", 2)):
            for r in (r for r in self.rejections if r.level == level):
                x0, y0, x1, y1 = r.bounds
                ox = self.panels.index(r.panel) * pw
                xs = slice(ox + int(x0 * pw), ox + max(int(x0 * pw) + 1, int(round(x1 * pw))))
                ys = slice(int(y0 * h), max(int(y0 * h) + 1, int(round(y1 * h))))
                out[ys, xs] = np.maximum(out[ys, xs], mark)
        return out

    def failing_pixels(self) -> int:
        """Pixels of the independent-seed film that some pixel test rejects."""
        return len({(r.panel, r.region) for r in self.rejections if r.level == "pixel"})

    def mde(self, t: Tests) -> np.ndarray:
        """(panels, regions, channels) relative bias each test of `t` catches with probability POWER."""
        c = t_upper(self.alpha_each(t.level) / 2, np.broadcast_to(np.asarray(t.df, np.float64), t.se.shape))
        q = t_upper(1.0 - POWER, np.broadcast_to(np.asarray(t.df, np.float64), t.se.shape))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(t.scale > 0, (t.margin() + (c + q) * t.se) / t.scale, math.inf)

    def _best(self, level: str) -> tuple[np.ndarray | None, Tests | None]:
        """The smaller MDE of the kinds at `level` (per panel, region, channel), on the grid of
        the first kind (a kind on another grid counts only where its median is better)."""
        best, ref = None, None
        for t in (t for t in self.tests if t.level == level):
            m = self.mde(t)
            if best is None:
                best, ref = m, t
            elif m.shape == best.shape:
                best = np.minimum(best, m)
            elif np.median(m) < np.median(best):
                best, ref = m, t
        return best, ref

    def _lit_channels(self, t: Tests) -> np.ndarray:
        """(panels, channels) lit enough to count towards the headline."""
        image = t.scale.sum(1)
        return image >= LIT_CHANNEL * image.max() if image.max() > 0 else np.ones_like(image, bool)

    def power(self) -> dict:
        """The MDEs: `image` (the worst lit channel of the first panel), `by_panel` (each panel's
        channels), `tile_median` and `tile_worst` (over lit tiles, each tile's worst lit channel)."""
        out = {"image": None, "by_panel": {}, "tile_median": None, "tile_worst": None, "tiles": 0}
        img, ref = self._best("image")
        if img is not None:
            lit = self._lit_channels(ref)
            for p, name in enumerate(self.panels):
                out["by_panel"][name or "image"] = {CHANNELS[c]: float(img[p, 0, c]) for c in range(img.shape[2])}
            out["image"] = float(np.max(np.where(lit[0], img[0, 0], 0.0)))
        tile, ref = self._best("tile")
        if tile is not None:
            lit_ch = self._lit_channels(ref)[0]
            per_pixel = ref.scale[0].sum(-1) / np.maximum(ref.pixels[0, :, 0], 1)
            lit = per_pixel >= LIT_TILE * ref.scale[0].sum() / max(ref.pixels[0].sum(), 1)
            worst = np.max(np.where(lit_ch[None, :], tile[0], 0.0), axis=-1)[lit & (per_pixel > 0)]
            if worst.size:
                out.update(tile_median=float(np.median(worst)), tile_worst=float(worst.max()), tiles=int(worst.size))
        return out

    def estimate(self) -> dict:
        """The image mean's relative difference (ours - stock) / |stock| per channel of the first
        panel and its 95% interval half-width, from the most precise kind."""
        tests = [t for t in self.tests if t.level == "image"]
        if not tests:
            return {}
        out = {}
        for c in range(3):
            t = min(tests, key=lambda t: t.se[0, 0, c] / max(t.scale[0, 0, c], 1e-300))
            sc = max(t.scale[0, 0, c], 1e-300)
            df = float(np.broadcast_to(np.asarray(t.df, np.float64), t.se.shape)[0, 0, c])
            half = float(t_upper(0.025, df)) * float(t.se[0, 0, c]) / sc
            out[CHANNELS[c]] = {"relative": float(t.estimate[0, 0, c] / sc), "ci95": half, "test": t.kind}
        return out

    def mde_text(self) -> str:
        """"no bias above X% of the image mean, Y% of a median tile's (Z% in the worst)"."""
        p = self.power()
        if p["image"] is None:
            return "no power measured"
        text = f"no bias above {_pct(p['image'])} of the image mean"
        if p["tile_median"] is not None:
            text += f", {_pct(p['tile_median'])} of a median tile's ({_pct(p['tile_worst'])} in the worst)"
        return text

    def summary(self) -> str:
        n = sum(self.counts.values())
        if self.rejected:
            return f"{len(self.rejections)} of {n} tests reject equal means; strongest: {self.rejections[0].describe()}"
        return (f"{self.mde_text()} ({100 * POWER:g}% power, family-wise alpha {ALPHA:g}, {n} tests: "
                f"{', '.join(sorted({t.kind for t in self.tests}))})")

    def as_dict(self) -> dict:
        return {"rejected": self.rejected, "summary": self.summary(), "mde": self.power(), "mde_text": self.mde_text(),
                "estimate": self.estimate(),
                "alpha": ALPHA, "power": POWER, "margin": MARGIN, "shares": SHARES,
                "tests": {lv: {"count": self.counts[lv], "alpha_each": self.alpha_each(lv),
                               "kinds": sorted({t.kind for t in self.tests if t.level == lv})} for lv in LEVELS},
                "rejections": [{"test": r.describe(), "kind": r.kind, "level": r.level, "panel": r.panel,
                                "region": r.region, "channel": r.channel, "relative": r.relative, "z": r.z}
                               for r in self.rejections[:20]],
                "rejections_total": len(self.rejections)}


def _pct(x: float) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{100 * x:.2g}%"


def reach(scene) -> int:
    """How far apart (in pixels) two film pixels can share a sample: ceil(2 r) - 1 for the
    scene's first sensor's reconstruction filter of radius r (a box of radius 0.5: 0)."""
    r = float(scene.sensors()[0].film().rfilter().radius())
    return max(0, math.ceil(2 * r - 1e-6) - 1)
