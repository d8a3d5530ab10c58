"""Memory model for traversal locality: warp coalescing, set-associative LRU caches, hardware presets."""
# Speed, measured by hand (not a test) on this project's dev VM (AMD EPYC, 2 vCPUs, AVX-512,
# 23 GiB), 100M cache_access calls from a cached numba loop:
#   sequential 4-byte scan (L1 hit rate 0.875-0.94):  2.6 s (cpu), 2.8 s (gtx965m), 3.4 s (h200)
#   uniform random 64-byte reads over 64 MiB, random units (almost all L1 misses): 6.3 s (gtx965m,
#   its tag arrays fit the host's caches), 28.9 s (cpu), 31.4 s (h200: 60 MiB of L2 is ~30 MiB of
#   tags and stamps, so most simulated accesses miss the host's own caches).
from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

KIB = 1024
MIB = 1024 * KIB

from .cachesim import (C_HITS, C_MISSES, C_WRITE_BACKS, C_WRITE_MISSES, COUNT_COLUMNS, EMPTY_TAG,  # noqa: F401
                       P_INSTANCES, P_LINE, P_OFFSET, P_SETS, P_SHARED, P_WAYS, PARAM_COLUMNS, cache_access,
                       coalesce, flush_private_levels)

# NVIDIA caches allocate and move 32-byte sectors (L1 lines and L2 lines are 128 bytes of four
# sectors, each with its own valid bit, and a miss fetches only the sectors it needs). We model each
# level as a cache of 32-byte lines with the same capacity: per-128-byte tags with sector valid bits
# are approximated by independent 32-byte lines (which may be evicted separately).
GPU_SECTOR_BYTES = 32
NVIDIA_WARP = 32
# A traversal kernel's register use caps occupancy well below the 64 warps an SM could hold.
GPU_RESIDENT_WARPS = 16
GPU_BLOCK_WARPS = 4  # 128-thread blocks
# NVIDIA documents neither L1 nor L2 associativity; these are stated assumptions.
GPU_L1_WAYS = 4
GPU_L2_WAYS = 16

# Dr.Jit's LLVM backend hands each pool thread blocks of 16K lanes (jit_llvm_block_size() == 16384 in
# drjit 1.5.0; drjit-core LLVMThreadState::launch uses it once a launch exceeds 2 * cores * 16K lanes,
# smaller launches are split evenly over the cores), and runs each SIMD packet's loop to completion
# before the next packet.
DRJIT_LLVM_BLOCK_LANES = 16384

CPU_CACHE_DIR = Path("/sys/devices/system/cpu/cpu0/cache")
CPU_INFO = Path("/proc/cpuinfo")
# /proc/cpuinfo flag -> the SIMD's name and its lanes of 32-bit floats, widest first (also what
# scripts/test.sh prints first, issue 64).
SIMD_BY_FLAG = (("avx512f", "AVX-512", 16), ("avx2", "AVX2", 8))
SIMD_LANES_DEFAULT = 4  # SSE / NEON


def cpu_flags(cpuinfo: Path = CPU_INFO) -> set[str]:
    """The flags /proc/cpuinfo lists (empty where there is none)."""
    try:
        return set(cpuinfo.read_text().split())
    except OSError:
        return set()


def simd_name(flags: set[str]) -> str:
    """"AVX-512", "AVX2" or "neither AVX2 nor AVX-512" for a CPU's flags."""
    return next((name for flag, name, _ in SIMD_BY_FLAG if flag in flags), "neither AVX2 nor AVX-512")
# Used only where /sys has no cache description (containers without sysfs, other OSes): typical
# current x86 server core, 64-byte lines.
FALLBACK_CPU_LEVELS = (
    ("L1", 32 * KIB, 8, 64, False),
    ("L2", 1 * MIB, 16, 64, False),
    ("L3", 32 * MIB, 16, 64, True),
)


