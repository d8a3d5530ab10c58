"""Entry point: the stability suite -> STABILITY.md (layerbvh_mitsuba.tools.stability.report); run `.venv/bin/python
scripts/stability_report.py --help`."""
import sys

from layerbvh_mitsuba.tools.stability.report import main

if __name__ == "__main__":
    sys.exit(main())
