"""Writers for `tracemap export`: intensity and connectivity PLY, VTK PolyData, GeoPackage, the sets table and
the facet planes in CloudCompare Compass's columns.

Every writer puts coordinates in the export frame: local + origin in float64 (UTM-sized coordinates keep
their millimetres), then the registration if one is given (`engine.register.to_world`); normals and the
dip/dip direction derived from them are rotated with it. The files open in CloudCompare, MeshLab, ParaView
and QGIS; the GeoPackage is written with sqlite3 (GeoPackage 1.3: the three required tables and the
standard geometry blob), so no GDAL is needed.
"""

from __future__ import annotations

import sqlite3
import struct
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from engine.errors import InputError
from engine.io import dip_dipdir, write_csv
from engine.mesh import Mesh
from engine.orientation import normal_to_dip_dipdir
from engine.register import Similarity, length_scale, rotate_directions, to_world
from engine.sets import Facet
from engine.traces import Trace3D

SETS_HEADER = ("set", "n", "dip", "dip_direction", "kappa", "alpha95")
# the header of the *_planes.csv files that CloudCompare's Compass plugin exports (ccCompass::onSave)
PLANES_HEADER = ("Name", "Strike", "Dip", "Dip_Dir", "Cx", "Cy", "Cz", "Nx", "Ny", "Nz", "Sample_Radius", "RMS")
GPKG_TABLE = "traces"
WKB_POINT_Z, WKB_LINESTRING_Z, WKB_POLYGON = 1001, 1002, 3
GPKG_APPLICATION_ID = 0x47504B47  # "GPKG"
GPKG_VERSION = 10300  # GeoPackage 1.3.0


# ---------------------------------------------------------------------------------------------------------
# PLY


def write_intensity_ply(path: str | Path, mesh: Mesh, scalars: Mapping[str, np.ndarray], *,
                        similarity: Similarity | None = None) -> Path:
    """Binary PLY of the mesh with one float property per entry of `scalars` (each (V,), NaN allowed),
    e.g. `{**intensity.scalars(), **p32.scalars()}`. Vertices are float64 in the export frame, and the
    scalars, intensities per metre of the mesh, are divided by the registration's scale into per metre of it."""
    n = len(mesh.vertices)
    columns = {}
    per_length = 1.0 / length_scale(similarity)
    for name, values in scalars.items():
        values = np.asarray(values, dtype=np.float32) * np.float32(per_length)
        if values.shape != (n,):
            raise InputError(path, f"vertex property {name!r} has shape {values.shape}, expected ({n},)")
        columns[_property_name(path, name)] = ("<f4", values)
    faces = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("v", "<i4", 3)])
    faces["n"], faces["v"] = 3, mesh.faces
    return _write_ply(path, to_world(mesh.vertices, mesh.origin, similarity), columns, faces,
                      "tracemap intensity maps: P21, P32 (m^-1) per vertex")


def write_connectivity_ply(path: str | Path, traces: Sequence[Trace3D], origin: np.ndarray, *,
                           similarity: Similarity | None = None) -> Path:
    """Binary PLY point cloud of every trace vertex with its trace's `component`, `trace` id and `set`."""
    points = np.vstack([t.points for t in traces]) if traces else np.zeros((0, 3))
    counts = [len(t.points) for t in traces]
    columns = {name: ("<i4", np.repeat(np.array([getattr(t, attr) for t in traces], dtype=np.int32), counts))
               for name, attr in (("component", "component"), ("trace", "id"), ("set", "set_id"))}
    return _write_ply(path, to_world(points, origin, similarity), columns, None,
                      "tracemap trace vertices with connectivity component, trace id and set")


def _property_name(path: str | Path, name: str) -> str:
    if not name or not all(c.isalnum() or c == "_" for c in name):
        raise InputError(path, f"vertex property {name!r}: expected letters, digits and underscores")
    return name


