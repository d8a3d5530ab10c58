"""The `layerbvh` command line: compare writes a complete report, render an EXR, bad input one clear error."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import mitsuba as mi
import numpy as np
import pytest

from layerbvh_mitsuba.ab.scene_integrator import integrator_name
from layerbvh_mitsuba.ab import report_schema
from layerbvh_mitsuba.cli import main

SCENES = Path(__file__).resolve().parents[2] / "scenes"


def test_compare_writes_every_file(tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", str(SCENES / "sphere_box.xml"), "--spp", "4", "--res", "24", "16", "--seed", "3",
               "--traversal", "per_ray", "--out", str(out), "--no-progress"])
    assert rc == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].endswith("index.html")
    for f in ("stock.exr", "ours.exr", "stock.png", "ours.png", "flip.png", "report.json", "index.html"):
        assert (out / f).stat().st_size > 0, f
    rep = json.loads((out / "report.json").read_text())
    assert report_schema.validate(rep) == []  # (every documented field, of its type: docs' report.json page)
    assert rep["spp"] == 4 and rep["resolution"] == [24, 16] and rep["seed"] == 3
    assert rep["scene"].endswith("sphere_box.xml")
    for k in ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs",
              "frac_pixels_over_1e-3"):
        assert k in rep["metrics"]
    assert rep["metrics"]["frac_pixels_over_1e-3"] <= 0.01, "same seed: ours matches stock"
    assert rep["stock"]["render_s"] > 0 and rep["ours"]["render_s"] > 0 and "build_s" in rep["ours"]
    assert rep["traversal"]["rays"] > 0
    assert mpimg.imread(out / "ours.png").shape[:2] == (16, 24)
    html = (out / "index.html").read_text()
    assert "sphere_box" in html and "<img" in html


def test_render_writes_exr(tmp_path):
    out = tmp_path / "img.exr"
    assert main(["render", str(SCENES / "cbox.xml"), "--spp", "2", "--res", "16", "12", "-o", str(out),
                 "--no-progress"]) == 0
    img = np.array(mi.Bitmap(str(out)))
    assert img.shape[:2] == (12, 16) and np.isfinite(img).all() and img.mean() > 0


def _err(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("layerbvh: error:"), err
    return err[0]


def test_bad_inputs_give_one_clear_line_and_no_output(tmp_path, capsys):
    out = tmp_path / "o.exr"
    assert main(["render", str(tmp_path / "missing.xml"), "-o", str(out), "--no-progress"]) == 2
    assert "not found" in _err(capsys)
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><bsdf type="no_such_bsdf" id="b"/></scene>')
    assert main(["render", str(bad), "-o", str(out), "--no-progress"]) == 2
    assert "no_such_bsdf" in _err(capsys)
    (tmp_path / "hair.txt").write_text("-1 0 0 0.1\n0 0.5 0 0.1\n1 0 0 0.1\n")
    curve = tmp_path / "curve.xml"
    curve.write_text("""<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm">
        <integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
        <shape type="shapegroup" id="grp"><shape type="linearcurve" id="hair">
          <string name="filename" value="hair.txt"/></shape></shape>
        <shape type="instance" id="inst1"><ref id="grp"/></shape></scene>""")
    assert main(["compare", str(curve), "--out", str(tmp_path / "cmp"), "--no-progress"]) == 2
    err = _err(capsys)
    assert "'hair'" in err and "linearcurve" in err and "grp" in err
    assert main(["render", str(SCENES / "cbox.xml"), "--traversal", "fast", "-o", str(out)]) == 2
    assert "--traversal" in _err(capsys)
    assert not out.exists() and not (tmp_path / "cmp").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


def _tiny(tmp_path, name: str, width: int = 4, height: int = 4, spp: int = 4) -> str:
    path = tmp_path / f"{name}.xml"
    path.write_text(f"""<scene version="3.0.0"><sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform><film type="hdrfilm">
        <integer name="width" value="{width}"/><integer name="height" value="{height}"/></film>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler></sensor>
        <shape type="sphere"/><emitter type="constant"/></scene>""")
    return str(path)


def test_legal_scene_numbers_and_seeds_a_sampler_cannot_take_are_one_line(tmp_path, capsys):
    """Issue 56: a scene's sampler with sample_count 0 (no --spp) died of SIGFPE, and so did a
    ptracer with samples_per_pass 0; a 0x0 film (no --res) was an internal error inside
    mi.render; --seed -1 or 2^32 gave two lines and an internal error; --spp 10^14 rendered for
    ever; a texture that is a Git LFS pointer failed naming no file. Each is one line naming it,
    exit 2, nothing written. A seed a user may legally give (a Unix time) renders in several
    passes: the pass seeds stay within 32 bits."""
    zero_spp, zero_film = _tiny(tmp_path, "zero_spp", spp=0), _tiny(tmp_path, "zero_film", 0, 0)
    out = tmp_path / "o.exr"

    def variant(name, old, new):  # a tiny scene with one value changed
        path = Path(_tiny(tmp_path, name))
        path.write_text(path.read_text().replace(old, new, 1))
        return path
    crop0 = variant("crop0", "</film>", '<integer name="crop_width" value="0"/></film>')
    ptracer0 = variant("ptracer0", "<sensor", '<integrator type="ptracer"><integer name="samples_per_pass" value="0"/>'
                                             '</integrator><sensor')
    rr0 = variant("rr0", "<sensor", '<integrator type="path"><integer name="rr_depth" value="0"/></integrator><sensor')
    cbox = SCENES / "cbox.xml"
    # The class (issue 56): every number of a scene that reaches a division or an allocation, and
    # every CLI number's range, one line each.
    for cmd, scene, extra, says in (
            ("render", zero_spp, [], "sample_count 0"), ("compare", zero_spp, [], "sample_count 0"),
            ("render", zero_film, [], "its film is 0x0 pixels"),
            ("compare", zero_film, ["--spp", "2"], "its film is 0x0"),
            ("render", crop0, [], "its film is 0x4 pixels"),
            ("compare", ptracer0, [], "samples_per_pass 0; it must be >= 1"),  # (stock dies of SIGFPE)
            ("render", rr0, [], '"rr_depth" must be set to a value greater than zero'),
            ("render", cbox, ["--seed", "-1"], "--seed must be from 0 to 4294967295"),
            ("compare", cbox, ["--seed", "4294967296"], "--seed must be from 0 to 4294967295"),
            ("compare", cbox, ["--spp", "0"], "--spp must be from 1 to 4294967295"),
            ("render", cbox, ["--spp", str(10 ** 14)], "--spp must be from 1 to 4294967295"),  # (rendered for ever)
            ("render", cbox, ["--res", "0", "8"], "--res must be positive"),
            ("render", cbox, ["--treelet-height", "0"], "--treelet-height must be in [1, 64]"),
            ("render", cbox, ["--leaf-size", "0"], "--leaf-size must be in [1, 16]"),
            ("render", cbox, ["--branching", "3"], "--branching must be one of 2, 4, 8")):
        target = ["-o", str(out)] if cmd == "render" else ["--out", str(tmp_path / "cmp")]
        assert main([cmd, str(scene), *extra, *target, "--no-progress"]) == 2, (cmd, scene, extra)
        assert says in _err(capsys), (cmd, scene, extra)
    for extra, says in ((["--seed", "-1"], "--seed must be from 0"), (["--spp", "4,0"], "--spp must be from 1")):
        assert main(["sweep", str(cbox), "--job", "compare", *extra, "--out", str(tmp_path / "sw")]) == 2
        assert says in _err(capsys), extra
    assert not out.exists() and not (tmp_path / "cmp").exists() and not (tmp_path / "sw").exists()
    # A texture that is a Git LFS pointer (a clone without `git lfs pull`): Mitsuba says "Bitmap:
    # Unknown file format!" and names no file; the line names it.
    (tmp_path / "wood.png").write_bytes(b"version https://git-lfs.github.com/spec/v1\noid sha256:4d7a\nsize 12\n")
    textured = Path(_tiny(tmp_path, "textured"))
    textured.write_text(textured.read_text().replace('<shape type="sphere"/>', """<shape type="sphere"><bsdf
        type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="wood.png"/>
        </texture></bsdf></shape>"""))
    assert main(["render", str(textured), "-o", str(out), "--no-progress"]) == 2
    assert "wood.png is a Git LFS pointer" in _err(capsys)
    # 65 spp: two passes (render.SPP_PER_PASS 64), pass seeds from 1,700,000,000 x 7919.
    assert main(["render", _tiny(tmp_path, "unix_time"), "--spp", "65", "--seed", "1700000000", "-o", str(out),
                 "--no-progress"]) == 0
    img = np.array(mi.Bitmap(str(out)))
    assert np.isfinite(img).all() and img.mean() > 0


@pytest.mark.parametrize("traversal", ["per_ray", "layer_sorted", "embree"])
def test_a_scene_without_emitters_renders_black_like_stock(tmp_path, capsys, traversal):
    """Regression: with nothing to add to L, the megakernel's loop state came back unchanged and
    Dr.Jit's loop optimisation refused the re-recorded loop (a traceback)."""
    scene = tmp_path / "dark.xml"
    scene.write_text("""<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm">
        <integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
        <shape type="shapegroup" id="grp"><shape type="sphere"/></shape>
        <shape type="instance" id="inst1"><ref id="grp"/></shape><shape type="rectangle"/></scene>""")
    assert main(["compare", str(scene), "--out", str(tmp_path / "cmp"), "--traversal", traversal,
                 "--no-progress"]) == 0, _err(capsys)
    rep = json.loads((tmp_path / "cmp" / "report.json").read_text())
    assert rep["metrics"]["rmse"] == 0


