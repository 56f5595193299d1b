"""Terminations (B/T/X/C), nodes and connectivity of a trace network (MATHS §6).

Vocabulary: the paper's B blind, T abutting, X crossing and C censored are Sanderson & Nixon's (2015) I, Y
and X nodes and fractopo's E (edge) node: B→I, T→Y, C→E. (In S&N branch names such as I–C, C means
*connected*, not censored.)

Each end node gets one code, from the first rule that holds (MATHS §6, DECISION (i)+(ii)+(iii)):

* C: the end lies within δ of the mesh boundary (its border or the rim of a hole); or, in every photo of
  the trace that sees it, within `border_px` of the photo border or of a masked region; or the trace's
  continuation just past the end is hidden from every photo of the trace (occluded, or the line of sight
  slides off a ledge onto a surface behind it).
* T: the end lies within δ of another trace's interior and farther than δ from that trace's end nodes,
  or within δ of a boundary trace (bedding: `boundaries`), which bounds the network without being in it.
* B: anything else.

X is not an end code: a crossing is an interior node where two traces come within δ of each other with
both closest points farther than δ from their own ends. In 3D, traces on a mesh almost never meet exactly,
so one tolerance δ = `scale` × ground sampling distance (default 2.5 GSD) serves every rule.

The geometry is dimension-free: a trace is a `Trace3D` or an (N, D) polyline, so the same rules serve
3D traces on the mesh and 2D traces on a map (engine.maps2d).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import chain

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from engine.cameras import Camera
from engine.errors import InputError
from engine.mesh import Mesh
from engine.raytrace import RayTracer
from engine.traces import Trace3D

TOLERANCE_SCALE = 2.5
"""δ = TOLERANCE_SCALE × ground sampling distance: MATHS §6 asks for 2–3 GSD."""

BORDER_PX = 3.0
"""Default δ_px: an end this close (pixels) to the photo border or a mask is censored in that photo."""

END_CODES = ("B", "T", "C")
ENDS = ("start", "end")
SOURCE_KEY = "termination_source"
"""Trace3D.extra key: {"start"|"end": "manual"|"auto"}. An end without a source (e.g. a cut made by
extraction) keeps a "C" and is classified otherwise."""

TraceLike = Trace3D | np.ndarray


@dataclass(frozen=True)
class Crossings:
    """X nodes: `traces` (K, 2) the indices i < j of the two traces, `points` (K, D) the midpoint of
    their closest approach and `distance` (K,) its length."""

    traces: np.ndarray
    points: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return len(self.distance)


@dataclass(frozen=True)
class NodeCounts:
    """End codes and S&N nodes with fractopo's topology parameters (MATHS §6).

    N_I = B, N_Y = T, N_X = X crossings, N_E = C; censored ends are left out of N_L and N_B:
    N_L = (N_I + N_Y)/2, N_B = (N_I + 3N_Y + 4N_X)/2, C_L = 2(N_Y + N_X)/N_L, C_B = (3N_Y + 4N_X)/N_B
    (0 when N_L or N_B is 0, as fractopo). `proportions` are P_I, P_Y, P_X of I + Y + X (ternary plot);
    `censored_fraction` is C over all ends, a quality flag.
    """

    B: int
    T: int
    X: int
    C: int
    N_I: int
    N_Y: int
    N_X: int
    N_E: int
    N_L: float
    N_B: float
    C_L: float
    C_B: float
    proportions: dict[str, float]
    censored_fraction: float


@dataclass(frozen=True)
class Connectivity:
    """Connected groups of traces that touch or cross (within δ).

    `labels` (n,) gives each trace's group, numbered by size (0 is the largest); `sizes` the number of
    traces per group; the largest group's share of all trace vertices and of the total trace length.
    """

    labels: np.ndarray
    sizes: np.ndarray
    largest_vertex_fraction: float
    largest_length_fraction: float

    @property
    def n_components(self) -> int:
        return len(self.sizes)


@dataclass(frozen=True)
class Topology:
    """What `analyse_topology` found, with the tolerance δ (metres) it used; `abutting` (n, 2) is the trace
    each end lies against (`abutting_ends`), whatever its code, an index into the traces then the
    boundaries."""

    terminations: list[tuple[str, str]]
    abutting: np.ndarray
    crossings: Crossings
    nodes: NodeCounts
    connectivity: Connectivity
    tolerance: float


def analyse_topology(traces: Sequence[Trace3D], *, mesh: Mesh, gsd: float | None = None,
                     cameras: Mapping[str, Camera] | None = None, tracer: RayTracer | None = None,
                     scale: float = TOLERANCE_SCALE, border_px: float = BORDER_PX,
                     masks: Mapping[str, np.ndarray] | None = None,
                     boundaries: Sequence[Trace3D] = ()) -> Topology:
    """Terminations, crossings, node counts and connected groups of 3D traces (the topology of `tracemap
    analyse`), with δ = `scale` × `gsd`; `gsd` defaults to `ground_sampling_distance(traces, cameras)`.
    boundaries : traces the network's ends may abut that are not in it (bedding): their own ends, their
    crossings and the connections through them are not counted.

    Traces are not changed: store the results with `apply_terminations` and `apply_components`, then
    measure lengths with engine.lengths.length_table, which reads the censored ends from the traces.
    """
    if gsd is None:
        if cameras is None:
            raise InputError(None, "give the ground sampling distance (gsd) or the cameras to estimate it from")
        gsd = ground_sampling_distance(traces, cameras)
    tolerance = _positive(scale, "scale") * _positive(gsd, "gsd")
    codes = classify_terminations(traces, mesh=mesh, gsd=gsd, cameras=cameras, tracer=tracer, scale=scale,
                                  border_px=border_px, masks=masks, boundaries=boundaries)
    crossings = find_crossings(traces, tolerance)
    return Topology(codes, abutting_ends([*traces, *boundaries], tolerance)[:len(traces)], crossings,
                    node_counts(codes, crossings), connectivity(traces, tolerance), tolerance)


# -- terminations ------------------------------------------------------------------------------------

def classify_terminations(traces: Sequence[Trace3D], *, mesh: Mesh, gsd: float,
                          cameras: Mapping[str, Camera] | None = None, tracer: RayTracer | None = None,
                          scale: float = TOLERANCE_SCALE, border_px: float = BORDER_PX,
                          masks: Mapping[str, np.ndarray] | None = None,
                          boundaries: Sequence[Trace3D] = ()) -> list[tuple[str, str]]:
    """The (start, end) code of every trace by the rules of the module docstring; traces are not changed.

    mesh : the mesh the traces lie on (local frame). gsd : ground sampling distance, metres per pixel
        (`ground_sampling_distance`); δ = `scale` × gsd, metres.
    cameras : the photos (local frame) by name; without them the photo-border and occlusion tests are
        skipped. tracer : ray tracer of `mesh`; without it the occlusion test is skipped and a photo is
        taken to see an end wherever the end projects into the frame.
    border_px : δ_px, pixels. masks : optional boolean (H, W) image per photo, True where pixels are valid.
    boundaries : traces an end may abut (T) that get no codes themselves (bedding).
    Manual codes (`set_termination`) are kept, and so is a "C" of unknown source (extraction marks the
    ends it cut "C").
    """
    tolerance = _positive(scale, "scale") * _positive(gsd, "gsd")
    lines = _polylines(traces)
    ends = _end_points(lines)
    censored = _near_mesh_boundary(ends, mesh, tolerance)
    if cameras is not None:
        censored |= _at_photo_border(traces, ends, cameras, tracer, _positive(border_px, "border_px"), masks,
                                     tolerance)
        if tracer is not None:
            censored |= _continuation_hidden(traces, lines, ends, cameras, tracer, tolerance)
    abutting = abutting_ends([*lines, *_polylines(boundaries)], tolerance)[:len(lines)] >= 0
    auto = np.where(censored, "C", np.where(abutting, "T", "B"))
    return [(_kept(t, 0, auto[i, 0]), _kept(t, 1, auto[i, 1])) for i, t in enumerate(traces)]


def apply_terminations(traces: Sequence[Trace3D], codes: Sequence[tuple[str, str]]) -> None:
    """Write `codes` (from `classify_terminations`) into term_start/term_end, recording them as automatic."""
    if len(codes) != len(traces):
        raise InputError(None, f"{len(codes)} termination pairs for {len(traces)} traces")
    for trace, pair in zip(traces, codes):
        source = trace.extra.setdefault(SOURCE_KEY, {})
        for end, code in zip(ENDS, pair):
            _check_code(code, trace, end)
            unchanged = code == getattr(trace, _field(end))
            # a kept manual code or extraction cut keeps its source, so the next run keeps it again
            if not (unchanged and (source.get(end) == "manual" or (source.get(end) is None and code == "C"))):
                source[end] = "auto"
            setattr(trace, _field(end), code)


def set_termination(trace: Trace3D, end: str, code: str) -> None:
    """Manual edit: set the `end` ("start" or "end") of `trace` to `code` (B, T or C; "" clears the edit).

    A manual code survives later runs of `classify_terminations`; clearing it hands the end back to them.
    """
    if end not in ENDS:
        raise InputError(None, f"trace {trace.id}: end {end!r} must be 'start' or 'end'")
    source = trace.extra.setdefault(SOURCE_KEY, {})
    if code == "":
        source.pop(end, None)
    else:
        _check_code(code, trace, end)
        source[end] = "manual"
    setattr(trace, _field(end), code)


def abutting_ends(traces: Sequence[TraceLike], tolerance: float) -> np.ndarray:
    """(n, 2) index of the trace each end abuts (T), or -1.

    An end abuts trace j when it lies within `tolerance` of j and farther than `tolerance` from both of
    j's end nodes; of several such traces the nearest is given.
    """
    tolerance = _positive(tolerance, "tolerance")
    lines = _polylines(traces)
    ends = _end_points(lines)
    index = _trace_index(lines, tolerance)
    points = ends.reshape(-1, ends.shape[-1])
    own = np.repeat(np.arange(len(lines)), 2)
    pt, seg = _candidates(index, points, tolerance)
    other = index.owner[seg]
    keep = other != own[pt]
    pt, seg, other = pt[keep], seg[keep], other[keep]
    distance = np.linalg.norm(points[pt] - _closest_on_segments(points[pt], index.a[seg], index.b[seg]), axis=1)
    from_ends = np.linalg.norm(points[pt, None, :] - ends[other], axis=2).min(axis=1)
    ok = (distance <= tolerance) & (from_ends > tolerance)
    pt, other, distance = pt[ok], other[ok], distance[ok]
    order = np.argsort(-distance, kind="stable")  # nearest written last, so it wins
    out = np.full(len(points), -1)
    out[pt[order]] = other[order]
    return out.reshape(-1, 2)


def find_crossings(traces: Sequence[TraceLike], tolerance: float) -> Crossings:
    """X nodes: places where two traces come within `tolerance` with both closest points farther than
    `tolerance` from their own trace's end nodes (segment–segment closest approach, any dimension).

    Neighbouring segment pairs of one crossing (a shallow crossing in 3D touches over several segments)
    give one node, at the pair of least distance.
    """
    tolerance = _positive(tolerance, "tolerance")
    lines = _polylines(traces)
    ends = _end_points(lines)
    index = _trace_index(lines, tolerance)
    i, j, c1, c2, distance = _contacts(index, tolerance)
    ti, tj = index.owner[i], index.owner[j]
    interior = ((np.linalg.norm(c1[:, None] - ends[ti], axis=2).min(axis=1) > tolerance)
                & (np.linalg.norm(c2[:, None] - ends[tj], axis=2).min(axis=1) > tolerance))
    i, j, c1, c2, distance, ti, tj = (x[interior] for x in (i, j, c1, c2, distance, ti, tj))
    swap = ti > tj
    ti, tj = np.where(swap, tj, ti), np.where(swap, ti, tj)
    c_lo, i_lo = np.where(swap[:, None], c2, c1), np.where(swap, j, i)
    position = index.arc[i_lo] + np.linalg.norm(c_lo - index.a[i_lo], axis=1)  # along trace ti
    order = np.lexsort((position, tj, ti))
    ti, tj, position, distance = ti[order], tj[order], position[order], distance[order]
    mid = 0.5 * (c1 + c2)[order]
    gap = 2 * tolerance + 2 * index.reach  # contacts of one crossing are at most one piece apart
    new = np.ones(len(ti), dtype=bool)
    new[1:] = (np.diff(ti) != 0) | (np.diff(tj) != 0) | (np.diff(position) > gap)
    group = np.cumsum(new) - 1
    best = np.lexsort((distance, group))
    best = best[np.diff(group[best], prepend=-1) != 0]
    dim = lines[0].shape[1] if lines else 3
    return Crossings(np.column_stack([ti[best], tj[best]]).reshape(-1, 2), mid[best].reshape(-1, dim),
                     distance[best])


def node_counts(terminations: Sequence[tuple[str, str]], crossings: Crossings | int) -> NodeCounts:
    """B/T/X/C counts and the S&N/fractopo topology parameters (class docstring of NodeCounts)."""
    codes = list(chain.from_iterable(terminations))
    for k, code in enumerate(codes):
        if code not in END_CODES:
            what = ("has no termination code; run classify_terminations first" if code == ""
                    else f"has code {code!r}; end codes are B, T, C (X is a crossing, not an end)")
            raise InputError(None, f"trace {k // 2} ({ENDS[k % 2]}) {what}")
    b, t, c = (codes.count(x) for x in END_CODES)
    x = len(crossings) if isinstance(crossings, Crossings) else int(crossings)
    n_l = (b + t) / 2
    n_b = (b + 3 * t + 4 * x) / 2
    connected = b + t + x
    proportions = {name: (n / connected if connected else float("nan"))
                   for name, n in (("P_I", b), ("P_Y", t), ("P_X", x))}
    return NodeCounts(B=b, T=t, X=x, C=c, N_I=b, N_Y=t, N_X=x, N_E=c, N_L=n_l, N_B=n_b,
                      C_L=2 * (t + x) / n_l if n_l else 0.0, C_B=(3 * t + 4 * x) / n_b if n_b else 0.0,
                      proportions=proportions, censored_fraction=c / len(codes) if codes else float("nan"))


def connectivity(traces: Sequence[TraceLike], tolerance: float) -> Connectivity:
    """Groups of traces joined where they touch or cross within `tolerance` (any contact: T, X or end to end)."""
    tolerance = _positive(tolerance, "tolerance")
    lines = _polylines(traces)
    n = len(lines)
    index = _trace_index(lines, tolerance)
    i, j, *_ = _contacts(index, tolerance)
    graph = coo_matrix((np.ones(len(i)), (index.owner[i], index.owner[j])), shape=(n, n))
    _, raw = connected_components(graph, directed=False)
    sizes = np.bincount(raw)
    order = np.argsort(-sizes, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    labels = rank[raw]
    vertices = np.array([len(p) for p in lines], dtype=float)
    lengths = np.array([_length(p) for p in lines])
    largest = labels == 0
    return Connectivity(labels, sizes[order], float(vertices[largest].sum() / vertices.sum()) if n else float("nan"),
                        float(lengths[largest].sum() / lengths.sum()) if n else float("nan"))


def apply_components(traces: Sequence[Trace3D], result: Connectivity) -> None:
    """Write the group labels of `connectivity` into each trace's `component`."""
    if len(result.labels) != len(traces):
        raise InputError(None, f"{len(result.labels)} component labels for {len(traces)} traces")
    for trace, label in zip(traces, result.labels):
        trace.component = int(label)