def _write_ply(path: str | Path, xyz: np.ndarray, columns: dict[str, tuple[str, np.ndarray]],
               faces: np.ndarray | None, comment: str) -> Path:
    path = Path(path)
    types = {"<f4": "float", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element vertex {len(xyz)}",
              "property double x", "property double y", "property double z"]
    header += [f"property {types[kind]} {name}" for name, (kind, _) in columns.items()]
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    vertex = np.empty(len(xyz), dtype=[("xyz", "<f8", 3)] + [(name, kind) for name, (kind, _) in columns.items()])
    vertex["xyz"] = xyz
    for name, (_, values) in columns.items():
        vertex[name] = values
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vertex.tobytes())
        if faces is not None:
            f.write(faces.tobytes())
    return path


# ---------------------------------------------------------------------------------------------------------
# VTK


def write_vtp(path: str | Path, traces: Sequence[Trace3D], origin: np.ndarray, *,
              similarity: Similarity | None = None) -> Path:
    """VTK PolyData (.vtp) with one polyline per trace and cell data id, set, dip, dip_direction, eigen_dip,
    eigen_dip_direction (degrees, NaN without an orientation), component, surface_length (m, in the export
    frame) and kind (fracture, vein, fault, bedding; a string array)."""
    import pyvista as pv

    path = Path(path)
    points = np.vstack([t.points for t in traces]) if traces else np.zeros((0, 3))
    counts = np.array([len(t.points) for t in traces], dtype=np.int64)
    starts = np.cumsum(counts) - counts
    lines = np.concatenate([np.r_[n, np.arange(s, s + n)] for s, n in zip(starts, counts)]) if traces else []
    poly = pv.PolyData(to_world(points, origin, similarity), lines=np.asarray(lines, dtype=np.int64))
    poly.cell_data["id"] = np.array([t.id for t in traces], dtype=np.int64)
    poly.cell_data["set"] = np.array([t.set_id for t in traces], dtype=np.int64)
    for name, values in _orientations(traces, similarity).items():
        poly.cell_data[name] = values
    poly.cell_data["component"] = np.array([t.component for t in traces], dtype=np.int64)
    poly.cell_data["surface_length"] = length_scale(similarity) * np.array([t.surface_length for t in traces],
                                                                           dtype=float)
    poly.cell_data["kind"] = np.array([t.kind for t in traces], dtype=str)
    poly.save(str(path), binary=True)
    return path


def write_scanlines_vtp(path: str | Path, measures: Sequence, origin: np.ndarray, *,
                        similarity: Similarity | None = None) -> Path:
    """VTK PolyData (.vtp) of scanlines (`engine.scanline.ScanlineMeasure`): the rock each sampled, as line
    segments, and its crossings, as vertices; cell data `scanline` (id) and `kind` (0 rock, 1 crossing), and
    for crossings `trace`, `set` and `distance` (m along the line, in the export frame)."""
    import pyvista as pv

    path = Path(path)
    segments = [m.rock.section.reshape(-1, 3) for m in measures]
    crossings = [np.array([c.point for c in m.crossings]).reshape(-1, 3) for m in measures]
    points = np.vstack([*segments, *crossings]) if measures else np.zeros((0, 3))
    n_seg = sum(len(s) for s in segments) // 2
    n_cross = sum(len(c) for c in crossings)
    lines = np.column_stack([np.full(n_seg, 2), np.arange(2 * n_seg).reshape(-1, 2)]).ravel()
    verts = np.column_stack([np.ones(n_cross, np.int64), 2 * n_seg + np.arange(n_cross)]).ravel()
    poly = pv.PolyData(to_world(points, origin, similarity), lines=lines.astype(np.int64),
                       verts=verts.astype(np.int64))
    # VTK orders cells verts first, then lines
    ids = np.concatenate([[m.line.id] * len(m.crossings) for m in measures] +
                         [[m.line.id] * (len(m.rock.section)) for m in measures]).astype(np.int64) if measures else []
    crossing = [c for m in measures for c in m.crossings]
    pad = np.full(n_seg, -1)
    poly.cell_data["scanline"] = np.asarray(ids, dtype=np.int64)
    poly.cell_data["kind"] = np.r_[np.ones(n_cross, np.int64), np.zeros(n_seg, np.int64)]
    poly.cell_data["trace"] = np.r_[np.array([c.trace_id for c in crossing], dtype=np.int64), pad]
    poly.cell_data["set"] = np.r_[np.array([c.set_id for c in crossing], dtype=np.int64), pad]
    poly.cell_data["distance"] = np.r_[length_scale(similarity) * np.array([c.distance for c in crossing], float),
                                       np.full(n_seg, np.nan)]
    poly.save(str(path), binary=True)
    return path


