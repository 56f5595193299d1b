import json
import os

import numpy as np
import pytest

from engine.errors import InputError
from engine.cli import main
from engine.map_intensity import _disc_triangles, disc_area_inside, intensity_grid, length_in_discs
from engine.maps2d import Area, MapTraces, analyse_map, analyse_traces, read_area
from tests.test_maps2d import HOLE, OFFSET, SHELL, _unit, _write, random_network

os.environ.setdefault("FRACTOPO_DISABLE_CACHE", "1")  # fractopo would cache to ./.cache otherwise


def _square(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]], float)


def test_disc_area_inside_analytic_cases():
    """A disc inside, halved by an edge, quartered at a corner, in a hole, outside, centred on a hole's
    corner and edges (where the inside test cannot tell); exact to rounding."""
    area = Area([[_square(0, 0, 100, 100), _square(40, 40, 60, 60)]], "square with a hole")
    centres = np.array([[20.0, 20], [50, 0], [0, 0], [100, 100], [50, 50], [200, 200], [50, 35]])
    r = 5.0
    full = np.pi * r * r
    ours = disc_area_inside(centres, r, *area.boundary)
    # the last: a disc just below the hole, its top cut by the hole's lower edge at y 40 (a chord 5 above)
    np.testing.assert_allclose(ours, [full, full / 2, full / 4, full / 4, 0.0, 0.0, full], rtol=1e-12, atol=1e-9)
    on_hole = disc_area_inside(np.array([[40.0, 40.0], [40.0, 50.0], [60.0, 45.0]]), r, *area.boundary)
    np.testing.assert_allclose(on_hole, [0.75 * full, full / 2, full / 2], rtol=1e-12)  # a hole's corner, edges
    cut = disc_area_inside(np.array([[50.0, 37.0]]), r, *area.boundary)[0]
    segment = r * r * np.arccos(3 / r) - 3 * np.sqrt(r * r - 9)  # the cap above the chord 3 from the centre
    assert cut == pytest.approx(full - segment, rel=1e-12)


def test_disc_area_inside_on_a_fine_grid_is_the_sum_over_every_edge():
    """62,500 cells of 4 over a 1000-gon (a circle of r 480), discs of r 6: the area from the inside test
    and the edges near each disc equals the sum over all 1000 edges at every cell (measured 6e-14; the
    sum over all edges took 11 s, this 0.11 s)."""
    t = np.linspace(0, 2 * np.pi, 1001)[:-1]
    ring = np.column_stack([500 + 480 * np.cos(t), 500 + 480 * np.sin(t)])
    a, b = ring, np.roll(ring, -1, axis=0)
    centres = np.stack(np.meshgrid(np.arange(2.0, 1000, 4), np.arange(2.0, 1000, 4)), -1).reshape(-1, 2)
    ours = disc_area_inside(centres, 6.0, a, b)
    check = np.random.default_rng(0).choice(len(centres), 3000, replace=False)
    every_edge = [_disc_triangles(a - c, b - c, 6.0).sum() for c in centres[check]]
    np.testing.assert_allclose(ours[check], every_edge, atol=1e-9)
    assert 0 < np.count_nonzero((ours > 1) & (ours < np.pi * 36 - 1))  # discs the edge cuts


def test_disc_area_inside_agrees_with_shapely():
    """200 discs over a concave polygon with a hole, against shapely's intersection with 4096-gon discs
    (which fall short of the circle by 4e-7 of its area): within 2e-6 of the disc's area."""
    geometry = pytest.importorskip("shapely.geometry")
    area = Area([[SHELL, HOLE]], "shell")
    polygon = geometry.Polygon(SHELL, [HOLE])
    centres = np.random.default_rng(0).uniform(-10, 110, (200, 2))
    r = 7.0
    ours = disc_area_inside(centres, r, *area.boundary)
    theirs = [geometry.Point(*c).buffer(r, quad_segs=1024).intersection(polygon).area for c in centres]
    np.testing.assert_allclose(ours, theirs, atol=2e-6 * np.pi * r * r)
    assert 0 < np.count_nonzero((ours > 1) & (ours < np.pi * r * r - 1))  # many discs cut by the edges