def ground_sampling_distance(traces: Sequence[Trace3D], cameras: Mapping[str, Camera]) -> float:
    """Median size of one pixel on the surface (metres) over all trace vertices: distance to the camera of
    the vertex's photo over its focal length in pixels."""
    sizes = []
    for t in traces:
        for k, name in enumerate(t.images):
            camera = _camera(cameras, name, t)
            sel = t.image_index == k
            sizes.append(np.linalg.norm(t.points[sel] - camera.centre, axis=1) / camera.K[0, 0])
    if not sizes:
        raise InputError(None, "no trace vertices: the ground sampling distance needs at least one 3D trace")
    return float(np.median(np.concatenate(sizes)))


def near_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray, tolerance: float) -> np.ndarray:
    """True where a point (N, D) lies within `tolerance` of any segment a[k]→b[k] (M, D)."""
    points = np.asarray(points, dtype=float)
    out = np.zeros(len(points), dtype=bool)
    if len(a) == 0 or len(points) == 0:
        return out
    index = _build_index(np.asarray(a, dtype=float), np.asarray(b, dtype=float), np.zeros(len(a), int),
                         np.zeros(len(a)), tolerance)
    pt, seg = _candidates(index, points, tolerance)
    distance = np.linalg.norm(points[pt] - _closest_on_segments(points[pt], index.a[seg], index.b[seg]), axis=1)
    out[pt[distance <= tolerance]] = True
    return out