WINDOW_KINDS = ("edge", "crossing", "end", "cut end")  # the `kind` codes of scan_circles.vtp


def write_scan_circles_vtp(path: str | Path, measures: Sequence, origin: np.ndarray, *,
                           similarity: Similarity | None = None) -> Path:
    """VTK PolyData (.vtp) of scan circles (`engine.scan_circle.WindowMeasure`): each window's edge on the rock
    as line segments, and where traces cross it, their ends inside and their cut ends inside, as vertices;
    cell data `scan_circle` (id) and `kind` (index in `WINDOW_KINDS`)."""
    import pyvista as pv

    path = Path(path)
    marks = [(m.circle.id, kind, points) for m in measures
             for kind, points in ((1, m.crossings), (2, m.ends), (3, m.cut_ends))]
    edges = [m.rock.edge.reshape(-1, 3) for m in measures]
    points = np.vstack([np.zeros((0, 3)), *edges, *(p for _, _, p in marks)])
    n_seg = sum(len(e) for e in edges) // 2
    n_marks = len(points) - 2 * n_seg
    lines = np.column_stack([np.full(n_seg, 2), np.arange(2 * n_seg).reshape(-1, 2)]).ravel()
    verts = np.column_stack([np.ones(n_marks, np.int64), 2 * n_seg + np.arange(n_marks)]).ravel()
    poly = pv.PolyData(to_world(points, origin, similarity), lines=lines.astype(np.int64),
                       verts=verts.astype(np.int64))
    # VTK orders cells verts first, then lines
    poly.cell_data["scan_circle"] = np.concatenate(
        [np.zeros(0, np.int64)] + [np.full(len(p), i, np.int64) for i, _, p in marks]
        + [np.full(len(m.rock.edge), m.circle.id, np.int64) for m in measures])
    poly.cell_data["kind"] = np.concatenate([np.zeros(0, np.int64)] + [np.full(len(p), k, np.int64) for _, k, p in marks]
                                            + [np.zeros(n_seg, np.int64)])
    poly.save(str(path), binary=True)
    return path


def _orientations(traces: Sequence[Trace3D], similarity: Similarity | None) -> dict[str, np.ndarray]:
    """Dip and dip direction (degrees) of each trace's final and eigen poles in the export frame, by
    attribute name; NaN where a trace has none."""
    final = np.array([dip_dipdir(t.normal, similarity) for t in traces]).reshape(-1, 2)
    eigen = np.array([dip_dipdir(t.extra.get("eigen_normal"), similarity) for t in traces]).reshape(-1, 2)
    return {"dip": final[:, 0], "dip_direction": final[:, 1], "eigen_dip": eigen[:, 0],
            "eigen_dip_direction": eigen[:, 1]}


# ---------------------------------------------------------------------------------------------------------
# GeoPackage

_UNDEFINED_SRS = (("Undefined cartesian SRS", -1, "NONE", -1, "undefined",
                   "undefined cartesian coordinate reference system"),
                  ("Undefined geographic SRS", 0, "NONE", 0, "undefined",
                   "undefined geographic coordinate reference system"),
                  ("WGS 84 geodetic", 4326, "EPSG", 4326,
                   'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,'
                   'AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0,'
                   'AUTHORITY["EPSG","8901"]],UNIT["degree",0.0174532925199433,AUTHORITY["EPSG","9122"]],'
                   'AXIS["Latitude",NORTH],AXIS["Longitude",EAST],AUTHORITY["EPSG","4326"]]',
                   "longitude/latitude coordinates in decimal degrees on the WGS 84 spheroid"))

