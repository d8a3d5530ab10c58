"""Entry point: stress scenes (spheres, terrain, soup) (layerbvh_mitsuba.tools.bench.stress); run `.venv/bin/python
scripts/gen_stress.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.stress import main

if __name__ == "__main__":
    sys.exit(main())
