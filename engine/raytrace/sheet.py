"""The mesh's main sheet: its largest edge-connected piece, if it is manifold and consistently wound.

The ray tracer (engine.raytrace.tracer) traces this sheet with Embree's fast, not watertight, test and catches
the rays that slip through its cracks by the side of the face they meet behind it: on one consistently wound
surface that is always its back, where the rock is. A separate piece (a loose block, a second chunk, debris)
breaks that: a ray through a crack in it may meet the front of the wall behind. So only the main sheet is
traced fast, and only when it qualifies.
"""

from __future__ import annotations

import numba
import numpy as np

from engine.raytrace.adjacency import MANY_FACES


def main_sheet(across: np.ndarray, alike: np.ndarray) -> np.ndarray:
    """Mask (F,) of the faces of the largest edge-connected piece, from
    `engine.raytrace.adjacency.edge_neighbours`; all False when that piece has an edge that more than two
    faces share or two faces wound alike."""
    if len(across) == 0:
        return np.zeros(0, dtype=bool)
    label = _pieces(across)
    main = int(np.argmax(np.bincount(label)))
    sheet = label == main
    if alike[sheet].any() or (across[sheet] == MANY_FACES).any():
        return np.zeros(len(across), dtype=bool)
    return sheet


@numba.njit(nogil=True, cache=True)
def _pieces(across: np.ndarray) -> np.ndarray:
    """Each face's piece, labelled by one of its faces (union–find over shared edges)."""
    parent = np.arange(len(across))
    for f in range(len(across)):
        for k in range(3):
            g = across[f, k]
            if g > f:
                a, b = _root(parent, f), _root(parent, g)
                parent[max(a, b)] = min(a, b)
    for f in range(len(across)):
        parent[f] = _root(parent, f)
    return parent


@numba.njit(nogil=True, cache=True)
def _root(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i
