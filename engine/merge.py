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
1. overlap: at least `min_fraction` of one trace's length lies within `tolerance` of the other's interior,
   or all of it within `tolerance` of the other (a short duplicate of the other's end zone), or they overlap
   end to end: each leaves the overlap, at least `tolerance` / 2 long on each, only past the other's end (two
   photos each showing part of a long trace; a trace crossing, abutting or leaving another leaves the
   overlap beside the other's interior). Pieces overlapping back by up to `tolerance` are bridges (B3);
2. orientation: where they overlap, the two traces run the same way: the median angle between their
   directions (chords one `tolerance` long) at each overlapping vertex and its nearest point on the other
   is at most `max_angle`. (Principal axes of the overlapping parts, used before, are undefined along a
   curve that turns: two copies of one bend, 0.8 mm apart, had axes 84° apart on the synthetic outcrop.)
   A trace shorter than `tolerance` lying wholly along the other has no direction at that scale, and
   this rule does not apply to it (rule 3 does);
3. coincidence: the mean separation over the overlap is at most tolerance / 2 (two parallel fractures a
   little less than `tolerance` apart overlap but do not coincide);
4. no divergence: at most DIVERGENCE of the overlapping length runs beside the other trace's interior
   between 1 and DIVERGENCE_REACH × `tolerance` away (duplicates only differ beyond each other's ends; a
   trace that crosses or leaves another at a small angle runs beside it there; farther parts of a curved
   trace may face the other's interior without saying anything about the overlap, and so do parts that
   come back beside it after passing its end, as a trace round a buttress or a bench edge does).
5. one photo, one trace: no stretch longer than `tolerance` of the two traces' vertices from the same
   photo lies within `tolerance` of each other. A photo shows a fracture's trace once, so two traces drawn
   in one photo along each other are two fractures (seen on the synthetic outcrop: two fractures whose
   traces run 4 mm apart for 45 cm); pieces of one trace split by an occlusion do not overlap and pass.
Pieces of one fracture seen end to end (an occlusion, or the end of a photo, cut the trace) overlap too
little for rule 1. A pair that fails rule 1 is suggested as a bridge (kind "bridge") if all of these hold
(DECISION; measured on noisy synthetic outcrops, where the gaps between pieces of one fracture that overlap
nothing are straight continuations only a few centimetres wide or else crooked slivers of grazing rays):
B1. gap: an end node of each lies within BRIDGE_REACH × `tolerance` of the other's (neither is a loop);
B2. alignment: the end directions (principal axes of the last BRIDGE_TANGENT tolerances) are within
    `max_angle` of carrying straight on;
B3. chord: each end node lies within tolerance / 2 + gap · sin(`max_angle` / 2) of the other's end line
    (across a smooth bend of up to `max_angle` the chord runs half way between the end directions; sideways,
    pieces may be as far apart as duplicates under rule 3), and at most `tolerance` back along it (little
    overlap);
B4. one plane: a trace of a planar fracture is a planar curve, so a common plane fits both end regions
    (BRIDGE_PLANE tolerances each) within PLANE_EXCESS × `tolerance` RMS of how well each fits its own
    (two straight pieces carry no evidence and pass);
B5. nothing crosses the gap: no other trace but the duplicates of either piece comes within `tolerance` of
    the chord between the ends (two fractures abutting a third from either side).
Given the survey (`sight`: mesh, cameras, ray tracer), a pair that fails B1–B4 is still suggested as a bridge
across a gap that no photo shows (a fracture crossing a bench edge or passing behind a buttress, whose pieces
meet at an angle, 0.3–1 m apart on the synthetic outcrops) if all of these hold (DECISION):
H1. gap: the end nodes lie within HIDDEN_REACH × `tolerance`, and where either end region is straight (H5)
    with at most `tolerance` of overlap back. Pieces that each show the plane (H2) may double back: a
    trace round a buttress runs back along itself (planar seeds 5 and 10: 105 → 103 and 97 → 95 traces,
    no fracture mixed on 23 outcrops);
H2. one plane, shown by each: each end region is a curve that shows its own plane (its spread across its
    main axis is at least PLANE_SIGNAL × its RMS distance from that plane, and at least PLANE_SPREAD ×
    `tolerance`), the two planes are within `max_angle`, and the pair passes rule B4. Two straight pieces
    would share a plane whenever their lines meet, as the traces of two fractures crossing behind an
    occluder do: they carry no evidence and are left to rules B1–B4. Neither plane may be the outcrop
    surface's (engine.orientation.surface_planes): any two curves drawn on one flat patch of rock share
    its plane (seen on the synthetic outcrop: two fractures' pieces 9–11 cm apart in one plane to 1 mm);
H3. hidden: followed along the rock from one end node, that plane's section through the mesh reaches the
    other (engine.sight.Sight.plane_path), and at most HIDDEN_SEEN of the path farther than 2 × `tolerance`
    from either end is shown by any photo (`Sight.shows`: seen, and off the occluding edges where a trace's
    pixels do not reach the mesh): the gap is explained by occlusion, not by a photo showing rock without
    the trace. Other curves where the plane cuts the rock (the front of a buttress the trace runs
    behind) are not the trace and do not count (counting every cut point within reach of the gap kept
    planar seed 5 at 109 traces for 98 seen; following the path, 106). A gap within B1's reach with no
    such path is a bend round an edge of the rock and passes;
H4. nothing crosses the gap: no other trace comes within `tolerance` of the path (B5 on the rock: the
    chord of a hidden gap runs through rock or air, where no trace can be, and passes near traces that
    cross the pieces at their ends). The bridge is laid along the path.
H5. straight pieces: where either end region is too straight to show a plane (H2), the pair is still a
    hidden-gap bridge if the gap is wider than B1's reach, the pieces bend by more than `max_angle` and
    their lines meet ahead of both ends within `tolerance` of each other and of the rock (a straight trace
    bends where it crosses an edge of the rock), both end regions together show a plane that is not the
    outcrop surface's, rules H1, H3, H4 and B4 hold, and nothing else could continue either piece: every
    bridge candidate (any rule, H5 included) at each of the two ends is a duplicate of the other piece.
    Without the bend and the meeting on the rock, H5 joined two fractures on three of ten held-out
    outcrops (nearly collinear pieces 0.7–1 m apart, and a 10 cm piece); with them, none of seventeen.
Pairs that fail these rules but may still continue each other across a hidden gap (the gap wider than
B1's reach, little overlap back, both end regions together showing a plane that is not the outcrop
surface's, whose path along the rock is hidden and uncrossed: H3, H4) are listed for the user to judge
(`suggest_merges(review=True)`, kind "candidate"), never merged automatically. On the synthetic outcrops
nothing in the geometry tells these pairs apart: across a bench top the cameras do not see, a steep
fracture's two traces are parallel lines on parallel faces, which share a plane whichever two are paired.
Chains of duplicates and bridges are merged transitively (union–find). Within a chain, each member must
pass rules 1–5 (or B1–B5) again against the trace merged so far, so a chain cannot join two fractures
through an ambiguous link; members left over start a merge of their own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.interpolate import splev, splprep
from scipy.spatial import cKDTree

from engine.errors import InputError
from engine.extract import EDGE_PX_KEY, extracted_edge_px
from engine.orientation import eigen_orientation, surface_planes, unoriented
from engine.sight import Sight
from engine.topology import connectivity
from engine.traces import Trace3D, network, resample_polyline

DIVERGENCE = 0.25
"""Rule 4: the largest share of the overlapping length that may run beside the other trace beyond tolerance."""

DIVERGENCE_REACH = 5.0
"""Rule 4 looks at vertices up to this many tolerances from the other trace."""

FALLBACK = 64
"""Segments per point examined at once where the nearest 8 midpoints cannot vouch for the nearest segment."""

END_ZONE = 1 / 6
"""The stabilising end zone covers at most this share of the polyline at each end, so a trace shorter than
a few tolerances keeps an interior (short duplicates, e.g. of a 5 cm fracture tip, must still overlap)."""

BRIDGE_WINDOW = 10
"""A spline bridge is fitted to each trace's end region of max(gap, BRIDGE_WINDOW × vertex spacing)."""

BRIDGE_REACH = 4.0
"""Rule B1: the widest gap, in tolerances, a bridge suggestion spans."""

BRIDGE_TANGENT = 5.0
"""Rule B2: an end direction is the principal axis of the trace's last BRIDGE_TANGENT tolerances."""

BRIDGE_PLANE = 30.0
"""Rule B4: the end regions, in tolerances, that must share a plane."""

PLANE_EXCESS = 0.1
"""Rule B4: how much worse (RMS, in tolerances) the common plane may fit than each region's own."""

HIDDEN_REACH = 40.0
"""Rule H1: the widest gap, in tolerances, a hidden-gap bridge spans."""

PLANE_SIGNAL = 5.0
"""Rule H2: how many times its RMS distance from its plane an end region must spread across its main axis
for that plane to be known (normal to within ~atan(1/5) ≈ 11°)."""

PLANE_SPREAD = 1 / 6
"""Rule H2: the least RMS spread, in tolerances, of an end region across its main axis (an almost straight
piece has a noise-sized spread and RMS)."""

HIDDEN_SEEN = 0.1
"""Rule H3: the largest share of the fracture plane's cut through the gap that a photo may see."""


@dataclass(frozen=True)
class Overlap:
    """How two traces A and B lie along each other (module docstring).

    fraction_ab / fraction_ba : share of A's (B's) length within tolerance of B's (A's) interior.
    separation : mean distance (m) from the overlapping vertices of both traces to the other trace.
    angle : median degrees (0–90) between the directions of A and B along the overlap (rule 2; 90 if
        neither overlapping part has 2 vertices), NaN if one, shorter than `tolerance`, lies wholly along
        the other: it has no direction at the scale of rule 2's chords (a tip or shred a photo saw), and
        rule 2 does not apply to it.
    same_direction : B runs the same way as A along the overlap.
    divergence : length (m) of either trace beside the other's interior, 1 to DIVERGENCE_REACH tolerances away.
    overlap_length : overlapping length (m) of A plus that of B.
    a_range / b_range : first and last overlapping vertex of A (B), or (-1, -1).
    end_to_end : the traces overlap end to end (rule 1): neither lies wholly along the other, and each
        leaves the overlap, at least `tolerance` / 2 long on each, only past the other's end.
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
    end_to_end: bool = False

    @property
    def overlaps(self) -> bool:
        """Some vertex of either trace overlaps the other."""
        return self.a_range[0] >= 0 or self.b_range[0] >= 0


@dataclass(frozen=True)
class Joint:
    """How trace B continues trace A across the gap between their nearest end nodes (rules B1–B4).

    a_end / b_end : the end of A (B) at the joint: 0 (start) or -1 (end).
    gap : distance (m) between the two end nodes.
    angle : degrees between A's outward end direction and B's inward one (0: B carries straight on).
    offset : distance (m) of the farther end node from the other trace's end line.
    back : how far (m) the farther end node lies back along the other's end direction (overlap), or 0.
    plane_excess : RMS distance (m) of both end regions from their common best-fit plane, less the larger of
        each region's RMS distance from its own.
    """

    a_end: int
    b_end: int
    gap: float
    angle: float
    offset: float
    back: float
    plane_excess: float


FOR_REVIEW = ("candidate", "kinds")
"""The kinds of merge suggestion left to the user's judgement: `suggest_merges(review=True)` lists them."""


@dataclass(frozen=True)
class MergeSuggestion:
    """Traces `a_id` and `b_id` look like one fracture: `score` in (0, 1], a sentence saying why, and the
    `kind` of evidence: "overlap" (duplicates, scored by overlap fraction scaled by how closely they
    coincide), "bridge" (pieces end to end, scored by how narrow the gap and how straight the joint),
    "candidate" (pieces that may continue each other across a hidden gap, for the user to judge) or "kinds"
    (duplicates of two kinds, e.g. a fracture and bedding: one trace given two kinds in two photos, which
    merges once given one). The last two (`FOR_REVIEW`) are never merged automatically."""

    a_id: int
    b_id: int
    score: float
    reason: str
    kind: str = "overlap"


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
    aside = (_linked(~on_b.at_end & ~in_a & (on_b.distance <= DIVERGENCE_REACH * tolerance), in_a, on_b.at_end),
             _linked(~on_a.at_end & ~in_b & (on_a.distance <= DIVERGENCE_REACH * tolerance), in_b, on_a.at_end))
    ia, ib = np.flatnonzero(in_a), np.flatnonzero(in_b)
    same = _runs_forward(on_b.arc[ia], pb) if len(ia) > 1 else _runs_forward(on_a.arc[ib], pa) if len(ib) > 1 \
        else True
    # a trace lying wholly within tolerance of the other (a short duplicate of its end zone) is all along it
    fraction_ab = 1.0 if (on_b.distance <= tolerance).all() else float(wa[in_a].sum() / wa.sum())
    fraction_ba = 1.0 if (on_a.distance <= tolerance).all() else float(wb[in_b].sum() / wb.sum())
    # a trace shorter than tolerance has no direction at the scale of rule 2's chords: noise sets it
    undirected = (fraction_ab == 1.0 and wa.sum() < tolerance) or (fraction_ba == 1.0 and wb.sum() < tolerance)
    angle = np.nan if undirected else _along_angle(pa, in_a, on_b.arc, pb, in_b, on_a.arc, tolerance)
    end_to_end = (_ends_beyond(pa, in_a, on_b.at_end, tolerance) and _ends_beyond(pb, in_b, on_a.at_end, tolerance)
                  and max(fraction_ab, fraction_ba) < 1.0)
    return Overlap(fraction_ab, fraction_ba, separation, angle, same,
                   float(wa[aside[0]].sum() + wb[aside[1]].sum()), float(covered),
                   (int(ia[0]), int(ia[-1])) if len(ia) else (-1, -1),
                   (int(ib[0]), int(ib[-1])) if len(ib) else (-1, -1), end_to_end)


def _linked(aside: np.ndarray, inside: np.ndarray, beyond: np.ndarray) -> np.ndarray:
    """The vertices of `aside` that the trace reaches from its overlap (`inside`) without passing beyond the
    other trace's end (`beyond`). A trace that leaves the other's interior runs beside it there; one that
    has passed the other's end and turns back (round a buttress) says nothing about the overlap."""
    k = np.flatnonzero(inside)
    if not len(k):
        return aside
    index = np.arange(len(aside))
    before, after = np.flatnonzero(beyond[:k[0]]), k[-1] + 1 + np.flatnonzero(beyond[k[-1] + 1:])
    lo = before[-1] + 1 if len(before) else 0
    hi = after[0] if len(after) else len(aside)
    return aside & (index >= lo) & (index < hi)


def _ends_beyond(points: np.ndarray, inside: np.ndarray, beyond: np.ndarray, tolerance: float) -> bool:
    """Rule 1, end to end: the overlapping span of a trace (first to last overlapping vertex) is at least
    `tolerance` / 2 long (the other's end zone, up to `tolerance`, lies beyond it) and, on each side, is the trace's own end or is followed by a vertex beyond the other
    trace's end: the trace leaves the overlap only past the other's end."""
    k = np.flatnonzero(inside)
    if len(k) < 2:
        return False
    arc = _arc_lengths(points)
    return bool(arc[k[-1]] - arc[k[0]] >= tolerance / 2 and (k[0] == 0 or beyond[k[0] - 1])
                and (k[-1] == len(points) - 1 or beyond[k[-1] + 1]))


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
    seg, distance = _nearest_segments(points, a, d, length2, DIVERGENCE_REACH * tolerance)
    t, _ = _segment_params(points, a[seg], d[seg], length2[seg])
    steps = np.sqrt(length2)
    cumulative = np.concatenate([[0.0], np.cumsum(steps)])
    arc, arc_total = cumulative[seg] + t * steps[seg], cumulative[-1]
    zone = min(tolerance, END_ZONE * arc_total)
    at_end = ((arc <= zone) | (arc >= arc_total - zone)) & (not _closed(polyline))
    return _Projection(distance, arc, a[seg] + t[:, None] * d[seg], at_end)


def _nearest_segments(points: np.ndarray, a: np.ndarray, d: np.ndarray, length2: np.ndarray,
                      reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest segment a + t·d of each point and the distance, exact within `reach` (m).

    The 8 segments with the nearest midpoints come first. The longest segments (gaps stepped over in
    extraction, bridges; up to FALLBACK of them, over twice the median) are then measured against every
    point. Any other segment is nearer only if its midpoint lies within the distance found + half the
    longest of them: those are measured too, FALLBACK at a time, or one by one beyond that.
    """
    tree = cKDTree(a + 0.5 * d)
    _, idx = tree.query(points, k=min(8, len(a)))
    idx = idx.reshape(len(points), -1)
    seg, distance = _best(points[:, None], a, d, length2, idx, np.ones(idx.shape, dtype=bool))
    steps = np.sqrt(length2)
    longest = np.argsort(steps)[::-1][:FALLBACK]
    longest = longest[steps[longest] > 2 * np.median(steps)]
    if len(longest):
        s, dist = _best(points[:, None], a, d, length2, np.broadcast_to(longest, (len(points), len(longest))),
                        np.ones((len(points), len(longest)), dtype=bool))
        nearer = dist < distance
        seg[nearer], distance[nearer] = s[nearer], dist[nearer]
    half = 0.5 * np.delete(steps, longest).max(initial=0.0)
    limit = np.minimum(distance, reach) + half
    unsure = np.flatnonzero(limit > np.linalg.norm(points - (a + 0.5 * d)[idx[:, -1]], axis=1))
    if len(unsure):
        near, cand = tree.query(points[unsure], k=min(FALLBACK, len(a)))
        cand, within = cand.reshape(len(unsure), -1), near.reshape(len(unsure), -1) <= limit[unsure, None]
        s, dist = _best(points[unsure, None], a, d, length2, cand, within)
        nearer = dist < distance[unsure]
        seg[unsure[nearer]], distance[unsure[nearer]] = s[nearer], dist[nearer]
        for i in unsure[within.all(axis=1)]:  # more midpoints within the limit than were measured
            cand = np.asarray(tree.query_ball_point(points[i], limit[i]), dtype=np.int64)
            _, dist = _segment_params(points[i], a[cand], d[cand], length2[cand])
            if dist.min() < distance[i]:
                seg[i], distance[i] = cand[dist.argmin()], dist.min()
    return seg, distance


def _best(points: np.ndarray, a: np.ndarray, d: np.ndarray, length2: np.ndarray, cand: np.ndarray,
          use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points (N, 1, 3), the nearest of their candidate segments cand (N, K) where `use`: index and
    distance (inf where none is used)."""
    _, dist = _segment_params(points, a[cand], d[cand], length2[cand])
    dist = np.where(use, dist, np.inf)
    pick = dist.argmin(axis=1)
    rows = np.arange(len(cand))
    return cand[rows, pick], dist[rows, pick]


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


def _along_angle(pa: np.ndarray, in_a: np.ndarray, arc_b: np.ndarray, pb: np.ndarray, in_b: np.ndarray,
                 arc_a: np.ndarray, tolerance: float) -> float:
    """Median angle (degrees, 0–90) between the two traces' directions at the overlapping vertices of both
    and their nearest points on the other (`arc_b`: positions along B of A's vertices, `arc_a` the converse);
    90 if neither has 2 overlapping vertices. Directions are chords one `tolerance` long, so vertex noise
    does not count; unlike principal axes, they stay defined along a curved overlap."""
    if np.count_nonzero(in_a) < 2 and np.count_nonzero(in_b) < 2:
        return 90.0
    angles = []
    for p, inside, arc, q in ((pa, in_a, arc_b, pb), (pb, in_b, arc_a, pa)):
        own = _arc_lengths(p)[inside]
        cos = np.abs(np.sum(_chord_directions(p, own, tolerance) * _chord_directions(q, arc[inside], tolerance), 1))
        angles.append(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))))
    return float(np.median(np.concatenate(angles)))


def _arc_lengths(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _chord_directions(polyline: np.ndarray, arc: np.ndarray, length: float) -> np.ndarray:
    """Unit directions (N, 3) of the chords of `polyline` from arc − length/2 to arc + length/2 (clipped to
    the polyline) at arc-length positions `arc` (N,)."""
    s = _arc_lengths(polyline)
    ends = [np.column_stack([np.interp(np.clip(arc + h, 0, s[-1]), s, polyline[:, k]) for k in range(3)])
            for h in (-length / 2, length / 2)]
    chord = ends[1] - ends[0]
    return chord / np.maximum(np.linalg.norm(chord, axis=1, keepdims=True), 1e-12)


# ---------------------------------------------------------------------------------------------------------
# joints (pieces end to end)


def joint(a: Trace3D, b: Trace3D, *, tolerance: float) -> Joint:
    """How trace `b` continues trace `a` end to end (module docstring, rules B1–B4); `tolerance` (m) scales
    the end regions. Loops have no ends: InputError."""
    _check_tolerance(tolerance)
    for t in (a, b):
        _check_trace(t)
        if _closed(t.points):
            raise InputError(None, f"trace {t.id} is a closed loop: it has no end to continue")
    return _joint(a.points, b.points, tolerance)


def _joint(pa: np.ndarray, pb: np.ndarray, tolerance: float) -> Joint:
    _, i, j = min((float(np.linalg.norm(pa[i] - pb[j])), i, j) for i in (0, -1) for j in (0, -1))
    ends = [_from_end(pa, i), _from_end(pb, j)]
    ta, tb = (_outward(_end_region(e, BRIDGE_TANGENT * tolerance)) for e in ends)
    chord = ends[1][0] - ends[0][0]
    # B's end node seen from A's end line, and A's seen from B's
    along = np.array([chord @ ta, -chord @ tb])
    offset = max(float(np.linalg.norm(chord - along[0] * ta)), float(np.linalg.norm(chord + along[1] * tb)))
    regions = [_end_region(e, BRIDGE_PLANE * tolerance) for e in ends]
    excess = _plane_rms(np.vstack(regions)) - max(_plane_rms(r) for r in regions)
    return Joint(i, j, float(np.linalg.norm(chord)), _angle(ta, -tb), offset, float(max(0.0, -along.min())),
                 float(excess))


def _from_end(points: np.ndarray, end: int) -> np.ndarray:
    """The polyline starting from its end `end` (0 or -1)."""
    return points if end == 0 else points[::-1]


def _outward(region: np.ndarray) -> np.ndarray:
    """Unit principal axis of an end region (first vertex = the end node), pointing out past the end."""
    axis = np.linalg.svd(region - region.mean(axis=0), full_matrices=False)[2][0]
    return axis if axis @ (region[0] - region.mean(axis=0)) >= 0 else -axis


def _plane_rms(points: np.ndarray) -> float:
    """RMS distance (m) of points (N ≥ 3, 3) from their best-fit plane."""
    return float(np.linalg.svd(points - points.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(points)))


def _angle(u: np.ndarray, v: np.ndarray) -> float:
    """Degrees between unit vectors."""
    return float(np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))))


