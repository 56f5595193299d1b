"""Merging the duplicate 3D traces of one fracture seen in overlapping photos (MATHS §5).

Overlap (nearest neighbour, "stabilised"): every vertex of trace A is projected onto the nearest point of
trace B's polyline (not B's nearest vertex, which jumps with B's sampling). A vertex whose nearest point is
an end node of B lies beyond B and does not overlap; otherwise it overlaps when it is within `tolerance`.
Stabilised: a nearest point within `tolerance` of B's end counts as the end node, since noisy pixel-density
traces zigzag and a vertex just inside the end can stick out past it.
The overlap fractions are shares of length (each vertex weighted by half its two segments), so unevenly
sampled traces compare fairly.

Merging: overlapping parts are replaced by their centroid (each vertex moves halfway to its nearest point
on the other trace, weighted by how many traces each side already averages), the parts beyond either trace
are kept, and everything is ordered along the longer trace. Traces that do not overlap are joined end to
end by a smoothing-spline bridge through both end regions (s = m·σ², de-duplicated points,
k = min(3, m − 1): MATHS §5 pitfalls). A closed loop (a fracture cutting a knob of rock all round) has no
end nodes: every vertex near it is interior, and it is never bridged.

Automatic merging (beyond the paper, which merged by hand) must never join two fractures. A pair is
suggested only if all of these hold (DECISION):
1. overlap: at least `min_fraction` of one trace's length lies within `tolerance` of the other's interior;
2. orientation: the principal axes of the two overlapping parts differ by at most `max_angle`;
3. coincidence: the mean separation over the overlap is at most tolerance / 2 (two parallel fractures a
   little less than `tolerance` apart overlap but do not coincide);
4. no divergence: at most DIVERGENCE of the overlapping length runs beside the other trace's interior
   between 1 and DIVERGENCE_REACH × `tolerance` away (duplicates only differ beyond each other's ends; a
   trace that crosses or leaves another at a small angle runs beside it there; farther parts of a curved
   trace may face the other's interior without saying anything about the overlap).
5. one photo, one trace: no stretch longer than `tolerance` of the two traces' vertices from the same
   photo lies within `tolerance` of each other. A photo shows a fracture's trace once, so two traces drawn
   in one photo along each other are two fractures (seen on the synthetic outcrop: two fractures whose
   traces run 4 mm apart for 45 cm); pieces of one trace split by an occlusion do not overlap and pass.
Chains of duplicates are merged transitively (union–find). Within a chain, each member must pass rules
1–5 again against the trace merged so far, so a chain cannot bridge two fractures through an ambiguous
link; members left over start a merge of their own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.interpolate import splev, splprep
from scipy.spatial import cKDTree

from engine.errors import InputError
from engine.topology import connectivity
from engine.traces import Trace3D, resample_polyline

DIVERGENCE = 0.25
"""Rule 4: the largest share of the overlapping length that may run beside the other trace beyond tolerance."""

DIVERGENCE_REACH = 5.0
"""Rule 4 looks at vertices up to this many tolerances from the other trace."""

BRIDGE_WINDOW = 10
"""A spline bridge is fitted to each trace's end region of max(gap, BRIDGE_WINDOW × vertex spacing)."""


@dataclass(frozen=True)
class Overlap:
    """How two traces A and B lie along each other (module docstring).

    fraction_ab / fraction_ba : share of A's (B's) length within tolerance of B's (A's) interior.
    separation : mean distance (m) from the overlapping vertices of both traces to the other trace.
    angle : degrees between the principal axes of the overlapping parts of A and B (90 if either part has
        fewer than 2 vertices).
    same_direction : B runs the same way as A along the overlap.
    divergence : length (m) of either trace beside the other's interior, 1 to DIVERGENCE_REACH tolerances away.
    overlap_length : overlapping length (m) of A plus that of B.
    a_range / b_range : first and last overlapping vertex of A (B), or (-1, -1).
    """

    fraction_ab: float
    fraction_ba: float
    separation: float
    angle: float
    same_direction: bool
    divergence: float
    overlap_length: float
    a_range: tuple[int, int]
    b_range: tuple[int, int]

    @property
    def overlaps(self) -> bool:
        """Some vertex of either trace overlaps the other."""
        return self.a_range[0] >= 0 or self.b_range[0] >= 0