def test_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, capsys):
    """compare into a filesystem with no room: one line naming the output and the reason, exit 2,
    no traceback file, nothing left behind (a real 256 KiB tmpfs, as root; CI runs as root)."""
    import os
    import subprocess
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs root to mount a small tmpfs")
    try:
        out = disk / "cmp"
        rc = main(["compare", str(SCENES / "cbox.xml"), "--spp", "2", "--res", "64", "64", "--traversal", "per_ray",
                   "--out", str(out), "--no-progress"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and err == [f"layerbvh: error: no space left on device writing {out}; nothing written"], err
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)], check=True)


def test_a_reader_that_leaves_the_pipe_is_no_internal_error(tmp_path):
    """`layerbvh render ... | true`: stdout's reader is gone before the summary line is printed.
    The output is written whole first; the command then ends as a shell expects of a closed
    pipe (status 141), with nothing on stderr (before: an "internal error" with a traceback)."""
    out = tmp_path / "img.exr"
    cmd = (f"{sys.executable} -m layerbvh_mitsuba.cli render {SCENES / 'cbox.xml'} --res 8 8 --spp 1 -o {out} "
           f"--no-progress | true; echo ${{PIPESTATUS[0]}} >&2")
    p = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=300)
    assert p.stderr.strip().splitlines() == ["141"], p.stderr
    assert out.is_file() and not list(tmp_path.glob(".*"))


