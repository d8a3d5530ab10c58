"""What a traversal carries per ray: the ray records read by slot, the state between wavefront steps, the results, and the MISS sentinel."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

NO_HIT = 0xFFFFFFFF


class RaySource:
    """Origins and directions of a ray batch, read by ray slot inside the traversal kernel.

    per_ray reads six slot-ordered arrays (its rays stay in slot order, so that streams). The
    layer modes keep one 32-byte record per slot, [ox oy oz dx dy dz 0 0]: a sorted step reads
    a ray's record with one cache line instead of carrying six arrays through every permutation."""

    STRIDE = 8

    def __init__(self, m, o, d, interleaved: bool):
        self.m, self.interleaved = m, interleaved
        if interleaved:
            n = dr.width(o[0])
            rec = dr.zeros(m.Float, n * self.STRIDE)
            idx = dr.arange(m.UInt32, n) * self.STRIDE
            for c, x in enumerate(tuple(o) + tuple(d)):
                dr.scatter(rec, x, idx + c)
            dr.eval(rec)
            self.rec = rec
        else:
            self.o, self.d = tuple(o), tuple(d)

    def load(self, slot):
        m = self.m
        if self.interleaved:
            base = slot * self.STRIDE
            x = [dr.gather(m.Float, self.rec, base + c) for c in range(6)]
            return x[:3], x[3:]
        return ([dr.gather(m.Float, a, slot) for a in self.o], [dr.gather(m.Float, a, slot) for a in self.d])


@dataclass
class RayState:
    """What a ray carries from one wavefront step to the next (one array per field; origins and
    directions stay in the batch's RaySource, read by slot).

    `link` is where the ray goes on (a node, leaf or exit link, or POP), `sp` the depth of its
    entry stack in global memory, `slot` its index in the caller's ray batch (and so which
    entry stack and ray record it owns), `treelet` the treelet it traverses in the coming step.
    The work counters are None unless statistics were asked for: permuting them every step
    costs as much as any other field."""

    t: object
    u: object
    v: object
    prim: object
    tri: object
    link: object
    sp: object
    slot: object
    treelet: object
    n_inner: object = None
    n_leaf: object = None
    n_tri: object = None
    n_iter: object = None

    def fields(self) -> dict:
        return {k: v for k, v in vars(self).items() if v is not None}


def _initial_state(m, n, tmax, count_work: bool) -> RayState:
    zero = dr.zeros(m.UInt32, n)
    s = RayState(t=m.Float(tmax), u=dr.zeros(m.Float, n), v=dr.zeros(m.Float, n),
                 prim=dr.full(m.UInt32, 0xFFFFFFFF, n), tri=dr.full(m.UInt32, NO_HIT, n),
                 link=zero, sp=zero, slot=dr.arange(m.UInt32, n), treelet=zero)
    if count_work:
        s.n_inner, s.n_leaf, s.n_tri, s.n_iter = zero, zero, zero, zero
    return s


def _take(m, s: RayState, idx) -> RayState:
    """The rays `idx` of `s`, physically copied so the next step reads them sequentially."""
    return RayState(**{k: dr.gather(type(v), v, idx) for k, v in s.fields().items()})


class Results:
    """Per-ray outputs, written by ray slot as rays finish."""

    def __init__(self, m, n):
        self.t = dr.full(m.Float, dr.inf, n)
        self.u = dr.zeros(m.Float, n)
        self.v = dr.zeros(m.Float, n)
        self.tri = dr.full(m.UInt32, NO_HIT, n)
        self.work = [dr.zeros(m.UInt32, n) for _ in range(4)]  # inner, leaf, tri, iterations

    def place(self, other: "Results", idx) -> None:
        """Copy the results of a sub-batch to the rays `idx`."""
        for dst, src in zip((self.t, self.u, self.v, self.tri, *self.work),
                            (other.t, other.u, other.v, other.tri, *other.work)):
            dr.scatter(dst, src, idx)

    def write(self, s: RayState, mask):
        for dst, src in ((self.t, s.t), (self.u, s.u), (self.v, s.v), (self.tri, s.tri)):
            dr.scatter(dst, src, s.slot, mask)
        if s.n_iter is not None:
            for dst, src in zip(self.work, (s.n_inner, s.n_leaf, s.n_tri, s.n_iter)):
                dr.scatter(dst, src, s.slot, mask)
