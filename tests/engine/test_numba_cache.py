"""Numba's on-disk cache follows the modules a cached function compiles in (layerbvh/numba_cache.py): edited
constants are not served stale."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_MODULE = """
import numba
import dep
from dep import K
from layerbvh import numba_cache

@numba.njit(cache=True)
def f():
    return K
{follow}
print(f())
"""


def _run(folder: Path, module: str) -> str:
    p = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True, timeout=120,
                       cwd=folder, env={"PYTHONPATH": f"{folder}:{ROOT}", "PATH": "/usr/bin:/bin",
                                        "HOME": str(folder)})
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout.strip()


def test_an_edited_dependency_is_compiled_again(tmp_path):
    """A cached njit function folds a constant of another module. Edited there, numba alone
    serves the old value from its cache (the negative control, `plain`); with numba_cache.follow
    the cache is dropped and the new value compiled."""
    (tmp_path / "dep.py").write_text("K = 1\n")
    (tmp_path / "plain.py").write_text(_MODULE.format(follow=""))
    (tmp_path / "following.py").write_text(_MODULE.format(follow="numba_cache.follow(globals(), dep)"))
    assert (_run(tmp_path, "plain"), _run(tmp_path, "following")) == ("1", "1")
    (tmp_path / "dep.py").write_text("K = 2  # edited\n")
    assert _run(tmp_path, "plain") == "1", "numba no longer serves a stale constant: follow may be unneeded"
    assert _run(tmp_path, "following") == "2"
    assert _run(tmp_path, "following") == "2"  # and the new cache is kept (no flush without an edit)
    assert (tmp_path / "__pycache__" / "following.follows").exists()
