"""Entry point: the instancing benchmark (layerbvh_mitsuba.bench.instances); run `.venv/bin/python scripts/bench_instances.py --help`."""
import sys

from layerbvh_mitsuba.bench.instances import main

if __name__ == "__main__":
    sys.exit(main())
