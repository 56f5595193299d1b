"""Skeleton to polylines: split at junctions, remove spurs, keep the wanted feature type, pair branches that
run straight through a junction, simplify (MATHS §4.1–4.2; Kovesi's edgelink, cleanedgelist and lineseg).

The skeleton is read as a pixel graph: 4-neighbours are joined, and diagonal neighbours only where no
4-path joins them, so a staircase is a path and not a chain of triangles. Junction pixels (three or more
neighbours) that touch form one junction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from engine.delineate.params import check
from engine.traces import polyline_length


@dataclass(frozen=True, eq=False)
class Segments:
    """Polylines (N, 2) in pixels (u = column, v = row); `free` (n, 2) is True where an end touches no other
    segment (line growing starts only there); `feature_type` (n,) is each one's feature type in radians
    (length-weighted mean of its branches' medians; 0 where no map was given)."""

    polylines: list[np.ndarray]
    free: np.ndarray
    feature_type: np.ndarray


@dataclass
class _Branch:
    """A run of skeleton pixels between junctions or end points; ends[k] is a junction id or -1."""

    pixels: np.ndarray  # (N, 2) (u, v)
    ends: list[int]
    feature_type: float = 0.0


def find_segments(skeleton: np.ndarray, feature_type: np.ndarray | None = None, *, feature: str = "dark",
                  line_phase: float = 20.0, spur_length: float = 10.0, junction_angle: float = 30.0,
                  direction_length: float = 10.0, simplify: float = 1.0) -> Segments:
    """Polylines from a one-pixel skeleton.

    feature_type : the phase-congruency feature type map; with `feature` "dark" or "bright", branches whose
        median |feature type| is below `line_phase` (degrees) or of the other polarity are dropped
        ("any", or no map, keeps all).
    spur_length : side branches (one free end) shorter than this (px) are removed.
    junction_angle : two branches continue through a junction if their directions deflect less (degrees),
        most collinear pair first; direction_length : length (px) of branch end used for its direction.
    simplify : Douglas–Peucker tolerance, px (0 keeps every pixel).
    """
    for name, value in (("feature", feature), ("line_phase", line_phase), ("spur_length", spur_length),
                        ("junction_angle", junction_angle), ("direction_length", direction_length),
                        ("simplify", simplify)):
        check(name, value)
    skeleton = np.asarray(skeleton, bool)
    branches, centres = _branches(skeleton)
    branches = _remove_spurs(branches, spur_length)
    if feature_type is not None and feature != "any":
        branches = _keep_feature(branches, feature_type, feature, line_phase)
    links = _pair_at_junctions(branches, centres, math.radians(junction_angle), direction_length)
    return _chains(branches, centres, links, simplify)


# -- skeleton graph ----------------------------------------------------------------------------------------

def _pixel_graph(skeleton: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[list[int]]]:
    """Pixel coordinates (n, 2) as (row, col), their degree, and neighbour lists."""
    rows, cols = np.nonzero(skeleton)
    height, width = skeleton.shape
    index = np.full(skeleton.shape, -1, np.int32)
    index[rows, cols] = np.arange(len(rows), dtype=np.int32)
    pairs = []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r, c = rows + dr, cols + dc
        inside = (r < height) & (c >= 0) & (c < width)
        a = np.flatnonzero(inside)
        b = index[r[inside], c[inside]]
        keep = b >= 0
        if dr and dc:  # a diagonal step counts only when no 4-path joins the two pixels
            keep &= ~skeleton[rows[a], cols[a] + dc] & ~skeleton[rows[a] + dr, cols[a]]
        pairs.append(np.column_stack([a[keep], b[keep]]))
    pairs = np.concatenate(pairs)
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    degree = np.bincount(both[:, 0], minlength=len(rows))
    bounds = np.concatenate([[0], np.cumsum(degree)]).tolist()
    targets = both[:, 1].tolist()
    neighbours = [targets[bounds[i]:bounds[i + 1]] for i in range(len(rows))]
    return np.column_stack([rows, cols]), degree, neighbours


def _branches(skeleton: np.ndarray) -> tuple[list[_Branch], np.ndarray]:
    """Branches between junctions/end points, and the (u, v) centre of each junction (pixel cluster)."""
    rc, degree, neighbours = _pixel_graph(skeleton)
    junction = degree >= 3
    cluster_map, n_clusters = ndimage.label(_mask(skeleton.shape, rc[junction]), np.ones((3, 3)))
    cluster = np.where(junction, cluster_map[rc[:, 0], rc[:, 1]] - 1, -1)
    centres = np.zeros((n_clusters, 2))
    if n_clusters:
        counts = np.bincount(cluster[junction], minlength=n_clusters)
        for axis, k in ((0, 1), (1, 0)):  # (u, v) = (col, row)
            centres[:, axis] = np.bincount(cluster[junction], rc[junction, k], n_clusters) / counts
    visited = junction.copy()
    branches = []

    def walk(start: int, before: int) -> _Branch:
        """Follow unvisited pixels from `start` (entered from junction pixel `before`, or -1) to an end."""
        head = int(cluster[before]) if before >= 0 else -1
        path, current = [start], start
        visited[start] = True
        while True:
            ahead = [v for v in neighbours[current] if v != before and (junction[v] or not visited[v])]
            if not ahead or junction[ahead[0]]:
                tail = int(cluster[ahead[0]]) if ahead else -1
                return _Branch(rc[path][:, ::-1].astype(np.float64), [head, tail])
            visited[ahead[0]] = True
            path.append(ahead[0])
            before, current = current, ahead[0]

    for start in np.flatnonzero((degree == 1) & ~junction):  # from free ends
        if not visited[start]:
            branches.append(walk(int(start), -1))
    for j in np.flatnonzero(junction):  # from junctions
        for start in neighbours[j]:
            if not visited[start]:
                branches.append(walk(start, int(j)))
    for start in np.flatnonzero(~visited & (degree == 2)):  # closed loops: no end at all
        if not visited[start]:
            loop = walk(int(start), -1)
            loop.pixels = np.vstack([loop.pixels, loop.pixels[:1]])
            branches.append(loop)
    return branches, centres


def _mask(shape: tuple[int, int], rc: np.ndarray) -> np.ndarray:
    mask = np.zeros(shape, bool)
    mask[rc[:, 0], rc[:, 1]] = True
    return mask


def _points(branch: _Branch, centres: np.ndarray) -> np.ndarray:
    """The branch's pixels with the centre of each junction it touches added at that end."""
    head = centres[[branch.ends[0]]] if branch.ends[0] >= 0 else np.empty((0, 2))
    tail = centres[[branch.ends[1]]] if branch.ends[1] >= 0 else np.empty((0, 2))
    return np.vstack([head, branch.pixels, tail])


def _remove_spurs(branches: list[_Branch], spur_length: float) -> list[_Branch]:
    """Drop short branches with a free end, and short loops from a junction back to itself (cleanedgelist)."""
    def spur(b: _Branch) -> bool:
        attached = [e for e in b.ends if e >= 0]
        short = polyline_length(b.pixels) + len(attached) < spur_length
        return short and (len(attached) == 1 or (len(attached) == 2 and attached[0] == attached[1]))

    return [b for b in branches if not spur(b)]


def _keep_feature(branches: list[_Branch], feature_type: np.ndarray, feature: str,
                  line_phase: float) -> list[_Branch]:
    """Keep branches whose median feature type is a line of the wanted polarity (Kovesi 2003)."""
    limit = math.radians(line_phase)
    kept = []
    for b in branches:
        cols, rows = b.pixels[:, 0].astype(int), b.pixels[:, 1].astype(int)
        b.feature_type = float(np.median(feature_type[rows, cols]))
        if (b.feature_type <= -limit) if feature == "dark" else (b.feature_type >= limit):
            kept.append(b)
    return kept


# -- junctions and chains ----------------------------------------------------------------------------------

def end_direction(points: np.ndarray, at_end: bool, length: float) -> np.ndarray:
    """Unit vector pointing out of the polyline at its last (or first) vertex, over `length` px of it."""
    pts = points[::-1] if at_end else points
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    reach = min(length, s[-1])
    inner = np.array([np.interp(reach, s, pts[:, 0]), np.interp(reach, s, pts[:, 1])])
    d = pts[0] - inner
    norm = np.linalg.norm(d)
    return d / norm if norm > 0 else np.zeros(2)


def _pair_at_junctions(branches: list[_Branch], centres: np.ndarray, max_deflection: float,
                       direction_length: float) -> dict[tuple[int, int], tuple[int, int]]:
    """Links (branch, end) ↔ (branch, end) through junctions, most collinear pair first (MATHS §4.1)."""
    at: dict[int, list[tuple[int, int]]] = {}
    for i, b in enumerate(branches):
        for e in (0, 1):
            if b.ends[e] >= 0:
                at.setdefault(b.ends[e], []).append((i, e))
    links = {}
    for ends in at.values():
        # outward direction of each branch as seen from the junction: into the branch
        into = [-end_direction(_points(branches[i], centres), e == 1, direction_length) for i, e in ends]
        candidates = []
        for a in range(len(ends)):
            for b in range(a + 1, len(ends)):
                if ends[a][0] == ends[b][0]:
                    continue  # a loop's two ends
                deflection = math.pi - math.acos(float(np.clip(into[a] @ into[b], -1, 1)))
                if deflection <= max_deflection:
                    candidates.append((deflection, a, b))
        used = set()
        for _, a, b in sorted(candidates):
            if a not in used and b not in used:
                used.update((a, b))
                links[ends[a]], links[ends[b]] = ends[b], ends[a]
    return links


def _chains(branches: list[_Branch], centres: np.ndarray, links: dict, simplify: float) -> Segments:
    """Join linked branches into polylines; an end is free if no other kept branch meets its junction."""
    meeting = np.bincount([e for b in branches for e in b.ends if e >= 0], minlength=len(centres))

    def free_end(i: int, e: int) -> bool:
        return branches[i].ends[e] < 0 or meeting[branches[i].ends[e]] == 1

    polylines, free, feature = [], [], []
    done = np.zeros(len(branches), bool)
    starts = [(i, e) for i in range(len(branches)) for e in (0, 1) if (i, e) not in links]
    starts += [(i, 0) for i in range(len(branches))]  # what is left are closed chains
    for first, first_end in starts:
        if done[first]:
            continue
        parts, kinds, i, e = [], [], first, first_end  # walk into branch i through its end e
        while True:
            done[i] = True
            pts = _points(branches[i], centres)
            parts.append(pts if e == 0 else pts[::-1])
            kinds.append((branches[i].feature_type, len(pts)))
            following = links.get((i, 1 - e))
            if following is None or done[following[0]]:
                break
            i, e = following
        points = _dedupe(np.vstack(parts))
        if len(points) < 2:
            continue
        polylines.append(_simplify(points, simplify))
        free.append((free_end(first, first_end), free_end(i, 1 - e)))
        feature.append(float(np.average([k for k, _ in kinds], weights=[n for _, n in kinds])))
    return Segments(polylines, np.array(free, bool).reshape(-1, 2), np.array(feature))


def _dedupe(points: np.ndarray) -> np.ndarray:
    """Drop consecutive repeats (where a branch and the junction centre it ends on coincide)."""
    keep = np.concatenate([[True], np.any(np.diff(points, axis=0) != 0, axis=1)])
    return points[keep]


def _simplify(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Douglas–Peucker simplification keeping both ends (Kovesi's lineseg, MATHS §4.2)."""
    if tolerance <= 0 or len(points) < 3:
        return points
    out = cv2.approxPolyDP(points.astype(np.float32).reshape(-1, 1, 2), float(tolerance), False)
    return out.reshape(-1, 2).astype(np.float64)
