"""The check that a locality replay follows the kernel: per ray, its hits, work counts and loads of each kind equal
what the kernel returned and counted."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import memsites as ms
from .state import MISS

@dataclass
class TraceCheck:
    """Where a replay and the kernel (LayerBVH.trace/occluded with stats) disagree, per ray."""

    mode: str
    rays: int
    hit_mismatches: int             # prim differs, or t's bits differ on a hit
    work_mismatches: dict           # per counter: rays whose count differs
    load_mismatches: dict           # per load kind (LOAD_KINDS): rays whose load count differs

    @property
    def exact(self) -> bool:
        return self.hit_mismatches == 0 and not any(self.work_mismatches.values()) \
            and not any(self.load_mismatches.values())


def check_trace(bvh, o, d, tmax, any_hit: bool, rep) -> TraceCheck:
    """`rep`: a locality.ReplayResult of rays (o, d, tmax). Trace the same rays with the kernel
    (bvh: a layerbvh.LayerBVH over the replayed layout, batch_rays >= the ray count) in rep.mode and
    compare hits and per-ray work counts."""
    if any_hit:
        q = bvh.occluded(o, d, tmax, mode=rep.mode, stats=True)
        kernel_hit = np.asarray(q.occluded, bool)
        hits = int(np.count_nonzero(kernel_hit != (rep.prim != MISS)))
        work = q.work
    else:
        h = bvh.trace(o, d, tmax, mode=rep.mode, stats=True)
        kp, kt = np.asarray(h.prim).astype(np.int64), np.asarray(h.t, np.float32)
        same_t = (kt.view(np.uint32) == rep.t.view(np.uint32)) | (kp == MISS)
        hits = int(np.count_nonzero((kp != rep.prim) | ~same_t))
        work = h.work
    mism = {name: int(np.count_nonzero(np.asarray(work[name]).astype(np.int64) != rep.work[name]))
            for name in rep.work}
    # The loads, per kind: what the kernel counted against what the replay fed to the cache model.
    counter = {kind: name for kind, (_, name) in ms.LOAD_KINDS.items()} | {"ray": "steps", "state": "steps"}
    loads = {kind: int(np.count_nonzero(np.asarray(work[counter[kind]]).astype(np.int64) != n))
             for kind, n in rep.loads.items()}
    return TraceCheck(mode=rep.mode, rays=len(rep.prim), hit_mismatches=hits, work_mismatches=mism,
                      load_mismatches=loads)


def same_as(rep, check: TraceCheck, ref) -> TraceCheck:
    """`check` (of `ref`, the same mode under another schedule) for `rep`: the kernel's mismatches
    plus the rays where `rep` differs from `ref`."""
    hits = int(np.count_nonzero((rep.prim != ref.prim) | (rep.t.view(np.uint32) != ref.t.view(np.uint32))))
    work = {k: check.work_mismatches[k] + int(np.count_nonzero(rep.work[k] != ref.work[k])) for k in rep.work}
    loads = {k: check.load_mismatches[k] + int(np.count_nonzero(rep.loads[k] != ref.loads[k])) for k in rep.loads}
    return TraceCheck(mode=rep.mode, rays=check.rays, hit_mismatches=check.hit_mismatches + hits, work_mismatches=work,
                      load_mismatches=loads)