@pytest.mark.parametrize("integrator,name", [
    ({"type": "moment", "inner": {"type": "volpath"}}, "moment(volpath)"),
    ({"type": "moment", "inner": {"type": "path"}}, "moment(path)"),
    ({"type": "moment", "a": {"type": "path"}, "b": {"type": "volpathmis"}}, "moment(path, volpathmis)"),
    ({"type": "aov", "aovs": "d:depth", "inner": {"type": "direct"}}, "aov(direct)"),
    ({"type": "moment", "x": {"type": "aov", "aovs": "d:depth", "inner": {"type": "path"}}}, "moment(aov(path))"),
    ({"type": "volpath"}, "volpath"), ({"type": "volpathmis"}, "volpathmis"), ({"type": "path"}, "path"),
    ({"type": "prb"}, "prb")])
def test_integrators_are_named_by_what_they_wrap(integrator, name):
    """Regression: a moment wrapper around volpath was named "moment(path)" (its test for an inner
    path, "PathIntegrator[" in its text, matched VolumetricSimplePathIntegrator[)."""
    assert integrator_name(mi.load_dict(integrator)) == name


def test_a_wrapped_scene_we_do_not_mirror_is_named_as_what_it_is(tmp_path, capsys):
    """moment(prb): refused by its own name without --as-path; with it, report.json says what the
    scene asked for and the depth comes from the prb inside. The same scene with volpath or
    volpathmis compares as it is: ours inside the wrapper."""
    def fog(integrator):
        scene = tmp_path / f"fog_{integrator}.xml"
        scene.write_text(f"""<scene version="3.0.0">
        <integrator type="moment"><integrator type="{integrator}"><integer name="max_depth" value="3"/></integrator>
        </integrator>
        <sensor type="perspective"><film type="hdrfilm">
            <integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
        <emitter type="constant"/>
        <shape type="rectangle"><transform name="to_world"><translate z="3"/></transform></shape></scene>""")
        return scene
    scene = fog("prb")
    assert main(["compare", str(scene), "--out", str(tmp_path / "no"), "--no-progress"]) == 2
    assert "moment(prb)" in _err(capsys)
    assert main(["compare", str(scene), "--out", str(tmp_path / "cmp"), "--as-path", "--spp", "4",
                 "--no-progress"]) == 0
    rep = json.loads((tmp_path / "cmp" / "report.json").read_text())
    assert rep["scene_integrator"] == "moment(prb)" and rep["integrator"]["max_depth"] == 3, rep["integrator"]
    for integrator in ("volpath", "volpathmis"):
        out = tmp_path / integrator
        assert main(["compare", str(fog(integrator)), "--out", str(out), "--spp", "4", "--no-progress"]) == 0
        rep = json.loads((out / "report.json").read_text())
        assert rep["scene_integrator"] == rep["compared_as"] == f"moment({integrator})", rep["compared_as"]
        assert rep["integrator"]["max_depth"] == 3 and rep["verdict"]["passed"], rep["verdict"]
