"""Entry point: the traversal benchmark (layerbvh_mitsuba.bench.traversal); run `.venv/bin/python scripts/bench_traversal.py --help`."""
import sys

from layerbvh_mitsuba.bench.traversal import main

if __name__ == "__main__":
    sys.exit(main())
