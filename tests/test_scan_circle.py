"""Mauldon's scan circles on the outcrop (engine.scan_circle.measure_scan_circle): hand-counted windows on a flat
wall, unbiased estimates on random segments, and the P21 they estimate against engine.intensity's exact
clipping on the synthetic outcrop. (The 2D map's circles are tested in tests/test_maps2d.py.)"""

import csv
import json
import sqlite3

import cv2
import numpy as np
import pytest
import pyvista as pv
import trimesh

from engine.cli import main
from engine.errors import InputError
from engine.intensity import p21_map
from engine.mesh import Mesh
from engine.project import SCHEMA_VERSION, Project
from engine.register import Similarity
from engine.scan_circle import (ScanCircle, grid_scan_circles, measure_scan_circle, pooled_windows,
                                scan_circle_plot)
from engine.synthetic import make_outcrop
from engine.traces import Trace3D
from tests.scenes import facing_camera, grid_wall
from tests.test_cli import OFFSET, new_project
from tests.test_project import as_version


def wall_trace(k, xz, *, ends=("", "")):
    """A trace on the wall y = 0 through (x, z) points, sampled every centimetre."""
    xz = np.asarray(xz, dtype=float)
    s = np.linspace(0.0, 1.0, 1 + int(100 * np.linalg.norm(np.diff(xz, axis=0), axis=1).sum()))
    x, z = np.interp(s, np.linspace(0, 1, len(xz)), xz[:, 0]), np.interp(s, np.linspace(0, 1, len(xz)), xz[:, 1])
    points = np.column_stack([x, np.zeros_like(x), z])
    n = len(points)
    return Trace3D(k, points, np.zeros((n, 2)), np.zeros(n, int), np.zeros(n, int), ("photo",),
                   term_start=ends[0], term_end=ends[1])


def test_hand_counted_window_on_a_flat_wall():
    """r 1 at (5, 3): a trace across (2 cuts), one inside (2 ends), one from inside out (1 end, 1 cut), one cut
    by an occlusion inside it (C: censored, 1 cut), one passing outside."""
    wall = Mesh(*grid_wall(step=0.25))
    traces = [wall_trace(1, [[3.0, 3.0], [7.0, 3.0]]), wall_trace(2, [[4.8, 2.8], [5.2, 3.2]]),
              wall_trace(3, [[5.0, 3.5], [5.0, 5.0]]), wall_trace(4, [[5.5, 2.5], [6.5, 1.5]], ends=("C", "B")),
              wall_trace(5, [[3.0, 5.0], [7.0, 5.0]])]
    window = measure_scan_circle(wall, traces, ScanCircle(np.array([5.0, 0.0, 3.0]), 1.0))
    m = window.counts
    assert (m.ends, m.cuts, m.censored, m.seen) == (3, 4, 1, 1.0)
    assert not window.rock.open and not window.unbiased  # whole, but a cut end inside
    corner = 5.0 + np.sqrt(0.5), 3.0 - np.sqrt(0.5)  # trace 4 leaves the circle at 45°
    np.testing.assert_allclose(sorted(window.crossings[:, [0, 2]].tolist()),
                               [[4.0, 3.0], [5.0, 4.0], list(corner), [6.0, 3.0]], atol=1e-9)
    np.testing.assert_allclose(sorted(window.ends[:, [0, 2]].tolist()), [[4.8, 2.8], [5.0, 3.5], [5.2, 3.2]],
                               atol=1e-9)
    np.testing.assert_allclose(window.cut_ends[:, [0, 2]], [[5.5, 2.5]], atol=1e-9)
    # the edge: interpolated along the 0.25 m grid's edges, so within 1% inside the circle
    np.testing.assert_allclose(np.linalg.norm(window.rock.edge - [5.0, 0.0, 3.0], axis=2), 0.995, atol=0.005)
    # the window's edge and area as the mesh has them: the circle's chords on a 0.25 m grid, 0.3% short
    assert m.perimeter == pytest.approx(2 * np.pi, rel=0.005) and m.area == pytest.approx(np.pi, rel=0.005)
    assert m.p21 == pytest.approx(1.0, rel=0.005) and m.mean_length == pytest.approx(np.pi / 2 * 4 / 3, rel=0.01)
    chord = wall_trace(6, [[3.0, 3.9], [7.0, 3.9]])  # two vertices only, both outside: it dips in and out
    chord = Trace3D(6, chord.points[[0, -1]], np.zeros((2, 2)), np.zeros(2, int), np.zeros(2, int), ("photo",))
    dipping = measure_scan_circle(wall, [chord], ScanCircle(np.array([5.0, 0.0, 3.0]), 1.0))
    np.testing.assert_allclose(sorted(dipping.crossings[:, 0]), 5.0 + np.array([-1, 1]) * np.sqrt(1 - 0.9**2))
    with pytest.raises(InputError, match="no rock within 1 m"):
        measure_scan_circle(wall, traces, ScanCircle(np.array([5.0, -3.0, 3.0]), 1.0)).counts


