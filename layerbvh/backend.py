"""Which Dr.Jit backend (LLVM or CUDA) a trace runs on, and its array types."""
from __future__ import annotations

import os

import drjit as dr


def module(backend: str):
    """The non-AD Dr.Jit array module of `backend` ('llvm' or 'cuda')."""
    if backend == "llvm":
        return dr.llvm
    if backend == "cuda":
        return dr.cuda
    raise ValueError(f"backend must be 'llvm' or 'cuda', got {backend!r}")


def default_backend() -> str:
    """LAYERBVH_BACKEND if set, else CUDA when a GPU is usable, else LLVM."""
    env = os.environ.get("LAYERBVH_BACKEND")
    if env:
        return env
    return "cuda" if dr.has_backend(dr.JitBackend.CUDA) else "llvm"


def backend_of(x) -> str | None:
    """The backend of a Dr.Jit array (or array of arrays), None for anything else."""
    if not dr.is_array_v(x):
        return None
    b = dr.backend_v(x)
    if b == dr.JitBackend.LLVM:
        return "llvm"
    if b == dr.JitBackend.CUDA:
        return "cuda"
    return None
