"""The robustness cases of the command line: what a user or a hostile tester does, run as they would
(a subprocess), each with its expected outcome.

Every case is a function `case() -> Outcome` registered in CASES. It runs `layerbvh` in a
fresh process on small scenes written to a temporary folder, then checks the exit code, the
one line on stderr, what is (not) left on disk and, where the case renders, the image against
stock Mitsuba. `tests/tools/test_robustness.py` asserts each; `scripts/stability_report.py` lists them
in STABILITY.md.
"""
from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import mitsuba as mi
import numpy as np

from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.render import SPP_PER_PASS, use_variant
from layerbvh_mitsuba.repo import SCENES

TIMEOUT_S = 300  # bound on any one command; a case that needs it has failed


@dataclass
class Outcome:
    case: str
    passed: bool
    outcome: str  # what happened, in one line (exit code, the message, what is on disk)


@dataclass
class Case:
    name: str
    what: str  # what the user does
    expected: str
    run: Callable[[Path], Outcome]


CASES: dict[str, Case] = {}


def case(name: str, what: str, expected: str):
    def register(fn):
        CASES[name] = Case(name, what, expected, fn)
        return fn
    return register


def run_case(name: str) -> Outcome:
    with tempfile.TemporaryDirectory(prefix=f"layerbvh-{name}-") as tmp:
        return CASES[name].run(Path(tmp))


# -- running the command line ------------------------------------------------------------------------


@dataclass
class Run:
    code: int
    stdout: str
    stderr: str

    @property
    def error_lines(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines() if ln.startswith("layerbvh:")]


def layerbvh(*args, limit_bytes: int | None = None, timeout: float = TIMEOUT_S) -> Run:
    """`layerbvh ARGS` in a fresh process (optionally under an address-space limit)."""
    def limit():
        if limit_bytes is not None:
            resource.setrlimit(resource.RLIMIT_AS, (limit_bytes, limit_bytes))
    p = subprocess.run([sys.executable, "-m", "layerbvh_mitsuba.cli", *map(str, args), "--no-progress"],
                       capture_output=True, text=True, timeout=timeout, preexec_fn=limit)
    return Run(p.returncode, p.stdout, p.stderr)


def leftovers(folder: Path) -> list[str]:
    """Temporary files or folders an output writer left behind."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") and ("tmp" in p.name or "old" in p.name))


def one_line(r: Run, code: int, *words: str) -> tuple[bool, str]:
    """Exit `code` with exactly one `layerbvh: ...` line on stderr containing every word."""
    lines = r.error_lines
    ok = r.code == code and len(lines) == 1 and all(w in lines[0] for w in words) and "Traceback" not in r.stderr
    return ok, f"exit {r.code}: {lines[0] if lines else r.stderr.strip().splitlines()[-1:] or '(nothing)'}"


def report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


def scene_file(folder: Path, name: str, body: str, res: int = 16, spp: int = 4) -> Path:
    path = folder / f"{name}.xml"
    path.write_text(f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/>
      <rfilter type="box"/></film>
    <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler></sensor>
  {body}
</scene>""")
    return path


LIT_QUAD = """<shape type="rectangle" id="floor">
    <transform name="to_world"><translate z="-1"/><scale value="3"/></transform></shape>
  <shape type="rectangle" id="lamp"><transform name="to_world"><translate y="0.5"/><scale value="0.4"/></transform>
    <emitter type="area"><rgb name="radiance" value="8"/></emitter></shape>"""


# -- the cases ---------------------------------------------------------------------------------------


@case("scene_path_settings", "compare a scene whose path integrator sets hide_emitters=true and max_depth=3",
      "both sides render with the scene's settings (the light is hidden in both); report.json lists them")
