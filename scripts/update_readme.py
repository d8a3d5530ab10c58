"""Splice a script's markdown output into a page between `<!-- SECTION:start -->` and `<!-- SECTION:end -->`
(--readme: the page, README.md by default; third_party lives in docs/scenes.md, bench_headline in docs/results.md)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from layerbvh_mitsuba import atomic


def readme_body(text: str) -> str:
    """Drop the script's own title and 'wrote' lines; its headings move two levels down."""
    lines = [ln for ln in text.splitlines() if not ln.startswith("# ") and not ln.startswith("wrote ")]
    return "\n".join(("###" + ln[1:]) if ln.startswith("## ") else ln for ln in lines).strip()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("section", help="marker name, e.g. bench or third_party")
    p.add_argument("markdown", help="file holding the script's markdown output")
    p.add_argument("--readme", default=str(ROOT / "README.md"))
    args = p.parse_args(argv)
    try:
        atomic.splice_section(args.readme, args.section, readme_body(Path(args.markdown).read_text()))
    except (OSError, ValueError) as e:
        print(f"update_readme: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