def format_bytes(n: int) -> str:
    """Exact binary size: '24 KiB', '1 MiB', '60 MiB', '100 B'."""
    for unit, scale in (("GiB", 1024 * MIB), ("MiB", MIB), ("KiB", KIB)):
        if n >= scale and n % scale == 0:
            return f"{n // scale} {unit}"
    return f"{n} B"


@dataclass(frozen=True)
class CacheLevel:
    name: str  # "L1", "L2", "L3"
    size_bytes: int
    ways: int
    line_bytes: int  # allocation/transfer granule (GPU: 32-byte sectors, CPU: 64-byte lines)
    shared: bool  # True: one instance for all units; False: one per unit (SM or core)

    def __post_init__(self):
        if self.size_bytes <= 0 or self.ways <= 0 or self.line_bytes <= 0:
            raise ValueError(f"{self.name}: size, ways and line bytes must be positive, got "
                             f"{self.size_bytes}, {self.ways}, {self.line_bytes}")
        if self.size_bytes % (self.ways * self.line_bytes):
            raise ValueError(f"{self.name}: size {self.size_bytes} is not a whole number of sets of "
                             f"{self.ways} ways x {self.line_bytes} B")

    @property
    def sets(self) -> int:
        return self.size_bytes // (self.ways * self.line_bytes)

    def describe(self) -> str:
        scope = "shared" if self.shared else "private"
        return (f"{self.name} {format_bytes(self.size_bytes)} {self.ways}-way "
                f"{self.line_bytes} B lines {scope}")


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    kind: str  # "gpu" or "cpu"
    units: int  # SMs or cores
    resident_warps: int  # warps one unit interleaves round-robin, one loop iteration each (CPU: 1)
    block_warps: int  # consecutive warps that go to one unit together
    warp: int  # natural width: 32 on NVIDIA, SIMD lanes of 32-bit floats on a CPU
    segment_bytes: int  # coalescing granule: one memory transaction
    levels: tuple  # tuple[CacheLevel, ...], nearest first; misses of the last go to DRAM
    flush_private_each_kernel: bool  # GPU L1s are not kept coherent across kernel launches
    source: str

    def as_dict(self) -> dict:
        d = asdict(self)
        d["levels"] = [asdict(level) for level in self.levels]
        return d

    def describe(self) -> str:
        unit = "SMs" if self.kind == "gpu" else "cores"
        group = "warps" if self.kind == "gpu" else "packets"
        levels = ", ".join(level.describe() for level in self.levels)
        flush = ("private levels flushed each kernel" if self.flush_private_each_kernel
                 else "caches kept across kernels")
        return (f"{self.name}: {self.description}; {self.kind}, {self.units} {unit} x "
                f"{self.resident_warps} resident {group} of {self.warp} lanes, "
                f"{self.block_warps} {group} per block, {self.segment_bytes} B segments; "
                f"{levels}; {flush}")


def nvidia_preset(name: str, part: str, sms: int, l1_bytes: int, l2_bytes: int, source: str) -> Preset:
    """An NVIDIA GPU: `sms` SMs of one private L1 each over a shared L2, 32-lane warps, 32-byte
    sectors, L1s flushed at each kernel launch; what differs between parts is the arguments."""
    return Preset(
        name=name,
        description=f"{part}; {GPU_RESIDENT_WARPS} resident warps per SM because a traversal kernel's register "
                    "use limits occupancy",
        kind="gpu", units=sms, resident_warps=GPU_RESIDENT_WARPS, block_warps=GPU_BLOCK_WARPS, warp=NVIDIA_WARP,
        segment_bytes=GPU_SECTOR_BYTES,
        levels=(CacheLevel("L1", l1_bytes, GPU_L1_WAYS, GPU_SECTOR_BYTES, shared=False),
                CacheLevel("L2", l2_bytes, GPU_L2_WAYS, GPU_SECTOR_BYTES, shared=True)),
        flush_private_each_kernel=True, source=source)