def _axial_angle(u: np.ndarray, v: np.ndarray) -> float:
    """Degrees between the lines of unit vectors u and v (0–90)."""
    return float(np.degrees(np.arccos(np.clip(abs(u @ v), 0.0, 1.0))))


def _bridgeable(jt: Joint, tolerance: float, max_angle: float) -> bool:
    """Rules B1–B4."""
    return (jt.gap <= BRIDGE_REACH * tolerance and jt.angle <= max_angle
            and jt.offset <= tolerance / 2 + jt.gap * np.sin(np.radians(max_angle / 2)) and jt.back <= tolerance
            and jt.plane_excess <= PLANE_EXCESS * tolerance)


def _hidden_gap(pa: np.ndarray, pb: np.ndarray, jt: Joint, tolerance: float, max_angle: float,
                sight: Sight, *, straight: bool = False) -> np.ndarray | None:
    """Rules H1–H3 (H2 or, with `straight`, H5): the path of the two end regions' common plane through the
    mesh across the gap, farther than 2 × `tolerance` from the ends (for rule H4 and the bridge), or None if
    the pair is not a bridge across a gap hidden from every photo."""
    if jt.gap > HIDDEN_REACH * tolerance or jt.plane_excess > PLANE_EXCESS * tolerance:
        return None
    ends = [_from_end(pa, jt.a_end), _from_end(pb, jt.b_end)]
    regions = [_end_region(e, BRIDGE_PLANE * tolerance) for e in ends]
    straight = straight and jt.gap > BRIDGE_REACH * tolerance and jt.angle > max_angle
    planar = _plane_evidence(regions, tolerance, max_angle, straight)
    if planar is None or len(planar) == 1 and (jt.back > tolerance or not _meet_on_rock(ends, tolerance, sight)):
        return None
    if surface_planes(planar, [eigen_orientation(r) for r in planar], sight.mesh).any():
        return None
    cut = _plane_cut(regions, jt, tolerance, sight)
    if cut is None or not len(cut):
        return np.zeros((0, 3)) if jt.gap <= BRIDGE_REACH * tolerance else None
    return None if sight.shows(cut, tolerance).mean() > HIDDEN_SEEN else cut


