"""How near its threshold each same-seed check and verdict of the test suite sits, per LLVM ISA (issue 64).

A test that asserts a same-seed criterion or a verdict label passes on one CPU and may fail on
another when float rounding (Embree's ISA path, Dr.Jit's LLVM vector width, FMA contraction)
moves a few paths. This script runs (part of) the suite with LAYERBVH_VERDICT_LOG set, once per
LLVM ISA this CPU can compile for (LAYERBVH_LLVM_ISA: avx512 and avx2 on an AVX-512 CPU), and
tabulates for each test the worst share of pixels within the same-seed tolerance, its margin
over the threshold, the labels it got, and whether the ISAs disagree. Embree's ISA cannot be
chosen (layerbvh/backend.py), so a case the two LLVM runs agree on may still differ on another
CPU: the margin column is what to read.

  .venv/bin/python scripts/cpu_margins.py run [--isa avx2 avx512] [-- PYTEST ARGS]   # resumable: a finished ISA is kept
  .venv/bin/python scripts/cpu_margins.py table                                       # from the logs
Logs and the table's JSON go to docs/cpu_margins/ (LOG_DIR).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOG_DIR = ROOT / "docs" / "cpu_margins"
# A same-seed check that passed is "near" its threshold when some pixel is already outside the
# tolerance (paths diverged there: at 0.999, a 32x32 film has room for one such pixel, and
# another CPU's rounding may move one more), or when its mean |diff| is above this share of the
# mean-|diff| bound.
NEAR_MEAN = 0.3


def _python() -> str:
    venv = ROOT / ".venv" / "bin" / "python"
    return str(venv) if venv.exists() else sys.executable


def run(isas: list[str], pytest_args: list[str]) -> None:
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    for isa in isas:
        done = LOG_DIR / f"{isa}.done.json"
        if done.exists():
            print(f"{isa}: kept ({done.relative_to(ROOT)}); delete it to run again")
            continue
        log = LOG_DIR / f"{isa}.jsonl"
        part = log.with_suffix(".jsonl.part")
        part.unlink(missing_ok=True)
        env = {**os.environ, "LAYERBVH_VERDICT_LOG": str(part), "LAYERBVH_LLVM_ISA": isa}
        cmd = [_python(), "-m", "pytest", "-q", "-n", "2", "--dist", "loadfile", "-p", "no:cacheprovider",
               *pytest_args]
        t0 = time.time()
        rc = subprocess.call(cmd, cwd=ROOT, env=env)
        part.replace(log)  # write, then rename
        meta = {"isa": isa, "rc": rc, "seconds": round(time.time() - t0, 1), "pytest_args": pytest_args,
                "cpu": _cpu(isa)}
        tmp = done.with_suffix(".tmp")
        tmp.write_text(json.dumps(meta, indent=1))
        tmp.replace(done)
        print(f"{isa}: pytest exited {rc} in {meta['seconds']} s; log {log.relative_to(ROOT)}")


def _cpu(isa: str) -> dict:
    out = subprocess.run([_python(), "-c", "import layerbvh as L; print(L.cpu_model()); print(L.llvm_isa()); "
                          "print(L.llvm_vector_width())"], capture_output=True, text=True,
                         env={**os.environ, "LAYERBVH_LLVM_ISA": isa}, cwd=ROOT)
    model, got, lanes = (out.stdout.strip().splitlines() + ["?"] * 3)[:3]
    return {"model": model, "llvm_isa": got, "lanes": lanes}


def _read(isa: str) -> list[dict]:
    log = LOG_DIR / f"{isa}.jsonl"
    return [json.loads(ln) for ln in log.read_text().splitlines() if ln.strip()] if log.exists() else []


def table() -> dict:
    isas = sorted(p.name.split(".")[0] for p in LOG_DIR.glob("*.done.json"))
    rows: dict[str, dict] = defaultdict(lambda: {"same_seed": {}, "labels": {}})
    for isa in isas:
        for rec in _read(isa):
            row = rows[rec["test"]]
            if rec["kind"] == "same_seed":
                margin_frac = rec["frac_within"] - rec["min_frac"]
                mean_share = rec["mean_abs"] / max(rec["max_mean_rel"] * rec["mean_ref"], 1e-30)
                prev = row["same_seed"].get(isa)
                # Keep the check nearest its threshold among those that passed, else the failing one.
                cur = {"passed": rec["passed"], "frac_within": rec["frac_within"], "margin_frac": margin_frac,
                       "mean_share": mean_share}
                if prev is None or (cur["passed"] and prev["passed"] and margin_frac < prev["margin_frac"]):
                    row["same_seed"][isa] = cur
            else:
                row["labels"].setdefault(isa, set()).add(rec["label"])
    out = {}
    for test, row in sorted(rows.items()):
        ss = row["same_seed"]
        labels = {isa: sorted(v) for isa, v in row["labels"].items()}
        near = any(v["passed"] and (v["frac_within"] < 1.0 or v["mean_share"] > NEAR_MEAN) for v in ss.values())
        split = len({json.dumps(v) for v in labels.values()}) > 1 or len({v["passed"] for v in ss.values()}) > 1
        out[test] = {"same_seed": ss, "labels": labels, "near": near, "isas_disagree": split}
    meta = {isa: json.loads((LOG_DIR / f"{isa}.done.json").read_text()) for isa in isas}
    result = {"isas": meta, "near_mean": NEAR_MEAN, "tests": out}
    tmp = LOG_DIR / "table.json.tmp"
    tmp.write_text(json.dumps(result, indent=1))
    tmp.replace(LOG_DIR / "table.json")
    _print(result)
    return result


def _print(result: dict) -> None:
    lines = _lines(result)
    print("\n".join(lines))
    tmp = LOG_DIR / "table.md.tmp"
    tmp.write_text("# Same-seed margins per LLVM ISA (scripts/cpu_margins.py table)\n\n" + "\n".join(lines) + "\n")
    tmp.replace(LOG_DIR / "table.md")


def _lines(result: dict) -> list[str]:
    out = []
    add = out.append  # (the table's lines, for the terminal and table.md)
    for isa, m in result["isas"].items():
        add(f"# {isa}: {m['cpu']['model']}, LLVM {m['cpu']['llvm_isa']} {m['cpu']['lanes']} lanes; "
            f"pytest rc {m['rc']} in {m['seconds']} s")
    add("")
    add("Tests near a threshold (a pixel already outside the same-seed tolerance, or mean |diff| above "
        f"{NEAR_MEAN:g} of its bound, judged by the default criterion: a test with its own tolerance may have "
        "more room) or whose outcome differs between the ISAs:")
    add("")
    add("| test | " + " | ".join(f"{isa} within (margin) / mean share" for isa in result["isas"])
        + " | labels | flag |")
    add("|---|" + "---|" * (len(result["isas"]) + 2))
    for test, r in result["tests"].items():
        cells = []
        for isa in result["isas"]:
            v = r["same_seed"].get(isa)
            cells.append("-" if v is None else f"{100 * v['frac_within']:.2f}% ({100 * v['margin_frac']:+.2f}) / "
                         f"{v['mean_share']:.2f}{'' if v['passed'] else ' FAIL'}")
        labels = "; ".join(f"{isa}: {', '.join(v)}" for isa, v in r["labels"].items())
        flag = " ".join(f for f, on in (("NEAR", r["near"]), ("ISA-SPLIT", r["isas_disagree"])) if on)
        if r["near"] or r["isas_disagree"] or "--all" in sys.argv:
            add(f"| {test} | " + " | ".join(cells) + f" | {labels} | {flag} |")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--isa", nargs="+", default=["avx512", "avx2"])
    r.add_argument("pytest_args", nargs="*")
    t = sub.add_parser("table")
    t.add_argument("--all", action="store_true", help="every test, not only those near a threshold or split")
    a = ap.parse_args(argv)
    if a.cmd == "run":
        run(a.isa, a.pytest_args)
    else:
        table()


if __name__ == "__main__":
    main()
