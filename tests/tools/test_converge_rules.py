"""converge's reading of its fits: no ratio from a fit that is not a power law, none read far outside the measured
times."""
from __future__ import annotations

import math

import pytest

from layerbvh_mitsuba.tools.converge import Config, equal_time_error_table, fits


def _config(name, seconds, errors, stock=False):
    c = Config(name, traversal=None if stock else "per_ray")
    c.points = [{"spp": 2 ** i, "seconds": t, "rel_mse": e, "flip": e, "delta_e2000": e}
                for i, (t, e) in enumerate(zip(seconds, errors))]
    c.fit = fits(c)
    return c


def test_a_clean_power_law_is_read():
    stock = _config("stock", [1, 2, 4, 8], [8, 4, 2, 1], stock=True)
    ours = _config("ours", [2, 4, 8, 16], [8, 4, 2, 1])
    row = equal_time_error_table([stock, ours])["rows"]["ours"]
    assert row["error_vs_base"] == pytest.approx(2.0) and row["time_vs_base"] == pytest.approx(2.0)


def test_noisy_points_give_no_ratio():
    """The issue's case: five noisy points whose fit said 32,252,995x stock at equal time."""
    stock = _config("stock", [1, 2, 4, 8, 16], [8, 4, 2, 1, 0.5], stock=True)
    noisy = _config("noisy", [1, 2, 4, 8, 16], [1.0, 1.0, 5.0, 0.05, 1.0])
    fit = noisy.fit["rel_mse_vs_seconds"]
    assert fit["slope"] < 0 and fit["r2"] < 0.9, fit
    row = equal_time_error_table([stock, noisy])["rows"]["noisy"]
    assert row["error_vs_base"] is None and row["time_vs_base"] is None and "R²" in row["why_not"]


def test_no_read_beyond_twice_the_measured_times():
    stock = _config("stock", [0.1, 0.2, 0.4, 0.8], [0.8, 0.4, 0.2, 0.1], stock=True)
    slow = _config("slow", [10, 20, 40, 80], [80, 40, 20, 10])  # reaching stock's error takes 8000 s
    row = equal_time_error_table([stock, slow])["rows"]["slow"]
    assert row["seconds_to_equal_error"] is None and "beyond 2x" in row["why_not"]
    assert row["rel_mse_at_equal_time"] is None  # the common time, 0.8 s, is 12x below its first render
    assert math.isfinite(equal_time_error_table([stock, slow])["equal_time_s"])
