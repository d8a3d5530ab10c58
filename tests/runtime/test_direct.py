"""`direct` scenes through our traversal: `layerbvh_direct` against stock `direct` at the same seed and at
independent seeds, on multi-shape scenes, in the megakernel and the wavefront path."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.render import use_variant

SAMPLES = {"default": "", "2e3b": '<integer name="emitter_samples" value="2"/><integer name="bsdf_samples" value="3"/>',
           "bsdf_only": '<integer name="emitter_samples" value="0"/>',
           "hidden": '<boolean name="hide_emitters" value="true"/>'}


def _direct(scene_as, scene: str, samples: str = "default") -> Path:
    return scene_as(scene, f'<integrator type="direct">{SAMPLES[samples]}</integrator>', "direct")


# Every traversal on the Cornell box; each sample setting and the multi-shape scenes in one mode
# each (the megakernel and the wavefront path both among them): a case is a few new kernels.
CASES = [("cbox", "default", "per_ray"), ("cbox", "default", "layer_sorted"), ("cbox", "default", "embree"),
         ("cbox", "2e3b", "layer_sorted"), ("cbox", "bsdf_only", "per_ray"), ("cbox", "hidden", "layer_sorted"),
         ("paper_mix", "default", "layer_sorted"), ("glass_mirror", "2e3b", "per_ray")]


def test_the_bsdf_draw_order_is_probed_from_the_wheel(scene_as, monkeypatch, tmp_path):
    """Issue 55: ours drew a BSDF sample's 2D number before its 1D one because GCC, which builds
    Mitsuba's wheels, evaluates `bsdf->sample(..., next_1d(), next_2d())` right to left; a wheel
    built otherwise would break every same-seed comparison of direct, ptracer and volpath
    silently. The order is now probed from the wheel (an empty cache: the probe runs here), and
    it is the one that matters: with it ours equals stock at the same seed, with the other order
    it does not."""
    from layerbvh_mitsuba.runtime import draw_order  # local: its cache is reset below
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(draw_order, "_answer", None)
    probed = draw_order.bsdf_2d_first()
    assert list((tmp_path / "cache" / "layerbvh" / "draw_order").glob("*.json")), "the answer was not kept"
    path = _direct(scene_as, "cbox", "bsdf_only")  # every vertex's light through a BSDF sample
    right = testing.same_seed(path, 4, (16, 16), 0, "per_ray", metrics.SAME_SEED_TOL, None)
    assert right.passed, right.summary()
    monkeypatch.setattr(draw_order, "_answer", not probed)
    wrong = testing.same_seed(path, 4, (16, 16), 0, "per_ray", metrics.SAME_SEED_TOL, None)
    assert not wrong.passed and wrong.mean_abs > 0.2 * wrong.mean_ref, wrong.summary()  # (measured 0.77 of it)


@pytest.mark.parametrize("scene,samples,traversal", CASES)
def test_direct_matches_stock_direct_at_the_same_seed(scene_as, scene, samples, traversal, layer_path_ran):
    """Every sample drawn in stock's order (its BSDF sample's next_1d and next_2d are arguments of
    one call, drawn in the order the wheel's compiler evaluates them: runtime/draw_order.py),
    every query ours."""
    layer = traversal.startswith("layer_")
    r = testing.assert_matches_stock(_direct(scene_as, scene, samples), spp=8, res=(32, 32), traversal=traversal,
                                     ours_props={"treelet_height": 2} if layer else None)
    assert r.ours_stats.traversal == traversal and r.ours_stats.bounces in (None, 1)
    if layer:
        layer_path_ran(r.ours_stats, traversal)


def test_the_comparison_is_against_direct(scene_as):
    """Negative control: our path tracer on the direct scene is not stock direct's image, so the
    test above compares estimators that could differ."""
    path = _direct(scene_as, "cbox")
    scene = testing.load(path, (32, 32))
    stock = np.array(mi.render(scene, integrator=mi.load_dict({"type": "direct"}), spp=8, seed=0))
    ours_path = np.array(mi.render(scene, integrator=mi.load_dict({"type": "layerbvh", "traversal": "per_ray"}),
                                   spp=8, seed=0))
    assert not metrics.same_seed_verdict(stock, ours_path)["passed"]


# The independent-seed test's settings for direct, shared with its negative control (issue 55:
# a control at the positive test's own settings).
DIRECT_Z = dict(spp=4096, res=(6, 6), traversal="layer_sorted", ours_props={"treelet_height": 2})


def test_direct_passes_the_independent_seed_test(scene_as):
    r = testing.assert_statistically_matches_stock(_direct(scene_as, "paper_mix"), **DIRECT_Z)
    assert r.pixels == 36 and r.ours_stats.loop == "wavefront"


def test_direct_independent_seed_test_has_the_power_it_states(scene_as):
    """Negative control at the settings above. Alone, the independent-seed test there rules out a
    bias of 7.4% of the image mean (its stated MDE, measured; paper_mix's glass makes direct
    light noisy), so every reflectance 2% higher passes it: a 2% bias is the same-seed test's to
    see (test_direct_matches_stock_direct_at_the_same_seed fails it on most pixels). What the
    test states it must keep: 10% higher is rejected."""
    same = testing.independent_seeds_vs_stock(_direct(scene_as, "paper_mix"), **DIRECT_Z)
    assert same.family.power()["image"] < 0.1, same.family.power()
    r = testing.independent_seeds_vs_stock(_direct(scene_as, "paper_mix"), modify=testing.scaled_reflectances(1.10),
                                          **DIRECT_Z)
    assert not r.passed, r.family.summary()


def test_direct_settings_are_checked_by_name():
    use_variant()
    with pytest.raises(Exception, match="shading_samples, or emitter_samples"):
        mi.load_dict({"type": "layerbvh_direct", "shading_samples": 2, "emitter_samples": 1})
    with pytest.raises(Exception, match="at least one emitter or BSDF sample"):
        mi.load_dict({"type": "layerbvh_direct", "emitter_samples": 0, "bsdf_samples": 0})


def test_direct_matches_stock_in_the_spectral_and_mono_variants(scene_as):
    """In its own process (the variant is process-wide): same seed, per_ray and layer_sorted."""
    scene = _direct(scene_as, "cbox", "2e3b")
    code = f"""
