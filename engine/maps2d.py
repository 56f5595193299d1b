"""Analysis of 2D trace maps: the terminations, topology, lengths and Kaplan–Meier of engine.topology and
engine.lengths, in the plane of a map (`tracemap analyse-map`).

Input is what fractopo and FracAbility read: LineString traces and a sampling-area polygon as GeoJSON,
GeoPackage or Shapefile. GeoJSON is parsed with `json`, GeoPackage (SQLite with GeoPackage/WKB geometry
blobs) with `sqlite3` and a small WKB reader, Shapefile with pyshp. Z and M coordinates are dropped;
coordinates are map units (a geographic CRS in degrees is refused where the file states it).

The traces are clipped to the area (even–odd rule over all rings, so holes work); every end within `snap`
of the area boundary, including every end made by clipping, is censored (C, fractopo's E node). Pieces
shorter than 2·snap are dropped, as fractopo does, since their two ends cannot be told apart. The other ends
are T (Y node) within `snap` of another trace's interior, else B (I node); X nodes are crossings.
"""

from __future__ import annotations

import json
import sqlite3
import struct
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from engine.errors import InputError, Progress, report
from engine.io import atomic_directory, write_csv, write_json
from engine.lengths import N_BOOTSTRAP, LengthAnalysis, LengthTable, analyse_lengths, by_set
from engine.topology import (Connectivity, Crossings, NodeCounts, abutting_ends, connectivity, find_crossings,
                             near_segments, node_counts)

SNAP = 0.001
"""Default snap tolerance, map units: fractopo's default snap_threshold."""

FORMATS = {".geojson": "GeoJSON", ".json": "GeoJSON", ".gpkg": "GeoPackage", ".shp": "Shapefile"}
SET_COLUMNS = ("set", "set_id", "f_set")
"""Attribute names taken as the set of a trace (case-insensitive) when no `set_column` is given."""
NODE_TYPES = {"B": "I", "T": "Y", "C": "E"}


@dataclass(frozen=True)
class MapTraces:
    """Trace polylines (N, 2) in map units, the set label of each (None without a set column) and the
    feature (0-based, in file order) each came from; a MultiLineString gives one trace per part."""

    lines: list[np.ndarray]
    sets: list[str | None]
    feature: np.ndarray
    source: str


@dataclass(frozen=True)
class Area:
    """Sampling-area polygons, each a list of rings (M, 2): the exterior first, then its holes."""

    polygons: list[list[np.ndarray]]
    source: str

    @property
    def rings(self) -> list[np.ndarray]:
        return [ring for polygon in self.polygons for ring in polygon]

    @property
    def size(self) -> float:
        """Area in square map units: exteriors less holes."""
        return float(sum(abs(_signed_area(p[0])) - sum(abs(_signed_area(h)) for h in p[1:])
                         for p in self.polygons))


@dataclass(frozen=True)
class MapAnalysis:
    """Everything `analyse_map` measured; coordinates in map units.

    traces : the clipped traces; feature : the input feature of each; sets : set label of each.
    terminations : (start, end) B/T/C codes; abutting : (n, 2) the trace each T end abuts (else -1).
    intensity : P20, P21, B22 and connection frequency, as fractopo (`_intensity`). n_short : pieces
    dropped for being no longer than 2·snap.
    """

    traces: list[np.ndarray]
    feature: np.ndarray
    sets: list[str | None]
    terminations: list[tuple[str, str]]
    abutting: np.ndarray
    crossings: Crossings
    nodes: NodeCounts
    connectivity: Connectivity
    area: float
    intensity: dict[str, float]
    lengths: LengthAnalysis
    lengths_by_set: dict[str, LengthAnalysis]
    n_short: int
    snap: float


