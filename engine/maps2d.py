"""Analysis of 2D trace maps: the terminations, topology, lengths and Kaplan–Meier of engine.topology and
engine.lengths, in the plane of a map (`tracemap analyse-map`).

Input is what fractopo and FracAbility read: LineString traces and a sampling-area polygon as GeoJSON,
GeoPackage or Shapefile. GeoJSON is parsed with `json`, GeoPackage (SQLite with GeoPackage/WKB geometry
blobs) with `sqlite3` and a small WKB reader, Shapefile with pyshp. Z and M coordinates are dropped;
coordinates are map units (a geographic CRS in degrees is refused where the file states it). Traces and
area whose files state different coordinate systems (by authority code, e.g. EPSG:3067) are refused; a
file that states none, or none with a code (an ESRI .prj), is taken to be in the other's.

The sampling area is the union of its polygons (each with its holes): where polygons overlap, or along an
edge two of them share, is inside the area, and an overlap counts once in its size. The traces are clipped
to the area; every end within `snap` of the area boundary, including every end made by clipping, is
censored (C, fractopo's E node). Pieces shorter than 2·snap are dropped, as fractopo does, since their two
ends cannot be told apart. The other ends are T (Y node) within `snap` of another trace's interior, else B
(I node); X nodes are crossings.
"""

from __future__ import annotations

import json
import re
import sqlite3
import struct
import sys
from collections.abc import Sequence
from contextlib import closing
from dataclasses import asdict, dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from engine.errors import InputError, Progress, report
from engine.io import atomic_directory, write_csv, write_json
from engine.lengths import N_BOOTSTRAP, LengthAnalysis, LengthTable, analyse_lengths, by_set
from engine.exports import write_polygon_geopackage
from engine.map_intensity import IntensityGrid, describe_grid, grid_features, grid_summary, intensity_grid
from engine.map_plots import map_plots, set_names
from engine.plots import Plot, save_figure, write_table_csv
from engine.relations import SetRelations, set_relations
from engine.rose import axial_mean, azimuth_groups, trace_azimuths
from engine.scan_circle import Mauldon, as_circle, circle_ring, pooled_counts
from engine.topology import (Connectivity, Crossings, NodeCounts, abutting_ends, connectivity, find_crossings,
                             near_segments, node_counts)

SNAP = 0.001
"""Default snap tolerance, map units: fractopo's default snap_threshold."""
MAX_CIRCLES = 10_000
"""The most circles a scan circle grid lays (each is measured on its own)."""

FORMATS = {".geojson": "GeoJSON", ".json": "GeoJSON", ".gpkg": "GeoPackage", ".shp": "Shapefile"}
SET_COLUMNS = ("set", "set_id", "f_set")
"""Attribute names taken as the set of a trace (case-insensitive) when no `set_column` is given."""
NODE_TYPES = {"B": "I", "T": "Y", "C": "E"}
Features = list[tuple[dict | None, dict]]
"""(GeoJSON-like geometry or None, attributes) of each feature of a file."""


@dataclass(frozen=True)
class MapTraces:
    """Trace polylines (N, 2) in map units, the set label of each (None without a set column) and the
    feature (0-based, in file order) each came from; a MultiLineString gives one trace per part. crs: the
    coordinate system the file states, as AUTHORITY:code (e.g. EPSG:3067), or None."""

    lines: list[np.ndarray]
    sets: list[str | None]
    feature: np.ndarray
    source: str
    crs: str | None = None


@dataclass(frozen=True)
class Area:
    """Sampling-area polygons, each a list of rings (M, 2): the exterior first, then its holes; the area is
    their union. crs as in `MapTraces`."""

    polygons: list[list[np.ndarray]]
    source: str
    crs: str | None = None

    @cached_property
    def boundary(self) -> tuple[np.ndarray, np.ndarray]:
        """Start and end points (E, 2) of the edges of the union's boundary, each with the area on its left."""
        return _union_boundary(self.polygons)

    @property
    def size(self) -> float:
        """Area of the union in square map units (Green's theorem over the boundary)."""
        a, b = self.boundary
        origin = self.polygons[0][0][0]  # a local origin (any point) keeps UTM-sized maps exact
        return 0.5 * float(_cross(a - origin, b - origin).sum())


@dataclass(frozen=True)
class CircleInventory:
    """The scan circles of radius `radius` (map units) laid on a grid wholly inside the area, each measured."""

    radius: float
    circles: tuple[Mauldon, ...]

    @property
    def pooled(self) -> Mauldon | None:
        """All circles as one (`engine.scan_circle.pooled_counts`); None without a circle."""
        return pooled_counts(self.circles) if self.circles else None


@dataclass(frozen=True)
class MapAnalysis:
    """Everything `analyse_map` measured; coordinates in map units.

    traces : the clipped traces; feature : the input feature of each; sets : set label of each.
    terminations : (start, end) B/T/C codes; abutting : (n, 2) the trace each T end abuts (else -1).
    relations : the abutting ends and crossings between and within sets (`engine.relations`).
    intensity : P20, P21, B22 and connection frequency, as fractopo (`_intensity`). lengths_by_set : of the
    traces of each set (one with no set is in `lengths` only). n_short : pieces
    dropped for being no longer than 2·snap. mauldon : Mauldon's estimators of the area when it is a circle
    (`engine.scan_circle`), else None; scan_circles : those of each scan circle asked for. grid : the P21
    and P20 samples on a grid (`engine.map_intensity`) when asked for, centres in map units. circle_grid :
    the scan circles of a circle inventory (`circle_inventory`) when asked for.
    """

    traces: list[np.ndarray]
    feature: np.ndarray
    sets: list[str | None]
    terminations: list[tuple[str, str]]
    abutting: np.ndarray
    crossings: Crossings
    nodes: NodeCounts
    connectivity: Connectivity
    relations: SetRelations
    area: float
    intensity: dict[str, float]
    lengths: LengthAnalysis
    lengths_by_set: dict[str, LengthAnalysis]
    n_short: int
    snap: float
    mauldon: Mauldon | None = None
    scan_circles: tuple[Mauldon, ...] = ()
    grid: IntensityGrid | None = None
    circle_grid: CircleInventory | None = None


@dataclass(frozen=True)
class MapOutput:
    """What `analyse_map` measured and wrote: the analysis, its plots by name (one skipped has no figure and
    says why), and the files it put in the output folder."""

    analysis: MapAnalysis
    plots: dict[str, Plot]
    files: tuple[Path, ...]


