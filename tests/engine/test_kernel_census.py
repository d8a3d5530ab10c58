"""The kernel census (layerbvh/kernel_census.py, scripts/kernel_census.py) records what a process compiles and groups
kernels that differ only by literals."""
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


def test_a_literal_inside_a_called_function_keeps_the_family():
    """A virtual call's target is named by a hash of its code: two kernels that differ only by a
    constant inside it (a medium's density) differ in that name too, and are one family."""
    from layerbvh import kernel_census

    def ir(name, value):
        return (f"call fastcc @func_{name}(<8 x float> %f1)\ndefine fastcc @func_{name}(<8 x float> %in_0) {{\n"
                f"  %f2 = fmul <8 x float> %in_0, {value}\n}}\n")
    a, b = ir("3d7133ddaf712eb2e0b32e0290247036", "2.0e+02"), ir("f45533560a403a474488185260488fd6", "1.0e-04")
    assert kernel_census.family(a) == kernel_census.family(b)
    assert kernel_census.family(a) != kernel_census.family(a.replace("fmul", "fadd"))
