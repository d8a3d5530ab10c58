"""The layerbvh Mitsuba integrator against stock `path`: same-seed images, Z-test, unsupported shapes, XML use."""
from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401  (registers the integrator)
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.runtime.scene_geometry import UnsupportedShapeError
from layerbvh_mitsuba.runtime.settings import Traversal

SCENES = Path(__file__).resolve().parents[2] / "scenes"
# The layer modes' image tests build treelets of height 2 (one level of the default 4-wide tree):
# at the default height 8, cbox, empty_box and sphere_box are one treelet each, where a layer mode
# cannot differ from per_ray. Each such test asserts the layer path ran (tests/runtime/conftest.py, layer_path_ran).
LAYER_HEIGHT = 2


def _ours_props(traversal: str) -> dict | None:
    return {"treelet_height": LAYER_HEIGHT} if traversal.startswith("layer_") else None


@pytest.mark.parametrize("name,traversal", [("cbox", "per_ray"), ("cbox", "layer_sorted"), ("cbox", "embree"),
                                            ("bunny_box", "per_ray"), ("bunny_box", "layer_sorted"),
                                            ("sphere_box", "per_ray"), ("sphere_box", "auto"),
                                            ("empty_box", "layer_unsorted")])
def test_same_seed_matches_stock(name, traversal, tmp_path, layer_path_ran):
    r = testing.assert_matches_stock(SCENES / f"{name}.xml", spp=8, res=(32, 32), traversal=traversal,
                                     diff_dir=tmp_path, ours_props=_ours_props(traversal))
    assert r.mean_ref > 0.01, "the scene should not render black"
    if traversal.startswith("layer_"):
        layer_path_ran(r.ours_stats, traversal)


def test_same_seed_glass_and_mirror(tmp_path):
    # A ray grazing a shared edge can take another specular path: 99% of pixels, not 99.9%.
    testing.assert_matches_stock(SCENES / "glass_mirror.xml", spp=8, res=(32, 32), min_frac=0.99,
                                 max_mean_rel=1e-3, diff_dir=tmp_path)


# One configuration of the verdict's independent-seed test (verdict.independent_seed_test) for the
# test and its negative control below: 36 pixels (one failing pixel fails the rule of at most 1%
# failing), 8192 samples per pixel a side.
Z_TEST = {"spp": 8192, "res": (6, 6)}


@pytest.mark.parametrize("traversal", ["per_ray", "embree", "layer_sorted"])
def test_z_test_passes_against_stock(traversal, layer_path_ran):
    # Measured: every pixel passes in each mode, the smallest p-value 5.7e-3 in each (the same
    # hits, the same pixel) against the Šidák threshold 2.8e-4.
    r = testing.assert_statistically_matches_stock(SCENES / "cbox.xml", traversal=traversal,
                                                   ours_props=_ours_props(traversal), **Z_TEST)
    assert r.pixels == 36
    if traversal.startswith("layer_"):
        layer_path_ran(r.ours_stats, traversal)


def test_z_test_catches_a_2_percent_albedo_change():
    """Negative control of the Z-test above (its configuration, Z_TEST): it must fail when one
    material's albedo (the floor's) changes by 2%. Measured: 7 of 36 pixels fail, smallest
    p-value 2.4e-12 against the threshold 2.8e-4. The control runs
    per_ray: its power is the configuration's (the traversal modes trace the same hits)."""
    def brighter_floor(params):
        key = "FloorBSDF.brdf_0.reflectance.value"
        params[key] = params[key] * 1.02
    r = testing.independent_seeds_vs_stock(SCENES / "cbox.xml", modify=brighter_floor, **Z_TEST)
    assert not r.passed, r.family.summary()


def test_integrator_from_xml_and_stats():
    scene = mi.load_string("""<scene version="3.0.0">
        <integrator type="layerbvh"><integer name="max_depth" value="4"/>
            <string name="traversal" value="layer_sorted"/><integer name="treelet_height" value="3"/></integrator>
        <sensor type="perspective">
            <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
            <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
            <sampler type="independent"><integer name="sample_count" value="4"/></sampler></sensor>
        <shape type="sphere" id="ball"/><shape type="rectangle" id="floor"><transform name="to_world">
            <translate z="-1.5"/><scale value="4"/></transform></shape>
        <emitter type="constant"/></scene>""")
    integ = scene.integrator()
    assert integ.estimator.max_depth == 4 and integ.traversal == Traversal("layer_sorted") and integ.treelet_height == 3
    img = np.array(mi.render(scene))
    assert np.isfinite(img).all() and img.mean() > 0.05
    st = integ.last_stats
    assert st.loop == "wavefront" and st.build_s > 0 and st.trace_s > 0 and st.shading_s >= 0
    assert st.queries > 0 and st.wavefront_steps > 0 and st.inner_nodes == 0  # no counters: stats off
    assert st.rays > 16 * 16 * 4 and st.bvh.triangles == 2
    tracer = integ.tracer(scene)
    mi.render(scene)
    assert integ.tracer(scene) is tracer, "the BVH is built once per scene and reused"


def test_bad_integrator_properties():
    with pytest.raises(Exception, match="traversal must be one of"):
        mi.load_dict({"type": "layerbvh", "traversal": "fast"})