def _plane_cut(regions: list[np.ndarray], jt: Joint, tolerance: float, sight: Sight) -> np.ndarray | None:
    """The path along the rock of the end regions' (each from its end node) common plane from one end node
    to the other, farther than 2 × `tolerance` from both, or None if the plane's section does not join them
    (engine.sight.Sight.plane_path)."""
    both = np.vstack(regions)
    centre = both.mean(axis=0)
    normal = np.linalg.svd(both - centre, full_matrices=False)[2][2]
    a, b = regions[0][0], regions[1][0]
    path = sight.plane_path(centre, normal, a, b, jt.gap + 2 * tolerance,
                            2 * tolerance + sight.mesh.mean_edge_length)
    if path is None:
        return None
    return path[np.minimum(np.linalg.norm(path - a, axis=1), np.linalg.norm(path - b, axis=1)) > 2 * tolerance]


def _plane_evidence(regions: list[np.ndarray], tolerance: float, max_angle: float,
                    straight: bool) -> list[np.ndarray] | None:
    """The curves showing the plane of a hidden-gap bridge: both end regions, if each shows its own plane
    and the two agree within `max_angle` (rule H2); with `straight`, where either is too straight to show
    one, both regions together if they show one (rule H5); else None."""
    normals = [_shown_plane(r, tolerance) for r in regions]
    if normals[0] is not None and normals[1] is not None:
        return regions if _axial_angle(normals[0], normals[1]) <= max_angle else None
    both = np.vstack(regions)
    return [both] if straight and _shown_plane(both, tolerance) is not None else None


