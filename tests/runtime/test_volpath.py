"""Scenes with participating media through our traversal: `layerbvh_volpath` against stock `volpath` on Mitsuba's own media test scenes (same seed, independent seeds, and Mitsuba's reference images with its own criterion) and on media scenes written here, in every JIT variant tested."""
from __future__ import annotations

import math
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

SCENES = Path(__file__).resolve().parents[2] / "scenes"
MEDIA = SCENES / "media"

# Mitsuba's volpath test scenes. In the heterogeneous ones same-seed paths diverge: the null-
# collision chain is chaotic in the hit position (measured: on Embree's own hits, barycentrics
# scaled by 1 + 1e-6 move 9% of the pixels of test_hetero_sigmat beyond 1e-3; our watertight test's
# barycentrics differ from Embree's by up to 1e-5), so the two-step verdict decides there.
SAME_SEED = ["test_homo_area_light", "test_homo_dielectric_envmap", "test_homo_emitter_inside_medium",
             "test_homo_null_envmap", "test_homo_obj_inside_medium", "test_homo_roughdielectric_spot",
             "test_surf_area_light", "test_hetero_spectral_sigmat_no_scattering"]
DIVERGING = ["test_hetero_sigmat", "test_hetero_sigmat_albedo"]


@pytest.fixture(autouse=True)
def variant():
    use_variant()


def _scene(name: str) -> Path:
    return MEDIA / f"{name}_volpath.xml"


@pytest.mark.parametrize("name", SAME_SEED)
def test_mitsuba_media_scene_matches_stock_at_the_same_seed(name):
    """The scene as it is (`moment(volpath)`): the wrapper kept on both sides, ours inside it."""
    r = testing.assert_matches_stock(_scene(name), spp=16, res=(32, 32), traversal="per_ray")
    assert r.compared_as == "moment(volpath)"
    assert r.ours_stats.features.media.on == (name != "test_surf_area_light")


@pytest.mark.parametrize("name", DIVERGING)
def test_heterogeneous_media_agree_with_stock_within_noise(name):
    v = testing.verdict_vs_stock(_scene(name), spp=16, res=(32, 32), traversal="per_ray")
    assert v.passed, v.summary


def test_the_statistical_step_can_fail_on_a_medium():
    """Negative control: ours on a copy of the scene whose medium only absorbs (albedo 0: the
    in-scattered light lost). Measured: albedo x 0.8 (9% darker on average) and x 0.5 pass the
    per-pixel step at 16 spp; media scenes are noisy per pixel, so the control runs at 64."""
    def darker(params):
        key = "medium1.albedo.value.value"
        params[key] = params[key] * 0.0
        params.update()
    v = testing.verdict_vs_stock(_scene("test_hetero_sigmat"), spp=64, res=(32, 32), traversal="per_ray",
                                 ours_modify=darker)
    assert not v.passed, v.summary


def test_layer_sorted_matches_stock_on_a_media_scene(layer_path_ran):
    """The wavefront path: media, a null-BSDF boundary and shadow rays stepping through both."""
    r = testing.assert_matches_stock(_scene("test_homo_null_envmap"), spp=4, res=(16, 16), traversal="layer_sorted",
                                     ours_props={"treelet_height": 2})
    layer_path_ran(r.ours_stats, "layer_sorted")


# -- Mitsuba's own reference test --------------------------------------------------------------------
def _z_test_pass_fraction(img, spp: int, ref, ref_var) -> float:
    """Mitsuba's render test (src/render/tests/test_renders.py): a per-pixel, per-channel Z-test
    of the image against the reference with the reference's per-sample variance (floored at
    1e-4), Šidák-corrected at 0.01 over the pixels; the share of channels that pass."""
    z = np.abs(img - ref) * np.sqrt(spp / np.maximum(ref_var, 1e-4))
    p_value = 2.0 * (1.0 - 0.5 * (1.0 + np.vectorize(math.erf)(z / np.sqrt(2.0))))
    pixels = img.shape[0] * img.shape[1]
    alpha = 1.0 - (1.0 - 0.01) ** (1.0 / pixels)
    return float(np.count_nonzero(p_value > alpha) / 3 / pixels)


def _xyz(path: Path) -> np.ndarray:
    return np.array(mi.Bitmap(str(path)).convert(mi.Bitmap.PixelFormat.XYZ, mi.Struct.Type.Float32, False))


def _ours_xyz(name: str, spp: int) -> np.ndarray:
    """Ours rendered as the scene asks (moment around ours, at its own 48x48, traversal auto): the
    first moment's XYZ channels, as Mitsuba's test reads them."""
    scene = mi.load_file(str(_scene(name)), spp=spp, integrator="layerbvh_volpath")
    mi.render(scene, spp=spp, seed=0)
    split = dict(scene.sensors()[0].film().bitmap(raw=False).split())
    return np.array(split["_arg_0"], np.float32)


