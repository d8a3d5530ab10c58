"""Splice the markdown that scripts/bench_traversal.py printed into README.md between the bench markers."""
from __future__ import annotations

import os
import sys
from pathlib import Path

START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python scripts/update_readme_bench.py BENCH_STDOUT.md", file=sys.stderr)
        return 2
    text = Path(argv[0]).read_text()
    # Drop the benchmark's own title; headings move two levels down inside the README section.
    lines = [ln for ln in text.splitlines() if not ln.startswith("# ") and not ln.startswith("wrote ")]
    body = "\n".join(("###" + ln[1:]) if ln.startswith("## ") else ln for ln in lines).strip()
    readme = Path(__file__).resolve().parents[1] / "README.md"
    old = readme.read_text()
    if START not in old or END not in old:
        print(f"{readme}: markers {START} / {END} not found", file=sys.stderr)
        return 2
    new = old[:old.index(START) + len(START)] + "\n" + body + "\n" + old[old.index(END):]
    tmp = readme.with_suffix(".md.tmp")
    tmp.write_text(new)
    os.replace(tmp, readme)
    return 0


if __name__ == "__main__":
    sys.exit(main())