import mitsuba as mi, numpy as np
for v in ("llvm_ad_spectral", "llvm_ad_mono"):
    mi.set_variant(v)
    import layerbvh_mitsuba
    from layerbvh_mitsuba.ab import metrics
    scene = mi.load_file({str(scene)!r}, resx=24, resy=24)
    stock = np.array(mi.render(scene, integrator=mi.load_dict({{"type": "direct", "emitter_samples": 2,
                                                                 "bsdf_samples": 3}}), spp=8, seed=1))
    for t in ("per_ray", "layer_sorted"):
        ours = mi.load_dict({{"type": "layerbvh_direct", "emitter_samples": 2, "bsdf_samples": 3, "traversal": t,
                              "treelet_height": 2}})
        img = np.array(mi.render(scene, integrator=ours, spp=8, seed=1))
        print(v, t, img.shape[-1], metrics.same_seed_verdict(stock, img)["passed"])
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = re.findall(r"(llvm_\w+) (\w+) (\d) (\w+)", p.stdout)  # (Mitsuba logs there too)
    assert [(v, t, ok) for v, t, _, ok in lines] == [(v, t, "True") for v in ("llvm_ad_spectral", "llvm_ad_mono")
                                                     for t in ("per_ray", "layer_sorted")], p.stdout
    assert [c for _, _, c, _ in lines] == ["3", "3", "1", "1"]  # RGB out of spectral, luminance in mono