def analyse_map(traces_path: str | Path, area_path: str | Path | None, outdir: str | Path, *,
                snap: float = SNAP, layer: str | None = None, area_layer: str | None = None,
                set_column: str | None = None, n_bootstrap: int = N_BOOTSTRAP, seed: int = 0,
                scan_circles: Sequence[tuple[np.ndarray, float]] = (), grid: float | None = None,
                grid_radius: float | None = None, scan_circle_grid: float | None = None,
                progress: Progress | None = None) -> MapOutput:
    """`tracemap analyse-map TRACES AREA -o OUTDIR`: read, analyse, and write summary.json, nodes.csv,
    traces.csv, kaplan_meier.csv, rose.csv, relations.csv (when the traces have sets) and the figures
    (`engine.map_plots`: map.png, length_histogram.png, kaplan_meier.png, terminations.png, rose.png,
    relations.png) into `outdir` (all or nothing); with `grid`, the P21 map
    too (p21_grid.png, c_b_grid.png, p21_grid.csv, and p21_grid.gpkg for a GIS).

    snap : tolerance of the node rules, map units. layer, area_layer : GeoPackage layer names (needed when
    a file holds several). set_column : attribute with the set of each trace (default: `SET_COLUMNS`).
    n_bootstrap, seed : of the AD p-values (engine.lengths.fit_lengths). scan_circles : (centre, radius) of
    Mauldon's scan circles (map units), each inside the area. grid, grid_radius : cell and disc radius of
    the P21 map (`engine.map_intensity.intensity_grid`; map units). scan_circle_grid : radius of the
    circles of a circle inventory (`circle_inventory`; map units).
    """
    if area_path is None:
        raise InputError(traces_path, "no sampling area given: a 2D map needs the polygon of the mapped area, "
                                      "where traces are censored (E nodes) and which P20/P21 are divided by")
    report(progress, 0.0, "reading the map")
    traces = read_traces(traces_path, layer=layer, set_column=set_column)
    area = read_area(area_path, layer=area_layer)
    _check_same_crs(traces, area)
    report(progress, 0.1, "topology")
    result = analyse_traces(traces, area, snap=snap, n_bootstrap=n_bootstrap, seed=seed, scan_circles=scan_circles,
                            grid=grid, grid_radius=grid_radius, scan_circle_grid=scan_circle_grid)
    report(progress, 0.9, "writing")
    plots = map_plots(result, area.polygons)
    with atomic_directory(outdir) as scratch:
        write_json(scratch / "summary.json", summary(result, traces, area))
        write_csv(scratch / "nodes.csv", NODES_HEADER, node_rows(result))
        write_csv(scratch / "traces.csv", TRACES_HEADER, trace_rows(result))
        write_csv(scratch / "kaplan_meier.csv", KM_HEADER, kaplan_meier_rows(result))
        for plot in plots.values():
            if plot.figure is not None:
                save_figure(plot.figure, scratch / f"{plot.name}.png")
        write_table_csv(plots["rose"].table, scratch / "rose.csv")
        if result.relations.sets:
            write_table_csv(plots["relations"].table, scratch / "relations.csv")
        if result.grid is not None:
            write_table_csv(plots["p21_grid"].table, scratch / "p21_grid.csv")
            write_polygon_geopackage(scratch / "p21_grid.gpkg", "p21_grid", "P21 map of a 2D trace map (tracemap)",
                                     *grid_features(result.grid), crs=_epsg(traces.crs))
        files = tuple(Path(outdir) / f.name for f in sorted(scratch.iterdir()))
        report(progress, 1.0, "done")  # the last chance to cancel: then the files are moved into place
    return MapOutput(result, plots, files)


def report_lines(result: MapAnalysis) -> list[str]:
    """What a map's analysis found, for people (the command line's and the application's words): nodes and
    topology, intensity, lengths per group, Mauldon's estimators, the circle inventory, the P21 map."""
    n, i = result.nodes, result.intensity
    lines = [f"{len(result.traces)} traces in the area ({result.n_short} pieces too short to keep); nodes "
             f"{n.N_I} I, {n.N_Y} Y, {n.N_X} X, {n.N_E} E; connections per line {n.C_L:.2f}, per branch {n.C_B:.2f}",
             f"area {result.area:.6g}; P21 {i['P21']:.4g}, P20 {i['P20']:.4g} (map units); "
             f"{result.connectivity.n_components} connected groups, the largest "
             f"{result.connectivity.largest_length_fraction:.0%} of the trace length"]
    for label, a in {"all traces": result.lengths, **{f"set {k}": v for k, v in result.lengths_by_set.items()}}.items():
        km = a.kaplan_meier
        median = ("" if km is None else ", Kaplan–Meier median not reached (too many censored)"
                  if not np.isfinite(km.median) else f", Kaplan–Meier median {km.median:.4g}")
        lines.append(f"lengths, {label}: {a.n} traces ({a.n_censored} censored){median}"
                     + ("" if km is not None else f"; {a.message}"))
    for label, m in ([("the circular area", result.mauldon)] if result.mauldon else []) + \
            [(f"scan circle {k + 1}", m) for k, m in enumerate(result.scan_circles)]:
        lines.append(f"Mauldon, {label} (r {m.radius:g}): {m.ends} ends inside, {m.cuts} edge cuts: "
                     f"P21 {m.p21:.4g}, P20 {m.p20:.4g}, mean trace length {m.mean_length:.4g} (map units)")
    lines += result.relations.describe()
    if result.circle_grid is not None:
        lines.append(_inventory_line(result.circle_grid))
    if result.grid is not None:
        lines.append(describe_grid(result.grid))
    return lines


def _inventory_line(inventory: CircleInventory) -> str:
    m = inventory.pooled
    if m is None:
        return (f"scan circle grid: no circle of radius {inventory.radius:g} fits wholly inside the area; "
                "expected a smaller radius")
    return (f"scan circle grid: {len(inventory.circles)} circles of r {inventory.radius:g} pooled: {m.ends} ends "
            f"inside, {m.cuts} edge cuts: P21 {m.p21:.4g}, P20 {m.p20:.4g}, mean trace length {m.mean_length:.4g} "
            "(map units)")


def _epsg(crs: str | None) -> int | None:
    """The EPSG code of an AUTHORITY:code coordinate system, else None (written as undefined)."""
    match = re.fullmatch(r"EPSG:(\d+)", crs or "", flags=re.IGNORECASE)
    return int(match.group(1)) if match else None