@dataclass(frozen=True)
class MergeSuggestion:
    """Traces `a_id` and `b_id` look like one fracture: `score` in (0, 1] (overlap fraction scaled by how
    closely they coincide) and a sentence saying why."""

    a_id: int
    b_id: int
    score: float
    reason: str


@dataclass(frozen=True)
class MergeResult:
    """Traces after merging (unmerged ones unchanged, merged ones with id 0 and `extra["merged_from"]`),
    with components relabelled; the ids merged together; and traces left out, with the reason."""

    traces: list[Trace3D]
    merged_groups: list[tuple[int, ...]]
    skipped: list[tuple[int, str]]


# ---------------------------------------------------------------------------------------------------------
# overlap


def overlap(a: Trace3D, b: Trace3D, *, tolerance: float) -> Overlap:
    """How traces `a` and `b` overlap within `tolerance` (m), by projecting each onto the other (MATHS §5)."""
    _check_tolerance(tolerance)
    _check_trace(a)
    _check_trace(b)
    return _overlap(a.points, b.points, tolerance)


def _overlap(pa: np.ndarray, pb: np.ndarray, tolerance: float) -> Overlap:
    on_b, on_a = _project(pa, pb, tolerance), _project(pb, pa, tolerance)
    in_a = ~on_b.at_end & (on_b.distance <= tolerance)
    in_b = ~on_a.at_end & (on_a.distance <= tolerance)
    wa, wb = _vertex_lengths(pa), _vertex_lengths(pb)
    covered = wa[in_a].sum() + wb[in_b].sum()
    separation = (float((wa * on_b.distance)[in_a].sum() + (wb * on_a.distance)[in_b].sum()) / covered
                  if covered > 0 else np.inf)
    aside = (~on_b.at_end & ~in_a & (on_b.distance <= DIVERGENCE_REACH * tolerance),
             ~on_a.at_end & ~in_b & (on_a.distance <= DIVERGENCE_REACH * tolerance))
    ia, ib = np.flatnonzero(in_a), np.flatnonzero(in_b)
    same = _runs_forward(on_b.arc[ia], pb) if len(ia) > 1 else _runs_forward(on_a.arc[ib], pa) if len(ib) > 1 \
        else True
    return Overlap(float(wa[in_a].sum() / wa.sum()), float(wb[in_b].sum() / wb.sum()), separation,
                   _axis_angle(pa[in_a], pb[in_b]), same, float(wa[aside[0]].sum() + wb[aside[1]].sum()),
                   float(covered), (int(ia[0]), int(ia[-1])) if len(ia) else (-1, -1),
                   (int(ib[0]), int(ib[-1])) if len(ib) else (-1, -1))


def _runs_forward(arc: np.ndarray, polyline: np.ndarray) -> bool:
    """Whether positions `arc` (m, in order along the other trace) advance along `polyline`. Along a loop the
    steps are taken the short way round, so crossing its seam does not reverse the direction."""
    if not _closed(polyline):
        return bool(arc[-1] >= arc[0])
    total = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).sum())
    steps = (np.diff(arc) + total / 2) % total - total / 2
    return bool(steps.sum() >= 0)


@dataclass(frozen=True)
class _Projection:
    """Nearest points of N points on a polyline: distance, arc-length position, the point itself, and
    whether it lies in an end zone of the polyline (the point is beyond that end)."""

    distance: np.ndarray
    arc: np.ndarray
    foot: np.ndarray
    at_end: np.ndarray