# Mitsuba's test spends 2e6 samples (868 spp). At 128 spp stock itself fails it on
# test_homo_area_light (99.57-99.65% of pixel channels pass, two seeds: the mean of few samples
# of a heavy-tailed pixel is not yet normal); at 256 stock and ours pass (99.83-99.87%).
REF_SPP = 256


def _refs(name: str) -> tuple[np.ndarray, np.ndarray]:
    base = name.removeprefix("test_")
    return _xyz(MEDIA / "refs" / f"test_{base}_ref_rgb.exr"), _xyz(MEDIA / "refs" / f"test_{base}_ref_rgb_var.exr")


@pytest.mark.parametrize("name", SAME_SEED + DIVERGING)
def test_ours_passes_mitsubas_reference_test(name):
    ref, var = _refs(name)
    frac = _z_test_pass_fraction(_ours_xyz(name, REF_SPP), REF_SPP, ref, var)
    assert frac >= 0.9975, f"{frac:.4%} of pixel channels pass (Mitsuba asks 99.75%)"


def test_the_reference_test_can_fail():
    """Negative control: the same render against the reference of the scene with an albedo grid."""
    ref, var = _refs("test_hetero_sigmat_albedo")
    assert _z_test_pass_fraction(_ours_xyz("test_hetero_sigmat", REF_SPP), REF_SPP, ref, var) < 0.9975


# -- media scenes written here ---------------------------------------------------------------------
def _write(tmp_path, name: str, body: str, camera: str = "0, 0.3, 4", sensor_medium: str = "") -> Path:
    text = f"""<scene version="3.0.0">
    <default name="max_depth" value="8"/>
    <default name="res" value="32"/>
    <integrator type="volpath"><integer name="max_depth" value="$max_depth"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="{camera}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>
            <rfilter type="box"/></film>
        <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
        {sensor_medium}
    </sensor>
    <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/>
        <translate y="-1"/></transform><bsdf type="diffuse"/></shape>
    <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="90"/><translate y="2.5"/></transform>
        <emitter type="area"><rgb name="radiance" value="6"/></emitter></shape>
    {body}
</scene>"""
    path = tmp_path / f"{name}.xml"
    path.write_text(text)
    return path


FOG = """<medium id="fog" type="homogeneous"><rgb name="sigma_t" value="0.8"/><rgb name="albedo" value="0.9"/>
        <phase type="hg"><float name="g" value="0.5"/></phase></medium>
    <shape type="cube"><transform name="to_world"><scale value="1.2"/></transform><bsdf type="null"/>
        <ref name="interior" id="fog"/></shape>
    <shape type="ply"><string name="filename" value="{sphere}"/><transform name="to_world"><scale value="0.5"/>
        </transform><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.5, 0.8"/></bsdf>
        <ref name="exterior" id="fog"/></shape>"""
GLASS = """<emitter type="constant"><rgb name="radiance" value="0.3"/></emitter>
    <medium id="ink" type="homogeneous"><rgb name="sigma_t" value="0.17, 0.5, 1"/><float name="scale" value="3"/><rgb name="albedo" value="0.8"/>
        <phase type="isotropic"/></medium>
    <shape type="ply"><string name="filename" value="{sphere}"/><bsdf type="dielectric"/>
        <ref name="interior" id="ink"/></shape>"""
# The camera and a point light inside one fog box (the sensor's medium), a small area light too.
INSIDE = """<medium id="fog" type="homogeneous"><rgb name="sigma_t" value="0.5"/><rgb name="albedo" value="0.7"/>
        </medium>
    <shape type="cube"><transform name="to_world"><scale value="3"/></transform><bsdf type="null"/>
        <ref name="interior" id="fog"/></shape>
    <emitter type="point"><point name="position" value="0.5, 0.5, 0.5"/><rgb name="intensity" value="3"/></emitter>
    <shape type="sphere"><point name="center" value="-0.6, 0, 0"/><float name="radius" value="0.2"/>
        <emitter type="area"><rgb name="radiance" value="4, 2, 1"/></emitter><ref name="exterior" id="fog"/></shape>"""


def _grid(tmp_path) -> Path:
    """A heterogeneous density: a soft ball with a hole, on a 24^3 grid."""
    x = (np.arange(24) + 0.5) / 24 - 0.5
    z, y, xx = np.meshgrid(x, x, x, indexing="ij")
    r = np.sqrt(xx ** 2 + y ** 2 + z ** 2)
    density = np.clip(1 - r / 0.5, 0, 1) * (1 - np.exp(-((xx - 0.15) ** 2 + y ** 2) / 0.01))
    path = tmp_path / "ball.vol"
    mi.VolumeGrid(density.astype(np.float32)[..., None]).write(str(path))
    return path