def test_unsupported_shape_is_refused_by_name(tmp_path):
    (tmp_path / "curve.txt").write_text("-1 0 0 0.1\n0 0.5 0 0.1\n1 0 0 0.1\n")
    scene = mi.load_string(f"""<scene version="3.0.0">
        <shape type="linearcurve" id="hair"><string name="filename" value="{tmp_path / 'curve.txt'}"/></shape>
        <shape type="rectangle" id="floor"/></scene>""")
    integ = mi.load_dict({"type": "layerbvh"})
    with pytest.raises(UnsupportedShapeError, match=r"LinearCurve 'hair'.*'linearcurve'.*not supported"):
        integ.tracer(scene)


@pytest.mark.parametrize("name", ["cbox", "sphere_box"])
def test_hide_emitters_matches_stock(name):
    scene = testing.load(SCENES / f"{name}.xml", (32, 32))
    props = {"max_depth": 6, "hide_emitters": True}
    a = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", **props}), spp=8, seed=0))
    b = np.array(mi.render(scene, integrator=mi.load_dict({"type": "layerbvh", "traversal": "per_ray", **props}),
                           spp=8, seed=0))
    d = np.abs(a - b).max(-1)
    assert np.mean(d <= 1e-3) >= 0.999, f"max |diff| {d.max()}"


@pytest.mark.parametrize("first", ["mitsuba", "layerbvh_mitsuba", "variant"])
def test_registered_for_every_variant_set_later(first):
    """No variant is set by importing the package; the integrators follow variant changes, whether
    Mitsuba is imported before the package, after it (the package imports nothing heavy: it
    registers right after Mitsuba's import), or with a variant already set."""
    import subprocess
    import sys
    imports = {"mitsuba": "import mitsuba as mi, layerbvh_mitsuba; assert mi.variant() is None",
               "layerbvh_mitsuba": "import layerbvh_mitsuba, sys; assert 'mitsuba' not in sys.modules; "
                                   "import mitsuba as mi; assert mi.variant() is None",
               "variant": "import mitsuba as mi; mi.set_variant('llvm_ad_spectral'); import layerbvh_mitsuba; "
                          "mi.load_dict({'type': 'layerbvh_volpath'})"}[first]
    code = (imports + "; mi.set_variant('llvm_ad_mono'); i = mi.load_dict({'type': 'layerbvh'}); "
            "mi.set_variant('llvm_ad_rgb'); j = mi.load_dict({'type': 'layerbvh_direct'}); "
            "print(type(i).__name__, type(j).__name__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.split() == ["LayerBVHIntegrator", "LayerBVHDirectIntegrator"], r.stderr


def _distinct_kernels(scene, integ) -> int:
    """Distinct JIT kernels (by hash) a warm render launches, from Dr.Jit's kernel history."""
    import drjit as dr
    mi.render(scene, integrator=integ, spp=4, seed=0)  # compiles; the counted render is warm
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        mi.render(scene, integrator=integ, spp=4, seed=1)
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return len({k["hash"] for k in history if k["type"] == dr.KernelType.JIT})


@pytest.mark.parametrize("traversal,loop", [("per_ray", "megakernel"), ("embree", "megakernel"),
                                            ("layer_sorted", "wavefront")])
def test_kernels_do_not_multiply_with_path_depth(traversal, loop):
    scene = testing.load(SCENES / "cbox.xml", (32, 32))
    counts = {}
    for depth in (4, 16, 48):
        integ = mi.load_dict({"type": "layerbvh", "traversal": traversal, "max_depth": depth, "treelet_height": 2})
        counts[depth] = _distinct_kernels(scene, integ)
        assert integ.last_stats.loop == loop
    # A bounce launches the same kernels whatever its number. The first bounces differ a little
    # (state that starts as a literal, Russian roulette from rr_depth on), so depth 16 may add a
    # few over depth 4, but from there on the count must stay put.
    assert counts[16] <= counts[4] + 12 and counts[48] <= counts[16] + 2, counts
    if loop == "megakernel":
        assert counts[48] <= 4, f"one kernel per render (plus film and sampler set-up): {counts}"


def test_every_integrator_is_a_subclass_of_the_one_driver_class():
    """The render driver is a class (issue 58): each of our integrators is a subclass of the driver
    over its Mitsuba base (runtime/driver.py's class statement, one per base), which defines the
    methods; the integrator's class adds its estimator and the aliases of its kind of `sample`
    and render, no method of its own. `super()` reaches the base: Mitsuba's properties parse."""
    from layerbvh_mitsuba.runtime.driver import driver_class
    from layerbvh_mitsuba.runtime.registry import PLUGINS, integrator_class
    aliases = {"sample", "render", "render_forward", "render_backward"}
    for plugin, (name, estimator) in PLUGINS.items():
        cls = integrator_class(plugin)
        driver = cls.__mro__[1]
        assert cls.__name__ == name and cls.ESTIMATOR is estimator and driver is driver_class(cls._base), plugin
        assert driver.__qualname__.endswith("<locals>.LayerBVHIntegrator") and "scene_state" in vars(driver)
        own = {k for k, v in vars(cls).items() if callable(v) and not isinstance(v, type)}
        assert own <= aliases, (plugin, own - aliases)
        assert all(getattr(cls, k) is vars(driver).get(getattr(cls, k).__name__) for k in own), plugin
    integ = mi.load_dict({"type": "layerbvh", "max_depth": 3, "traversal": "per_ray"})
    assert integ.estimator.max_depth == 3 and str(integ).startswith("LayerBVHIntegrator[max_depth=3,")
