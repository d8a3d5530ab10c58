#!/usr/bin/env bash
# The test command (README, CI): bootstrap, then the whole pytest suite in two processes
# (pytest-xdist, one file per process at a time): much of the suite's time is LLVM compiling
# kernels on one thread, which the second process overlaps (on 2 cores with a cold kernel cache:
# 8 min instead of 14). Extra arguments go to pytest (`-n 0` runs it in one process).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" --test
cd "$root"
exec .venv/bin/python -m pytest -q -n 2 --dist loadfile "$@"