def analyse_traces(traces: MapTraces, area: Area, *, snap: float = SNAP, n_bootstrap: int = N_BOOTSTRAP,
                   seed: int = 0, scan_circles: Sequence[tuple[np.ndarray, float]] = (), grid: float | None = None,
                   grid_radius: float | None = None, scan_circle_grid: float | None = None) -> MapAnalysis:
    """Clip to the area, classify end nodes, find crossings and groups, and analyse the lengths; Mauldon's
    estimators of the area if it is a circle, and of each scan circle (centre, radius), which must lie
    inside the area; the P21 map on a grid of cell `grid` if given (discs of `grid_radius`); a circle
    inventory of circles of radius `scan_circle_grid` if given."""
    if scan_circle_grid is not None and not (np.isfinite(scan_circle_grid) and scan_circle_grid > 0):
        raise InputError(None, f"scan circle grid radius {scan_circle_grid!r}: expected a positive length in map units")
    if not (np.isfinite(snap) and snap > 0):
        raise InputError(None, f"snap must be a positive number (map units), got {snap!r}")
    a, b = area.boundary
    origin = np.floor(np.concatenate([a, b]).min(axis=0))  # a local origin keeps UTM-sized maps exact
    boundary = a - origin, b - origin
    pieces, owner, n_short = _pieces_in_area(traces, area, boundary, origin, snap)
    codes, abutting = _terminations(pieces, boundary, snap)
    crossings = find_crossings(pieces, snap)
    nodes = node_counts(codes, crossings)
    sets = [traces.sets[k] for k in owner]
    table = LengthTable(np.arange(len(pieces)), np.array([s or "" for s in sets]),
                        np.array([np.linalg.norm(p[-1] - p[0]) for p in pieces]),
                        np.array([_length(p) for p in pieces]), np.array([pair.count("C") for pair in codes]))
    return MapAnalysis(
        [p + origin for p in pieces], traces.feature[owner], sets, codes, abutting,
        Crossings(crossings.traces, crossings.points + origin, crossings.distance), nodes,
        connectivity(pieces, snap),
        set_relations(sets, codes, abutting, crossings.traces, names=set_names(sets)), area.size, _intensity(nodes, float(table.surface.sum()), area.size),
        analyse_lengths(table.surface, table.censored, n_bootstrap=n_bootstrap, seed=seed),
        by_set(table.subset(table.set_id != ""), n_bootstrap=n_bootstrap, seed=seed), n_short, snap,
        _area_mauldon(area, nodes),
        tuple(scan_circle(pieces, boundary, np.asarray(c, dtype=float) - origin, r, snap, origin)
              for c, r in scan_circles),
        None if grid is None else _grid(pieces, sets, codes, crossings, boundary, origin, grid, grid_radius),
        None if scan_circle_grid is None else circle_inventory(pieces, boundary, scan_circle_grid, snap, origin))


def _grid(pieces: list[np.ndarray], sets: list[str | None], codes: list[tuple[str, str]], crossings: Crossings,
          boundary: tuple[np.ndarray, np.ndarray], origin: np.ndarray, cell: float,
          radius: float | None) -> IntensityGrid:
    """The P21 map in the local frame (`intensity_grid`), its centres moved back into map units."""
    ends = [(p[(0, -1)[k]], s, NODE_TYPES[pair[k]]) for p, s, pair in zip(pieces, sets, codes)
            for k in (0, 1) if pair[k] != "C"]
    grid = intensity_grid(pieces, boundary, cell, sets=sets, radius=radius,
                          ends=np.array([e for e, _, _ in ends]).reshape(-1, 2), end_sets=[s for _, s, _ in ends],
                          end_nodes=[n for _, _, n in ends], crossings=crossings.points)
    return replace(grid, x=grid.x + origin[0], y=grid.y + origin[1])


def _area_mauldon(area: Area, nodes: NodeCounts) -> Mauldon | None:
    """Mauldon's counts of a circular area: n = I + Y nodes (ends inside), m = E nodes, as fractopo's."""
    circle = as_circle(area.polygons)
    return None if circle is None else Mauldon(circle[0], circle[1], nodes.N_I + nodes.N_Y, nodes.N_E)


def scan_circle(pieces: list[np.ndarray], boundary: tuple[np.ndarray, np.ndarray], centre: np.ndarray,
                radius: float, snap: float, origin: np.ndarray) -> Mauldon:
    """Mauldon's counts of a circle inside the area (local frame; `origin` turns it back into map units):
    the area's traces clipped to it, ends within `snap` of its edge counted as cuts, the others as ends."""
    if not _circles_inside(centre[None], radius, boundary, snap)[0]:
        raise InputError(None, f"scan circle at ({', '.join(f'{x:g}' for x in centre + origin)}) of radius "
                               f"{radius:g}: it reaches beyond the sampling area; expected a circle inside it")
    ring = circle_ring(centre, radius)
    edge = ring[:-1], ring[1:]
    near = [p for p in pieces if np.all(p.min(axis=0) <= centre + radius) and np.all(p.max(axis=0) >= centre - radius)]
    inside = [piece for piece in clip_to_area(near, edge)[0] if _length(piece) > 2 * snap]
    ends = np.array([[p[0], p[-1]] for p in inside]).reshape(-1, 2)
    cuts = int(np.count_nonzero(near_segments(ends, *edge, snap)))
    return Mauldon(centre + origin, float(radius), len(ends) - cuts, cuts)


def _circles_inside(centres: np.ndarray, radius: float, boundary: tuple[np.ndarray, np.ndarray],
                    snap: float) -> np.ndarray:
    """True where the circle of `radius` about a centre (K, 2) lies inside the area, clear of its edge by
    more than `snap`: the centre inside, and no edge within r + snap of it."""
    a, b = boundary
    return _even_odd(centres, a, b) & ~near_segments(centres, a, b, radius + snap)


