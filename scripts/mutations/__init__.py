"""The mutation check's table (scripts/mutation_check.py runs it): the engine's mutations, then
the Mitsuba side's."""
from .base import Mutation
from .engine import ENGINE
from .mitsuba import MITSUBA

MUTATIONS = ENGINE + MITSUBA

__all__ = ["MUTATIONS", "Mutation"]
