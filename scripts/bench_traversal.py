"""Entry point: the traversal benchmark (layerbvh_mitsuba.tools.bench.traversal); run `.venv/bin/python
scripts/bench_traversal.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.traversal import main

if __name__ == "__main__":
    sys.exit(main())