def test_length_in_discs_agrees_with_shapely_and_chords():
    geometry = pytest.importorskip("shapely.geometry")
    r = 4.0
    a, b = np.array([[-10.0, 0], [-10, 3], [1, 1]]), np.array([[10.0, 0], [10, 3], [2, 1]])
    length = length_in_discs(np.zeros((1, 2)), r, a, b)[0, 0]
    assert length == pytest.approx(2 * r + 2 * np.sqrt(r * r - 9) + 1, rel=1e-12)  # diameter, chord, inside
    rng = np.random.default_rng(1)
    lines = [rng.uniform(0, 50, (4, 2)) for _ in range(40)]
    grid = intensity_grid(lines, Area([[_square(0, 0, 50, 50)]], "square").boundary, 5.0, radius=r)
    theirs = [sum(geometry.Point(x, y).buffer(r, quad_segs=1024).intersection(geometry.LineString(p)).length
                  for p in lines) for y in grid.y for x in grid.x]
    np.testing.assert_allclose(grid.length["all"].ravel(), theirs, atol=1e-3)


def test_grid_by_set_and_ends():
    """Per-set lengths add up to all traces'; P20 is half the uncensored ends per area; nodes and C_B of the
    hand-counted cells."""
    area = Area([[_square(0, 0, 20, 10)]], "strip")
    lines = [np.array([[1.0, 5], [9, 5]]), np.array([[5.0, 2], [5, 8]]), np.array([[12.0, 1], [12, 9]])]
    grid = intensity_grid(lines, area.boundary, 10.0, radius=5.0, sets=["a", "b", "a"],
                          ends=np.array([[1.0, 5], [9, 5], [5, 2], [5, 8]]), end_sets=["a", "a", "b", "b"],
                          end_nodes=["I", "I", "Y", "I"], crossings=np.array([[5.0, 5.0]]))
    assert list(grid.length) == ["all", "a", "b"] and grid.x.tolist() == [5.0, 15.0] and grid.y.tolist() == [5.0]
    np.testing.assert_allclose(grid.length["a"] + grid.length["b"], grid.length["all"])
    np.testing.assert_allclose(grid.area, np.pi * 25)  # both discs inside the 20 × 10 strip: r 5 at y 5
    assert grid.length["all"][0, 0] == pytest.approx(8 + 6)  # the trace at x 12 is 7 from the centre x 5
    assert grid.length["all"][0, 1] == pytest.approx(2 * np.sqrt(25 - 9))  # x 12 is 3 from the centre x 15
    assert grid.ends["all"].tolist() == [[4.0, 0.0]] and grid.ends["b"].tolist() == [[2.0, 0.0]]
    assert grid.p20()[0, 0] == pytest.approx(2 / (25 * np.pi))
    assert grid.p21("a")[0, 0] == pytest.approx(8 / (25 * np.pi))
    assert [grid.nodes[k][0, 0] for k in "IYX"] == [3, 1, 1] and [grid.nodes[k][0, 1] for k in "IYX"] == [0, 0, 0]
    c_b = grid.connections_per_branch()[0]
    assert c_b[0] == pytest.approx((3 + 4) / ((3 + 3 + 4) / 2)) and np.isnan(c_b[1])  # no node in the second
    assert grid.connection_frequency()[0, 0] == pytest.approx(2 / (25 * np.pi))


def test_grid_is_unbiased_at_the_edges_of_the_area():
    """Segments of length 6 at uniform positions and directions (P21 0.6) over a wider region than the
    100 × 100 area, 20 maps, cells of 10 (discs of r 15). Measured: the interior cells' mean P21 0.599, the
    edge cells' 0.604, the corners' 0.593 (within 4%), where length over the whole disc (fractopo's) gives
    the edges 0.428 and the corners 0.293: 0.6 times the share of their discs inside, 0.708 and 0.494."""
    area = Area([[_square(0, 0, 100, 100)]], "square")
    totals = np.zeros((10, 10))
    whole = np.zeros((10, 10))
    for seed in range(20):
        rng = np.random.default_rng(seed)
        n = int(0.6 * 140**2 / 6)
        c, d = rng.uniform(-20, 120, (n, 2)), 3.0 * _unit(rng.uniform(0, 180, n)).T
        pieces = _clip_to_square([np.array([p - q, p + q]) for p, q in zip(c, d)], 100.0)
        grid = intensity_grid(pieces, area.boundary, 10.0)
        totals += grid.p21()
        whole += grid.length["all"] / (np.pi * grid.radius ** 2)
    assert grid.sampled.all() and grid.share.min() == pytest.approx(0.4936, abs=1e-4)  # the corners' share
    mean, whole = totals / 20, whole / 20
    edge = np.zeros((10, 10), bool)
    edge[[0, -1], :] = edge[:, [0, -1]] = True
    corner = np.zeros((10, 10), bool)
    corner[[0, 0, -1, -1], [0, -1, 0, -1]] = True
    print(f"\nP21 interior {mean[~edge].mean():.3f}, edge {mean[edge & ~corner].mean():.3f}, corner "
          f"{mean[corner].mean():.3f}; whole disc: edge {whole[edge & ~corner].mean():.3f}, corner {whole[corner].mean():.3f}")
    for cells in (~edge, edge & ~corner, corner):
        assert mean[cells].mean() == pytest.approx(0.6, rel=0.04)
    share = grid.share  # the same on every map
    assert whole[corner].mean() == pytest.approx(0.6 * share[corner].mean(), rel=0.05)
    assert whole[edge & ~corner].mean() == pytest.approx(0.6 * share[edge & ~corner].mean(), rel=0.05)


