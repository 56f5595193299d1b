"""Virtual scanlines: a tape stretched across the outcrop, the traces it crosses, P10 and spacing per set.

The field's oldest fracture measure (Priest & Hudson 1976; Priest 1993, §3), taken on the 3D trace map: a
straight line between two points on the rock, and every trace that crosses the rock under it. "Under it" is
the section of the mesh by the plane holding the line and the rock's mean normal along it, within `reach`
of the line (a tape pressed onto the rock), and with the survey only where some photo sees it (no trace
can be drawn on rock no photo shows); a trace crossing that plane there is counted once, where it comes
nearest the line. Distances are along the line, as a tape pulled taut measures them.

Per set: P10 = n / L (L: the metres of the line with rock sampled under it), the Terzaghi (1965) weighted
P10 (w = 1/|cos δ| capped at `W_MAX`, δ the angle between the trace's pole and the line; MATHS §8), apparent
spacings between consecutive crossings, normal spacings (apparent × |cos δ_m|, δ_m from the set's mean
pole: Priest 1993, eq. 3.3), their coefficient of variation (1 for a Poisson process, below it regular,
above it clustered: Gillespie et al. 1993) and P32 = P10 / E_f[|cos δ|] for a Fisher set
(`engine.intensity.p10_p32_factor`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from matplotlib.figure import Figure

from engine.errors import InputError
from engine.intensity import p10_p32_factor
from engine.mesh import Mesh, contour_segments
from engine.plots import FIGSIZE, NON_SYSTEMATIC, Plot, Table, set_color
from engine.register import Similarity, length_scale, to_world
from engine.sets import W_MAX
from engine.sight import Sight
from engine.traces import Trace3D, network

REACH_SHARE, MIN_REACH = 0.1, 0.5
"""The default reach of a scanline (how far from the straight line the rock under it may lie): a tenth of
its length, at least 0.5 m. An outcrop's face wanders about its chord by a few per cent of the length (the
demo's wall, 18 m lines: half the line had rock within 0.5 m, all of it within 1.8 m)."""
SEEN_SPACINGS = 2.0
"""A photo sees a point of the rock under the line when the first surface on its line of sight lies within
this many mesh spacings of it (`engine.sight.Sight.seen`)."""
RUN_SLACK = 1e-6  # m: a crossing this close to a run of rock counts on it (rounding)


@dataclass(frozen=True)
class Scanline:
    """A scanline from `start` to `end` (local frame, metres), counting crossings within `reach` of it (m;
    None: `default_reach` of its length)."""

    start: np.ndarray
    end: np.ndarray
    reach: float | None = None
    name: str = ""
    id: int = -1

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", np.asarray(self.start, dtype=float).reshape(3))
        object.__setattr__(self, "end", np.asarray(self.end, dtype=float).reshape(3))
        if not (np.all(np.isfinite(self.start)) and np.all(np.isfinite(self.end))):
            raise InputError(None, f"{self.label}: its start and end must be finite points")
        if self.length <= 0:
            raise InputError(None, f"{self.label}: its start and end are the same point; expected a line")
        if self.reach is None:
            object.__setattr__(self, "reach", default_reach(self.length))
        if not (np.isfinite(self.reach) and self.reach > 0):
            raise InputError(None, f"{self.label}: reach {self.reach!r}: expected a distance > 0 m")

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    @property
    def label(self) -> str:
        """How messages name it: "scanline 3 (north wall)", "scanline 3", or "the scanline" before it is stored."""
        number = f"scanline {self.id}" if self.id >= 0 else "the scanline"
        return f"{number} ({self.name})" if self.name else number

    @property
    def direction(self) -> np.ndarray:
        return (self.end - self.start) / self.length


def default_reach(length: float) -> float:
    """The reach of a scanline `length` m long when none is given (`REACH_SHARE`, `MIN_REACH`)."""
    return max(MIN_REACH, REACH_SHARE * float(length))


@dataclass(frozen=True)
class Crossing:
    """A trace crossing a scanline: at `distance` (m) along it, `point` (local), δ (degrees, NaN for a
    trace without a pole) and its Terzaghi weight (1 without a pole)."""

    trace_id: int
    set_id: int
    distance: float
    point: np.ndarray
    delta: float
    weight: float