def _meet_on_rock(ends: list[np.ndarray], tolerance: float, sight: Sight) -> bool:
    """Rule H5: the lines of two end regions (`ends`: each polyline from its end node) meet ahead of both
    ends, within `tolerance` of each other and of the mesh, as a straight trace's do where it bends across
    an edge of the rock."""
    a, b = ends[0][0], ends[1][0]
    ta, tb = (_outward(_end_region(e, BRIDGE_TANGENT * tolerance)) for e in ends)
    w, k = a - b, float(ta @ tb)
    denom = 1.0 - k * k
    if denom < 1e-9:  # parallel lines (a piece folded straight back) meet nowhere
        return False
    s, u = (k * (tb @ w) - ta @ w) / denom, (tb @ w - k * (ta @ w)) / denom
    p, q = a + s * ta, b + u * tb
    return bool(s > 0 and u > 0 and np.linalg.norm(p - q) <= tolerance
                and sight.distance((p + q) / 2) <= tolerance)


def _shown_plane(points: np.ndarray, tolerance: float) -> np.ndarray | None:
    """The unit normal of the plane a curve (N ≥ 3, 3) shows, or None if it is too straight to show one
    (rule H2)."""
    _, spread, axes = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    shown = spread[1] >= max(PLANE_SIGNAL * spread[2], PLANE_SPREAD * tolerance * np.sqrt(len(points)))
    return axes[2] if shown else None


# ---------------------------------------------------------------------------------------------------------
# merging a pair


def merge_pair(a: Trace3D, b: Trace3D, *, tolerance: float, smoothing_sigma: float | None = None,
               max_angle: float = 15.0, sight: Sight | None = None) -> Trace3D:
    """One trace from two: centroid averaging where they overlap, a spline bridge where they do not.

    tolerance : overlap distance (m), about 2–3 × the registration or ray-casting error (MATHS §5).
    smoothing_sigma : expected positional noise (m) of the bridge spline, s = m·σ²; default tolerance / 3.
    sight : the survey; with it, a bridge across a gap no photo shows (rules H1–H3, with `max_angle`) is
        laid on the rock where the pieces' plane cuts the mesh.
    The result has id 0 (the project assigns ids), the union of the images and parent 2D traces, the ids it
    replaces in `extra["merged_from"]`, per-vertex provenance wherever a vertex comes from an original one
    (bridge vertices have image_index −1, uv NaN and face −1), and each end censored only if censored in
    every source that covers it. Traces of two kinds raise InputError.
    """
    _check_tolerance(tolerance)
    sigma = tolerance / 3 if smoothing_sigma is None else float(smoothing_sigma)
    if not (np.isfinite(sigma) and sigma >= 0):
        raise InputError(None, f"smoothing_sigma={smoothing_sigma!r}: expected a noise level ≥ 0 m")
    _check_trace(a)
    _check_trace(b)
    if a.id and a.id == b.id:
        raise InputError(None, f"trace {a.id} cannot be merged with itself")
    if a.kind != b.kind:
        raise InputError(None, f"trace {a.id} is {a.kind}, trace {b.id} {b.kind}: traces of two kinds are never one "
                               "trace; give them one kind first")
    merged, _ = _merge(_Weighted.of(a), _Weighted.of(b), tolerance, sigma, max_angle, sight)
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


