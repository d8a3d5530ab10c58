"""Mitsuba's instances held still while Dr.Jit records a render: no Python garbage collection
between the first and the last call a kernel records.

Why (issue 39; found as a worker abort of the suite that depended on the tests run before it):
Dr.Jit dispatches a call on a pointer array (`mi.MediumPtr`, `mi.BSDFPtr`, ...) over every live
instance of that class in its registry. Mitsuba objects of earlier renders often die only when
Python's cyclic collector runs, and that can happen at any allocation in the middle of recording
`sample`. Then one kernel holds a call recorded over two instances and a later one over the one
left. Dr.Jit 1.5.0 (drjit-core's `jitc_assemble_func`) keys the deduplicated callable bodies by
(body hash, direct or indirect), but names both `func_<body hash>` in the LLVM module: the same
body emitted twice, "invalid redefinition of function", and `jitc_fail` aborts the process.
(Reproduced deterministically in tests/runtime/test_held_instances.py.)

So while a render is recorded the collector is paused: the registry holds the same instances from
the first call to the last. (What was garbage before stays until the render ends; a full collection
first would drop their callables from the kernel, but costs ~0.12 s per render with Mitsuba, numba
and Dask loaded, measured here: more than many small renders take.) The hold is layerbvh.collector_held.
"""
from __future__ import annotations

import layerbvh

# The hold itself is the engine's (layerbvh.collector_held): one counter for the renders and the
# frozen wavefront steps inside them, so neither switches the collector on under the other.
instances_held = layerbvh.collector_held
