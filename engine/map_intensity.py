"""P21 and P20 of a 2D trace map on a grid (`tracemap analyse-map --grid CELL`): the intensity map a 2D
mapper reads beside the totals, as fractopo's contour grid (`Network.contour_grid`: at each cell's
centre, a disc of radius 1.5 cells) and FracPaQ's circular-window maps.

fractopo divides a disc's trace length by the whole disc's area, so near the edge of the mapped area it
reports intensity falling to half (at a straight edge) or less (at a corner) where none is missing. Here
each sample is the part of the disc inside the sampling area: the traces clipped to the area are clipped
again to the disc (exactly, on each segment's chord), and that length is divided by the exact area of
disc ∩ area (Green's theorem over the area's boundary, each edge's triangle or sector with the centre).
Where under `min_share` of the disc is inside the area, the sample is too small to read and is left
blank (NaN), as the 3D maps leave vertices their sphere sees too little of.

P20 is fractopo's (N_I + N_Y) / 2 per area: half the trace ends inside the sample that the area's edge did
not make (I and Y nodes), so a trace wholly inside counts once. The I, Y and X nodes in each sample give
its connections per branch C_B and connection frequency, fractopo's, so connectivity is mapped as well.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import PathPatch
from matplotlib.path import Path
from scipy.spatial import cKDTree

from engine.errors import InputError
from engine.plots import FIGSIZE, Plot, Table

RADIUS_CELLS = 1.5
"""Default disc radius, in cells: fractopo's contour grid (√(cell area) · 1.5), so discs overlap and the map is smooth."""
MIN_SHARE = 0.25
"""A sample is read where at least this share of its disc lies inside the sampling area: a quarter, what a
disc centred on a right-angled corner keeps (at the default radius a rectangle's corner cells keep 0.49)."""
MAX_CELLS = 250_000
"""The most grid cells asked for at once (500 × 500): beyond, a cell is finer than any map can be read at."""
_CENTRES = 4096  # centres whose nearby segments are gathered at once


@dataclass(frozen=True)
class IntensityGrid:
    """Samples at the centres of a square grid of `cell` over the sampling area (map units).

    x (nx,), y (ny,) : the centres; radius : of each sample's disc; area (ny, nx) : of disc ∩ sampling
    area; length, ends : per group ("all", then each set) (ny, nx), the trace length and the uncensored
    trace ends in each sample; nodes : the I, Y and X nodes in each sample (all traces); min_share : the
    share of the disc a sample needs to be read.
    """

    x: np.ndarray
    y: np.ndarray
    cell: float
    radius: float
    area: np.ndarray
    length: dict[str, np.ndarray]
    ends: dict[str, np.ndarray]
    nodes: dict[str, np.ndarray]
    min_share: float = MIN_SHARE

    @property
    def share(self) -> np.ndarray:
        """The share of each disc inside the sampling area."""
        return self.area / (np.pi * self.radius ** 2)

    @property
    def sampled(self) -> np.ndarray:
        return self.share >= self.min_share

    def p21(self, group: str = "all") -> np.ndarray:
        """Trace length per area (map units⁻¹); NaN where not sampled."""
        return self._per_area(self.length[group])

    def p20(self, group: str = "all") -> np.ndarray:
        """Traces per area, (N_I + N_Y) / 2 per area (map units⁻²); NaN where not sampled."""
        return self._per_area(self.ends[group] / 2.0)

    def connections_per_branch(self) -> np.ndarray:
        """fractopo's C_B = (3N_Y + 4N_X) / N_B, N_B = (N_I + 3N_Y + 4N_X) / 2, of the nodes in each sample;
        NaN where not sampled or without a node (fractopo's 0 there would map as unconnected)."""
        i, y, x = (self.nodes[k] for k in "IYX")
        branches = (i + 3 * y + 4 * x) / 2
        return np.where(self.sampled & (branches > 0), (3 * y + 4 * x) / np.where(branches > 0, branches, 1.0), np.nan)

    def connection_frequency(self) -> np.ndarray:
        """(N_Y + N_X) per area (map units⁻²); NaN where not sampled."""
        return self._per_area(self.nodes["Y"] + self.nodes["X"])

    def _per_area(self, amount: np.ndarray) -> np.ndarray:
        out = np.full(self.area.shape, np.nan)
        ok = self.sampled
        out[ok] = amount[ok] / self.area[ok]
        return out


