"""Entry point: the walk kernel's cost per branching (layerbvh_mitsuba.tools.bench.kernel_cost); run
`.venv/bin/python scripts/bench_kernel.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.kernel_cost import main

if __name__ == "__main__":
    sys.exit(main())