def _polylines(traces: Sequence[TraceLike]) -> list[np.ndarray]:
    """The vertex arrays of `traces`, checked: each (N ≥ 2, D) finite, of positive length, one D for all."""
    lines = []
    for k, t in enumerate(traces):
        name = f"trace {t.id}" if isinstance(t, Trace3D) else f"trace {k}"
        p = t.points if isinstance(t, Trace3D) else np.asarray(t, dtype=float)
        if p.ndim != 2 or len(p) < 2:
            raise InputError(None, f"{name} has {len(p)} vertex; a trace needs at least 2 vertices")
        if not np.all(np.isfinite(p)):
            raise InputError(None, f"{name} has NaN or infinite coordinates")
        if _length(p) == 0:
            raise InputError(None, f"{name} has zero length (all its vertices coincide)")
        if lines and p.shape[1] != lines[0].shape[1]:
            raise InputError(None, f"{name} has {p.shape[1]} coordinates per vertex, trace 0 has "
                                   f"{lines[0].shape[1]}")
        lines.append(p)
    return lines


# -- the C tests -------------------------------------------------------------------------------------

def _near_mesh_boundary(ends: np.ndarray, mesh: Mesh, tolerance: float) -> np.ndarray:
    edges = mesh.vertices[mesh.boundary_edges]
    return near_segments(ends.reshape(-1, 3), edges[:, 0], edges[:, 1], tolerance).reshape(-1, 2)