def intensity_grid(traces: Sequence[np.ndarray], boundary: tuple[np.ndarray, np.ndarray], cell: float, *,
                   ends: np.ndarray | None = None, sets: Sequence[str | None] | None = None,
                   end_sets: Sequence[str | None] | None = None, end_nodes: Sequence[str] | None = None,
                   crossings: np.ndarray | None = None, radius: float | None = None,
                   min_share: float = MIN_SHARE) -> IntensityGrid:
    """P21 and P20 samples on a grid of `cell` (map units) over the area bounded by the edges a→b of
    `boundary` (the area on their left, `engine.maps2d.Area.boundary`).

    traces : polylines (N, 2) already clipped to the area; sets : the set of each (None or "" for none).
    ends : (M, 2) the uncensored trace ends, end_sets the set of each, end_nodes the node of each ("I" or
    "Y"; default all I). crossings : (K, 2) the X nodes. radius : of the discs (default `RADIUS_CELLS`
    cells). Coordinates are best in a local frame (UTM-sized ones lose digits in the squares of the disc
    test).
    """
    radius = RADIUS_CELLS * cell if radius is None else radius
    _check(cell, radius, min_share)
    a, b = (np.asarray(v, dtype=float) for v in boundary)
    x, y = _centres(a, b, cell)
    centres = np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
    shape = (len(y), len(x))
    groups = _groups(sets, end_sets)
    length = length_in_discs(centres, radius, *_segments(traces, sets, groups, radius), len(groups))
    ends = np.zeros((0, 2)) if ends is None else np.asarray(ends, dtype=float).reshape(-1, 2)
    labels = np.array([s or "" for s in (end_sets or [""] * len(ends))], dtype=object)
    kinds = np.array(end_nodes if end_nodes is not None else ["I"] * len(ends), dtype=object)
    crossings = np.zeros((0, 2)) if crossings is None else np.asarray(crossings, dtype=float).reshape(-1, 2)
    within = {g: ends if g == "all" else ends[labels == g] for g in groups}
    nodes = {"I": ends[kinds == "I"], "Y": ends[kinds == "Y"], "X": crossings}
    return IntensityGrid(x, y, float(cell), float(radius), disc_area_inside(centres, radius, a, b).reshape(shape),
                         {g: length[:, k].reshape(shape) for k, g in enumerate(groups)},
                         {g: _count_within(centres, radius, p).reshape(shape) for g, p in within.items()},
                         {k: _count_within(centres, radius, p).reshape(shape) for k, p in nodes.items()}, min_share)


