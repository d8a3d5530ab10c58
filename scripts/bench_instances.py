"""Entry point: the instancing benchmark (layerbvh_mitsuba.tools.bench.instances); run `.venv/bin/python
scripts/bench_instances.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.instances import main

if __name__ == "__main__":
    sys.exit(main())
