"""Which face lies across each edge of a triangle mesh, for the ray tracer's quads and main sheet."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

NO_FACE, MANY_FACES = -1, -2
"""`across` for a border edge (or any edge of a face with a repeated vertex), and for an edge that more than
two faces share."""


def edge_neighbours(faces: np.ndarray, n_vertices: int, *,
                    pool: ThreadPoolExecutor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`across` (F, 3): the face across edge k, (f_k, f_k+1), of each face, or NO_FACE or MANY_FACES; and
    `alike` (F, 3): whether that face is wound the same way along the edge (the two disagree on which side
    is out). Computed in parts on `pool`'s threads."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    start, around = _faces_around_vertices(faces, n_vertices)
    across = np.empty((len(faces), 3), dtype=np.int64)
    alike = np.empty((len(faces), 3), dtype=np.bool_)
    bounds = np.linspace(0, len(faces), (1 if pool is None else 8) + 1).astype(np.int64)

    def part(k: int) -> None:
        _across(faces, start, around, bounds[k], bounds[k + 1], across, alike)

    list(map(part, range(len(bounds) - 1)) if pool is None else pool.map(part, range(len(bounds) - 1)))
    return across, alike


@numba.njit(nogil=True, cache=True)
def _faces_around_vertices(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The faces around each vertex as compressed rows: those of vertex i are around[start[i]:start[i + 1]]."""
    start = np.zeros(n_vertices + 1, np.int64)
    for f in range(len(faces)):
        for k in range(3):
            start[faces[f, k] + 1] += 1
    for i in range(n_vertices):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    around = np.empty(3 * len(faces), np.int64)
    for f in range(len(faces)):
        for k in range(3):
            around[fill[faces[f, k]]] = f
            fill[faces[f, k]] += 1
    return start, around


@numba.njit(nogil=True, cache=True)
def _degenerate(faces: np.ndarray, f: int) -> bool:
    return faces[f, 0] == faces[f, 1] or faces[f, 1] == faces[f, 2] or faces[f, 0] == faces[f, 2]


@numba.njit(nogil=True, cache=True)
def _across(faces: np.ndarray, start: np.ndarray, around: np.ndarray, lo: int, hi: int, across: np.ndarray,
            alike: np.ndarray) -> None:
    for f in range(lo, hi):
        for k in range(3):
            across[f, k] = NO_FACE
            alike[f, k] = False
            if _degenerate(faces, f):
                continue
            a, b = faces[f, k], faces[f, (k + 1) % 3]
            for i in range(start[a], start[a + 1]):
                g = around[i]  # has a; shares the edge if it has b too
                if g == f or _degenerate(faces, g) or not (
                        faces[g, 0] == b or faces[g, 1] == b or faces[g, 2] == b):
                    continue
                across[f, k] = g if across[f, k] == NO_FACE else MANY_FACES
                for m in range(3):
                    if faces[g, m] == a and faces[g, (m + 1) % 3] == b:
                        alike[f, k] = True