def _project(points: np.ndarray, polyline: np.ndarray, tolerance: float) -> _Projection:
    """Nearest point on `polyline` (M ≥ 2, 3) of each point (N, 3): exact for points within
    DIVERGENCE_REACH × `tolerance` of it (the farthest any rule looks), an upper bound beyond.

    A nearest point within `tolerance` (m of arc length) of an end counts as that end node: the stabilised
    nearest neighbour. Pixel-density traces zigzag by their noise, so a vertex a little inside the end can
    stick out past it and catch the nearest point of a point beyond the end. A closed polyline has no ends.
    """
    a, d = polyline[:-1], np.diff(polyline, axis=0)
    length2 = np.einsum("ij,ij->i", d, d)
    tree = cKDTree(a + 0.5 * d)
    k = min(8, len(a))
    _, idx = tree.query(points, k=k)
    idx = idx.reshape(len(points), k)
    _, dist = _segment_params(points[:, None], a[idx], d[idx], length2[idx])
    best = dist.argmin(axis=1)
    seg, distance = idx[np.arange(len(points)), best], dist[np.arange(len(points)), best]
    # a segment not among the k nearest midpoints is nearer only if its midpoint is within distance + half
    # the longest segment of the point; that matters only up to the reach of the rules
    half = 0.5 * np.sqrt(length2.max())
    far = np.linalg.norm(points - (a + 0.5 * d)[idx[:, -1]], axis=1)
    limit = np.minimum(distance, DIVERGENCE_REACH * tolerance) + half
    for i in np.flatnonzero(limit > far):
        cand = np.asarray(tree.query_ball_point(points[i], limit[i]), dtype=np.int64)
        _, dc = _segment_params(points[i], a[cand], d[cand], length2[cand])
        if len(cand) and dc.min() < distance[i]:
            seg[i], distance[i] = cand[dc.argmin()], dc.min()
    t, _ = _segment_params(points, a[seg], d[seg], length2[seg])
    steps = np.sqrt(length2)
    cumulative = np.concatenate([[0.0], np.cumsum(steps)])
    arc, arc_total = cumulative[seg] + t * steps[seg], cumulative[-1]
    at_end = ((arc <= tolerance) | (arc >= arc_total - tolerance)) & (not _closed(polyline))
    return _Projection(distance, arc, a[seg] + t[:, None] * d[seg], at_end)


def _closed(points: np.ndarray) -> bool:
    """The polyline is a loop: its end nodes coincide (a fracture cutting a knob of rock all round)."""
    length = float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
    return bool(np.linalg.norm(points[-1] - points[0]) <= 1e-9 * max(length, 1e-300))


def _segment_params(p, a, d, length2):
    """Clamped parameter t ∈ [0, 1] of the nearest point of each segment a + t·d, and the distance."""
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.clip(np.where(length2 > 0, np.einsum("...k,...k->...", p - a, d) / length2, 0.0), 0.0, 1.0)
    return t, np.linalg.norm(p - (a + t[..., None] * d), axis=-1)


def _vertex_lengths(points: np.ndarray) -> np.ndarray:
    """Length each vertex stands for: half of each adjacent segment."""
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return 0.5 * (np.append(step, 0.0) + np.insert(step, 0, 0.0))


def _axis_angle(p: np.ndarray, q: np.ndarray) -> float:
    """Angle (degrees, 0–90) between the principal axes of two point sets; 90 if either has < 2 points."""
    if len(p) < 2 or len(q) < 2:
        return 90.0
    axes = [np.linalg.svd(x - x.mean(axis=0), full_matrices=False)[2][0] for x in (p, q)]
    return float(np.degrees(np.arccos(min(1.0, abs(float(axes[0] @ axes[1]))))))


# ---------------------------------------------------------------------------------------------------------
# merging a pair


