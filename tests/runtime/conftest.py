"""The Mitsuba runtime's tests: Mitsuba's variant, the check that an image test of a layer mode
really ran the layer path, and our scenes rewritten for another integrator."""
from __future__ import annotations

import re
from pathlib import Path

import mitsuba as mi
import pytest

mi.set_variant("llvm_ad_rgb")

SCENES = Path(__file__).resolve().parents[2] / "scenes"


def _layer_path_ran(stats: dict, mode: str) -> None:
    """An image test of a layer mode really ran the layer path, from the integrator's last_stats:
    the wavefront bounce loop, every query in `mode`, a BVH of more than one treelet, and more
    than one wavefront step per query on average. A fallback to per_ray, or a BVH of one treelet
    (cbox at the default treelet height 8), takes at most one step per query (measured there:
    15 steps for 17 queries, a query with no ray left takes none); cbox at height 3 takes 3.6."""
    assert stats.loop == "wavefront", stats.loop
    assert set(stats.modes_used) == {mode}, stats.modes_used
    assert stats.bvh.treelets > 1, "one treelet: the layer modes cannot differ from per_ray"
    assert stats.wavefront_steps > stats.queries, \
        f"{stats.wavefront_steps} wavefront steps for {stats.queries} queries: the wavefront path did not run"


@pytest.fixture(scope="session")
def layer_path_ran():
    """assert layer_path_ran(integrator.last_stats, "layer_sorted"): see _layer_path_ran."""
    return _layer_path_ran


@pytest.fixture
def scene_as(tmp_path):
    """scene_as(scene, integrator, tag): scenes/<scene>.xml with its `path` integrator element
    replaced by the XML `integrator`, written to tmp_path as <scene>_<tag>.xml (the depth, direct,
    volpath and ptracer versions of our scenes). scenes/ goes on Mitsuba's file resolver, so the
    copy still finds its meshes."""
    def make(scene: str, integrator: str, tag: str) -> Path:
        text, n = re.subn(r'<integrator type="path">.*?</integrator>', integrator,
                          (SCENES / f"{scene}.xml").read_text(), count=1, flags=re.S)
        assert n == 1, f"{scene}.xml: no path integrator to replace"
        mi.file_resolver().prepend(str(SCENES))
        out = tmp_path / f"{scene}_{tag}.xml"
        out.write_text(text)
        return out
    return make
