"""Mauldon's scan circles on the outcrop (engine.scan_circle.mesh_scan_circle): hand-counted windows on a flat
wall, unbiased estimates on random segments, and the P21 they estimate against engine.intensity's exact
clipping on the synthetic outcrop. (The 2D map's circles are tested in tests/test_maps2d.py.)"""

import json

import cv2
import numpy as np
import pytest
import trimesh

from engine.cli import main
from engine.errors import InputError
from engine.intensity import p21_map
from engine.mesh import Mesh
from engine.project import Project
from engine.scan_circle import mesh_scan_circle
from engine.synthetic import make_outcrop
from engine.traces import Trace3D
from tests.scenes import facing_camera, grid_wall
from tests.test_cli import OFFSET, new_project


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
    m = mesh_scan_circle(wall, traces, np.array([5.0, 0.0, 3.0]), 1.0)
    assert (m.ends, m.cuts, m.censored, m.seen) == (3, 4, 1, 1.0)
    # the window's edge and area as the mesh has them: the circle's chords on a 0.25 m grid, 0.3% short
    assert m.perimeter == pytest.approx(2 * np.pi, rel=0.005) and m.area == pytest.approx(np.pi, rel=0.005)
    assert m.p21 == pytest.approx(1.0, rel=0.005) and m.mean_length == pytest.approx(np.pi / 2 * 4 / 3, rel=0.01)
    chord = wall_trace(6, [[3.0, 3.9], [7.0, 3.9]])  # two vertices only, both outside: it dips in and out
    chord = Trace3D(6, chord.points[[0, -1]], np.zeros((2, 2)), np.zeros(2, int), np.zeros(2, int), ("photo",))
    assert mesh_scan_circle(wall, [chord], np.array([5.0, 0.0, 3.0]), 1.0).cuts == 2
    with pytest.raises(InputError, match="no rock within 1 m"):
        mesh_scan_circle(wall, traces, np.array([5.0, -3.0, 3.0]), 1.0)


def test_windows_on_random_segments_are_unbiased():
    """Segments of length 1.5 at uniform positions and directions on a 30 × 20 m flat wall (P21 = 1.2):
    twelve windows of r 2 on each of six walls. Measured: mean length 1.49, P21 1.18."""
    wall = Mesh(*grid_wall(width=30.0, height=20.0, step=0.5))
    centres = [np.array([x, 0.0, z]) for x in (4.0, 9.0, 14.0, 19.0, 24.0, 28.0 - 2) for z in (5.0, 13.0)]
    ends = cuts = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        n = int(1.2 * 30 * 20 / 1.5)
        mid = rng.uniform([0, 0], [30, 20], (n, 2))
        angle = rng.uniform(0, np.pi, n)
        half = 0.75 * np.column_stack([np.cos(angle), np.sin(angle)])
        traces = [wall_trace(k, [c - h, c + h]) for k, (c, h) in enumerate(zip(mid, half))]
        for centre in centres:
            m = mesh_scan_circle(wall, traces, centre, 2.0)
            ends, cuts = ends + m.ends, cuts + m.cuts
    assert np.pi * 2.0 / 2 * cuts / ends == pytest.approx(1.5, rel=0.05)
    assert cuts / (4 * 2.0) / (6 * len(centres)) == pytest.approx(1.2, rel=0.05)  # a flat disc: m/(4r)


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
    windows = [mesh_scan_circle(mesh, traces, mesh.vertices[v], 1.5) for v in vertices]
    assert sum(w.p21 for w in windows) / np.nansum(exact) == pytest.approx(1.0, rel=0.10)


def test_the_scan_circle_command_reads_windows_and_refuses_one_off_the_rock(tmp_path, capsys):
    """`tracemap scan-circle` on a flat wall seen by two photos, with the hand-counted traces: the same counts,
    in the mesh file's coordinates (UTM-sized)."""
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
    assert main(["scan-circle", str(path), "--at", *map(str, OFFSET + [5.0, 0.0, 3.0]), "--radius", "1"]) == 0
    out = capsys.readouterr().out
    assert "scan circle at (500005, 4200000, 103), r 1 m: 3 trace ends inside, 3 edge cuts: P21 0.75" in out
    assert "note" not in out  # wholly seen, no cut ends
    assert main(["scan-circle", str(path), "--at", *map(str, OFFSET + [5.0, -4.0, 3.0]), "--radius", "1"]) == 2
    assert "no rock within 1 m of its centre" in capsys.readouterr().err


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
    assert "2 trace ends inside, 2 edge cuts: P21 0.25" in out and "P20 0.080 /m²" in out
    assert "mean trace length 3.1" in out and "(GCPs' frame)" in out
