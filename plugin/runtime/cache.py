"""Where the runtime and the tools keep what outlives a process: $XDG_CACHE_HOME/layerbvh/<kind>."""
from __future__ import annotations

import os
from pathlib import Path


def cache_dir(kind: str) -> Path:
    """$XDG_CACHE_HOME/layerbvh/<kind> (default ~/.cache/layerbvh/<kind>): auto's decisions, stock
    references, recorded rays, the pytest plugin's stock images."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "layerbvh" / kind