# The box floats above the floor: a box face on the floor would be coplanar with it, where the
# closest hit is a tie that Embree and our traversal break differently (measured with the box on
# the floor: ours 7% darker, the difference in the rows of the floor; on Embree's hits our loop
# equals stock exactly).
GRID = """<emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
    <medium id="smoke" type="heterogeneous"><float name="scale" value="8"/><rgb name="albedo" value="0.9"/>
        <volume name="sigma_t" type="gridvolume"><string name="filename" value="{grid}"/>
            <transform name="to_world"><translate value="-0.5, -0.5, -0.5"/><scale value="1.8"/></transform></volume>
    </medium>
    <shape type="cube"><transform name="to_world"><scale value="0.9"/></transform><bsdf type="null"/>
        <ref name="interior" id="smoke"/></shape>"""


def _own(tmp_path, kind: str) -> Path:
    sphere = str(SCENES / "meshes" / "sphere.ply")
    if kind == "fog_box":
        return _write(tmp_path, kind, FOG.format(sphere=sphere))
    if kind == "medium_in_dielectric":
        return _write(tmp_path, kind, GLASS.format(sphere=sphere))
    if kind == "emitter_and_camera_in_medium":
        return _write(tmp_path, kind, INSIDE, camera="0, 0.3, 2.5", sensor_medium='<ref name="medium" id="fog"/>')
    return _write(tmp_path, kind, GRID.format(grid=_grid(tmp_path)))


@pytest.mark.parametrize("kind", ["fog_box", "medium_in_dielectric", "emitter_and_camera_in_medium"])
def test_own_media_scenes_match_stock_at_the_same_seed(tmp_path, kind):
    r = testing.assert_matches_stock(_own(tmp_path, kind), spp=16, res=(32, 32), traversal="per_ray")
    features = r.ours_stats.features
    assert features.media.on and features.transmittance.on
    assert r.mean_ref > 0.01  # not a black image


def test_generated_heterogeneous_grid_agrees_with_stock(tmp_path):
    v = testing.verdict_vs_stock(_own(tmp_path, "grid"), spp=16, res=(32, 32), traversal="per_ray")
    assert v.passed, v.summary


def test_a_scene_without_media_leaves_media_out_and_keeps_the_image(tmp_path):
    """volpath on the Cornell box: no medium and no null surface, so no free-flight sampling and
    any-hit shadow rays; the image is the one everything-on renders, and stock's."""
    text = (SCENES / "cbox.xml").read_text()
    text, n = re.subn(r'<integrator type="path">.*?</integrator>', '<integrator type="volpath"/>', text, count=1,
                      flags=re.S)
    assert n == 1
    path = tmp_path / "cbox_volpath.xml"
    path.write_text(text)
    mi.file_resolver().prepend(str(SCENES))
    scene = testing.load(path, (24, 24))
    images = {}
    for adaptive in (True, False):
        integ = mi.load_dict({"type": "layerbvh_volpath", "traversal": "per_ray", "adaptive": adaptive})
        images[adaptive] = np.array(mi.render(scene, integrator=integ, spp=8, seed=2))
        plan = integ.last_stats.features
        assert plan.media.on == (not adaptive) and plan.transmittance.on == (not adaptive)
    stock = np.array(mi.render(scene, integrator=mi.load_dict({"type": "volpath"}), spp=8, seed=2))
    assert metrics.same_seed_verdict(images[False], images[True])["passed"]
    assert metrics.same_seed_verdict(stock, images[True])["passed"]


def test_volpath_matches_stock_in_the_spectral_and_mono_variants(tmp_path):
    """In its own process (the variant is process-wide): same seed, per_ray and layer_sorted, on
    the fog box (spectral: a hero wavelength per sample, mono: no colour channel drawn)."""
    scene = _own(tmp_path, "fog_box")
    code = f"""
import mitsuba as mi, numpy as np
for v in ("llvm_ad_spectral", "llvm_ad_mono"):
    mi.set_variant(v)
    import layerbvh_mitsuba
    from layerbvh_mitsuba.ab import metrics
    for t, res in (("per_ray", 32), ("layer_sorted", 12)):
        scene = mi.load_file({str(scene)!r}, res=res)
        stock = np.array(mi.render(scene, integrator=mi.load_dict({{"type": "volpath"}}), spp=4, seed=1))
        ours = mi.load_dict({{"type": "layerbvh_volpath", "traversal": t, "treelet_height": 2}})
        img = np.array(mi.render(scene, integrator=ours, spp=4, seed=1))
        print(v, t, img.shape[-1], metrics.same_seed_verdict(stock, img)["passed"])
"""
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    lines = re.findall(r"(llvm_\w+) (\w+) (\d) (\w+)", p.stdout)
    assert [(v, t, ok) for v, t, _, ok in lines] == [(v, t, "True") for v in ("llvm_ad_spectral", "llvm_ad_mono")
                                                     for t in ("per_ray", "layer_sorted")], p.stdout