_GPKG_SCHEMA = """
CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY,
    organization TEXT NOT NULL, organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL,
    description TEXT);
CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL,
    identifier TEXT UNIQUE, description TEXT DEFAULT '',
    last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')),
    min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
    CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL,
    geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
    CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name),
    CONSTRAINT uk_gc_table_name UNIQUE (table_name),
    CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
    CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
"""

_FEATURE_COLUMNS = (("id", "INTEGER"), ("set_id", "INTEGER"), ("dip", "DOUBLE"), ("dip_direction", "DOUBLE"),
                    ("eigen_dip", "DOUBLE"), ("eigen_dip_direction", "DOUBLE"), ("component", "INTEGER"), ("term_start", "TEXT"), ("term_end", "TEXT"),
                    ("censored", "BOOLEAN"), ("chord_length", "DOUBLE"), ("surface_length", "DOUBLE"), ("kind", "TEXT"))


_SCANLINE_COLUMNS = (("id", "INTEGER"), ("name", "TEXT"), ("length_m", "DOUBLE"), ("sampled_m", "DOUBLE"),
                     ("reach_m", "DOUBLE"), ("crossings", "INTEGER"), ("p10_per_m", "DOUBLE"),
                     ("p10_terzaghi_per_m", "DOUBLE"), ("mean_spacing_m", "DOUBLE"), ("spacing_cv", "DOUBLE"))
_WINDOW_COLUMNS = (("id", "INTEGER"), ("name", "TEXT"), ("radius_m", "DOUBLE"), ("edge_cuts", "INTEGER"),
                   ("ends_inside", "INTEGER"), ("censored_ends_inside", "INTEGER"), ("p21_per_m", "DOUBLE"),
                   ("p20_per_m2", "DOUBLE"), ("mean_length_m", "DOUBLE"), ("seen_share", "DOUBLE"),
                   ("area_m2", "DOUBLE"), ("edge_m", "DOUBLE"), ("open", "BOOLEAN"))


def write_geopackage(path: str | Path, traces: Sequence[Trace3D], origin: np.ndarray, crs: int | None = None, *,
                     crs_wkt: str | None = None, similarity: Similarity | None = None,
                     scanlines: Sequence[Mapping] = (), windows: Sequence[Mapping] = ()) -> Path:
    """GeoPackage with a LINESTRING Z layer "traces": one feature per trace with id, set_id, dip,
    dip_direction, eigen_dip, eigen_dip_direction, component, terminations, censored, lengths (m, in the
    export frame) and kind (fracture, vein, fault, bedding); given their reports in the export frame (`engine.scanline.scanline_report`,
    `engine.scan_circle.window_report`), a LINESTRING Z layer "scanlines" (start to end, with the P10 and
    spacing of all traces) and a POINT Z layer "scan_circles" (the centre, with the radius and Mauldon's
    counts and estimators: a GIS draws the window as the centre buffered by the radius).

    crs : EPSG code of the export frame (e.g. a UTM zone after registration); default an undefined
        cartesian frame. crs_wkt : its WKT definition, if known (else the code alone identifies it).
    An existing file at `path` is replaced.
    """
    world = [to_world(t.points, origin, similarity) for t in traces]
    angles = np.column_stack(list(_orientations(traces, similarity).values()))
    scale = length_scale(similarity)
    with _geopackage(path, crs, crs_wkt) as (db, srs_id):
        _gpkg_layer(db, GPKG_TABLE, "LINESTRING", srs_id, "3D fracture traces (tracemap)", _FEATURE_COLUMNS, world,
                    [(t.id, t.set_id, *_finite(a), t.component, t.term_start, t.term_end, int(t.censored),
                      scale * t.chord_length, scale * t.surface_length, t.kind) for t, a in zip(traces, angles)])
        if scanlines:
            _gpkg_layer(db, "scanlines", "LINESTRING", srs_id, "virtual scanlines (tracemap)", _SCANLINE_COLUMNS,
                        [np.array([r["start"], r["end"]]) for r in scanlines],
                        [(r["id"], r["name"], r["length_m"], r["sampled_m"], r["reach_m"], r["crossings"],
                          *(r["groups"]["all"][k] for k in ("p10_per_m", "p10_terzaghi_per_m", "mean_spacing_m",
                                                             "spacing_cv"))) for r in scanlines])
        if windows:
            _gpkg_layer(db, "scan_circles", "POINT", srs_id, "scan circles, Mauldon's estimators (tracemap)",
                        _WINDOW_COLUMNS, [np.array([r["centre"]]) for r in windows],
                        [tuple(r[name] for name, _ in _WINDOW_COLUMNS) for r in windows])
    return Path(path)


