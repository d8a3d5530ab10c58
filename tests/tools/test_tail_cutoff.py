"""scripts/tail_cutoff.py: the step cap's model rows and CPU timings, checked against the kernel and resumable."""
from __future__ import annotations

import json

from layerbvh_mitsuba.tools.bench import tail_cutoff


def test_each_cap_is_modelled_timed_and_kept(tmp_path, capsys):
    """A point per (kind, height, k): the replay equals the kernel, k = 1 takes at most two kernel
    calls per ray, the timings keep every configuration's hits equal; a second run measures
    nothing again (the file's points are kept) and the table has a row per k."""
    out = tmp_path / "tail.json"
    args = ["--mesh", "procedural:8000", "--rays", "3000", "--steps", "1,32", "--runs", "1", "--out", str(out)]
    assert tail_cutoff.main(args) == 0
    doc = json.loads(out.read_text())
    pts = doc["points"]
    base = "procedural:8000|incoherent|K4|H8"
    assert set(pts) == {f"{base}|per_ray", f"{base}|1", f"{base}|32", f"{base}|cpu"}
    assert all(p["row"]["trace_exact"] for k, p in pts.items() if "row" in p)
    one, full = pts[f"{base}|1"]["row"], pts[f"{base}|32"]["row"]
    assert one["kernels"] == 2 and 1 < one["steps_per_ray"] <= 2 and full["steps_per_ray"] >= one["steps_per_ray"]
    assert one["break_even_bytes_per_ray_step"] is not None
    assert set(pts[f"{base}|cpu"]["seconds"]) == {"per_ray", "k1", "k32"}
    before = out.read_text()
    capsys.readouterr()
    assert tail_cutoff.main(args) == 0
    printed = capsys.readouterr().out
    assert "B/ray, steps/ray" not in printed and "|cpu:" not in printed  # nothing measured again
    assert json.loads(out.read_text())["points"] == json.loads(before)["points"]
    assert printed.count("| procedural:8000") == 2


def test_the_benchmarks_section_is_the_committed_json():
    """BENCHMARKS.md's step-cap section is generated from docs/bench/tail_cutoff.json (--benchmarks),
    never edited by hand: it regenerates without a diff."""
    from layerbvh_mitsuba import atomic
    from layerbvh_mitsuba.repo import ROOT
    doc = json.loads((ROOT / "docs" / "bench" / "tail_cutoff.json").read_text())
    assert atomic.read_section(ROOT / "BENCHMARKS.md", tail_cutoff.SECTION) == tail_cutoff.section(doc).strip()
