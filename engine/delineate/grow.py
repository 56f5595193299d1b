"""Line growing: link segment ends across gaps, iterate, drop short traces (MATHS §4.3).

From each free end a search path runs along the end's direction: a strip `link_buffer` px either side of
the ray, `link_distance` px long. Another trace's free end inside it, pointing back within `link_angle`, is
a match (so a short fragment whose own direction is poor can still be reached from a longer trace);
matches are taken best first by a score weighing angular deviation against distance, each end at most once
and never closing a trace on itself. Linked traces have new ends, so the search repeats until nothing
links. Linking defaults are PCI Geomatica LINE's (ATHR 30°, DTHR 20 px). Its LTHR of 30 px becomes
10 px here: the segments have already passed the brightness-profile test, and a faint trace often survives only
as 10–30 px pieces.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from engine.delineate.params import check
from engine.delineate.segments import Segments, end_direction
from engine.traces import polyline_length

MAX_ROUNDS = 50  # each round links at least one pair, so this only guards against a bug looping forever


def grow_traces(segments: Segments, *, link_distance: float = 20.0, link_angle: float = 30.0,
                link_buffer: float = 4.0, link_weight: float = 0.5, direction_length: float = 10.0,
                min_length: float = 10.0) -> list[np.ndarray]:
    """Traces (polylines (N, 2), px) grown from segments by linking free ends; those < min_length px dropped.

    link_distance : longest gap bridged (px); link_buffer : half-width of the search path (px);
    link_angle : largest angle between an end's direction and the reversed direction of the end it links
    to (degrees); link_weight : score = w·angle/link_angle + (1 − w)·gap/link_distance;
    direction_length : length of trace end used for its direction (px).
    """
    for name, value in (("link_distance", link_distance), ("link_angle", link_angle),
                        ("link_buffer", link_buffer), ("link_weight", link_weight),
                        ("direction_length", direction_length), ("min_length", min_length)):
        check(name, value)
    polylines, free = list(segments.polylines), segments.free.copy()
    for _ in range(MAX_ROUNDS):
        links = _links(polylines, free, link_distance, math.radians(link_angle), link_buffer, link_weight,
                       direction_length)
        if not links:
            break
        polylines, free = _join(polylines, free, links)
    return [p for p in polylines if polyline_length(p) >= min_length]


def _links(polylines: list[np.ndarray], free: np.ndarray, distance: float, angle: float, buffer: float,
           weight: float, direction_length: float) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Accepted links (trace, end) ↔ (trace, end) of one round, best score first."""
    ends = [(i, e) for i in range(len(polylines)) for e in (0, 1) if free[i, e]]
    if len(ends) < 2 or distance == 0:
        return []
    points = np.array([polylines[i][-1 if e else 0] for i, e in ends])
    outward = np.array([end_direction(polylines[i], e == 1, direction_length) for i, e in ends])
    pairs = cKDTree(points).query_pairs(distance, output_type="ndarray")
    if len(pairs) == 0:
        return []
    a, b = pairs[:, 0], pairs[:, 1]
    owner = np.array([i for i, _ in ends])
    gap = points[b] - points[a]
    length = np.linalg.norm(gap, axis=1)
    turn = np.arccos(np.clip(-np.einsum("ij,ij->i", outward[a], outward[b]), -1, 1))
    ok = (owner[a] != owner[b]) & (turn <= angle) \
        & (_in_path(outward[a], gap, buffer) | _in_path(outward[b], -gap, buffer))
    score = weight * turn / max(angle, 1e-12) + (1 - weight) * length / distance
    accepted, used = [], set()
    group = list(range(len(polylines)))  # union-find over traces, so no link closes a trace on itself

    def root(k: int) -> int:
        while group[k] != k:
            group[k] = group[group[k]]
            k = group[k]
        return k

    for k in np.flatnonzero(ok)[np.argsort(score[ok], kind="stable")]:
        p, q = ends[a[k]], ends[b[k]]
        if p in used or q in used or root(p[0]) == root(q[0]):
            continue
        used.update((p, q))
        group[root(p[0])] = root(q[0])
        accepted.append((p, q))
    return accepted


def _in_path(direction: np.ndarray, gap: np.ndarray, buffer: float) -> np.ndarray:
    """Whether each gap vector lies ahead of its end and within `buffer` px of the end's ray."""
    along = np.einsum("ij,ij->i", direction, gap)
    across = np.abs(direction[:, 0] * gap[:, 1] - direction[:, 1] * gap[:, 0])
    touching = np.linalg.norm(gap, axis=1) == 0
    return touching | ((along > 0) & (across <= buffer))


def _join(polylines: list[np.ndarray], free: np.ndarray,
          links: list[tuple[tuple[int, int], tuple[int, int]]]) -> tuple[list[np.ndarray], np.ndarray]:
    """Concatenate linked traces (the gap is bridged by a straight segment); linked ends are no longer free."""
    partner = {}
    for p, q in links:
        partner[p], partner[q] = q, p
    done = np.zeros(len(polylines), bool)
    out, out_free = [], []
    starts = [(i, e) for i in range(len(polylines)) for e in (0, 1) if (i, e) not in partner]
    for first, first_end in starts:
        if done[first]:
            continue
        parts, i, e = [], first, first_end
        while True:
            done[i] = True
            part = polylines[i] if e == 0 else polylines[i][::-1]
            touching = parts and np.array_equal(parts[-1][-1], part[0])  # a gap of zero: one shared vertex
            parts.append(part[1:] if touching else part)
            following = partner.get((i, 1 - e))
            if following is None:
                break
            i, e = following
        out.append(np.vstack(parts))
        out_free.append((free[first, first_end], free[i, 1 - e]))
    return out, np.array(out_free, bool).reshape(-1, 2)
