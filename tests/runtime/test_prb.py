"""`layerbvh_prb`, `layerbvh_prb_basic` and `layerbvh_prbvolpath` (issue 43): Mitsuba's differentiable path tracers
through our traversal, against stock at the same seed in primal mode and in their derivatives (forward and backward),
with the gradient verdict's statistical step and its negative controls."""
from __future__ import annotations

import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401  (registers the integrators)
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab import gradient, metrics, report_schema
from layerbvh_mitsuba.ab.render import UserError
from layerbvh_mitsuba.ab.scene_integrator import path_settings

SCENES = Path(__file__).resolve().parents[2] / "scenes"
LAYER_HEIGHT = 2  # (cbox at the default height is one treelet)
# The two parameters differentiated per scene: a BSDF's reflectance and the emitter's radiance.
# A material, a light, and a geometric key (issue 55): the bunny's vertex positions (forward: every
# coordinate at once, a move along (1, 1, 1)), whose derivative needs the replay's area Jacobian
# and turned direction (replay.reattached_reflection; without the Jacobian ours is off by up to
# 15 against 10.8 at the same seed).
# And a roughness (issue 55 item 6): the rough gold of paper_mix, GGX alpha 0.4, whose derivative
# flows through the microfacet distribution's sampling and evaluation alike (measured: -16.43 at
# the same seed on both sides).
PARAMS = {"cbox": ("LeftWallBSDF.brdf_0.reflectance.value", "Light.emitter.radiance.value"),
          "bunny_box": ("red.reflectance.value", "bunny.vertex_positions"),
          "paper_mix": ("gold_bsdf.alpha.value",)}


def _as(scene_as, scene: str, integrator: str) -> Path:
    """The scene's version rendered by `integrator` (prb, prb_basic, prbvolpath), 6 vertices at most."""
    return scene_as(scene, f'<integrator type="{integrator}"><integer name="max_depth" value="6"/></integrator>',
                    integrator)


def _ours(traversal: str) -> dict | None:
    return {"treelet_height": LAYER_HEIGHT} if traversal.startswith("layer_") else None


@pytest.mark.parametrize("integrator,name,traversal", [
    ("prb", "cbox", "layer_sorted"), ("prb", "bunny_box", "per_ray"), ("prb", "paper_mix", "auto"),
    ("prb_basic", "cbox", "per_ray"), ("prb_basic", "bunny_box", "layer_unsorted"), ("prb_basic", "paper_mix", "auto"),
    ("prbvolpath", "cbox", "layer_sorted"), ("prbvolpath", "bunny_box", "auto"),
    ("prbvolpath", "paper_mix", "per_ray")])
def test_primal_same_seed_as_stock(scene_as, integrator, name, traversal):
    """Primal mode, same seed: every draw in stock's order, every query ours, so the image
    equals stock's to float noise. On paper_mix a path meeting a shared edge of the glass may
    take the other triangle: prb there leaves one pixel of 1024 outside the tolerance on AVX-512
    and with LAYERBVH_LLVM_ISA=avx2 (docs/cpu_margins/table.json), exactly the default
    criterion's room, so another CPU may fail it by one pixel (issue 64): paper_mix gets 1% (ten
    pixels). One such pixel also moves the mean: a fresh clone on an AVX2 machine had prbvolpath's
    single diverged pixel off by 1.87, a mean |diff| of 1.1e-3 of the mean pixel against the
    default 1e-4 (three runs before it: none). paper_mix's mean criterion is 2e-3 (two such
    pixels); every reflectance x1.02 still fails it (measured above 3e-3:
    test_primal_negative_control_at_the_primal_settings)."""
    room = {"min_frac": 0.99, "max_mean_rel": 2e-3} if name == "paper_mix" else {}
    r = testing.assert_matches_stock(_as(scene_as, name, integrator), spp=8, res=(32, 32), traversal=traversal,
                                     ours_props=_ours(traversal), **room)
    assert r.compared_as == integrator and r.mean_ref > 0.01, (r.compared_as, r.summary())
    if traversal.startswith("layer_"):
        assert r.ours_stats.loop == "wavefront" and r.ours_stats.wavefront_steps > r.ours_stats.queries


