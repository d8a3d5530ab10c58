"""The GPU check's device half and its report: the device script's kernel listing, run here on the LLVM backend, is
what gpu_report splits into traversal, stack-move and sort time."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT
from layerbvh_mitsuba.tools.bench import gpu_report


@pytest.fixture(scope="module")
def listing(tmp_path_factory):
    """`gpu_check_device.py --kernels` on a small soup (20k rays: several steps before the tail), binary tree at
    height 4, on the CPU."""
    folder = tmp_path_factory.mktemp("gpu_check")
    (folder / "model.json").write_text(json.dumps({"configs": [[2, 4]]}))
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu_check_device.py"), str(folder), "--backend",
                          "llvm", "--kernels", "20000", "--soup", "4000"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


def test_the_kernel_listing_splits_into_the_sorted_paths_stages(listing):
    rows = {r["mode"]: r for r in gpu_report.kernel_split(listing)}
    assert set(rows) == {"per_ray", "layer_sorted"}
    p, s = rows["per_ray"], rows["layer_sorted"]
    # per_ray is one traversal kernel and a few set-up launches; nothing is sorted or moved
    assert p["steps"] == 1 and p["between_ms"] == 0 and p["sort_ms"] == 0
    # the sorted path: one traversal kernel per wavefront step, then straight to a counting sort
    # (MkPerm): the step kernel wrote the entries its rays hold, no kernel moves them (entry 45);
    # by default one step, then the per-ray tail (PERFORMANCE.md entry 61)
    assert s["steps"] == layerbvh.TAIL_STEPS + 1 and s["between_ms"] == 0 and s["sort_ms"] > 0
    split = s["traversal_ms"] + s["between_ms"] + s["sort_ms"] + s["rest_ms"]
    assert split == pytest.approx(s["kernels_ms"], rel=0.02, abs=0.05)  # every launch counted once
    assert s["host_gaps_ms"] == pytest.approx(s["wall_ms"] - s["kernels_ms"])
    assert s["launches"] > p["launches"]


def test_a_launch_between_a_step_and_its_sort_is_counted_apart():
    """(The H200 listings were made when a kernel moved the held entries after each step.)"""
    text = "\n".join([
        "K=2 H=8 layer_sorted: 10 rays, 6 launches, kernels 7.00 ms of 9.00 ms wall",
        "   KernelType.JIT         width         10 ops     35 in   6 out   1    0.500 ms",
        "   KernelType.JIT         width         10 ops    700 in  18 out   7    3.000 ms",
        "   KernelType.JIT         width        160 ops     27 in   8 out   2    1.000 ms",
        "   KernelType.MkPerm      width         10 ops      0 in   1 out   1    0.250 ms",
        "   KernelType.JIT         width         10 ops     12 in   2 out   1    0.250 ms",
        "   KernelType.JIT         width          6 ops    700 in  13 out   1    2.000 ms"])
    (r,) = gpu_report.kernel_split(text)
    assert (r["traversal_ms"], r["steps"], r["between_ms"], r["sort_ms"], r["rest_ms"]) == (5.0, 2, 1.0, 0.25, 0.75)
    assert r["host_gaps_ms"] == 2.0


def test_the_committed_gpu_section_is_what_the_report_writes():
    """BENCHMARKS.md's GPU section is generated from docs/bench/gpu_h200, never edited by hand."""
    have = atomic.read_section(ROOT / "BENCHMARKS.md", gpu_report.GPU_SECTION)
    assert have is not None and have == gpu_report.section(gpu_report.DEFAULT_FOLDER).strip()


def test_the_device_half_prints_each_steps_split(capsys):
    """Issue 57 item 4: per step, its rays, tracing, kernels and sort (layerbvh.stats.StepTime), the tail named."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import gpu_check_device
    finally:
        sys.path.pop(0)
    gpu_check_device.print_steps({"step_times": [
        {"rays": 1_000_000, "trace_s": 0.004, "kernel_s": 0.0031, "sort_s": 0.0005, "tail": False},
        {"rays": 2_000, "trace_s": 0.0001, "kernel_s": 0.0002, "sort_s": 0.0, "tail": True}]})
    out = capsys.readouterr().out.splitlines()
    assert "step 1: 1,000,000 rays; trace 4.00 ms, kernels 3.10 ms, sort 0.50 ms" in out[0]
    assert "step 2 (tail): 2,000 rays" in out[1]