@dataclass(frozen=True)
class Spacing:
    """The crossings of one set (or all) on a scanline sampling `length` m of rock.

    spacing: apparent spacings (m) between consecutive crossings; normal_spacing: the same along the set's
    mean pole (None for all traces or a set without a mean); p32: P10 / E_f[|cos δ|] (NaN without a set's κ).
    """

    n: int
    length: float
    weight: float
    spacing: np.ndarray
    normal_spacing: np.ndarray | None = None
    p32: float = np.nan

    @property
    def p10(self) -> float:
        return self.n / self.length

    @property
    def p10_terzaghi(self) -> float:
        return self.weight / self.length

    @property
    def cv(self) -> float:
        """Coefficient of variation of the spacings (sample standard deviation / mean); NaN under 2."""
        s = self.spacing
        return float(np.std(s, ddof=1) / np.mean(s)) if len(s) >= 2 and np.mean(s) > 0 else np.nan


@dataclass(frozen=True)
class RockUnder:
    """The rock under a scanline: `plane_normal` of the cutting plane, the `section` (segments (K, 2, 3)) and
    the `runs` (R, 2) of the line with rock under it (metres from the start: where the mesh has a hole or the
    rock lies beyond `reach` or no photo sees it, nothing can be counted). It depends on the mesh, the
    photos and the line alone, so a scanline measured again after the traces changed reuses it."""

    plane_normal: np.ndarray
    section: np.ndarray
    runs: np.ndarray

    @property
    def sampled(self) -> float:
        """Metres of the line with rock under it."""
        return float(np.sum(self.runs[:, 1] - self.runs[:, 0]))


@dataclass(frozen=True)
class ScanlineMeasure:
    """A scanline measured: the `rock` under it, the `crossings` by distance, `all` traces and each set (−1:
    traces in no set). P10 is per metre sampled; a spacing is measured only between crossings on one run of
    rock (across a gap in the rock it is unknown)."""

    line: Scanline
    rock: RockUnder
    crossings: tuple[Crossing, ...]
    all: Spacing
    sets: dict[int, Spacing] = field(default_factory=dict)

    @property
    def sampled(self) -> float:
        return self.rock.sampled


def measure_scanline(mesh: Mesh, traces: Sequence[Trace3D], line: Scanline, *, sets: Sequence[Mapping] = (),
                     w_max: float = W_MAX, sight: Sight | None = None,
                     rock: RockUnder | None = None) -> ScanlineMeasure:
    """Count and space the traces a scanline crosses (module docstring), on the rock under it that some photo
    sees when the survey (`sight`) is given; crossings elsewhere (a bridge laid across a hidden gap) are
    not counted, as that rock is not sampled.

    sets : the stored set statistics of `tracemap orient` (id, normal, kappa), for normal spacings and P32.
    Bedding traces are not counted (`engine.traces.network`).
    w_max : cap of the Terzaghi weights.
    rock : `rock_under(mesh, line, sight=sight)` if known, else found here.
    """
    rock = rock_under(mesh, line, sight=sight) if rock is None else rock
    crossings = [c for c in scanline_crossings(network(traces), line, rock.plane_normal, w_max=w_max)
                 if _on_runs(c.distance, rock.runs)]
    known = {int(s["id"]): s for s in sets}
    by_set = {}
    for k in sorted({c.set_id for c in crossings}):
        members = [c for c in crossings if c.set_id == k]
        by_set[k] = _spacing(members, line, rock.runs, known.get(k))
    return ScanlineMeasure(line, rock, tuple(crossings), _spacing(crossings, line, rock.runs, None), by_set)


def rock_under(mesh: Mesh, line: Scanline, *, sight: Sight | None = None) -> RockUnder:
    """The rock under a scanline (`RockUnder`); with the survey (`sight`), only the rock some photo sees:
    no trace can be drawn on rock no photo shows (a bench top, the far side of a buttress), so it is not
    sampled. Refuses a line whose ends are off the rock, that runs into the rock, or that has no rock (seen)
    within reach under it."""
    _check_ends(mesh, line)
    faces = faces_near(mesh, line)
    plane_normal = cutting_plane(mesh, line, faces)
    section = rock_section(mesh, line, plane_normal, faces)
    if sight is not None and len(section):
        section = section[sight.seen(section.mean(axis=1), SEEN_SPACINGS * mesh.mean_edge_length)]
    runs = sampled_runs(section, line)
    if len(runs) == 0:
        raise InputError(None, f"{line.label}: no rock {'a photo sees ' if sight is not None else ''}within "
                               f"{line.reach:g} m under it; expected a line along the imaged outcrop")
    return RockUnder(plane_normal, section, runs)