def _clip_to_square(lines, size):
    """Straight segments clipped to [0, size]² (Liang–Barsky), the pieces inside."""
    out = []
    for p, q in lines:
        d, t0, t1 = q - p, 0.0, 1.0
        for k in range(2):
            for edge, sign in ((0.0, -1.0), (size, 1.0)):
                if d[k] == 0:
                    if (p[k] - edge) * sign > 0:
                        t0, t1 = 1.0, 0.0
                    continue
                t = (edge - p[k]) / d[k]
                if sign * d[k] > 0:
                    t1 = min(t1, t)
                else:
                    t0 = max(t0, t)
        if t1 > t0:
            out.append(np.array([p + t0 * d, p + t1 * d]))
    return out


def test_grid_agrees_with_fractopo_contour_grid(tmp_path):
    """fractopo's `run_grid_sampling` on the same cells of a generated map (UTM-sized coordinates): where a
    disc lies wholly inside the area, trace length and the count of I and Y nodes agree (fractopo's disc is
    a 64-gon, 0.16% smaller: length within 0.5%, counts within one node in a few cells, so branches within
    2 and connections per branch within 0.03), and its P21 is ours × 0.9984; where a disc reaches out of the area, fractopo's falls with the share inside, ours not."""
    pytest.importorskip("fractopo")
    gpd = pytest.importorskip("geopandas")
    geometry = pytest.importorskip("shapely.geometry")
    from fractopo.analysis.contour_grid import run_grid_sampling
    from fractopo import Network
    lines, sets = random_network(3)
    (traces_path, area_path), traces, area = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GPKG", ".gpkg")
    result = analyse_map(traces_path, area_path, tmp_path / "out", n_bootstrap=0, grid=10.0).analysis
    grid = result.grid
    xx, yy = np.meshgrid(grid.x, grid.y)
    cells = gpd.GeoDataFrame(geometry=[geometry.box(x - 5, y - 5, x + 5, y + 5) for x, y in zip(xx.ravel(), yy.ravel())],
                             crs=traces.crs)
    network = Network(traces, area, name="grid", determine_branches_nodes=True, truncate_traces=True,
                      snap_threshold=0.001)
    theirs = run_grid_sampling(network.trace_gdf, network.branch_gdf, network.node_gdf, cell_width=10.0,
                               snap_threshold=0.001, precursor_grid=cells)
    their_area = theirs["Area"].to_numpy()
    their_length = theirs["Fracture Intensity P21"].to_numpy() * their_area
    their_ends = 2 * theirs["Areal Frequency P20"].to_numpy() * their_area
    whole = (grid.share > 1 - 1e-9).ravel()
    assert whole.sum() >= 30
    np.testing.assert_allclose(grid.length["all"].ravel()[whole], their_length[whole], rtol=5e-3, atol=0.2)
    differ = np.abs(grid.ends["all"].ravel()[whole] - their_ends[whole])
    assert differ.max() <= 1 + 1e-9 and np.count_nonzero(differ > 0.5) <= 3
    np.testing.assert_allclose(their_area[whole], 0.9984 * np.pi * 15.0 ** 2, rtol=1e-3)
    ours_branches = ((grid.nodes["I"] + 3 * grid.nodes["Y"] + 4 * grid.nodes["X"]) / 2).ravel()[whole]
    assert np.abs(ours_branches - theirs["Number of Branches"].to_numpy()[whole]).max() <= 2
    c_b, their_c_b = grid.connections_per_branch().ravel()[whole], theirs["Connections per Branch"].to_numpy()[whole]
    known = np.isfinite(c_b)  # no node in the disc: fractopo says 0, we say unknown
    np.testing.assert_allclose(c_b[known], their_c_b[known], atol=0.03)
    assert np.all(their_c_b[~known] == 0) and known.mean() > 0.9
    cut = (grid.share < 0.8).ravel() & grid.sampled.ravel()
    ratio = theirs["Fracture Intensity P21"].to_numpy()[cut] / grid.p21().ravel()[cut]
    assert cut.sum() >= 10 and np.median(ratio) < 0.8  # fractopo's P21 falls at the area's edge