def scene_path_settings(tmp: Path) -> Outcome:
    scene = scene_file(tmp, "hidden", f"""<integrator type="path"><integer name="max_depth" value="3"/>
    <boolean name="hide_emitters" value="true"/></integrator>
  {LIT_QUAD}""")
    r = layerbvh("compare", scene, "--out", tmp / "cmp", "--traversal", "per_ray")
    rep = report(tmp / "cmp") if r.code == 0 else {}
    props = rep.get("integrator", {})
    hidden = bool(rep) and props.get("hide_emitters") is True and props.get("max_depth") == 3
    same = bool(rep) and rep["metrics"]["frac_pixels_over_1e-3"] <= 0.001
    return Outcome("scene_path_settings", r.code == 0 and hidden and same,
                   f"exit {r.code}; integrator in report.json {props}; pixels over 1e-3 "
                   f"{rep.get('metrics', {}).get('frac_pixels_over_1e-3')}")


@case("non_path_integrator", "compare a scene whose integrator is prb_projective (one we do not mirror), with and "
      "without --as-path",
      "refused in one line naming prb_projective; with --as-path both sides render path with its max_depth, "
      "and report.json and index.html say so")
def non_path_integrator(tmp: Path) -> Outcome:
    scene = scene_file(tmp, "prb_projective", f"""<integrator type="prb_projective">
    <integer name="max_depth" value="4"/></integrator>
  {LIT_QUAD}""")
    refused = layerbvh("compare", scene, "--out", tmp / "cmp")
    ok1, line = one_line(refused, 2, "prb_projective", "--as-path")
    ok1 &= not (tmp / "cmp").exists()
    r = layerbvh("compare", scene, "--out", tmp / "cmp", "--as-path")
    rep = report(tmp / "cmp") if r.code == 0 else {}
    ok2 = (rep.get("scene_integrator") == "prb_projective" and rep.get("compared_as") == "path (--as-path)"
           and rep.get("integrator", {}).get("max_depth") == 4
           and "--as-path" in (tmp / "cmp" / "index.html").read_text())
    return Outcome("non_path_integrator", ok1 and ok2,
                   f"without --as-path {line}; with it exit {r.code}, "
                   f"scene_integrator {rep.get('scene_integrator')!r}, "
                   f"compared_as {rep.get('compared_as')!r}")


@case("ctrl_c", "Ctrl-C (SIGINT) during `layerbvh render` of 40 passes",
      "stops within one pass, exit 130, one line, no output file and no temporary file")
