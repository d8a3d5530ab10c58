"""Entry point: the tail's step cap, modelled and timed (layerbvh_mitsuba.tools.bench.tail_cutoff); run
`.venv/bin/python scripts/tail_cutoff.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.tail_cutoff import main

if __name__ == "__main__":
    sys.exit(main())