def _at_photo_border(traces: Sequence[Trace3D], ends: np.ndarray, cameras: Mapping[str, Camera],
                     tracer: RayTracer | None, border_px: float, masks: Mapping[str, np.ndarray] | None,
                     tolerance: float) -> np.ndarray:
    """True where the end is within `border_px` of the border or a mask in every photo of its trace that sees it.

    The photo an end vertex came from sees it at its recorded pixel; another photo of the trace sees it
    where it projects into the frame (and, with a tracer, is not hidden by the mesh).
    """
    near = np.ones(ends.shape[:2], dtype=bool)
    for name in sorted({image for t in traces for image in t.images}):
        rows = np.array([(i, k) for i, t in enumerate(traces) if name in t.images for k in (0, 1)])
        camera = _camera(cameras, name, traces[rows[0, 0]])
        points = ends[rows[:, 0], rows[:, 1]]
        uv = camera.project(points)
        own = np.zeros(len(rows), dtype=bool)
        for r, (i, k) in enumerate(rows):
            t, vertex = traces[i], (0, -1)[k]
            if t.images[t.image_index[vertex]] == name:
                uv[r], own[r] = t.uv[vertex], True
        sees = own | (np.all(np.isfinite(uv), axis=1) & (_clearance(uv, camera, None) > 0))
        if tracer is not None:
            other = np.flatnonzero(sees & ~own)
            sees[other] = ~tracer.occluded(camera.centre, points[other], tolerance=tolerance)
        mask = None if masks is None else masks.get(name)
        near[rows[sees, 0], rows[sees, 1]] &= _clearance(uv[sees], camera, mask) <= border_px
    return near


