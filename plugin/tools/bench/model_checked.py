"""Whether the locality model behind a verdict was checked, and against what: valgrind's cache simulator for a CPU
preset (the committed docs/bench/cachegrind_*.json), nothing yet for a GPU preset."""
from __future__ import annotations

import json
from pathlib import Path

from layerbvh_mitsuba.repo import ROOT

# Where scripts/check_model_cachegrind.py's results are committed (bench_all.sh writes them).
CHECKS = ROOT / "docs" / "bench"
PATTERN = "cachegrind_*.json"
GPU_NOTE = ("model unchecked: no GPU cache simulator or hardware counters have been held against it "
            "(its H200 run measured time only)")


def cpu_checks(folder: Path = CHECKS) -> list[dict]:
    """The committed valgrind checks of the model (each with its `verdicts`), readable ones only."""
    out = []
    for path in sorted(Path(folder).glob(PATTERN)):
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(doc, dict) and doc.get("verdicts"):
            out.append(doc)
    return out


def note(kind: str, folder: Path = CHECKS) -> str:
    """What a verdict from a preset of `kind` ("cpu" or "gpu") rests on, in one clause: for a CPU,
    where the model's sorted / per_ray miss ratio agreed with valgrind's (ratio within the check's
    tolerance and the same verdict) and where it did not, over the committed checks."""
    if kind != "cpu":
        return GPU_NOTE
    docs = cpu_checks(folder)
    if not docs:
        return ("model unchecked here: no committed valgrind check "
                "(scripts/check_model_cachegrind.py writes docs/bench/cachegrind_*.json)")
    tally: dict[tuple, list] = {}
    for doc in docs:
        for v in doc["verdicts"]:
            key = (v["level"], v["d1_kib"], v.get("misses", "reads"))
            tally.setdefault(key, []).append(bool(v["ratio_agrees"] and v["verdict_agrees"]))
    kinds = [k for k in ("reads", "writes") if any(key[2] == k for key in tally)]
    where = lambda key: ((f"D1 {key[1]} KiB" if key[0] == "D1" else f"{key[0]} beside D1 {key[1]} KiB")  # noqa: E731
                         + (f" ({key[2]})" if len(kinds) > 1 else ""))
    agrees = [where(k) for k, ok in tally.items() if all(ok)]
    differs = [f"{where(k)}, {sum(ok)} of {len(ok)} meshes agreeing" for k, ok in tally.items() if not all(ok)]
    meshes = ", ".join(f"{Path(d.get('mesh', '?')).name} ({d.get('triangles', 0):,} triangles)" for d in docs)
    return (f"model checked against valgrind's cache simulator on {meshes}, {' and '.join(kinds)}"
            + (" only" if len(kinds) == 1 else "") + ": sorted / per_ray "
            + (f"agrees at {', '.join(agrees)}" if agrees else "agrees nowhere")
            + (f"; DISAGREES at {'; '.join(differs)}" if differs else "")
            + " (BENCHMARKS.md)")


def notes(kinds: dict, folder: Path = CHECKS) -> dict:
    """Each preset's note (`kinds`: its kind by name), each kind's worked out once."""
    by_kind = {kind: note(kind, folder) for kind in set(kinds.values())}
    return {name: by_kind[kind] for name, kind in kinds.items()}


def with_note(verdicts: dict, preset_notes: dict) -> dict:
    """Each preset's verdict sentence with its note (`preset_notes`, from `notes`); a preset
    without one counts as unchecked."""
    return {name: f"{line} [{preset_notes.get(name, GPU_NOTE)}]" for name, line in verdicts.items()}
