"""What a render will need in memory (film, camera rays, the traversal's work), against what the machine has: refused
by name before it starts."""
from __future__ import annotations

import resource
from pathlib import Path

from layerbvh_mitsuba.ab.render import UserError, passes_for


# Estimates, rounded up from what a render allocates (Mitsuba's block and ours); see memory_estimate.
FILM_BYTES_PER_PIXEL = 96
RAY_BYTES = {"megakernel": 160, "wavefront": 1024}
MAX_LANES = 1 << 32  # Dr.Jit arrays hold fewer than 2^32 entries


def available_memory() -> int | None:
    """Bytes this process can still allocate: the least of the system's MemAvailable, the
    cgroup's limit less its usage (containers) and the address-space limit (`ulimit -v`) less
    this process's size; None where none can be read."""
    limits = []
    try:
        with open("/proc/meminfo") as fh:
            limits += [int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("MemAvailable:")]
    except OSError:
        pass
    try:
        cap = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if cap != "max":
            limits.append(int(cap) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        try:
            with open("/proc/self/status") as fh:
                size = next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmSize:"))
            limits.append(soft - size)
        except (OSError, StopIteration):
            limits.append(soft)
    return max(min(limits), 0) if limits else None


def memory_estimate(width: int, height: int, spp: int, loop: str, work_bytes: int = 0) -> dict:
    """What a render of width x height at `spp` needs, in bytes: the film, one pass's rays
    (`passes_for`) in the given loop ("megakernel" or "wavefront"), and the traversal's BVH and
    work memory (`work_bytes`)."""
    pixels = width * height
    passes, per_pass = passes_for(pixels, spp)
    rays = pixels * min(per_pass, spp)
    film = pixels * FILM_BYTES_PER_PIXEL
    per_pass_bytes = rays * RAY_BYTES[loop]
    return {"pixels": pixels, "rays_per_pass": rays, "passes": passes, "film": film, "rays": per_pass_bytes,
            "traversal": work_bytes, "total": film + per_pass_bytes + work_bytes}


def check_memory(width: int, height: int, spp: int, loop: str = "wavefront", work_bytes: int = 0,
                 what: str = "the render") -> dict:
    """The estimate, or a UserError (one line) when it exceeds the available memory or what one
    Dr.Jit array can index."""
    e = memory_estimate(width, height, spp, loop, work_bytes)
    gib = (lambda b: f"{b / 2 ** 30:.1f} GiB")
    if e["rays_per_pass"] >= MAX_LANES:
        raise UserError(f"{what} at {width}x{height} traces {e['rays_per_pass']:,} camera rays in one pass, more "
                        f"than Dr.Jit arrays can hold ({MAX_LANES:,}); lower the resolution")
    free = available_memory()
    if free is not None and e["total"] > free:
        raise UserError(f"{what} at {width}x{height}, {spp} spp needs about {gib(e['total'])} (film "
                        f"{gib(e['film'])}, one pass of {e['rays_per_pass']:,} rays {gib(e['rays'])}, traversal "
                        f"{gib(e['traversal'])}); {gib(free)} is available: lower --res or --spp")
    return e