def _clearance(uv: np.ndarray, camera: Camera, mask: np.ndarray | None) -> np.ndarray:
    """Distance (pixels) from pixel positions to the photo border, and to the nearest masked pixel."""
    u, v = uv[:, 0], uv[:, 1]
    d = np.minimum(np.minimum(u + 0.5, v + 0.5), np.minimum(camera.width - 0.5 - u, camera.height - 0.5 - v))
    if mask is None:
        return d
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (camera.height, camera.width):
        raise InputError(None, f"mask of photo {camera.name!r} is {mask.shape[1]}×{mask.shape[0]}, the photo is "
                               f"{camera.width}×{camera.height}")
    if mask.all():
        return d
    to_masked = ndimage.distance_transform_edt(mask) - 0.5  # to the edge of the nearest masked pixel
    col = np.clip(np.rint(u), 0, camera.width - 1).astype(int)
    row = np.clip(np.rint(v), 0, camera.height - 1).astype(int)
    return np.minimum(d, to_masked[row, col])


def _continuation_hidden(traces: Sequence[Trace3D], lines: list[np.ndarray], ends: np.ndarray,
                         cameras: Mapping[str, Camera], tracer: RayTracer, tolerance: float) -> np.ndarray:
    """True where the trace continued past its end would be hidden from every photo of the trace.

    The trace is extended straight by δ/3, 2δ/3 and δ. A photo fails to see an extended point when the
    first surface on its line of sight lies more than δ in front of it (occluded) or behind it, or is
    missing (the line of sight slides off a ledge or the mesh).
    """
    steps = tolerance * np.array([1, 2, 3]) / 3
    direction = np.stack([[_end_direction(p, tolerance, k) for k in (0, 1)] for p in lines])
    hidden = np.ones(ends.shape[:2], dtype=bool)
    for name in sorted({image for t in traces for image in t.images}):
        rows = np.array([(i, k) for i, t in enumerate(traces) if name in t.images for k in (0, 1)])
        camera = _camera(cameras, name, traces[rows[0, 0]])
        q = ends[rows[:, 0], rows[:, 1], None] + steps[:, None] * direction[rows[:, 0], rows[:, 1], None]
        q = q.reshape(-1, 3)
        hits = tracer.intersect(camera.centre, q - camera.centre)
        seen = hits.hit & (np.abs(hits.t - np.linalg.norm(q - camera.centre, axis=1)) <= tolerance)
        hidden[rows[:, 0], rows[:, 1]] &= ~seen.reshape(-1, len(steps)).all(axis=1)
    return hidden


