"""Entry point: BENCHMARKS.md from benchmark JSON (layerbvh_mitsuba.bench.report); run `.venv/bin/python scripts/report.py --help`."""
import sys

from layerbvh_mitsuba.bench.report import main

if __name__ == "__main__":
    sys.exit(main())
