"""Entry point: record the rays a render traces (layerbvh_mitsuba.tools.bench.record_rays); run `.venv/bin/python
scripts/record_rays.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.record_rays import main

if __name__ == "__main__":
    sys.exit(main())
