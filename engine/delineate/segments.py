"""Skeleton to polylines: split at junctions, remove spurs, pair branches that run straight through a junction,
keep the chains that are lines of the wanted kind, simplify (MATHS §4.1–4.2; Kovesi's edgelink, cleanedgelist
and lineseg).

The skeleton is read as a pixel graph: 4-neighbours are joined, and diagonal neighbours only where no
4-path joins them, so a staircase is a path and not a chain of triangles. Junction pixels (three or more
neighbours) that touch form one junction.

Chains are judged whole, after pairing, not branch by branch: texture edges that touch a faint trace cut it
into branches of a few pixels, too short for a steady median of feature type or brightness profile. A chain
that fails is judged again branch by branch, because pairing can join a trace to a crease it meets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from engine.delineate.line_profile import are_lines, log_brightness
from engine.delineate.params import check
from engine.errors import InputError
from engine.traces import polyline_length


@dataclass(frozen=True, eq=False)
class Segments:
    """Polylines (N, 2) in pixels (u = column, v = row); `free` (n, 2) is True where an end touches no other
    segment (line growing starts only there); `feature_type` (n,) is each one's median feature type in
    radians (0 where no map was given). `rejected` are the skeleton's chains of the wanted polarity that the
    brightness profile turned down (none without a feature-type map), unsimplified (1 px steps): another photo of the same rock may show them
    (`engine.delineate.support`)."""

    polylines: list[np.ndarray]
    free: np.ndarray
    feature_type: np.ndarray
    rejected: list[np.ndarray] = field(default_factory=list)


@dataclass
class _Branch:
    """A run of skeleton pixels between junctions or end points; ends[k] is a junction id or -1."""

    pixels: np.ndarray  # (N, 2) (u, v)
    ends: list[int]


@dataclass(eq=False)
class _Chain:
    """Branches joined through junctions: its pixel path, the junction at each end (or -1) and every
    junction it meets."""

    points: np.ndarray  # (N, 2) (u, v), junction centres included
    ends: tuple[int, int]
    junctions: set[int]
    branches: list[int]


def find_segments(skeleton: np.ndarray, feature_type: np.ndarray | None = None, *, image: np.ndarray | None = None,
                  feature: str = "dark", line_phase: float = 20.0, line_contrast: float = 0.07,
                  line_asymmetry: float = 0.15, faint_asymmetry: float = 0.25, faint_contrast: float = 0.3,
                  photo: np.ndarray | None = None, raw_contrast: float = 0.12,
                  trace_width: float = 3.0, spur_length: float = 10.0,
                  junction_angle: float = 30.0, direction_length: float = 10.0, simplify: float = 1.0) -> Segments:
    """Polylines from a one-pixel skeleton.

    feature_type : the phase-congruency feature type map; with `feature` "dark" or "bright", chains whose
        median |feature type| is below `line_phase` (degrees) or of the other polarity are dropped.
    image : the 8-bit grey photo the skeleton came from; with `feature` "dark" ("bright"), chains are kept only
        if they are at least `line_contrast` (ln brightness) darker (brighter) than both sides with a dip no
        more asymmetric than `line_asymmetry` (`faint_asymmetry` if less than `faint_contrast` darker), in
        profiles sized for traces up to `trace_width` px wide
        (`line_profile`). "any", or no map or image, keeps all.
    photo : the 8-bit grey photo before denoising, if `image` is denoised: a chain `image` rejects is kept if
        it is at least `raw_contrast` darker (brighter) on it, measured where `image` has its dip.
    spur_length : side branches (one free end) shorter than this (px) are removed.
    junction_angle : two branches continue through a junction if their directions deflect less (degrees),
        most collinear pair first; direction_length : length (px) of branch end used for its direction.
    simplify : Douglas–Peucker tolerance, px (0 keeps every pixel).
    """
    for name, value in (("feature", feature), ("line_phase", line_phase), ("line_contrast", line_contrast),
                        ("line_asymmetry", line_asymmetry), ("faint_asymmetry", faint_asymmetry),
                        ("faint_contrast", faint_contrast), ("raw_contrast", raw_contrast),
                        ("trace_width", trace_width),
                        ("spur_length", spur_length), ("junction_angle", junction_angle),
                        ("direction_length", direction_length), ("simplify", simplify)):
        check(name, value)
    skeleton = np.asarray(skeleton, bool)
    for name, given in (("image", image), ("photo", photo)):
        if given is not None and (np.asarray(given).dtype != np.uint8 or np.shape(given) != skeleton.shape):
            raise InputError(None, f"find_segments: {name} must be the 8-bit grey photo of the skeleton's shape "
                                   f"{skeleton.shape}; got {np.asarray(given).dtype} {np.shape(given)}")
    branches, centres = _branches(skeleton)
    branches = _remove_spurs(branches, spur_length)
    links = _pair_at_junctions(branches, centres, math.radians(junction_angle), direction_length)
    chains = _chains(branches, centres, links)
    if feature != "any":
        sign = 1 if feature == "dark" else -1
        log_image = None if image is None else log_brightness(image) * sign
        raw = None if photo is None or image is None else (log_brightness(photo) * sign, raw_contrast)

        def wanted(candidates: list[_Chain]) -> list[_Chain]:
            keep = _lines_of_kind(candidates, feature_type, log_image, feature, line_phase, line_contrast,
                                  (line_asymmetry, faint_asymmetry, faint_contrast), trace_width, raw)
            return [c for c, k in zip(candidates, keep) if k]

        kept = wanted(chains)
        # a rejected chain is judged again branch by branch: a trace paired through a junction with a crease
        # or a texture edge must not go down with it
        accepted = {id(c) for c in kept}
        pieces = [_branch_chain(branches[b], centres, b) for c in chains
                  if id(c) not in accepted and len(c.branches) > 1 for b in c.branches]
        kept_pieces = wanted(pieces)
        taken = {id(c) for c in kept_pieces}
        turned_down = [c for c in chains if id(c) not in accepted and len(c.branches) == 1] + \
                      [c for c in pieces if id(c) not in taken]
        of_kind = _lines_of_kind(turned_down, feature_type, None, feature, line_phase, line_contrast,
                                 (line_asymmetry, faint_asymmetry, faint_contrast), trace_width)
        # without a feature-type map the polarity of a turned-down chain is unknown: none is offered
        rejected = [] if feature_type is None else [c.points for c, k in zip(turned_down, of_kind) if k]
        chains = kept + kept_pieces
    else:
        rejected = []
    return Segments([simplify_polyline(c.points, simplify) for c in chains], _free_ends(chains),
                    _median_types(chains, feature_type), rejected)


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


def _chains(branches: list[_Branch], centres: np.ndarray, links: dict) -> list[_Chain]:
    """Join linked branches into chains, each walked from an unlinked end (closed chains from anywhere)."""
    chains = []
    done = np.zeros(len(branches), bool)
    starts = [(i, e) for i in range(len(branches)) for e in (0, 1) if (i, e) not in links]
    starts += [(i, 0) for i in range(len(branches))]  # what is left are closed chains
    for first, first_end in starts:
        if done[first]:
            continue
        parts, junctions, members, i, e = [], set(), [], first, first_end  # walk into branch i through end e
        while True:
            done[i] = True
            members.append(i)
            pts = _points(branches[i], centres)
            parts.append(pts if e == 0 else pts[::-1])
            junctions.update(j for j in branches[i].ends if j >= 0)
            following = links.get((i, 1 - e))
            if following is None or done[following[0]]:
                break
            i, e = following
        points = _dedupe(np.vstack(parts))
        if len(points) >= 2:
            chains.append(_Chain(points, (branches[first].ends[first_end], branches[i].ends[1 - e]), junctions,
                                 members))
    return chains


def _branch_chain(branch: _Branch, centres: np.ndarray, index: int) -> _Chain:
    """Branch `index` alone as a chain."""
    return _Chain(_points(branch, centres), (branch.ends[0], branch.ends[1]), {j for j in branch.ends if j >= 0},
                  [index])


def _lines_of_kind(chains: list[_Chain], feature_type: np.ndarray | None, log_image: np.ndarray | None,
                   feature: str, line_phase: float, contrast: float, asymmetry: tuple[float, float, float],
                   trace_width: float, raw: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """(n,) bool: chains whose median feature type is a line of the wanted polarity (Kovesi 2003) and whose
    brightness profile is a symmetric line (`line_profile`; `log_image` negated for bright lines); `asymmetry`:
    the limit, the limit for faint chains, and the contrast below which a chain is faint; `raw`: the photo
    before denoising (log, negated alike) and the contrast that passes a chain on it."""
    keep = np.ones(len(chains), bool)
    if feature_type is not None:
        types, limit = _median_types(chains, feature_type), math.radians(line_phase)
        keep &= types <= -limit if feature == "dark" else types >= limit
    if log_image is not None:
        candidates = np.flatnonzero(keep)
        keep[candidates] = are_lines(log_image, [chains[k].points for k in candidates], trace_width=trace_width,
                                     contrast=contrast, asymmetry=asymmetry[0], faint_asymmetry=asymmetry[1],
                                     faint_contrast=asymmetry[2], raw_log_image=None if raw is None else raw[0],
                                     raw_contrast=math.inf if raw is None else raw[1])
    return keep


def _median_types(chains: list[_Chain], feature_type: np.ndarray | None) -> np.ndarray:
    """(n,) median feature type (radians) under each chain's pixels; 0 without a map."""
    if feature_type is None or not chains:
        return np.zeros(len(chains))
    n = np.array([len(c.points) for c in chains])
    points = np.rint(np.vstack([c.points for c in chains])).astype(int)
    values = feature_type[np.clip(points[:, 1], 0, feature_type.shape[0] - 1),
                          np.clip(points[:, 0], 0, feature_type.shape[1] - 1)].astype(np.float64)
    ordered = values[np.lexsort((values, np.repeat(np.arange(len(chains)), n)))]  # sorted within each chain
    start = np.cumsum(n) - n
    return 0.5 * (ordered[start + (n - 1) // 2] + ordered[start + n // 2])


def _free_ends(chains: list[_Chain]) -> np.ndarray:
    """(n, 2): an end is free if it is no junction, or no other of the chains meets its junction."""
    meeting: dict[int, int] = {}
    for c in chains:
        for j in c.junctions:
            meeting[j] = meeting.get(j, 0) + 1
    return np.array([[j < 0 or meeting[j] == 1 for j in c.ends] for c in chains], bool).reshape(-1, 2)


def _dedupe(points: np.ndarray) -> np.ndarray:
    """Drop consecutive repeats (where a branch and the junction centre it ends on coincide)."""
    keep = np.concatenate([[True], np.any(np.diff(points, axis=0) != 0, axis=1)])
    return points[keep]


def simplify_polyline(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Douglas–Peucker simplification keeping both ends (Kovesi's lineseg, MATHS §4.2)."""
    if tolerance <= 0 or len(points) < 3:
        return points
    out = cv2.approxPolyDP(points.astype(np.float32).reshape(-1, 1, 2), float(tolerance), False)
    return out.reshape(-1, 2).astype(np.float64)
