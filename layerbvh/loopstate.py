"""What a Dr.Jit loop reads but never changes, held out of the loop's state so that its body is traced once."""
from __future__ import annotations

import drjit as dr

# Why (PERFORMANCE.md entry 58): @dr.syntax makes every name a loop body reads or writes a loop
# state variable, and drjit 1.5.0, finding one that the body left unchanged (by index), drops it
# and traces the whole body again ("re-recording loop ... to eliminate redundant loop state
# variables", with JitFlag.OptimizeLoops on or off). Held values are no state variables: Dr.Jit
# compares a non-array state variable with itself after the body and traces it once.


class Held:
    """A value a loop reads but does not change, held where Dr.Jit's loop state does not look
    (it traverses arrays, tuples, lists, dicts and dataclasses, not this): attribute reads,
    indexing and iteration go to the value."""

    __slots__ = ("_value",)

    def __init__(self, value):
        object.__setattr__(self, "_value", value)

    @staticmethod
    def of(value):
        """`value` held (None stays None: the loop tests `is not None`)."""
        return None if value is None else Held(value)

    @staticmethod
    def unless(changes: bool, value):
        """`value` as it is where the loop changes it, else held."""
        return value if changes else Held(value)

    @staticmethod
    def value(x):
        """The held value (or `x`, not held)."""
        return object.__getattribute__(x, "_value") if isinstance(x, Held) else x

    def __getattr__(self, name):
        return getattr(object.__getattribute__(self, "_value"), name)

    def __getitem__(self, i):
        return object.__getattribute__(self, "_value")[i]

    def __iter__(self):
        return iter(object.__getattribute__(self, "_value"))

    def __len__(self):
        return len(object.__getattribute__(self, "_value"))


def body_traces(fn) -> list[int]:
    """Run `fn` and return, for each Dr.Jit loop it ran, how many times the loop traced its body
    (1 when its state holds only what the body changes)."""
    counts, original = [], dr.while_loop

    def counting(state, cond, body, *args, **kwargs):
        n = [0]

        def traced(*s):
            n[0] += 1
            return body(*s)
        out = original(state, cond, traced, *args, **kwargs)
        counts.append(n[0])
        return out
    dr.while_loop = counting
    try:
        fn()
    finally:
        dr.while_loop = original
    return counts
