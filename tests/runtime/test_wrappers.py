"""Scenes whose integrator is an `aov` or `moment` wrapper around `path` or `direct`: kept on both sides (stock's
estimator inside on one, ours on the other), compared on their radiance, the wrapper's own channels from our hits."""
from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.compare import CompareSettings, compare
from layerbvh_mitsuba.ab.render import render_passes, use_variant
from layerbvh_mitsuba.ab.scene_integrator import path_settings
from layerbvh_mitsuba.cli import main
from layerbvh_mitsuba.runtime.settings import Traversal

CBOX = Path(__file__).resolve().parents[2] / "scenes" / "cbox.xml"
PATH = '<integrator type="path">\n        <integer name="max_depth" value="$max_depth"/>\n    </integrator>'
WRAPPED = {
    "moment": f'<integrator type="moment">{PATH}</integrator>',
    "aov": f'<integrator type="aov"><string name="aovs" value="dd.y:depth,nn:sh_normal"/>{PATH}</integrator>',
    "moment_aov": f'<integrator type="moment"><integrator type="aov"><string name="aovs" value="dd.y:depth"/>'
                  f'{PATH}</integrator></integrator>',
    "moment_direct": '<integrator type="moment"><integrator type="direct"/></integrator>',
}
NAMES = {"moment": "moment(path)", "aov": "aov(path)", "moment_aov": "moment(aov(path))",
         "moment_direct": "moment(direct)"}


def _scene(tmp_path, wrapper: str) -> Path:
    text = CBOX.read_text()
    assert PATH in text
    out = tmp_path / f"cbox_{wrapper}.xml"
    out.write_text(text.replace(PATH, WRAPPED[wrapper]))
    return out


@pytest.mark.parametrize("wrapper", list(WRAPPED))
def test_a_wrapped_path_scene_compares_with_its_wrapper_on_both_sides(tmp_path, wrapper, layer_path_ran):
    """No --as-path: both sides keep the wrapper; our layerbvh ran inside it (its statistics, the
    layer path at treelet height 2) and its radiance is stock's, same seed."""
    c = compare(use_variant(), CompareSettings(scene=_scene(tmp_path, wrapper), res=(32, 32), spp=8,
                                                       traversal=Traversal.parse("layer_sorted"), treelet_height=2))
    assert c.path.wrapper is not None and c.path.scene_integrator == NAMES[wrapper]
    assert c.info()["compared_as"] == NAMES[wrapper]
    assert c.path.props.get("max_depth", 8) == 8 and c.path.estimator == NAMES[wrapper].rstrip(")").split("(")[-1]
    assert c.verdict.label == metrics.SAME_PATHS, c.verdict.summary()
    layer_path_ran(c.stats, "layer_sorted")


def test_the_wrappers_own_channels_come_from_our_hits(tmp_path):
    """`layerbvh render` of an aov(path) scene writes the wrapper's channels (depth, normals) as
    stock's own integrator does, from our hits: they equal stock's at the same seed."""
    scene_path = _scene(tmp_path, "aov")
    out = tmp_path / "ours.exr"
    assert main(["render", str(scene_path), "--res", "24", "24", "--spp", "4", "--traversal", "per_ray", "-o",
                 str(out), "--no-progress"]) == 0
    ours = np.array(mi.Bitmap(str(out)), np.float32)
    mi_ = use_variant()
    scene = testing.load(scene_path, (24, 24))
    stock, _ = render_passes(mi_, scene, scene.integrator(), 4, 0, "stock", False)
    assert ours.shape == stock.shape and ours.shape[-1] == 7, (ours.shape, stock.shape)  # RGB, depth, normal
    extra = ours[..., 3:] - stock[..., 3:]
    assert np.mean(np.abs(extra).max(-1) <= 1e-3) >= 0.999, np.abs(extra).max()
    assert metrics.same_seed_verdict(stock, ours)["passed"]


def test_a_wrapper_around_an_integrator_we_do_not_mirror_is_still_refused(tmp_path):
    text = CBOX.read_text().replace(PATH, '<integrator type="moment"><integrator type="prb"/></integrator>')
    scene_path = tmp_path / "prb.xml"
    scene_path.write_text(text)
    mi_ = use_variant()
    with pytest.raises(Exception, match=r"moment\(prb\)"):
        path_settings(mi_, testing.load(scene_path, (8, 8)), scene_path=scene_path)


def test_a_wrapper_from_an_included_file_is_read(tmp_path):
    """Mitsuba's test scenes state their `moment` wrapper in an <include>d fragment: it is found
    where it stands, and the comparison keeps it."""
    (tmp_path / "fragment.xml").write_text('<scene version="3.0.0"><integrator type="moment">'
                                           '<integrator type="path"><integer name="max_depth" value="3"/>'
                                           '</integrator></integrator></scene>')
    scene_path = tmp_path / "main.xml"
    scene_path.write_text(CBOX.read_text().replace(PATH, '<include filename="fragment.xml"/>'))
    mi_ = use_variant()
    path = path_settings(mi_, testing.load(scene_path, (8, 8)), scene_path=scene_path)
    assert path.wrapper is not None and path.compared_as == "moment(path)" and path.props["max_depth"] == 3


def test_a_wrapper_in_a_nested_include_is_found_where_mitsuba_finds_it(tmp_path):
    """An included file includes another by a name relative to the scene's folder (as Mitsuba's
    media scenes do with include/preamble.xml): Mitsuba finds it there, so must we (before, the
    wrapper was looked for next to the including file, not found, and the scene refused)."""
    (tmp_path / "include").mkdir()
    (tmp_path / "include" / "base.xml").write_text('<scene version="3.0.0"><include filename="include/integ.xml"/>'
                                                   '</scene>')
    (tmp_path / "include" / "integ.xml").write_text('<scene version="3.0.0"><integrator type="moment">'
                                                    '<integrator type="path"/></integrator></scene>')
    scene_path = tmp_path / "main.xml"
    scene_path.write_text(CBOX.read_text().replace(PATH, '<include filename="include/base.xml"/>'))
    path = path_settings(use_variant(), testing.load(scene_path, (8, 8)), scene_path=scene_path)
    assert path.wrapper is not None and path.compared_as == "moment(path)"
