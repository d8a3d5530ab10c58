"""Entry point: auto against per_ray on whole renders (layerbvh_mitsuba.tools.bench.auto_render); run
`.venv/bin/python scripts/bench_auto.py --help`."""
import sys

from layerbvh_mitsuba.tools.bench.auto_render import main

if __name__ == "__main__":
    sys.exit(main())