def circle_inventory(pieces: list[np.ndarray], boundary: tuple[np.ndarray, np.ndarray], radius: float,
                     snap: float, origin: np.ndarray) -> CircleInventory:
    """Rohrbaugh et al.'s (2002) circle inventory: circles of `radius` on a square grid 2r apart, as many
    as the area's bounding box holds clear of its sides, centred in it; those wholly inside the area are
    measured (`scan_circle`; local frame)."""
    a, b = boundary
    lo, hi = np.minimum(a.min(axis=0), b.min(axis=0)), np.maximum(a.max(axis=0), b.max(axis=0))
    counts = np.maximum(0, np.floor((hi - lo - 4 * snap) / (2 * radius))).astype(int)
    nx, ny = (int(n) for n in counts)
    lo = lo + (hi - lo - 2 * radius * counts) / 2  # the margin split between both sides
    if nx * ny > MAX_CIRCLES:
        raise InputError(None, f"scan circle grid of radius {radius:g}: {nx} × {ny} circles over the sampling "
                               f"area, more than {MAX_CIRCLES:,}; expected a larger radius")
    grid = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), axis=-1).reshape(-1, 2)
    centres = lo + radius * (1 + 2 * grid)
    centres = centres[_circles_inside(centres, radius, boundary, snap)]
    return CircleInventory(float(radius), tuple(scan_circle(pieces, boundary, c, radius, snap, origin)
                                                for c in centres))


def _check_same_crs(traces: MapTraces, area: Area) -> None:
    """Refuse traces and area that their files say are in different coordinate systems: the clipping, the
    lengths and the intensities would mix units."""
    if traces.crs and area.crs and traces.crs != area.crs:
        raise InputError(traces.source, f"the traces are in {traces.crs} but the sampling area {area.source} is in "
                                        f"{area.crs}; reproject one to the other's coordinate system")


def _pieces_in_area(traces: MapTraces, area: Area, boundary: tuple[np.ndarray, np.ndarray], origin: np.ndarray,
                    snap: float) -> tuple[list[np.ndarray], np.ndarray, int]:
    """The traces (local frame) clipped to the area (`boundary` in the local frame), less pieces no longer
    than 2·snap: pieces, the line each came from, and how many were dropped."""
    pieces, owner = clip_to_area([line - origin for line in traces.lines], boundary)
    keep = np.array([_length(p) > 2 * snap for p in pieces], dtype=bool)
    if not keep.any():
        raise InputError(traces.source, f"no trace lies inside the sampling area {area.source} "
                                        "(are both in the same coordinate system?)")
    return [p for p, k in zip(pieces, keep) if k], owner[keep], int(np.count_nonzero(~keep))


def _terminations(pieces: list[np.ndarray], boundary: tuple[np.ndarray, np.ndarray],
                  snap: float) -> tuple[list, np.ndarray]:
    """(start, end) codes: C within `snap` of the area boundary, else T, else B; and the trace each T abuts."""
    a, b = boundary
    ends = np.stack([[p[0], p[-1]] for p in pieces])
    on_boundary = near_segments(ends.reshape(-1, 2), a, b, snap).reshape(-1, 2)
    abutting = abutting_ends(pieces, snap)
    codes = np.where(on_boundary, "C", np.where(abutting >= 0, "T", "B"))
    return [(str(s), str(e)) for s, e in codes], np.where(codes == "T", abutting, -1)


def _intensity(nodes: NodeCounts, total_length: float, size: float) -> dict[str, float]:
    """fractopo's P20 = N_L/area, P21 = ΣL/area, B22 = P21·ΣL/N_B and connection frequency (N_Y + N_X)/area."""
    return {"P20": nodes.N_L / size, "P21": total_length / size,
            "B22": total_length / size * (total_length / nodes.N_B) if nodes.N_B else 0.0,
            "connection_frequency": (nodes.N_Y + nodes.N_X) / size}


