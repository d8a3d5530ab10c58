"""The kernel census (layerbvh/kernel_census.py, scripts/kernel_census.py) records what a process compiles and groups kernels that differ only by literals."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# Two kernels that differ only by a baked-in constant, one with another operation, and the same
# first kernel again (found in memory: not recorded).
CHILD = r"""
import drjit as dr, layerbvh
from drjit.llvm import Float
for c in (2.5, 3.5):
    dr.eval(dr.arange(Float, 1000) * c + 1)
dr.eval(dr.sqrt(dr.arange(Float, 1000)) * 2.5 + 1)
dr.eval(dr.arange(Float, 1000) * 2.5 + 1)
"""


def test_the_census_records_compiles_and_groups_literal_variants(tmp_path):
    folder = tmp_path / "census"
    env = dict(os.environ, LAYERBVH_KERNEL_CENSUS=str(folder), HOME=str(tmp_path))  # (an empty kernel cache)
    subprocess.run([sys.executable, "-c", CHILD], check=True, env=env, cwd=ROOT, timeout=120)
    rows = [json.loads(line) for f in folder.glob("*.jsonl") for line in f.read_text().splitlines()]
    assert len(rows) == 3 and not any(r["disk"] for r in rows), rows
    assert rows[0]["family"] == rows[1]["family"] != rows[2]["family"]
    assert rows[0]["hash"] != rows[1]["hash"]
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import kernel_census
    finally:
        sys.path.pop(0)
    c = kernel_census.census(rows)
    assert c["distinct_kernels"] == 3
    assert [f["kernels"] for f in c["literal_families"]] == [2]