def _on_runs(distance: float, runs: np.ndarray) -> bool:
    return bool(np.any((runs[:, 0] - RUN_SLACK <= distance) & (distance <= runs[:, 1] + RUN_SLACK)))


def _check_ends(mesh: Mesh, line: Scanline) -> None:
    """Both ends within `reach` of the rock. The gap told is a lower bound: the distance to the nearest face
    centroid less that face's extent."""
    for name, point in (("start", line.start), ("end", line.end)):
        gap, face = mesh.face_tree.query(point)
        gap -= float(mesh.face_reach[face])
        if gap > line.reach:
            raise InputError(None, f"{line.label}: its {name} lies {gap:.2f} m or more from the mesh (reach "
                                   f"{line.reach:g} m); expected both ends on the rock")


def faces_near(mesh: Mesh, line: Scanline) -> np.ndarray:
    """Indices of the faces that may hold rock within reach of the line, from the face k-d tree: centroids
    within reach plus the largest face's extent of the line (sampled every `reach` along it). A scanline is
    measured on a few thousand faces instead of millions (VTK's cutter crosses them all)."""
    step = line.reach
    samples = line.start + np.linspace(0.0, line.length, int(np.ceil(line.length / step)) + 1)[:, None] * line.direction
    radius = float(np.hypot(line.reach + mesh.face_reach.max(), step / 2))
    found = mesh.face_tree.query_ball_point(samples, radius, return_sorted=False)
    near = np.zeros(len(mesh.faces), dtype=bool)
    for f in found:  # a mask, not np.unique: the balls overlap, and sorting their 10⁵–10⁶ indices is slower
        near[f] = True
    return np.flatnonzero(near)


def sampled_runs(section: np.ndarray, line: Scanline) -> np.ndarray:
    """The stretches (R, 2) of the line, in metres from its start, with rock under it: the union of the section
    segments' spans."""
    if len(section) == 0:
        return np.zeros((0, 2))
    t = np.sort((section - line.start) @ line.direction, axis=1)
    t = t[np.argsort(t[:, 0])]
    starts = np.flatnonzero(np.r_[True, t[1:, 0] > np.maximum.accumulate(t[:, 1])[:-1] + 1e-9])
    return np.column_stack([t[starts, 0], np.maximum.reduceat(t[:, 1], starts)])


def cutting_plane(mesh: Mesh, line: Scanline, faces: np.ndarray) -> np.ndarray:
    """Unit normal of the plane holding the line and the rock's mean normal along it.

    The mean normal is the principal axis of the area-weighted normals of the faces (of `faces`) whose
    centroid is within `reach` of the line (axial, so faces wound either way agree), less its component
    along the line.
    """
    near = faces[_distance_to_line(mesh.face_centroids[faces], line) <= line.reach]
    if len(near) == 0:
        raise InputError(None, f"{line.label}: no mesh face within {line.reach:g} m of it; "
                               f"expected both ends on the rock")
    n = mesh.face_normals[near]
    tensor = (n * mesh.face_areas[near, None]).T @ n
    outcrop = np.linalg.eigh(tensor)[1][:, -1]
    across = np.cross(line.direction, outcrop)
    if np.linalg.norm(across) < np.sin(np.radians(10.0)):
        raise InputError(None, f"{line.label}: it runs within 10° of the rock's normal "
                               f"(into the rock); expected a line along the outcrop")
    return across / np.linalg.norm(across)


