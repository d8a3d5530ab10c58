#!/usr/bin/env bash
# The test command (README, CI): bootstrap, then the whole pytest suite.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" --test
cd "$root"
exec .venv/bin/python -m pytest -q "$@"
