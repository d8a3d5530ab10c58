"""The verdict's tests of equal means (plugin/ab/hypotheses.py) on synthetic images whose truth is known: the
false-alarm rate under equal means is at most the stated alpha (also where neighbouring pixels share samples), a bias
of the stated MDE is caught at the stated power, a third of it mostly is not, and the report's map marks the rejected
tile."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from layerbvh_mitsuba.ab import hypotheses as hy

H = W = 32
REPS = 300


def _shared_noise(rng, k: int, sigma: float) -> np.ndarray:
    """(H, W, 3) noise in which each pixel sums the iid samples of a (2k+1)^2 window, as a film
    filter of radius k + 1/2 mixes samples: pixels up to 2k apart share some."""
    e = rng.normal(0, sigma, (H + 2 * k, W + 2 * k, 3))
    out = np.zeros((H, W, 3))
    for dy in range(2 * k + 1):
        for dx in range(2 * k + 1):
            out += e[dy:dy + H, dx:dx + W]
    return out / (2 * k + 1)


def _base(rng) -> np.ndarray:
    return 0.2 + 0.6 * rng.random((H, W, 3))


def _paired_family(rng, base, k, bias=0.0, reach=None, sigma=0.005):
    stock = base + rng.normal(0, 0.1, base.shape)            # the shared part: the same samples
    ours = stock + _shared_noise(rng, k, sigma) + bias * base  # where paths diverge, and a bias
    return hy.Family(hy.paired(stock, ours, 2 * k if reach is None else reach, hy.TILE))


def test_t_quantiles_over_a_whole_grid_of_degrees_of_freedom(monkeypatch):
    """t_upper over a tile grid's many Welch degrees of freedom (1 to 200) at once, down to the
    Bonferroni shares of alpha a large film gives (1e-9): each t's tail probability is q (to 1e-9
    of q), and each element stops at its own convergence. (Before: the bracket's top of 1e4
    returned 1e4 where df 1 needs 3e8; the whole array took 40 tail evaluations per element
    where most need 2-5, most of test_hypotheses' time.) The tail evaluations are the work
    asserted, not a time."""
    from layerbvh_mitsuba.ab import metrics
    tail, evaluated = metrics._two_sided_p_student, []

    def counted(t, df):
        evaluated.append(np.size(t))
        return tail(t, df)
    monkeypatch.setattr(metrics, "_two_sided_p_student", counted)
    df = np.concatenate([np.random.default_rng(2).uniform(1, 200, 5000), [1.0, 2.0, 3.5]])
    for q in (1e-9, 1e-4, 0.05):
        evaluated.clear()
        t = hy.t_upper(q, df)
        assert np.max(np.abs(0.5 * tail(t, df) - q)) < 1e-9 * q, q
        assert len(evaluated) <= 25 and sum(evaluated) <= 12 * df.size, (q, len(evaluated), sum(evaluated) / df.size)
    q = 1e-9  # df 1 is Cauchy's: P(T > t) = 1/2 - atan(t)/pi
    assert float(hy.t_upper(q, 1.0)) == pytest.approx(1 / math.tan(math.pi * q), rel=1e-9)
    assert float(hy.t_upper(0.001, 1.0)) == pytest.approx(318.3088, rel=1e-6)  # Student t tables


def test_quantiles_and_reach():
    assert hy.normal_upper(0.025) == pytest.approx(1.959964, abs=1e-5)
    assert float(hy.t_upper(0.025, 10.0)) == pytest.approx(2.228139, abs=1e-4)  # Student t tables
    assert float(hy.t_upper(0.05, math.inf)) == pytest.approx(1.644854, abs=1e-5)

    def scene(radius):
        film = SimpleNamespace(rfilter=lambda: SimpleNamespace(radius=lambda: radius))
        return SimpleNamespace(sensors=lambda: [SimpleNamespace(film=lambda: film)])
    assert [hy.reach(scene(r)) for r in (0.5, 1.0, 1.5, 2.0)] == [0, 1, 2, 3]  # box, tent, ..., gaussian


@pytest.mark.parametrize("k", [0, 1])
def test_paired_false_alarms_stay_below_alpha(k, monkeypatch):
    """Equal means, no equivalence margin (so the variance estimate alone keeps the rate):
    rejections in REPS verdicts at most alpha's, with room for chance (binomial, 3 sigma)."""
    monkeypatch.setattr(hy, "MARGIN", 0.0)
    rng = np.random.default_rng(7 + k)
    base = _base(rng)
    alarms = sum(_paired_family(rng, base, k).rejected for _ in range(REPS))
    assert alarms <= REPS * hy.ALPHA + 3 * math.sqrt(REPS * hy.ALPHA) + 1, alarms


def test_a_bias_of_the_stated_mde_is_caught_at_the_stated_power():
    rng = np.random.default_rng(3)
    base = _base(rng)
    mde = _paired_family(rng, base, 1).power()["image"]
    assert 0 < mde < 0.01, mde
    caught = np.mean([_paired_family(rng, base, 1, bias=mde).rejected for _ in range(100)])
    missed = np.mean([_paired_family(rng, base, 1, bias=mde / 3).rejected for _ in range(100)])
    assert caught >= hy.POWER - 0.07, caught
    assert missed <= 0.5, missed


def test_the_margin_tolerates_rounding_but_no_more():
    """A systematic difference below MARGIN of the mean is never rejected, however precise; 3x it is."""
    rng = np.random.default_rng(5)
    base = _base(rng)
    stock = base + rng.normal(0, 0.1, base.shape)
    assert not hy.Family(hy.paired(stock, stock * (1 + 0.5 * hy.MARGIN), 0, hy.TILE)).rejected
    assert hy.Family(hy.paired(stock, stock * (1 + 3 * hy.MARGIN), 0, hy.TILE)).rejected


def _moments(rng, base, n, bias=0.0, renders=False):
    v = base[:, :, None] * (1 + bias) + rng.normal(0, 0.5, (H, W, n, 3)) * base[:, :, None]
    m = hy.Moments(v.mean(2), v.var(2, ddof=1), n)
    if renders:
        m.renders = np.moveaxis(v, 2, 0)
    return m


@pytest.mark.parametrize("renders", [False, True])
def test_independent_false_alarms_and_power(renders):
    rng = np.random.default_rng(11)
    base = _base(rng)
    n = 16
    fams = [hy.Family(hy.independent(_moments(rng, base, n, renders=renders), _moments(rng, base, n, renders=renders)))
            for _ in range(100)]
    assert sum(f.rejected for f in fams) <= 100 * hy.ALPHA + 3 * math.sqrt(100 * hy.ALPHA) + 1
    mde = float(np.median([f.power()["image"] for f in fams]))
    caught = np.mean([hy.Family(hy.independent(_moments(rng, base, n, renders=renders),
                                               _moments(rng, base, n, mde, renders))).rejected for _ in range(60)])
    assert caught >= hy.POWER - 0.1, (mde, caught)


def test_one_correction_over_every_test():
    rng = np.random.default_rng(2)
    base = _base(rng)
    f = hy.Family(hy.paired(base, base, 0, hy.TILE) + hy.independent(_moments(rng, base, 4), _moments(rng, base, 4)))
    total = sum(f.alpha_each(lv) * f.counts[lv] for lv in hy.LEVELS)
    assert total == pytest.approx(hy.ALPHA)
    assert f.counts == {"image": 6, "tile": 2 * 16 * 3, "pixel": H * W * 3}


@pytest.mark.parametrize("film,panels", [((32, 32), 1), ((32, 18), 1), ((13, 7), 5)])
def test_the_planned_counts_are_what_the_independent_tests_make(film, panels):
    """independent_counts, which the verdict counts in before the renders exist, must be the
    counts `independent` then makes (else the early thresholds would not be the family's)."""
    rng = np.random.default_rng(4)
    w, h = film
    moments = [hy.Moments(rng.random((h, w * panels, 3)), rng.random((h, w * panels, 3)), 8) for _ in range(2)]
    made = hy.Family(hy.independent(*moments, panels=panels), tuple(str(p) for p in range(panels))).counts
    assert hy.independent_counts(film, panels) == made


def test_an_early_rejection_is_a_rejection_of_the_whole_family():
    """A paired test that rejects with the independent tests counted in (Family.planned) rejects
    in the family that holds them, with the same statistic, whatever they find: the verdict's
    'differs' without the independent-seed renders is the full verdict's. And a bias too small
    for the whole family's threshold is not decided early."""
    rng = np.random.default_rng(9)
    base = _base(rng)
    stock = base + rng.normal(0, 0.1, base.shape)
    indep = hy.independent(_moments(rng, base, 4), _moments(rng, base, 4))
    planned = hy.independent_counts((W, H))
    for bias, decided in ((0.02, True), (0.0004, False)):
        paired = hy.paired(stock, stock + _shared_noise(rng, 0, 0.005) + bias * base, 0, hy.TILE)
        early = hy.Family(paired, planned=planned)
        full = hy.Family(paired + indep)
        assert early.counts == full.counts and early.rejected == decided, (bias, early.summary())
        assert [(r.level, r.region, r.channel, r.z) for r in early.rejections] == \
            [(r.level, r.region, r.channel, r.z) for r in full.rejections if r.kind == hy.PAIRED]


def test_the_map_marks_the_rejected_tile():
    rng = np.random.default_rng(4)
    stock = _base(rng)
    ours = stock.copy()
    ours[8:16, 16:24] *= 1.2                         # tile (2, 1) of 8x8 pixels
    f = hy.Family([t for t in hy.paired(stock, ours, 0, hy.TILE) if t.level == "tile"])
    assert {r.region for r in f.rejections} == {(2, 1)}, f.summary()
    where = f.rejection_map(64, 64)                  # at twice the film's size
    assert where[16:32, 32:48].all() and where.sum() == 16 * 16, np.argwhere(where)[[0, -1]]
