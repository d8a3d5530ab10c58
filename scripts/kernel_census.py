#!/usr/bin/env python3
"""Where the suite's cold time goes: the kernels Dr.Jit compiled, by test file and test, and the
"families" of kernels that differ only by literals (a size or constant baked into the code, so
each new value compiles again; passed opaque, one kernel would serve them all).

    rm -rf /tmp/census && LAYERBVH_KERNEL_CENSUS=/tmp/census HOME=$(mktemp -d) bash scripts/test.sh
    .venv/bin/python scripts/kernel_census.py /tmp/census [--json docs/suite_durations/census.json]

The folder holds one JSON line per kernel launch not found in a process's memory
(layerbvh/kernel_census.py): compiled ("disk": false) or read from Dr.Jit's disk cache.
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path


def load(folder: Path) -> list[dict]:
    rows = []
    for f in sorted(folder.glob("*.jsonl")):
        for line in f.read_text().splitlines():
            if line.strip():
                rows.append(json.loads(line))
    return rows


def census(rows: list[dict]) -> dict:
    """Compiled kernels (first compile of each hash: a second process reads it from disk), by file,
    test and literal family."""
    compiled = [r for r in rows if not r["disk"]]
    by_file, by_test = collections.Counter(), collections.Counter()
    n_file = collections.Counter()
    for r in compiled:
        test = r["test"] or "(outside a test)"
        by_test[test] += r["ms"] / 1e3
        by_file[test.split("::")[0]] += r["ms"] / 1e3
        n_file[test.split("::")[0]] += 1
    fams = collections.defaultdict(list)
    for r in compiled:
        fams[r["family"]].append(r)
    families = []
    for fam, rs in fams.items():
        hashes = {r["hash"] for r in rs}
        if len(hashes) > 1:
            files = collections.Counter(r["test"].split("::")[0] for r in rs)
            families.append({"family": fam, "kernels": len(hashes), "seconds": sum(r["ms"] for r in rs) / 1e3,
                             "ops": max(r["ops"] or 0 for r in rs), "files": dict(files.most_common(4))})
    families.sort(key=lambda f: -f["seconds"])
    return {"compile_seconds": sum(r["ms"] for r in compiled) / 1e3, "kernels_compiled": len(compiled),
            "distinct_kernels": len({r["hash"] for r in compiled}), "disk_reads": len(rows) - len(compiled),
            "by_file": {f: {"seconds": round(s, 1), "kernels": n_file[f]} for f, s in by_file.most_common()},
            "by_test": {t: round(s, 1) for t, s in by_test.most_common(40)},
            "literal_families": families[:40],
            "seconds_in_repeated_families": sum(f["seconds"] for f in families)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--json", type=Path, help="also write the census here")
    a = ap.parse_args(argv)
    rows = load(a.folder)
    if not rows:
        print(f"kernel_census: no records in {a.folder} (was LAYERBVH_KERNEL_CENSUS set?)", file=sys.stderr)
        return 2
    c = census(rows)
    print(f"{c['kernels_compiled']} kernels compiled ({c['distinct_kernels']} distinct) in "
          f"{c['compile_seconds']:.0f} s of LLVM; {c['disk_reads']} read from the disk cache")
    print(f"kernels that differ from another only by literals: {c['seconds_in_repeated_families']:.0f} s")
    print("\ncompile seconds by test file:")
    for f, v in list(c["by_file"].items())[:25]:
        print(f"  {v['seconds']:7.1f} s {v['kernels']:5d} kernels  {f}")
    print("\nby test:")
    for t, s in list(c["by_test"].items())[:20]:
        print(f"  {s:7.1f} s  {t}")
    print("\nliteral families (kernels, seconds, ops, files):")
    for f in c["literal_families"][:20]:
        print(f"  {f['family']} {f['kernels']:4d} {f['seconds']:7.1f} s {f['ops']:6d}  {f['files']}")
    if a.json:
        tmp = a.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(c, indent=1))
        tmp.replace(a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
