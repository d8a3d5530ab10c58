"""`depth` scenes through our traversal: `layerbvh_depth` (the estimator added as one file plus one registry line,
issue 42) against stock `depth` at the same seed, on multi-shape scenes, in the megakernel and the wavefront path,
through `compare`."""
from __future__ import annotations

import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.cli import main


def _depth(scene_as, scene: str) -> Path:
    return scene_as(scene, '<integrator type="depth"/>', "depth")


@pytest.mark.parametrize("scene,traversal", [("cbox", "per_ray"), ("paper_mix", "layer_sorted"),
                                             ("instanced_bunnies", "layer_sorted")])
def test_depth_matches_stock_depth_at_the_same_seed(scene_as, scene, traversal, layer_path_ran):
    layer = traversal.startswith("layer_")
    r = testing.assert_matches_stock(_depth(scene_as, scene), spp=4, res=(32, 32), traversal=traversal,
                                     ours_props={"treelet_height": 2} if layer else None)
    assert r.ours_stats.traversal == traversal and r.ours_stats.bounces in (None, 1)
    if layer:
        layer_path_ran(r.ours_stats, traversal)


def test_the_comparison_is_against_depth(scene_as):
    """Negative control: the depth image is distances (far above radiance on these scenes), and
    our path tracer on the depth scene is not it."""
    scene = testing.load(_depth(scene_as, "cbox"), (32, 32))
    stock = np.array(mi.render(scene, integrator=mi.load_dict({"type": "depth"}), spp=4, seed=0))
    ours = np.array(mi.render(scene, integrator=mi.load_dict({"type": "layerbvh_depth", "traversal": "per_ray"}),
                              spp=4, seed=0))
    assert stock.mean() > 1.0 and np.allclose(stock[..., 0], stock[..., 1])
    assert metrics.same_seed_verdict(stock, ours)["passed"]
    ours_path = np.array(mi.render(scene, integrator=mi.load_dict({"type": "layerbvh", "traversal": "per_ray"}),
                                   spp=4, seed=0))
    assert not metrics.same_seed_verdict(stock, ours_path)["passed"]


def test_compare_takes_a_depth_scene(scene_as, tmp_path):
    """The command line compares it as what it is: no refusal, no --as-path."""
    out = tmp_path / "cmp"
    assert main(["compare", str(_depth(scene_as, "cbox")), "--res", "16", "16", "--spp", "2", "--traversal",
                 "per_ray", "--no-progress", "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["verdict"]["passed"] and rep["scene_integrator"] == "depth", rep["verdict"]
