import csv
import json
import os
import sqlite3

import numpy as np
import pytest

from engine.errors import InputError
from engine.maps2d import Area, MapTraces, analyse_map, analyse_traces, clip_to_area, read_area, read_traces

os.environ.setdefault("FRACTOPO_DISABLE_CACHE", "1")  # fractopo would cache to ./.cache otherwise

OFFSET = np.array([500_000.0, 6_700_000.0])  # UTM-sized coordinates
SHELL = np.array([[0, 0], [100, 0], [100, 60], [60, 100], [0, 100], [0, 0]], float)  # not convex
HOLE = np.array([[30, 30], [45, 30], [45, 45], [30, 45], [30, 30]], float)


def random_network(seed, n1=150, n2=250, size=100.0, p_abut=0.6):
    """Two sets of straight traces in and around [0, size]²: set 2 traces end exactly on set 1 traces (Y
    nodes) or cross them (X nodes); set 1 traces also cross each other; many run out of the area (E)."""
    rng = np.random.default_rng(seed)
    lines, sets = [], []
    for _ in range(n1):
        c = rng.uniform(-0.1 * size, 1.1 * size, 2)
        d = _unit(rng.normal(30, 8))
        h = rng.lognormal(np.log(0.25 * size), 0.5) / 2
        lines.append(np.array([c - h * d, c + h * d]))
        sets.append("1")
    set1 = list(lines)
    for _ in range(n2):
        c = rng.uniform(-0.1 * size, 1.1 * size, 2)
        d = _unit(rng.normal(120, 10))
        h = rng.lognormal(np.log(0.2 * size), 0.6) / 2
        ends = [c + sign * _reach(c, sign * d, h, set1 if rng.random() < p_abut else []) * d for sign in (-1, 1)]
        lines.append(np.array(ends))
        sets.append("2")
    return lines, sets


def _unit(degrees):
    return np.array([np.cos(np.radians(degrees)), np.sin(np.radians(degrees))])


def _reach(c, d, h, stops):
    """Distance from c along d to the first trace of `stops` within h, else h."""
    reach = h
    for a, b in stops:
        e, w = b - a, a - c
        den = d[0] * e[1] - d[1] * e[0]
        if den != 0:
            t, u = (w[0] * e[1] - w[1] * e[0]) / den, (w[0] * d[1] - w[1] * d[0]) / den
            if 0 < t < reach and 0 <= u <= 1:
                reach = t
    return reach


def _write(tmp_path, lines, sets, polygons, driver, suffix):
    gpd = pytest.importorskip("geopandas")
    shapely = pytest.importorskip("shapely.geometry")
    traces = gpd.GeoDataFrame({"set": sets}, geometry=[shapely.LineString(line + OFFSET) for line in lines],
                              crs="EPSG:3067")
    area = gpd.GeoDataFrame(geometry=[shapely.Polygon(p[0] + OFFSET, [h + OFFSET for h in p[1:]]) for p in polygons],
                            crs="EPSG:3067")
    paths = tmp_path / f"traces{suffix}", tmp_path / f"area{suffix}"
    traces.to_file(paths[0], driver=driver)
    area.to_file(paths[1], driver=driver)
    return paths, traces, area


def test_node_counts_agree_with_fractopo(tmp_path):
    fractopo = pytest.importorskip("fractopo")
    lines, sets = random_network(1)
    (traces_path, area_path), traces, area = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GPKG", ".gpkg")
    (json_traces, json_area), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GeoJSON", ".geojson")
    result = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0)
    from_json, from_gpkg = read_traces(json_traces).lines, read_traces(traces_path).lines
    assert len(from_json) == len(from_gpkg) == len(lines)  # the same map either way
    for a, b in zip(from_json, from_gpkg):
        np.testing.assert_array_equal(a, b)
    network = fractopo.Network(traces, area, name="generated", determine_branches_nodes=True, truncate_traces=True,
                               snap_threshold=0.001, circular_target_area=False)
    theirs = network.node_counts
    ours = {"I": result.nodes.N_I, "Y": result.nodes.N_Y, "X": result.nodes.N_X, "E": result.nodes.N_E}
    print(f"\nnodes: tracemap {ours}, fractopo {({k: int(theirs[k]) for k in ours})}")
    for kind, n in ours.items():
        assert n == pytest.approx(theirs[kind], rel=0.02), kind
    assert min(ours.values()) > 100  # a network with plenty of every node type
    parameters = network.parameters
    assert result.area == pytest.approx(parameters["Area"], rel=1e-9)
    assert result.intensity["P21"] == pytest.approx(parameters["Fracture Intensity P21"], rel=1e-9)
    assert len(result.traces) == parameters["Number of Traces (Real)"]
    assert result.nodes.C_L == pytest.approx(parameters["Connections per Trace"], rel=0.02)
    assert result.nodes.C_B == pytest.approx(parameters["Connections per Branch"], rel=0.02)
    assert result.intensity["B22"] == pytest.approx(parameters["Dimensionless Intensity B22"], rel=0.02)


