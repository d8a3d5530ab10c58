"""The cache simulator's numba kernels: one access through set-associative LRU levels (loads, and stores with
write-allocate and write-back), a flush of the private levels, and warp coalescing."""
from __future__ import annotations

import numba
import numpy as np

# Columns of Caches.arrays' params; one row per level.
PARAM_COLUMNS = 6
P_SETS, P_WAYS, P_LINE, P_SHARED, P_OFFSET, P_INSTANCES = range(PARAM_COLUMNS)

# Columns of Caches.arrays' counts; one row per level and a last row for DRAM. A level's misses
# include its write misses. DRAM's row: C_HITS = transactions that reached DRAM (every level
# missed), C_WRITE_BACKS = lines written back into it.
COUNT_COLUMNS = 4
C_HITS, C_MISSES, C_WRITE_MISSES, C_WRITE_BACKS = range(COUNT_COLUMNS)

EMPTY_TAG = -1  # line numbers are >= 0 because addresses are

# Stores (issue 57, item 5): every level is write-back and write-allocate, as the CPU's caches are
# and as valgrind's simulator counts them (a store that misses D1 fetches its line: a D1 write
# miss, and an LL write miss where the LL misses too). A store makes its line dirty in the first
# level only; a level that evicts a dirty line writes it back to the nearest level below that holds
# the line (marking it dirty there, its recency unchanged) or, where none does, to DRAM. Valgrind
# counts no write-backs; the model's are DRAM write traffic. On NVIDIA GPUs, what the replay
# stores is the local entry stack, which L1 caches write-back (global stores go through L1 to L2:
# the replay makes none).


# This function's shape is tuned by measurement (20-25 ns per L1 hit, against 30-50 ns for
# equivalent code): numba passes each array as ~7 scalars, so a call that LLVM does not inline costs
# ~15 ns, and it inlines only a small body with few exits; a raise, an extra return or a break out of
# the level loop each tipped it over. Reference counting is off (_nrt=False: nothing here allocates)
# because numba's pruning of the per-argument atomic incref/decref pairs failed for most shapes.
# Hence: invalid input returns -1 rather than raising, one merged scan of the set, and the hit
# returns from inside it. (Dropping the input check entirely would save another ~10 ns.) The
# write-back of a dirty victim is a call of its own: rare, and kept out of the hit path.
@numba.njit(cache=True, _nrt=False)
def cache_access(tags, stamps, dirty, params, counts, clock, unit, addr, write):
    """One access to byte address `addr` by unit `unit` (an SM or core), a store where `write`:
    looks it up level by level (each level uses its own line = addr // line_bytes, its own set
    index = line % sets, LRU within the set, instance = unit if the level is private else 0),
    counts hits/misses per level (and a store's misses as write misses), fills every level that
    missed (inclusive fill, LRU victim; a dirty victim is written back first), marks the line
    dirty in the first level on a store, and returns the index of the level that held it
    (len(levels) = DRAM). A negative address, or a unit outside [0, units) while the nearest level
    is private, returns -1 and counts nothing."""
    nlevels = params.shape[0]
    # Caches puts private levels first, each with one instance per unit, so level 0 bounds `unit`.
    if addr < 0 or (params[0, P_SHARED] == 0 and (unit < 0 or unit >= params[0, P_INSTANCES])):
        nlevels = -1
    clock[0] += 1
    now = clock[0]
    for k in range(max(nlevels, 0)):
        sets = params[k, P_SETS]
        ways = params[k, P_WAYS]
        line = _line_of(addr, params[k, P_LINE])
        instance = unit if params[k, P_SHARED] == 0 else 0
        base = params[k, P_OFFSET] + (instance * sets + _set_of(line, sets)) * ways
        empty = -1
        victim = base
        oldest = stamps[base]
        for i in range(base, base + ways):
            tag = tags[i]
            if tag == line:
                stamps[i] = now
                counts[k, C_HITS] += 1
                if write and k == 0:
                    dirty[i] = 1
                return k
            if tag == EMPTY_TAG:
                if empty < 0:
                    empty = i
            elif stamps[i] < oldest:
                oldest = stamps[i]
                victim = i
        counts[k, C_MISSES] += 1
        if write:
            counts[k, C_WRITE_MISSES] += 1
        if empty >= 0:
            victim = empty
        elif dirty[victim]:
            write_back(tags, dirty, params, counts, k, unit, tags[victim] * params[k, P_LINE])
        # Filling on the way down equals filling after the lower levels answered: each level has
        # its own tag array.
        tags[victim] = line
        stamps[victim] = now
        dirty[victim] = 1 if (write and k == 0) else 0
    if nlevels >= 0:
        counts[nlevels, C_HITS] += 1
    return nlevels


