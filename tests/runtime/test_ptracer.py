"""`layerbvh_ptracer` (issue 43): light paths through our traversal against stock `ptracer`, same seed and
statistically, with a negative control; its settings and its light rays."""
from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401  (registers the integrators)
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.scene_integrator import path_settings

SCENES = Path(__file__).resolve().parents[2] / "scenes"
LAYER_HEIGHT = 2  # (as in test_mitsuba_backend: cbox at the default height is one treelet)


def _ptracer(scene_as, scene: str) -> Path:
    """The scene's ptracer version, at its max_depth."""
    return scene_as(scene, '<integrator type="ptracer"><integer name="max_depth" value="$max_depth"/></integrator>',
                    "ptracer")


def _ours(traversal: str) -> dict | None:
    return {"treelet_height": LAYER_HEIGHT} if traversal.startswith("layer_") else None


# The verdicts each scene may get. Same seed, a light ray meeting a shared edge may take the
# other triangle and splat elsewhere; whether it does depends on float rounding, which differs
# between CPUs (Embree's ISA path, Dr.Jit's LLVM vector width, FMA contraction): bunny_box
# layer_unsorted kept 99.61% of pixels within tolerance on an AVX-512 EPYC ("agrees", the
# statistical step decides) and 100% on an AVX2 EPYC ("same paths"; issue 64). Both are right,
# so both are accepted there. cbox has no edge a light path meets at these settings.
VERDICTS = {"cbox": {metrics.SAME_PATHS},
            "bunny_box": {metrics.SAME_PATHS, metrics.AGREES},
            "paper_mix": {metrics.SAME_PATHS, metrics.AGREES}}
# Power at the test's own settings (spp 8, 32x32): the statistical step there draws 16 spp per
# pixel and cannot see a 2% albedo change (issue 55), so an "agrees" alone would pass a wrong
# estimator. Same-seed paths that diverge at a few shared edges leave most pixels within
# tolerance (measured: bunny_box 99.6-100%, paper_mix 97.0%); a wrong estimator at the same seed
# leaves few (every reflectance x1.02: bunny_box 2.8%, paper_mix 11.0%). The bound sits far
# from both, so no CPU's rounding decides it.
MIN_SAME_SEED_FRAC = 0.9
SIZE = dict(spp=8, res=(32, 32))


def _ptracer_verdict(scene_as, name, traversal, ours_modify=None):
    return testing.verdict_vs_stock(_ptracer(scene_as, name), traversal=traversal, ours_props=_ours(traversal),
                                    ours_modify=ours_modify, **SIZE)


def _matches_stock(name, v) -> bool:
    """The test's criterion: a verdict this scene may get, and same-seed paths that diverged at a
    few edges at most (MIN_SAME_SEED_FRAC)."""
    return v.label in VERDICTS[name] and v.same_seed["values"]["frac_within"] >= MIN_SAME_SEED_FRAC


@pytest.mark.parametrize("name,traversal", [("cbox", "per_ray"), ("cbox", "layer_sorted"), ("cbox", "embree"),
                                            ("bunny_box", "layer_unsorted"), ("paper_mix", "auto")])
def test_ptracer_agrees_with_stock(scene_as, name, traversal):
    """The scene's ptracer version, stock `ptracer` against ours, the two-step
    verdict at its users' settings (the scene's max_depth). Same seed, stock's draws in stock's
    order: `embree` (our loop with Mitsuba's queries) gives stock's image to float noise, and our
    traversal the same paths on cbox. Where a light ray meets a shared edge, our traversal may
    return the other triangle, and that light path goes elsewhere and splats on other pixels;
    how many do is up to the CPU's rounding (VERDICTS), so the statistical step may decide."""
    v = _ptracer_verdict(scene_as, name, traversal)
    assert _matches_stock(name, v), f"{name} ({traversal}): {v.label}: {v.summary()}"
    same = v.same_seed["values"]
    assert same["mean_ref"] > 0.01, "the scene should not render black"
    if traversal == "embree":
        assert same["max_abs"] < 1e-4, same


def test_ptracer_agreement_has_power_at_its_settings(scene_as):
    """Negative control of the test above at its own settings (bunny_box, layer_unsorted, spp 8,
    32x32): ours with every reflectance 2% brighter must fail its criterion."""
    v = _ptracer_verdict(scene_as, "bunny_box", "layer_unsorted", ours_modify=testing.scaled_reflectances(1.02))
    assert not _matches_stock("bunny_box", v), f"a 2% brighter scene passed: {v.label}: {v.summary()}"