def _end_direction(p: np.ndarray, back: float, k: int) -> np.ndarray:
    """Unit direction in which the trace leaves end k (0 start, 1 end), from the chord over the last `back`."""
    p = p if k == 1 else p[::-1]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    target = max(s[-1] - back, 0.0)
    behind = np.array([np.interp(target, s, p[:, d]) for d in range(p.shape[1])])
    chord = p[-1] - behind
    return chord / np.linalg.norm(chord)


def _kept(trace: Trace3D, k: int, auto: str) -> str:
    """A manual code, or a C of unknown source (an extraction cut), else the automatic code."""
    end = ENDS[k]
    source = trace.extra.get(SOURCE_KEY, {}).get(end)
    current = getattr(trace, _field(end))
    if source == "manual" or (source is None and current == "C"):
        return current
    return str(auto)


# -- geometry ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Index:
    """Segments split into pieces no longer than 2·reach, with a KD-tree over the piece midpoints.

    `owner` is the trace of each piece and `arc` the arc length along it at the piece's start.
    """

    a: np.ndarray
    b: np.ndarray
    owner: np.ndarray
    arc: np.ndarray
    reach: float
    tree: cKDTree


def _trace_index(lines: list[np.ndarray], tolerance: float) -> _Index:
    if not lines:
        return _build_index(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, int), np.zeros(0), tolerance)
    a = np.concatenate([p[:-1] for p in lines])
    b = np.concatenate([p[1:] for p in lines])
    owner = np.repeat(np.arange(len(lines)), [len(p) - 1 for p in lines])
    arc = np.concatenate([np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))[:-1]])
                          for p in lines])
    return _build_index(a, b, owner, arc, tolerance)


