"""The integrator's settings, parsed once where they come in (an XML scene's properties, the command line): the
traversal choice and the rules for every property."""
from __future__ import annotations

from dataclasses import dataclass

import layerbvh

EMBREE = "embree"  # the control: our loop, Mitsuba's (Embree's) queries
CHOICES = layerbvh.TRACE_MODES + (EMBREE,)


@dataclass(frozen=True)
class Traversal:
    """What answers the bounce loop's ray queries: one of layerbvh's trace modes (`mode`:
    per_ray, layer_sorted, layer_unsorted or auto), or the control, Mitsuba's own Embree queries
    (`mode` None). The control is the same loop with another traversal, which isolates the
    traversal's cost; it is not an engine mode and never reaches the engine."""

    mode: str | None

    @classmethod
    def parse(cls, text: str) -> "Traversal":
        """The choice named `text`; a ValueError naming the choices otherwise."""
        if text == EMBREE:
            return cls(None)
        if text not in layerbvh.TRACE_MODES:
            raise ValueError(f"traversal must be one of {', '.join(CHOICES)}; got {text!r}")
        return cls(text)

    @property
    def control(self) -> bool:
        return self.mode is None

    @property
    def auto(self) -> bool:
        return self.mode == layerbvh.AUTO

    @property
    def name(self) -> str:
        return EMBREE if self.mode is None else self.mode

    def __str__(self) -> str:
        return self.name


def check_depths(max_depth: int, rr_depth: int) -> None:
    """The path estimators' rules for their depths (stock's): a ValueError naming the property."""
    if max_depth < -1:
        raise ValueError(f"max_depth must be -1 (infinite) or >= 0, got {max_depth}")
    if rr_depth <= 0:
        raise ValueError(f"rr_depth must be > 0, got {rr_depth}")


def check_traversal_settings(treelet_height: int, leaf_size: int | None, batch_rays: int,
                             branching: int = layerbvh.DEFAULT_BRANCHING,
                             tail_steps: int = layerbvh.TAIL_STEPS) -> None:
    """The render driver's rules for the traversal's properties: a ValueError naming the property
    and what it must be."""
    layerbvh.check_param("treelet_height", treelet_height)
    if leaf_size is not None:  # None: the branching's default (layerbvh.default_leaf_size)
        layerbvh.check_param("leaf_size", leaf_size)
    layerbvh.check_param("batch_rays", batch_rays)
    layerbvh.check_param("branching", branching)
    layerbvh.check_param("tail_steps", tail_steps)