def analyse_map(traces_path: str | Path, area_path: str | Path | None, outdir: str | Path, *,
                snap: float = SNAP, layer: str | None = None, area_layer: str | None = None,
                set_column: str | None = None, n_bootstrap: int = N_BOOTSTRAP, seed: int = 0,
                progress: Progress | None = None) -> MapAnalysis:
    """`tracemap analyse-map TRACES AREA -o OUTDIR`: read, analyse, and write summary.json, nodes.csv,
    traces.csv and kaplan_meier.csv into `outdir` (all or nothing).

    snap : tolerance of the node rules, map units. layer, area_layer : GeoPackage layer names (needed when
    a file holds several). set_column : attribute with the set of each trace (default: `SET_COLUMNS`).
    n_bootstrap, seed : of the AD p-values (engine.lengths.fit_lengths).
    """
    if area_path is None:
        raise InputError(traces_path, "no sampling area given: a 2D map needs the polygon of the mapped area, "
                                      "where traces are censored (E nodes) and which P20/P21 are divided by")
    report(progress, 0.0, "reading the map")
    traces = read_traces(traces_path, layer=layer, set_column=set_column)
    area = read_area(area_path, layer=area_layer)
    report(progress, 0.1, "topology")
    result = analyse_traces(traces, area, snap=snap, n_bootstrap=n_bootstrap, seed=seed)
    report(progress, 0.9, "writing")
    with atomic_directory(outdir) as scratch:
        write_json(scratch / "summary.json", summary(result, traces, area))
        write_csv(scratch / "nodes.csv", NODES_HEADER, node_rows(result))
        write_csv(scratch / "traces.csv", TRACES_HEADER, trace_rows(result))
        write_csv(scratch / "kaplan_meier.csv", KM_HEADER, kaplan_meier_rows(result))
    report(progress, 1.0, "done")
    return result


def analyse_traces(traces: MapTraces, area: Area, *, snap: float = SNAP, n_bootstrap: int = N_BOOTSTRAP,
                   seed: int = 0) -> MapAnalysis:
    """Clip to the area, classify end nodes, find crossings and groups, and analyse the lengths."""
    if not (np.isfinite(snap) and snap > 0):
        raise InputError(None, f"snap must be a positive number (map units), got {snap!r}")
    origin = np.floor(np.concatenate(area.rings).min(axis=0))  # a local origin keeps UTM-sized maps exact
    rings = [r - origin for r in area.rings]
    pieces, owner, n_short = _pieces_in_area(traces, area, rings, origin, snap)
    codes, abutting = _terminations(pieces, rings, snap)
    crossings = find_crossings(pieces, snap)
    nodes = node_counts(codes, crossings)
    sets = [traces.sets[k] for k in owner]
    table = LengthTable(np.arange(len(pieces)), np.array([s or "" for s in sets]),
                        np.array([np.linalg.norm(p[-1] - p[0]) for p in pieces]),
                        np.array([_length(p) for p in pieces]), np.array([pair.count("C") for pair in codes]))
    return MapAnalysis(
        [p + origin for p in pieces], traces.feature[owner], sets, codes, abutting,
        Crossings(crossings.traces, crossings.points + origin, crossings.distance), nodes,
        connectivity(pieces, snap), area.size, _intensity(nodes, float(table.surface.sum()), area.size),
        analyse_lengths(table.surface, table.censored, n_bootstrap=n_bootstrap, seed=seed),
        by_set(table, n_bootstrap=n_bootstrap, seed=seed) if any(sets) else {}, n_short, snap)


def _pieces_in_area(traces: MapTraces, area: Area, rings: list[np.ndarray], origin: np.ndarray,
                    snap: float) -> tuple[list[np.ndarray], np.ndarray, int]:
    """The traces (local frame) clipped to the area, less pieces no longer than 2·snap: pieces, the line
    each came from, and how many were dropped."""
    pieces, owner = clip_to_area([line - origin for line in traces.lines], rings)
    keep = np.array([_length(p) > 2 * snap for p in pieces], dtype=bool)
    if not keep.any():
        raise InputError(traces.source, f"no trace lies inside the sampling area {area.source} "
                                        "(are both in the same coordinate system?)")
    return [p for p, k in zip(pieces, keep) if k], owner[keep], int(np.count_nonzero(~keep))


def _terminations(pieces: list[np.ndarray], rings: list[np.ndarray], snap: float) -> tuple[list, np.ndarray]:
    """(start, end) codes: C within `snap` of the area boundary, else T, else B; and the trace each T abuts."""
    a, b = _ring_edges(rings)
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


