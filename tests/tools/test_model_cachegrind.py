"""The locality model against valgrind's cache simulator on the real kernels (scripts/check_model_cachegrind.py),
small: a few thousand bunny rays, per_ray and layer_sorted, one D1 size."""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys

import pytest

from layerbvh_mitsuba.repo import ROOT, SCENES

# On a fresh clone this test takes ~75 s (Dr.Jit compiles the kernels again for valgrind's CPU,
# under valgrind), more than the suite's 10-minute budget has left: it runs where asked for
# (LAYERBVH_VALGRIND_TEST=1; the mutation check asks), and bench_all.sh runs the full check.
needs_valgrind = pytest.mark.skipif(
    shutil.which("valgrind") is None or shutil.which("callgrind_control") is None
    or os.environ.get("LAYERBVH_VALGRIND_TEST") != "1",
    reason="needs valgrind (Debian: apt-get install valgrind) and LAYERBVH_VALGRIND_TEST=1 (about 75 s on a "
           "fresh clone, outside the suite's time budget); bench_all.sh runs the full check")


def _check_module():
    """scripts/check_model_cachegrind.py loaded as a module (a fresh copy per call)."""
    script = ROOT / "scripts" / "check_model_cachegrind.py"
    spec = importlib.util.spec_from_file_location("check_model_cachegrind", script)
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)
    return check


@needs_valgrind
@pytest.mark.timeout(450)  # (~60 s quiet; on a loaded machine it ran past the suite's 150 s: issue 56)
def test_the_model_misses_what_valgrind_misses_on_the_per_ray_kernel(tmp_path):
    out = tmp_path / "cg.json"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "check_model_cachegrind.py"), "--mesh",
                          str(SCENES / "meshes" / "bunny.ply"), "--rays", "4000", "--d1", "32",
                          "--modes", "per_ray,layer_sorted", "--json", str(out)],
                         capture_output=True, text=True, timeout=400)
    # Exit 3: the layer mode's ratio disagrees at these 4,000 rays, as it did before the check
    # failed on it (measured at 44a6ae1: sorted / per_ray D1 model 0.98, valgrind 5.89). The
    # region difference (2N rays less N) cancels a trace call's constant host work but not the
    # steps that 2N rays take beyond N's (Python tracing each step, launches, the sort: 10,400
    # instructions per ray against per_ray's 2,700). At bench_all.sh's 20,000 rays they agree at
    # D1 32 KiB (0.72 against 0.72; docs/bench/cachegrind_bunny.json), and bench_all.sh fails
    # where they do not (issue 57 item 5).
    assert run.returncode in (0, _check_module().DISAGREES_EXIT), run.stderr[-2000:]
    doc = json.loads(out.read_text())
    rows = {(r["mode"], r["level"]): r for r in doc["rows"]}
    assert set(rows) == {(m, lv) for m in ("per_ray", "layer_sorted") for lv in ("D1", "LL")}
    # the kernels under valgrind return the model's hits, ray for ray, in both modes
    assert all(r["hits_equal"] for r in rows.values())
    # per_ray's trace call is its one kernel: the model's read misses are valgrind's, within the
    # issue's ±30% (measured: 8.3 against 8.8 in D1, 3.5 against 3.7 in LL at 20k rays)
    for level in ("D1", "LL"):
        r = rows[("per_ray", level)]
        assert r["cachegrind_misses_per_ray"] > 1.0, r
        model, valgrind = r["model_misses_per_ray"], r["cachegrind_misses_per_ray"]
        assert abs(model - valgrind) <= 0.3 * valgrind, r
    # a step's stores (keys, state records, held entries; the model replays the kernels' own, valgrind
    # also counts the sort's and the host's): both see the layer mode write more than per_ray
    for side in ("cachegrind_write_misses_per_ray", "model_write_misses_per_ray"):
        assert rows[("layer_sorted", "D1")][side] > rows[("per_ray", "D1")][side] > 0, side


def test_without_valgrind_the_check_says_so_in_one_line(tmp_path):
    env_path = str(tmp_path)  # a PATH with no valgrind on it
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "check_model_cachegrind.py"), "--mesh",
                          str(SCENES / "meshes" / "bunny.ply")], capture_output=True, text=True, timeout=120,
                         env={"PATH": env_path, "HOME": str(tmp_path)})
    assert run.returncode == 2
    assert run.stderr.strip().count("\n") == 0 and "valgrind is not installed" in run.stderr


def test_a_disturbed_measurement_is_refused():
    """Events per ray are the 2N-ray region's less the N-ray one's; more events for N rays than for
    2N means something else ran in the N-ray region (seen once: -430 read misses per ray), and the
    check must stop instead of tabulating it."""
    check = _check_module()
    a = {"D1mr": 100, "DLmr": 50, "D1mw": 10, "DLmw": 5, "Ir": 1000}
    b = {"D1mr": 300, "DLmr": 90, "D1mw": 30, "DLmw": 15, "Ir": 3000}
    assert check.region_difference(a, b, 10, "x") == {"D1": 20, "LL": 4, "D1_writes": 2, "LL_writes": 1,
                                                      "instructions": 200}
    with pytest.raises(RuntimeError, match="more events"):
        check.region_difference(b, a, 10, "per_ray, D1 32 KiB")