GTX965M = nvidia_preset(
    "gtx965m", "NVIDIA GeForce GTX 965M (Maxwell GM204, the paper's GPU)", 8, 24 * KIB, 1 * MIB,
    (
        "8 SMM: 1024 CUDA cores / 128 per Maxwell SMM (GeForce GTX 980 Whitepaper, 'GM204 Hardware "
        "Architecture In-Depth'; GTX 965M launch specs: 1024 cores, 128-bit bus). "
        "L1 24 KB per SM: CUDA C++ Programming Guide, Compute Capability 5.x: 'a unified L1/texture "
        "cache of 24 KB used to cache reads from global memory'; Maxwell Tuning Guide 'Unified "
        "L1/Texture Cache': GM204 caches global loads there for read-only (LDG/texture) loads or with "
        "-Xptxas -dlcm=ca (we assume the traversal's node/triangle loads take that path). "
        "L2 1 MB: not published for the GTX 965M; GTX 980 Whitepaper: 'Tied to each memory controller "
        "are 16 ROP units and 512KB of L2 cache' (four 64-bit controllers, 2048 KB), so the 965M's "
        "128-bit bus (two controllers, 32 ROPs) gives 2 x 512 KB = 1 MB, as third-party spec tables "
        "list it. 32-byte sectors: Nsight (VSE) 'Memory Statistics - Caches' (L2 and texture "
        "transactions are 32 bytes) and NVIDIA's forum answer that Maxwell-Pascal L1/TEX lines are "
        "128 B of four 32 B sectors, fetched per sector. Ways: not documented; assumed L1 "
        f"{GPU_L1_WAYS}-way, L2 {GPU_L2_WAYS}-way. Resident warps {GPU_RESIDENT_WARPS} and "
        f"{GPU_BLOCK_WARPS}-warp blocks: modelling choices (register-limited occupancy, 128-thread "
        "blocks)."
    ))

H200 = nvidia_preset(
    "h200", "NVIDIA H200 SXM (Hopper GH100, 132 SMs)", 132, 256 * KIB, 60 * MIB,
    (
        "132 SMs: NVIDIA H100 Tensor Core GPU Architecture whitepaper (H100 SXM5: 132 SMs; H200 is "
        "the same GH100 configuration). L1 256 KB: Hopper Tuning Guide, 'Unified Shared Memory/L1/"
        "Texture Cache': compute capability 9.0 'increases the maximum capacity of the combined L1 "
        "cache, texture cache, and shared memory to 256 KB' with shared-memory carveouts of 0, 8, "
        "..., 228 KB; a kernel using no shared memory can get the 0 KB carveout, leaving all 256 KB "
        "as L1 (an upper bound: the carveout is a hint the driver may round up). L2 60 MB (NOT the "
        "H100's 50 MB): the whitepaper gives 'A 50 MB L2 cache in H100' for the H100 SXM5 with five "
        "HBM3 stacks; the full GH100 die has 60 MB of L2 beside 12 512-bit memory controllers "
        "(Chips and Cheese, 'Nvidia's H100: Funny L2, and Tons of Bandwidth': the H100 PCIe enables "
        "50 MB with 10 controllers), and the H200 populates all six HBM3e stacks; the CUDA runtime on "
        "an H200 reports 60 MB of L2 and 132 multiprocessors (torch.cuda.get_device_properties, as "
        "recorded 2026-10-28 in this workplace's notes on its lent H200 machines). "
        "The L2 is two partitions joined by a crossbar; modelled as one shared cache. 32-byte "
        "sectors: Nsight Compute memory chart (L1/TEX and L2 lines are four 32-byte sectors). Ways: "
        "not documented; assumed L1 "
        f"{GPU_L1_WAYS}-way, L2 {GPU_L2_WAYS}-way. Resident warps {GPU_RESIDENT_WARPS} and "
        f"{GPU_BLOCK_WARPS}-warp blocks: modelling choices."
    ))


def _parse_size(text: str) -> int:
    m = re.fullmatch(r"\s*(\d+)\s*([KMG]?)B?\s*", text, re.IGNORECASE)
    if not m:
        raise ValueError(f"unreadable cache size {text!r}")
    return int(m.group(1)) * {"": 1, "K": KIB, "M": MIB, "G": 1024 * MIB}[m.group(2).upper()]