def test_a_window_over_a_hole_or_the_mesh_edge_is_open_and_the_radius_is_checked():
    wall = Mesh(*grid_wall(step=0.25, hole=(4.5, 5.5, 2.5, 3.5)))
    assert measure_scan_circle(wall, [], ScanCircle([5.0, 0.0, 1.0], 1.0)).rock.open is False  # clear of the hole
    assert measure_scan_circle(wall, [], ScanCircle([5.0, 0.0, 3.0], 1.0)).rock.open is True
    assert measure_scan_circle(wall, [], ScanCircle([0.5, 0.0, 1.5], 1.0)).rock.open is True  # over the border
    with pytest.raises(InputError, match="radius -1.0: expected a distance > 0 m"):
        ScanCircle([5.0, 0.0, 3.0], -1.0)
    with pytest.raises(InputError, match="centre must be a finite point"):
        ScanCircle([5.0, np.nan, 3.0], 1.0)


def test_the_plot_shows_the_windows_on_the_face_seen_from_in_front():
    """Two windows on the wall facing −y (south): seen from the south, along it is east (x) and up is z, from
    the windows' mean centre; a registration of scale 2 doubles the distances and halves P21."""
    wall = Mesh(*grid_wall(step=0.25))
    traces = [wall_trace(1, [[2.0, 3.0], [8.0, 3.0]]), wall_trace(2, [[6.8, 3.8], [7.2, 4.2]], ends=("C", "B"))]
    windows = [measure_scan_circle(wall, traces, ScanCircle([x, 0.0, z], 1.0, "", k + 1))
               for k, (x, z) in enumerate([(3.0, 2.5), (7.0, 3.5)])]
    plot = scan_circle_plot(windows)
    assert plot.name == "scan_circles" and plot.figure is not None
    rows = {row[0]: dict(zip(plot.table.columns, row)) for row in plot.table.rows}
    assert (rows[1]["along_m"], rows[1]["up_m"]) == pytest.approx((-2.0, -0.5), abs=1e-9)
    assert (rows[2]["along_m"], rows[2]["up_m"]) == pytest.approx((2.0, 0.5), abs=1e-9)
    assert rows[1]["p21_per_m"] == pytest.approx(windows[0].counts.p21) and rows[1]["edge_cuts"] == 2
    assert rows[1]["unbiased"] and not rows[2]["unbiased"]  # a cut end inside the second
    assert "2 scan circles: pooled P21" in plot.figure.axes[0].get_title()
    scaled = Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0)
    row = dict(zip(plot.table.columns, scan_circle_plot(windows, scaled).table.rows[1]))
    assert (row["along_m"], row["radius_m"]) == pytest.approx((4.0, 2.0))
    assert row["p21_per_m"] == pytest.approx(windows[1].counts.p21 / 2)
    with pytest.raises(InputError, match="one or more measured windows"):
        scan_circle_plot([])


def test_a_grid_of_windows_covers_the_face_whole_and_pooled_is_unbiased():
    """Segments of length 1.5 at uniform positions and directions on a 30 × 20 m flat wall (P21 = 1.2): the
    grid of r 2 windows (7 × 5, touching, the outer ones touching the wall's edge) on six walls, pooled.
    Measured: mean length 1.507, P21 1.198."""
    wall = Mesh(*grid_wall(width=30.0, height=20.0, step=0.5))
    circles = grid_scan_circles(wall, 2.0)
    centres = np.array([c.centre for c in circles])
    np.testing.assert_allclose(centres[:, 1], 0.0, atol=1e-9)  # on the rock
    assert sorted(set(centres[:, 0].round(9))) == [3.0, 7.0, 11.0, 15.0, 19.0, 23.0, 27.0]
    assert sorted(set(centres[:, 2].round(9))) == [2.0, 6.0, 10.0, 14.0, 18.0]
    assert centres[0].tolist() == pytest.approx([3.0, 0.0, 2.0]) and circles[-1].name == "grid 35"
    windows = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        n = int(1.2 * 34 * 24 / 1.5)  # midpoints over the wall and a band 2 m beyond it: P21 even over the wall
        mid = rng.uniform([-2, -2], [32, 22], (n, 2))
        angle = rng.uniform(0, np.pi, n)
        half = 0.75 * np.column_stack([np.cos(angle), np.sin(angle)])
        traces = [wall_trace(k, [c - h, c + h]) for k, (c, h) in enumerate(zip(mid, half))]
        windows += [measure_scan_circle(wall, traces, circle) for circle in circles]
    assert not any(w.rock.open for w in windows)
    pool = pooled_windows(windows)
    print(f"\npooled over {len(windows)} windows: mean length {pool.mean_length:.3f}, P21 {pool.p21:.3f}")
    assert pool.mean_length == pytest.approx(1.5, rel=0.05) and pool.p21 == pytest.approx(1.2, rel=0.05)
    assert pool.cuts / (4 * 2.0) / len(windows) == pytest.approx(pool.p21, rel=0.01)  # a flat disc: n/(4r)
    assert pool.area == pytest.approx(len(windows) * np.pi * 4.0, rel=0.01)