def _build_index(a: np.ndarray, b: np.ndarray, owner: np.ndarray, arc: np.ndarray, tolerance: float) -> _Index:
    """Split long segments so a fixed search radius finds every piece near a point (no piece is longer
    than max(4δ, the median segment)); zero-length segments are dropped."""
    length = np.linalg.norm(b - a, axis=1)
    keep = length > 0
    a, b, owner, arc, length = a[keep], b[keep], owner[keep], arc[keep], length[keep]
    piece = max(4 * tolerance, float(np.median(length))) if len(length) else tolerance
    n = np.maximum(np.ceil(length / piece).astype(int), 1)
    seg = np.repeat(np.arange(len(a)), n)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)
    d = (b - a)[seg]
    f0, f1 = k / n[seg], (k + 1) / n[seg]
    pa, pb = a[seg] + f0[:, None] * d, a[seg] + f1[:, None] * d
    reach = 0.5 * float((length / n).max()) if len(length) else 0.0
    midpoints = 0.5 * (pa + pb) if len(pa) else np.zeros((0, a.shape[1] if a.ndim == 2 else 3))
    return _Index(pa, pb, owner[seg], arc[seg] + f0 * length[seg], reach, cKDTree(midpoints))


def _candidates(index: _Index, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(point, piece) index pairs with the piece possibly within `tolerance` of the point."""
    if len(index.a) == 0 or len(points) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    lists = index.tree.query_ball_point(points, tolerance + index.reach)
    counts = np.fromiter(map(len, lists), dtype=int, count=len(lists))
    piece = np.fromiter(chain.from_iterable(lists), dtype=int, count=int(counts.sum()))
    return np.repeat(np.arange(len(points)), counts), piece


def _contacts(index: _Index, tolerance: float):
    """Piece pairs (i, j) of different traces within `tolerance`: closest points c1, c2 and distance."""
    if len(index.a) == 0:
        empty = np.zeros((0, index.a.shape[1]))
        return np.zeros(0, int), np.zeros(0, int), empty, empty, np.zeros(0)
    pairs = index.tree.query_pairs(tolerance + 2 * index.reach, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    other = index.owner[i] != index.owner[j]
    i, j = i[other], j[other]
    c1, c2 = _closest_between(index.a[i], index.b[i], index.a[j], index.b[j])
    distance = np.linalg.norm(c1 - c2, axis=1)
    near = distance <= tolerance
    return i[near], j[near], c1[near], c2[near], distance[near]


def _closest_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    s = np.clip(np.einsum("ij,ij->i", p - a, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    return a + s[:, None] * d


def _closest_between(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of segments p1→q1 and p2→q2 (rows; positive lengths), any dimension.

    Clamped parameters as in Ericson (2005) Real-Time Collision Detection §5.1.9.
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("ij,ij->i", d1, d1), np.einsum("ij,ij->i", d2, d2)
    b, c, f = np.einsum("ij,ij->i", d1, d2), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d2, r)
    denom = a * e - b * b
    parallel = denom <= 1e-12 * a * e
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(parallel, 0.0, np.clip((b * f - c * e) / np.where(parallel, 1.0, denom), 0.0, 1.0))
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1, np.clip((b - c) / a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return p1 + s[:, None] * d1, p2 + t[:, None] * d2


def _end_points(lines: list[np.ndarray]) -> np.ndarray:
    if not lines:
        return np.zeros((0, 2, 3))
    return np.stack([np.stack([p[0], p[-1]]) for p in lines])


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _camera(cameras: Mapping[str, Camera], name: str, trace: Trace3D) -> Camera:
    if name not in cameras:
        raise InputError(None, f"trace {trace.id}: photo {name!r} has no camera")
    return cameras[name]


def _field(end: str) -> str:
    return "term_start" if end == "start" else "term_end"


def _check_code(code: str, trace: Trace3D, end: str) -> None:
    if code not in END_CODES:
        raise InputError(None, f"trace {trace.id} ({end}): termination {code!r} must be one of B, T, C "
                               "(X is a crossing, found by find_crossings, not an end code)")


def _positive(value: float, name: str) -> float:
    if not (np.isfinite(value) and value > 0):
        raise InputError(None, f"{name} must be a positive number, got {value}")
    return float(value)