def merge_pair(a: Trace3D, b: Trace3D, *, tolerance: float, smoothing_sigma: float | None = None) -> Trace3D:
    """One trace from two: centroid averaging where they overlap, a spline bridge where they do not.

    tolerance : overlap distance (m), about 2–3 × the registration or ray-casting error (MATHS §5).
    smoothing_sigma : expected positional noise (m) of the bridge spline, s = m·σ²; default tolerance / 3.
    The result has id 0 (the project assigns ids), the union of the images and parent 2D traces, the ids it
    replaces in `extra["merged_from"]`, per-vertex provenance wherever a vertex comes from an original one
    (bridge vertices have image_index −1, uv NaN and face −1), and each end censored only if censored in
    every source that covers it.
    """
    _check_tolerance(tolerance)
    sigma = tolerance / 3 if smoothing_sigma is None else float(smoothing_sigma)
    if not (np.isfinite(sigma) and sigma >= 0):
        raise InputError(None, f"smoothing_sigma={smoothing_sigma!r}: expected a noise level ≥ 0 m")
    _check_trace(a)
    _check_trace(b)
    merged, _ = _merge(_Weighted.of(a), _Weighted.of(b), tolerance, sigma)
    return merged


@dataclass(frozen=True)
class _Weighted:
    """A trace with the number of original traces averaged into each vertex (1 for an original trace)."""

    trace: Trace3D
    support: np.ndarray

    @classmethod
    def of(cls, trace: Trace3D) -> _Weighted:
        return cls(trace, np.ones(len(trace.points)))

    def reversed(self) -> _Weighted:
        t = self.trace
        return _Weighted(replace(t, points=t.points[::-1], uv=t.uv[::-1], face=t.face[::-1],
                                 image_index=t.image_index[::-1], term_start=t.term_end, term_end=t.term_start),
                         self.support[::-1])


def _merge(a: _Weighted, b: _Weighted, tolerance: float, sigma: float) -> tuple[Trace3D, np.ndarray]:
    """The merged trace and its per-vertex support."""
    ov = _overlap(a.trace.points, b.trace.points, tolerance)
    if not ov.overlaps:
        for t in (a.trace, b.trace):
            if _closed(t.points):
                raise InputError(None, f"trace {t.id or 'merged'} is a closed loop and the other trace does not "
                                       f"overlap it within {tolerance:g} m: a loop has no end to bridge from")
        return _bridge(a, b, tolerance, sigma)
    if not ov.same_direction:
        b = b.reversed()
    longer, shorter = (a, b) if a.trace.surface_length >= b.trace.surface_length else (b, a)
    parts = _averaged(longer, shorter, tolerance)
    order = np.argsort(parts.arc, kind="stable")
    keep = np.r_[True, np.any(np.diff(parts.points[order], axis=0) != 0, axis=1)]  # no zero-length steps
    order = order[keep]
    merged = _assemble([longer.trace, shorter.trace], parts.points[order], parts.source[order],
                       parts.vertex[order], tolerance)
    return merged, parts.support[order]


@dataclass(frozen=True)
class _Parts:
    """Candidate vertices of a merged trace: position, arc position along the longer trace, which source
    trace (0 longer, 1 shorter) and vertex each came from, and support."""

    points: np.ndarray
    arc: np.ndarray
    source: np.ndarray
    vertex: np.ndarray
    support: np.ndarray


