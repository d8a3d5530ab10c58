"""gen_stress: each kind loads and renders in Mitsuba at the requested size, byte for byte repeatable, refusing what
will not fit."""
from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import layerbvh
from layerbvh_mitsuba.tools.bench import stress as gen_stress
from layerbvh.meshes import load_mesh
from layerbvh_mitsuba.repo import ROOT

mi.set_variant("llvm_ad_rgb")

SCRIPT = ROOT / "scripts" / "gen_stress.py"  # the entry point users run
N = 10_000


def generate(out: Path, kind: str, *extra: str) -> int:
    return gen_stress.main([kind, "--triangles", str(N), "--out", str(out), *extra])


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("stress")
    for kind in gen_stress.KINDS:
        assert generate(root / kind, kind) == 0
    return root


@pytest.mark.parametrize("kind", gen_stress.KINDS)
def test_scene_loads_renders_and_has_the_requested_triangles(scenes, kind):
    out = scenes / kind
    plys = sorted((out / "meshes").glob("*.ply"))
    assert (out / "scene.xml").is_file() and plys
    shapes = ET.parse(out / "scene.xml").getroot().iter("shape")
    assert all(sh.get("id") for sh in shapes), "every shape has an id"
    scene = mi.load_file(str(out / "scene.xml"), resx=16, resy=16, spp=1)
    # Mitsuba merges shapes that share a BSDF (the box's grey walls), so count all meshes: ours
    # plus at most the box's 7 two-triangle rectangles.
    tris = sum(s.face_count() for s in scene.shapes() if isinstance(s, mi.Mesh))
    ply_tris = sum(len(load_mesh(p)[1]) for p in plys)
    assert abs(tris - N) <= 0.05 * N and abs(ply_tris - N) <= 0.05 * N, (tris, ply_tris)
    assert ply_tris <= tris <= ply_tris + 14, "Mitsuba reads every triangle of our PLYs"
    img = np.array(mi.render(scene, spp=1))
    assert img.shape == (16, 16, 3) and np.isfinite(img).all() and img.mean() > 0


def test_scene_uses_the_declared_defaults(scenes):
    xml = (scenes / "spheres" / "scene.xml").read_text()
    for decl in ('name="resx" value="128"', 'name="resy" value="128"', 'name="spp" value="16"',
                 'name="max_depth" value="8"', 'type="independent"', 'type="hdrfilm"', '<rfilter type="box"/>'):
        assert decl in xml, decl
    for use in ("$resx", "$resy", "$spp", "$max_depth"):
        assert use in xml, use
    for bsdf in ("dielectric", "conductor", "roughconductor", "diffuse"):
        assert f'type="{bsdf}"' in xml, bsdf
    sensor = mi.load_file(str(scenes / "spheres" / "scene.xml")).sensors()[0]
    assert list(sensor.film().size()) == [128, 128] and sensor.sampler().sample_count() == 16


def test_res_spp_and_depth_options_become_the_defaults(tmp_path):
    assert generate(tmp_path / "s", "soup", "--res", "24", "12", "--spp", "3", "--max-depth", "5") == 0
    sensor = mi.load_file(str(tmp_path / "s" / "scene.xml")).sensors()[0]
    assert list(sensor.film().size()) == [24, 12] and sensor.sampler().sample_count() == 3
    assert 'name="max_depth" value="5"' in (tmp_path / "s" / "scene.xml").read_text()


@pytest.mark.parametrize("kind", gen_stress.KINDS)
def test_same_arguments_give_identical_bytes(tmp_path, kind):
    assert generate(tmp_path / "a", kind, "--seed", "7") == 0
    assert generate(tmp_path / "b", kind, "--seed", "7") == 0
    assert generate(tmp_path / "c", kind, "--seed", "8") == 0
    a, b, c = tree(tmp_path / "a"), tree(tmp_path / "b"), tree(tmp_path / "c")
    assert a == b
    assert a != c, "the seed changes the meshes"