def ctrl_c(tmp: Path) -> Outcome:
    out = tmp / "x.exr"
    # Progress on: the bar's first line on stderr says rendering has started.
    p = subprocess.Popen([sys.executable, "-m", "layerbvh_mitsuba.cli", "render", str(SCENES / "cbox.xml"),
                          "--spp", str(40 * 64), "--res", "48", "48", "--traversal", "per_ray", "-o", str(out)],
                         stderr=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0,
                         # As from a terminal: a shell's background job (CI runners, `cmd &`)
                         # starts with SIGINT ignored, which the child would inherit.
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + TIMEOUT_S
    seen = ""
    # Unbuffered byte reads: communicate() below reads the raw pipe, so anything a buffered
    # reader had pulled in beyond "spp" would be lost and two lines would seem to merge.
    while "spp" not in seen and time.monotonic() < deadline and p.poll() is None:
        seen += os.read(p.stderr.fileno(), 1).decode(errors="replace")
    p.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    try:
        _, err = p.communicate(timeout=TIMEOUT_S)
        err = err.decode(errors="replace")
    except subprocess.TimeoutExpired:
        p.kill()
        return Outcome("ctrl_c", False, "still running after SIGINT")
    stopped_in = time.monotonic() - t0
    out_lines = (seen + err).replace("\r", "\n").splitlines()
    lines = [ln for ln in out_lines if ln.startswith("layerbvh:") and "%|" not in ln]
    done = [ln for ln in out_lines if "spp" in ln]
    # "Within one pass", counted in samples rather than seconds: the progress bar may have gone at
    # most one pass (64 spp) beyond what it showed when SIGINT was sent.
    at_signal, at_end = progress_spp(seen), progress_spp(seen + err)
    one_pass = at_signal is not None and at_end is not None and at_end <= at_signal + SPP_PER_PASS
    ok = p.returncode == 130 and lines == ["layerbvh: interrupted; nothing written"] and not out.exists() \
        and not leftovers(tmp) and one_pass
    return Outcome("ctrl_c", ok, f"exit {p.returncode} {stopped_in:.1f} s after SIGINT: {lines}; progress {at_signal} "
                                 f"spp at SIGINT, {at_end} at the end (one pass: {SPP_PER_PASS}); last progress "
                                 f"{done[-1].strip() if done else '-'}; output left: {out.exists() or leftovers(tmp)}")


def progress_spp(text: str) -> int | None:
    """The largest sample count a tqdm progress bar ("  5%|...| 128/2560 [...]") printed in `text`."""
    counts = [int(m.group(1)) for m in re.finditer(r"\|\s*(\d+)/(\d+)\s*\[", text)]
    return max(counts) if counts else None


@case("spectral_variant", "compare in llvm_ad_spectral (and ask for scalar_rgb)",
      "renders like stock in the spectral variant; scalar variants refused in one line")
def spectral_variant(tmp: Path) -> Outcome:
    r = layerbvh("compare", SCENES / "cbox.xml", "--res", "24", "24", "--spp", "8", "--variant", "llvm_ad_spectral",
                 "--traversal", "per_ray", "--out", tmp / "cmp")
    rep = report(tmp / "cmp") if r.code == 0 else {}
    ok1 = rep.get("variant") == "llvm_ad_spectral" and rep["metrics"]["frac_pixels_over_1e-3"] <= 0.001
    s = layerbvh("render", SCENES / "cbox.xml", "--variant", "scalar_rgb", "-o", tmp / "x.exr")
    ok2, line = one_line(s, 2, "scalar_rgb", "llvm_")
    return Outcome("spectral_variant", ok1 and ok2,
                   f"spectral: exit {r.code}, pixels over 1e-3 {rep.get('metrics', {}).get('frac_pixels_over_1e-3')}; "
                   f"scalar: {line}")


@case("no_triangles", "compare a scene holding only an analytic sphere, and one with no shape at all",
      "both render, matching stock (the BVH is empty; the sphere is intersected by Mitsuba's own test)")
def no_triangles(tmp: Path) -> Outcome:
    lines, ok = [], True
    scenes = {name: scene_file(tmp, name, body)
              for name, body in (("sphere_only", '<shape type="sphere"/><emitter type="constant"/>'),
                                 ("no_shapes", '<emitter type="constant"/>'))}
    runs = [(name, scene, traversal) for name, scene in scenes.items() for traversal in ("per_ray", "layer_sorted")]
    # Four independent commands, each its own process and output folder: run at once (most of
    # each is start-up and waiting on the other).
    with ThreadPoolExecutor(max_workers=len(runs)) as pool:
        results = list(pool.map(lambda run: layerbvh("compare", run[1], "--traversal", run[2], "--out",
                                                     tmp / f"{run[0]}_{run[2]}"), runs))
    for (name, _, traversal), r in zip(runs, results):
        rep = report(tmp / f"{name}_{traversal}") if r.code == 0 else {}
        good = r.code == 0 and rep["metrics"]["frac_pixels_over_1e-3"] == 0 and rep["metrics"]["mean_ref"] > 0
        ok &= good
        lines.append(f"{name}/{traversal}: exit {r.code}" + ("" if good else f" {r.error_lines or r.stderr[-200:]}"))
    return Outcome("no_triangles", ok, "; ".join(lines))


@case("huge_resolution", "render at --res 100000 100000, and at --res 20000 20000 under a 6 GB memory limit",
      "refused before rendering with an estimate of the memory needed, one line, exit 2; never a crash")
def huge_resolution(tmp: Path) -> Outcome:
    a = layerbvh("render", SCENES / "cbox.xml", "--res", "100000", "100000", "-o", tmp / "a.exr")
    ok1, line1 = one_line(a, 2, "100000x100000")
    b = layerbvh("render", SCENES / "cbox.xml", "--res", "20000", "20000", "-o", tmp / "b.exr",
                 limit_bytes=6 * 2 ** 30)
    ok2, line2 = one_line(b, 2, "20000x20000", "needs about", "available")
    return Outcome("huge_resolution", ok1 and ok2 and not list(tmp.iterdir()), f"{line1}; {line2}")


@case("bad_output", "--out an existing file, --out below a file (no folder can be made), -o a folder",
      "each refused before rendering (a 10^8-spp render would not return), one line, exit 2")
def bad_output(tmp: Path) -> Outcome:
    afile, folder = tmp / "afile", tmp / "render.exr"
    afile.write_text("mine")
    folder.mkdir()
    huge = ["--spp", "100000000", "--res", "64", "64"]
    checks = [(layerbvh("compare", SCENES / "cbox.xml", *huge, "--out", afile), ("afile", "not a folder")),
              (layerbvh("compare", SCENES / "cbox.xml", *huge, "--out", afile / "sub"), ("cannot write",)),
              (layerbvh("render", SCENES / "cbox.xml", *huge, "-o", folder), ("is a folder",))]
    results = [one_line(r, 2, *words) for r, words in checks]
    return Outcome("bad_output", all(ok for ok, _ in results) and afile.read_text() == "mine",
                   "; ".join(line for _, line in results))


@case("one_run_per_folder", "two `compare` runs (seeds 1 and 2) into the same --out at the same time, and a third "
      "into a folder of unrelated files", "the folder holds the files of one run (its metrics recomputed from "
      "its EXRs agree with its report.json); a folder of someone else's files is refused, untouched")
def one_run_per_folder(tmp: Path) -> Outcome:
    out = tmp / "cmp"
    cmd = [sys.executable, "-m", "layerbvh_mitsuba.cli", "compare", str(SCENES / "cbox.xml"), "--res", "24", "24",
           "--spp", "4", "--traversal", "per_ray", "--out", str(out), "--no-progress"]
    procs = [subprocess.Popen(cmd + ["--seed", str(s)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
             for s in (1, 2)]
    codes = [p.wait(timeout=TIMEOUT_S) for p in procs]
    rep = report(out)
    use_variant()
    stock, ours = (np.array(mi.Bitmap(str(out / f)), np.float32)[:, :, :3] for f in ("stock.exr", "ours.exr"))
    again = metrics.compare_images(stock, ours)
    consistent = all(abs(again[k] - rep["metrics"][k]) <= 1e-12 + 1e-6 * abs(rep["metrics"][k])
                     for k in ("rmse", "rel_mse", "max_abs", "mean_ref"))
    theirs = tmp / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("keep")
    r = layerbvh("compare", SCENES / "cbox.xml", "--res", "8", "8", "--spp", "1", "--out", theirs)
    ok3, line = one_line(r, 2, "not a layerbvh output")
    ok = codes == [0, 0] and consistent and ok3 and sorted(p.name for p in theirs.iterdir()) == ["notes.txt"] \
        and not leftovers(tmp)
    return Outcome("one_run_per_folder", ok, f"exits {codes}; folder from seed {rep['seed']}, metrics consistent "
                                             f"{consistent}; unrelated folder: {line}")


@case("converge_no_wild_reads", "converge on the Cornell box at 32x32 with a 5 s budget and a 256-spp reference",
      "no ratio read from a fit with log-log R² < 0.9 or further than 2x outside the rendered times: n/a with the "
      "reason")
def converge_no_wild_reads(tmp: Path) -> Outcome:
    r = layerbvh("converge", SCENES / "cbox.xml", "--budget", "5", "--res", "32", "32", "--ref-spp", "256",
                 "--cache", tmp / "cache", "--out", tmp / "conv")
    if r.code != 0:
        return Outcome("converge_no_wild_reads", False, f"exit {r.code}: {r.stderr[-300:]}")
    doc = json.loads((tmp / "conv" / "convergence.json").read_text())
    bad, reads = [], 0
    for c in doc["configs"]:
        row = doc["table"]["rows"][c["name"]]
        fit = c["fit"]["rel_mse_vs_seconds"]
        times = [p["seconds"] for p in c["points"]]
        for key, t in (("rel_mse_at_equal_time", doc["table"]["equal_time_s"]), ("seconds_to_equal_error", None)):
            if row[key] is None:
                if not row.get("why_not"):
                    bad.append(f"{c['name']} {key}: n/a without a reason")
                continue
            reads += 1
            t = row[key] if t is None else t
            if fit["r2"] < 0.9 or not min(times) / 2 <= t <= max(times) * 2:
                bad.append(f"{c['name']} {key} read at {t:.3g} s from a fit of R² {fit['r2']:.2f}")
    md = (tmp / "conv" / "convergence.md").read_text()
    return Outcome("converge_no_wild_reads", not bad, f"{reads} reads, all within the rules" if not bad else
                   "; ".join(bad) + ("" if "n/a" not in md else " (n/a shown)"))


@case("damaged_reference_cache", "truncate the cached reference EXR, then run converge again",
      "one-line notice, the reference is rendered again, the run succeeds")
def damaged_reference_cache(tmp: Path) -> Outcome:
    args = ["converge", SCENES / "cbox.xml", "--budget", "2", "--res", "16", "16", "--ref-spp", "64", "--configs",
            "stock", "--cache", tmp / "cache"]
    first = layerbvh(*args, "--out", tmp / "a")
    exrs = list((tmp / "cache").glob("*.exr"))
    if first.code != 0 or len(exrs) != 1:
        return Outcome("damaged_reference_cache", False, f"first run exit {first.code}: {first.stderr[-300:]}")
    exrs[0].write_bytes(exrs[0].read_bytes()[:100])
    second = layerbvh(*args, "--out", tmp / "b")
    notice = [ln for ln in second.stderr.splitlines() if "cached reference" in ln]
    doc = json.loads((tmp / "b" / "convergence.json").read_text()) if second.code == 0 else {}
    ok = second.code == 0 and len(notice) == 1 and doc["reference"]["cached"] is False
    return Outcome("damaged_reference_cache", ok, f"exit {second.code}; notice {notice}")


@case("directory_as_scene", "pass a folder as the scene", "one line: it is a directory, exit 2")
def directory_as_scene(tmp: Path) -> Outcome:
    ok, line = one_line(layerbvh("render", SCENES, "-o", tmp / "x.exr"), 2, "is a directory")
    return Outcome("directory_as_scene", ok, line)


@case("bad_integrator_property", "a scene whose layerbvh integrator sets treelet_height=0",
      "refused when the scene loads, with the same rule and message as --treelet-height")
def bad_integrator_property(tmp: Path) -> Outcome:
    scene = scene_file(tmp, "th0", f"""<integrator type="layerbvh">
    <integer name="treelet_height" value="0"/></integrator>
  {LIT_QUAD}""")
    ok, line = one_line(layerbvh("render", scene, "-o", tmp / "x.exr"), 2, "treelet_height must be in [1, 64], got 0")
    ok2, line2 = one_line(layerbvh("render", scene, "--treelet-height", "0", "-o", tmp / "x.exr"), 2,
                          "treelet-height must be in [1, 64], got 0")
    return Outcome("bad_integrator_property", ok and ok2, f"{line}; {line2}")


def markdown(results: list[Outcome]) -> str:
    """The STABILITY.md section: each case, what was done, what is expected, what happened."""
    lines = ["| case | what the user does | expected | outcome | result |", "|---|---|---|---|---|"]
    for r in results:
        c = CASES[r.case]
        lines.append(f"| {r.case} | {c.what} | {c.expected} | {r.outcome.replace('|', '/')} | "
                     f"{'pass' if r.passed else '**FAIL**'} |")
    return "\n".join(lines) + "\n"

