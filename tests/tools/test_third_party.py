"""The third-party A/B script: one row per scene with a verdict, instanced scenes traced, refusals by plugin name,
atomic outputs (project scenes only)."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import mitsuba as mi

from layerbvh_mitsuba.ab.metrics import SAME_PATHS
from layerbvh_mitsuba.ab.scene_integrator import path_props

ROOT = Path(__file__).resolve().parents[2]

INSTANCED = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="-1"/></integrator>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="constant"/>
  <shape type="shapegroup" id="grp"><shape type="cube"/></shape>
  <shape type="instance" id="inst1"><ref id="grp"/></shape>
</scene>"""


CURVE = """<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>
  <emitter type="constant"/>
  <shape type="linearcurve" id="hair"><string name="filename" value="curve.txt"/></shape>
</scene>"""


def test_max_depth_minus_one_survives_the_uint32_round_trip():
    scene = mi.load_string(INSTANCED.replace('<shape type="instance" id="inst1"><ref id="grp"/></shape>', "")
                           .replace('<shape type="shapegroup" id="grp"><shape type="cube"/></shape>',
                                    '<shape type="cube"/>'))
    assert path_props(mi, scene)["max_depth"] == -1


def test_table_has_a_verdict_per_scene_and_names_refused_plugins(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (root / "instanced.xml").write_text(INSTANCED)
    (root / "curve.xml").write_text(CURVE)
    (root / "curve.txt").write_text("-1 0 0 0.1\n0 0.5 0 0.1\n1 0 0 0.1\n")
    cbox = (ROOT / "scenes" / "cbox.xml").read_text()
    (root / "cbox.xml").write_text(cbox)
    # Mitsuba's test scenes wrap their integrator in `moment`; this one wraps `direct`.
    (root / "direct.xml").write_text(re.sub(r'<integrator type="path">.*?</integrator>',
                                            '<integrator type="moment"><integrator type="direct"/></integrator>',
                                            cbox, count=1, flags=re.S))
    md, js = tmp_path / "table.md", tmp_path / "table.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "third_party.py"), "--root", str(root),
                           "--scenes", "cbox.xml", "direct.xml", "instanced.xml", "curve.xml", "missing/*.xml",
                           "cbox.xml@ptracer", "cbox.xml@prb_projective", "--res", "16", "16",
                           "--spp", "4", "--check-rays", "20000", "--md", str(md), "--json", str(js),
                           "--out", str(tmp_path / "sweep"), "--workers", "2"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    rows = {r["scene"]: r for r in json.loads(js.read_text())["scenes"]}
    assert rows["cbox.xml"]["result"] == SAME_PATHS, rows["cbox.xml"]
    assert rows["cbox.xml"]["same_seed"]["frac_within_1e-3"] >= 0.999
    # The scene's own integrator where ours mirrors it: moment(direct) on both sides, ours inside.
    assert rows["direct.xml"]["compared_as"] == "moment(direct)" and rows["direct.xml"]["result"] == SAME_PATHS, \
        rows["direct.xml"]
    # The ray check traced real rays, and every disagreement with Embree is a tie (block bottoms on the floor).
    rc = rows["cbox.xml"]["ray_check"]
    assert rc["rays"] == 20000 and rc["other_prim"] == rc["ties"], rc
    # Instances are traced (and their placed triangles checked ray by ray against Embree).
    assert rows["instanced.xml"]["result"] == SAME_PATHS, rows["instanced.xml"]
    assert rows["instanced.xml"]["ray_check"]["other_prim"] == rows["instanced.xml"]["ray_check"]["ties"]
    # SCENE@INTEGRATOR: the scene rendered with that integrator at its own depths; one we do not mirror is refused.
    lt = rows["cbox.xml@ptracer"]
    assert (lt["compared_as"], lt["result"], lt["integrator"]["max_depth"]) == ("ptracer", SAME_PATHS, 8), lt
    assert "rendered with ptracer instead of the scene's path (max_depth=8" in lt["notes"][0], lt["notes"]
    assert rows["cbox.xml@prb_projective"]["result"].startswith("refused: the scene's integrator is prb_projective")
    refused = rows["curve.xml"]["result"]
    assert refused.startswith("refused:") and "'linearcurve'" in refused and "hair" in refused
    table = md.read_text()
    assert "| `cbox.xml` | 36 | - | path |" in table and "| moment(direct) |" in table
    assert "Not found under root (skipped): `missing/*.xml`" in table
    assert not list(tmp_path.glob(".*.tmp*")), "temporary files left behind"
    # Each scene was a point of the sweep (its own process), with its row in the sweep's table too.
    sweep_rows = {r["scene"]: r for r in json.loads((tmp_path / "sweep" / "results.json").read_text())["rows"]}
    assert sweep_rows["cbox.xml"]["result"] == sweep_rows["instanced.xml"]["result"] == SAME_PATHS
    assert sweep_rows["curve.xml"]["result"] == refused
    assert all(r["host"] and r["status"] == "ok" for r in sweep_rows.values())
