#!/usr/bin/env bash
# Makes a fresh Debian machine ready: Python 3.11, Debian's libllvm19 (Dr.Jit's LLVM backend),
# and a virtualenv in .venv with the project installed. Safe to run again: it skips what is done.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

say() { printf 'bootstrap: %s\n' "$*" >&2; }

python=""
for cand in python3.11 python3; do
  if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    python="$(command -v "$cand")"; break
  fi
done
if [ -z "$python" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing python3.11 (Debian packages python3.11 python3.11-venv)"
    apt-get update -qq && apt-get install -y -qq python3.11 python3.11-venv >/dev/null
    python="$(command -v python3.11)"
  else
    say "Python 3.11 is required. Install it, e.g.: sudo apt-get install python3.11 python3.11-venv"; exit 1
  fi
fi

# Dr.Jit's LLVM backend loads a shared libLLVM; Debian's 14 and 15 crash at the first kernel.
if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing Debian package libllvm19 (needed by Dr.Jit's LLVM backend)"
    apt-get update -qq && apt-get install -y -qq libllvm19 >/dev/null
  else
    say "Debian package libllvm19 is missing (Dr.Jit's LLVM backend needs it; libllvm14/15 crash)."
    say "Install it as root: sudo apt-get install -y libllvm19"; exit 1
  fi
fi

# The test suite's browser test drives Debian's chromium through chromedriver (scripts/test.sh
# passes --test); without them that one test is skipped with its reason.
if [ "${1:-}" = "--test" ] && ! { command -v chromium >/dev/null && command -v chromedriver >/dev/null; }; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing Debian packages chromium and chromium-driver (the report page's browser test)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null
  else
    say "chromium/chromedriver are missing: the browser test will be skipped (sudo apt-get install chromium chromium-driver)"
  fi
fi

stamp=".venv/.layerbvh-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  if [ ! -x .venv/bin/python ]; then
    say "creating virtualenv .venv"
    "$python" -m venv .venv || { say "python3.11 -m venv failed: install python3.11-venv"; exit 1; }
  fi
  say "installing the project and its pinned dependencies into .venv"
  # (--no-compile: byte-compiling every installed module took half the install's time; Python
  # compiles what a run imports, once, into __pycache__)
  # uv (from PyPI, into .venv) installs the same pinned set in 16 s where pip takes 39 s (a fresh
  # clone, this project's 2-core machine; `pip freeze` identical): a sixth of what a cold test
  # run spends outside its tests. Where uv cannot be had or fails (no wheel for the platform, an
  # index only pip is configured for), pip installs as before.
  if .venv/bin/python -m pip install -q --no-compile --disable-pip-version-check uv 2>/dev/null \
      && .venv/bin/python -m uv pip install -q --python .venv/bin/python -e '.[test]'; then
    :
  else
    say "uv could not install; installing with pip"
    .venv/bin/python -m pip install -q --no-compile --disable-pip-version-check -e '.[test]'
  fi
  # ... but not where PYTHONDONTWRITEBYTECODE is set (this project's machines set it): there
  # every process compiled the ~900 modules it imports from source, 3 s of a 6 s `compare` on a
  # small scene (PERFORMANCE.md, entry 50). Written here once for what the tools import; later
  # processes read it whatever that variable says.
  say "byte-compiling the modules the tools import"
  env -u PYTHONDONTWRITEBYTECODE .venv/bin/python -W ignore -c \
    'import layerbvh_mitsuba.cli, layerbvh_mitsuba.tools.sweep.runner, colour, matplotlib.pyplot, dask.distributed' \
    || say "byte-compiling failed (the tools still run, each compiling what it imports)"
  echo "$want" > "$stamp"
fi
