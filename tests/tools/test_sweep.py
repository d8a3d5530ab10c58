"""`layerbvh sweep`: one row per point equal to the single command's, resumable by key, failures as rows, timed
points one at a time, an external Dask scheduler."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import layerbvh
from layerbvh_mitsuba.tools.sweep import runner, store
from layerbvh_mitsuba.cli import main
from layerbvh_mitsuba.ab.metrics import AGREES, SAME_PATHS

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes"
TINY = ["--spp", "2", "--res", "16", "12", "--no-progress"]
METRICS = ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs", "mean_abs")
STARTUP_S = 60  # deadline for the external scheduler and worker to come up


def _rows(out: Path) -> list[dict]:
    return json.loads((out / "results.json").read_text())["rows"]


def _last_run(out: Path) -> dict:
    return json.loads((out / "runs.json").read_text())["runs"][-1]


def _no_temporaries(out: Path) -> None:
    assert not [p for p in out.rglob("*") if p.name.startswith((".tmp", ".old-")) or ".tmp" in p.suffixes]


def test_compare_grid_matches_single_commands_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    scenes = [SCENES / "sphere_box.xml"]
    argv = ["sweep", *map(str, scenes), "--job", "compare", "--traversal", "per_ray,layer_sorted", *TINY,
            "--out", str(out), "--workers", "2"]
    assert main(argv) == 0
    rows = _rows(out)
    assert [(Path(r["scene"]).name, r["config"]) for r in rows] == [
        (s.name, f"{t} K={layerbvh.DEFAULT_BRANCHING} h=8") for s in scenes for t in ("per_ray", "layer_sorted")]
    assert all(r["status"] == "ok" and r["verdict"] in (SAME_PATHS, AGREES) and r["host"] for r in rows), rows
    # Each row states what its verdict rules out (issue 55): a relative bias of the image mean.
    assert all(0 < r["mde_image"] < 0.05 for r in rows), [r["mde_image"] for r in rows]
    assert sorted(_last_run(out)["ran"]) == sorted(r["key"] for r in rows)

    # The same point as one `layerbvh compare` (its own process is not needed: same seed, same images).
    for r in rows:  # (sphere_box: no coplanar ties in view)
        single = tmp_path / f"single-{r['key'][:8]}"
        scene = next(s for s in scenes if s.name == Path(r["scene"]).name)
        assert main(["compare", str(scene), "--traversal", r["config"].split()[0], *TINY, "--out", str(single)]) == 0
        rep = json.loads((single / "report.json").read_text())
        assert {k: r[k] for k in METRICS} == {k: rep["metrics"][k] for k in METRICS}
        assert r["triangles"] == rep["traversal"]["bvh"]["triangles"] and r["resolution"] == rep["resolution"]
        assert (out / r["report"]).is_file() and r["report"].endswith("compare/index.html")
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 3 and csv_lines[0].startswith("scene,config,spp,resolution,status,error,triangles,host")
    for name in ("summary.md", "index.html"):
        text = (out / name).read_text()
        assert all(r["report"] in text for r in rows), name

    # Same arguments again: nothing runs.
    assert main(argv) == 0
    again = _last_run(out)
    assert again["ran"] == [] and sorted(again["reused"]) == sorted(r["key"] for r in rows)
    assert [r["ran"] for r in _rows(out)] == ["reused"] * 2

    # One point's result deleted: only that point runs, and it gives the same figures.
    victim = rows[1]
    shutil.rmtree(out / victim["dir"])
    assert main(argv) == 0
    assert _last_run(out)["ran"] == [victim["key"]]
    redone = next(r for r in _rows(out) if r["key"] == victim["key"])
    assert redone["ran"] == "this run" and {k: redone[k] for k in METRICS} == {k: victim[k] for k in METRICS}
    _no_temporaries(out)


def test_timed_points_run_one_at_a_time_and_merge_per_scene(tmp_path):
    out = tmp_path / "conv"
    assert main(["sweep", str(SCENES / "cbox.xml"), "--job", "converge", "--configs", "stock,per_ray",
                 "--budget", "0.2", "--ref-spp", "16", "--max-spp", "2", "--res", "8", "6", "--out", str(out),
                 "--workers", "2", "--no-progress"]) == 0
    rows = _rows(out)
    assert [r["config"] for r in rows] == ["stock", "per_ray"] and all(r["status"] == "ok" for r in rows)
    assert all(r["triangles"] == 36 and r["spp_reached"] >= 1 for r in rows)
    # Two idle workers, yet the two timed points did not overlap (the 'exclusive' resource).
    spans = sorted((r["start_time"], r["end_time"]) for r in
                   (json.loads((out / row["dir"] / "result.json").read_text()) for row in rows))
    assert spans[0][1] <= spans[1][0], spans
    merged = json.loads((out / "converge" / "cbox" / "convergence.json").read_text())
    assert [c["name"] for c in merged["configs"]] == ["stock", "per_ray"]
    assert set(merged["table"]["rows"]) == {"stock", "per_ray"}
    assert merged["table"]["base"] == "stock" and (out / "converge" / "cbox" / "convergence.png").is_file()
    for r in rows:  # the row's equal-time figures are the merged table's (None where a fit has no falling slope)
        assert r["rel_mse_at_equal_time"] == merged["table"]["rows"][r["config"]]["rel_mse_at_equal_time"]


def test_failures_are_rows_and_an_external_scheduler_runs_the_points(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><bsdf type="no_such_bsdf" id="b"/></scene>')
    dask = Path(sys.executable).parent / "dask"
    sched_file = tmp_path / "scheduler.json"
    logs = tmp_path / "dask.log"
    procs = []
    with open(logs, "wb") as log:
        try:
            procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                           "--scheduler-file", sched_file], stdout=log, stderr=log))
            deadline = time.monotonic() + STARTUP_S
            while not (sched_file.is_file() and sched_file.stat().st_size):
                assert time.monotonic() < deadline and procs[0].poll() is None, logs.read_text()
                time.sleep(0.1)
            address = json.loads(sched_file.read_text())["address"]  # the scheduler removes the file when it stops
            procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", sched_file, "--host", "127.0.0.1",
                                           "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                           "--resources", "exclusive=1", "--memory-limit", "0"],
                                          stdout=log, stderr=log))
            out = tmp_path / "ext"
            assert main(["sweep", str(SCENES / "cbox.xml"), str(bad), "--job", "compare", "--traversal", "per_ray",
                         *TINY, "--out", str(out), "--scheduler", str(sched_file)]) == 1  # a point failed
        finally:
            for p in reversed(procs):
                p.terminate()
            for p in reversed(procs):
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(30)
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["ok", "error"], rows
    assert rows[0]["verdict"] in (SAME_PATHS, AGREES), rows[0]["verdict"]
    assert "cannot load scene" in rows[1]["error"] and "no_such_bsdf" in rows[1]["error"]
    assert "\n" not in rows[1]["error"] and rows[1]["report"].endswith("log.txt")
    assert address.startswith("tcp://127.0.0.1:")
    assert json.loads((out / "results.json").read_text())["cluster"]["scheduler"] == address
    assert "no_such_bsdf" in (out / "summary.md").read_text()
    assert _last_run(out)["failed"] == [rows[1]["key"]]


def test_sigterm_stops_a_sweep_as_ctrl_c_does(tmp_path):
    """Issue 56: SIGTERM (a scheduler's stop, `kill`) killed the sweep outright: stored rows were
    kept, but its Dask processes left "leaked semaphore objects" warnings. Now it stops as on
    Ctrl-C: the stored point kept and in the tables, one line, exit 143, no process left behind.
    Dask's default dashboard port is held meanwhile, as another sweep running beside this one would
    hold it: the sweep's own cluster must not warn that it is taken (it did: dashboard_address)."""
    import psutil
    import socket
    out = tmp_path / "sw"
    beside = socket.socket()
    try:
        beside.bind(("127.0.0.1", 8787))
        beside.listen()
    except OSError:  # (already held: by another sweep, the same test's condition)
        pass
    p = subprocess.Popen([sys.executable, "-m", "layerbvh_mitsuba.cli", "sweep", str(SCENES / "cbox.xml"), "--job",
                          "compare", "--traversal", "per_ray,layer_sorted,layer_unsorted", *TINY, "--workers", "1",
                          "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list((out / "points").glob("*/result.json")) and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.1)
    children = psutil.Process(p.pid).children(recursive=True)
    p.terminate()
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    stored = len(list((out / "points").glob("*/result.json")))
    assert err.strip().splitlines() == [f"layerbvh: interrupted; {stored} of 3 points stored, tables written"], err
    assert stored >= 1 and len([r for r in _rows(out) if r["status"] == "ok"]) == stored
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, [c.cmdline() for c in alive]
    beside.close()


def test_a_point_over_its_memory_limit_is_killed_and_recorded():
    [point] = store.make_points("compare", [(str(SCENES / "cbox.xml"), "cbox.xml")],
                                [{"traversal": "per_ray", "treelet_height": 8, "spp": 2, "res": [16, 12], "seed": 0,
                                  "variant": "llvm_ad_rgb"}])
    # A Mitsuba process always holds far more than 32 MiB: the limit must trip.
    run = runner.run_point_task(asdict(point), asdict(runner.Limits(memory_bytes=32 << 20)))
    assert run["status"] == "killed" and run["error"].startswith("killed: resident memory"), run
    assert run["peak_rss_bytes"] > 32 << 20 and "log.txt" in run["files"]


def test_bad_sweep_input_gives_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "o"

    def err(argv):
        assert main(["sweep", *argv, "--out", str(out), "--no-progress"]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("layerbvh: error:"), lines
        return lines[0]
    assert "scene file not found" in err([str(tmp_path / "missing.xml"), "--job", "compare"])
    assert "no scene file matches" in err([str(tmp_path / "*.xml"), "--job", "compare"])
    assert "--budget does not apply to --job compare" in err([str(SCENES / "cbox.xml"), "--job", "compare",
                                                                "--budget", "3"])
    assert "--traversal" in err([str(SCENES / "cbox.xml"), "--job", "compare", "--traversal", "per_ray,fast"])
    assert "--budget" in err([str(SCENES / "cbox.xml"), "--job", "converge"])
    assert "--rays" in err([str(SCENES / "cbox.xml"), "--job", "bench", "--rays", "sideways"])
    assert "--seed must be from 0" in err([str(SCENES / "cbox.xml"), "--job", "compare", "--seed", "4294967296"])
    assert not out.exists()
    # Issue 56: --out an existing file was an internal error; a folder of the user's own files
    # (no runs.json: not a sweep's) had its index.html, results.csv and summary.md overwritten.
    out.write_text("mine")
    assert "exists and is not a folder" in err([str(SCENES / "cbox.xml"), "--job", "compare"])
    out.unlink()
    out.mkdir()
    for name in ("index.html", "results.csv", "summary.md"):
        (out / name).write_text("mine")
    assert "not a layerbvh output (no runs.json)" in err([str(SCENES / "cbox.xml"), "--job", "compare"])
    assert sorted(p.name for p in out.iterdir()) == ["index.html", "results.csv", "summary.md"]
    assert all((out / p).read_text() == "mine" for p in ("index.html", "results.csv", "summary.md"))