def test_ptracer_layer_path_ran(scene_as, layer_path_ran):
    """The layer modes really trace ptracer's light paths in wavefront steps."""
    scene = testing.load(_ptracer(scene_as, "cbox"), (16, 16))
    integ = mi.load_dict({"type": "layerbvh_ptracer", "traversal": "layer_sorted", "treelet_height": LAYER_HEIGHT})
    img = np.array(mi.render(scene, integrator=integ, spp=4, seed=1))
    assert np.isfinite(img).all() and img.mean() > 0.01
    layer_path_ran(integ.last_stats, "layer_sorted")


def test_ptracer_statistical_step_catches_a_2_percent_albedo_change(scene_as):
    """Negative control of the verdict's second step for an adjoint integrator (moments from
    independent renders, verdict.MOMENT_RENDERS): ours with the floor 2% brighter must fail,
    and the same configuration passes unchanged."""
    def brighter_floor(params):
        key = "FloorBSDF.brdf_0.reflectance.value"
        params[key] = params[key] * 1.02
    kw = {"spp": 16384, "res": (6, 6)}
    same = testing.independent_seeds_vs_stock(_ptracer(scene_as, "cbox"), **kw)
    assert same.passed, same.family.summary()
    off = testing.independent_seeds_vs_stock(_ptracer(scene_as, "cbox"), modify=brighter_floor, **kw)
    assert not off.passed, off.family.summary()


def test_ptracer_settings_come_from_the_scene(tmp_path):
    """compare renders both sides with the scene's ptracer settings: depths from the loaded
    integrator, hide_emitters and samples_per_pass from the XML (an adjoint integrator states
    neither)."""
    path = tmp_path / "scene.xml"
    path.write_text("""<scene version="3.0.0">
        <integrator type="ptracer"><integer name="max_depth" value="3"/><integer name="rr_depth" value="2"/>
            <boolean name="hide_emitters" value="true"/><integer name="samples_per_pass" value="2"/></integrator>
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
            <integer name="height" value="8"/></film></sensor>
        <shape type="sphere"/><emitter type="constant"/></scene>""")
    s = path_settings(mi, mi.load_file(str(path)), scene_path=path)
    assert s.estimator == "ptracer" and s.ours_type == "layerbvh_ptracer"
    assert s.props == {"max_depth": 3, "rr_depth": 2, "hide_emitters": True, "samples_per_pass": 2}, s.props


def test_ptracer_refuses_bad_settings():
    """Stock's rules, stock's words (the adjoint base checks them)."""
    for bad in ({"max_depth": -2}, {"rr_depth": 0}):
        with pytest.raises(Exception, match="depth"):
            mi.load_dict({"type": "layerbvh_ptracer", **bad})


def test_light_rays_are_recorded_and_replayed_exactly():
    """`record_rays --light` (or a ptracer scene) keeps a particle tracer's light rays (kind
    "light") and its sensor connections ("shadow"), no camera rays; the locality model's replay
    follows the kernel on them exactly (hits, work, loads and stores per ray)."""
    from layerbvh_mitsuba.tools.bench.record_rays import record_scene
    import layerbvh
    from layerbvh import locality
    from layerbvh.memmodel import preset
    rec = record_scene(mi, SCENES / "bunny_box.xml", (16, 16), 2, 0, 4000, light=True)
    assert rec.recorder.count["light"] == 4000 and rec.recorder.count["shadow"] > 0
    assert rec.recorder.count["camera"] == 0 and rec.meta["integrator"]["type"] == "ptracer"
    o, d, tmax = rec.recorder.arrays("light")
    bvh = layerbvh.build(rec.vertices, rec.faces, treelet_height=3, batch_rays=len(o), tail_rays=64,
                         tail_fraction=0.02, tail_steps=32)
    rep = locality.replay_tree(bvh, o, d, tmax, "layer_sorted", False, 32, preset("gtx965m"))
    chk = locality.check_trace(bvh, o, d, tmax, False, rep)
    assert chk.exact, chk
    assert (rep.prim != layerbvh.MISS).mean() > 0.5 and rep.kernels > 2
