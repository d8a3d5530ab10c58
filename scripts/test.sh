#!/usr/bin/env bash
# The test command (README, CI): bootstrap, then the whole pytest suite in two processes
# (pytest-xdist, one file per process at a time): much of the suite's time is LLVM compiling
# kernels on one thread, which the second process overlaps (times from fresh clones: docs/testing.md).
# Extra arguments go to pytest (`-n 0` runs it in one process).
#
# It can never hang (issue 39): a test running past pytest-timeout's limit (pyproject.toml) ends
# its process; a worker that dies (that, or an abort) stops the run naming its test
# (--max-worker-restart 0: xdist's replacement worker of a --dist loadfile run waits forever for
# work, measured); and if pytest itself still runs after SUITE_LIMIT_S, it is stopped here, naming
# the tests that were running (tests/conftest.py keeps them in $LAYERBVH_RUNNING_TESTS).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" --test
cd "$root"
# The suite starts some hundred Python processes (CLI commands, sweep and SLURM workers, pytest's
# own): with PYTHONDONTWRITEBYTECODE set (as on this project's machines) each compiled every
# module it imports from source, ours and pytest's too. Unset, the first writes __pycache__ (it is
# in .gitignore) and the rest read it (PERFORMANCE.md, entry 50).
unset PYTHONDONTWRITEBYTECODE
# The machine first (issue 64): a failure reads against its CPU, its SIMD and Dr.Jit's lanes.
.venv/bin/python -c 'import layerbvh as L, os
simd = L.memmodel.simd_name(L.memmodel.cpu_flags())
isa = os.environ.get(L.backend.LLVM_ISA_ENV)
print(f"test.sh: CPU {L.cpu_model()}, {os.cpu_count()} cores, {simd}; Dr.Jit LLVM {L.llvm_isa()}, "
      f"{L.llvm_vector_width()} lanes" + (f" ({L.backend.LLVM_ISA_ENV}={isa})" if isa else ""))' || true
SUITE_LIMIT_S="${SUITE_LIMIT_S:-2400}"
running="$(mktemp)"
trap 'rm -f "$running"' EXIT
set +e
LAYERBVH_RUNNING_TESTS="$running" timeout -k 30 "$SUITE_LIMIT_S" \
  .venv/bin/python -m pytest -q -n 2 --dist loadfile --max-worker-restart 0 "$@"
rc=$?
set -e
if [ "$rc" = 124 ] || [ "$rc" = 137 ]; then
  echo "test.sh: the test suite ran past ${SUITE_LIMIT_S} s and was stopped; running then:" >&2
  sed 's/^/  /' "$running" >&2
  exit 1
fi
exit "$rc"