def test_grid_command_writes_the_map(tmp_path, capsys):
    lines, sets = random_network(1)
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL, HOLE]], "GPKG", ".gpkg")
    out = tmp_path / "out"
    assert main(["analyse-map", str(traces_path), str(area_path), "-o", str(out), "--bootstrap", "0",
                 "--grid", "5", "--grid-radius", "6"]) == 0
    said = capsys.readouterr().out
    assert "P21 map:" in said and "cells of 5 read (discs of radius 6" in said
    summary = json.loads((out / "summary.json").read_text())["p21_grid"]
    assert (summary["cell"], summary["radius"], summary["columns"], summary["rows"]) == (5.0, 6.0, 20, 20)
    assert set(summary["groups"]) == {"all", "1", "2"}
    c_b = summary["connections_per_branch"]  # the map's own is 1.80
    assert 0 <= c_b["min"] and 1.5 < c_b["mean"] < c_b["max"] <= 2
    rows = (out / "p21_grid.csv").read_text().splitlines()
    assert rows[0] == "group,x,y,area,share,length,ends,P21,P20,I,Y,X,C_B,connection_frequency"
    assert len(rows) == 1 + 3 * 400
    first = rows[1].split(",")
    assert float(first[1]) == pytest.approx(OFFSET[0] + 2.5) and float(first[2]) == pytest.approx(OFFSET[1] + 2.5)
    assert (out / "p21_grid.png").stat().st_size > 10_000 and (out / "c_b_grid.png").stat().st_size > 10_000
    read = [r.split(",") for r in rows[1:401] if r.split(",")[7] != ""]
    assert summary["sampled"] == len(read)
    cells = read_area(out / "p21_grid.gpkg")  # the GIS layer: one square per cell read, in the map's CRS
    assert len(cells.polygons) == len(read) and cells.crs == "EPSG:3067"
    np.testing.assert_allclose(cells.polygons[0][0][:-1].mean(axis=0), [float(v) for v in read[0][1:3]], atol=1e-6)
    pyogrio = pytest.importorskip("pyogrio")
    frame = pyogrio.read_dataframe(out / "p21_grid.gpkg")
    assert pyogrio.read_info(out / "p21_grid.gpkg")["geometry_type"] == "Polygon"
    assert list(frame.columns[:13]) == ["x", "y", "area", "share", "length", "ends", "n_i", "n_y", "n_x", "c_b",
                                        "connection_frequency", "p21", "p20"]
    assert {"p21_1", "p20_1", "p21_2", "p20_2"} <= set(frame.columns)
    np.testing.assert_allclose(frame["p21"], [float(r[7]) for r in read])
    np.testing.assert_allclose(frame["p21_1"] + frame["p21_2"], frame["p21"], rtol=1e-12)
    assert frame.geometry.iloc[0].area == pytest.approx(25.0)


def test_grid_bad_requests_are_named(tmp_path, capsys):
    lines, sets = random_network(1)
    (traces_path, area_path), *_ = _write(tmp_path, lines, sets, [[SHELL]], "GPKG", ".gpkg")
    out = tmp_path / "out"
    base = ["analyse-map", str(traces_path), str(area_path), "-o", str(out), "--bootstrap", "0"]
    assert main([*base, "--grid-radius", "6"]) == 2
    assert "give the map's cell with --grid" in capsys.readouterr().err
    assert main([*base, "--grid", "0.1"]) == 2
    assert "more than 250,000; expected a larger cell" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*base, "--grid", "-1"])
    assert "argument --grid: expected a number > 0" in capsys.readouterr().err
    assert not out.exists()  # nothing written by a refused command
    area = Area([[_square(0, 0, 10, 10)]], "square")
    traces = MapTraces([np.array([[1.0, 1], [9, 9]])], [None], np.arange(1), "one")
    with pytest.raises(InputError, match="grid radius"):
        analyse_traces(traces, area, n_bootstrap=0, grid=1.0, grid_radius=float("nan"))
