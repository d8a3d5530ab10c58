"""Numba's on-disk cache of a module's functions, dropped when a module they compile in changes."""
from __future__ import annotations

import hashlib
import inspect
import os
from pathlib import Path

import numba
from numba.core.caching import FunctionCache

# Numba keys a cached function on its own source file alone. A function that inlines another
# module's njit function (memtrace's replay compiles cachesim's cache_access into itself) or folds
# another module's constants (memsites' load sites, layout's bit fields) kept the old code after
# that module was edited, until someone removed layerbvh/__pycache__/*.nb* by hand. `follow` keeps
# a digest of those modules' sources beside the cache and drops the cache when it differs.


def sources_digest(modules) -> str:
    """A digest of the source files of `modules`."""
    h = hashlib.sha256()
    for mod in modules:
        h.update(Path(inspect.getsourcefile(mod)).read_bytes())
    return h.hexdigest()


def follow(namespace: dict, *modules) -> bool:
    """Drop the on-disk cache of every cached njit function in `namespace` (a module's globals)
    when the sources of `modules` differ from those it was compiled with; returns whether it
    did. A cache folder that cannot be written is left as numba leaves it."""
    cached = [f for f in namespace.values()
              if isinstance(f, numba.core.registry.CPUDispatcher) and f.__module__ == namespace["__name__"]
              and isinstance(getattr(f, "_cache", None), FunctionCache)]
    if not cached:
        return False
    stamp = Path(cached[0]._cache._cache_path) / f"{namespace['__name__']}.follows"
    digest = sources_digest(modules)
    try:
        if stamp.exists() and stamp.read_text() == digest:
            return False
        for f in cached:
            f._cache.flush()
        tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}.tmp")
        tmp.write_text(digest)
        os.replace(tmp, stamp)
    except OSError:
        return False
    return True