def write_polygon_geopackage(path: str | Path, table: str, description: str, rings: Sequence[np.ndarray],
                             columns: Sequence[tuple[str, str]], rows: Sequence[tuple], crs: int | None = None) -> Path:
    """GeoPackage with one layer `table` of 2D polygons, each one closed ring (N, 2) with its row of `columns`
    ((name, SQL type) pairs); crs : EPSG code of the coordinates, default an undefined cartesian frame. An
    existing file at `path` is replaced."""
    with _geopackage(path, crs, None) as (db, srs_id):
        _gpkg_layer(db, table, "POLYGON", srs_id, description, columns, rings, rows)
    return Path(path)


@contextmanager
def _geopackage(path: str | Path, crs: int | None, crs_wkt: str | None):
    """A new GeoPackage at `path` (replacing any file there) with its metadata tables and the spatial
    reference system of EPSG code `crs` (undefined cartesian without): (connection, srs_id) inside one
    transaction."""
    path = Path(path)
    srs_id = -1 if crs is None else int(crs)
    path.unlink(missing_ok=True)
    db = sqlite3.connect(path)
    try:
        with db:
            db.execute(f"PRAGMA application_id = {GPKG_APPLICATION_ID}")
            db.execute(f"PRAGMA user_version = {GPKG_VERSION}")
            db.executescript(_GPKG_SCHEMA)
            db.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", _UNDEFINED_SRS)
            if srs_id not in (-1, 0, 4326):
                db.execute("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, 'EPSG', ?, ?, ?)",
                           (f"EPSG:{srs_id}", srs_id, srs_id, crs_wkt or "undefined", "tracemap export frame"))
            yield db, srs_id
    finally:
        db.close()


def _gpkg_layer(db: sqlite3.Connection, table: str, kind: str, srs_id: int, description: str,
                columns: Sequence[tuple[str, str]], geometries: Sequence[np.ndarray], rows: Sequence[tuple]) -> None:
    """A feature table of `kind` (LINESTRING or POINT with Z, or POLYGON in 2D) registered in gpkg_contents and
    gpkg_geometry_columns, one feature per geometry ((N, 3), or a polygon's closed ring (N, 2)) and row of
    `columns`."""
    planar = kind == "POLYGON"
    points = np.vstack(geometries) if len(geometries) else np.full((1, 3), np.nan)  # no extent: NULLs
    lo, hi = points.min(axis=0), points.max(axis=0)
    db.execute(f"CREATE TABLE {table} (fid INTEGER PRIMARY KEY AUTOINCREMENT, geom {kind}, "
               f"{', '.join(f'{name} {sql}' for name, sql in columns)})")
    db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, description, min_x, min_y, max_x, "
               "max_y, srs_id) VALUES (?, 'features', ?, ?, ?, ?, ?, ?, ?)",
               (table, table, description, *_finite(lo[:2]), *_finite(hi[:2]), srs_id))
    db.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, ?, ?, 0)", (table, kind, srs_id, int(not planar)))
    db.executemany(f"INSERT INTO {table} (geom, {', '.join(n for n, _ in columns)}) "
                   f"VALUES ({', '.join('?' * (len(columns) + 1))})",
                   [(_gpkg_polygon(g, srs_id) if planar else _gpkg_geometry(g, srs_id), *(_finite([v])[0] if isinstance(v, float) else v for v in row))
                    for g, row in zip(geometries, rows)])  # NaN (no orientation, no end inside) as NULL


def _finite(values) -> list[float | None]:
    """SQL NULL for NaN."""
    return [float(v) if np.isfinite(v) else None for v in values]


