"""Mauldon's circular scan windows: trace intensity, density and mean length from two counts.

Mauldon, Dunne & Rohrbaugh (2001, J. Struct. Geol. 23, 247–258) and Rohrbaugh, Dunne & Mauldon (2002, AAPG
Bull. 86, 2089–2104): in a circle of radius r on a trace map, the n points where traces cross its edge and
the m trace ends inside it estimate (MATHS §6, with its and Mauldon's letters)

    P21 = n / (4r),   P20 = m / (2πr²),   mean trace length μ = (πr / 2) · n / m,

whatever the traces' lengths and however many run beyond the circle: no trace need be measured, so the
estimates carry neither the censoring nor the length bias of a window's measured lengths (the bias
Kaplan–Meier corrects in `engine.lengths`). fractopo gives the same three for a circular target area, with
n = E nodes and m = I + Y nodes (`fractopo.analysis.parameters`); `tracemap analyse-map` does both: its
sampling area when that is a circle, and any scan circles the user places inside it.

On the outcrop (`ScanCircle`, `measure_scan_circle`, `tracemap scan-circle`) the window is the rock within
r of a point on it (a disc where the rock is flat): n counts where traces cross the sphere of radius r, m
their ends inside it, with the window's own edge length L and area A on the mesh: P21 = πn / (2L),
P20 = m / (2A). Ends the traces were cut at (C: the mesh's edge, an occlusion) are not fracture tips and
are not counted in m but told apart, as are the share of the window's rock no photo sees and a window that
reaches the mesh's edge: a window is only unbiased where it is whole, wholly seen and holds no cut ends.
Windows on a grid over the face (`grid_scan_circles`) pool into one estimate (`pooled_windows`), as
Rohrbaugh et al. (2002) lay them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from engine.errors import InputError
from engine.intensity import subtriangle_centroids
from engine.mesh import Mesh, contour_segments, first_hit
from engine.plots import FIGSIZE, Plot, Table
from engine.register import Similarity, length_scale, to_world
from engine.sight import Sight
from engine.traces import Trace3D, network

SIDES = 720
"""Sides of the polygon a scan circle is clipped with: its edge lies within r(1 − cos(π/720)) ≈ 1e-5 r of the
circle."""
ROUND = 0.01
"""An area polygon whose vertices all lie within this fraction of their mean distance from its centroid, that
distance within it of the radius of a circle of the polygon's area, is taken for a circle (fractopo's
`circular_target_area`); its radius is then that of the circle of its area, as fractopo's."""
MIN_SIDES = 16
SEEN_ENOUGH = 0.99
"""A window is taken for wholly seen when the photos see this share of its rock: faces a photo sees edge-on
leave a few per mille unseen (the quick demo's windows clear of its bench: 0.15 and 0.43%; those across it
4–15%)."""
WINDOW_SUBDIVISION = 16
"""Sub-triangles per edge of a face the window's edge crosses, for the area inside it (as the P21 map's
reference area, `tests/benchmarks/bench_intensity.py`)."""


@dataclass(frozen=True)
class Mauldon:
    """The counts of a scan circle of `radius` at `centre` (map units): `ends` inside, `cuts` of its edge."""

    centre: np.ndarray
    radius: float
    ends: int
    cuts: int
    censored: int = 0  # ends inside that traces were cut at (on the outcrop), not counted in `ends`
    seen: float = 1.0  # share of the window's rock area some photo sees (on the outcrop)
    area: float | None = None  # the window's area and edge length: a disc's, πr² and 2πr, unless given
    perimeter: float | None = None

    def __post_init__(self) -> None:
        if self.area is None:
            object.__setattr__(self, "area", np.pi * self.radius**2)
        if self.perimeter is None:
            object.__setattr__(self, "perimeter", 2.0 * np.pi * self.radius)

    @property
    def p21(self) -> float:
        """Trace length per unit area: π n / (2 L) for a window of edge length L, n / (4r) for a disc
        (isotropic traces cross an edge of length L (2/π) P21 L times)."""
        return np.pi * self.cuts / (2.0 * self.perimeter)

    @property
    def p20(self) -> float:
        """Traces per unit area: m / (2A) (each trace has two ends), m / (2πr²) for a disc."""
        return self.ends / (2.0 * self.area)

    @property
    def mean_length(self) -> float:
        """Mean trace length P21 / P20, (πr / 2) · n / m for a disc; NaN without an end inside."""
        return self.p21 / self.p20 if self.ends else np.nan

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "radius": self.radius, "ends_inside": self.ends,
                "edge_cuts": self.cuts, "P21": self.p21, "P20": self.p20, "mean_length": self.mean_length,
                "censored_ends_inside": self.censored, "seen_share": self.seen, "window_area": self.area,
                "window_perimeter": self.perimeter}