def _cpu_list_len(text: str) -> int:
    """How many cpus a list like '0-3,8,10-11' names."""
    count = 0
    for part in text.strip().split(","):
        if not part:
            continue
        lo, _, hi = part.partition("-")
        count += int(hi or lo) - int(lo) + 1
    return count


def _read_sys_levels(cache_dir: Path) -> list[CacheLevel]:
    levels = []
    for index in sorted(cache_dir.glob("index*")):
        def read(name: str) -> str:
            return (index / name).read_text().strip()

        if read("type") not in ("Data", "Unified"):
            continue
        size = _parse_size(read("size"))
        line = int(read("coherency_line_size"))
        ways = int(read("ways_of_associativity"))
        if ways <= 0:  # the kernel reports 0 for fully associative caches
            ways = size // line
        levels.append((int(read("level")), CacheLevel(
            f"L{read('level')}", size, ways, line, shared=_cpu_list_len(read("shared_cpu_list")) > 1)))
    return [level for _, level in sorted(levels, key=lambda item: item[0])]


def _read_cpuinfo(cpuinfo: Path) -> tuple[str, int]:
    """(model name, SIMD lanes of 32-bit floats) of the first cpu listed."""
    model, flags = "unknown CPU", set()
    try:
        text = cpuinfo.read_text()
    except OSError:
        return model, SIMD_LANES_DEFAULT
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model == "unknown CPU":
            model = value.strip()
        elif key in ("flags", "Features") and not flags:
            flags = set(value.split())
    lanes = next((n for flag, _, n in SIMD_BY_FLAG if flag in flags), SIMD_LANES_DEFAULT)
    return model, lanes