def _averaged(p: _Weighted, q: _Weighted, tolerance: float) -> _Parts:
    """P's vertices (averaged where they overlap Q), Q's overlapping vertices (averaged) and the parts of Q
    beyond P's ends, placed along P's arc length. Q runs the same way as P."""
    pp, qp = p.trace.points, q.trace.points
    on_q, on_p = _project(pp, qp, tolerance), _project(qp, pp, tolerance)
    p_in = ~on_q.at_end & (on_q.distance <= tolerance)
    q_in = ~on_p.at_end & (on_p.distance <= tolerance)
    p_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pp, axis=0), axis=1))])
    q_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(qp, axis=0), axis=1))])
    support_q_at = q.support[np.clip(np.searchsorted(q_arc, on_q.arc), 0, len(qp) - 1)]
    support_p_at = p.support[np.clip(np.searchsorted(p_arc, on_p.arc), 0, len(pp) - 1)]

    p_pts = pp.copy()
    p_pts[p_in] = _centroid(pp[p_in], p.support[p_in], on_q.foot[p_in], support_q_at[p_in])
    p_sup = np.where(p_in, p.support + support_q_at, p.support)
    q_pts = _centroid(qp, q.support, on_p.foot, support_p_at)
    q_arc_on_p = on_p.arc.copy()
    q_keep = q_in.copy()
    if q_in.any():  # Q beyond P's ends continues from the first/last overlapping vertex along Q
        first, last = np.flatnonzero(q_in)[[0, -1]]
        before, after = np.arange(len(qp)) < first, np.arange(len(qp)) > last
        q_arc_on_p[before] = on_p.arc[first] - (q_arc[first] - q_arc[before])
        q_arc_on_p[after] = on_p.arc[last] + (q_arc[after] - q_arc[last])
        q_pts[before | after] = qp[before | after]
        q_keep |= (before & (q_arc_on_p < 0)) | (after & (q_arc_on_p > p_arc[-1]))
    q_sup = np.where(q_in, q.support + support_p_at, q.support)
    return _Parts(np.vstack([p_pts, q_pts[q_keep]]), np.concatenate([p_arc, q_arc_on_p[q_keep]]),
                  np.repeat([0, 1], [len(pp), int(q_keep.sum())]),
                  np.concatenate([np.arange(len(pp)), np.flatnonzero(q_keep)]),
                  np.concatenate([p_sup, q_sup[q_keep]]))


def _centroid(x: np.ndarray, wx: np.ndarray, y: np.ndarray, wy: np.ndarray) -> np.ndarray:
    return (x * wx[:, None] + y * wy[:, None]) / (wx + wy)[:, None]


def _bridge(a: _Weighted, b: _Weighted, tolerance: float, sigma: float) -> tuple[Trace3D, np.ndarray]:
    """Join two non-overlapping traces across their nearest ends with a smoothing spline (MATHS §5)."""
    ends = [(np.linalg.norm(a.trace.points[i] - b.trace.points[j]), i, j) for i in (0, -1) for j in (0, -1)]
    _, i, j = min(ends, key=lambda e: e[0])
    first = a if i == -1 else a.reversed()  # first ends where second begins
    second = b if j == 0 else b.reversed()
    p, q = first.trace.points, second.trace.points
    gap = float(np.linalg.norm(q[0] - p[-1]))
    spacing = float(np.median(np.concatenate([np.linalg.norm(np.diff(x, axis=0), axis=1) for x in (p, q)])))
    n_new = max(int(np.ceil(gap / spacing)) - 1, 0) if spacing > 0 else 0
    bridge = _spline_bridge(p, q, n_new, max(gap, BRIDGE_WINDOW * spacing), sigma)
    points = np.vstack([p, bridge, q])
    source = np.repeat([0, 2, 1], [len(p), n_new, len(q)])
    vertex = np.concatenate([np.arange(len(p)), np.zeros(n_new, int), np.arange(len(q))])
    merged = _assemble([first.trace, second.trace], points, source, vertex, tolerance)
    return merged, np.concatenate([first.support, np.ones(n_new), second.support])


def _spline_bridge(p: np.ndarray, q: np.ndarray, n: int, window: float, sigma: float) -> np.ndarray:
    """`n` points (n, 3) across the gap from p[-1] to q[0] on a smoothing spline through both end regions
    (s = m·σ², de-duplicated, k = min(3, m − 1): MATHS §5)."""
    if n == 0:
        return np.zeros((0, 3))
    tail, head = _dedup(_end_region(p[::-1], window)[::-1]), _dedup(_end_region(q, window))
    fit = np.vstack([tail, head])
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(fit, axis=0), axis=1))])
    u = chord / chord[-1]
    tck, _ = splprep(fit.T, u=u, k=min(3, len(fit) - 1), s=len(fit) * sigma**2)
    return np.column_stack(splev(np.linspace(u[len(tail) - 1], u[len(tail)], n + 2)[1:-1], tck))