def _centres(a: np.ndarray, b: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The centres of the cells covering the boundary's bounding box from its lower-left corner."""
    lo, hi = np.minimum(a.min(axis=0), b.min(axis=0)), np.maximum(a.max(axis=0), b.max(axis=0))
    nx, ny = (max(1, int(np.ceil(n))) for n in (hi - lo) / cell)
    if nx * ny > MAX_CELLS:
        raise InputError(None, f"grid cell {cell:g}: {nx} × {ny} cells over the sampling area, more than "
                               f"{MAX_CELLS:,}; expected a larger cell")
    return lo[0] + cell * (np.arange(nx) + 0.5), lo[1] + cell * (np.arange(ny) + 0.5)


def _check(cell: float, radius: float, min_share: float) -> None:
    for name, value in (("grid cell", cell), ("grid radius", radius)):
        if not (np.isfinite(value) and value > 0):
            raise InputError(None, f"{name} {value!r}: expected a positive length in map units")
    if not 0 < min_share <= 1:
        raise InputError(None, f"min_share {min_share!r}: expected a share in (0, 1]")


def _groups(sets: Sequence[str | None] | None, end_sets: Sequence[str | None] | None) -> list[str]:
    """"all", then the sets named by traces or ends, sorted."""
    names = {s for s in (*(sets or ()), *(end_sets or ())) if s}
    return ["all", *sorted(names)]


def _segments(traces: Sequence[np.ndarray], sets: Sequence[str | None] | None, groups: list[str],
              radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The traces' segments cut into pieces no longer than `radius` (`_split`), and the group column
    (1 + set, 0 without one) of each."""
    column = {g: k for k, g in enumerate(groups)}
    lines = [np.asarray(t, dtype=float).reshape(-1, 2) for t in traces]
    a = np.concatenate([p[:-1] for p in lines] or [np.zeros((0, 2))])
    b = np.concatenate([p[1:] for p in lines] or [np.zeros((0, 2))])
    labels = np.concatenate([np.full(len(p) - 1, column[sets[k]] if sets and sets[k] else 0)
                             for k, p in enumerate(lines)] or [np.zeros(0, dtype=np.int64)])
    a, b, seg = _split(a, b, radius)
    return a, b, labels[seg].astype(np.int64)


def _split(a: np.ndarray, b: np.ndarray, longest: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments a→b cut into equal pieces no longer than `longest`, and the segment each came from: lengths
    and areas add, so sums over the pieces are unchanged, and a piece reaches at most longest/2 from its
    midpoint (what `_near_pairs` relies on)."""
    parts = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / longest)).astype(np.int64)
    seg = np.repeat(np.arange(len(a)), parts)
    step = (np.arange(len(seg)) - np.repeat(np.cumsum(parts) - parts, parts)) / parts[seg]
    d = (b - a)[seg]
    return a[seg] + step[:, None] * d, a[seg] + (step + 1.0 / parts[seg])[:, None] * d, seg


def _near_pairs(centres: np.ndarray, a: np.ndarray, b: np.ndarray, radius: float):
    """(centre, segment) index pairs, a batch of centres at a time, among which is every segment a→b that
    comes within `radius` of its centre (segments no longer than `radius`: found by their midpoints)."""
    if len(a) == 0:
        return
    tree = cKDTree(0.5 * (a + b))
    reach = radius + 0.5 * float(np.linalg.norm(b - a, axis=1).max())
    for start in range(0, len(centres), _CENTRES):
        near = tree.query_ball_point(centres[start:start + _CENTRES], reach)
        owner = np.repeat(np.arange(len(near)), [len(n) for n in near]) + start
        yield owner, np.fromiter((s for n in near for s in n), dtype=np.int64, count=len(owner))


def length_in_discs(centres: np.ndarray, radius: float, a: np.ndarray, b: np.ndarray,
                    group: np.ndarray | None = None, n_groups: int = 1) -> np.ndarray:
    """(K, n_groups) length of the segments a→b (S, 2) within `radius` of each centre (K, 2), by group
    (0 is all; a segment of group g > 0 counts in 0 and g). Segments should be no longer than `radius`
    (`_split`)."""
    group = np.zeros(len(a), dtype=np.int64) if group is None else group
    out = np.zeros((len(centres), n_groups))
    for owner, seg in _near_pairs(centres, a, b, radius):
        inside = _chord_length(a[seg] - centres[owner], b[seg] - centres[owner], radius)
        np.add.at(out[:, 0], owner, inside)
        extra = group[seg] > 0
        np.add.at(out, (owner[extra], group[seg][extra]), inside[extra])
    return out


def _chord_length(p: np.ndarray, q: np.ndarray, radius: float) -> np.ndarray:
    """Length of each segment p→q (centre at the origin) inside the circle of `radius`."""
    t1, t2, d = _circle_params(p, q, radius)
    return np.linalg.norm(d, axis=1) * np.maximum(0.0, np.minimum(t2, 1.0) - np.maximum(t1, 0.0))