def _merge(a: _Weighted, b: _Weighted, tolerance: float, sigma: float, max_angle: float = 15.0,
           sight: Sight | None = None) -> tuple[Trace3D, np.ndarray]:
    """The merged trace and its per-vertex support; with the survey (`sight`), a bridge across a hidden gap
    follows the rock (`_bridge`)."""
    ov = _overlap(a.trace.points, b.trace.points, tolerance)
    if not ov.overlaps:
        for t in (a.trace, b.trace):
            if _closed(t.points):
                raise InputError(None, f"trace {t.id or 'merged'} is a closed loop and the other trace does not "
                                       f"overlap it within {tolerance:g} m: a loop has no end to bridge from")
        return _bridge(a, b, tolerance, sigma, max_angle, sight)
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


def _bridge(a: _Weighted, b: _Weighted, tolerance: float, sigma: float, max_angle: float = 15.0,
            sight: Sight | None = None) -> tuple[Trace3D, np.ndarray]:
    """Join two non-overlapping traces across their nearest ends with a smoothing spline (MATHS §5). Across
    a gap wider than rules B1–B4 bridge, given the survey (`sight`), the bridge instead follows the path
    where the pieces' common plane cuts the mesh (`_rock_cut`): the trace lies on the rock, and a spline
    across a bench edge or behind a buttress would cut through rock or air."""
    ends = [(np.linalg.norm(a.trace.points[i] - b.trace.points[j]), i, j) for i in (0, -1) for j in (0, -1)]
    _, i, j = min(ends, key=lambda e: e[0])
    first = a if i == -1 else a.reversed()  # first ends where second begins
    second = b if j == 0 else b.reversed()
    p, q = first.trace.points, second.trace.points
    gap = float(np.linalg.norm(q[0] - p[-1]))
    spacing = float(np.median(np.concatenate([np.linalg.norm(np.diff(x, axis=0), axis=1) for x in (p, q)])))
    n_new = max(int(np.ceil(gap / spacing)) - 1, 0) if spacing > 0 else 0
    bridge = _spline_bridge(p, q, n_new, max(gap, BRIDGE_WINDOW * spacing), sigma)
    cut = _rock_cut(p, q, tolerance, max_angle, sight) if len(bridge) and sight is not None else None
    if cut is not None and len(cut):
        bridge = resample_polyline(np.vstack([p[-1], cut, q[0]]), spacing)[0][1:-1]
        n_new = len(bridge)
    points = np.vstack([p, bridge, q])
    source = np.repeat([0, 2, 1], [len(p), n_new, len(q)])
    vertex = np.concatenate([np.arange(len(p)), np.zeros(n_new, int), np.arange(len(q))])
    merged = _assemble([first.trace, second.trace], points, source, vertex, tolerance)
    return merged, np.concatenate([first.support, np.ones(n_new), second.support])


