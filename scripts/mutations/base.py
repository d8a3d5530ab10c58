"""What one mutation is: a realistic bug, the text it changes and the tests that must catch it."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Mutation:
    name: str
    what: str         # the bug, in words
    path: str         # the file it is made in, relative to the repository root
    old: str          # text that occurs exactly once in that file ...
    new: str          # ... and what replaces it
    tests: tuple      # pytest node ids that should catch it (run with -x, in this order)
    cpu_flag: str = ""  # a /proc/cpuinfo flag the bug needs to show (else skipped on this CPU, not missed)


MB = "tests/runtime/test_mitsuba_backend.py::"
SAME_SEED_LAYER = (MB + "test_same_seed_matches_stock[cbox-layer_sorted]",
                   MB + "test_same_seed_matches_stock[empty_box-layer_unsorted]")