def _circle_params(p: np.ndarray, q: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the line p + t(q − p) enters and leaves the circle (t1 ≤ t2; both 1 when it misses), and q − p."""
    d = q - p
    aa = np.einsum("ij,ij->i", d, d)
    bb = 2.0 * np.einsum("ij,ij->i", p, d)
    cc = np.einsum("ij,ij->i", p, p) - radius ** 2
    disc = bb ** 2 - 4.0 * aa * cc
    hit = (disc > 0) & (aa > 0)
    root = np.sqrt(np.where(hit, disc, 0.0))
    denominator = np.where(hit, 2.0 * aa, 1.0)
    return (np.where(hit, (-bb - root) / denominator, 1.0), np.where(hit, (-bb + root) / denominator, 1.0), d)


def disc_area_inside(centres: np.ndarray, radius: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,) area of the disc of `radius` about each centre (K, 2) inside the region bounded by the edges a→b
    (E, 2), the region on their left. Exact: Σ over the edges of the signed area of disc ∩ triangle
    (centre, a, b) (`_disc_triangles`). An edge that stays out of the disc adds its sector, r²/2 times the
    angle it subtends, and those angles sum to 2π inside the region and 0 outside; so the area is πr²
    where the centre is inside (`_inside`), plus, for the edges within r, what each adds beyond its sector
    (found from a k-d tree): linear in the cells and the edges near them, not in cells × edges."""
    inside = _inside(centres, a, b)
    out = np.where(inside, np.pi * radius ** 2, 0.0)
    a, b, _ = _split(a, b, radius)
    on_edge = np.zeros(len(centres), dtype=bool)
    for owner, seg in _near_pairs(centres, a, b, radius):
        p, q = a[seg] - centres[owner], b[seg] - centres[owner]
        np.add.at(out, owner, _disc_triangles(p, q, radius) - _sector(p, q, radius))
        on_edge[owner[_through_origin(p, q)]] = True
    if on_edge.any():  # a centre on an edge: its inside and its sectors are ambiguous, the sum over all edges is not
        out[on_edge] = [_disc_triangles(a - c, b - c, radius).sum() for c in centres[on_edge]]
    return out


def _disc_triangles(p: np.ndarray, q: np.ndarray, radius: float) -> np.ndarray:
    """Signed area of disc ∩ triangle (0, p, q) for each segment p→q (the disc of `radius` at the origin):
    each segment split where it crosses the circle, its chord a triangle and the rest arcs (sectors)."""
    t1, t2, d = _circle_params(p, q, radius)
    s1, s2 = np.clip(t1, 0.0, 1.0)[:, None], np.clip(t2, 0.0, 1.0)[:, None]
    enter, leave = p + s1 * d, p + s2 * d
    return _sector(p, enter, radius) + 0.5 * _cross(enter, leave) + _sector(leave, q, radius)


def _through_origin(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Segments p→q passing through the origin (within rounding)."""
    scale = np.linalg.norm(p, axis=1) * np.linalg.norm(q, axis=1)
    return (np.abs(_cross(p, q)) <= 1e-12 * scale) & (np.einsum("ij,ij->i", p, q) <= 0)


def _inside(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Even–odd rule for each point (K, 2) against the edges a→b, a row of equal y at a time: the edges'
    crossings of the row found once, then counted beyond each point's x (a grid has few rows)."""
    inside = np.zeros(len(points), dtype=bool)
    ys, row = np.unique(points[:, 1], return_inverse=True)
    order = np.argsort(row, kind="stable")
    for y, members in zip(ys, np.split(order, np.cumsum(np.bincount(row, minlength=len(ys)))[:-1])):
        spans = (a[:, 1] > y) != (b[:, 1] > y)
        pa, pb = a[spans], b[spans]
        xs = np.sort(pa[:, 0] + (y - pa[:, 1]) * (pb[:, 0] - pa[:, 0]) / (pb[:, 1] - pa[:, 1]))
        beyond = len(xs) - np.searchsorted(xs, points[members, 0], side="right")
        inside[members] = beyond % 2 == 1
    return inside


def _sector(u: np.ndarray, v: np.ndarray, radius: float) -> np.ndarray:
    return 0.5 * radius ** 2 * np.arctan2(_cross(u, v), np.einsum("ij,ij->i", u, v))


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]


def _count_within(centres: np.ndarray, radius: float, points: np.ndarray) -> np.ndarray:
    if len(points) == 0:
        return np.zeros(len(centres))
    return cKDTree(points).query_ball_point(centres, radius, return_length=True).astype(float)


# -- for people ----------------------------------------------------------------------------------------

GRID_COLUMNS = ("group", "x", "y", "area", "share", "length", "ends", "P21", "P20", "I", "Y", "X", "C_B",
                "connection_frequency")


def grid_table(grid: IntensityGrid) -> Table:
    """A row per sample and group (all first); the nodes and connectivity on the rows of all traces."""
    xx, yy = np.meshgrid(grid.x, grid.y)
    topology = np.column_stack([*(grid.nodes[k].ravel() for k in "IYX"), grid.connections_per_branch().ravel(),
                                grid.connection_frequency().ravel()])
    rows = []
    for g in grid.length:
        p21, p20 = grid.p21(g), grid.p20(g)
        rows += [(g, float(x), float(y), float(area), float(share), float(length), int(ends), _value(a), _value(b),
                  *((int(t[0]), int(t[1]), int(t[2]), _value(t[3]), _value(t[4])) if g == "all" else ("",) * 5))
                 for x, y, area, share, length, ends, a, b, t in zip(
                     xx.ravel(), yy.ravel(), grid.area.ravel(), grid.share.ravel(), grid.length[g].ravel(),
                     grid.ends[g].ravel(), p21.ravel(), p20.ravel(), topology)]
    return Table(GRID_COLUMNS, rows)


def grid_features(grid: IntensityGrid) -> tuple[list[np.ndarray], tuple[tuple[str, str], ...], list[tuple]]:
    """The samples read as GIS features: each cell's square ring, and columns x, y, area, share, length,
    ends, the nodes n_i, n_y, n_x, c_b and connection_frequency, then p21, p20 of all traces and `p21_<set>`,
    `p20_<set>` of each set (names made SQL-safe)."""
    names = {g: "" if g == "all" else "_" + _field(g) for g in grid.length}
    columns = (("x", "DOUBLE"), ("y", "DOUBLE"), ("area", "DOUBLE"), ("share", "DOUBLE"),
               ("length", "DOUBLE"), ("ends", "INTEGER"), ("n_i", "INTEGER"), ("n_y", "INTEGER"), ("n_x", "INTEGER"),
               ("c_b", "DOUBLE"), ("connection_frequency", "DOUBLE"),
               *((f"{kind}{suffix}", "DOUBLE") for suffix in names.values() for kind in ("p21", "p20")))
    xx, yy = np.meshgrid(grid.x, grid.y)
    per_area = {g: (grid.p21(g), grid.p20(g)) for g in grid.length}
    c_b, frequency = grid.connections_per_branch(), grid.connection_frequency()
    rings, rows = [], []
    h = grid.cell / 2
    for i, j in zip(*np.nonzero(grid.sampled)):
        x, y = float(xx[i, j]), float(yy[i, j])
        rings.append(np.array([[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h], [x - h, y - h]]))
        rows.append((x, y, float(grid.area[i, j]), float(grid.share[i, j]), float(grid.length["all"][i, j]),
                     int(grid.ends["all"][i, j]), *(int(grid.nodes[k][i, j]) for k in "IYX"), float(c_b[i, j]),
                     float(frequency[i, j]), *(float(v[i, j]) for pair in per_area.values() for v in pair)))
    return rings, columns, rows


def _field(name: str) -> str:
    return re.sub(r"\W", "_", name, flags=re.ASCII)


def _value(v: float) -> float | str:
    return float(v) if np.isfinite(v) else ""


def grid_summary(grid: IntensityGrid) -> dict:
    """What summary.json says of the grid: its layout and, per group, P21 and P20 over the samples read."""
    def stats(values: np.ndarray) -> dict:
        v = values[np.isfinite(values)]
        if len(v) == 0:
            return {"mean": None, "min": None, "max": None, "cv": None}
        mean = float(v.mean())
        return {"mean": mean, "min": float(v.min()), "max": float(v.max()),
                "cv": float(v.std() / mean) if mean > 0 else None}
    return {"cell": grid.cell, "radius": grid.radius, "min_share": grid.min_share,
            "columns": len(grid.x), "rows": len(grid.y), "sampled": int(grid.sampled.sum()),
            "groups": {g: {"P21": stats(grid.p21(g)), "P20": stats(grid.p20(g))} for g in grid.length},
            "connections_per_branch": stats(grid.connections_per_branch()),
            "connection_frequency": stats(grid.connection_frequency())}


def describe_grid(grid: IntensityGrid) -> str:
    """One line for people: how many samples were read and the spread of P21 over them."""
    p21 = grid.p21()
    read = p21[np.isfinite(p21)]
    spread = (f"P21 {read.min():.4g} to {read.max():.4g}, mean {read.mean():.4g} (map units)" if len(read)
              else "no cell read: the discs reach too far out of the area; expected a smaller cell or radius")
    return (f"P21 map: {len(read)} of {p21.size} cells of {grid.cell:g} read (discs of radius {grid.radius:g}, "
            f"at least {grid.min_share:.0%} inside the area): {spread}")


MAPS = {"p21": ("P21", "P21 (map units⁻¹)"), "c_b": ("Connections per branch", "C_B (0 to 2)")}
"""The measures `intensity_grid_plot` maps: name → (title, colour bar label)."""


def intensity_grid_plot(grid: IntensityGrid, traces: Sequence[np.ndarray],
                        polygons: Sequence[Sequence[np.ndarray]], measure: str = "p21") -> Plot:
    """The map of a measure (`MAPS`: P21 of all traces, or connections per branch on its whole range 0–2):
    each sample's cell coloured, blank where not read and clipped to the sampling area (`polygons`: each a
    list of rings, exterior first, as `engine.maps2d.Area`), with the traces and the area's outline over it;
    map units, +y up, equal scale. Its table is the whole grid's (`grid_table`)."""
    title, label = MAPS[measure]
    values = np.ma.masked_invalid(grid.p21() if measure == "p21" else grid.connections_per_branch())
    top = 2.0 if measure == "c_b" else (float(values.max()) if values.count() else 0.0) or 1.0
    fig = Figure(figsize=FIGSIZE, layout="compressed")  # "constrained" put the y label off a map with a colour bar
    ax = fig.add_subplot()
    edges_x = grid.x[0] - grid.cell / 2 + grid.cell * np.arange(len(grid.x) + 1)
    edges_y = grid.y[0] - grid.cell / 2 + grid.cell * np.arange(len(grid.y) + 1)
    mesh = ax.pcolormesh(edges_x, edges_y, values, cmap="viridis", norm=Normalize(0.0, top), shading="flat")
    outline = PathPatch(area_path(polygons), facecolor="none", edgecolor="black", linewidth=1.0)
    ax.add_patch(outline)
    mesh.set_clip_path(outline)
    fig.colorbar(mesh, ax=ax, label=label, shrink=0.85)
    for line in traces:
        ax.plot(*np.asarray(line).T, color="white", linewidth=0.6, alpha=0.9)
    map_axes(ax)
    ax.set_title(f"{title}, discs of radius {grid.radius:g} every {grid.cell:g} "
                 f"({int(grid.sampled.sum())} of {grid.area.size} read)", fontsize="medium")
    return Plot(f"{measure}_grid", f"{title} map", fig, grid_table(grid))


def map_axes(ax) -> None:
    """Axes of a map: equal scale, x and y, coordinates in full (a UTM northing as 6700000, not +6.7e6)."""
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.ticklabel_format(useOffset=False, style="plain")


def area_path(polygons: Sequence[Sequence[np.ndarray]]) -> Path:
    """A matplotlib path of the union of the polygons: exteriors anticlockwise, holes clockwise, so that the
    nonzero winding rule fills exactly the union (a hole another polygon covers stays filled)."""
    rings = []
    for polygon in polygons:
        for k, ring in enumerate(polygon):
            ring = np.asarray(ring, dtype=float)
            anticlockwise = _cross(ring, np.roll(ring, -1, axis=0)).sum() > 0
            rings.append(ring if anticlockwise == (k == 0) else ring[::-1])
    return Path.make_compound_path(*(Path(r, closed=True) for r in rings))