@pytest.mark.parametrize("integrator,name,traversal", [
    ("prb", "bunny_box", "per_ray"), ("prb_basic", "cbox", "layer_sorted"), ("prbvolpath", "paper_mix", "per_ray")])
def test_primal_negative_control_at_the_primal_settings(scene_as, integrator, name, traversal):
    """Issue 55 item 3: the primal test's criterion, at its own size, spp and depth, fails ours
    with every reflectance 2% higher (one scene per integrator), so its "same paths" has power."""
    r = testing.same_seed(_as(scene_as, name, integrator), spp=8, res=(32, 32), traversal=traversal,
                          ours_props=_ours(traversal), ours_modify=testing.scaled_reflectances(1.02))
    assert r.compared_as == integrator and not r.passed and r.mean_abs > 3e-3 * r.mean_ref, r.summary()


@pytest.mark.parametrize("integrator,name,traversal", [
    ("prb", "cbox", "layer_sorted"), ("prb", "bunny_box", "per_ray"), ("prb", "paper_mix", "per_ray"),
    ("prb_basic", "cbox", "per_ray"), ("prb_basic", "bunny_box", "layer_sorted")])
def test_gradients_same_seed_as_stock(scene_as, integrator, name, traversal):
    """Forward (an image) and backward (the parameter's gradient) derivatives with respect to
    two parameters equal stock's at the same seed, to float tolerance (the image criterion).
    In the wavefront loop forward mode must keep the parameters' gradients across vertices
    (replay.propagate)."""
    scene_path = _as(scene_as, name, integrator)
    scene = testing.load(scene_path, (24, 24))
    stock = mi.load_dict({"type": integrator, "max_depth": 6})
    ours = mi.load_dict({"type": f"layerbvh_{integrator}", "max_depth": 6, "traversal": traversal,
                         **(_ours(traversal) or {})})
    for key in PARAMS[name]:
        s = gradient.gradients(mi, scene, stock, key, 8, 3, forward=True)
        o = gradient.gradients(mi, scene, ours, key, 8, 3, forward=True)
        same = gradient.same_seed(s, o)
        if key.endswith("vertex_positions"):
            # A vertex's gradient sums many paths' contributions through atomic adds whose order
            # differs between runs: float32 rounding of ~1e-3 absolute on gradients up to ~30
            # (measured 0.0015), which the per-component criterion (1e-3 x max(1, |stock|))
            # does not allow below 1. Judged against the gradient's scale instead: measured
            # 5e-5 of it; without the replay's area Jacobian 0.39.
            assert same["forward"]["passed"], (key, same["forward"])
            scale = np.abs(s.backward).max()
            err = np.abs(o.backward - s.backward).max()
            assert err <= 1e-3 * scale, (key, err, scale)
        else:
            assert same["passed"], (key, same)
        assert np.abs(s.forward).max() > 1e-3 and np.abs(s.backward).max() > 1.0, key  # not a vacuous 0 = 0


def test_prbvolpath_in_media_same_seed_and_backward(tmp_path):
    """prbvolpath on one of Mitsuba's homogeneous-media test scenes (a medium with a null
    boundary, an area light): the primal image and the backward gradients of the medium's
    albedo and extinction equal stock's at the same seed, in the megakernel and between kernels.
    Forward mode is refused, as stock refuses it."""
    scene = testing.load(SCENES / "media" / "test_homo_area_light_volpath.xml", (8, 8))
    stock = mi.load_dict({"type": "prbvolpath", "max_depth": 6})
    a = np.array(mi.render(scene, integrator=stock, spp=8, seed=3))
    for traversal, keys in (("per_ray", ("medium1.albedo.value.value", "medium1.sigma_t.value.value")),
                            ("layer_sorted", ("medium1.albedo.value.value",))):
        ours = mi.load_dict({"type": "layerbvh_prbvolpath", "max_depth": 6, "traversal": traversal,
                             "treelet_height": LAYER_HEIGHT})
        b = np.array(mi.render(scene, integrator=ours, spp=8, seed=3))
        assert metrics.same_seed_verdict(a, b)["passed"], traversal
        for key in keys:
            s = gradient.gradients(mi, scene, stock, key, 8, 3, forward=False)
            o = gradient.gradients(mi, scene, ours, key, 8, 3, forward=False)
            assert gradient.same_seed(s, o)["passed"], (traversal, key, s.backward, o.backward)
            assert np.abs(s.backward).max() > 1.0
    with pytest.raises(Exception, match="forward"):
        gradient.gradients(mi, scene, ours, "medium1.albedo.value.value", 4, 3, forward=True)


