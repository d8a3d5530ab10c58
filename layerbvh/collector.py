"""Python's cycle collector paused while Dr.Jit records kernels: one nested, thread-safe hold for
every recording (a render's, a frozen wavefront step's).

Why: whatever the collector frees runs its release in the middle of the recording, and Dr.Jit
1.5.0 aborts the process on two such releases (both reproduced in subprocess tests):
- a Mitsuba object of an earlier render dying while a render's virtual calls are recorded: the
  call is then recorded over two sets of instances, and the module names one body twice
  (plugin/runtime/held_instances.py, tests/runtime/test_held_instances.py);
- anything released through a host callback (a Mitsuba scene, an Embree scene, a DLPack import)
  while a frozen function records: "enqueue_host_func(): this function cannot be recorded"
  (layerbvh/wavefront.py's frozen steps, tests/runtime/test_frozen_recording.py).
What was garbage before waits for the next collection after the outermost hold (a full collection
instead costs ~0.12 s with Mitsuba, numba and Dask loaded: more than many small renders take).
"""
from __future__ import annotations

import contextlib
import gc
import threading

_lock = threading.Lock()
_depth = 0                # holds entered and not left (nested, or in other threads)
_was_enabled = True       # the collector's state before the outermost one


@contextlib.contextmanager
def collector_held():
    """Pause the cyclic collector until the outermost holder leaves (also on an exception); a
    collector the caller had paused stays paused. Usable as a decorator."""
    global _depth, _was_enabled
    with _lock:
        if _depth == 0:
            _was_enabled = gc.isenabled()
            gc.disable()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _was_enabled:
                gc.enable()
