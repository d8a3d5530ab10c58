"""Entry point: the README's status matrix (layerbvh_mitsuba.tools.status_matrix); `--readme` splices it, `--check`
checks every named test exists."""
import sys

from layerbvh_mitsuba.tools.status_matrix import main

if __name__ == "__main__":
    sys.exit(main())