def test_a_textured_area_emitter_differentiates_as_stock_in_the_wavefront_loop(scene_as, tmp_path):
    """Issue 55 item 6: the cbox light's radiance a 4x4 bitmap (raw, nearest), differentiated with
    respect to its texels in the wavefront loop (layer_sorted). The texture's lookups read an
    array derived from the texels (an interior AD node made when the scene updates, outside the
    render's isolate_grad scope): pushed per vertex with its edges cleared, only the first vertex
    reached the texels (measured: forward 12.26 against stock's 16.19, 495 of 576 pixels off;
    replay.propagate). Forward and backward equal stock's at the same seed."""
    rng = np.random.default_rng(0)
    texels = np.array([17, 12, 4], np.float32) * rng.uniform(0.3, 1.7, (4, 4, 1)).astype(np.float32)
    mi.Bitmap(texels).write(str(tmp_path / "radiance.exr"))
    path = _as(scene_as, "cbox", "prb")
    text = path.read_text()
    assert text.count('<rgb name="radiance" value="17, 12, 4"/>') == 1
    path.write_text(text.replace('<rgb name="radiance" value="17, 12, 4"/>',
                                 '<texture type="bitmap" name="radiance">'
                                 f'<string name="filename" value="{tmp_path / "radiance.exr"}"/>'
                                 '<boolean name="raw" value="true"/>'
                                 '<string name="filter_type" value="nearest"/></texture>'))
    scene = testing.load(path, (24, 24))
    key = "Light.emitter.radiance.data"
    stock = mi.load_dict({"type": "prb", "max_depth": 6})
    ours = mi.load_dict({"type": "layerbvh_prb", "max_depth": 6, "traversal": "layer_sorted",
                         "treelet_height": LAYER_HEIGHT})
    s = gradient.gradients(mi, scene, stock, key, 8, 3, forward=True)
    o = gradient.gradients(mi, scene, ours, key, 8, 3, forward=True)
    assert gradient.same_seed(s, o)["passed"], (s.forward.sum(), o.forward.sum(), s.backward.sum(), o.backward.sum())
    assert s.backward.size == 4 * 4 * 3 and np.count_nonzero(s.backward) >= 24  # (texels reached: not a vacuous 0 = 0)


@pytest.mark.parametrize("key,control", [
    ("LeftWallBSDF.brdf_0.reflectance.value", "light"),   # d image / d reflectance scales with the light
    ("Light.emitter.radiance.value", "reflectances")])    # ... / d radiance with every reflectance
def test_gradient_statistical_step_and_its_negative_control(scene_as, key, control):
    """The gradient verdict's second step (gradient.GRAD_SAMPLES a side over verdict.MOMENT_RENDERS
    render pairs, stock and ours at the same seed in a pair; a paired t-test per pixel, per
    component and of their sums) passes ours against stock and fails ours with a parameter 2%
    off: the light 2% brighter for a reflectance's gradient, every reflectance 2% higher for the
    light's. Forward and backward. Stock's renders are reused by the control, for the suite's
    time. (Welch's test over independent seeds needed 2^20 samples a side for these controls,
    47 + 34 s of the suite on an AVX2 machine; mutation gradient_step_not_paired.)"""
    def off(params):
        for k in params.keys():
            if (control == "light" and k.endswith("radiance.value")) or \
                    (control == "reflectances" and k.endswith("reflectance.value")):
                params[k] = params[k] * 1.02
    path = _as(scene_as, "cbox", "prb")
    args = (mi, path, (8, 8), {"type": "prb", "max_depth": 6}, {"type": "layerbvh_prb", "max_depth": 6}, key, True)
    same = gradient.statistical_step(*args)
    assert same.passed, same
    bad = gradient.statistical_step(*args, ours_modify=off, stock_side=same.stock_side)
    assert not bad.passed, bad
    for part in (bad.forward, bad.backward):  # both derivatives see the 2%, in their sums too
        assert part["rejected"] > 0 and max(abs(x) for x in part["sum_relative"]) > 0.01, part


