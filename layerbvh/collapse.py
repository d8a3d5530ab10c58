"""SAH-guided collapse of the binary BVH into a 4- or 8-wide tree (the wide Layer BVH is cut from it)."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .sah import BinaryBVH


@dataclass
class WideTree:
    """A K-wide tree over the nodes of a BinaryBVH, indexed by binary node id.

    kids     int64 (M, K)  for each binary node that is a wide inner node: the binary ids of its
                           children (inner nodes or leaves), -1 for an empty slot; -1 rows else
    is_node  bool  (M,)    whether the binary node is a wide inner node (the root always is)

    Every binary leaf is a child of exactly one wide node; binary inner nodes absorbed by a
    collapse are in neither role. With K = 2 it is the binary tree itself."""

    kids: np.ndarray
    is_node: np.ndarray

    @property
    def branching(self) -> int:
        return self.kids.shape[1]


def surface_areas(b: BinaryBVH) -> np.ndarray:
    e = np.maximum(b.hi.astype(np.float64) - b.lo.astype(np.float64), 0.0)
    return e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]


def collapse(b: BinaryBVH, branching: int) -> WideTree:
    """The K-wide tree of `b`: from the root down, each wide node starts with its binary node's
    two children and pulls up the inner child of largest surface area (replacing it by its two
    children) until it has K children or only leaves (Wald, Benthin, Boulos 2008; Embree's
    BVH4/8 builders do the same). The child of largest area is the one a random ray is most
    likely to enter, so opening it saves the most dependent node loads per ray."""
    if branching == 2:
        inner = b.left >= 0
        kids = np.full((len(b.left), 2), -1, np.int64)
        kids[inner, 0], kids[inner, 1] = b.left[inner], b.left[inner] + 1
        return WideTree(kids=kids, is_node=inner.copy())
    kids, is_node = _collapse(b.left, surface_areas(b), branching)
    return WideTree(kids=kids, is_node=is_node)


@numba.njit(cache=True)
def _collapse(left, area, k):
    m = len(left)
    kids = np.full((m, k), -1, np.int64)
    is_node = np.zeros(m, np.bool_)
    todo = np.empty(m, np.int64)  # wide nodes still to fill (a stack; order does not matter here)
    todo[0], n_todo = 0, 1
    while n_todo > 0:
        n_todo -= 1
        n = todo[n_todo]
        is_node[n] = True
        kids[n, 0], kids[n, 1], count = left[n], left[n] + 1, 2
        while count < k:
            best, best_area = -1, -1.0
            for j in range(count):
                c = kids[n, j]
                if left[c] >= 0 and area[c] > best_area:
                    best, best_area = j, area[c]
            if best < 0:
                break
            c = kids[n, best]
            # The opened child's two children take its slot and the next free one.
            kids[n, best], kids[n, count] = left[c], left[c] + 1
            count += 1
        for j in range(count):
            c = kids[n, j]
            if left[c] >= 0:
                todo[n_todo] = c
                n_todo += 1
    return kids, is_node
