"""Geometry of editing polylines by hand: picking, splitting, joining, vertex changes (arrays in, arrays out).

Polylines are (N, 2) float64 pixel coordinates, N ≥ 2. Nothing here knows Qt or the project.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.errors import InputError

END_TOLERANCE = 1e-6  # a split this close to an end vertex is at that vertex


@dataclass(frozen=True)
class Hit:
    """The point of polyline `index` nearest to a query: on segment `segment`, fraction `t` along it."""

    index: int
    distance: float
    segment: int
    t: float


def closest_point(polyline: np.ndarray, p: Sequence[float]) -> Hit:
    """Nearest point of one polyline to p (index 0)."""
    a, b = polyline[:-1], polyline[1:]
    d = b - a
    length2 = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", np.asarray(p) - a, d) / np.where(length2 > 0, length2, 1), 0, 1)
    distance = np.hypot(*(a + t[:, None] * d - p).T)
    k = int(np.argmin(distance))
    return Hit(0, float(distance[k]), k, float(t[k]))


def nearest(polylines: Sequence[np.ndarray], p: Sequence[float], radius: float) -> Hit | None:
    """The polyline passing nearest to p within `radius`, or None."""
    best: Hit | None = None
    for index, polyline in enumerate(polylines):
        lo, hi = polyline.min(axis=0) - radius, polyline.max(axis=0) + radius
        if not (lo[0] <= p[0] <= hi[0] and lo[1] <= p[1] <= hi[1]):
            continue
        hit = closest_point(polyline, p)
        if hit.distance <= radius and (best is None or hit.distance < best.distance):
            best = Hit(index, hit.distance, hit.segment, hit.t)
    return best


def nearest_vertex(polyline: np.ndarray, p: Sequence[float]) -> tuple[int, float]:
    """Index of the vertex nearest to p, and its distance."""
    distance = np.hypot(*(polyline - p).T)
    k = int(np.argmin(distance))
    return k, float(distance[k])


def point_on(polyline: np.ndarray, segment: int, t: float) -> np.ndarray:
    return polyline[segment] + t * (polyline[segment + 1] - polyline[segment])


def split(polyline: np.ndarray, segment: int, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Two polylines sharing the split point; at a vertex if t is 0 or 1 (within END_TOLERANCE)."""
    if t <= END_TOLERANCE:
        vertex = segment
    elif t >= 1 - END_TOLERANCE:
        vertex = segment + 1
    else:
        q = point_on(polyline, segment, t)
        return np.vstack([polyline[:segment + 1], q]), np.vstack([q, polyline[segment + 1:]])
    if vertex in (0, len(polyline) - 1):
        raise InputError(None, "cannot split a trace at its end; click further along it")
    return polyline[:vertex + 1].copy(), polyline[vertex:].copy()


def insert_vertex(polyline: np.ndarray, segment: int, t: float) -> np.ndarray:
    """A new vertex on segment `segment` at fraction t."""
    return np.insert(polyline, segment + 1, point_on(polyline, segment, t), axis=0)


def move_vertex(polyline: np.ndarray, index: int, p: Sequence[float]) -> np.ndarray:
    moved = polyline.copy()
    moved[index] = p
    return moved


def delete_vertex(polyline: np.ndarray, index: int) -> np.ndarray:
    if len(polyline) <= 2:
        raise InputError(None, "a trace needs two vertices; erase the trace instead")
    return np.delete(polyline, index, axis=0)


def join_nearest_ends(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One polyline: a, then b, joined across the closest pair of their end vertices."""
    ends = [(np.hypot(*(a[i] - b[j])), i, j) for i in (0, -1) for j in (0, -1)]
    _, i, j = min(ends)
    first = a if i == -1 else a[::-1]
    second = b if j == 0 else b[::-1]
    if np.array_equal(first[-1], second[0]):  # touching ends: keep one vertex
        second = second[1:]
    return np.vstack([first, second])


def crosses_rect(polyline: np.ndarray, lo: Sequence[float], hi: Sequence[float]) -> bool:
    """Whether any part of the polyline lies in the axis-aligned rectangle [lo, hi] (Liang–Barsky clipping)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if np.all((polyline >= lo) & (polyline <= hi), axis=1).any():
        return True
    a, d = polyline[:-1], np.diff(polyline, axis=0)
    t0, t1 = np.zeros(len(a)), np.ones(len(a))
    for axis in (0, 1):
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo[axis] - a[:, axis]) / d[:, axis], (hi[axis] - a[:, axis]) / d[:, axis]
        parallel = d[:, axis] == 0
        outside = parallel & ((a[:, axis] < lo[axis]) | (a[:, axis] > hi[axis]))
        t0 = np.where(parallel, t0, np.maximum(t0, np.minimum(ta, tb)))
        t1 = np.where(parallel, t1, np.minimum(t1, np.maximum(ta, tb)))
        t1 = np.where(outside, -1.0, t1)
    return bool(np.any(t0 <= t1))