def clip_to_area(lines: Sequence[np.ndarray],
                 boundary: tuple[np.ndarray, np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """The parts of each line (N, 2) inside the area bounded by the edges a→b of `boundary` (`Area.boundary`;
    even–odd rule), and the index of the line each part came from. Parts are cut exactly at the boundary."""
    a, b = boundary
    pieces, owner = [], []
    for k, line in enumerate(lines):
        for part in _inside_parts(np.asarray(line, dtype=float), a, b):
            pieces.append(part)
            owner.append(k)
    return pieces, np.array(owner, dtype=np.int64)


# -- reading -----------------------------------------------------------------------------------------

def read_traces(path: str | Path, *, layer: str | None = None, set_column: str | None = None) -> MapTraces:
    """LineString/MultiLineString traces from a GeoJSON, GeoPackage or Shapefile (module docstring)."""
    features, crs = _read_features(path, layer)
    if not features:
        raise InputError(path, "no features: the traces file is empty")
    column = _set_column(path, features, set_column)
    lines, sets, feature = [], [], []
    for k, (geometry, properties) in enumerate(features):
        for field, part in _parts(path, k, geometry, ("LineString", "MultiLineString"), "a trace"):
            line = _coordinates(path, k, part, field)
            if len(line) < 2:
                raise InputError(path, f"feature {k}: a trace has {len(line)} vertex; at least 2 are needed")
            if _length(line) == 0:
                raise InputError(path, f"feature {k}: a trace has zero length (all its vertices coincide)")
            lines.append(line)
            value = None if column is None else properties.get(column)
            sets.append(None if value is None else str(value))
            feature.append(k)
    return MapTraces(lines, sets, np.array(feature, dtype=np.int64), str(path), crs)


def read_area(path: str | Path, *, layer: str | None = None) -> Area:
    """Polygon/MultiPolygon sampling area(s) from a GeoJSON, GeoPackage or Shapefile."""
    features, crs = _read_features(path, layer)
    polygons = []
    for k, (geometry, _) in enumerate(features):
        for field, part in _parts(path, k, geometry, ("Polygon", "MultiPolygon"), "the sampling area"):
            rings = [_coordinates(path, k, ring, f"{field}[{r}]")
                     for r, ring in enumerate(_nested(path, k, part, field, "a list of rings"))]
            if not rings or any(len(r) < 3 for r in rings):
                raise InputError(path, f"feature {k}: a polygon ring has fewer than 3 vertices")
            polygons.append(rings)
    if not polygons:
        raise InputError(path, "no polygon: the sampling-area file holds no features")
    area = Area(polygons, str(path), crs)
    if not area.size > 0:
        raise InputError(path, "the sampling area has zero size")
    return area


def _read_features(path: str | Path, layer: str | None) -> tuple[Features, str | None]:
    """The features of a map file and the AUTHORITY:code of the coordinate system it states (or None)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise InputError(path, f"unknown map format {path.suffix!r}; expected GeoJSON (.geojson, .json), "
                               "GeoPackage (.gpkg) or Shapefile (.shp)")
    reader = {"GeoJSON": _read_geojson, "GeoPackage": _read_geopackage, "Shapefile": _read_shapefile}[kind]
    return reader(path, layer)


def _read_geojson(path: Path, layer: str | None) -> tuple[Features, str | None]:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad UTF-8 or JSON; RecursionError: deep nesting
        raise InputError(path, f"cannot read GeoJSON ({exc})") from exc
    kind = data.get("type") if isinstance(data, dict) else None
    if kind == "FeatureCollection":
        features = data.get("features", [])
        if not isinstance(features, list):
            raise InputError(path, f"features is {_show(features)}; expected a list of GeoJSON Features")
    elif kind == "Feature":
        features = [data]
    elif kind in ("LineString", "MultiLineString", "Polygon", "MultiPolygon"):
        features = [{"geometry": data}]
    else:
        raise InputError(path, f"GeoJSON type {_show(kind)}; expected a FeatureCollection, Feature or geometry")
    return [_geojson_feature(path, k, f) for k, f in enumerate(features)], _crs(path, _geojson_crs(path, data))


def _geojson_feature(path: Path, k: int, feature: object) -> tuple[dict | None, dict]:
    """(geometry, properties) of feature `k`, checked to be objects; null (RFC 7946 allows it) stands for none."""
    if not isinstance(feature, dict):
        raise InputError(path, f"feature {k} is {_show(feature)}; expected a GeoJSON Feature object")
    geometry, properties = feature.get("geometry"), feature.get("properties")
    if not isinstance(geometry, dict | None):
        raise InputError(path, f"feature {k}: geometry is {_show(geometry)}; expected a GeoJSON geometry object")
    if not isinstance(properties, dict | None):
        raise InputError(path, f"feature {k}: properties is {_show(properties)}; expected an object of attributes")
    return geometry, properties or {}


def _geojson_crs(path: Path, data: dict) -> str:
    """The name in a (pre-RFC 7946) named crs member, e.g. "urn:ogc:def:crs:EPSG::3067"; "" without one."""
    crs = data.get("crs")
    properties = crs.get("properties") if isinstance(crs, dict) else None
    name = properties.get("name", "") if isinstance(properties, dict) else ""
    if not isinstance(crs, dict | None) or not isinstance(properties, dict | None) or not isinstance(name, str):
        raise InputError(path, f"crs is {_show(crs)}; expected an object such as "
                               '{"type": "name", "properties": {"name": "EPSG:3067"}}')
    return name


def _read_geopackage(path: Path, layer: str | None) -> tuple[Features, str | None]:
    try:
        with closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
            table, column, srs = _geopackage_layer(path, db, layer)
            crs = _geopackage_crs(path, db, srs)
            quoted = '"' + str(table).replace('"', '""') + '"'  # an SQL identifier: quotes in it doubled
            cursor = db.execute(f"SELECT * FROM {quoted}")
            names = [d[0] for d in cursor.description]
            rows = cursor.fetchall()
    except sqlite3.Error as exc:
        raise InputError(path, f"cannot read GeoPackage ({exc})") from exc
    if column not in names:
        raise InputError(path, f"layer {table!r}: gpkg_geometry_columns names the geometry column {column!r}, "
                               f"which the table does not have (its columns: {', '.join(names)})")
    g = names.index(column)
    where = f"layer {table!r}, column {column!r}"
    return [(None if row[g] is None else _gpkg_geometry(path, f"{where}, feature {k}", row[g]),
             {n: v for n, v in zip(names, row) if n != column}) for k, row in enumerate(rows)], crs


def _geopackage_layer(path: Path, db: sqlite3.Connection, layer: str | None) -> tuple:
    """(table, geometry column, srs id) of the feature layer named `layer`, or of the only one."""
    tables = {str(row[0]).lower() for row in db.execute("SELECT name FROM sqlite_master WHERE type IN ('table', 'view')")}
    missing = [t for t in ("gpkg_geometry_columns", "gpkg_spatial_ref_sys") if t not in tables]
    if missing:
        raise InputError(path, f"not a GeoPackage of features: no table {' and no table '.join(missing)}")
    layers = db.execute("SELECT table_name, column_name, srs_id FROM gpkg_geometry_columns").fetchall()
    if layer is not None:
        layers = [row for row in layers if row[0] == layer] or _no_layer(path, layer, layers)
    if len(layers) != 1:
        names = ", ".join(str(row[0]) for row in layers) or "none"
        raise InputError(path, f"choose a layer: the GeoPackage holds feature layers {names}")
    if str(layers[0][0]).lower() not in tables:  # SQL names are case-insensitive
        raise InputError(path, f"layer {layers[0][0]!r} is listed in gpkg_geometry_columns but has no table")
    return layers[0]


def _geopackage_crs(path: Path, db: sqlite3.Connection, srs: object) -> str | None:
    """AUTHORITY:code of spatial reference system `srs` (`_crs`)."""
    row = db.execute("SELECT organization, organization_coordsys_id, definition FROM gpkg_spatial_ref_sys "
                     "WHERE srs_id = ?", (srs,)).fetchone()
    organization, code, definition = row or (None, None, None)
    stated = isinstance(organization, str) and organization.upper() != "NONE"  # NONE: GeoPackage's undefined
    return _crs(path, definition if isinstance(definition, str) else "",
                f"{organization.upper()}:{code}" if stated else None)


def _no_layer(path: Path, layer: str, layers: list) -> list:
    names = ", ".join(str(r[0]) for r in layers) or "none"
    raise InputError(path, f"no layer {layer!r}; the GeoPackage holds {names}")


def _read_shapefile(path: Path, layer: str | None) -> tuple[Features, str | None]:
    import shapefile  # pyshp

    prj = path.with_suffix(".prj")
    crs = _crs(path, prj.read_text(errors="replace") if prj.is_file() else "")
    try:
        with shapefile.Reader(str(path)) as reader:
            names = [f[0] for f in reader.fields[1:]]
            return [(None if s.shape.shapeType == shapefile.NULL else s.shape.__geo_interface__,
                     dict(zip(names, s.record))) for s in reader.iterShapeRecords()], crs
    except (shapefile.ShapefileException, OSError, struct.error) as exc:
        raise InputError(path, f"cannot read Shapefile ({exc})") from exc


def _gpkg_geometry(path: Path, where: str, blob: object) -> dict | None:
    """A GeoPackage geometry blob: 'GP' header (version, flags, SRS id, optional envelope), then WKB."""
    if not isinstance(blob, bytes):
        raise InputError(path, f"{where}: the geometry is {_show(blob)}, not a GeoPackage geometry blob")
    if blob[:2] != b"GP" or len(blob) < 8:
        raise InputError(path, f"{where}: the geometry is not a GeoPackage geometry blob (no 'GP' header)")
    flags = blob[3]
    if flags & 0x10:  # empty geometry
        return None
    indicator = (flags >> 1) & 0x7
    if indicator > 4:
        raise InputError(path, f"{where}: invalid GeoPackage envelope code {indicator}")
    try:
        return _wkb(blob, 8 + (0, 32, 48, 48, 64)[indicator])[0]
    except (struct.error, ValueError, IndexError) as exc:
        raise InputError(path, f"{where}: cannot decode the WKB geometry ({exc})") from exc


_WKB_TYPES = {2: "LineString", 3: "Polygon", 5: "MultiLineString", 6: "MultiPolygon"}
_WKB_PARTS = {5: 2, 6: 3}
"""The single type of the parts of each multi type: a part of another type is damage, not a trace."""


def _wkb(blob: bytes, offset: int, allowed: Sequence[int] = tuple(_WKB_TYPES)) -> tuple[dict, int]:
    """Decode one WKB geometry (ISO or EWKB Z/M flags) of a type in `allowed` at `offset`: (GeoJSON-like
    dict with (N, 2) arrays for point lists, next offset)."""
    if blob[offset] not in (0, 1):
        raise ValueError(f"byte-order mark {blob[offset]} at byte {offset} (expected 0 or 1)")
    order = "<" if blob[offset] == 1 else ">"
    (code,) = struct.unpack_from(order + "I", blob, offset + 1)
    offset += 5
    if code & 0x20000000:  # EWKB with an SRID
        offset += 4
    iso = (code & 0x0FFFFFFF) // 1000
    ndim = 2 + (bool(code & 0x80000000) or iso in (1, 3)) + (bool(code & 0x40000000) or iso in (2, 3))
    base = (code & 0x0FFFFFFF) % 1000
    if base not in allowed:
        raise ValueError(f"WKB geometry type {base} where a {' or '.join(_WKB_TYPES[t] for t in allowed)} "
                         "was expected")

    def count() -> int:
        nonlocal offset
        (n,) = struct.unpack_from(order + "I", blob, offset)
        offset += 4
        return n

    def points() -> np.ndarray:
        nonlocal offset
        n = count()
        xy = np.frombuffer(blob, dtype=order + "f8", count=n * ndim, offset=offset).reshape(n, ndim)[:, :2]
        offset += 8 * n * ndim
        return xy.astype(float)

    kind = _WKB_TYPES[base]
    if kind == "LineString":
        coordinates = points()
    elif kind == "Polygon":
        coordinates = [points() for _ in range(count())]
    else:
        parts = []
        for _ in range(count()):
            part, offset = _wkb(blob, offset, (_WKB_PARTS[base],))
            parts.append(part["coordinates"])
        coordinates = parts
    return {"type": kind, "coordinates": coordinates}, offset


def _crs(path: Path, definition: str, code: str | None = None) -> str | None:
    """The AUTHORITY:code of a stated coordinate system: `code` if given, else the one its definition (a
    GeoJSON crs name or WKT) ends with, else None. Refuses a geographic one (degrees): lengths would be in
    degrees."""
    text = definition.strip().upper()
    if text.startswith(("GEOGCS", "GEOGCRS", "GEODCRS")) or text.endswith(("CRS84", "EPSG::4326", "EPSG:4326")):
        raise InputError(path, "coordinates are geographic (degrees); reproject the map to a projected "
                               "coordinate system in metres (e.g. UTM) first")
    # WKT: the outermost AUTHORITY/ID closes the text; a name: EPSG:3067, urn:ogc:def:crs:EPSG::3067 or .../EPSG/0/3067
    found = (re.search(r'\b(?:AUTHORITY|ID)\[\s*"([^"]+)"\s*,\s*"?(\d+)"?\s*\]\s*\]$', text)
             or re.search(r"\b([A-Z]+)(?:::|:[\d.]*:|:|/[\d.]*/)(\d+)$", text))
    return code or (f"{found[1]}:{found[2]}" if found else None)


def _set_column(path: str | Path, features: Features, given: str | None) -> str | None:
    columns = {name for _, properties in features for name in properties}
    if given is not None:
        if given not in columns:
            raise InputError(path, f"no attribute {given!r}; the traces have {', '.join(sorted(columns)) or 'none'}")
        return given
    return next((c for c in sorted(columns) if c.lower() in SET_COLUMNS), None)


def _parts(path: str | Path, k: int, geometry: dict | None, kinds: tuple[str, str],
           what: str) -> list[tuple[str, list | np.ndarray]]:
    """(field, coordinates) of each single part of a geometry of one of `kinds` (single, multi)."""
    coordinates = None if geometry is None else geometry.get("coordinates")
    if coordinates is None or (isinstance(coordinates, list | tuple | np.ndarray) and len(coordinates) == 0):
        raise InputError(path, f"feature {k} has no geometry")
    kind = geometry.get("type")
    if kind not in kinds:
        raise InputError(path, f"feature {k} is a {kind}; {what} must be a {' or '.join(kinds)}")
    if kind == kinds[0]:
        return [("coordinates", coordinates)]
    return [(f"coordinates[{j}]", part)
            for j, part in enumerate(_nested(path, k, coordinates, "coordinates", f"a list of {kinds[0]}s"))]


def _nested(path: str | Path, k: int, value: object, field: str, expected: str) -> list | np.ndarray:
    """`value` checked to be a list (or, from WKB, an array)."""
    if not isinstance(value, list | tuple | np.ndarray):
        raise InputError(path, f"feature {k}: geometry {field} is {_show(value)}; expected {expected}")
    return value


def _coordinates(path: str | Path, k: int, coordinates: object, field: str) -> np.ndarray:
    """(N, 2) x, y of a list of positions, each checked to be two or more numbers with finite x and y."""
    points = _nested(path, k, coordinates, field, "a list of positions [x, y]")
    wkb = isinstance(points, np.ndarray)  # (N, 2) numbers already
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1)) if wkb else [
        i for i, c in enumerate(points) if not _is_position(c)]
    if len(bad):
        raise InputError(path, f"feature {k}: geometry {field}[{bad[0]}] is {_show(points[bad[0]])}; "
                               "expected a position [x, y] of finite numbers")
    return points if wkb else np.array([c[:2] for c in points], dtype=float).reshape(-1, 2)


def _is_position(c: object) -> bool:
    """A GeoJSON position: two or more numbers (not true/false), x and y finite floats."""
    return (isinstance(c, list | tuple) and len(c) >= 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) and abs(v) <= sys.float_info.max
                    for v in c[:2]))


def _show(value: object) -> str:
    """`value` as JSON, cut short: for messages about a malformed file."""
    text = json.dumps(value.tolist() if isinstance(value, np.ndarray) else value, default=repr)
    return text if len(text) <= 60 else text[:57] + "..."


# -- geometry ----------------------------------------------------------------------------------------

_BLOCK = 1 << 22
"""Most (point or edge) × edge pairs held in one numpy block: bounds memory for areas of many vertices."""


def _union_boundary(polygons: Sequence[Sequence[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Edges a→b of the boundary of the union of `polygons`, the area on their left: the edges of every
    polygon (exteriors anticlockwise, holes clockwise) cut where another polygon's edges meet them, less the
    pieces inside another polygon or shared with one (a piece two polygons share with the area on the same
    side is kept once)."""
    origin = np.concatenate([ring for polygon in polygons for ring in polygon]).min(axis=0)  # local: exact cuts
    edges = [_oriented_edges([ring - origin for ring in polygon]) for polygon in polygons]
    if len(edges) > 1:
        scale = float(np.ptp(np.concatenate([a for a, _ in edges]), axis=0).max())
        first = np.cumsum([0] + [len(a) for a, _ in edges])
        ids = [first[k] + np.arange(len(a)) for k, (a, _) in enumerate(edges)]
        edges = [_outer_edges(k, edges, ids, scale) for k in range(len(edges))]
    return np.concatenate([a for a, _ in edges]) + origin, np.concatenate([b for _, b in edges]) + origin


def _oriented_edges(polygon: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The ring edges of a polygon turned so that its inside is on their left."""
    return _ring_edges([ring if (_signed_area(ring) >= 0) == (i == 0) else ring[::-1]
                        for i, ring in enumerate(polygon)])


def _outer_edges(k: int, edges: list[tuple[np.ndarray, np.ndarray]], ids: list[np.ndarray],
                 scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The pieces of polygon k's edges on the boundary of the union of all (`_union_boundary`); ids: a
    number for each edge of each polygon (`_split`); `scale`: the size of the area, to which the tolerances
    of coincidence are relative."""
    a, b = edges[k]
    lo, hi = np.minimum(a, b).min(axis=0), np.maximum(a, b).max(axis=0)
    others = [j for j, (c, d) in enumerate(edges) if j != k and np.all(np.minimum(c, d).min(axis=0) <= hi)
              and np.all(np.maximum(c, d).max(axis=0) >= lo)]
    if not others:
        return a, b
    c, d = (np.concatenate([edges[j][i] for j in others]) for i in (0, 1))
    start, end = _split(a, b, c, d, ids[k], np.concatenate([ids[j] for j in others]))
    keep = np.any(start != end, axis=1)
    start, end = start[keep], end[keep]
    mid, v = 0.5 * (start + end), end - start
    # A piece lying on another polygon's edge is judged by the points just beside it, left and right
    on = near_segments(mid, c, d, 1e-9 * scale)[:, None]
    side = np.where(on, 1e-7 * scale * np.c_[-v[:, 1], v[:, 0]] / np.linalg.norm(v, axis=1)[:, None], 0.0)
    outside = ~_inside_any(mid - side, [edges[j] for j in others])  # the union does not go on past it
    unclaimed = ~_inside_any(mid + side, [edges[j] for j in others if j < k])  # no lower polygon has it
    return start[outside & unclaimed], end[outside & unclaimed]


def _inside_any(points: np.ndarray, polygons: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """True where a point is inside (even–odd) any of the polygons given by their edges."""
    inside = np.zeros(len(points), dtype=bool)
    for a, b in polygons:
        inside |= _even_odd(points, a, b)
    return inside


def _ring_edges(rings: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (E, 2) of every ring edge, closing rings that are not closed."""
    closed = [r if np.array_equal(r[0], r[-1]) else np.vstack([r, r[:1]]) for r in rings]
    return np.concatenate([r[:-1] for r in closed]), np.concatenate([r[1:] for r in closed])


def _split(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, ids: np.ndarray,
           other_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges a→b cut where an edge c→d crosses or touches them: start and end points of the pieces.

    Both edges of a crossing must be cut at the very same point, or the boundary made of their pieces has
    gaps that an even–odd ray can slip through: the point is the end of c→d it touches, else where the
    edge of lower id (`ids`, `other_ids`) puts it."""
    step = max(1, _BLOCK // max(len(c), 1))
    edge, fraction, point = [np.arange(len(a))] * 2, [np.zeros(len(a)), np.ones(len(a))], [a, b]
    for i in range(0, len(a), step):
        segment, other, s, t = _cuts(a[i:i + step], b[i:i + step], c, d)
        segment += i
        own = a[segment] * (1 - s)[:, None] + b[segment] * s[:, None]
        theirs = c[other] * (1 - t)[:, None] + d[other] * t[:, None]  # t = 0, 1 give c, d exactly
        use = (t == 0) | (t == 1) | (other_ids[other] < ids[segment])
        edge.append(segment)
        fraction.append(s)
        point.append(np.where(use[:, None], theirs, own))
    edge, fraction, point = (np.concatenate(v) for v in (edge, fraction, point))
    order = np.lexsort((fraction, edge))
    edge, point = edge[order], point[order]
    same = edge[:-1] == edge[1:]
    return point[:-1][same], point[1:][same]


def _cuts(a: np.ndarray, b: np.ndarray, c: np.ndarray,
          d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where an edge c→d not parallel to a segment a→b crosses or touches it between its ends: the index of
    the segment and of the edge, and the fraction along each."""
    lo, hi = np.minimum(a, b).min(axis=0), np.maximum(a, b).max(axis=0)
    near = np.all(np.minimum(c, d) <= hi, axis=1) & np.all(np.maximum(c, d) >= lo, axis=1)
    r, e, w = b - a, (d - c)[near], c[near][None, :, :] - a[:, None, :]
    denom = _cross(r[:, None, :], e[None, :, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = _cross(w, e[None, :, :]) / denom
        t = _cross(w, r[:, None, :]) / denom
    segment, edge = np.nonzero((denom != 0) & (s > 0) & (s < 1) & (t >= 0) & (t <= 1))
    return segment, np.flatnonzero(near)[edge], s[segment, edge], t[segment, edge]


def _inside_parts(line: np.ndarray, a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """Cut `line` where it crosses an edge a→b and keep the runs whose pieces are inside (even–odd)."""
    segment, _, s, _ = _cuts(line[:-1], line[1:], a, b)
    u = np.unique(np.r_[np.arange(len(line), dtype=float), segment + s])
    points = _along(line, u)
    inside = _even_odd(_along(line, 0.5 * (u[:-1] + u[1:])), a, b)
    change = np.flatnonzero(np.diff(np.r_[0, inside.astype(np.int8), 0]))
    return [points[i:j + 1] for i, j in zip(change[::2], change[1::2])]


def _along(line: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points at parameter u along a polyline: vertex i at u = i, linear in between."""
    i = np.minimum(np.floor(u).astype(int), len(line) - 2)
    f = (u - i)[:, None]
    return line[i] + f * (line[i + 1] - line[i])


def _even_odd(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """True where a point lies inside the rings made of edges a→b (crossing number, even–odd rule)."""
    inside = np.zeros(len(points), dtype=bool)
    step = max(1, _BLOCK // max(len(a), 1))
    for i in range(0, len(points), step):
        x, y = points[i:i + step, :1], points[i:i + step, 1:]
        straddle = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            crossing = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        inside[i:i + step] = (np.count_nonzero(straddle & (x < crossing), axis=1) % 2) == 1
    return inside


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


# -- writing -----------------------------------------------------------------------------------------

NODES_HEADER = ("node", "x", "y", "type", "trace", "other")
TRACES_HEADER = ("id", "feature", "set", "length", "chord", "azimuth", "censored", "n_censored_ends",
                 "term_start", "term_end", "component")
KM_HEADER = ("group", "length", "survival", "ci_low", "ci_high", "n_at_risk", "n_events")


def node_rows(result: MapAnalysis):
    """One row per node: end nodes (I, Y, E) of each trace, then X nodes; `other` is the trace abutted or
    crossed (-1 for none)."""
    node = 0
    for i, (trace, codes) in enumerate(zip(result.traces, result.terminations)):
        for k, code in enumerate(codes):
            x, y = trace[(0, -1)[k]]
            yield node, f"{x:.6f}", f"{y:.6f}", NODE_TYPES[code], i, int(result.abutting[i, k])
            node += 1
    for (i, j), (x, y) in zip(result.crossings.traces, result.crossings.points):
        yield node, f"{x:.6f}", f"{y:.6f}", "X", int(i), int(j)
        node += 1


def trace_rows(result: MapAnalysis):
    azimuths = trace_azimuths(result.traces)
    for i, (trace, codes) in enumerate(zip(result.traces, result.terminations)):
        n_censored = codes.count("C")
        yield (i, int(result.feature[i]), result.sets[i] or "", f"{_length(trace):.6f}",
               f"{np.linalg.norm(trace[-1] - trace[0]):.6f}", f"{azimuths[i]:.3f}", int(n_censored > 0),
               n_censored, codes[0], codes[1], int(result.connectivity.labels[i]))


def _azimuth_summary(result: MapAnalysis) -> dict:
    means = {k: (axial_mean(a, w), len(a)) for k, (a, w) in azimuth_groups(result.traces, result.sets).items()}
    entry = {k: {"mean": m.azimuth, "resultant": m.resultant, "n": n} for k, (m, n) in means.items()}
    return {"all": entry.pop("all"), "sets": entry, "weights": "length", "convention":
            "degrees clockwise from the map's +y, axial [0, 180); resultant: R̄ of the doubled angles"}


def kaplan_meier_rows(result: MapAnalysis):
    groups = {"all": result.lengths, **{f"set {k}": v for k, v in result.lengths_by_set.items()}}
    for name, analysis in groups.items():
        km = analysis.kaplan_meier
        if km is None:
            continue
        for row in zip(km.times, km.survival, km.ci_low, km.ci_high, km.n_at_risk, km.n_events):
            yield (name, *(f"{v:.8g}" for v in row[:4]), int(row[4]), int(row[5]))


def summary(result: MapAnalysis, traces: MapTraces, area: Area) -> dict:
    """What summary.json holds: inputs, counts, topology, intensity and length statistics."""
    groups = result.connectivity
    return _finite({
        "traces_file": traces.source, "area_file": area.source, "snap": result.snap,
        "features": len(np.unique(traces.feature)), "traces_in_area": len(result.traces),
        "short_pieces_dropped": result.n_short, "area": result.area,
        "nodes": asdict(result.nodes),
        "connectivity": {"components": groups.n_components, "largest_traces": int(groups.sizes[0]),
                         "largest_vertex_fraction": groups.largest_vertex_fraction,
                         "largest_length_fraction": groups.largest_length_fraction},
        "intensity": result.intensity,
        "mauldon": None if result.mauldon is None else result.mauldon.to_dict(),
        "scan_circles": [c.to_dict() for c in result.scan_circles],
        "p21_grid": None if result.grid is None else grid_summary(result.grid),
        "scan_circle_grid": _circle_grid_summary(result.circle_grid),
        "azimuth": _azimuth_summary(result),
        "relations": result.relations.to_dict() if result.relations.sets else None,
        "lengths": {"all": _length_summary(result.lengths),
                    "sets": {k: _length_summary(v) for k, v in result.lengths_by_set.items()}},
    })


def _circle_grid_summary(inventory: CircleInventory | None) -> dict | None:
    if inventory is None:
        return None
    pooled = inventory.pooled
    return {"radius": inventory.radius, "circles": len(inventory.circles),
            "pooled": None if pooled is None else pooled.to_dict(), "windows": [c.to_dict() for c in inventory.circles]}


def _length_summary(analysis: LengthAnalysis) -> dict:
    km = analysis.kaplan_meier
    out = {"n": analysis.n, "n_censored": analysis.n_censored, "message": analysis.message,
           "fits": [asdict(f) for f in analysis.fits]}
    if km is not None:
        out["kaplan_meier"] = {"median": km.median, "median_ci": list(km.median_ci), "rmst": km.rmst,
                               "rmst_ci": list(km.rmst_ci), "horizon": km.horizon, "confidence": km.confidence,
                               "ci_method": km.ci_method}
    return out


def _finite(value):
    """JSON has no Infinity or NaN: they are written as null."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