def test_hand_counted_map():
    area = Area([[np.array([[0.0, 0], [10, 0], [10, 10], [0, 10]])]], "square")
    lines = [np.array([[1.0, 5], [9, 5]]),  # I, I
             np.array([[5.0, 5], [5, 8]]),  # Y on the first, I
             np.array([[3.0, 2], [3, 7]]),  # I, I; X with the first
             np.array([[7.0, 8], [12, 8]]),  # I, E (clipped at x = 10)
             np.array([[2.0, -1], [2, 1]]),  # E (clipped at y = 0), I
             np.array([[-1.0, 9], [11, 9.5]])]  # E, E: crosses the area
    result = analyse_traces(MapTraces(lines, [None] * 6, np.arange(6), "hand"), area, snap=0.01, n_bootstrap=0)
    n = result.nodes
    assert (n.N_I, n.N_Y, n.N_X, n.N_E) == (7, 1, 1, 4)
    assert result.terminations == [("B", "B"), ("T", "B"), ("B", "B"), ("B", "C"), ("C", "B"), ("C", "C")]
    assert result.abutting[1].tolist() == [0, -1]
    np.testing.assert_allclose(result.crossings.points, [[3.0, 5.0]])
    np.testing.assert_allclose(result.traces[3], [[7, 8], [10, 8]])
    total = 8 + 3 + 5 + 3 + 1 + np.hypot(10, 5 / 12)
    assert result.area == 100.0 and result.intensity["P21"] == pytest.approx(total / 100)
    assert result.connectivity.sizes.tolist() == [3, 1, 1, 1] and result.lengths.kaplan_meier is not None


def test_clipping_to_a_polygon_with_a_hole():
    rings = [SHELL, HOLE]
    line = np.array([[-10.0, 40.0], [110.0, 40.0]])  # through the shell and the hole
    pieces, owner = clip_to_area([line], rings)
    assert owner.tolist() == [0, 0]
    np.testing.assert_allclose(pieces[0], [[0, 40], [30, 40]])
    np.testing.assert_allclose(pieces[1], [[45, 40], [100, 40]])
    bent = np.array([[50.0, 95.0], [75.0, 95.0], [75.0, 50.0]])  # leaves across the cut corner, comes back
    pieces, owner = clip_to_area([bent], rings)
    assert owner.tolist() == [0, 0]
    np.testing.assert_allclose(pieces[0], [[50, 95], [65, 95]])
    np.testing.assert_allclose(pieces[1], [[75, 85], [75, 50]])


@pytest.mark.parametrize("driver, suffix", [("GeoJSON", ".geojson"), ("GPKG", ".gpkg"), ("ESRI Shapefile", ".shp")])
def test_each_format_is_read(tmp_path, driver, suffix):
    lines, sets = random_network(2, n1=10, n2=15)
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], driver, suffix)
    traces = read_traces(traces_path)
    assert len(traces.lines) == len(lines) and traces.sets == sets
    np.testing.assert_allclose(np.concatenate(traces.lines), np.concatenate(lines) + OFFSET, rtol=0, atol=1e-9)
    area = read_area(area_path)
    assert area.size == pytest.approx(100 * 100 - 40 * 40 / 2 - 15 * 15) and len(area.rings) == 2


def test_geopackage_with_z_multilines_and_layers(tmp_path):
    gpd = pytest.importorskip("geopandas")
    geometry = pytest.importorskip("shapely.geometry")
    path = tmp_path / "map.gpkg"
    multi = geometry.MultiLineString([[(0, 0, 1), (1, 1, 2)], [(2, 2, 3), (3, 2, 4), (4, 4, 4)]])
    gpd.GeoDataFrame({"Set": ["a"]}, geometry=[multi], crs="EPSG:3067").to_file(path, layer="traces")
    gpd.GeoDataFrame(geometry=[geometry.box(-1, -1, 5, 5)], crs="EPSG:3067").to_file(path, layer="area")
    with pytest.raises(InputError, match="choose a layer: the GeoPackage holds feature layers"):
        read_traces(path)
    with pytest.raises(InputError, match="no layer 'faults'"):
        read_traces(path, layer="faults")
    traces = read_traces(path, layer="traces")
    assert traces.feature.tolist() == [0, 0] and traces.sets == ["a", "a"]  # one trace per part, Z dropped
    np.testing.assert_array_equal(traces.lines[1], [[2, 2], [3, 2], [4, 4]])
    assert read_area(path, layer="area").size == 36.0