def _end_region(points: np.ndarray, window: float) -> np.ndarray:
    """The first vertices of `points` within `window` (m) of arc length, at least 3."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return points[:max(3, int(np.searchsorted(arc, window, side="right")))]


def _dedup(points: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicates: splprep fails on zero-length steps (MATHS §5 pitfall)."""
    return points[np.r_[True, np.any(np.diff(points, axis=0) != 0, axis=1)]]


def _assemble(sources: list[Trace3D], points: np.ndarray, source: np.ndarray, vertex: np.ndarray,
              tolerance: float) -> Trace3D:
    """A merged Trace3D from vertices tagged with their source trace (0, 1; 2 = new) and source vertex."""
    images = tuple(dict.fromkeys(name for t in sources for name in t.images))
    index = {name: k for k, name in enumerate(images)}
    n = len(points)
    uv, face, image_index = np.full((n, 2), np.nan), np.full(n, -1), np.full(n, -1)
    for k, t in enumerate(sources):
        sel = source == k
        remap = np.append([index[name] for name in t.images], -1)  # -1: a bridge vertex stays without a photo
        uv[sel], face[sel], image_index[sel] = t.uv[vertex[sel]], t.face[vertex[sel]], remap[t.image_index[vertex[sel]]]
    ends = [(t.points[0], t.term_start) for t in sources] + [(t.points[-1], t.term_end) for t in sources]
    set_ids = {t.set_id for t in sources}
    return Trace3D(0, points, uv, face, image_index, images,
                   parents=tuple(sorted({p for t in sources for p in t.parents})),
                   set_id=set_ids.pop() if len(set_ids) == 1 else -1,
                   term_start=_merged_end(points[0], ends, tolerance),
                   term_end=_merged_end(points[-1], ends, tolerance),
                   extra={"merged_from": sorted({i for t in sources for i in _replaced_ids(t)})})


def _merged_end(point: np.ndarray, ends: list[tuple[np.ndarray, str]], tolerance: float) -> str:
    """The termination of a merged end: the sources' common code at that end, else unclassified (""). So it
    is censored only if every source that reaches it is censored there."""
    codes = {code for p, code in ends if np.linalg.norm(p - point) <= tolerance}
    return codes.pop() if len(codes) == 1 else ""


def _replaced_ids(trace: Trace3D) -> list[int]:
    """The project ids a merge replaces: the trace's own id, or for a merge not yet stored (id 0) its sources."""
    return [trace.id] if trace.id != 0 else list(trace.extra.get("merged_from", []))


def trim(trace: Trace3D, start: int, stop: int) -> Trace3D:
    """Vertices [start, stop) of `trace` (Python slice rules, negative indices count from the end).

    A cut end becomes unclassified (""); an end kept keeps its termination. At least 2 vertices must remain.
    """
    n = len(trace.points)
    lo, hi, _ = slice(start, stop).indices(n)
    if hi - lo < 2:
        raise InputError(None, f"trace {trace.id}: trimming to vertices [{start}, {stop}) of {n} leaves "
                               f"{max(hi - lo, 0)}; expected 0 ≤ start < stop − 1 ≤ {n - 1}")
    sl = slice(lo, hi)
    return replace(trace, points=trace.points[sl], uv=trace.uv[sl], face=trace.face[sl],
                   image_index=trace.image_index[sl], term_start=trace.term_start if lo == 0 else "",
                   term_end=trace.term_end if hi == n else "", extra=dict(trace.extra))


# ---------------------------------------------------------------------------------------------------------
# automatic merging


