"""The mesh's main sheet: its largest piece of faces joined by edges that two faces share, wound oppositely.

The ray tracer (engine.raytrace.tracer) traces this sheet with Embree's fast, not watertight, test and catches
the rays that slip through its cracks by the side of the face they meet behind it: on one consistently wound
sheet that is always its back, where the rock is. A separate piece (a loose block, a second chunk, debris)
breaks that: a ray through a crack in it may meet the front of the wall behind. So only the main sheet is
traced fast. A face wound against its neighbours, or on an edge of three faces, is left out of it (a hole in
the sheet, which a ray passes through to its back or to nothing, as through a crack).
"""

from __future__ import annotations

import numba
import numpy as np

from engine.raytrace.adjacency import MANY_FACES


def main_sheet(across: np.ndarray, alike: np.ndarray) -> np.ndarray:
    """Mask (F,) of the faces of the main sheet, from `engine.raytrace.adjacency.edge_neighbours`: the
    largest piece joined across edges wound oppositely by their two faces, of faces on no edge of three."""
    if len(across) == 0:
        return np.zeros(0, dtype=bool)
    fin = (across == MANY_FACES).any(axis=1)
    label = _pieces(across, alike, fin)
    sizes = np.bincount(label[~fin], minlength=len(across))
    return (label == int(np.argmax(sizes))) & ~fin


@numba.njit(nogil=True, cache=True)
def _pieces(across: np.ndarray, alike: np.ndarray, fin: np.ndarray) -> np.ndarray:
    """Each face's piece, labelled by one of its faces (union–find over the edges that join; faces on an
    edge of three join nothing)."""
    parent = np.arange(len(across))
    for f in range(len(across)):
        for k in range(3):
            g = across[f, k]
            if g > f and not alike[f, k] and not fin[f] and not fin[g]:
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
