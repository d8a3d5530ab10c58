"""What a wavefront step moves besides its traversal kernel's loads (the layer modes' "between steps" bytes), and the
limits a step design has to meet to save memory traffic."""
from __future__ import annotations

from .state import LEAN_STATE_BYTES
from .wavefront import ENTRY_BYTES

HIT_BYTES = 16              # t, u, v, prim: one hit written to the results


def result_traffic(per_ray: bool, rays: int, hits_written: int) -> int:
    """Bytes a trace writes to its results (t, u, v, prim by slot), in every mode, so that modes
    compare fairly: per_ray's kernel writes each ray's once, as it finishes, hit or miss; the
    layer modes write each closer hit as a step (or the tail) finds it (`hits_written`, traced by
    the replay and counted by the kernel), so a ray that improves its hit twice writes twice and
    a ray that misses writes nothing. (The results' first fill is the same in every mode.)"""
    return HIT_BYTES * (rays if per_ray else hits_written)


def sort_traffic(n: int, pushed: int, done: int, sort: bool, last: bool, record_bytes: int, ray_bytes: int = 0) -> int:
    """Bytes a wavefront step of `n` rays moves besides its traversal kernel's loads (issue 40's
    design, wavefront.trace): each array element read or written once, all of it counted as DRAM
    traffic (streams far larger than any cache). `pushed` (the entries the rays that go on still
    hold at the step's end) and `done` (rays that finished) are traced by the replay as the kernel
    runs.
    - the step kernel's writes: every lane's sort key, in lane order; the state record of each ray
      that goes on, in lane order (`record_bytes`: its format's, state.StateRecords, written whole);
      the entries each such ray still holds, above its global stack, as its walk ends (walk's
      spill: an entry pushed and taken within the step never leaves the kernel's local stack);
      in the first step also the ray record of each such ray (`ray_bytes`, by slot: the later
      kernels read it; state.RayRecords.write);
      the finished-ray count is an atomic on one word (no bytes per ray);
    - then, unless every ray finished, the sort (block_mkperm reads the keys, writes the
      permutation) or the compaction (keys read, the rays that go on written);
    - the permutation, read by the next step as it gathers each ray's record through it. The
      record gather itself is one of the next kernel's loads (cache-simulated with them).
    The hits a step writes to the results are counted apart, as every mode's are (result_traffic).
    The write-back's reads of the lane's local stack (memory that lane wrote in the same kernel)
    are not counted."""
    left = n - done
    kernel = n * 4 + left * (record_bytes + ray_bytes) + pushed * ENTRY_BYTES
    if last:
        return kernel
    order = n * 4 + n * 4 if sort else n * 4 + left * 4  # block_mkperm; compress
    return kernel + order + left * 4


def limits(rows: list) -> None:
    """Fill in each layer row's break-even and lower bound (per ray and wavefront step):
    - break-even: (per_ray's DRAM bytes per ray, its results' writes and set-up included, - the
      layer kernels' own, their results' writes and their set-up) / the ray's wavefront steps: what
      the steps may move between them and still cost the bus less than per_ray;
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
                r.break_even_bytes_per_ray_step = (p.total_dram_bytes_per_ray - r.dram_bytes_per_ray
                                                   - r.result_bytes_per_ray - (r.setup_bytes_per_ray or 0.0)
                                                   ) / wave_steps
                r.lower_bound_bytes_per_ray_step = ((LEAN_STATE_BYTES - 4) * r.carried_per_ray_step
                                                    + ENTRY_BYTES * r.pushed_per_ray_step)