@numba.njit(cache=True, _nrt=False)
def write_back(tags, dirty, params, counts, k, unit, addr):
    """Level `k` evicts (or flushes) the dirty line at byte address `addr`: counted as its write-back,
    and the line is marked dirty in the nearest level below that holds it (its recency unchanged),
    or written into DRAM where none does."""
    counts[k, C_WRITE_BACKS] += 1
    nlevels = params.shape[0]
    for j in range(k + 1, nlevels):
        sets = params[j, P_SETS]
        ways = params[j, P_WAYS]
        line = _line_of(addr, params[j, P_LINE])
        instance = unit if params[j, P_SHARED] == 0 else 0
        base = params[j, P_OFFSET] + (instance * sets + _set_of(line, sets)) * ways
        for i in range(base, base + ways):
            if tags[i] == line:
                dirty[i] = 1
                return j
    counts[nlevels, C_WRITE_BACKS] += 1
    return nlevels


@numba.njit(cache=True, inline="always")
def _line_of(addr, line_bytes):
    """addr // line_bytes for addr >= 0. numba's signed // is two hardware divisions plus a sign
    fix-up and dominated an access; line and segment sizes are powers of two in practice."""
    if line_bytes & (line_bytes - 1) == 0:
        shift = 0
        while (1 << shift) < line_bytes:
            shift += 1
        return addr >> shift
    return np.int64(np.uint64(addr) // np.uint64(line_bytes))


@numba.njit(cache=True, inline="always")
def _set_of(line, sets):
    if sets & (sets - 1) == 0:
        return line & (sets - 1)
    return np.int64(np.uint64(line) % np.uint64(sets))


@numba.njit(cache=True)
def flush_private_levels(tags, dirty, params, counts):
    """Empties every private level, writing its dirty lines back first (a GPU's L1s at a kernel's
    end: the next kernel starts cold, and what its stores left reaches L2)."""
    for k in range(params.shape[0]):
        if params[k, P_SHARED] == 0:
            start = params[k, P_OFFSET]
            per_unit = params[k, P_SETS] * params[k, P_WAYS]
            end = start + params[k, P_INSTANCES] * per_unit
            for i in range(start, end):
                if dirty[i] and tags[i] != EMPTY_TAG:
                    write_back(tags, dirty, params, counts, k, (i - start) // per_unit, tags[i] * params[k, P_LINE])
                dirty[i] = 0
            tags[start:end] = EMPTY_TAG


@numba.njit(cache=True, _nrt=False)
def coalesce(addrs, active, n, size_bytes, seg_bytes, out):
    """Distinct segments (segment id = byte address // seg_bytes) touched by the byte ranges
    [addrs[i], addrs[i] + size_bytes) of the first n lanes where active[i] (an address < 0 also
    means no request); writes the segment ids to out in ascending order (out needs
    n * (size_bytes // seg_bytes + 2) entries) and returns how many. This is the coalescing model:
    one load instruction of a warp issues one memory transaction per distinct segment.
    size_bytes or seg_bytes < 1 returns -1."""
    if size_bytes < 1 or seg_bytes < 1:
        return -1
    count = 0
    for i in range(n):
        a = addrs[i]
        if not active[i] or a < 0:
            continue
        for s in range(_line_of(a, seg_bytes), _line_of(a + size_bytes - 1, seg_bytes) + 1):
            # Insertion into the sorted distinct list: a warp's segments arrive nearly sorted
            # when it coalesces well, and there are at most a few dozen when it does not.
            j = count
            while j > 0 and out[j - 1] > s:
                j -= 1
            if j > 0 and out[j - 1] == s:
                continue
            for m in range(count, j, -1):
                out[m] = out[m - 1]
            out[j] = s
            count += 1
    return count
