"""`layerbvh converge`: error falls at the Monte Carlo rate for every configuration, outputs are whole, the reference
cache is keyed by content."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import matplotlib.image as mpimg
import pytest

from layerbvh_mitsuba.cli import main
from layerbvh_mitsuba.ab.stock_cache import SceneFilesError, reference_key
from layerbvh_mitsuba.tools.converge import ConvergeError, parse_configs

SCENES = Path(__file__).resolve().parents[2] / "scenes"


@pytest.fixture(scope="module")
def converged(tmp_path_factory):
    out, cache = tmp_path_factory.mktemp("conv"), tmp_path_factory.mktemp("cache")
    argv = ["converge", str(SCENES / "cbox.xml"), "--budget", "600", "--res", "32", "32", "--ref-spp", "1024",
            "--max-spp", "64", "--configs", "stock,per_ray,layer_sorted:2", "--cache", str(cache),
            "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    return out, cache, argv


def test_error_falls_at_the_monte_carlo_rate(converged):
    out, _, _ = converged
    doc = json.loads((out / "convergence.json").read_text())
    assert [c["name"] for c in doc["configs"]] == ["stock", "per_ray", "layer_sorted:2"]
    for c in doc["configs"]:
        assert [p["spp"] for p in c["points"]] == [1, 2, 4, 8, 16, 32, 64], c["name"]
        slope = c["fit"]["rel_mse_vs_spp"]["slope"]
        assert -1.3 <= slope <= -0.7, f"{c['name']}: relMSE falls as spp^{slope:.2f}"
        assert c["points"][-1]["rel_mse"] < c["points"][0]["rel_mse"] / 10
        assert c["points"][-1]["flip"] < c["points"][0]["flip"]
        assert all(p["seconds"] > 0 and p["compile_s"] >= 0 for p in c["points"])
        assert len({p["seed"] for p in c["points"]}) == len(c["points"]), "independent seeds"
    seeds = [p["seed"] for c in doc["configs"] for p in c["points"]]
    assert len(set(seeds)) == len(seeds), "no two renders share a seed"
    assert doc["configs"][0]["build_s"] == 0.0 and doc["configs"][2]["build_s"] > 0.0


def test_every_output_is_written(converged):
    out, _, _ = converged
    with open(out / "convergence.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {"config", "spp", "seconds", "rel_mse", "flip", "delta_e2000"} <= set(rows[0])
    assert len(rows) == 21 and all(float(r["delta_e2000"]) >= 0 for r in rows)
    assert mpimg.imread(out / "convergence.png").shape[1] > 1000
    page = (out / "convergence.html").read_text()
    assert '<img src="convergence.png"' in page and all(f"<td>{n}</td>" in page for n in ("stock", "per_ray"))
    md = (out / "convergence.md").read_text()
    for name in ("stock", "per_ray", "layer_sorted:2"):
        assert f"| {name} |" in md
    table = json.loads((out / "convergence.json").read_text())["table"]
    stock = table["rows"]["stock"]
    # Stock against itself is 1, unless its time fit is too noisy to read (tiny renders: R² < 0.9).
    assert table["base"] == "stock" and (stock["time_vs_base"] == pytest.approx(1.0)
                                         or (stock["time_vs_base"] is None and "R²" in stock["why_not"]))
    assert not list(out.glob(".*.tmp*")), "no temporary files left behind"


def test_reference_is_reused_from_the_cache(converged, tmp_path):
    out, cache, argv = converged
    first = json.loads((out / "convergence.json").read_text())["reference"]
    assert first["cached"] is False
    argv = list(argv)
    argv[argv.index("--out") + 1] = str(tmp_path)
    argv[argv.index("--configs") + 1] = "stock"
    assert main(argv) == 0
    second = json.loads((tmp_path / "convergence.json").read_text())["reference"]
    assert second["cached"] is True and second["key"] == first["key"] and second["path"] == first["path"]


def test_reference_key_follows_content(tmp_path):
    shutil.copy(SCENES / "bunny_box.xml", tmp_path / "scene.xml")
    (tmp_path / "meshes").mkdir()
    mesh = tmp_path / "meshes" / "bunny.ply"
    shutil.copy(SCENES / "meshes" / "bunny.ply", mesh)
    settings = {"ref_spp": 64, "resolution": [8, 8]}
    k0 = reference_key(tmp_path / "scene.xml", settings)
    assert reference_key(tmp_path / "scene.xml", settings) == k0
    assert reference_key(tmp_path / "scene.xml", {**settings, "ref_spp": 128}) != k0
    data = bytearray(mesh.read_bytes())
    data[-1] ^= 1  # one bit of the mesh a scene references
    mesh.write_bytes(bytes(data))
    assert reference_key(tmp_path / "scene.xml", settings) != k0
    mesh.unlink()
    with pytest.raises(SceneFilesError, match="bunny.ply"):
        reference_key(tmp_path / "scene.xml", settings)


def test_scene_files_resolve_as_mitsuba_does():
    """Regression: Mitsuba's media test scenes include include/test-scene-base.xml, which includes
    `include/preamble.xml` and references `meshes/...`: names Mitsuba finds from the scene's
    folder, not the including file's. The key read them there and refused the scene (converge
    failed on every media scene)."""
    from layerbvh_mitsuba.ab.stock_cache import scene_files
    files = {p.relative_to(SCENES / "media").as_posix()
             for p in scene_files(SCENES / "media" / "test_homo_spectral_sigmat_volpathmis.xml")}
    assert {"include/test-scene-base.xml", "include/preamble.xml"} <= files, files
    assert any(f.startswith("meshes/") for f in files), files


def test_bad_configs_are_named(capsys):
    assert [c.name for c in parse_configs("stock, per_ray, layer_sorted:6")] == ["stock", "per_ray", "layer_sorted:6"]
    for text, word in (("stock,foo", "foo"), ("layer_sorted:x", "layer_sorted:x"), ("per_ray,per_ray", "twice"),
                       ("layer_sorted:0", "layer_sorted:0")):
        with pytest.raises(ConvergeError, match=word):
            parse_configs(text)
    assert main(["converge", str(SCENES / "cbox.xml"), "--budget", "1", "--out", "/nonexistent/x",
                 "--configs", "stock,bogus"]) == 2
    assert "bogus" in capsys.readouterr().err


def test_report_quotes_the_convergence_table(converged):
    from layerbvh_mitsuba.tools.bench import report
    out, _, _ = converged
    text = "\n".join(report.converge_section([out], out.parent))
    assert "layerbvh converge" in text and "--configs stock,per_ray,layer_sorted:2" in text
    assert "| layer_sorted:2 |" in text and f"({out.name}/convergence.png)" in text
