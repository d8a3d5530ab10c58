"""Entry point: BENCHMARKS.md from benchmark JSON (layerbvh_mitsuba.tools.bench.report); run `.venv/bin/python
scripts/report.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.report import main

if __name__ == "__main__":
    sys.exit(main())
