"""Triangles paired into quads across shared edges, for the ray tracer.

Embree traces a scene of quads (triangle pairs) faster than one of their triangles: half the primitives
make a shallower tree (tests/benchmarks/bench_raytrace.py). A pair is chosen for the smallest box around its
four vertices, so the tree's leaves stay tight, and faces that are each other's best choice pair first, so
one early choice does not push every later face off its natural partner (a grid's cells pair whole).
A hit on a quad is turned back into the mesh's face and its barycentric coordinates by `to_faces`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

NONE = 0xFFFFFFFF
"""A quad's second triangle when it has none (a face that found no partner)."""


def pair_triangles(faces: np.ndarray, vertices: np.ndarray, across: np.ndarray, *,
                   pool: ThreadPoolExecutor | None = None, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Embree quads (Q, 4) uint32 over `faces` (F, 3) int64, and their lookup (Q, 2) int64.

    `across` is `engine.raytrace.adjacency.edge_neighbours` of `faces`. Embree splits quad (v0, v1, v2, v3)
    into the triangles (v0, v1, v3) and (v2, v3, v1). A face without a partner becomes (a, b, c, c). `lookup[q, j]`
    holds the face of triangle j in its low 32 bits (NONE for none) and, 2 bits each from bit 32, the quad
    slot of each of the face's own three vertices. `rounds` of mutual best choices come before a last round
    where every free face takes its best free neighbour; the choices of a round are computed on `pool`'s
    threads.
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    partner = np.full(len(faces), -1, np.int64)
    shared = np.full(len(faces), -1, np.int8)  # k where the pair's edge is (f_k, f_k+1), on one face of each pair
    best = np.full(len(faces), -1, np.int64)
    best_edge = np.zeros(len(faces), np.int8)
    parts = 1 if pool is None else 8
    bounds = np.linspace(0, len(faces), parts + 1).astype(np.int64)
    for rounds_left in range(rounds, -1, -1):
        def choose(part: int) -> None:
            _best_partners(faces, vertices, across, partner, best, best_edge, bounds[part], bounds[part + 1])

        list(map(choose, range(parts)) if pool is None else pool.map(choose, range(parts)))
        _pair(partner, shared, best, best_edge, rounds_left == 0)
    return _quads(faces, partner, shared)


@numba.njit(nogil=True, cache=True)
def _box_area(vertices: np.ndarray, a: int, b: int, c: int, d: int) -> float:
    """Half the surface area of the box around four vertices (what a leaf costs a ray-tracing tree)."""
    x = _span(vertices, 0, a, b, c, d)
    y = _span(vertices, 1, a, b, c, d)
    z = _span(vertices, 2, a, b, c, d)
    return x * y + y * z + z * x


@numba.njit(nogil=True, cache=True)
def _span(vertices: np.ndarray, axis: int, a: int, b: int, c: int, d: int) -> float:
    return max(vertices[a, axis], vertices[b, axis], vertices[c, axis], vertices[d, axis]) - min(
        vertices[a, axis], vertices[b, axis], vertices[c, axis], vertices[d, axis])


@numba.njit(nogil=True, cache=True)
def _best_partners(faces: np.ndarray, vertices: np.ndarray, across: np.ndarray, partner: np.ndarray,
                   best: np.ndarray, best_edge: np.ndarray, lo: int, hi: int) -> None:
    """For each free face f in lo..hi, the free neighbour whose quad with f has the smallest box (best[f],
    -1 for none) and the edge k, (f_k, f_k+1), they share (best_edge[f])."""
    for f in range(lo, hi):
        best[f] = -1
        if partner[f] >= 0:
            continue
        best_area = np.inf
        for k in range(3):
            g = across[f, k]
            if g < 0 or partner[g] >= 0:
                continue
            a, b = faces[f, k], faces[f, (k + 1) % 3]
            s = faces[g, 0] + faces[g, 1] + faces[g, 2] - a - b
            if s == faces[f, (k + 2) % 3]:  # the same triangle twice
                continue
            area = _box_area(vertices, faces[f, 0], faces[f, 1], faces[f, 2], s)
            if area < best_area:
                best[f], best_edge[f], best_area = g, k, area


@numba.njit(nogil=True, cache=True)
def _pair(partner: np.ndarray, shared: np.ndarray, best: np.ndarray, best_edge: np.ndarray, greedy: bool) -> None:
    """Pair the faces that are each other's best choice (every free face with its choice, if still free,
    when `greedy`)."""
    for f in range(len(partner)):
        g = best[f]
        if partner[f] < 0 and g >= 0 and partner[g] < 0 and (greedy or best[g] == f):
            partner[f], partner[g], shared[f] = g, f, best_edge[f]


@numba.njit(nogil=True, cache=True)
def _quads(faces: np.ndarray, partner: np.ndarray, shared: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The quads of the pairs, in the order of their first face, and their lookup (see pair_triangles)."""
    n_quads = len(faces) - np.count_nonzero(shared >= 0)
    quads = np.empty((n_quads, 4), np.uint32)
    lookup = np.full((n_quads, 2), NONE, np.int64)
    q = 0
    for f in range(len(faces)):
        if partner[f] < 0:
            quads[q] = faces[f, 0], faces[f, 1], faces[f, 2], faces[f, 2]
            lookup[q, 0] = f | (_code(0, 1, 3) << 32)
        elif shared[f] >= 0:
            g, k = partner[f], shared[f]
            a, b, p = faces[f, k], faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]
            s = faces[g, 0] + faces[g, 1] + faces[g, 2] - a - b
            quads[q] = p, a, s, b  # triangle (p, a, b) is f, (s, b, a) is g
            slot = (1, 3, 0)  # of a, b and p
            lookup[q, 0] = f | (_code(slot[(0 - k) % 3], slot[(1 - k) % 3], slot[(2 - k) % 3]) << 32)
            lookup[q, 1] = g | (_code(_slot_in_g(faces[g, 0], a, b), _slot_in_g(faces[g, 1], a, b),
                                      _slot_in_g(faces[g, 2], a, b)) << 32)
        else:
            continue
        q += 1
    return quads, lookup


@numba.njit(nogil=True, cache=True)
def _slot_in_g(vertex: int, a: int, b: int) -> int:
    """The slot of a vertex of the second triangle in the quad (p, a, s, b)."""
    return 1 if vertex == a else (3 if vertex == b else 2)


@numba.njit(nogil=True, cache=True)
def _code(first: int, second: int, third: int) -> int:
    return first | (second << 2) | (third << 4)


@numba.njit(nogil=True, cache=True)
def to_faces(lookup: np.ndarray, face: np.ndarray, bary: np.ndarray, lo: int, hi: int) -> None:
    """Turn hits lo..hi on quads (quad index in `face`, Embree's u, v in `bary`) into hits on the mesh's
    faces and their barycentric coordinates, in place; misses (face < 0) stay.

    Embree reports a hit on a quad's second triangle (v2, v3, v1) as u → 1 - u, v → 1 - v, so u + v > 1
    there. A pass of its own after the tracing: its reads of `lookup` are independent and overlap, where
    interleaved with Embree's they each waited for memory (a fifth of a photo's time)."""
    for i in range(lo, hi):
        q = face[i]
        if q < 0:
            continue
        u, v = bary[i, 0], bary[i, 1]  # the weights of slots 1 and 3; slot 0 or 2 has the rest
        entry = lookup[q, 0]
        if u + v > 1.0 and lookup[q, 1] != NONE:
            entry = lookup[q, 1]
            u, v = 1.0 - v, 1.0 - u
        face[i] = entry & 0xFFFFFFFF
        for k in range(2):
            slot = (entry >> (34 + 2 * k)) & 3
            bary[i, k] = u if slot == 1 else (v if slot == 3 else 1.0 - u - v)