def suggest_merges(traces: Sequence[Trace3D], *, tolerance: float, min_fraction: float = 0.5,
                   max_angle: float = 15.0) -> list[MergeSuggestion]:
    """Pairs of traces that look like one fracture seen twice, best first (module docstring, rules 1–5).

    tolerance : overlap distance (m), about 2–3 × the registration or ray-casting error.
    min_fraction : rule 1, share of the shorter trace's length along the other (0–1).
    max_angle : rule 2, degrees between the overlapping parts' principal axes.
    Traces that cannot be merged (fewer than 3 vertices) are left out; ids must be unique;
    NaN coordinates raise InputError.
    """
    _check_tolerance(tolerance)
    if not 0 < min_fraction <= 1:
        raise InputError(None, f"min_fraction={min_fraction!r}: expected a share in (0, 1]")
    if not 0 <= max_angle <= 90:
        raise InputError(None, f"max_angle={max_angle!r}: expected degrees in [0, 90]")
    for t in traces:
        _check_finite(t)
    usable = [t for t in traces if _problem(t) is None]
    ids = [t.id for t in usable]
    if len(set(ids)) != len(ids):
        raise InputError(None, "trace ids must be unique to name merge suggestions (the project assigns them)")
    out = []
    for i, j in _near_pairs(usable, tolerance):
        ov = _overlap(usable[i].points, usable[j].points, tolerance)
        if _passes(ov, tolerance, min_fraction, max_angle) and not _same_photo(usable[i], usable[j], tolerance):
            out.append(_suggestion(usable[i].id, usable[j].id, ov, tolerance))
    return sorted(out, key=lambda s: (-s.score, s.a_id, s.b_id))


def _near_pairs(traces: Sequence[Trace3D], tolerance: float) -> list[tuple[int, int]]:
    """Index pairs (i < j) of traces that come within about `tolerance` of each other (MATHS §5 step 2)."""
    samples = [resample_polyline(t.points, tolerance / 2)[0] for t in traces]
    if not samples:
        return []
    owner = np.repeat(np.arange(len(samples)), [len(s) for s in samples])
    pairs = cKDTree(np.vstack(samples)).query_pairs(tolerance, output_type="ndarray")
    i, j = owner[pairs[:, 0]], owner[pairs[:, 1]]
    keep = i != j
    unique = np.unique(np.sort(np.column_stack([i[keep], j[keep]]), axis=1), axis=0)
    return [(int(a), int(b)) for a, b in unique]


def _passes(ov: Overlap, tolerance: float, min_fraction: float, max_angle: float) -> bool:
    return (max(ov.fraction_ab, ov.fraction_ba) >= min_fraction and ov.angle <= max_angle
            and ov.separation <= tolerance / 2 and ov.divergence <= DIVERGENCE * ov.overlap_length)


def _same_photo(a: Trace3D, b: Trace3D, tolerance: float) -> bool:
    """Rule 5: vertices of a and b from one photo lie along each other for more than `tolerance`."""
    weight = _vertex_lengths(a.points)
    for name in set(a.images) & set(b.images):
        mine = a.image_index == a.images.index(name)
        theirs = b.points[b.image_index == b.images.index(name)]
        if mine.any() and len(theirs):
            distance, _ = cKDTree(theirs).query(a.points[mine], distance_upper_bound=tolerance)
            if weight[mine][np.isfinite(distance)].sum() > tolerance:
                return True
    return False


def _suggestion(a_id: int, b_id: int, ov: Overlap, tolerance: float) -> MergeSuggestion:
    share, covered, other = ((ov.fraction_ba, b_id, a_id) if ov.fraction_ba >= ov.fraction_ab
                             else (ov.fraction_ab, a_id, b_id))
    reason = (f"{share:.0%} of trace {covered} lies within {tolerance:g} m along trace {other}: mean gap "
              f"{ov.separation * 1000:.1f} mm, axes {ov.angle:.1f}° apart")
    return MergeSuggestion(a_id, b_id, float(share * (1 - ov.separation / tolerance)), reason)


