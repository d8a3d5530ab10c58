#!/usr/bin/env bash
# Mutation check (docs/testing.md): applies named, realistic bugs to a temporary copy of this
# checkout one at a time and runs the tests that should catch each; one line per mutation,
# `caught` or `MISSED`; exit status non-zero if any is missed or no longer applies. A few
# minutes. Needs the test environment (bash scripts/test.sh creates .venv); arguments go to
# scripts/mutation_check.py (--list, --dry-run, --only NAME,..., --no-baseline, --keep).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
python="${LAYERBVH_PYTHON:-$root/.venv/bin/python}"
if [ ! -x "$python" ]; then
    echo "mutation_check: $python not found: run bash scripts/test.sh once (it creates .venv)" >&2
    exit 2
fi
exec "$python" "$root/scripts/mutation_check.py" --repo "$root" --python "$python" "$@"
