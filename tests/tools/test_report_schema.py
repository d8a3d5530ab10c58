"""The report.json schema (plugin/ab/report_schema.py) can fail: a missing field, a field of another type and an
unknown verdict label are each named; the real reports the CLI, --grad and pytest-plugin tests write are checked
against it there."""
from __future__ import annotations

import copy

from layerbvh_mitsuba.ab import metrics, report_schema

MINIMAL = {
    "scene": "s.xml", "spp": 4, "resolution": [24, 16], "seed": 0, "variant": "llvm_ad_rgb", "integrator": {},
    "compared_as": "path", "stock": {"render_s": 0.1, "compile_s": 0.0},
    "ours": {"render_s": 0.2, "compile_s": 0.0, "build_s": 0.01, "loop": "wavefront", "traversal": "layer_sorted",
             "treelet_height": 8, "branching": 4},
    "metrics": {k: 0.0 for k in ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs",
                                 "frac_pixels_over_1e-3")},
    "verdict": {"label": metrics.SAME_PATHS, "passed": True, "summary": "", "mde": None, "criterion": "",
                "same_seed": {"passed": True, "frac_within": 1.0}},
}


def test_a_report_with_every_required_field_holds():
    assert report_schema.validate(MINIMAL) == []


def test_what_is_wrong_is_named():
    bad = copy.deepcopy(MINIMAL)
    del bad["seed"]
    bad["resolution"] = [24, "16"]
    bad["verdict"]["label"] = "agrees"
    bad["ours"]["branching"] = True  # (a bool is not an integer here)
    assert report_schema.validate(bad) == [
        "report.seed: missing", "report.resolution[1]: str, not integer",
        "report.ours.branching: bool, not integer", f"report.verdict.label: 'agrees' is none of "
        f"{[metrics.SAME_PATHS, metrics.AGREES, metrics.DIFFERS, metrics.SAME_SEED_DIFFERS]}"]


def test_the_reference_page_lists_every_field():
    page = report_schema.markdown()
    for field in ("`scene`", "`verdict.label`", "`verdict.same_seed.frac_within`", "`ours.branching`",
                  "`metrics.rmse`"):
        assert field in page, field