def circle_ring(centre: np.ndarray, radius: float, sides: int = SIDES) -> np.ndarray:
    """The closed polygon (sides + 1, 2), anticlockwise, whose vertices lie on the circle."""
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(None, f"scan circle radius {radius!r}: expected a positive length in map units")
    t = np.linspace(0.0, 2.0 * np.pi, sides + 1)
    return np.asarray(centre, dtype=float) + radius * np.column_stack([np.cos(t), np.sin(t)])


def as_circle(polygons: list[list[np.ndarray]]) -> tuple[np.ndarray, float] | None:
    """(centre, radius) if the area is one polygon without holes that is a circle (`ROUND`), else None."""
    if len(polygons) != 1 or len(polygons[0]) != 1:
        return None
    ring = polygons[0][0]
    ring = ring[:-1] if np.array_equal(ring[0], ring[-1]) else ring
    if len(ring) < MIN_SIDES:
        return None
    local = ring - ring.mean(axis=0)  # a local origin keeps UTM-sized maps exact
    x, y = local[:, 0], local[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = 0.5 * cross.sum()
    centre = (((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()) / (6.0 * area)
    distance = np.linalg.norm(local - centre, axis=1)
    mean = float(distance.mean())
    radius = float(np.sqrt(abs(area) / np.pi))  # fractopo's: the circle of the polygon's area
    if np.abs(distance - mean).max() > ROUND * mean or abs(radius / mean - 1) > ROUND:
        return None
    return ring.mean(axis=0) + np.asarray(centre), radius


@dataclass(frozen=True)
class ScanCircle:
    """A scan window: the rock within `radius` (m) of `centre` (local frame, a point on the rock)."""

    centre: np.ndarray
    radius: float
    name: str = ""
    id: int = -1

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre", np.asarray(self.centre, dtype=float).reshape(3))
        object.__setattr__(self, "radius", float(self.radius))
        if not np.all(np.isfinite(self.centre)):
            raise InputError(None, f"{self.label}: its centre must be a finite point")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise InputError(None, f"{self.label}: radius {self.radius!r}: expected a distance > 0 m")

    @property
    def label(self) -> str:
        """How messages name it: "scan circle 3 (north wall)", "scan circle 3", or "the scan circle" unstored."""
        number = f"scan circle {self.id}" if self.id >= 0 else "the scan circle"
        return f"{number} ({self.name})" if self.name else number


@dataclass(frozen=True)
class WindowRock:
    """The rock of a scan circle: its `area` on the mesh, the `seen` share of it some photo sees, its `edge`
    where the sphere cuts the mesh (K, 2, 3 segments), `open` when it reaches the mesh's edge (its border or a
    hole), so part of the disc is missing and traces there are cut short. It depends on the mesh, the photos
    and the circle alone, so a tool measures a stored window again after an edit of the traces without it."""

    area: float
    seen: float
    edge: np.ndarray
    open: bool
    normal: np.ndarray  # the way the window's rock faces: the area-weighted mean of its faces' normals

    @property
    def perimeter(self) -> float:
        return float(np.linalg.norm(self.edge[:, 1] - self.edge[:, 0], axis=1).sum())


@dataclass(frozen=True)
class WindowMeasure:
    """A scan circle measured on the outcrop: its `counts`, its `rock`, the traces' `crossings` of its edge
    (n, 3), their tip `ends` inside (m, 3) and the `cut_ends` inside (C, not counted)."""

    circle: ScanCircle
    counts: Mauldon
    rock: WindowRock
    crossings: np.ndarray
    ends: np.ndarray
    cut_ends: np.ndarray

    @property
    def unbiased(self) -> bool:
        """Whole, seen (`SEEN_ENOUGH`) and with no cut ends: Mauldon's estimators hold as they stand."""
        return not self.rock.open and self.counts.seen >= SEEN_ENOUGH and self.counts.censored == 0


def window_rock(mesh: Mesh, circle: ScanCircle, *, sight: Sight | None = None) -> WindowRock:
    """The rock within the circle's radius of its centre (`WindowRock`): the faces inside the sphere and the
    share of each inside it; with the survey (`sight`), the share some photo sees. Refuses a centre with no
    rock within the radius."""
    centre, radius = circle.centre, circle.radius
    near = _faces_near(mesh, centre, radius)
    faces, area = _window_faces(mesh, near, centre, radius)
    if len(faces) == 0:
        raise InputError(None, f"{circle.label}: no rock within {radius:g} m of its centre; expected a centre on "
                               f"the mesh")
    seen = 1.0 if sight is None else float(area[sight.seen(mesh.face_centroids[faces],
                                                           2.0 * mesh.mean_edge_length)].sum() / area.sum())
    is_open = _reaches(mesh.vertices[np.unique(mesh.boundary_edges)], centre, radius)
    normal = (mesh.face_normals[faces] * area[:, None]).sum(axis=0)
    return WindowRock(float(area.sum()), seen, _sphere_section(mesh, near, centre, radius), is_open,
                      normal / np.linalg.norm(normal))


def measure_scan_circle(mesh: Mesh, traces: Sequence[Trace3D], circle: ScanCircle, *,
                        sight: Sight | None = None, rock: WindowRock | None = None) -> WindowMeasure:
    """Mauldon's counts of a window of rock (module docstring): traces' crossings of the sphere (a segment
    with both ends outside that dips into it crosses twice) and their ends inside it, censored (C) ends apart;
    the window's mesh area and edge length (where the sphere cuts the mesh), which rough rock makes larger
    than a disc's; with the survey (`sight`), the share of its area some photo sees. Bedding traces are
    not counted (`engine.traces.network`).

    rock : `window_rock(mesh, circle, sight=sight)` if known, else found here.
    """
    rock = window_rock(mesh, circle, sight=sight) if rock is None else rock
    centre, radius = circle.centre, circle.radius
    crossings, ends, cut_ends = [np.empty((0, 3))], [np.empty((0, 3))], [np.empty((0, 3))]
    for trace in network(traces):
        if np.linalg.norm(np.clip(centre, trace.points.min(axis=0), trace.points.max(axis=0)) - centre) > radius:
            continue  # its box lies clear of the sphere: no crossing, no end inside
        crossings.append(sphere_crossings(trace.points, centre, radius))
        for k, code in ((0, trace.term_start), (-1, trace.term_end)):
            if np.linalg.norm(trace.points[k] - centre) <= radius:
                (cut_ends if code == "C" else ends).append(trace.points[k][None])
    crossings, ends, cut_ends = (np.concatenate(a) for a in (crossings, ends, cut_ends))
    counts = Mauldon(centre, radius, len(ends), len(crossings), len(cut_ends), rock.seen, rock.area, rock.perimeter)
    return WindowMeasure(circle, counts, rock, crossings, ends, cut_ends)


def _reaches(rim: np.ndarray, centre: np.ndarray, radius: float) -> bool:
    """Whether a vertex of the mesh's edge lies inside the sphere (one on it, by rounding, leaves it whole)."""
    return bool(len(rim)) and bool(np.any(np.linalg.norm(rim - centre, axis=1) < radius * (1.0 - 1e-9)))


def sphere_crossings(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Where a polyline crosses the sphere (k, 3): once on a segment from inside (≤ r) to outside, twice on
    one with both ends outside whose closest point to the centre lies inside (a chord dipping in and out)."""
    a, d = points[:-1], np.diff(points, axis=0)
    f = a - centre
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-300)
    half_b, c = np.einsum("ij,ij->i", f, d), np.einsum("ij,ij->i", f, f) - radius**2
    inside = np.linalg.norm(points - centre, axis=1) <= radius
    root = np.sqrt(np.maximum(half_b**2 - dd * c, 0.0))
    near, far = (-half_b - root) / dd, (-half_b + root) / dd  # the ray's entry and exit of the sphere
    t_closest = np.clip(-half_b / dd, 0.0, 1.0)
    dips = ~inside[:-1] & ~inside[1:] & (np.linalg.norm(f + t_closest[:, None] * d, axis=1) <= radius)
    leaving, entering = inside[:-1] & ~inside[1:], ~inside[:-1] & inside[1:]
    t = np.concatenate([far[leaving], near[entering], near[dips], far[dips]])
    segment = np.concatenate([np.flatnonzero(m) for m in (leaving, entering, dips, dips)])
    return a[segment] + np.clip(t, 0.0, 1.0)[:, None] * d[segment]


def grid_scan_circles(mesh: Mesh, radius: float, *, spacing: float | None = None,
                      up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> list[ScanCircle]:
    """Scan circles of `radius` (m) on a square grid over the outcrop's face, `spacing` (m, default 2r: the
    circles touch but do not overlap, so no trace end is counted twice) apart along its strike and up its
    dip, each centred where the grid point's line along the face's normal first meets the rock from the
    side the face looks to (`engine.mesh.first_hit`); a window reaching the mesh's edge is left out (Rohrbaugh
    et al. 2002 lay their circles whole on the outcrop). Rows from the foot up, each along strike. `up`: the
    vertical in the mesh's frame (a registration turns it)."""
    ScanCircle(np.zeros(3), radius)  # checks the radius
    spacing = 2.0 * radius if spacing is None else float(spacing)
    if not (np.isfinite(spacing) and spacing > 0):
        raise InputError(None, f"grid spacing {spacing!r}: expected a distance > 0 m")
    normal, strike, dip = _face_axes(mesh, np.asarray(up, dtype=float))
    v = mesh.vertices
    middle = v.mean(axis=0)
    along, height = (v - middle) @ strike, (v - middle) @ dip
    front = float(np.max((v - middle) @ normal)) + radius  # in front of all the rock
    rim = mesh.vertices[np.unique(mesh.boundary_edges)]
    circles = []
    for h in _grid_steps(height, radius, spacing):
        for a in _grid_steps(along, radius, spacing):
            hit = first_hit(mesh, middle + a * strike + h * dip + front * normal, -normal)
            if hit is None or _reaches(rim, hit, radius):
                continue
            circles.append(ScanCircle(hit, radius, f"grid {len(circles) + 1}"))
    if not circles:
        raise InputError(None, f"scan circle grid: no window of radius {radius:g} m fits whole on the rock; "
                               f"expected a radius under half the outcrop's height")
    return circles


def _face_axes(mesh: Mesh, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outcrop face's normal (the way its rock looks: the area-weighted mean of its faces' normals), its
    strike and the up-dip direction in it (`_plane_axes`)."""
    return _plane_axes((mesh.face_normals * mesh.face_areas[:, None]).sum(axis=0), up)


def _plane_axes(normal: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit `normal`, the strike (horizontal, in the plane: to the right of one looking at the face along
    −normal) and the up-dip direction in the plane."""
    normal = normal / np.linalg.norm(normal)
    strike = np.cross(up, normal)
    if np.linalg.norm(strike) < 1e-6:  # a flat pavement: any horizontal axis
        strike = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    strike /= np.linalg.norm(strike)
    return normal, strike, np.cross(normal, strike)


def _grid_steps(values: np.ndarray, radius: float, spacing: float) -> np.ndarray:
    """Grid positions `spacing` apart, centred on the span of `values`, at least `radius` inside its ends."""
    lo, hi = float(values.min()) + radius, float(values.max()) - radius
    if hi < lo:
        return np.empty(0)
    n = int(np.floor((hi - lo) / spacing))
    return 0.5 * (lo + hi) + spacing * (np.arange(n + 1) - 0.5 * n)


def pooled_windows(measures: Sequence[WindowMeasure]) -> Mauldon:
    """Several windows as one (Rohrbaugh et al. 2002): their counts, areas and edge lengths summed, so
    P21 = π Σn / (2 ΣL), P20 = Σm / (2 ΣA) and μ = P21 / P20; the seen share weighted by area."""
    if not measures:
        raise InputError(None, "pooled scan circles: expected one or more windows")
    return pooled_counts([m.counts for m in measures])


def pooled_counts(counts: Sequence[Mauldon]) -> Mauldon:
    """Mauldon's counts of several windows as one (`pooled_windows`): the centre and radius their means."""
    area = sum(c.area for c in counts)
    return Mauldon(np.mean([c.centre for c in counts], axis=0), float(np.mean([c.radius for c in counts])),
                   sum(c.ends for c in counts), sum(c.cuts for c in counts), sum(c.censored for c in counts),
                   sum(c.seen * c.area for c in counts) / area, area, sum(c.perimeter for c in counts))


def window_report(measure: WindowMeasure, origin: np.ndarray, similarity: Similarity | None = None) -> dict:
    """A measured scan circle in the export frame (summary.json, the CLI, the 3D viewer's readout): the centre
    as world or registered coordinates, lengths × the registration's scale, areas × its square, P21 ÷ it, P20
    ÷ its square."""
    scale = length_scale(similarity)
    c, circle = measure.counts, measure.circle
    return {"id": circle.id, "name": circle.name, "centre": to_world(circle.centre, origin, similarity).tolist(),
            "radius_m": circle.radius * scale, **counts_report(c, scale), "open": measure.rock.open,
            "unbiased": measure.unbiased}


def counts_report(c: Mauldon, scale: float = 1.0) -> dict:
    """Mauldon's counts and estimators in a frame `scale` times the mesh's."""
    return {"edge_cuts": c.cuts, "ends_inside": c.ends, "censored_ends_inside": c.censored,
            "p21_per_m": c.p21 / scale, "p20_per_m2": c.p20 / scale**2,
            "mean_length_m": None if not np.isfinite(c.mean_length) else c.mean_length * scale,
            "seen_share": c.seen, "area_m2": c.area * scale**2, "edge_m": c.perimeter * scale}


def describe_window(report: dict, frame: str = "") -> str:
    """Lines for a person: a scan circle's counts and estimators (from `window_report`; `frame` follows them,
    e.g. " (GCPs' frame)"), and why they may be biased."""
    name = f"scan circle {report['id']}" + (f" ({report['name']})" if report["name"] else "")
    where = ", ".join(f"{x:.10g}" for x in report["centre"])
    text = f"{name} at ({where}), r {report['radius_m']:g} m: " + _estimates(report) + frame
    notes = [f"{report['censored_ends_inside']} cut (C) ends inside"] if report["censored_ends_inside"] else []
    if report["seen_share"] < SEEN_ENOUGH:
        notes.append(f"{100 * (1 - report['seen_share']):.0f}% of its rock unseen")
    if report["open"]:
        notes.append("it reaches the mesh's edge")
    if notes:
        text += f"\n  note: {', '.join(notes)}: the estimates assume a whole window, wholly seen, with no cut ends"
    return text


def describe_pooled_windows(report: dict, n_windows: int) -> str:
    """A line for a person: `counts_report(pooled_windows(...))` over `n_windows`."""
    return f"all {n_windows} scan circles ({report['area_m2']:.1f} m² of rock): " + _estimates(report)


def _estimates(r: dict) -> str:
    length = "no end inside" if r["mean_length_m"] is None else f"{r['mean_length_m']:.2f} m"
    return (f"{r['edge_cuts']} edge cuts, {r['ends_inside']} trace ends inside: P21 {r['p21_per_m']:.3f} /m, "
            f"P20 {r['p20_per_m2']:.3f} /m², mean trace length {length}")


WINDOWS_HEADER = ("scan_circle", "name", "x", "y", "z", "radius_m", "edge_cuts", "ends_inside",
                  "censored_ends_inside", "p21_per_m", "p20_per_m2", "mean_length_m", "seen_share", "area_m2",
                  "edge_m", "open")


def window_row(report: dict) -> tuple:
    """A row of scan_circles.csv (`WINDOWS_HEADER`) from `window_report`."""
    return (report["id"], report["name"], *report["centre"], *(report[k] for k in WINDOWS_HEADER[5:]))


def _faces_near(mesh: Mesh, centre: np.ndarray, radius: float) -> np.ndarray:
    """The faces that may reach into the sphere, from the face k-d tree: those whose centroid lies within
    r plus two mesh spacings of the centre, and the few larger faces wherever they are."""
    step = 2.0 * mesh.mean_edge_length
    near = np.asarray(mesh.face_tree.query_ball_point(centre, radius + step), dtype=np.int64)
    return np.union1d(near, np.flatnonzero(mesh.face_reach > step))


def _window_faces(mesh: Mesh, near: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Of the faces `near`, those with rock within the sphere and the area of each inside it: whole faces
    inside, and the share of the WINDOW_SUBDIVISION² sub-triangles inside of the faces its edge crosses."""
    inside = np.linalg.norm(mesh.vertices[mesh.faces[near]] - centre, axis=2) <= radius
    whole, edge = near[inside.all(axis=1)], near[inside.any(axis=1) & ~inside.all(axis=1)]
    bary = subtriangle_centroids(WINDOW_SUBDIVISION)
    sub = np.einsum("sk,fkj->fsj", bary, mesh.vertices[mesh.faces[edge]])
    share = (np.linalg.norm(sub - centre, axis=2) <= radius).mean(axis=1)
    faces = np.concatenate([whole, edge[share > 0]])
    return faces, np.concatenate([mesh.face_areas[whole], (mesh.face_areas[edge] * share)[share > 0]])


def _sphere_section(mesh: Mesh, near: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """The window's edge (K, 2, 3): where the sphere cuts the faces `near` (`engine.mesh.contour_segments` of
    the distance from the centre less the radius)."""
    corners = mesh.faces[near]
    return contour_segments(mesh.vertices, corners, np.linalg.norm(mesh.vertices[corners] - centre, axis=2) - radius)


PLOT_HEADER = ("scan_circle", "name", "along_m", "up_m", "radius_m", "edge_cuts", "ends_inside", "p21_per_m",
               "p20_per_m2", "mean_length_m", "unbiased")


def scan_circle_plot(measures: Sequence[WindowMeasure], similarity: Similarity | None = None) -> Plot:
    """The scan circles on the face, coloured by P21 (`scan_circles`): a circle inventory (Rohrbaugh et al.
    2002), to see how intensity varies over the outcrop. Seen along the rock's mean normal (the windows'
    normals by area), along its strike (to the right) and up its dip, in the export frame's metres from the
    windows' mean centre; a biased window (`WindowMeasure.unbiased`) is drawn dashed. The title holds the
    pooled estimates; the table each window."""
    if not measures:
        raise InputError(None, "scan circle plot: expected one or more measured windows")
    scale = length_scale(similarity)
    up = np.array([0.0, 0.0, 1.0]) if similarity is None else similarity.R.T @ np.array([0.0, 0.0, 1.0])
    _, strike, dip = _plane_axes(sum(m.rock.normal * m.rock.area for m in measures), up)
    centres = np.array([m.circle.centre for m in measures])
    xy = (centres - centres.mean(axis=0)) @ np.column_stack([strike, dip]) * scale
    p21 = np.array([m.counts.p21 for m in measures]) / scale
    fig = Figure(figsize=FIGSIZE, layout="constrained")
    ax = fig.add_subplot()
    norm, cmap = Normalize(0.0, max(float(p21.max()), 1e-9)), colormaps["viridis"]  # as the P21 maps
    for m, (x, y), value in zip(measures, xy, p21):
        ax.add_patch(Circle((x, y), m.circle.radius * scale, facecolor=cmap(norm(value)), edgecolor="0.2",
                            ls="-" if m.unbiased else "--", lw=1.0))
        ax.annotate(str(m.circle.id), (x, y), ha="center", va="center", fontsize="small")
    reach = max(m.circle.radius for m in measures) * scale
    ax.set_xlim(xy[:, 0].min() - reach, xy[:, 0].max() + reach)
    ax.set_ylim(xy[:, 1].min() - reach, xy[:, 1].max() + reach)
    ax.set_aspect("equal")
    ax.set_xlabel("along the face (m)")
    ax.set_ylabel("up the face (m)")
    fig.colorbar(ScalarMappable(norm, cmap), ax=ax, label="P21 (m/m²)", location="bottom", shrink=0.6)
    pool = pooled_windows(measures)
    length = "" if not np.isfinite(pool.mean_length) else f", mean trace length {pool.mean_length * scale:.2f} m"
    ax.set_title(f"{len(measures)} scan circles: pooled P21 {pool.p21 / scale:.3g} /m{length}\n(dashed: biased by "
                 f"cut ends, unseen rock or the mesh's edge)", fontsize="medium")
    reports = [counts_report(m.counts, scale) for m in measures]
    rows = [(m.circle.id, m.circle.name, float(x), float(y), m.circle.radius * scale, r["edge_cuts"],
             r["ends_inside"], r["p21_per_m"], r["p20_per_m2"], r["mean_length_m"], m.unbiased)
            for m, (x, y), r in zip(measures, xy, reports)]
    return Plot("scan_circles", "Scan circles", fig, Table(PLOT_HEADER, rows))
