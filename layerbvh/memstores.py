"""The locality replay's stores: as a lane ends, the hit it writes to the results, and in a wavefront step its sort
key, its state record and the entries it still holds; and the trace call's passes before its first kernel."""
from __future__ import annotations

import numba

from . import cachesim, memsites, numba_cache
from .cachesim import cache_access, coalesce
from .memsites import (FIRST_STEP, I_DONE, I_HITS, I_NL, I_SP, NO_READ, S_END, S_FRAME_READ, S_FRAME_WRITE, S_KEY_OUT,
                       S_RAY_OUT, S_RES_T, S_RES_V, S_SPILL_LINK, S_SPILL_T, S_STATE_OUT, SITES)

# What the kernels do (walk.walk, wavefront._step/_tail): per_ray's kernel writes every ray's hit
# (or miss) by slot as the ray ends (Results.write); a step and the tail write each closer hit by
# slot as they find it, which the replay stands for by one write of the ray's last closer hit as
# its lane ends (a ray that improves its hit twice in a step writes the same slot's lines again,
# which the first write brought into L1). A step writes every lane's sort key, and each going-on
# ray's state record, in lane order (StateRecords.write into the step's `rec_out`); the first step
# also each going-on ray's ray record, by slot (RayRecords.write).


@numba.njit(cache=True, inline="always")
def reset(req_j):
    """No store yet this iteration: the output sites' entries of one lane's row of requests."""
    for k in range(S_END, SITES):
        req_j[k] = NO_READ


@numba.njit(cache=True, inline="always")
def lane_end(s, position, bounded, use_global, ist, req_j):
    """The stores of ray `s` whose lane (at `position` in the launch) ended this iteration, as
    element indices in its row of requests; returns the sites as a bit mask. (The entries it still
    holds are spill_stores'.)"""
    used = 0
    if (not bounded and not use_global) or ist[s, I_HITS] > 0:
        for k in range(S_RES_T, S_RES_V + 1):
            req_j[k] = s
            used |= 1 << k
    if bounded:
        req_j[S_KEY_OUT] = position
        used |= 1 << S_KEY_OUT
        if ist[s, I_DONE] == 0:
            req_j[S_STATE_OUT] = position
            used |= 1 << S_STATE_OUT
            if bounded == FIRST_STEP:
                req_j[S_RAY_OUT] = s
                used |= 1 << S_RAY_OUT
    return used


@numba.njit(cache=True)
def spill_stores(s, ist, cap_g, site_base, seg_bytes, unit, tags, stamps, dirty, params, counts, clock, tally,
                 levels_hit, loads, addr, every, segs):
    """Ray `s` writes the entries it still holds (before walk's spill moves its stack pointer)
    above its global stack (row `s` of `cap_g` entries): one range of 4-byte words in each of the
    link and distance arrays, a store of each segment it touches."""
    held, sp = ist[s, I_NL], ist[s, I_SP]
    if held == 0:
        return
    n_levels = levels_hit.shape[1] - 1
    for k in (S_SPILL_LINK, S_SPILL_T):
        addr[0] = site_base[k] + (s * cap_g + sp) * 4
        m = coalesce(addr, every, 1, held * 4, seg_bytes, segs)
        tally[k, 0] += m
        tally[k, 1] += held
        loads[s, k] += held
        for i in range(m):
            lvl = cache_access(tags, stamps, dirty, params, counts, clock, unit, segs[i] * seg_bytes, True)
            levels_hit[k, min(lvl, n_levels)] += 1


@numba.njit(cache=True)
def setup_pass(site, base, nbytes, write, seg_bytes, unit, tags, stamps, dirty, params, counts, clock, tally,
               levels_hit):
    """One pass of the trace call over `nbytes` from byte `base` (a fill, the compaction's mask read
    and index write, the records' packing): one access per segment, in order, counted at `site`."""
    n_levels = levels_hit.shape[1] - 1
    first = base - base % seg_bytes
    for a in range(first, base + nbytes, seg_bytes):
        lvl = cache_access(tags, stamps, dirty, params, counts, clock, unit, a, write)
        tally[site, 0] += 1
        tally[site, 1] += 1
        levels_hit[site, min(lvl, n_levels)] += 1


@numba.njit(cache=True)
def frame_pass(slot_id, site_base, site_bytes, seg_bytes, unit, tags, stamps, dirty, params, counts, clock, tally,
               levels_hit):
    """A packet iteration's stack frame (memsites.S_FRAME_READ) in the packet slot `slot_id`: the
    registers it spills written, then read back, one access per segment (none where it is 0 bytes)."""
    nbytes = site_bytes[S_FRAME_READ]
    if nbytes > 0:
        for site, write in ((S_FRAME_WRITE, True), (S_FRAME_READ, False)):
            setup_pass(site, site_base[S_FRAME_READ] + slot_id * nbytes, nbytes, write, seg_bytes, unit, tags, stamps,
                       dirty, params, counts, clock, tally, levels_hit)


numba_cache.follow(globals(), cachesim, memsites)  # what these compile in (numba_cache)
