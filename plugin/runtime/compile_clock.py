"""Seconds Dr.Jit spent compiling kernels over a stretch of work, for nested timers (a render, and auto's pre-pass
inside it)."""
from __future__ import annotations

import drjit as dr

# dr.kernel_history() hands out its entries once and empties itself, so two timers reading it
# directly would steal each other's entries (auto's pre-pass runs inside a timed render). Every
# reader goes through this log instead; `start` of the outermost timer clears it.
_log: list = []
_depth = 0


def _drain() -> None:
    _log.extend(dr.kernel_history())


def compile_seconds(entries) -> float:
    """LLVM/NVRTC time of the kernels in `entries` that were compiled, not found in the cache."""
    return sum(k.get("backend_time", 0.0) + k.get("codegen_time", 0.0)
               for k in entries if not k.get("cache_hit")) / 1e3  # ms


class CompileClock:
    """`with CompileClock() as c: ...`, then `c.seconds`: kernel compile time inside the block.
    Nestable; turns Dr.Jit's kernel history on for the outermost block."""

    def __enter__(self) -> "CompileClock":
        global _depth
        if _depth == 0:
            self._was_on = dr.flag(dr.JitFlag.KernelHistory)
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()  # what came before is not ours
            _log.clear()
        else:
            _drain()
        _depth += 1
        self._mark = len(_log)
        self.seconds = 0.0
        return self

    def __exit__(self, *exc) -> None:
        global _depth
        _drain()
        self.seconds = compile_seconds(_log[self._mark:])
        _depth -= 1
        if _depth == 0:
            dr.set_flag(dr.JitFlag.KernelHistory, self._was_on)
            _log.clear()
