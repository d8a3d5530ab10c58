"""Mutation check: does the test suite catch realistic bugs?

Copies the repository (tracked and untracked, not ignored files, as they are in the working
tree) to a temporary folder, then for each mutation in its table (scripts/mutations/), one at a
time: replaces one piece of text in one file of the copy (it must occur exactly once there, else the mutation is
"not applicable": the code moved on and the table must follow), runs the tests that should catch
it (pytest -x, in the copy: PYTHONPATH points `layerbvh` and `layerbvh_mitsuba` at the copied
packages, ahead of the editable install of the original checkout), prints one line, and puts
the file back. First the union of all listed tests runs on the unmutated copy (the baseline): a
test that fails there would "catch" anything.

A listed test whose process crashes (a signal, while pytest -v shows that test running) also catches
it: the suite stops there and names the test. Exit status 0 when every mutation is caught; 1 when
one is missed, not applicable or its run broke (a collection error or a timeout is not a catch); 2
when the baseline fails or the copy does not import its own packages.

    bash scripts/mutation_check.sh [--only NAME,...] [--list] [--dry-run] [--no-baseline] [--keep]
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from layerbvh import memmodel

sys.path.insert(0, str(Path(__file__).resolve().parent))  # (the table beside it: scripts/mutations/)
from mutations import MUTATIONS  # noqa: E402


def copy_repository(src: Path, dst: Path) -> int:
    """Tracked and untracked (not ignored) files of `src` as they are in the working tree, with
    their times (numba's cache checks them); numba's compiled kernels (ignored __pycache__
    files) too, so the copy does not recompile the builder. Returns the number of files."""
    out = subprocess.run(["git", "-C", str(src), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         capture_output=True, check=True).stdout.decode()
    names = [n for n in out.split("\0") if n]
    copied = 0
    for name in names:
        s = src / name
        if s.is_file() and not s.is_symlink():  # a tracked file deleted in the working tree is left out
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(s, dst / name)
            copied += 1
    # (with the digests numba_cache.follow keeps beside them: a mutated dependency drops them)
    for cache in [*src.glob("layerbvh/__pycache__/*.nb[ic]"), *src.glob("layerbvh/__pycache__/*.follows")]:
        (dst / cache.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(cache, dst / cache.relative_to(src))
    return copied


def import_path(copy: Path) -> Path:
    """A folder holding `layerbvh` and `layerbvh_mitsuba` (the copy's plugin/) as symlinks: the
    packages' names, pointing at the copied sources."""
    imp = copy / ".mutation_imports"
    imp.mkdir()
    (imp / "layerbvh").symlink_to(copy / "layerbvh", target_is_directory=True)
    (imp / "layerbvh_mitsuba").symlink_to(copy / "plugin", target_is_directory=True)
    return imp


def run_tests(python: str, copy: Path, env: dict, tests, timeout: float) -> tuple[int | None, str]:
    """pytest -x on `tests` in the copy: (exit status or None on timeout, output)."""
    cmd = [python, "-m", "pytest", "-x", "-v", "-n", "0", "-p", "no:cacheprovider", "-p", "no:randomly",
           "--no-header", "-rf", *tests]  # (-v: each test's id is printed as it starts; see crash_site)
    try:
        p = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        return None, (e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
    return p.returncode, p.stdout + p.stderr


def crash_site(rc: int | None, output: str, tests) -> str | None:
    """The listed test that was running when pytest was killed by a signal (a mutation that makes a
    kernel read out of bounds crashes the test that runs it: caught, as the suite's run fails
    there); None otherwise (a crash at import or elsewhere is not a catch)."""
    if rc is None or rc >= 0:
        return None
    # pytest -v prints a test's id when it starts and its result when it ends: the last id printed
    # without a result is the test that was running.
    started = re.findall(r"^(\S+::\S+) (?!PASSED|FAILED|SKIPPED|ERROR|XFAIL|XPASS)", output, re.M)
    running = started[-1] if started else None
    if running is None:
        return None
    # (A listed test without parameters names all its parametrized cases.)
    return next((t for t in tests if running.endswith(t) or running.split("[")[0].endswith(t)), None)


def first_failure(output: str, width: int = 90) -> str:
    """The first failed test of pytest's -rf summary, with the start of its message."""
    m = re.search(r"^FAILED (\S+)(?: - (.*))?$", output, re.M)
    if not m:
        return "?"
    why = (m.group(2) or "").strip()
    return m.group(1) + (f": {why[:width]}{'...' if len(why) > width else ''}" if why else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1], help="the checkout to copy")
    ap.add_argument("--python", default=None, help="the interpreter (default: REPO/.venv/bin/python)")
    ap.add_argument("--only", default="", help="comma-separated mutation names")
    ap.add_argument("--list", action="store_true", help="print the mutations and exit")
    ap.add_argument("--dry-run", action="store_true",
                    help="only check that each mutation's text occurs exactly once in the checkout and its tests' "
                    "files exist (no copy, no tests)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of the listed tests")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copy")
    ap.add_argument("--timeout", type=float, default=600, help="seconds per pytest run")
    args = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only.split(",")]
    unknown = set(filter(None, args.only.split(","))) - {m.name for m in MUTATIONS}
    if unknown:
        print(f"mutation_check: unknown mutation(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    if args.list:
        for m in chosen:
            print(f"{m.name}: {m.what}\n    {m.path}: {m.old.strip()!r} -> {m.new.strip()!r}\n    tests: "
                  + " ".join(m.tests))
        return 0
    repo = args.repo.resolve()
    if args.dry_run:
        bad = 0
        for m in chosen:
            there = (repo / m.path).is_file()
            found = (repo / m.path).read_text().count(m.old) if there else 0
            missing = [t for t in m.tests if not (repo / t.split("::")[0]).is_file()]
            bad += found != 1 or bool(missing)
            why = [] if found == 1 else [f"its text occurs {found} times in {m.path}" if there else f"no file {m.path}"]
            why += [f"no test file {t.split('::')[0]}" for t in missing]
            print(f"{m.name:34s} {'not applicable: ' + '; '.join(why) if why else 'applicable'}")
        return 1 if bad else 0
    python = args.python or str(repo / ".venv" / "bin" / "python")
    t_start = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="layerbvh-mutation-"))
    try:
        copy = tmp / "repo"
        n = copy_repository(repo, copy)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(import_path(copy)),
                                                                          os.environ.get("PYTHONPATH")])),
               "PYTHONDONTWRITEBYTECODE": "1", "COLUMNS": "250",  # COLUMNS: pytest's summary lines whole
               "LAYERBVH_VALGRIND_TEST": "1"}  # (the valgrind test, off in the suite's time budget)
        probe = subprocess.run([python, "-c", "import layerbvh, layerbvh_mitsuba, os; "
                                "print(os.path.realpath(layerbvh.__file__)); "
                                "print(os.path.realpath(layerbvh_mitsuba.__file__))"],
                               cwd=copy, env=env, capture_output=True, text=True)
        where = probe.stdout.split()
        if probe.returncode != 0 or len(where) != 2 or not all(w.startswith(str(copy.resolve())) for w in where):
            print(f"mutation_check: the copy does not import its own packages: {where or probe.stderr.strip()}",
                  file=sys.stderr)
            return 2
        print(f"mutation_check: {n} files copied to {copy}; {len(chosen)} mutation(s)", flush=True)
        if not args.no_baseline:
            tests = list(dict.fromkeys(t for m in chosen for t in m.tests))
            rc, out = run_tests(python, copy, env, tests, args.timeout * 2)
            if rc != 0:
                print(f"mutation_check: the unmutated copy fails its tests (exit {rc}): {first_failure(out)}\n"
                      + out[-3000:], file=sys.stderr)
                return 2
            print(f"baseline: {len(tests)} tests pass unmutated", flush=True)
        bad = skipped = 0
        flags = memmodel.cpu_flags()
        for m in chosen:
            if m.cpu_flag and m.cpu_flag not in flags:  # (an AVX2 CPU's ISA override changes nothing to catch)
                print(f"{m.name:34s} skipped: this CPU has no {m.cpu_flag}, which the bug needs to show", flush=True)
                skipped += 1
                continue
            target = copy / m.path
            text = target.read_text()
            found = text.count(m.old)
            if found != 1:
                print(f"{m.name:34s} not applicable: its text occurs {found} times in {m.path} (update the table)",
                      flush=True)
                bad += 1
                continue
            t0 = time.perf_counter()
            target.write_text(text.replace(m.old, m.new))
            try:
                rc, out = run_tests(python, copy, env, m.tests, args.timeout)
            finally:
                target.write_text(text)
            dt = time.perf_counter() - t0
            crashed_in = crash_site(rc, out, m.tests)
            if rc == 1:
                print(f"{m.name:34s} caught   by {first_failure(out)} ({dt:.0f} s)", flush=True)
            elif crashed_in:
                print(f"{m.name:34s} caught   by {crashed_in}: the test's process crashed (signal {-rc}; the suite "
                      f"stops there, naming it) ({dt:.0f} s)", flush=True)
            else:
                bad += 1
                why = "MISSED" if rc == 0 else ("ERROR    (timeout)" if rc is None else f"ERROR    (pytest exit {rc})")
                print(f"{m.name:34s} {why}: {m.what} ({dt:.0f} s)", flush=True)
                if rc not in (0, None):
                    print(out[-2000:], flush=True)
        print(f"mutation_check: {len(chosen) - bad - skipped} of {len(chosen) - skipped} caught"
              + (f" ({skipped} skipped on this CPU)" if skipped else "") + f" in {time.perf_counter() - t_start:.0f} s",
              flush=True)
        return 1 if bad else 0
    finally:
        if args.keep:
            print(f"mutation_check: copy kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
