"""The kernel census: every kernel Dr.Jit compiles in a process, by the pytest test that was running, for finding
where the suite's cold time goes (scripts/kernel_census.py reads it)."""
from __future__ import annotations

import atexit
import hashlib
import json
import os
import re

import drjit as dr

# Set to a folder, every process that imports layerbvh (pytest's workers and the CLI, sweep and
# SLURM processes the tests start: they inherit PYTEST_CURRENT_TEST) appends one JSON line per
# kernel launch that was not found in Dr.Jit's in-memory cache to FOLDER/<pid>.jsonl. Off by
# default: the kernel history keeps every launch's IR until it is read.
ENV = "LAYERBVH_KERNEL_CENSUS"
# Set as well, each compiled kernel's LLVM IR goes to FOLDER/ir/<hash>.ll, for diffing the members
# of a literal family (which constant differs, and where it comes from).
ENV_IR = "LAYERBVH_KERNEL_CENSUS_IR"

# Literals (decimal, hex, the kernel's own hash in its name) are what two kernels of one
# "family" differ in when a size or a constant was baked into the code instead of passed opaque.
# Also the names of the functions it calls (a virtual call's targets, `func_<hash of their
# code>`): a literal inside one renames it. Without them, three media cases of the stability
# suite (one scene, three densities) counted no family; with them, 54 of their 137 kernels.
_LITERAL = re.compile(r"(drjit|func)_[0-9a-f]{32}|0x[0-9A-Fa-f]+|\b\d+(\.\d+)?([eE][-+]?\d+)?\b")
_original = dr.kernel_history
_path: str | None = None


def family(ir: str) -> str:
    """A hash of the kernel's IR with its literals blanked: equal for kernels that differ only by them."""
    return hashlib.blake2b(_LITERAL.sub("#", ir).encode(), digest_size=8).hexdigest()


def _record(entries) -> None:
    test = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0]
    lines = []
    for k in entries:
        if k.get("cache_hit") or not k.get("hash"):
            continue  # found in this process's memory (no compile, no disk read), or not a traced kernel
        ir = k.get("ir")
        text = ir.getvalue() if hasattr(ir, "getvalue") else str(ir or "")
        if os.environ.get(ENV_IR) and not k.get("cache_disk"):
            os.makedirs(os.path.join(os.path.dirname(_path), "ir"), exist_ok=True)
            with open(os.path.join(os.path.dirname(_path), "ir", f"{k.get('hash')}.ll"), "w") as f:
                f.write(text)
        lines.append(json.dumps({"test": test, "hash": k.get("hash"), "family": family(text),
                                 "disk": bool(k.get("cache_disk")), "ops": k.get("operation_count"),
                                 "size": k.get("size"),
                                 "ms": k.get("backend_time", 0.0) + k.get("codegen_time", 0.0)}))
    if lines:
        with open(_path, "a") as f:
            f.write("\n".join(lines) + "\n")


def _tee():
    """dr.kernel_history that also records what it hands out (its readers drain it: compile_clock)."""
    entries = _original()
    _record(entries)
    return entries


def flush() -> None:
    """Record what nobody read yet (a test's end, the process's exit)."""
    if _path is not None:
        _record(_original())


def start_from_env() -> None:
    """Turn the census on where ENV names a folder (layerbvh's import does this)."""
    global _path
    folder = os.environ.get(ENV)
    if not folder or _path is not None:
        return
    os.makedirs(folder, exist_ok=True)
    _path = os.path.join(folder, f"{os.getpid()}.jsonl")
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history = _tee
    atexit.register(flush)
