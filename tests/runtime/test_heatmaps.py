"""Traversal-cost heat maps: per-pixel work that sums to the traversal statistics' totals, and shows where a scene is
expensive."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.repo import SCENES

SPP = 4


def _counted(scene_name, traversal, res=(40, 32)):
    scene = testing.load(SCENES / f"{scene_name}.xml", res)
    integ = mi.load_dict({"type": "layerbvh", "traversal": traversal, "stats": True, "treelet_height": 4})
    mi.render(scene, integrator=integ, spp=SPP, seed=0)
    return integ.heatmaps(scene), integ.last_stats


@pytest.mark.parametrize("traversal", ["per_ray", "layer_sorted"])
def test_heat_maps_sum_to_the_totals(traversal):
    maps, st = _counted("bunny_box", traversal)
    expected = {"camera_inner", "camera_triangles", "path_inner", "path_triangles"}
    assert expected | ({"path_steps"} if traversal == "layer_sorted" else set()) == set(maps)
    for m in maps.values():
        assert m.shape == (32, 40)
    # Mean per sample times samples per pixel, summed over pixels: every counted unit once.
    assert round(maps["path_inner"].sum() * SPP) == st.inner_nodes
    assert round(maps["path_triangles"].sum() * SPP) == st.triangles
    assert (maps["camera_inner"] <= maps["path_inner"]).all() and maps["camera_inner"].sum() > 0
    if traversal == "layer_sorted":
        assert maps["path_steps"].min() >= 1 and maps["path_steps"].sum() * SPP > st.queries


def test_a_bunny_costs_more_than_an_empty_box():
    empty, _ = _counted("empty_box", "per_ray")
    bunny, _ = _counted("bunny_box", "per_ray")
    # (over 2x with the binary tree; 1.9x measured with the default 4-wide one, whose nodes each
    # stand for two binary levels: the bunny adds fewer, wider node visits)
    assert bunny["camera_inner"].mean() > 1.6 * empty["camera_inner"].mean()
    # ... and where the bunny is: the busiest tenth of the pixels are far above the box's walls.
    cam = bunny["camera_inner"]
    assert np.percentile(cam, 95) > 3 * np.median(cam)