def rock_section(mesh: Mesh, line: Scanline, plane_normal: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Segments (K, 2, 3) where the cutting plane meets the mesh faces `faces` (`faces_near`), clipped to the
    line's extent, within reach."""
    corners = mesh.faces[faces]
    signed = (mesh.vertices[corners] - line.start) @ plane_normal
    return _within(contour_segments(mesh.vertices, corners, signed), line)


def _within(segments: np.ndarray, line: Scanline) -> np.ndarray:
    """The parts of segments (K, 2, 3) whose distance along the line is in [0, length], then those whose
    middle lies within reach of the line."""
    t = (segments - line.start) @ line.direction
    lo, hi = t.min(axis=1), t.max(axis=1)
    keep = (hi >= 0) & (lo <= line.length) & (hi > lo)
    segments, t = segments[keep], t[keep]
    span = t[:, 1] - t[:, 0]
    clipped = np.stack([np.clip(t, 0.0, line.length)[:, k] for k in (0, 1)], axis=1)
    f = (clipped - t[:, :1]) / span[:, None]
    segments = segments[:, :1] + f[:, :, None] * (segments[:, 1:] - segments[:, :1])
    return segments[_distance_to_line(segments.mean(axis=1), line) <= line.reach]


def scanline_crossings(traces: Sequence[Trace3D], line: Scanline, plane_normal: np.ndarray, *,
                       w_max: float = W_MAX) -> tuple[Crossing, ...]:
    """Each trace's crossing of the cutting plane nearest the line, if within its extent and reach; by distance."""
    out = []
    d = line.direction
    for trace in traces:
        p = trace.points
        s = (p - line.start) @ plane_normal
        i = np.flatnonzero((s[:-1] >= 0) != (s[1:] >= 0))
        if len(i) == 0:
            continue
        x = p[i] + (s[i] / (s[i] - s[i + 1]))[:, None] * (p[i + 1] - p[i])
        along = (x - line.start) @ d
        off = _distance_to_line(x, line)
        inside = (along >= 0) & (along <= line.length) & (off <= line.reach)
        if not inside.any():
            continue
        j = np.flatnonzero(inside)[np.argmin(off[inside])]
        delta, weight = _terzaghi(trace.normal, d, w_max)
        out.append(Crossing(trace.id, trace.set_id, float(along[j]), x[j], delta, weight))
    return tuple(sorted(out, key=lambda c: c.distance))


def _terzaghi(normal: np.ndarray | None, direction: np.ndarray, w_max: float) -> tuple[float, float]:
    if normal is None or not np.all(np.isfinite(normal)):
        return np.nan, 1.0
    cos = abs(float(np.dot(normal, direction) / np.linalg.norm(normal)))
    return float(np.degrees(np.arccos(min(cos, 1.0)))), float(min(1.0 / cos, w_max)) if cos > 0 else w_max


def _spacing(crossings: list[Crossing], line: Scanline, runs: np.ndarray, set_stats: Mapping | None) -> Spacing:
    distances = np.array([c.distance for c in crossings])
    run = np.searchsorted(runs[:, 0], distances, side="right")
    spacing = np.diff(distances)[np.diff(run) == 0]
    weight = float(sum(c.weight for c in crossings))
    sampled = float(np.sum(runs[:, 1] - runs[:, 0]))
    if set_stats is None:
        return Spacing(len(crossings), sampled, weight, spacing)
    mean = np.asarray(set_stats["normal"], dtype=float)
    delta_m = float(np.degrees(np.arccos(min(abs(mean @ line.direction) / np.linalg.norm(mean), 1.0))))
    factor = float(p10_p32_factor(float(set_stats["kappa"]), delta_m))
    return Spacing(len(crossings), sampled, weight, spacing, spacing * np.cos(np.radians(delta_m)),
                   factor * len(crossings) / sampled)


def _distance_to_line(points: np.ndarray, line: Scanline) -> np.ndarray:
    """Distance of points (N, 3) from the segment start–end."""
    v = points - line.start
    t = np.clip(v @ line.direction, 0.0, line.length)
    return np.linalg.norm(v - t[:, None] * line.direction, axis=1)


def level_scanlines(mesh: Mesh, n: int, *, margin: float = 1.0, up: np.ndarray = np.array([0.0, 0.0, 1.0]),
                    reach: float | None = None) -> list[Scanline]:
    """`n` level scanlines along the outcrop, a scanline survey of its face (Priest 1993, §3.2): at heights
    evenly spaced from `margin` (m) above its foot to `margin` below its top, each running from end to end of
    the rock at its height, `margin` in from either end, along the outcrop's strike (the principal horizontal
    axis of its vertices). `up`: the vertical in the mesh's frame (a registration turns it). Each end is the
    mesh vertex nearest its place, so it lies on the rock."""
    if n < 1:
        raise InputError(None, f"levels {n}: expected 1 or more scanlines")
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    v = mesh.vertices
    height = v @ up
    flat = v - np.outer(height, up)
    flat -= flat.mean(axis=0)
    strike = np.linalg.eigh(flat.T @ flat)[1][:, -1]
    strike *= np.sign(strike[np.argmax(np.abs(strike))])  # a sign of its own, not the solver's: lines run the same way
    along = v @ strike
    band = 2.0 * mesh.mean_edge_length
    lines = []
    for k, h in enumerate(np.linspace(height.min() + margin, height.max() - margin, n)):
        near = np.flatnonzero(np.abs(height - h) <= band)
        if len(near) < 2 or np.ptp(along[near]) <= 2 * margin:
            raise InputError(None, f"level {k + 1}: the rock at height {h:.2f} m is narrower than twice the "
                                   f"margin {margin:g} m; expected an outcrop wider than it is tall")
        ends = [near[np.argmin(np.abs(along[near] - a) + np.abs(height[near] - h))]
                for a in (along[near].min() + margin, along[near].max() - margin)]
        lines.append(Scanline(v[ends[0]], v[ends[1]], reach=reach, name=f"level {k + 1}"))
    return lines


def pooled(measures: Sequence[ScanlineMeasure], similarity: Similarity | None = None) -> dict[str, dict]:
    """Several scanlines as one sample, per group ("all", "set<k>", "non_systematic"), in the export frame:
    crossings, metres sampled, P10 and Terzaghi P10 over all the metres, and P32 = Σ P32_i L_i / Σ L_i over
    the lines (each line's own δ_m; a line crossing none of the set adds its metres and no P32)."""
    scale = length_scale(similarity)
    sampled = float(sum(m.sampled for m in measures))
    if sampled <= 0:
        return {}
    out: dict[str, dict] = {}
    for m in measures:
        groups = {"all": m.all, **{("non_systematic" if k < 0 else f"set{k}"): v for k, v in m.sets.items()}}
        for name, g in groups.items():
            acc = out.setdefault(name, {"n": 0, "weight": 0.0, "p32": None})
            acc["n"] += g.n
            acc["weight"] += g.weight
            if np.isfinite(g.p32):
                acc["p32"] = (acc["p32"] or 0.0) + g.p32 * g.length
    return {name: {"n": acc["n"], "sampled_m": sampled * scale, "p10_per_m": acc["n"] / sampled / scale,
                   "p10_terzaghi_per_m": acc["weight"] / sampled / scale,
                   "p32_per_m": None if acc["p32"] is None else acc["p32"] / sampled / scale}
            for name, acc in out.items()}


def scanline_report(measure: ScanlineMeasure, origin: np.ndarray, similarity: Similarity | None = None) -> dict:
    """A measured scanline in the export frame (summary.json, the CLI, the 3D viewer's readout): ends as
    world or registered coordinates, lengths × the registration's scale, P10 and P32 ÷ it. Groups: "all",
    "set<k>", "non_systematic"."""
    scale = length_scale(similarity)
    line = measure.line
    groups = {"all": measure.all, **{("non_systematic" if k < 0 else f"set{k}"): v for k, v in measure.sets.items()}}
    return {"id": line.id, "name": line.name,
            "start": to_world(line.start, origin, similarity).tolist(),
            "end": to_world(line.end, origin, similarity).tolist(),
            "length_m": line.length * scale, "sampled_m": measure.sampled * scale,
            "reach_m": line.reach * scale, "crossings": len(measure.crossings),
            "groups": {name: _spacing_report(s, scale) for name, s in groups.items()}}


def _spacing_report(s: Spacing, scale: float) -> dict:
    def stat(values: np.ndarray | None, f) -> float | None:
        return None if values is None or len(values) == 0 else float(f(values)) * scale

    return {"n": s.n, "p10_per_m": s.p10 / scale, "p10_terzaghi_per_m": s.p10_terzaghi / scale,
            "mean_spacing_m": stat(s.spacing, np.mean), "median_spacing_m": stat(s.spacing, np.median),
            "mean_normal_spacing_m": stat(s.normal_spacing, np.mean),
            "spacing_cv": None if not np.isfinite(s.cv) else s.cv,
            "p32_per_m": None if not np.isfinite(s.p32) else s.p32 / scale}


def describe_scanline(report: dict) -> str:
    """Lines for a person: a scanline's length, crossings, P10 and spacing per set (from `scanline_report`)."""
    name = f"scanline {report['id']}" + (f" ({report['name']})" if report["name"] else "")
    lines = [f"{name}: {report['length_m']:.2f} m ({report['sampled_m']:.2f} m of it over rock), "
             f"{report['crossings']} traces crossed"]
    for group, g in report["groups"].items():
        label = "all" if group == "all" else "non-systematic" if group == "non_systematic" else f"set {group[3:]}"
        text = f"  {label}: {g['n']} traces, P10 {g['p10_per_m']:.3f} /m (Terzaghi {g['p10_terzaghi_per_m']:.3f} /m)"
        if g["mean_spacing_m"] is not None:
            text += f", spacing mean {g['mean_spacing_m']:.2f} m, median {g['median_spacing_m']:.2f} m"
        if g["mean_normal_spacing_m"] is not None:
            text += f", normal {g['mean_normal_spacing_m']:.2f} m"
        if g["spacing_cv"] is not None:
            text += f", CV {g['spacing_cv']:.2f}"
        if g["p32_per_m"] is not None:
            text += f", P32 {g['p32_per_m']:.3f} /m"
        lines.append(text)
    return "\n".join(lines)


def describe_pooled(report: dict[str, dict], n_lines: int) -> str:
    """Lines for a person: `pooled` over `n_lines` scanlines."""
    if not report:
        return f"all {n_lines} scanlines: no rock sampled"
    lines = [f"all {n_lines} scanlines: {report['all']['sampled_m']:.2f} m sampled, {report['all']['n']} crossings"]
    for group, g in report.items():
        label = "all" if group == "all" else "non-systematic" if group == "non_systematic" else f"set {group[3:]}"
        text = f"  {label}: P10 {g['p10_per_m']:.3f} /m (Terzaghi {g['p10_terzaghi_per_m']:.3f} /m)"
        lines.append(text + (f", P32 {g['p32_per_m']:.3f} /m" if g["p32_per_m"] is not None else ""))
    return "\n".join(lines)


CROSSINGS_HEADER = ("scanline", "name", "trace", "set", "distance_m", "x", "y", "z", "delta_deg", "terzaghi_weight")


def crossing_rows(measure: ScanlineMeasure, origin: np.ndarray, similarity: Similarity | None = None) -> list[tuple]:
    """scanlines.csv rows (`CROSSINGS_HEADER`), one per crossing, in the export frame."""
    scale = length_scale(similarity)
    line = measure.line
    return [(line.id, line.name, c.trace_id, c.set_id, round(c.distance * scale, 4),
             *np.round(to_world(c.point, origin, similarity), 4).tolist(),
             round(c.delta, 2) if np.isfinite(c.delta) else None, round(c.weight, 4)) for c in measure.crossings]


def scanline_plot(measure: ScanlineMeasure, similarity: Similarity | None = None) -> Plot:
    """The cumulative count of crossings along a scanline, per set (`scanline_<id>`).

    A cumulative frequency diagram: against distance along the line (export frame), the number of each set's
    crossings so far, beside the same number spread evenly over the rock sampled (dashed); steps steeper
    than it are clusters, flats the gaps between them. Stretches without rock under the line are shaded. The table holds
    each crossing (set, distance, count so far).
    """
    scale = length_scale(similarity)
    line = measure.line
    fig = Figure(figsize=FIGSIZE, layout="constrained")
    ax = fig.add_subplot()
    edges = np.r_[0.0, measure.rock.runs.ravel(), line.length]
    for lo, hi in edges.reshape(-1, 2):  # the gaps before, between and after the runs of rock
        if hi > lo:
            ax.axvspan(lo * scale, hi * scale, color="0.9", lw=0)
    rows = []
    groups = [("all", measure.all, [c for c in measure.crossings], "0.2")]
    groups += [(_group_label(k), s, [c for c in measure.crossings if c.set_id == k],
                NON_SYSTEMATIC if k < 0 else set_color(k)) for k, s in measure.sets.items()]
    for label, spacing, members, color in groups:
        distances = np.array([c.distance for c in members]) * scale
        count = np.arange(1, len(distances) + 1)
        ax.step(np.r_[0.0, distances, line.length * scale], np.r_[0, count, len(count)], where="post", color=color,
                label=f"{label}: {spacing.n}, P10 {spacing.p10 / scale:.3g} /m")
        ax.plot(edges * scale, len(count) * _sampled_before(measure.rock.runs, edges) / spacing.length,
                color=color, lw=0.8, ls="--")
        rows += [(label, float(d), int(n)) for d, n in zip(distances, count)]
    ax.set_xlim(0.0, line.length * scale)
    ax.set_xlabel("distance along the scanline (m)")
    ax.set_ylabel("crossings so far")
    ax.set_title(f"{line.label}: cumulative crossings (dashed: evenly spaced)")
    ax.legend(loc="upper left", fontsize="small")
    return Plot(f"scanline_{line.id}", f"Scanline {line.id}", fig, Table(("group", "distance_m", "count"), rows))


def _sampled_before(runs: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Metres of rock sampled between the line's start and each distance x."""
    return np.clip(x[:, None] - runs[:, 0], 0.0, runs[:, 1] - runs[:, 0]).sum(axis=1)


def _group_label(set_id: int) -> str:
    return "non-systematic" if set_id < 0 else f"set {set_id}"