def test_grid_windows_on_the_rough_synthetic_wall_lie_on_it_whole_and_apart():
    outcrop = make_outcrop(4, n_cameras=1, image_size=(64, 48), mesh_spacing=0.1)
    mesh = outcrop.mesh
    circles = grid_scan_circles(mesh, 1.5, spacing=4.0)
    centres = np.array([c.centre for c in circles])
    assert len(circles) >= 6
    on_rock = np.min(np.linalg.norm(mesh.vertices[None] - centres[:, None], axis=2), axis=1)
    assert on_rock.max() < mesh.mean_edge_length
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=2) + 1e9 * np.eye(len(centres))
    assert gaps.min() >= 4.0 - 1e-6  # in the face's plane 4 m apart; off it, farther
    rim = mesh.vertices[np.unique(mesh.boundary_edges)]
    assert np.min(np.linalg.norm(rim[None] - centres[:, None], axis=2)) >= 1.5 * (1 - 1e-9)
    with pytest.raises(InputError, match="no window of radius 40 m fits whole on the rock"):
        grid_scan_circles(mesh, 40.0)


def test_window_p21_on_the_synthetic_outcrop_matches_the_exact_p21_map():
    """On the synthetic outcrop's rough wall (true traces), m/(4r) in windows of r 1.5 at 40 vertices, against
    the P21 map at those vertices (trace length clipped to the ball over the mesh area in it, engine.intensity):
    pooled within 10%. Measured on seed 3: 1.07 of it with the window's own edge length and area (the rough
    rock's are 1.09 and 1.15 times a disc's), 1.16 with a disc's m/(4r)."""
    outcrop = make_outcrop(3, n_cameras=1, image_size=(64, 48), mesh_spacing=0.05)
    mesh = outcrop.mesh
    traces = [Trace3D(t.id, t.points - outcrop.origin, np.zeros((len(t.points), 2)), t.face,
                      np.zeros(len(t.points), int), ("x",), term_start=t.ends[0], term_end=t.ends[1])
              for t in outcrop.traces3d if not t.closed]
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    rng = np.random.default_rng(0)
    targets = rng.uniform(lo + [2.0, 0, 2.0], hi - [2.0, 0, 2.0], (40, 3))
    vertices = [int(np.argmin(np.linalg.norm(mesh.vertices[:, [0, 2]] - t[[0, 2]], axis=1))) for t in targets]
    exact = p21_map(mesh, traces, radius=1.5).p21[vertices]
    windows = [measure_scan_circle(mesh, traces, ScanCircle(mesh.vertices[v], 1.5)).counts for v in vertices]
    assert sum(w.p21 for w in windows) / np.nansum(exact) == pytest.approx(1.0, rel=0.10)


def two_photo_wall(tmp_path):
    """A project of the flat wall (UTM-sized coordinates) seen by two photos, with three hand-counted traces."""
    v, f = grid_wall(step=0.25, offset=OFFSET)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "wall.obj")
    cams = [facing_camera("left", centre=(3.0, -8.0, 3.0), offset=OFFSET),
            facing_camera("right", centre=(7.0, -8.0, 3.0), offset=OFFSET)]
    (tmp_path / "images").mkdir()
    for c in cams:
        cv2.imwrite(str(tmp_path / "images" / f"{c.name}.png"), np.zeros((c.height, c.width, 3), np.uint8))
    (tmp_path / "cameras.json").write_text(json.dumps(
        {"format": "tracemap-cameras", "version": 1, "cameras": [c.to_dict() for c in cams]}))
    assert new_project(tmp_path) == 0
    path = tmp_path / "p.tracemap"
    with Project.open(path) as p:
        shift = OFFSET - p.origin
        traces = [wall_trace(1, [[3.0, 3.0], [7.0, 3.0]]), wall_trace(2, [[4.8, 2.8], [5.2, 3.2]]),
                  wall_trace(3, [[5.0, 3.5], [5.0, 5.0]])]
        p.add_traces3d([Trace3D(t.id, t.points + shift, t.uv, t.face, t.image_index, ("left",)) for t in traces])
    return path


