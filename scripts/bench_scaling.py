"""Entry point: the scaling benchmark (layerbvh_mitsuba.tools.bench.scaling); run `.venv/bin/python
scripts/bench_scaling.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.scaling import main

if __name__ == "__main__":
    sys.exit(main())