def test_geojson_written_by_hand_with_set_column(tmp_path):
    features = [{"type": "Feature", "properties": {"family": 3},
                 "geometry": {"type": "LineString", "coordinates": [[0, 0, 5], [1, 1, 5]]}}]
    path = tmp_path / "t.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    assert read_traces(path, set_column="family").sets == ["3"]
    assert read_traces(path).sets == [None]
    with pytest.raises(InputError, match="no attribute 'kind'; the traces have family"):
        read_traces(path, set_column="kind")


def test_bad_maps_give_clear_messages(tmp_path):
    traces = tmp_path / "t.geojson"
    traces.write_text(json.dumps({"type": "LineString", "coordinates": [[0, 0], [1, 1]]}))
    with pytest.raises(InputError, match="no sampling area given: a 2D map needs the polygon"):
        analyse_map(traces, None, tmp_path / "out")
    with pytest.raises(InputError, match="feature 0 is a LineString; the sampling area must be a Polygon"):
        read_area(traces)
    short = tmp_path / "short.geojson"
    short.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "LineString", "coordinates": [[0, 0]]}}]}))
    with pytest.raises(InputError, match="feature 0: a trace has 1 vertex; at least 2 are needed"):
        read_traces(short)
    geographic = tmp_path / "g.geojson"
    crs84 = {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}
    geographic.write_text(json.dumps({"type": "LineString", "coordinates": [[24, 60], [24.1, 60]], "crs": crs84}))
    with pytest.raises(InputError, match="geographic"):
        read_traces(geographic)
    with pytest.raises(InputError, match="unknown map format '.dxf'"):
        read_traces(_touch(tmp_path / "t.dxf"))
    with pytest.raises(InputError, match="file not found"):
        read_traces(tmp_path / "missing.shp")
    broken = tmp_path / "broken.gpkg"
    sqlite3.connect(broken).execute("CREATE TABLE x (a)").connection.close()
    with pytest.raises(InputError, match="cannot read GeoPackage"):
        read_traces(broken)
    far = tmp_path / "far.geojson"
    far.write_text(json.dumps({"type": "Polygon", "coordinates": [[[50, 50], [60, 50], [60, 60], [50, 50]]]}))
    with pytest.raises(InputError, match="no trace lies inside the sampling area"):
        analyse_map(traces, far, tmp_path / "out")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def _touch(path):
    path.write_text("")
    return path


def test_outputs_are_complete_and_strict_json(tmp_path):
    lines, sets = random_network(3, n1=20, n2=30)
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GeoJSON", ".geojson")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    result = analyse_map(traces_path, area_path, out, n_bootstrap=19)
    assert sorted(p.name for p in out.iterdir()) == ["kaplan_meier.csv", "keep.txt", "nodes.csv", "summary.json",
                                                     "traces.csv"]

    def refuse(token):
        raise ValueError(f"non-JSON number {token}")

    summary = json.loads((out / "summary.json").read_text(), parse_constant=refuse)
    assert summary["nodes"]["N_Y"] == result.nodes.N_Y and summary["traces_in_area"] == len(result.traces)
    assert set(summary["lengths"]["sets"]) == {"1", "2"}
    assert {f["model"] for f in summary["lengths"]["all"]["fits"]} == {"lognorm", "expon", "weibull_min", "powerlaw"}
    with open(out / "nodes.csv") as f:
        nodes = list(csv.DictReader(f))
    kinds = [n["type"] for n in nodes]
    assert [kinds.count(k) for k in "IYXE"] == [result.nodes.N_I, result.nodes.N_Y, result.nodes.N_X, result.nodes.N_E]
    x = np.array([float(n["x"]) for n in nodes])
    assert np.all((x >= OFFSET[0]) & (x <= OFFSET[0] + 100))  # map coordinates, origin added back
    with open(out / "traces.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(result.traces) and {r["set"] for r in rows} == {"1", "2"}
    assert sum(int(r["n_censored_ends"]) for r in rows) == result.nodes.N_E
    # a second run that fails leaves the first run's files as they were
    before = (out / "summary.json").read_text()
    with pytest.raises(InputError):
        analyse_map(traces_path, tmp_path / "missing.geojson", out)
    assert (out / "summary.json").read_text() == before