def _gpkg_geometry(points: np.ndarray, srs_id: int) -> bytes:
    """GeoPackage geometry blob: header "GP", version 0, flags (little endian, XYZ envelope), srs_id,
    envelope (minx, maxx, miny, maxy, minz, maxz), then ISO WKB, little endian: a Point Z (type 1001) for one
    point, else a LineString Z (type 1002)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    flags = 0b0000_0101  # bit 0: little endian; bits 1–3: envelope code 2 (XYZ); empty 0; standard binary
    header = b"GP" + struct.pack("<BBi6d", 0, flags, srs_id, lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    coordinates = np.ascontiguousarray(points, dtype="<f8").tobytes()
    if len(points) == 1:
        return header + struct.pack("<BI", 1, WKB_POINT_Z) + coordinates
    return header + struct.pack("<BII", 1, WKB_LINESTRING_Z, len(points)) + coordinates


def _gpkg_polygon(ring: np.ndarray, srs_id: int) -> bytes:
    """GeoPackage geometry blob of a 2D polygon of one closed ring (N, 2): header with an XY envelope, then
    ISO WKB Polygon (type 3), little endian."""
    lo, hi = ring.min(axis=0), ring.max(axis=0)
    flags = 0b0000_0011  # bit 0: little endian; bits 1–3: envelope code 1 (XY)
    header = b"GP" + struct.pack("<BBi4d", 0, flags, srs_id, lo[0], hi[0], lo[1], hi[1])
    return (header + struct.pack("<BIII", 1, WKB_POLYGON, 1, len(ring))
            + np.ascontiguousarray(ring, dtype="<f8").tobytes())


# ---------------------------------------------------------------------------------------------------------
# sets


def write_sets_csv(path: str | Path, set_stats: Sequence) -> Path:
    """sets.csv: set, n, dip, dip_direction, kappa, alpha95 (degrees). Each entry is an object with the
    attributes id (or set), n, dip, dip_direction, kappa, alpha95 (`engine.sets.FractureSetStats`) or a
    plain sequence of those six values."""
    path = Path(path)
    rows = []
    for k, s in enumerate(set_stats):
        if isinstance(s, Sequence) and not isinstance(s, str):
            values = tuple(s)
        else:
            values = (getattr(s, "id", getattr(s, "set", None)), *(getattr(s, a, None) for a in SETS_HEADER[1:]))
        if len(values) != len(SETS_HEADER) or any(v is None for v in values):
            raise InputError(path, f"set entry {k}: expected {', '.join(SETS_HEADER)}")
        rows.append((int(values[0]), int(values[1]), *(_number(v, 2) for v in values[2:4]), _number(values[4], 3),
                     _number(values[5], 2)))
    write_csv(path, SETS_HEADER, rows)
    return path


def write_planes_csv(path: str | Path, facets: Sequence[Facet], origin: np.ndarray, *,
                     similarity: Similarity | None = None) -> Path:
    """planes.csv: the facets measured on the mesh in Compass's plane columns, so a user moving between the
    tools finds them where Compass puts them. Strike is the dip direction − 90° (right-hand rule), the normal
    points up, the centre is in the export frame, and the sample radius and RMS are in its units (metres,
    times the registration's scale)."""
    path = Path(path)
    scale = length_scale(similarity)
    rows = []
    for facet in facets:
        normal = rotate_directions(np.asarray(facet.normal, dtype=float), similarity)
        normal = normal if normal[2] >= 0 else -normal
        dip, dip_direction = (float(a) for a in normal_to_dip_dipdir(normal))
        centre = to_world(np.asarray(facet.centroid, dtype=float), origin, similarity)
        rows.append((f"facet{facet.id}", _number((dip_direction - 90.0) % 360.0, 2), _number(dip, 2),
                     _number(dip_direction, 2), *(f"{c:.4f}" for c in centre), *(_number(c, 6) for c in normal),
                     _number(facet.radius * scale, 4), _number(facet.rms * scale, 5)))
    write_csv(path, PLANES_HEADER, rows)
    return path


def _number(value, digits: int) -> str:
    value = float(value)
    return f"{value:.{digits}f}" if np.isfinite(value) else ""