def test_a_disturbed_measurement_is_measured_again():
    """Issue 56: under load the check once stopped on a disturbed measurement, then passed on a
    rerun. It measures a disturbed (D1, N) pair again, at most ATTEMPTS times, before it stops."""
    check = _check_module()
    calls = []

    def disturbed_once(*args):
        calls.append(args)
        if len(calls) == 1:
            check.region_difference({"D1mr": 3, "DLmr": 3, "Ir": 3, "D1mw": 0, "DLmw": 0},
                                    {"D1mr": 1, "DLmr": 1, "Ir": 1, "D1mw": 0, "DLmw": 0},
                                    1, "per_ray, D1 32 KiB")
        return {"per_ray": {"D1": 1.0}, "lanes": 8}
    got = check.cachegrind_misses("work", 10, ["per_ray"], 32, 1024, measure=disturbed_once)
    assert got["attempts"] == 2 and got["per_ray"] == {"D1": 1.0} and len(calls) == 2
    calls.clear()

    def always(*args):
        calls.append(args)
        check.region_difference({"D1mr": 3, "DLmr": 3, "Ir": 3, "D1mw": 0, "DLmw": 0},
                                {"D1mr": 1, "DLmr": 1, "Ir": 1, "D1mw": 0, "DLmw": 0},
                                1, "per_ray, D1 32 KiB")
    with pytest.raises(RuntimeError, match=f"{check.ATTEMPTS} measurements, each disturbed"):
        check.cachegrind_misses("work", 10, ["per_ray"], 32, 1024, measure=always)
    assert len(calls) == check.ATTEMPTS >= 3


def test_a_disagreement_with_valgrind_fails_the_check(capsys):
    """Issue 57 item 5: the check exits non-zero, naming where, when the model's sorted / per_ray
    ratio is beyond the tolerance or its verdict is the other one, at any D1 size or level."""
    check = _check_module()
    agree = {"d1_kib": 32, "level": "D1", "ratio_agrees": True, "verdict_agrees": True}
    assert check.disagreement([agree, {**agree, "level": "LL"}]) == 0
    assert capsys.readouterr().err == ""
    flipped = {**agree, "d1_kib": 8, "verdict_agrees": False}  # (the 8 KiB D1 of issue 57: 0.76 against 1.07)
    off = {**agree, "level": "LL", "ratio_agrees": False}
    assert check.disagreement([agree, flipped, off]) == check.DISAGREES_EXIT != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "at D1 reads (D1 8 KiB), LL reads (D1 32 KiB)" in err, err
    # Writes are held as reads are: the model's stores against valgrind's write misses.
    assert check.disagreement([agree, {**agree, "misses": "writes", "ratio_agrees": False}]) == check.DISAGREES_EXIT
    assert "at D1 writes (D1 32 KiB)" in capsys.readouterr().err


def test_write_misses_get_verdicts_of_their_own():
    """Issue 57 item 5: sorted / per_ray is compared for write misses as for read misses, where the
    rows hold the model's write misses (a JSON from before the model's stores has none)."""
    check = _check_module()

    def row(mode, reads, writes, cg_reads, cg_writes):
        return {"mode": mode, "level": "D1", "d1_kib": 32, "model_misses_per_ray": reads,
                "cachegrind_misses_per_ray": cg_reads, "model_write_misses_per_ray": writes,
                "cachegrind_write_misses_per_ray": cg_writes}
    # (bunny, 20,000 rays, 32 KiB: reads 6.16 / 8.49 against 6.94 / 8.54; writes 2.62 / 0.51 against 6.81 / 0.69)
    got = check.verdicts([row("per_ray", 8.49, 0.51, 8.54, 0.69), row("layer_sorted", 6.16, 2.62, 6.94, 6.81)])
    by = {v["misses"]: v for v in got}
    assert set(by) == {"reads", "writes"}
    assert by["reads"]["ratio_agrees"] and by["reads"]["verdict_agrees"]
    assert abs(by["writes"]["model_ratio"] - 2.62 / 0.51) < 1e-12 and not by["writes"]["ratio_agrees"]
    assert by["writes"]["verdict_agrees"]  # both say sorting writes more
    old = [{k: v for k, v in r.items() if k != "model_write_misses_per_ray"} for r in
           (row("per_ray", 8.49, 0.51, 8.54, 0.69), row("layer_sorted", 6.16, 2.62, 6.94, 6.81))]
    assert [v["misses"] for v in check.verdicts(old)] == ["reads"]