def _host_units() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def host_cpu_preset(*, cache_dir: Path | str = CPU_CACHE_DIR, cpuinfo: Path | str = CPU_INFO,
                    units: int | None = None) -> Preset:
    """The machine this runs on. Shared levels (shared_cpu_list names more than one cpu) are one
    instance for all `units` cores, even where the hardware has one per core complex."""
    cache_dir, cpuinfo = Path(cache_dir), Path(cpuinfo)
    try:
        levels = _read_sys_levels(cache_dir)
    except (OSError, ValueError):
        levels = []
    if levels:
        where = (f"{cache_dir}/index*/{{level,type,size,ways_of_associativity,coherency_line_size,"
                 f"shared_cpu_list}} (data and unified caches)")
    else:
        levels = [CacheLevel(*spec) for spec in FALLBACK_CPU_LEVELS]
        where = (f"FALLBACK: {cache_dir} unreadable, so a typical x86 server core is assumed ("
                 + ", ".join(level.describe() for level in levels) + ")")
    model, lanes = _read_cpuinfo(cpuinfo)
    units = units or _host_units()
    return Preset(
        name="cpu",
        description=f"this host: {model}, {units} cores, {lanes}-lane SIMD",
        kind="cpu",
        units=units,
        resident_warps=1,
        block_warps=max(1, DRJIT_LLVM_BLOCK_LANES // lanes),
        warp=lanes,
        segment_bytes=levels[0].line_bytes,
        levels=tuple(levels),
        flush_private_each_kernel=False,
        source=(f"levels: {where}; cores: os.sched_getaffinity (else os.cpu_count); model and SIMD "
                f"width: {cpuinfo} (avx512f -> 16, avx2 -> 8, else 4 lanes); block_warps assumes "
                f"Dr.Jit LLVM's work block of {DRJIT_LLVM_BLOCK_LANES} lanes (jit_llvm_block_size() "
                "in drjit 1.5.0) and that each packet runs its loop to completion (resident 1)"),
    )


PRESETS: dict[str, Preset] = {"gtx965m": GTX965M, "h200": H200, "cpu": host_cpu_preset()}


def preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; one of: {', '.join(PRESETS)}") from None


def with_segment(p: Preset, segment_bytes: int) -> Preset:
    """`p` with transactions of `segment_bytes` (e.g. 128-byte lines instead of a GPU's 32-byte
    sectors): every level then allocates at least that much per line, so one transaction is one
    line everywhere. Named NAME-sS (the rows of different segment sizes stay apart)."""
    if segment_bytes < 1 or segment_bytes & (segment_bytes - 1):
        raise ValueError(f"segment size must be a power of two, got {segment_bytes}")
    if segment_bytes == p.segment_bytes:
        return p
    levels = tuple(CacheLevel(lv.name, lv.size_bytes, lv.ways, max(lv.line_bytes, segment_bytes), lv.shared)
                   for lv in p.levels)
    return Preset(**{**p.__dict__, "name": f"{p.name}-s{segment_bytes}", "segment_bytes": segment_bytes,
                     "levels": levels})


class Caches:
    """A preset's hierarchy as numba-ready arrays, plus its counters."""

    def __init__(self, preset: Preset):
        self.preset = preset
        levels = preset.levels
        if not levels:
            raise ValueError(f"{preset.name}: no cache levels")
        shared = [level.shared for level in levels]
        if shared != sorted(shared):
            # cache_access bounds `unit` by level 0's instances, which needs private levels first.
            raise ValueError(f"{preset.name}: private levels must come before shared ones")
        params = np.zeros((len(levels), PARAM_COLUMNS), dtype=np.int64)
        offset = 0
        for k, level in enumerate(levels):
            # Re-checked here because a CacheLevel can be built around __post_init__ (replace, copy).
            if level.size_bytes % (level.ways * level.line_bytes):
                raise ValueError(f"{level.name}: size {level.size_bytes} is not a whole number of "
                                 f"sets of {level.ways} ways x {level.line_bytes} B")
            instances = 1 if level.shared else preset.units
            params[k] = (level.sets, level.ways, level.line_bytes, int(level.shared), offset, instances)
            offset += instances * level.sets * level.ways
        tags = np.full(offset, EMPTY_TAG, dtype=np.int64)
        stamps = np.zeros(offset, dtype=np.int64)
        dirty = np.zeros(offset, dtype=np.int8)
        counts = np.zeros((len(levels) + 1, COUNT_COLUMNS), dtype=np.int64)
        clock = np.zeros(1, dtype=np.int64)
        # (cache_access's leading arguments, in its order: `cache_access(*caches.arrays, unit, addr, write)`)
        self.arrays = (tags, stamps, dirty, params, counts, clock)

    @property
    def counts(self) -> np.ndarray:
        """Per level, then DRAM: hits, misses, write misses, write-backs (cachesim's C_* columns)."""
        return self.arrays[4]

    def reset(self) -> None:
        tags, stamps, dirty, _, counts, clock = self.arrays
        tags.fill(EMPTY_TAG)
        stamps.fill(0)
        dirty.fill(0)
        counts.fill(0)
        clock[0] = 0

    def flush_private(self) -> None:
        tags, _, dirty, params, counts, _ = self.arrays
        flush_private_levels(tags, dirty, params, counts)

    def hit_rates(self) -> list[float]:
        rates = []
        for hits, misses in self.counts[:-1, :C_WRITE_MISSES]:
            total = hits + misses
            rates.append(float(hits / total) if total else 0.0)
        return rates

    def bytes_below(self) -> list[int]:
        """Bytes each level fetched from below (its misses, loads and stores alike: a store's miss
        fetches its line)."""
        params = self.arrays[3]
        return [int(self.counts[k, C_MISSES] * params[k, P_LINE]) for k in range(len(params))]

    def bytes_written_below(self) -> list[int]:
        """Bytes each level wrote back to the levels below (its dirty lines evicted or flushed)."""
        params = self.arrays[3]
        return [int(self.counts[k, C_WRITE_BACKS] * params[k, P_LINE]) for k in range(len(params))]

    def dram_write_bytes(self) -> int:
        """Bytes written back into DRAM (dirty lines no cache level below their own held)."""
        return int(self.counts[-1, C_WRITE_BACKS] * self.arrays[3][-1, P_LINE])
