"""Robustness of the command line (layerbvh_mitsuba.tools.stability.robustness): every case a user or a hostile
tester meets, run as a subprocess, with its expected outcome."""
from __future__ import annotations

import pytest

from layerbvh_mitsuba.tools.stability import robustness as rb


@pytest.mark.parametrize("name", list(rb.CASES))
def test_case(name):
    r = rb.run_case(name)
    assert r.passed, f"{name}: expected {rb.CASES[name].expected}; got {r.outcome}"