def _rock_cut(p: np.ndarray, q: np.ndarray, tolerance: float, max_angle: float, sight: Sight) -> np.ndarray | None:
    """Where the common plane of p's and q's end regions cuts the mesh in the gap from p[-1] to q[0], if the
    gap is wider than rules B1–B4 bridge and the pieces show a plane that is not the outcrop surface's; else
    None. Whether the pieces are one fracture is for the merge rules (or the user) to say: this is only
    where the trace between them must lie, on the rock rather than through it or through air."""
    jt = _joint(p, q, tolerance)
    if _bridgeable(jt, tolerance, max_angle):
        return None
    regions = [_end_region(e, BRIDGE_PLANE * tolerance) for e in (p[::-1], q)]
    both = np.vstack(regions)
    if _shown_plane(both, tolerance) is None \
            or surface_planes([both], [eigen_orientation(both)], sight.mesh).any():
        return None
    return _plane_cut(regions, jt, tolerance, sight)


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
    edge_px = {image: px for t in sources for image, px in t.extra.get(EDGE_PX_KEY, {}).items()}
    return Trace3D(0, points, uv, face, image_index, images, kind=sources[0].kind,
                   parents=tuple(sorted({p for t in sources for p in t.parents})),
                   set_id=set_ids.pop() if len(set_ids) == 1 else -1,
                   term_start=_merged_end(points[0], ends, tolerance),
                   term_end=_merged_end(points[-1], ends, tolerance),
                   extra={"merged_from": sorted({i for t in sources for i in _replaced_ids(t)}),
                          **({EDGE_PX_KEY: edge_px} if edge_px else {})})


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

    A cut end becomes unclassified (""); an end kept keeps its termination; the orientation is cleared (it was
    fitted to the whole trace). At least 2 vertices must remain.
    """
    n = len(trace.points)
    lo, hi, _ = slice(start, stop).indices(n)
    if hi - lo < 2:
        raise InputError(None, f"trace {trace.id}: trimming to vertices [{start}, {stop}) of {n} leaves "
                               f"{max(hi - lo, 0)}; expected 0 ≤ start < stop − 1 ≤ {n - 1}")
    sl = slice(lo, hi)
    return unoriented(replace(trace, points=trace.points[sl], uv=trace.uv[sl], face=trace.face[sl],
                              image_index=trace.image_index[sl], term_start=trace.term_start if lo == 0 else "",
                              term_end=trace.term_end if hi == n else ""))


# ---------------------------------------------------------------------------------------------------------
# automatic merging


def suggest_merges(traces: Sequence[Trace3D], *, tolerance: float, min_fraction: float = 0.5,
                   max_angle: float = 15.0, sight: Sight | None = None,
                   review: bool = False) -> list[MergeSuggestion]:
    """Pairs of traces that look like one fracture, best first: duplicates seen in overlapping photos (kind
    "overlap", rules 1–5) and pieces seen end to end (kind "bridge", rules B1–B5, or H1–H5 across a gap that
    no photo of `sight` shows; module docstring).

    tolerance : overlap distance (m), about 2–3 × the registration or ray-casting error.
    min_fraction : rule 1, share of the shorter trace's length along the other (0–1).
    max_angle : rules 2 and B2–B3, degrees between the traces' directions along the overlap, or off straight
        across a joint.
    sight : the survey (mesh, cameras, ray tracer, local frame); without it only rules B1–B5 bridge. What a
        photo would show (rule H3) is judged with the `edge_px` the traces record for it.
    review : with the survey, also list pieces that may continue each other across a gap no photo shows
        but that the rules leave apart (kind "candidate", scored below every bridge, the reason saying
        which evidence is missing): for the user to judge in the photos; and, survey or not, duplicates of
        two kinds (kind "kinds", scored below those). `auto_merge` never takes them.
    Traces of two kinds (a fracture and bedding, `engine.traces.KINDS`) are never paired otherwise. Traces that cannot
    be merged (fewer than 3 vertices) are left out; ids must be unique; NaN coordinates raise InputError.
    """
    return _suggest(traces, tolerance, min_fraction, max_angle, _as_extracted(sight, traces), review)[0]


def _as_extracted(sight: Sight | None, traces: Sequence[Trace3D]) -> Sight | None:
    """`sight` judging what each photo would show with the `edge_px` its traces were extracted with, where
    they record it (engine.extract.EDGE_PX_KEY): a photo extracted with edge_px 0 places trace pixels on
    occluding edges, so a gap it sees there is not hidden."""
    if sight is None:
        return None
    edge_px = {**sight.edge_px, **extracted_edge_px(traces)}
    return sight if edge_px == dict(sight.edge_px) else replace(sight, edge_px=edge_px)


def _suggest(traces: Sequence[Trace3D], tolerance: float, min_fraction: float, max_angle: float,
             sight: Sight | None, review: bool = False) -> tuple[list[MergeSuggestion], set[frozenset[int]]]:
    """`suggest_merges`, and the pairs among them bridged by rule H5 (id pairs)."""
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
    samples = _Samples.of(usable, tolerance)
    rules = _Rules(tolerance, min_fraction, max_angle, 0.0, samples, _Photos.of(usable), sight)
    out, overlaps = [], {}
    for i, j in samples.near_pairs(tolerance):
        a, b = usable[i], usable[j]
        if a.kind != b.kind and not review:
            continue
        ov = overlaps[i, j] = _overlap(a.points, b.points, tolerance)
        if _duplicates(a, b, ov, rules):
            found = _suggestion(a.id, b.id, ov, tolerance, min_fraction)
            out.append(found if a.kind == b.kind else _kinds_differ(a, b, found))
    duplicates = DisjointSet(ids)
    for s in out:
        if s.kind == "overlap":
            duplicates.merge(s.a_id, s.b_id)
    straight, ends = [], []
    # a trace with any share along another has samples (every tolerance / 2) within 1.5 tolerances of the
    # other's; pairs farther apart overlap nothing, and the wide reach of rule H1 brings many of them
    close = set(samples.near_pairs(1.5 * tolerance))
    for i, j in _end_pairs(usable, (BRIDGE_REACH if sight is None else HIDDEN_REACH) * tolerance):
        a, b = usable[i], usable[j]
        if a.kind != b.kind:
            continue
        if (i, j) in close:
            ov = overlaps[i, j] if (i, j) in overlaps else _overlap(a.points, b.points, tolerance)
            if max(ov.fraction_ab, ov.fraction_ba) >= min_fraction:
                continue  # rule 1 decides between duplicates and near misses
        if duplicates.connected(a.id, b.id):
            continue  # duplicates need no bridge
        jt = _joint(a.points, b.points, tolerance)
        exclude = duplicates.subset(a.id) | duplicates.subset(b.id)
        hidden = _bridge_kind(a.points, b.points, jt, rules, exclude)
        if hidden is not None:
            out.append(_bridge_suggestion(a.id, b.id, jt, tolerance, max_angle, hidden))
            ends.append(((a.id, jt.a_end), (b.id, jt.b_end)))
        elif sight is not None and _bridge_kind(a.points, b.points, jt, rules, exclude, straight=True):
            straight.append((a.id, b.id, jt))
            ends.append(((a.id, jt.a_end), (b.id, jt.b_end)))
        elif review and sight is not None and (doubt := _doubt(a.points, b.points, jt, rules, exclude)):
            out.append(_candidate(a.id, b.id, jt, tolerance, doubt))
    rivalled = [(a, b, jt) for a, b, jt in straight
                if not _unrivalled(((a, jt.a_end), (b, jt.b_end)), ends, duplicates)]
    straight = [x for x in straight if x not in rivalled]
    out += [_bridge_suggestion(a, b, jt, tolerance, max_angle, True, True) for a, b, jt in straight]
    if review:
        out += [_candidate(a, b, jt, tolerance, "another piece could continue one of them (rule H5)")
                for a, b, jt in rivalled]
    return sorted(out, key=lambda s: (-s.score, s.a_id, s.b_id)), {frozenset((a, b)) for a, b, _ in straight}


def _kinds_differ(a: Trace3D, b: Trace3D, found: MergeSuggestion) -> MergeSuggestion:
    """Duplicates of two kinds for the user to settle, scored below every other suggestion (under 0.05)."""
    reason = (f"{found.reason}, but trace {a.id} is {a.kind} and trace {b.id} {b.kind}: give them one kind "
              "(`tracemap kind`, or Kind → Make selected traces) and they merge")
    return MergeSuggestion(a.id, b.id, 0.05 * found.score, reason, kind="kinds")


def _doubt(pa: np.ndarray, pb: np.ndarray, jt: Joint, rules: _Rules, exclude: set[int]) -> str | None:
    """Why the rules leave apart two pieces that may be one fracture across a gap no photo shows, or None if
    nothing says they may be. They may be if the gap is wider than B1's reach with little overlap back
    (H1), both end regions together show a plane that is not the outcrop surface's, and that plane's path
    along the rock joins the ends, hidden (H3) and clear of other traces (H4). What is missing is the
    evidence that it is one plane: a straight piece shows none (H2), and the pieces of an undulating
    fracture across a 0.5–1 m gap fit one plane little better than two fractures' pieces do (B4: on the
    synthetic outcrops, same and different fractures interleave over 0–15 mm of excess)."""
    tol = rules.tolerance
    if jt.gap <= BRIDGE_REACH * tol or jt.back > tol:
        return None
    regions = [_end_region(e, BRIDGE_PLANE * tol) for e in (_from_end(pa, jt.a_end), _from_end(pb, jt.b_end))]
    both = np.vstack(regions)
    if _shown_plane(both, tol) is None \
            or surface_planes([both], [eigen_orientation(both)], rules.sight.mesh).any():
        return None
    cut = _plane_cut(regions, jt, tol, rules.sight)
    if cut is None or len(cut) and rules.sight.shows(cut, tol).mean() > HIDDEN_SEEN \
            or rules.samples.near(cut, tol, exclude):
        return None
    if jt.plane_excess > PLANE_EXCESS * tol:
        return (f"their end regions fit one plane {jt.plane_excess * 1000:.0f} mm RMS worse than each fits its "
                f"own (rule B4)")
    normals = [_shown_plane(r, tol) for r in regions]
    if normals[0] is None or normals[1] is None:
        return "a piece is too straight to show its own plane (rule H2)"
    if (angle := _axial_angle(normals[0], normals[1])) > rules.max_angle:
        return f"the planes they show are {angle:.0f}° apart (rule H2)"
    return "a piece's own plane is the outcrop surface's (rule H2)"


def _candidate(a_id: int, b_id: int, jt: Joint, tolerance: float, doubt: str) -> MergeSuggestion:
    """A pair for the user to judge, scored 1/20 to 1/10 by the width of the gap (below every bridge)."""
    reason = (f"trace {b_id} may continue trace {a_id} across a {jt.gap * 1000:.0f} mm gap that no photo shows "
              f"(ends {jt.angle:.0f}° apart, nothing crossing the gap), but {doubt}: judge it in the photos")
    return MergeSuggestion(a_id, b_id, float(0.1 * (1 - jt.gap / (2 * HIDDEN_REACH * tolerance))), reason,
                           kind="candidate")


def _unrivalled(pair: tuple[tuple[int, int], tuple[int, int]], ends: list[tuple[tuple[int, int], tuple[int, int]]],
                duplicates: DisjointSet) -> bool:
    """Rule H5's last condition: every bridge candidate at either end of `pair` ((id, end) each) continues
    it with a duplicate of the same trace."""
    for end in pair:
        partners = {q[0] for p, q in ends if p == end} | {p[0] for p, q in ends if q == end}
        if len({duplicates[i] for i in partners}) > 1:
            return False
    return True


@dataclass(frozen=True)
class _Samples:
    """All traces resampled every tolerance / 2 in one KD-tree, each sample labelled with its trace's
    index (`owner`) and id."""

    tree: cKDTree
    owner: np.ndarray
    ids: np.ndarray

    @classmethod
    def of(cls, traces: Sequence[Trace3D], tolerance: float) -> _Samples:
        points = [resample_polyline(t.points, tolerance / 2)[0] for t in traces]
        owner = np.repeat(np.arange(len(points)), [len(p) for p in points])
        ids = np.array([t.id for t in traces], dtype=np.int64)
        return cls(cKDTree(np.vstack(points) if points else np.zeros((0, 3))), owner, ids[owner])

    def near_pairs(self, tolerance: float) -> list[tuple[int, int]]:
        """Index pairs (i < j) of traces that come within about `tolerance` of each other (MATHS §5 step 2)."""
        pairs = self.tree.query_pairs(tolerance, output_type="ndarray")
        return _unique_pairs(self.owner[pairs[:, 0]], self.owner[pairs[:, 1]])

    def crossed(self, p: np.ndarray, q: np.ndarray, tolerance: float, exclude: set[int]) -> bool:
        """Rule B5: a trace not in `exclude` (ids) comes within `tolerance` of the segment p–q."""
        return self.near(resample_polyline(np.vstack([p, q]), tolerance / 2)[0], tolerance, exclude)

    def near(self, points: np.ndarray, tolerance: float, exclude: set[int]) -> bool:
        """A trace not in `exclude` (ids) comes within `tolerance` of one of `points` (rule H4)."""
        if not len(points):
            return False
        near = np.concatenate(self.tree.query_ball_point(points, tolerance)).astype(np.int64)
        return bool(set(self.ids[near].tolist()) - exclude)


def _end_pairs(traces: Sequence[Trace3D], reach: float) -> list[tuple[int, int]]:
    """Index pairs (i < j) of open traces with end nodes within `reach` (m) of each other (rule B1)."""
    open_ = [k for k, t in enumerate(traces) if not _closed(t.points)]
    if not open_:
        return []
    owner = np.repeat(open_, 2)
    pairs = cKDTree(np.vstack([traces[k].points[[0, -1]] for k in open_])).query_pairs(reach, output_type="ndarray")
    return _unique_pairs(owner[pairs[:, 0]], owner[pairs[:, 1]])


def _unique_pairs(i: np.ndarray, j: np.ndarray) -> list[tuple[int, int]]:
    """The distinct pairs (min, max) of two labels, without self-pairs."""
    keep = i != j
    unique = np.unique(np.sort(np.column_stack([i[keep], j[keep]]), axis=1).reshape(-1, 2), axis=0)
    return [(int(a), int(b)) for a, b in unique]


def _passes(ov: Overlap, tolerance: float, min_fraction: float, max_angle: float) -> bool:
    return ((max(ov.fraction_ab, ov.fraction_ba) >= min_fraction or ov.end_to_end) and not ov.angle > max_angle
            and ov.separation <= tolerance / 2 and ov.divergence <= DIVERGENCE * ov.overlap_length)


def _duplicates(a: Trace3D, b: Trace3D, ov: Overlap, rules: _Rules) -> bool:
    """Rules 1–5 for traces `a` and `b` overlapping as `ov`. Where they overlap end to end and neither lies
    mostly along the other, rule 5 also holds for every trace along the overlap: no photo shows two traces
    there. The traces of two fractures taking over from each other along a few centimetres look, in 3D,
    like one trace seen in part by each photo; only a photo showing both tells them apart (seen on planar
    synthetic outcrop 8: two fractures' traces 5 mm apart for 27 cm, each photo showing both)."""
    tol = rules.tolerance
    if not _passes(ov, tol, rules.min_fraction, rules.max_angle) or _same_photo(a, b, tol):
        return False
    if max(ov.fraction_ab, ov.fraction_ba) >= rules.min_fraction:
        return True
    span = resample_polyline(a.points[ov.a_range[0]:ov.a_range[1] + 1], tol / 2)[0]
    return not rules.photos.two_along(span, tol)


@dataclass(frozen=True)
class _Photos:
    """Every trace's vertices by the photo they came from, one KD-tree each, labelled with the trace's id."""

    trees: dict[str, tuple[cKDTree, np.ndarray]]

    @classmethod
    def of(cls, traces: Sequence[Trace3D]) -> _Photos:
        points: dict[str, list[np.ndarray]] = {}
        ids: dict[str, list[np.ndarray]] = {}
        for t in traces:
            for k, name in enumerate(t.images):
                mine = t.points[t.image_index == k]
                points.setdefault(name, []).append(mine)
                ids.setdefault(name, []).append(np.full(len(mine), t.id, dtype=np.int64))
        return cls({name: (cKDTree(np.vstack(points[name])), np.concatenate(ids[name])) for name in points})

    def two_along(self, samples: np.ndarray, tolerance: float) -> bool:
        """Some photo shows two traces each within `tolerance` of three or more of `samples` (points every
        `tolerance` / 2: a stretch of over `tolerance`)."""
        for tree, ids in self.trees.values():
            counts: dict[int, int] = {}
            for near in tree.query_ball_point(samples, tolerance):
                for i in set(ids[near].tolist()):
                    counts[i] = counts.get(i, 0) + 1
            if sum(n >= 3 for n in counts.values()) >= 2:
                return True
        return False


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


def _suggestion(a_id: int, b_id: int, ov: Overlap, tolerance: float, min_fraction: float) -> MergeSuggestion:
    share, covered, other = ((ov.fraction_ba, b_id, a_id) if ov.fraction_ba >= ov.fraction_ab
                             else (ov.fraction_ab, a_id, b_id))
    where = (f"traces {a_id} and {b_id} overlap end to end for {ov.overlap_length * 500:.0f} mm within "
             f"{tolerance:g} m" if share < min_fraction else
             f"{share:.0%} of trace {covered} lies within {tolerance:g} m along trace {other}")
    direction = "too short for a direction" if np.isnan(ov.angle) else f"directions {ov.angle:.1f}° apart"
    reason = f"{where}: mean gap {ov.separation * 1000:.1f} mm, {direction}"

    return MergeSuggestion(a_id, b_id, float(share * (1 - ov.separation / tolerance)), reason)


def _bridge_kind(pa: np.ndarray, pb: np.ndarray, jt: Joint, rules: _Rules, exclude: set[int], *,
                 straight: bool = False) -> bool | None:
    """None if the pair is no bridge; else whether the bridge crosses a hidden gap (rules H1–H4, or H5 with
    `straight`) rather than a narrow one (B1–B5). `exclude`: ids of traces that do not count as crossing
    the gap."""
    a_end, b_end = pa[jt.a_end], pb[jt.b_end]
    if _bridgeable(jt, rules.tolerance, rules.max_angle):
        return None if rules.samples.crossed(a_end, b_end, rules.tolerance, exclude) else False
    if rules.sight is None:
        return None
    cut = _hidden_gap(pa, pb, jt, rules.tolerance, rules.max_angle, rules.sight, straight=straight)
    return None if cut is None or rules.samples.near(cut, rules.tolerance, exclude) else True


def _bridge_suggestion(a_id: int, b_id: int, jt: Joint, tolerance: float, max_angle: float,
                       hidden: bool, straight: bool = False) -> MergeSuggestion:
    """A bridge across a narrow gap scores ¼ to 1: halved at the widest gap, halved again at the sharpest
    joint; across a hidden gap, ⅛ to ¼ by width (less evidence: nothing was seen between the pieces)."""
    if hidden:
        reason = (f"trace {b_id} continues trace {a_id} in one plane across a {jt.gap * 1000:.0f} mm gap that no "
                  f"photo shows: ends {jt.angle:.1f}° apart, nothing crossing the gap"
                  + (", nothing else continuing either piece" if straight else ""))
        return MergeSuggestion(a_id, b_id, float(0.25 * (1 - jt.gap / (2 * HIDDEN_REACH * tolerance))), reason,
                               kind="bridge")
    reason = (f"trace {b_id} continues trace {a_id} end to end across a {jt.gap * 1000:.0f} mm gap: ends "
              f"{jt.angle:.1f}° off straight, {jt.offset * 1000:.1f} mm off line, nothing crossing the gap")
    score = (1 - jt.gap / (2 * BRIDGE_REACH * tolerance)) * (1 - jt.angle / (2 * max_angle) if max_angle else 1)
    return MergeSuggestion(a_id, b_id, float(score), reason, kind="bridge")


def auto_merge(traces: Sequence[Trace3D], *, tolerance: float, min_fraction: float = 0.5,
               max_angle: float = 15.0, smoothing_sigma: float | None = None,
               sight: Sight | None = None) -> MergeResult:
    """Merge every group of duplicates and pieces that `suggest_merges` links (union–find, so chains merge
    together).

    Each group is merged starting from its longest trace, adding the member sharing the most length with
    the merged trace while one passes rules 1–5 against it, else the nearest one passing rules B1–B5 (a
    bridge); the members left over are merged among themselves the same way. Merged traces take the place
    of their group's first member; components are relabelled over the result. `sight` (the survey) lets
    pieces be bridged across gaps that no photo shows (rules H1–H5). The result is merged again until
    nothing more merges: a merged trace, longer and averaged, can pass a rule its pieces failed (one to
    two more merges on 4 of 23 noisy synthetic outcrops, none of two fractures), and merging the result
    again changes nothing.
    """
    sigma = tolerance / 3 if smoothing_sigma is None else float(smoothing_sigma)
    sight = _as_extracted(sight, traces)
    current, origin = list(traces), {}  # origin: temporary id of a merged trace → the input ids it replaces
    fresh = max((t.id for t in traces), default=0) + 1  # temporary ids above every input id
    while True:
        current, merged = _merge_pass(current, tolerance, min_fraction, max_angle, sigma, sight)
        if not merged:
            break
        for k in merged:  # name each new merge (ids must be unique to be suggested) by the inputs it replaces
            t = current[k]
            ids = sorted({j for i in t.extra["merged_from"] for j in origin.get(i, [i])})
            origin[fresh] = ids
            current[k] = replace(t, id=fresh, extra={**t.extra, "merged_from": ids})
            fresh += 1
    out = [replace(t, id=0) if t.id in origin else t for t in current]
    groups = sorted(tuple(origin[t.id]) for t in current if t.id in origin)
    skipped = [(t.id, problem) for t in traces if (problem := _problem(t)) is not None]
    return MergeResult(relabel_components(out, tolerance), groups, skipped)


def _merge_pass(traces: list[Trace3D], tolerance: float, min_fraction: float, max_angle: float, sigma: float,
                sight: Sight | None) -> tuple[list[Trace3D], list[int]]:
    """One round of `auto_merge`: the traces with each merged group in the place of its first member (id 0),
    and the positions of the merged traces."""
    suggestions, straight = _suggest(traces, tolerance, min_fraction, max_angle, sight)
    usable = [t for t in traces if _problem(t) is None]
    rules = _Rules(tolerance, min_fraction, max_angle, sigma, _Samples.of(usable, tolerance), _Photos.of(usable),
                   sight, straight)
    by_id = {t.id: t for t in traces}
    groups = DisjointSet(by_id)
    for s in suggestions:
        groups.merge(s.a_id, s.b_id)
    position = {t.id: k for k, t in enumerate(traces)}
    replaced: dict[int, Trace3D | None] = {}
    for members in groups.subsets():
        if len(members) < 2:
            continue
        for merged, used in _merge_group([by_id[i] for i in members], rules):
            if len(used) > 1:
                replaced.update({i: None for i in used})
                replaced[min(used, key=position.__getitem__)] = merged
    out = [t for t in (replaced.get(t.id, t) for t in traces) if t is not None]
    new = {id(t) for t in replaced.values() if t is not None}
    return out, [k for k, t in enumerate(out) if id(t) in new]


@dataclass(frozen=True)
class _Rules:
    """What pairs are checked against: the suggestion settings, the bridge spline's noise level, every
    trace's samples (rules B5, H4) and vertices by photo (rule 5 along an end-to-end overlap), the survey
    (rules H1–H3), if known, and the pairs rule H5 bridges."""

    tolerance: float
    min_fraction: float
    max_angle: float
    sigma: float
    samples: _Samples
    photos: _Photos
    sight: Sight | None = None
    straight: set[frozenset[int]] = field(default_factory=set)


def _merge_group(members: list[Trace3D], rules: _Rules) -> list[tuple[Trace3D, list[int]]]:
    """Merge a group of linked traces greedily: from the longest, add the next member (`_next_member`)
    while there is one; the rest start again. Returns (merged trace, ids)."""
    pending = sorted(members, key=lambda t: -t.surface_length)
    group = {t.id for t in members}
    out = []
    while pending:
        current = _Weighted.of(pending.pop(0))
        used = [current.trace.id]
        while (k := _next_member(current.trace, used, pending, group, rules)) is not None:
            trace = pending.pop(k)
            merged, support = _merge(current, _Weighted.of(trace), rules.tolerance, rules.sigma, rules.max_angle,
                                     rules.sight)
            current = _Weighted(merged, support)
            used.append(trace.id)
        out.append((current.trace, used))
    return out


def _next_member(current: Trace3D, used: list[int], pending: list[Trace3D], group: set[int],
                 rules: _Rules) -> int | None:
    """Index of the pending trace sharing the most length with `current` (merged from `used`) under rules
    1–5, else of the one nearest its end under rules B1–B5 or H1–H4, or H5 if it was suggested with one of
    `used` (traces of the group do not count as crossing the gap), else None."""
    tol = rules.tolerance
    overlaps, bridges = [], []
    for k, t in enumerate(pending):
        ov = _overlap(current.points, t.points, tol)
        if _passes(ov, tol, rules.min_fraction, rules.max_angle):
            if _duplicates(current, t, ov, rules):
                overlaps.append((ov.overlap_length, k))
        elif max(ov.fraction_ab, ov.fraction_ba) < rules.min_fraction and not _closed(current.points) \
                and not _closed(t.points):
            jt = _joint(current.points, t.points, tol)
            straight = any(frozenset((i, t.id)) in rules.straight for i in used)
            if _bridge_kind(current.points, t.points, jt, rules, group, straight=straight) is not None:
                bridges.append((-jt.gap, k))
    best = max(overlaps, default=None) or max(bridges, default=None)
    return None if best is None else best[1]


def relabel_components(traces: Sequence[Trace3D], tolerance: float) -> list[Trace3D]:
    """The traces with `component` set to their connected group (traces touching within `tolerance`, m),
    numbered by size, 0 the largest (engine.topology.connectivity), as the analysis labels them: over the
    fracture network, bedding in none (−1). Run it after every merge."""
    fractures = network(traces)
    labels = dict(zip(map(id, fractures), connectivity(fractures, tolerance).labels if fractures else []))
    return [replace(t, component=int(labels.get(id(t), -1))) for t in traces]


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