def clip_to_area(lines: Sequence[np.ndarray], rings: Sequence[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """The parts of each line (N, 2) inside the area bounded by `rings` (even–odd rule), and the index of
    the line each part came from. Parts are cut exactly at the boundary."""
    a, b = _ring_edges(rings)
    pieces, owner = [], []
    for k, line in enumerate(lines):
        for part in _inside_parts(np.asarray(line, dtype=float), a, b):
            pieces.append(part)
            owner.append(k)
    return pieces, np.array(owner, dtype=np.int64)


# -- reading -----------------------------------------------------------------------------------------

def read_traces(path: str | Path, *, layer: str | None = None, set_column: str | None = None) -> MapTraces:
    """LineString/MultiLineString traces from a GeoJSON, GeoPackage or Shapefile (module docstring)."""
    features = _read_features(path, layer)
    if not features:
        raise InputError(path, "no features: the traces file is empty")
    column = _set_column(path, features, set_column)
    lines, sets, feature = [], [], []
    for k, (geometry, properties) in enumerate(features):
        for part in _parts(path, k, geometry, ("LineString", "MultiLineString"), "a trace"):
            line = _coordinates(path, k, part)
            if len(line) < 2:
                raise InputError(path, f"feature {k}: a trace has {len(line)} vertex; at least 2 are needed")
            if _length(line) == 0:
                raise InputError(path, f"feature {k}: a trace has zero length (all its vertices coincide)")
            lines.append(line)
            value = None if column is None else properties.get(column)
            sets.append(None if value is None else str(value))
            feature.append(k)
    return MapTraces(lines, sets, np.array(feature, dtype=np.int64), str(path))


def read_area(path: str | Path, *, layer: str | None = None) -> Area:
    """Polygon/MultiPolygon sampling area(s) from a GeoJSON, GeoPackage or Shapefile."""
    features = _read_features(path, layer)
    polygons = []
    for k, (geometry, _) in enumerate(features):
        for part in _parts(path, k, geometry, ("Polygon", "MultiPolygon"), "the sampling area"):
            rings = [_coordinates(path, k, ring) for ring in part]
            if not rings or any(len(r) < 3 for r in rings):
                raise InputError(path, f"feature {k}: a polygon ring has fewer than 3 vertices")
            polygons.append(rings)
    if not polygons:
        raise InputError(path, "no polygon: the sampling-area file holds no features")
    area = Area(polygons, str(path))
    if not area.size > 0:
        raise InputError(path, "the sampling area has zero size")
    return area


def _read_features(path: str | Path, layer: str | None) -> list[tuple[dict | None, dict]]:
    """(GeoJSON-like geometry or None, attributes) of each feature."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    kind = FORMATS.get(path.suffix.lower())
    if kind is None:
        raise InputError(path, f"unknown map format {path.suffix!r}; expected GeoJSON (.geojson, .json), "
                               "GeoPackage (.gpkg) or Shapefile (.shp)")
    reader = {"GeoJSON": _read_geojson, "GeoPackage": _read_geopackage, "Shapefile": _read_shapefile}[kind]
    return reader(path, layer)


def _read_geojson(path: Path, layer: str | None) -> list[tuple[dict | None, dict]]:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"cannot read GeoJSON ({exc})") from exc
    kind = data.get("type") if isinstance(data, dict) else None
    if kind == "FeatureCollection":
        features = data.get("features") or []
    elif kind == "Feature":
        features = [data]
    elif kind in ("LineString", "MultiLineString", "Polygon", "MultiPolygon"):
        features = [{"geometry": data, "properties": {}}]
    else:
        raise InputError(path, f"GeoJSON type {kind!r}; expected a FeatureCollection, Feature or geometry")
    _check_crs(path, ((data.get("crs") or {}).get("properties") or {}).get("name", ""))
    return [(f.get("geometry"), f.get("properties") or {}) for f in features]


def _read_geopackage(path: Path, layer: str | None) -> list[tuple[dict | None, dict]]:
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            layers = db.execute("SELECT table_name, column_name, srs_id FROM gpkg_geometry_columns").fetchall()
            if layer is not None:
                layers = [row for row in layers if row[0] == layer] or _no_layer(path, layer, layers)
            if len(layers) != 1:
                names = ", ".join(row[0] for row in layers) or "none"
                raise InputError(path, f"choose a layer: the GeoPackage holds feature layers {names}")
            table, column, srs = layers[0]
            definition = db.execute("SELECT definition FROM gpkg_spatial_ref_sys WHERE srs_id = ?", (srs,)).fetchone()
            _check_crs(path, definition[0] if definition else "")
            cursor = db.execute(f'SELECT * FROM "{table}"')
            names = [d[0] for d in cursor.description]
            rows = cursor.fetchall()
    except sqlite3.Error as exc:
        raise InputError(path, f"cannot read GeoPackage ({exc})") from exc
    g = names.index(column)
    return [(None if row[g] is None else _gpkg_geometry(path, k, row[g]),
             {n: v for n, v in zip(names, row) if n != column}) for k, row in enumerate(rows)]


def _no_layer(path: Path, layer: str, layers: list) -> list:
    raise InputError(path, f"no layer {layer!r}; the GeoPackage holds {', '.join(r[0] for r in layers) or 'none'}")


def _read_shapefile(path: Path, layer: str | None) -> list[tuple[dict | None, dict]]:
    import shapefile  # pyshp

    prj = path.with_suffix(".prj")
    _check_crs(path, prj.read_text(errors="replace") if prj.is_file() else "")
    try:
        with shapefile.Reader(str(path)) as reader:
            names = [f[0] for f in reader.fields[1:]]
            return [(None if s.shape.shapeType == shapefile.NULL else s.shape.__geo_interface__,
                     dict(zip(names, s.record))) for s in reader.iterShapeRecords()]
    except (shapefile.ShapefileException, OSError, struct.error) as exc:
        raise InputError(path, f"cannot read Shapefile ({exc})") from exc


def _gpkg_geometry(path: Path, k: int, blob: bytes) -> dict | None:
    """A GeoPackage geometry blob: 'GP' header (version, flags, SRS id, optional envelope), then WKB."""
    blob = bytes(blob)
    if blob[:2] != b"GP" or len(blob) < 8:
        raise InputError(path, f"feature {k}: geometry is not a GeoPackage blob")
    flags = blob[3]
    if flags & 0x10:  # empty geometry
        return None
    indicator = (flags >> 1) & 0x7
    if indicator > 4:
        raise InputError(path, f"feature {k}: invalid GeoPackage envelope code {indicator}")
    try:
        return _wkb(blob, 8 + (0, 32, 48, 48, 64)[indicator])[0]
    except (struct.error, ValueError, IndexError) as exc:
        raise InputError(path, f"feature {k}: cannot decode the WKB geometry ({exc})") from exc


_WKB_TYPES = {2: "LineString", 3: "Polygon", 5: "MultiLineString", 6: "MultiPolygon"}


def _wkb(blob: bytes, offset: int) -> tuple[dict, int]:
    """Decode one WKB geometry (ISO or EWKB Z/M flags) at `offset`: (GeoJSON-like dict, next offset)."""
    order = "<" if blob[offset] == 1 else ">"
    (code,) = struct.unpack_from(order + "I", blob, offset + 1)
    offset += 5
    if code & 0x20000000:  # EWKB with an SRID
        offset += 4
    iso = (code & 0x0FFFFFFF) // 1000
    ndim = 2 + (bool(code & 0x80000000) or iso in (1, 3)) + (bool(code & 0x40000000) or iso in (2, 3))
    base = (code & 0x0FFFFFFF) % 1000
    if base not in _WKB_TYPES:
        raise ValueError(f"WKB geometry type {base} (expected LineString, Polygon or their Multi types)")

    def count() -> int:
        nonlocal offset
        (n,) = struct.unpack_from(order + "I", blob, offset)
        offset += 4
        return n

    def points() -> list:
        nonlocal offset
        n = count()
        xy = np.frombuffer(blob, dtype=order + "f8", count=n * ndim, offset=offset).reshape(n, ndim)[:, :2]
        offset += 8 * n * ndim
        return xy.tolist()

    kind = _WKB_TYPES[base]
    if kind == "LineString":
        coordinates = points()
    elif kind == "Polygon":
        coordinates = [points() for _ in range(count())]
    else:
        parts = []
        for _ in range(count()):
            part, offset = _wkb(blob, offset)
            parts.append(part["coordinates"])
        coordinates = parts
    return {"type": kind, "coordinates": coordinates}, offset


def _check_crs(path: Path, definition: str) -> None:
    """Refuse coordinates that the file says are geographic (degrees): lengths would be in degrees."""
    text = definition.strip().upper()
    if text.startswith(("GEOGCS", "GEOGCRS", "GEODCRS")) or text.endswith(("CRS84", "EPSG::4326", "EPSG:4326")):
        raise InputError(path, "coordinates are geographic (degrees); reproject the map to a projected "
                               "coordinate system in metres (e.g. UTM) first")


def _set_column(path: str | Path, features: list[tuple[dict | None, dict]], given: str | None) -> str | None:
    columns = {name for _, properties in features for name in properties}
    if given is not None:
        if given not in columns:
            raise InputError(path, f"no attribute {given!r}; the traces have {', '.join(sorted(columns)) or 'none'}")
        return given
    return next((c for c in sorted(columns) if c.lower() in SET_COLUMNS), None)


def _parts(path: str | Path, k: int, geometry: dict | None, kinds: tuple[str, str], what: str) -> list:
    """Coordinates of each single part of a geometry of one of `kinds` (single, multi)."""
    if not geometry or geometry.get("coordinates") in (None, []):
        raise InputError(path, f"feature {k} has no geometry")
    kind = geometry.get("type")
    if kind not in kinds:
        raise InputError(path, f"feature {k} is a {kind}; {what} must be a {' or '.join(kinds)}")
    return [geometry["coordinates"]] if kind == kinds[0] else list(geometry["coordinates"])


def _coordinates(path: str | Path, k: int, coordinates: list) -> np.ndarray:
    try:
        xy = np.array([c[:2] for c in coordinates], dtype=float).reshape(-1, 2)
    except (TypeError, ValueError, IndexError) as exc:
        raise InputError(path, f"feature {k}: malformed coordinates ({exc})") from exc
    if not np.all(np.isfinite(xy)):
        raise InputError(path, f"feature {k}: NaN or infinite coordinates")
    return xy


# -- geometry ----------------------------------------------------------------------------------------

def _ring_edges(rings: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (E, 2) of every ring edge, closing rings that are not closed."""
    closed = [r if np.array_equal(r[0], r[-1]) else np.vstack([r, r[:1]]) for r in rings]
    return np.concatenate([r[:-1] for r in closed]), np.concatenate([r[1:] for r in closed])


def _inside_parts(line: np.ndarray, a: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    """Cut `line` where it crosses an edge a→b and keep the runs whose pieces are inside (even–odd)."""
    lo, hi = line.min(axis=0), line.max(axis=0)
    near = np.all(np.minimum(a, b) <= hi, axis=1) & np.all(np.maximum(a, b) >= lo, axis=1)
    p, r = line[:-1], np.diff(line, axis=0)
    e, w = (b - a)[near], a[near][None, :, :] - p[:, None, :]
    denom = _cross(r[:, None, :], e[None, :, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = _cross(w, e[None, :, :]) / denom
        t = _cross(w, r[:, None, :]) / denom
    cut = (denom != 0) & (s > 0) & (s < 1) & (t >= 0) & (t <= 1)
    segment, edge = np.nonzero(cut)
    u = np.unique(np.r_[np.arange(len(line), dtype=float), segment + s[segment, edge]])
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
    x, y = points[:, :1], points[:, 1:]
    straddle = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        crossing = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.count_nonzero(straddle & (x < crossing), axis=1) % 2) == 1


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _signed_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


# -- writing -----------------------------------------------------------------------------------------

NODES_HEADER = ("node", "x", "y", "type", "trace", "other")
TRACES_HEADER = ("id", "feature", "set", "length", "chord", "censored", "n_censored_ends", "term_start",
                 "term_end", "component")
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
    for i, (trace, codes) in enumerate(zip(result.traces, result.terminations)):
        n_censored = codes.count("C")
        yield (i, int(result.feature[i]), result.sets[i] or "", f"{_length(trace):.6f}",
               f"{np.linalg.norm(trace[-1] - trace[0]):.6f}", int(n_censored > 0), n_censored, codes[0], codes[1],
               int(result.connectivity.labels[i]))


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
        "features": int(len(np.unique(traces.feature))), "traces_in_area": len(result.traces),
        "short_pieces_dropped": result.n_short, "area": result.area,
        "nodes": asdict(result.nodes),
        "connectivity": {"components": groups.n_components, "largest_traces": int(groups.sizes[0]),
                         "largest_vertex_fraction": groups.largest_vertex_fraction,
                         "largest_length_fraction": groups.largest_length_fraction},
        "intensity": result.intensity,
        "lengths": {"all": _length_summary(result.lengths),
                    "sets": {k: _length_summary(v) for k, v in result.lengths_by_set.items()}},
    })


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
