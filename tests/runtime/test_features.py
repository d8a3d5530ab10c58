"""The scene-adaptive pipeline: features a scene does not need are left out, visibly, and without changing the image."""
from __future__ import annotations

import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.cli import main

SCENES = Path(__file__).resolve().parents[2] / "scenes"

POINT_LIT = """<scene version="3.0.0">
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/>
      <rfilter type="box"/></film>
    <sampler type="independent"><integer name="sample_count" value="8"/></sampler></sensor>
  <emitter type="point"><point name="position" x="1" y="2" z="3"/>
    <rgb name="intensity" value="30"/></emitter>
  <shape type="cube" id="block">
    <transform name="to_world"><rotate y="1" angle="30"/><scale value="0.8"/></transform></shape>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><translate z="-1"/><scale value="5"/></transform></shape>
</scene>"""


def _render(scene, **props):
    integ = mi.load_dict({"type": "layerbvh", "max_depth": 3, "traversal": "layer_sorted", **props})  # (3: for time)
    img = np.array(mi.render(scene, integrator=integ, spp=8, seed=2))
    return img, integ.last_stats.features.as_dict()


def _left(features):
    return {f["feature"] for f in features["left_out"]}


@pytest.mark.parametrize("case", ["cbox", "point_lit", "sphere_box"])  # (sphere_box: one treelet, sort left out)
def test_left_out_features_do_not_change_the_image(case):
    if case == "point_lit":
        scene = mi.load_string(POINT_LIT)
        expect_left, expect_on = {"emitter_hits", "analytic_shapes"}, {"emitter_sampling"}
        props = {}
    elif case == "sphere_box":
        scene = testing.load(SCENES / "sphere_box.xml", (24, 24))
        # 12 triangles: one treelet
        expect_left, expect_on = {"sort"}, {"analytic_shapes", "emitter_hits", "emitter_sampling"}
        props = {}
    else:
        scene = testing.load(SCENES / "cbox.xml", (24, 24))
        expect_left, expect_on = {"analytic_shapes", "statistics"}, {"emitter_hits", "sort"}
        props = {"treelet_height": 2}  # 38 triangles: several treelets only when they are short
    img, feats = _render(scene, **props)
    assert expect_left <= _left(feats), feats
    assert expect_on <= set(feats["active"]), feats
    assert img.mean() > 0.01
    # Everything forced on (in a fresh integrator, so the BVH and plan are rebuilt): same pixels.
    full, full_feats = _render(scene, adaptive=False, stats=True, **props)
    assert not (_left(full_feats) - {"sort"}), full_feats
    assert np.array_equal(img, full), f"max |diff| {np.abs(img - full).max()}"


def test_statistics_only_when_asked(bunny):
    import layerbvh
    v, f = bunny
    rng = np.random.default_rng(0)
    o = (v.mean(0) + rng.normal(size=(2000, 3)) * 0.01).astype(np.float32)
    d = rng.normal(size=(2000, 3)).astype(np.float32)
    bvh = layerbvh.build(v, f)
    a = bvh.trace(o, d, stats=False)
    b = bvh.trace(o, d)
    assert np.array_equal(a.prim, b.prim) and np.array_equal(a.t, b.t)
    assert a.stats.inner_nodes == 0 and b.stats.inner_nodes > 2000


def test_report_lists_features(tmp_path):
    out = tmp_path / "cmp"
    assert main(["compare", str(SCENES / "cbox.xml"), "--spp", "2", "--res", "16", "16", "--out", str(out),
                 "--no-progress"]) == 0
    rep = json.loads((out / "report.json").read_text())
    feats = rep["features"]
    assert "emitter_sampling" in feats["active"]
    left = {f["feature"]: f["reason"] for f in feats["left_out"]}
    assert "analytic_shapes" in left and "sphere" in left["analytic_shapes"]
    # The timed render runs without work counters; the statistics come from a counted pass.
    assert "statistics" in left and rep["statistics_pass"]["spp"] == 2 and rep["traversal"]["inner_nodes"] > 0
