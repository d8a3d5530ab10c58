"""Which Dr.Jit backend (LLVM or CUDA) a trace runs on, and its array types."""
from __future__ import annotations

import ctypes
import os
import platform
from pathlib import Path

import drjit as dr
import numpy as np

# Byte alignment of every numpy array handed to Dr.Jit (a cache line; an AVX-512 packet).
# Dr.Jit 1.5 maps a contiguous numpy array's memory as it is, without a copy. A kernel that reads
# an array not aligned to its packet is compiled with `align 1` loads: another kernel hash for the
# same code, so each kernel compiled once per alignment pattern of its inputs (numpy's malloc
# gives 16-byte alignment, so the pattern is chance: ~4,200 kernels compiled in the test suite,
# issue 39), and a gather from it falls back to one vpgatherdd per float (layout.py).
ALIGN = 64



def module(backend: str):
    """The non-AD Dr.Jit array module of `backend` ('llvm' or 'cuda')."""
    if backend == "llvm":
        return dr.llvm
    if backend == "cuda":
        return dr.cuda
    raise ValueError(f"backend must be 'llvm' or 'cuda', got {backend!r}")


def aligned(a: np.ndarray, align: int = ALIGN) -> np.ndarray:
    """`a` itself if it is contiguous and starts on an `align`-byte boundary, else such a copy."""
    if a.flags.c_contiguous and a.ctypes.data % align == 0:
        return a
    buf = np.empty(a.nbytes + align, np.uint8)
    start = -buf.ctypes.data % align
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def from_numpy(T, a):
    """Dr.Jit array of type `T` (any backend, AD or not) holding numpy array `a`, mapped from
    aligned memory (see ALIGN): every numpy array goes to Dr.Jit through here. A Dr.Jit array
    is converted as `T(a)` would."""
    return T(a) if dr.is_array_v(a) else T(aligned(np.asarray(a)))


def default_backend() -> str:
    """LAYERBVH_BACKEND if set, else CUDA when a GPU is usable, else LLVM."""
    env = os.environ.get("LAYERBVH_BACKEND")
    if env:
        return env
    return "cuda" if dr.has_backend(dr.JitBackend.CUDA) else "llvm"


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else what `platform` says: part of what a
    timing depends on (auto's decisions, benchmark headers)."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            return next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), model)
    except OSError:
        return model


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


def llvm_vector_width() -> int:
    """Lanes per packet of Dr.Jit's LLVM backend (8 with AVX2, 16 with AVX-512)."""
    return _llvm_target()[2]()


def set_llvm_vector_width(width: int) -> None:
    """Make the LLVM backend compile kernels for packets of `width` lanes (a power of two,
    4..64; wider than the CPU's vectors, LLVM splits each operation). Dr.Jit 1.5 does not expose
    this in Python; drjit-core exports `jit_llvm_set_target(cpu, features, width)`, called here
    with the current CPU and features. Kernels compiled afterwards use the new width."""
    if width not in (4, 8, 16, 32, 64):
        raise ValueError(f"vector width must be 4, 8, 16, 32 or 64, got {width}")
    cpu, features, _, set_target = _llvm_target()
    set_target(cpu(), features(), width)


# The instruction sets the LLVM backend can be told to compile for (LAYERBVH_LLVM_ISA): the
# project's machines are AVX2 (8 lanes) or AVX-512 (16 lanes) CPUs, and float rounding in a
# kernel (vector width, FMA contraction, the ISA's min/max and rcp) may differ between them
# (issue 64). "avx2" on an AVX-512 CPU compiles every kernel as an AVX2 CPU would get it, so a
# test's expectation can be checked at both; Embree's ISA cannot be chosen (Mitsuba passes
# Embree a fixed configuration, and its Embree 3 reads no configuration file).
LLVM_ISAS = {"avx2": 8, "avx512": 16}
LLVM_ISA_ENV = "LAYERBVH_LLVM_ISA"


def llvm_isa() -> str:
    """The instruction set the LLVM backend compiles for: "avx512", "avx2" or "other"."""
    features = _llvm_target()[1]().decode().split(",")
    return "avx512" if "+avx512f" in features else "avx2" if "+avx2" in features else "other"


def set_llvm_isa(isa: str) -> None:
    """Make the LLVM backend compile kernels for `isa` (LLVM_ISAS) at its vector width: "avx2"
    turns off every AVX-512 feature of this CPU's (it must have AVX2); "avx512" needs a CPU
    that has it. Kernels compiled afterwards (Mitsuba's too) use it."""
    if isa not in LLVM_ISAS:
        raise ValueError(f"{LLVM_ISA_ENV}: the LLVM ISA must be one of {', '.join(LLVM_ISAS)}, got {isa!r}")
    cpu, features, _, set_target = _llvm_target()
    have = features().decode().split(",")
    need = "+avx512f" if isa == "avx512" else "+avx2"
    if need not in have:
        raise RuntimeError(f"{LLVM_ISA_ENV}={isa}: this CPU ({cpu_model()}) has no {need[1:]}")
    if isa == "avx2":
        have = [("-" + f[1:]) if f.startswith("+avx512") or f == "+evex512" else f for f in have]
    set_target(cpu(), ",".join(have).encode(), LLVM_ISAS[isa])


def apply_llvm_isa_from_env() -> None:
    """Honour LAYERBVH_LLVM_ISA (unset: the CPU's own); called once when layerbvh is imported."""
    isa = os.environ.get(LLVM_ISA_ENV)
    if isa:
        try:
            set_llvm_isa(isa)
        except (ValueError, RuntimeError) as e:  # one line, not a traceback from an import
            raise SystemExit(f"layerbvh: {e}") from None


def _llvm_target():
    dr.llvm.Float(0).index  # noqa: B018  (initialises the LLVM backend)
    try:
        lib = ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so"))
        cpu, features = lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv
        width, set_target = lib._Z21jit_llvm_vector_widthv, lib._Z19jit_llvm_set_targetPKcS0_j
    except (OSError, AttributeError) as e:
        raise RuntimeError(f"this Dr.Jit build does not export the LLVM target settings ({e})") from None
    cpu.restype = features.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    return cpu, features, width, set_target