def auto_merge(traces: Sequence[Trace3D], *, tolerance: float, min_fraction: float = 0.5,
               max_angle: float = 15.0, smoothing_sigma: float | None = None) -> MergeResult:
    """Merge every group of duplicates that `suggest_merges` links (union–find, so chains merge together).

    Each group is merged starting from its longest trace, adding the member sharing the most length with
    the merged trace while one passes rules 1–5 against it; the members left over are merged among themselves the same
    way. Merged traces take the place of their group's first member; components are relabelled over the
    result.
    """
    suggestions = suggest_merges(traces, tolerance=tolerance, min_fraction=min_fraction, max_angle=max_angle)
    sigma = tolerance / 3 if smoothing_sigma is None else float(smoothing_sigma)
    by_id = {t.id: t for t in traces}
    groups = DisjointSet(by_id)
    for s in suggestions:
        groups.merge(s.a_id, s.b_id)
    position = {t.id: k for k, t in enumerate(traces)}
    replaced: dict[int, Trace3D | None] = {}
    merged_groups = []
    for members in groups.subsets():
        if len(members) < 2:
            continue
        for merged, used in _merge_group([by_id[i] for i in members], tolerance, sigma, min_fraction, max_angle):
            if len(used) > 1:
                first = min(used, key=position.__getitem__)
                replaced.update({i: None for i in used})
                replaced[first] = merged
                merged_groups.append(tuple(sorted(used)))
    out = [replaced.get(t.id, t) for t in traces]
    out = relabel_components([t for t in out if t is not None], tolerance)
    skipped = [(t.id, problem) for t in traces if (problem := _problem(t)) is not None]
    return MergeResult(out, sorted(merged_groups), skipped)


def _merge_group(members: list[Trace3D], tolerance: float, sigma: float, min_fraction: float,
                 max_angle: float) -> list[tuple[Trace3D, list[int]]]:
    """Merge a group of linked traces greedily: from the longest, add the member sharing the most length
    with the merged trace while one passes rules 1–5; the rest start again. Returns (merged trace, ids)."""
    pending = sorted(members, key=lambda t: -t.surface_length)
    out = []
    while pending:
        current = _Weighted.of(pending.pop(0))
        used = [current.trace.id]
        while True:
            fits = []
            for k, t in enumerate(pending):
                ov = _overlap(current.trace.points, t.points, tolerance)
                if _passes(ov, tolerance, min_fraction, max_angle) and not _same_photo(current.trace, t, tolerance):
                    fits.append((ov.overlap_length, k))
            if not fits:
                break
            trace = pending.pop(max(fits)[1])
            merged, support = _merge(current, _Weighted.of(trace), tolerance, sigma)
            current = _Weighted(merged, support)
            used.append(trace.id)
        out.append((current.trace, used))
    return out


def relabel_components(traces: Sequence[Trace3D], tolerance: float) -> list[Trace3D]:
    """The traces with `component` set to their connected group (traces touching within `tolerance`, m),
    numbered by size, 0 the largest (engine.topology.connectivity). Run it after every merge."""
    labels = connectivity(traces, tolerance).labels if traces else []
    return [replace(t, component=int(label)) for t, label in zip(traces, labels)]


# ---------------------------------------------------------------------------------------------------------
# checks


def _check_tolerance(tolerance: float) -> None:
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise InputError(None, f"tolerance={tolerance!r}: expected a positive distance in metres")


def _check_finite(trace: Trace3D) -> None:
    bad = ~np.isfinite(trace.points).all(axis=1)
    if bad.any():
        raise InputError(None, f"trace {trace.id}: {int(bad.sum())} of its {len(bad)} vertices are NaN or "
                               "infinite; expected finite coordinates (metres, mesh frame)")


def _problem(trace: Trace3D) -> str | None:
    """Why a finite `trace` cannot be merged, or None."""
    p = trace.points
    if len(p) < 3:
        return f"trace {trace.id}: {len(p)} vertices; merging needs at least 3"
    return None


def _check_trace(trace: Trace3D) -> None:
    _check_finite(trace)
    problem = _problem(trace)
    if problem is not None:
        raise InputError(None, problem)