def test_compare_grad_end_to_end(scene_as, tmp_path):
    """`layerbvh compare --grad KEY`: both verdicts in report.json, the derivative images and
    the page's section; a key the scene lacks and a scene whose integrator does not
    differentiate are refused in one line before anything renders."""
    from layerbvh_mitsuba.cli import main
    path = _as(scene_as, "cbox", "prb_basic")
    key = PARAMS["cbox"][0]
    out = tmp_path / "cmp"
    assert main(["compare", str(path), "--res", "16", "16", "--spp", "4", "--grad", key, "--out", str(out),
                 "--no-progress"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert report_schema.validate(rep) == []
    assert rep["gradient"]["key"] == key and rep["gradient"]["label"] == metrics.SAME_PATHS
    assert len(rep["gradient"]["backward"]["ours"]) == 3
    assert (out / "ours_grad.exr").is_file() and (out / "stock_grad.png").is_file()
    page = (out / "index.html").read_text()
    assert 'id="gradient-verdict" data-passed="true"' in page and "ours_grad.png" in page
    scene = testing.load(path, (8, 8))
    with pytest.raises(UserError, match="no parameter nope"):
        gradient.check_gradient(mi, "prb_basic", scene, "nope")
    with pytest.raises(UserError, match="differentiable integrator"):
        gradient.check_gradient(mi, "path", scene, key)


def test_prb_settings_come_from_the_scene(tmp_path):
    """compare renders both sides with the scene's prb settings; prbvolpath's rr_depth, which its
    loaded integrator does not print, from the XML."""
    for integrator, expect in (("prb", {"max_depth": 3, "rr_depth": 2, "hide_emitters": True}),
                               ("prbvolpath", {"max_depth": 3, "rr_depth": 2, "hide_emitters": True})):
        path = tmp_path / f"{integrator}.xml"
        path.write_text(f"""<scene version="3.0.0">
            <integrator type="{integrator}"><integer name="max_depth" value="3"/><integer name="rr_depth" value="2"/>
                <boolean name="hide_emitters" value="true"/></integrator>
            <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
                <integer name="height" value="8"/></film></sensor>
            <shape type="sphere"/><emitter type="constant"/></scene>""")
        s = path_settings(mi, mi.load_file(str(path)), scene_path=path)
        assert s.estimator == integrator and s.ours_type == f"layerbvh_{integrator}"
        assert s.props == expect, (integrator, s.props)


def test_prb_refuses_bad_settings_and_unattached_gradients():
    """Stock's depth rules by name; a replay whose parameter was never given dr.enable_grad is
    refused by name (as stock prb refuses it), not silently 0."""
    for bad in ({"max_depth": -2}, {"rr_depth": 0}):
        with pytest.raises(Exception, match="depth"):
            mi.load_dict({"type": "layerbvh_prb", **bad})
    scene = testing.load(SCENES / "cbox.xml", (8, 8))
    # (Between kernels the error reaches the caller as it is; a symbolic loop wraps it.)
    ours = mi.load_dict({"type": "layerbvh_prb", "traversal": "layer_sorted", "treelet_height": LAYER_HEIGHT})
    with pytest.raises(ValueError, match="attached to no scene parameter"):
        ours.render_forward(scene, mi.traverse(scene), spp=1)
    dr.eval()