def test_absurd_request_is_refused_with_exit_2_and_writes_nothing(tmp_path):
    out = tmp_path / "huge"
    r = subprocess.run([sys.executable, str(SCRIPT), "spheres", "--triangles", "10000000000", "--out", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gen_stress: error:"), err
    assert "10000000000 triangles" in err[0] and "estimated" in err[0] and "available" in err[0], err[0]
    assert list(tmp_path.iterdir()) == [], "nothing written, not even a temporary folder"
    assert "memory estimate" in r.stdout, "the estimate is printed before refusing"


def test_check_only_prints_the_estimate_and_writes_nothing(tmp_path, capsys):
    assert gen_stress.main(["terrain", "--triangles", "1000000", "--out", str(tmp_path / "x"), "--check-only"]) == 0
    out = capsys.readouterr().out
    assert "memory estimate" in out and "will write" in out
    assert list(tmp_path.iterdir()) == []


def test_non_empty_output_is_kept_unless_force(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert generate(out, "soup") == 2
    assert "--force" in capsys.readouterr().err
    assert tree(out) == {"keep.txt": b"x"}
    assert generate(out, "soup", "--force") == 0
    assert (out / "scene.xml").is_file() and not (out / "keep.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"], "no temporary folders left behind"


def test_memory_estimate_bounds_what_is_built(scenes):
    """The estimate decides what gen_stress refuses, so it must not fall short of what a scene
    really takes, nor far exceed it: for each kind's 10k-triangle scene, the PLY files on disk,
    the Layer BVH built over its meshes (BVHStats.bytes) and Mitsuba's mesh arrays (faces,
    positions, normals, texture coordinates) against their estimates. Measured estimate / real:
    mesh 0.997-1.0003 (one PLY header counted; spheres writes four files), bvh 1.20-1.25 (the
    leaf count is bounded from above), mitsuba 0.9991-1.0 (the box's rectangles carry texture
    coordinates, which the estimate leaves out). Bounds: 1% below and 5% above for the files and
    Mitsuba's arrays; for the BVH never below and at most 1.4 (about 10% over the worst)."""
    for kind in gen_stress.KINDS:
        plys = sorted((scenes / kind / "meshes").glob("*.ply"))
        parts = [load_mesh(p) for p in plys]
        tris, verts = sum(len(f) for _, f in parts), sum(len(v) for v, _ in parts)
        est = gen_stress.estimate_bytes(tris, vertices=verts)
        offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
        v = np.concatenate([v for v, _ in parts]).astype(np.float32)
        f = np.concatenate([f + k for (_, f), k in zip(parts, offsets)])
        scene = mi.load_file(str(scenes / kind / "scene.xml"), resx=8, resy=8, spp=1)
        meshes = [sh for sh in scene.shapes() if isinstance(sh, mi.Mesh)]
        mi_bytes = sum(4 * sum(_width(buf) for buf in (sh.faces_buffer(), sh.vertex_positions_buffer(),
                                                        sh.vertex_normals_buffer(), sh.vertex_texcoords_buffer()))
                       for sh in meshes)
        mi_est = gen_stress.estimate_bytes(sum(sh.face_count() for sh in meshes),
                                           vertices=sum(sh.vertex_count() for sh in meshes))["mitsuba"]
        real = {"mesh": sum(p.stat().st_size for p in plys), "bvh": layerbvh.build(v, f).stats.total_bytes,
                "mitsuba": mi_bytes}
        ratio = {k: (mi_est if k == "mitsuba" else est[k]) / real[k] for k in real}
        assert 0.99 <= ratio["mesh"] <= 1.05 and 0.99 <= ratio["mitsuba"] <= 1.05, (kind, ratio)
        assert 1.0 <= ratio["bvh"] <= 1.4, (kind, ratio)


def _width(buf) -> int:
    return dr.width(buf) if buf is not None else 0
