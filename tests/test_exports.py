"""Export writers round-trip: PLY (own parser and trimesh), VTP (pyvista), GeoPackage (sqlite3 + WKB, pyogrio)."""

import csv
import sqlite3
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from engine.errors import InputError
from engine.exports import (write_connectivity_ply, write_geopackage, write_intensity_ply, write_sets_csv,
                            write_vtp)
from engine.mesh import Mesh
from engine.orientation import dip_dipdir_to_normal
from engine.register import Similarity
from engine.traces import Trace3D
from tests.scenes import grid_wall

ORIGIN = np.array([512345.0, 4212345.0, 210.0])  # UTM-sized: must survive to the millimetre


def read_ply(path):
    """A minimal binary little-endian PLY reader: {element: structured array}."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    kinds = {"double": "<f8", "float": "<f4", "int": "<i4", "uchar": "u1"}
    elements, current = [], None
    for line in lines:
        words = line.split()
        if words[0] == "element":
            current = (words[1], int(words[2]), [])
            elements.append(current)
        elif words[0] == "property" and words[1] == "list":
            current[2].extend([("n", kinds[words[2]]), (words[4], kinds[words[3]], 3)])  # triangles only
        elif words[0] == "property":
            current[2].append((words[2], kinds[words[1]]))
    out, offset = {}, end
    for name, count, dtype in elements:
        arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        out[name] = arr
        offset += arr.nbytes
    assert offset == len(data)
    return out


def traces():
    rng = np.random.default_rng(0)
    out = []
    for k in range(3):
        p = np.cumsum(rng.normal(0, 0.05, (20 + k, 3)), axis=0) + k
        n = len(p)
        extra = {"eigen_normal": dip_dipdir_to_normal(50.0 + k, 100.0).tolist()} if k else {}
        out.append(Trace3D(10 + k, p, np.zeros((n, 2)), np.zeros(n), np.zeros(n), ("img",), component=k % 2,
                           set_id=k - 1, normal=dip_dipdir_to_normal(60.0 + k, 120.0) if k else None,
                           term_start="C" if k == 2 else "B", term_end="T", extra=extra))
    return out


def test_intensity_ply_round_trips_world_coordinates_and_scalars(tmp_path):
    v, f = grid_wall(4.0, 3.0, 0.5)
    mesh = Mesh(v, f, ORIGIN)
    p21 = np.linspace(0, 2, len(v))
    p21[3] = np.nan
    path = write_intensity_ply(tmp_path / "intensity.ply", mesh, {"p21": p21, "p32_set0": 2 * p21})
    ply = read_ply(path)
    xyz = np.column_stack([ply["vertex"][c] for c in "xyz"])
    np.testing.assert_allclose(xyz, v + ORIGIN, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ply["vertex"]["p21"], p21, rtol=1e-6, equal_nan=True)
    np.testing.assert_array_equal(ply["face"]["vertex_indices"], f)
    assert np.all(ply["face"]["n"] == 3)
    import trimesh

    loaded = trimesh.load(path, process=False)
    np.testing.assert_allclose(loaded.vertices, v + ORIGIN, atol=1e-9)
    np.testing.assert_allclose(loaded.metadata["_ply_raw"]["vertex"]["data"]["p32_set0"], 2 * p21, rtol=1e-6,
                               equal_nan=True)
    with pytest.raises(InputError, match="'p21' has shape \\(3,\\)"):
        write_intensity_ply(tmp_path / "bad.ply", mesh, {"p21": np.zeros(3)})
    with pytest.raises(InputError, match="'p 21': expected letters"):
        write_intensity_ply(tmp_path / "bad.ply", mesh, {"p 21": p21})


def test_intensity_ply_in_the_registered_frame(tmp_path):
    v, f = grid_wall(2.0, 2.0, 1.0)
    sim = Similarity(1.5, Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([10.0, 0, 0]),
                     np.zeros((3, 3)), np.zeros(3), 0.0)
    p21 = np.linspace(0.0, 3.0, len(v))  # per metre of the mesh
    ply = read_ply(write_intensity_ply(tmp_path / "r.ply", Mesh(v, f, [1.0, 2.0, 3.0]), {"p21": p21},
                                       similarity=sim))
    xyz = np.column_stack([ply["vertex"][c] for c in "xyz"])
    np.testing.assert_allclose(xyz, 1.5 * (v + [1, 2, 3]) @ sim.R.T + [10, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ply["vertex"]["p21"], p21 / 1.5, rtol=1e-6)  # per metre of the registered frame


def test_connectivity_ply_labels_every_trace_vertex(tmp_path):
    ts = traces()
    ply = read_ply(write_connectivity_ply(tmp_path / "connectivity.ply", ts, ORIGIN))["vertex"]
    assert len(ply) == sum(len(t.points) for t in ts) and "face" not in ply.dtype.names
    np.testing.assert_allclose(np.column_stack([ply[c] for c in "xyz"]), np.vstack([t.points for t in ts]) + ORIGIN,
                               atol=1e-9)
    np.testing.assert_array_equal(ply["trace"], np.repeat([10, 11, 12], [20, 21, 22]))
    np.testing.assert_array_equal(ply["component"], np.repeat([0, 1, 0], [20, 21, 22]))
    np.testing.assert_array_equal(ply["set"], np.repeat([-1, 0, 1], [20, 21, 22]))


def test_vtp_round_trips_lines_and_cell_data(tmp_path):
    import pyvista as pv

    ts = traces()
    poly = pv.read(write_vtp(tmp_path / "traces.vtp", ts, ORIGIN))
    assert poly.n_lines == 3 and poly.points.dtype == np.float64
    np.testing.assert_allclose(poly.points, np.vstack([t.points for t in ts]) + ORIGIN, atol=1e-9)
    np.testing.assert_array_equal(poly.cell_data["id"], [10, 11, 12])
    np.testing.assert_array_equal(poly.cell_data["set"], [-1, 0, 1])
    np.testing.assert_allclose(poly.cell_data["dip"], [np.nan, 61.0, 62.0], equal_nan=True)
    np.testing.assert_allclose(poly.cell_data["dip_direction"], [np.nan, 120.0, 120.0], equal_nan=True)
    np.testing.assert_allclose(poly.cell_data["eigen_dip"], [np.nan, 51.0, 52.0], equal_nan=True)
    np.testing.assert_allclose(poly.cell_data["eigen_dip_direction"], [np.nan, 100.0, 100.0], equal_nan=True)
    np.testing.assert_allclose(poly.cell_data["surface_length"], [t.surface_length for t in ts])
    assert list(poly.lines[:21]) == [20, *range(20)]
    turned = Similarity(1.0, Rotation.from_euler("z", -90, degrees=True).as_matrix(), np.zeros(3), np.zeros((3, 3)),
                        np.zeros(3), 0.0)  # a registration turns the dip direction with the frame
    poly = pv.read(write_vtp(tmp_path / "turned.vtp", ts, ORIGIN, similarity=turned))
    np.testing.assert_allclose(poly.cell_data["dip_direction"][1:], [210.0, 210.0])
    np.testing.assert_allclose(poly.cell_data["eigen_dip_direction"][1:], [190.0, 190.0])
    scaled = Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0)
    poly = pv.read(write_vtp(tmp_path / "scaled.vtp", ts, ORIGIN, similarity=scaled))  # lengths in its metres
    np.testing.assert_allclose(poly.cell_data["surface_length"], [2 * t.surface_length for t in ts])


def parse_gpkg_geometry(blob):
    """GeoPackage binary header + ISO WKB LineString Z → (srs_id, envelope (6,), points (N, 3))."""
    assert blob[:2] == b"GP" and blob[2] == 0
    flags = blob[3]
    assert flags & 1 and (flags >> 1) & 7 == 2 and not flags & 0b0010_0000  # little endian, XYZ envelope
    srs_id, *envelope = struct.unpack_from("<i6d", blob, 4)
    order, kind, n = struct.unpack_from("<BII", blob, 56)
    assert order == 1 and kind == 1002
    points = np.frombuffer(blob, dtype="<f8", count=3 * n, offset=65).reshape(n, 3)
    assert 65 + points.nbytes == len(blob)
    return srs_id, np.array(envelope), points


def test_geopackage_follows_the_spec_and_round_trips(tmp_path):
    ts = traces()
    path = write_geopackage(tmp_path / "traces.gpkg", ts, ORIGIN, crs=32630)
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA application_id").fetchone()[0] == 0x47504B47
    assert db.execute("PRAGMA user_version").fetchone()[0] == 10300
    srs = {row[0] for row in db.execute("SELECT srs_id FROM gpkg_spatial_ref_sys")}
    assert {-1, 0, 4326, 32630} <= srs
    contents = db.execute("SELECT table_name, data_type, srs_id FROM gpkg_contents").fetchall()
    assert contents == [("traces", "features", 32630)]
    geometry = db.execute("SELECT * FROM gpkg_geometry_columns").fetchall()
    assert geometry == [("traces", "geom", "LINESTRING", 32630, 1, 0)]
    rows = db.execute("SELECT geom, id, set_id, dip, dip_direction, component, term_start, censored, surface_length, "
                      "eigen_dip, eigen_dip_direction FROM traces ORDER BY fid").fetchall()
    db.close()
    for t, row in zip(ts, rows):
        srs_id, envelope, points = parse_gpkg_geometry(row[0])
        world = t.points + ORIGIN
        assert srs_id == 32630
        np.testing.assert_allclose(points, world, atol=1e-9)
        np.testing.assert_allclose(envelope, np.ravel(np.column_stack([world.min(0), world.max(0)])), atol=1e-9)
        assert row[1:3] == (t.id, t.set_id) and row[5:8] == (t.component, t.term_start, int(t.censored))
        assert row[8] == pytest.approx(t.surface_length)
    assert rows[0][3] is None and rows[1][3] == pytest.approx(61.0)  # no orientation: NULL
    assert rows[0][9] is None and rows[2][9:] == pytest.approx((52.0, 100.0))
    scaled = Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0)
    db = sqlite3.connect(write_geopackage(tmp_path / "scaled.gpkg", ts, ORIGIN, similarity=scaled))
    lengths = db.execute("SELECT chord_length, surface_length FROM traces ORDER BY fid").fetchall()
    db.close()
    np.testing.assert_allclose(lengths, [(2 * t.chord_length, 2 * t.surface_length) for t in ts], rtol=1e-12)


def test_geopackage_opens_in_gdal(tmp_path):
    pyogrio = pytest.importorskip("pyogrio")
    ts = traces()
    path = write_geopackage(tmp_path / "traces.gpkg", ts, ORIGIN, crs=32630)
    info = pyogrio.read_info(path)
    assert info["geometry_type"] == "LineString Z" and info["features"] == 3
    assert "32630" in str(info["crs"])
    frame = pyogrio.read_dataframe(path)
    np.testing.assert_allclose(np.asarray(frame.geometry.iloc[1].coords), ts[1].points + ORIGIN, atol=1e-9)
    assert list(frame["id"]) == [10, 11, 12]
    undefined = pyogrio.read_info(write_geopackage(tmp_path / "local.gpkg", ts, np.zeros(3)))
    assert undefined["features"] == 3


def test_sets_csv_from_set_statistics_or_plain_rows(tmp_path):
    stats = SimpleNamespace(id=0, n=41, dip=84.96, dip_direction=137.0, kappa=9.81, alpha95=2.345)  # as engine.sets
    path = write_sets_csv(tmp_path / "sets.csv", [stats, (1, 12, 88.0, 232.04, 13.4, float("nan"))])
    with open(path) as f:
        rows = list(csv.reader(f))
    assert rows == [["set", "n", "dip", "dip_direction", "kappa", "alpha95"],
                    ["0", "41", "84.96", "137.00", "9.810", "2.35"],
                    ["1", "12", "88.00", "232.04", "13.400", ""]]
    with pytest.raises(InputError, match="set entry 0: expected set, n, dip"):
        write_sets_csv(tmp_path / "bad.csv", [(1, 2, 3)])


def test_geopackage_layers_of_scanlines_and_scan_circles(tmp_path):
    """The reports as `tracemap export` gives them: a LINESTRING Z "scanlines" layer from start to end and a
    POINT Z "scan_circles" layer at the centres, their readouts as columns (None and NaN as NULL); GDAL reads
    all three layers."""
    line = {"id": 3, "name": "bench", "start": [500001.0, 4200000.0, 103.0], "end": [500009.0, 4200000.0, 103.0],
            "length_m": 8.0, "sampled_m": 7.5, "reach_m": 0.8, "crossings": 7,
            "groups": {"all": {"p10_per_m": 0.933, "p10_terzaghi_per_m": 1.1, "mean_spacing_m": None,
                               "spacing_cv": None}}}
    window = {"id": 2, "name": "", "centre": [500005.0, 4200000.0, 103.0], "radius_m": 1.0, "edge_cuts": 3,
              "ends_inside": 0, "censored_ends_inside": 0, "p21_per_m": 0.75, "p20_per_m2": 0.0,
              "mean_length_m": None, "seen_share": 1.0, "area_m2": 3.14, "edge_m": 6.28, "open": False}
    path = write_geopackage(tmp_path / "traces.gpkg", traces(), ORIGIN, crs=32630, scanlines=[line],
                            windows=[window])
    db = sqlite3.connect(path)
    assert db.execute("SELECT table_name, geometry_type_name, z FROM gpkg_geometry_columns ORDER BY table_name"
                      ).fetchall() == [("scan_circles", "POINT", 1), ("scanlines", "LINESTRING", 1),
                                       ("traces", "LINESTRING", 1)]
    geom, name, p10, spacing = db.execute("SELECT geom, name, p10_per_m, mean_spacing_m FROM scanlines").fetchone()
    _, _, points = parse_gpkg_geometry(geom)
    np.testing.assert_array_equal(points, [line["start"], line["end"]])
    assert (name, p10, spacing) == ("bench", 0.933, None)
    blob, cuts, length, is_open = db.execute("SELECT geom, edge_cuts, mean_length_m, open FROM scan_circles").fetchone()
    assert struct.unpack_from("<BI3d", blob, 56) == (1, 1001, *window["centre"]) and len(blob) == 56 + 29
    assert (cuts, length, is_open) == (3, None, 0)
    extent = db.execute("SELECT min_x, max_x FROM gpkg_contents WHERE table_name = 'scan_circles'").fetchone()
    assert extent == (500005.0, 500005.0)
    db.close()
    pyogrio = pytest.importorskip("pyogrio")
    assert [name for name, _ in pyogrio.list_layers(path)] == ["traces", "scanlines", "scan_circles"]
    assert pyogrio.read_info(path, layer="scan_circles")["geometry_type"] == "Point Z"
    frame = pyogrio.read_dataframe(path, layer="scan_circles")
    assert frame.geometry.iloc[0].coords[0] == pytest.approx(window["centre"]) and frame["p21_per_m"][0] == 0.75
