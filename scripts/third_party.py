"""Entry point: A/B check on third-party scenes (layerbvh_mitsuba.tools.third_party); run `.venv/bin/python
scripts/third_party.py --help`."""
import sys

from layerbvh_mitsuba.tools.third_party import main

if __name__ == "__main__":
    sys.exit(main())
