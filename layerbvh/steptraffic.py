"""What a wavefront step moves besides its traversal kernel's loads (the layer modes' "between steps" bytes), and the limits a step design has to meet to save memory traffic."""
from __future__ import annotations

from .state import LEAN_STATE_BYTES, STATE_RECORD_BYTES
from .wavefront import ENTRY_BYTES

HIT_BYTES = 16              # t, u, v, prim: what a step writes by slot for each closer hit it finds


def sort_traffic(n: int, pushed: int, improved: int, done: int, sort: bool, last: bool) -> int:
    """Bytes a wavefront step of `n` rays moves besides its traversal kernel's loads (issue 40's
    design, wavefront.trace): each array element read or written once, all of it counted as DRAM
    traffic (streams far larger than any cache). `pushed` (the entries the rays that go on still
    hold at the step's end), `improved` (closer hits the step found: each is written at once) and
    `done` (rays that finished) are traced by the replay as the kernel runs.
    - the step kernel's writes: every lane's sort key, in lane order; the state record
      (STATE_RECORD_BYTES, written whole) of each ray that goes on, in lane order; the entries each
      such ray still holds, above its global stack, as its walk ends (walk's spill: an entry pushed
      and taken within the step never leaves the kernel's local stack); each closer hit by slot
      (the finished-ray count is an atomic on one word: no bytes per ray);
    - then, unless every ray finished, the sort (block_mkperm reads the keys, writes the
      permutation) or the compaction (keys read, the rays that go on written);
    - the permutation, read by the next step as it gathers each ray's record through it. The
      record gather itself is one of the next kernel's loads (cache-simulated with them).
    The results a ray writes when it finishes are not counted: per_ray writes the same. Nor are
    the write-back's reads of the lane's local stack (memory that lane wrote in the same kernel)."""
    left = n - done
    kernel = n * 4 + left * STATE_RECORD_BYTES + pushed * ENTRY_BYTES + improved * HIT_BYTES
    if last:
        return kernel
    order = n * 4 + n * 4 if sort else n * 4 + left * 4  # block_mkperm; compress
    return kernel + order + left * 4


def limits(rows: list) -> None:
    """Fill in each layer row's break-even and lower bound (per ray and wavefront step):
    - break-even: (per_ray's DRAM bytes per ray - the layer kernels' own) / the ray's wavefront
      steps: what the steps may move between them and still cost the bus less than per_ray;
    - lower bound, for any exact wavefront design that keeps every exit (state.LEAN_STATE): each
      ray that goes on must write the next step's state once per step (t, prim, link, sp and the
      sort key: 20 bytes, LEAN_STATE_BYTES less slot, which a design could keep in place; a ray that
      finished needs none) and every entry it still holds once (ENTRY_BYTES each); the ray record
      and the state the step reads are already in the kernels' DRAM bytes. Sorting (at least a key
      read and a permutation written) comes on top for the sorted mode."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r.kind, r.preset, r.warp, r.treelet_height, r.branching), {})[r.mode] = r
    for g in groups.values():
        p = g.get("per_ray")
        for mode, r in g.items():
            if mode == "per_ray" or p is None or r.steps_per_ray == 0:
                continue
            wave_steps = r.sort_bytes_per_ray / r.sort_bytes_per_ray_step if r.sort_bytes_per_ray_step else 0.0
            if wave_steps:
                r.break_even_bytes_per_ray_step = (p.dram_bytes_per_ray - r.dram_bytes_per_ray) / wave_steps
                r.lower_bound_bytes_per_ray_step = ((LEAN_STATE_BYTES - 4) * r.carried_per_ray_step
                                                    + ENTRY_BYTES * r.pushed_per_ray_step)