def test_the_scan_circle_command_lays_lists_pools_exports_and_removes(tmp_path, capsys):
    path = two_photo_wall(tmp_path)
    at = [str(x) for x in OFFSET + [5.0, 0.0, 3.0]]
    assert main(["scan-circle", str(path), "--at", *at, "--radius", "1", "--name", "middle"]) == 0
    out = capsys.readouterr().out
    assert ("scan circle 1 (middle) at (500005, 4200000, 103), r 1 m: 3 edge cuts, 3 trace ends inside: "
            "P21 0.75") in out
    assert "note" not in out  # whole, wholly seen, no cut ends
    assert main(["scan-circle", str(path), "--at", *map(str, OFFSET + [1.5, 0.0, 3.0]), "--radius", "1"]) == 0
    assert ("scan circle 2 at (500001.5, 4200000, 103), r 1 m: 0 edge cuts, 0 trace ends inside: P21 0.000 /m, "
            "P20 0.000 /m², mean trace length no end inside") in capsys.readouterr().out
    assert main(["scan-circle", str(path)]) == 0
    out = capsys.readouterr().out
    assert "scan circle 1 (middle)" in out and "scan circle 2 at" in out
    assert "all 2 scan circles (6.3 m² of rock): 3 edge cuts, 3 trace ends inside: P21 0.376 /m" in out
    assert main(["export", str(path), str(tmp_path / "out"), "--format", "csv,vtp,gpkg"]) == 0
    with open(tmp_path / "out" / "scan_circles.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["name"] for r in rows] == ["middle", ""] and [r["edge_cuts"] for r in rows] == ["3", "0"]
    assert float(rows[0]["x"]) == pytest.approx(OFFSET[0] + 5.0) and rows[0]["open"] == "False"
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["scan_circles"][0]["p21_per_m"] == pytest.approx(summary["scan_circles"][0]["edge_cuts"] * np.pi
                                                                   / (2 * summary["scan_circles"][0]["edge_m"]))
    assert summary["scan_circles_pooled"]["ends_inside"] == 3
    poly = pv.read(tmp_path / "out" / "scan_circles.vtp")
    kind, ids = np.asarray(poly.cell_data["kind"]), np.asarray(poly.cell_data["scan_circle"])
    assert np.count_nonzero(kind == 1) == 3 and np.count_nonzero(kind == 2) == 3  # crossings and ends
    assert set(ids[kind == 0].tolist()) == {1, 2} and poly.n_lines == np.count_nonzero(kind == 0)
    ends = np.asarray(poly.points)[poly.verts.reshape(-1, 2)[:, 1]][kind[: poly.n_verts] == 2] - OFFSET
    np.testing.assert_allclose(sorted(ends[:, [0, 2]].tolist()), [[4.8, 2.8], [5.0, 3.5], [5.2, 3.2]], atol=1e-6)
    gpkg = sqlite3.connect(tmp_path / "out" / "traces.gpkg")
    assert gpkg.execute("SELECT name, edge_cuts FROM scan_circles ORDER BY id").fetchall() == [("middle", 3), ("", 0)]
    gpkg.close()
    assert main(["plot", str(path), "-o", str(tmp_path / "plots")]) == 0
    with open(tmp_path / "plots" / "scan_circles.csv", newline="") as f:
        assert [int(r["edge_cuts"]) for r in csv.DictReader(f)] == [3, 0]
    assert (tmp_path / "plots" / "scan_circles.png").stat().st_size > 10_000
    assert main(["scan-circle", str(path), "--remove", "2"]) == 0
    assert [c.id for c in Project.open(path).scan_circles()] == [1]


def test_the_scan_circle_command_lays_a_grid(tmp_path, capsys):
    path = two_photo_wall(tmp_path)
    assert main(["scan-circle", str(path), "--grid", "--radius", "1", "--spacing", "2.5", "--name", "row"]) == 0
    out = capsys.readouterr().out
    with Project.open(path) as p:
        circles = p.scan_circles()
        centres = np.array([c.centre for c in circles]) + p.origin - OFFSET
    # the 10 × 6 m wall: centres 2.5 m apart, at least 1 m in: x 1.25 … 8.75 (4), z 0.5 + … (2 rows of r 1 fit)
    assert sorted(set(centres[:, 0].round(6))) == [1.25, 3.75, 6.25, 8.75]
    assert sorted(set(centres[:, 2].round(6))) == [1.75, 4.25]
    assert [c.name for c in circles][:2] == ["row 1", "row 2"] and len(circles) == 8
    assert f"all {len(circles)} scan circles" in out


@pytest.mark.parametrize("more, message", [
    (["--at", "500005", "4199996", "103", "--radius", "1"], "--at 500005 4199996 103: the scan circle: no rock"),
    (["--at", "500005", "4200000", "103"], "give the windows' radius, --radius R"),
    (["--spacing", "2", "--radius", "1"], "--spacing is the grid's; give it with --grid"),
    (["--grid", "--radius", "1", "--remove", "1"], "give one of --at, --grid or --remove"),
    (["--remove", "7"], "no scan circle with id 7"),
    (["--grid", "--radius", "9"], "no window of radius 9 m fits whole on the rock"),
])
def test_bad_scan_circle_commands_name_the_problem_and_store_nothing(tmp_path, capsys, more, message):
    path = two_photo_wall(tmp_path)
    capsys.readouterr()
    assert main(["scan-circle", str(path), *more]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert Project.open(path).scan_circles() == []


def test_scan_circles_are_stored_restored_and_a_version_3_project_gains_their_table(tmp_path):
    path = two_photo_wall(tmp_path)
    as_version(path, 3)
    with Project.open(path) as p:
        assert p.scan_circles() == []
        first = p.add_scan_circle(ScanCircle([5.0, 0.0, 3.0], 1.0, "middle"))
        second = p.add_scan_circle(ScanCircle([2.0, 0.0, 3.0], 0.5))
        kept = p.scan_circles()
        assert [(c.id, c.name, c.radius) for c in kept] == [(first, "middle", 1.0), (second, "", 0.5)]
        np.testing.assert_array_equal(kept[0].centre, [5.0, 0.0, 3.0])
        p.remove_scan_circle(first)
        assert [c.id for c in p.scan_circles()] == [second]
        p.restore_scan_circle(kept[0])
        assert [c.id for c in p.scan_circles()] == [first, second]
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert sqlite3.connect(tmp_path / "p.v3.bak.tracemap").execute("PRAGMA user_version").fetchone()[0] == 3


def test_scan_circle_readouts_are_in_the_registered_frame(tmp_path, capsys):
    """A registration of scale 2: --radius is in its metres (2 here is 1 on the mesh), P21 halves, P20 quarters
    and the mean trace length doubles."""
    from engine.register import Registration, Similarity

    v, f = grid_wall(step=0.25, offset=OFFSET)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "wall.obj")
    camera = facing_camera("left", centre=(5.0, -8.0, 3.0), offset=OFFSET)
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "left.png"), np.zeros((camera.height, camera.width, 3), np.uint8))
    (tmp_path / "cameras.json").write_text(json.dumps(
        {"format": "tracemap-cameras", "version": 1, "cameras": [camera.to_dict()]}))
    assert new_project(tmp_path) == 0
    path = tmp_path / "p.tracemap"
    with Project.open(path) as p:
        shift = OFFSET - p.origin
        traces = [wall_trace(1, [[3.0, 3.0], [7.0, 3.0]]), wall_trace(2, [[4.8, 2.8], [5.2, 3.2]])]
        p.add_traces3d([Trace3D(t.id, t.points + shift, t.uv, t.face, t.image_index, ("left",)) for t in traces])
        p.set_registration(Registration(("a", "b", "c"), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3),
                                        (("left",),) * 3,
                                        Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0)))
    assert main(["scan-circle", str(path), "--at", *map(str, OFFSET + [5.0, 0.0, 3.0]), "--radius", "2"]) == 0
    out = capsys.readouterr().out
    # on the mesh: r 1, n 2, m 2: P21 0.5, P20 1/π, mean length π/2; in the GCPs' frame: 0.25, 1/4π, π
    assert "2 edge cuts, 2 trace ends inside: P21 0.251 /m" in out and "P20 0.080 /m²" in out  # chords: 0.3% short
    assert "mean trace length 3.1" in out and "(GCPs' frame)" in out
