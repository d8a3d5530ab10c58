"""What a traversal carries per ray: the rays read by slot, the state between wavefront steps, the results, and the
MISS sentinel."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import drjit as dr


class EntryStack(NamedTuple):
    """The global entry stack of a wavefront trace: entries pushed in earlier steps, `rows` per
    ray slot (entry k of slot i at i * rows + k), link and entry distance in two arrays. A step's
    kernel reads it through one EntryStack and writes the entries its rays still hold through a
    second over the same memory (wavefront.trace; walk's spill)."""

    link: object  # UInt32 (slots * rows)
    t: object     # Float (slots * rows)
    rows: int


# The one "no hit" value: the primitive of a ray that hit nothing (uint32), and the instance of
# a ray that hit nothing or is not inside an instance.
MISS = 0xFFFFFFFF

# What a ray carries between wavefront steps (the layer modes): one record per ray (StateRecords),
# 4-byte words, in one of two formats (issue 40: was 8 arrays, 32 bytes, with u and v, permuted
# every step). The full record, 8 words:
#   t        float32  closest hit distance so far (culls entries; bounds the slab tests)
#   prim     uint32   its primitive (of two hits at the same t the lower id wins)
#   link     uint32   where the ray goes on: a node or exit link (never a leaf or POP: a step
#                     tests a leaf it pops and ends only at another treelet's node or exit)
#   sp       uint32   the depth of its entry stack in global memory, the entries it still held at
#                     the end of the step that wrote the record included (written there by that
#                     step's kernel as the ray's walk ended)
#   slot     uint32   its ray: which ray record, entry-stack rows and results are its own
#   treelet  uint32   the treelet of its next step: its sort key
#   inst     uint32   instanced layouts: the instance it is inside (else unused)
#   hit_inst uint32   instanced layouts: the instance of its closest hit (else unused)
# total: 32 bytes, one GPU sector and half a CPU cache line: the next step gathers a ray's record
# by the sort's permutation with one aligned load (six 4-byte arrays gathered in permuted order
# would cost a sector each). u and v are not carried: a step that improves a ray's hit writes t,
# u, v and prim to the results by slot. Statistics runs carry the work counters beside it.
# The compact record, 4 words, wherever it can hold the state (no instances, entry stacks under
# 2^SP_BITS rows, batches under 2^(32 - SP_BITS) rays; StateRecords.words):
#   t        float32  as above
#   prim     uint32   as above
#   link     uint32   as above
#   slot|sp  uint32   slot << SP_BITS | sp
# total: 16 bytes, half the full record's writes per ray that goes on. The treelet is not stored:
# an exit link names its treelet, and the next step looks a node link's up (layout.node_treelet;
# nodes of one treelet are contiguous, so a sorted warp's lookups share a sector or two).
LEAN_STATE = ("t", "prim", "link", "sp", "slot", "treelet")
LEAN_STATE_BYTES = 4 * len(LEAN_STATE)   # what the next step needs: 24 bytes ...
STATE_RECORD_WORDS = 8
STATE_RECORD_BYTES = 4 * STATE_RECORD_WORDS  # ... stored in a 32-byte record (written whole) ...
COMPACT_RECORD_WORDS = 4
COMPACT_RECORD_BYTES = 4 * COMPACT_RECORD_WORDS  # ... or, packed and less the treelet, in 16
SP_BITS = 8
# Work counted per ray when statistics are asked for: RayState field -> Results/Hits name.
# The last two are the stores a wavefront step makes besides its state record and sort key: the
# entries a ray still holds at a step's end, written above its global stack (walk's spill), and
# the closer hits written by slot as they are found (steps and tail). locality.check_trace holds
# them against the replay, whose between-step bytes (steptraffic.sort_traffic) count them.
WORK = {"n_inner": "inner_nodes", "n_leaf": "leaves", "n_tri": "triangles", "n_iter": "iterations",
        "n_steps": "steps", "n_stack": "stack_reads", "n_treelet": "treelet_reads", "n_root": "root_reads",
        "n_spill": "entries_written", "n_hitw": "hits_written"}
# ... and per level in an instanced layout: the inner nodes of those that were of the top level
# (the rest were inside instances) and the instances entered.
INSTANCE_WORK = {"n_top": "top_inner_nodes", "n_enter": "instance_entries"}


def work_fields(instanced: bool) -> dict:
    """The work counted per ray: RayState field -> Results/Hits name."""
    return {**WORK, **INSTANCE_WORK} if instanced else WORK


class SlotRays:
    """Origins and directions as six slot-ordered arrays (per_ray: its rays stay in slot order,
    so each lane's reads stream)."""

    def __init__(self, m, o, d):
        self.m, self.o, self.d = m, tuple(o), tuple(d)

    def load(self, slot):
        """(origin, direction) of the rays in `slot`, as three Floats each."""
        m = self.m
        return [dr.gather(m.Float, a, slot) for a in self.o], [dr.gather(m.Float, a, slot) for a in self.d]


class RayRecords:
    """Origins and directions as one 32-byte record per slot, [ox oy oz dx dy dz 0 0] (the layer
    modes: a sorted step reads a ray with one cache line instead of carrying six arrays through
    every permutation). A trace's records are written by its first wavefront step, for the rays
    that go on (`unfilled`, `write`): that step reads its rays in slot order, where the six arrays
    coalesce, and a ray that finishes there needs no record (PERFORMANCE.md entry 63)."""

    STRIDE = 8  # floats per record; total: 32 bytes

    def __init__(self, m, o, d):
        """Every ray's record, packed by one kernel (scripts/bench_ray_records.py measures it)."""
        self.m = m
        n = dr.width(o[0])
        self.rec = dr.empty(m.Float, n * self.STRIDE)
        self.write(o, d, dr.arange(m.UInt32, n), True)
        dr.eval(self.rec)

    @classmethod
    def unfilled(cls, m, n: int) -> "RayRecords":
        """Room for `n` records, none written yet (evaluated: a frozen step takes it as an input)."""
        rays = cls.over(m, dr.empty(m.Float, n * cls.STRIDE))
        dr.make_opaque(rays.rec)  # (allocated, no kernel: dr.eval leaves an empty array undefined)
        return rays

    def write(self, o, d, slot, active) -> None:
        """The records of the rays `slot` where `active`, each written whole (its padding too, so
        nothing fills the array first: six scatters of one component each were six kernels, each
        passing over every record, valgrind's 3.5 write misses per ray, PERFORMANCE.md entry 59)."""
        zero = dr.zeros(self.m.Float, dr.width(slot))
        dr.scatter(self.rec, self.m.ArrayXf([*o, *d] + [zero] * (self.STRIDE - 6)), slot, active)

    @classmethod
    def over(cls, m, rec) -> "RayRecords":
        """The records `rec` (another RayRecords' array) as a RayRecords, with no copy."""
        rays = cls.__new__(cls)
        rays.m, rays.rec = m, rec
        return rays

    def load(self, slot):
        """(origin, direction) of the rays in `slot`, as three Floats each (one packet load)."""
        x = dr.gather(self.m.ArrayXf, self.rec, slot, shape=(self.STRIDE, dr.width(slot)))
        return [x[c] for c in range(3)], [x[c] for c in range(3, 6)]


class StateRecords:
    """The rays' states between wavefront steps as one record per lane of the step that wrote them
    (the formats above LEAN_STATE): a step writes its lanes' records in lane order (one packet
    store per lane, coalesced), and the next step reads each of its rays' with one gather by the
    sort's permutation, so nothing permutes the states in between (issue 40)."""

    @staticmethod
    def words(instanced: bool, rows: int, n: int) -> int:
        """The words of a record for a trace of `n` rays with `rows` entry-stack rows per ray: the
        compact format wherever its packed slot and depth fit, else the full one."""
        fits = not instanced and rows < (1 << SP_BITS) and n <= (1 << (32 - SP_BITS))
        return COMPACT_RECORD_WORDS if fits else STATE_RECORD_WORDS

    @staticmethod
    def write(m, s: "RayState", active, words: int, into=None):
        """The records of the lanes of `s` where `active` (the rays that go on), in lane order (a
        flat UInt32 array, `words` words a lane; the others' rows are left unwritten), into a new
        array or into `into` (a frozen step's: an array allocated inside one has the size of the
        call it was recorded at, whatever the lanes of a later call)."""
        n = dr.width(s.link)
        t = dr.reinterpret_array(m.UInt32, s.t)
        if words == COMPACT_RECORD_WORDS:
            w = [t, s.prim, s.link, (s.slot << SP_BITS) | s.sp]
        else:
            spare = dr.full(m.UInt32, MISS, n)
            w = [t] + [getattr(s, f) for f in LEAN_STATE[1:]] \
                + [s.inst if s.inst is not None else spare, s.hit_inst if s.hit_inst is not None else spare]
        rec = dr.empty(m.UInt32, n * words) if into is None else into
        dr.scatter(rec, m.ArrayXu(w), dr.arange(m.UInt32, n), active)
        return rec

    @staticmethod
    def read(m, rec, idx, instanced: bool, words: int) -> "RayState":
        """The states of the records `idx` (one gather of `words` words a lane; lazy: it runs
        inside the kernel that uses it). A compact record's treelet is None: walk finds it."""
        w = dr.gather(m.ArrayXu, rec, idx, shape=(words, dr.width(idx)))
        t = dr.reinterpret_array(m.Float, w[0])
        if words == COMPACT_RECORD_WORDS:
            return RayState(t=t, prim=w[1], link=w[2], sp=w[3] & ((1 << SP_BITS) - 1), slot=w[3] >> SP_BITS,
                            treelet=None)
        s = RayState(t=t, prim=w[1], link=w[2], sp=w[3], slot=w[4], treelet=w[5])
        if instanced:
            s.inst, s.hit_inst = w[6], w[7]
        return s


class DirectRays:
    """Origins and directions held as they are, one per lane (a trace inside a caller's kernel,
    where every lane is its own ray and no slot indirection exists)."""

    def __init__(self, o, d):
        self.o, self.d = list(o), list(d)

    def load(self, slot):
        return self.o, self.d


@dataclass
class RayState:
    """What a ray carries from one wavefront step to the next (one array per field; origins and
    directions stay in the batch's ray records, read by slot).

    `t, u, v, prim` are the closest hit so far (prim = MISS: none; between wavefront steps u and
    v are None: a step writes an improved hit to the results by slot, and t, prim are all the next
    step reads of it: LEAN_STATE), `link` where the ray goes on
    (a node, leaf or exit link, or layout.POP), `sp` the depth of its entry stack in global
    memory, `slot` its index in the caller's ray batch (and so which entry stack and ray record
    it owns), `treelet` the treelet it traverses in the coming step. The work counters are None
    unless statistics were asked for: permuting them every step costs as much as any other field.
    In an instanced layout `inst` is the instance the ray is inside (MISS: in world space) and
    `hit_inst` the instance of the closest hit so far; both None otherwise."""

    t: object
    prim: object
    link: object
    sp: object
    slot: object
    treelet: object
    u: object = None
    v: object = None
    n_inner: object = None
    n_leaf: object = None
    n_tri: object = None
    n_iter: object = None
    n_steps: object = None  # kernel calls (wavefront steps, or the per-ray kernel) the ray took part in
    n_stack: object = None    # global entry-stack entries read (each: link and distance)
    n_treelet: object = None  # node-treelet lookups (a popped global entry's, a compact record's link's)
    n_root: object = None     # exit roots looked up (treelet_first)
    n_spill: object = None    # entries written above the global entry stack at steps' ends
    n_hitw: object = None     # closer hits written to the results by slot as found
    n_top: object = None
    n_enter: object = None
    inst: object = None
    hit_inst: object = None

    @classmethod
    def start(cls, m, tmax, count_work: bool, instanced: bool = False) -> "RayState":
        """Every ray at the root, no hit yet, slot = its index."""
        n = dr.width(tmax)
        zero = dr.zeros(m.UInt32, n)
        s = cls(t=m.Float(tmax), prim=dr.full(m.UInt32, MISS, n), link=zero, sp=zero, slot=dr.arange(m.UInt32, n),
                treelet=zero)
        if count_work:
            for field in work_fields(instanced):
                setattr(s, field, zero)
        if instanced:
            s.inst, s.hit_inst = dr.full(m.UInt32, MISS, n), dr.full(m.UInt32, MISS, n)
        return s

    @classmethod
    def begin(cls, m, slot, tmax, instanced: bool = False) -> "RayState":
        """A wavefront trace's first step's states, built in its kernel from each lane's `slot` (the
        batch index of its ray) and the batch's `tmax` (read by slot): every ray at the root (node 0,
        in treelet 0, so no lookup), no hit yet, nothing on its stack. The set-up writes no state
        records for the first step to read back (issue 57 item 2: 16 or 32 bytes per ray, twice)."""
        n = dr.width(slot)
        zero, miss = dr.zeros(m.UInt32, n), dr.full(m.UInt32, MISS, n)
        s = cls(t=dr.gather(m.Float, tmax, slot), prim=miss, link=zero, sp=zero, slot=slot, treelet=zero)
        if instanced:
            s.inst, s.hit_inst = miss, miss
        return s

    def fields(self) -> dict:
        return {k: v for k, v in vars(self).items() if v is not None}

    def take(self, idx) -> "RayState":
        """The rays `idx`, physically copied so the next step reads them sequentially."""
        return RayState(**{k: dr.gather(type(v), v, idx) for k, v in self.fields().items()})


class Results:
    """Per-ray outputs, written by ray slot as rays finish: the closest hit (prim = MISS: none;
    for any-hit queries, prim != MISS means occluded), its instance (instanced layouts only,
    else None) and the work counters."""

    def __init__(self, m, n, instanced: bool = False):
        self.t = dr.full(m.Float, dr.inf, n)
        self.u = dr.zeros(m.Float, n)
        self.v = dr.zeros(m.Float, n)
        self.prim = dr.full(m.UInt32, MISS, n)
        self.inst = dr.full(m.UInt32, MISS, n) if instanced else None
        self.work = {name: dr.zeros(m.UInt32, n) for name in work_fields(instanced).values()}  # per ray (statistics)

    def arrays(self) -> tuple:
        inst = (self.inst,) if self.inst is not None else ()
        return (self.t, self.u, self.v, self.prim, *self.work.values()) + inst

    def fields(self) -> dict:
        """The arrays by name (a PyTree: what a frozen step takes, `over` gives back)."""
        return {"t": self.t, "u": self.u, "v": self.v, "prim": self.prim, "inst": self.inst, "work": self.work}

    @classmethod
    def over(cls, fields: dict) -> "Results":
        """Results writing into the arrays of `fields` (another Results' `fields()`), no copy."""
        res = cls.__new__(cls)
        for k, v in fields.items():
            setattr(res, k, v)
        return res

    def write_hits(self, s: RayState, u, v, mask) -> None:
        """The closest hits of the rays `mask` (hit t, prim and instance from `s`), by slot."""
        for dst, src in ((self.t, s.t), (self.u, u), (self.v, v), (self.prim, s.prim), (self.inst, s.hit_inst)):
            if dst is not None:
                dr.scatter(dst, src, s.slot, mask)

    def place(self, other: "Results", idx) -> None:
        """Copy the results of a sub-batch to the rays `idx`."""
        for dst, src in zip(self.arrays(), other.arrays()):
            dr.scatter(dst, src, idx)

    def write(self, s: RayState, mask) -> None:
        """The hits (when `s` carries u and v: a per_ray walk's) and work counters of the rays
        `mask`, by slot."""
        if s.u is not None:
            self.write_hits(s, s.u, s.v, mask)
        if s.n_iter is not None:
            for field, name in work_fields(self.inst is not None).items():
                dr.scatter(self.work[name], getattr(s, field), s.slot, mask)
