"""Virtual scanlines (engine.scanline): crossings, P10 and spacing against analytic walls, the synthetic outcrop's
fracture discs and scipy's von Mises–Fisher sampler; storage, the command line and the exports."""

import csv
import json
import sqlite3

import numpy as np
import pytest
from scipy.stats import vonmises_fisher

from engine.cli import main
from engine.errors import InputError
from engine.intensity import p10_p32_factor
from engine.mesh import Mesh
from engine.project import SCHEMA_VERSION, Project
from engine.register import Registration, Similarity
from engine.scanline import Scanline, level_scanlines, measure_scanline, pooled, scanline_plot
from engine.synthetic import make_outcrop
from engine.traces import Trace3D
from tests.scenes import grid_wall
from tests.test_cli import OFFSET, new_project, survey  # noqa: F401 (the survey fixture)
from tests.test_project import as_version

EAST = np.array([1.0, 0.0, 0.0])


def vertical_traces(xs, *, set_id=0, offset=(0.0, 0.0, 0.0), z=(0.5, 5.5)):
    """Straight vertical traces on the wall y = 0 at each x, poles east (planes x = const)."""
    out = []
    for i, x in enumerate(xs):
        zs = np.linspace(*z, 11)
        points = np.column_stack([np.full(11, x), np.zeros(11), zs]) + np.asarray(offset)
        out.append(Trace3D(i + 1, points, np.zeros((11, 2)), np.zeros(11, int), np.zeros(11, int), ("left",),
                           normal=EAST, set_id=set_id))
    return out


@pytest.fixture
def wall():
    return Mesh(*grid_wall(step=0.25))


def test_a_level_line_across_parallel_traces_counts_and_spaces_them_exactly(wall):
    traces = vertical_traces(np.arange(1.0, 9.5, 0.75))  # 12 traces 0.75 m apart
    line = Scanline([0.3, 0.0, 3.0], [9.7, 0.0, 3.0])
    m = measure_scanline(wall, traces, line, sets=[{"id": 0, "normal": EAST, "kappa": 1e6}])
    assert [c.trace_id for c in m.crossings] == list(range(1, 13))
    np.testing.assert_allclose([c.distance for c in m.crossings], np.arange(1.0, 9.5, 0.75) - 0.3, atol=1e-9)
    assert m.sampled == pytest.approx(9.4)
    s = m.sets[0]
    assert s.n == 12 and s.p10 == pytest.approx(12 / 9.4)
    np.testing.assert_allclose(s.spacing, 0.75, atol=1e-9)
    np.testing.assert_allclose(s.normal_spacing, 0.75, atol=1e-9)
    assert s.cv == pytest.approx(0.0, abs=1e-9)
    assert s.p10_terzaghi == pytest.approx(s.p10) and s.p32 == pytest.approx(s.p10, rel=1e-5)
    assert all(c.delta == pytest.approx(0.0, abs=1e-6) and c.weight == 1.0 for c in m.crossings)


def test_an_oblique_line_gives_apparent_spacing_and_terzaghi_weights(wall):
    """At α from the traces' poles a line meets them s / cos α apart; normal spacing and the weighted P10
    undo the slant (Priest 1993, eq. 3.3; Terzaghi 1965)."""
    traces = vertical_traces(np.arange(1.0, 9.5, 0.5))
    alpha = np.radians(25.0)
    start = np.array([0.6, 0.0, 1.0])
    line = Scanline(start, start + 8.5 * np.array([np.cos(alpha), 0.0, np.sin(alpha)]))
    m = measure_scanline(wall, traces, line, sets=[{"id": 0, "normal": EAST, "kappa": 1e6}])
    s = m.sets[0]
    np.testing.assert_allclose(s.spacing, 0.5 / np.cos(alpha), rtol=1e-9)
    np.testing.assert_allclose(s.normal_spacing, 0.5, rtol=1e-9)
    assert all(c.delta == pytest.approx(25.0) and c.weight == pytest.approx(1 / np.cos(alpha)) for c in m.crossings)
    assert s.p10_terzaghi == pytest.approx(s.n / np.cos(alpha) / 8.5)
    assert s.p32 == pytest.approx(s.p10_terzaghi, rel=1e-4)  # a set of one orientation: the two agree


def test_a_hole_in_the_mesh_is_not_sampled(wall):
    """Where the mesh has no rock under the line (a hole, the rock beyond reach) nothing can be counted: P10
    is per metre sampled, and the spacing across the gap is unknown."""
    holed = Mesh(*grid_wall(step=0.25, hole=(4.5, 6.5, 2.0, 4.0)))
    traces = [t for t in vertical_traces(np.arange(1.0, 9.5, 1.0)) if not 4.5 < t.points[0, 0] < 6.5]
    m = measure_scanline(holed, traces, Scanline([0.5, 0.0, 3.0], [9.5, 0.0, 3.0]))
    np.testing.assert_allclose(m.rock.runs, [[0.0, 4.0], [6.0, 9.0]], atol=1e-9)
    assert m.sampled == pytest.approx(7.0)
    assert m.all.n == 7 and m.all.p10 == pytest.approx(1.0)
    np.testing.assert_allclose(m.all.spacing, 1.0)  # 4 → 7 m is not a spacing
    plot = scanline_plot(m)
    assert plot.name == "scanline_-1" and [r[0] for r in plot.table.rows] == ["all"] * 7 + ["set 0"] * 7
    assert [r[2] for r in plot.table.rows[:7]] == list(range(1, 8))
    even = plot.figure.axes[0].lines[1]  # the same count spread evenly over the rock: flat across the hole
    np.testing.assert_allclose(even.get_xdata(), [0.0, 0.0, 4.0, 6.0, 9.0, 9.0])
    np.testing.assert_allclose(even.get_ydata(), [0.0, 0.0, 4.0, 4.0, 7.0, 7.0])


def test_a_trace_is_counted_once_and_only_within_reach():
    """A trace that crosses the cutting plane twice counts once; the rock of a second wall 2 m behind is out of
    a 0.5 m reach."""
    v, f = grid_wall(step=0.25)
    v2, f2 = grid_wall(step=0.25, offset=(0.0, 2.0, 0.0))
    mesh = Mesh(np.vstack([v, v2]), np.vstack([f, f2 + len(v)]))
    zigzag = np.array([[2.0, 0.0, 2.0], [2.1, 0.0, 3.5], [2.2, 0.0, 2.5], [2.3, 0.0, 3.4]])
    behind = vertical_traces([5.0], offset=(0.0, 2.0, 0.0))[0]
    traces = [Trace3D(7, zigzag, np.zeros((4, 2)), np.zeros(4, int), np.zeros(4, int), ("left",)), behind]
    m = measure_scanline(mesh, traces, Scanline([0.5, 0.0, 3.0], [9.5, 0.0, 3.0]))
    assert [c.trace_id for c in m.crossings] == [7]
    assert np.isnan(m.crossings[0].delta) and m.crossings[0].weight == 1.0  # no pole: no Terzaghi weight
    assert min(abs(m.crossings[0].distance - x + 0.5) for x in (2.0 + 0.1 / 1.5, 2.15, 2.2 + 0.1 / 1.8)) < 1e-9


@pytest.mark.parametrize("start, end, reach, message", [
    ((0.5, -3.0, 3.0), (9.5, 0.0, 3.0), 0.5, "its start lies 2.82 m or more from the mesh"),
    ((5.0, 0.0, 3.0), (5.0, -0.4, 3.0), 0.5, "within 10° of the rock's normal"),
    ((1.0, 0.0, 3.0), (1.0, 0.0, 3.0), 0.5, "the same point"),
    ((1.0, 0.0, 3.0), (2.0, 0.0, 3.0), 0.0, "reach 0.0: expected a distance > 0 m"),
])
def test_bad_scanlines_are_refused_with_the_reason(wall, start, end, reach, message):
    with pytest.raises(InputError, match=message):
        measure_scanline(wall, [], Scanline(start, end, reach=reach))


def test_crossings_on_the_synthetic_outcrop_are_where_the_fracture_discs_cut_the_rock():
    """Oracle: the true traces a scanline crosses are the fractures whose discs the rock under it passes
    through, found from the discs and the clean mesh alone, at the same distances (within 1 mm)."""
    outcrop = make_outcrop(2, n_cameras=1, image_size=(64, 48), mesh_spacing=0.05)
    mesh, fractures = outcrop.mesh, {f.id: f for f in outcrop.fractures}
    traces = [Trace3D(t.id, t.points - outcrop.origin, np.zeros((len(t.points), 2)), t.face,
                      np.zeros(len(t.points), int), ("x",), normal=fractures[t.fracture_id].normal,
                      set_id=fractures[t.fracture_id].set_id) for t in outcrop.traces3d]
    fracture_of = {t.id: t.fracture_id for t in outcrop.traces3d}
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    counted = 0
    for z in np.linspace(lo[2] + 0.8, hi[2] - 0.8, 5):
        line = Scanline([lo[0] + 0.5, 0.0, z], [hi[0] - 0.5, 0.0, z], reach=1.5)
        line = Scanline(_on_rock(mesh, line.start), _on_rock(mesh, line.end), reach=1.5)
        m = measure_scanline(mesh, traces, line)
        expected = _disc_crossings(m, fractures.values(), outcrop.origin)
        found = {}
        for c in m.crossings:
            found.setdefault(fracture_of[c.trace_id], []).append(c.distance)
        assert set(found) == set(expected)
        for fid, distances in found.items():
            for d in distances:
                assert np.min(np.abs(np.array(expected[fid]) - d)) < 1e-3
        counted += len(m.crossings)
    assert counted >= 40  # the oracle was tried on enough crossings to mean something


def _on_rock(mesh, point):
    """The mesh vertex nearest a point's horizontal line through the wall (y free)."""
    i = np.argmin(np.linalg.norm(mesh.vertices[:, [0, 2]] - point[[0, 2]], axis=1))
    return mesh.vertices[i]


def _disc_crossings(m, fractures, origin):
    """Distances along the line where the rock section under it crosses each planar fracture inside its disc."""
    a, b = m.rock.section[:, 0] + origin, m.rock.section[:, 1] + origin
    out = {}
    for f in fractures:
        sa, sb = (a - f.centre) @ f.normal, (b - f.centre) @ f.normal
        cut = (sa > 0) != (sb > 0)
        x = a[cut] + (sa[cut] / (sa[cut] - sb[cut]))[:, None] * (b[cut] - a[cut])
        inside = np.linalg.norm(x - f.centre, axis=1) <= f.radius
        if inside.any():
            out[f.id] = list((x[inside] - origin - m.line.start) @ m.line.direction)
    return out


@pytest.mark.parametrize("kappa, delta", [(0.0, 0.0), (0.0, 70.0), (5.0, 20.0), (20.0, 60.0), (100.0, 85.0)])
def test_p10_to_p32_factor_matches_scipys_von_mises_fisher_sampler(kappa, delta):
    """P32 = P10 / E_f[|cos δ|] (MATHS §8, linear sampling): against the mean over 2M poles drawn by
    scipy.stats.vonmises_fisher (standard error under 0.1%), and the limits 2 (uniform) and 1/cos δ."""
    d = np.radians(delta)
    line = np.array([np.sin(d), 0.0, np.cos(d)])
    if kappa == 0:
        expected = 2.0
    else:
        poles = vonmises_fisher(np.array([0.0, 0.0, 1.0]), kappa).rvs(2_000_000, random_state=np.random.default_rng(5))
        expected = 1.0 / np.abs(poles @ line).mean()
    assert float(p10_p32_factor(kappa, delta)) == pytest.approx(expected, rel=2e-3)
    assert float(p10_p32_factor(1e6, delta)) == pytest.approx(1 / np.cos(d), rel=1e-3)


def test_scanlines_are_stored_undone_and_a_version_2_project_gains_their_table(survey):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    path = d / "p.tracemap"
    as_version(path, 2)
    with Project.open(path) as p:
        assert p.scanlines() == []
        first = p.add_scanline(Scanline([1.0, 0.0, 3.0], [9.0, 0.0, 3.0], reach=0.3, name="north"))
        second = p.add_scanline(Scanline([1.0, 0.0, 2.0], [9.0, 0.0, 2.0]))
        kept = p.scanlines()
        assert [(s.id, s.name, s.reach) for s in kept] == [(first, "north", 0.3), (second, "", 0.8)]  # 8 m / 10
        np.testing.assert_array_equal(kept[0].end, [9.0, 0.0, 3.0])
        p.remove_scanline(first)
        assert [s.id for s in p.scanlines()] == [second]
        p.restore_scanline(kept[0])
        assert [s.id for s in p.scanlines()] == [first, second]
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert sqlite3.connect(d / "p.v2.bak.tracemap").execute("PRAGMA user_version").fetchone()[0] == 2


def test_the_scanline_command_lays_lists_removes_and_exports(survey, capsys):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    path = d / "p.tracemap"
    with Project.open(path) as p:
        p.add_traces3d([t for t in vertical_traces(np.arange(1.0, 9.5, 1.0), offset=OFFSET - p.origin)])
    start, end = OFFSET + [0.5, 0.0, 3.0], OFFSET + [9.5, 0.0, 3.0]
    args = ["scanline", str(path), "--from", *map(str, start), "--to", *map(str, end), "--name", "level"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "scanline 1 (level): 9.00 m (9.00 m of it over rock), 9 traces crossed" in out
    assert "set 0: 9 traces, P10 1.000 /m" in out and "spacing mean 1.00 m" in out
    assert main(["scanline", str(path)]) == 0 and "scanline 1 (level)" in capsys.readouterr().out
    assert main(["export", str(d / "p.tracemap"), str(d / "out")]) == 0
    with open(d / "out" / "scanlines.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["distance_m"]) for r in rows] == pytest.approx(np.arange(0.5, 9.0, 1.0))
    assert float(rows[0]["x"]) == pytest.approx(OFFSET[0] + 1.0) and float(rows[0]["y"]) == pytest.approx(OFFSET[1])
    report = json.loads((d / "out" / "summary.json").read_text())["scanlines"]
    assert report[0]["name"] == "level" and report[0]["groups"]["set0"]["p10_per_m"] == pytest.approx(1.0)
    assert report[0]["start"] == pytest.approx(list(start))
    assert main(["export", str(path), str(d / "gpkg"), "--format", "gpkg"]) == 0
    gpkg = sqlite3.connect(d / "gpkg" / "traces.gpkg")
    assert gpkg.execute("SELECT name, crossings, p10_per_m FROM scanlines").fetchall() == [("level", 9, 1.0)]
    gpkg.close()
    assert main(["export", str(path), str(d / "vtp"), "--format", "vtp"]) == 0
    import pyvista as pv

    poly = pv.read(d / "vtp" / "scanlines.vtp")
    kind = np.asarray(poly.cell_data["kind"])
    assert poly.n_verts == 9 and np.count_nonzero(kind == 1) == 9 and np.count_nonzero(kind == 0) == poly.n_lines
    crossing_x = np.asarray(poly.points)[poly.verts.reshape(-1, 2)[:, 1], 0] - OFFSET[0]
    np.testing.assert_allclose(np.sort(crossing_x), np.arange(1.0, 9.5, 1.0), atol=1e-6)
    assert set(np.asarray(poly.cell_data["scanline"]).tolist()) == {1}
    np.testing.assert_allclose(np.sort(np.asarray(poly.cell_data["distance"])[kind == 1]), np.arange(0.5, 9.0, 1.0))
    assert main(["plot", str(path), "-o", str(d / "plots")]) == 0
    with open(d / "plots" / "scanline_1.csv", newline="") as f:
        assert [int(r["count"]) for r in csv.DictReader(f) if r["group"] == "set 0"] == list(range(1, 10))
    assert (d / "plots" / "scanline_1.png").stat().st_size > 10_000
    assert main(["scanline", str(path), "--remove", "1"]) == 0
    assert main(["scanline", str(path)]) == 0 and "no scanlines yet" in capsys.readouterr().out


def test_scanline_readouts_and_exports_are_in_the_registered_frame(survey, capsys):  # noqa: F811
    """A registration of scale 2: distances and spacing twice as long, P10 half, --reach in its metres."""
    d, _ = survey
    assert new_project(d) == 0
    path = d / "p.tracemap"
    with Project.open(path) as p:
        p.add_traces3d(vertical_traces(np.arange(1.0, 9.5, 1.0), offset=OFFSET - p.origin))
        sim = Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0)
        p.set_registration(Registration(("a", "b", "c"), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3),
                                        (("left",),) * 3, sim))
    start, end = OFFSET + [0.5, 0.0, 3.0], OFFSET + [9.5, 0.0, 3.0]
    assert main(["scanline", str(path), "--from", *map(str, start), "--to", *map(str, end), "--reach", "1"]) == 0
    out = capsys.readouterr().out
    assert "18.00 m (18.00 m of it over rock)" in out and "P10 0.500 /m" in out and "GCPs' frame" in out
    with Project.open(path) as p:
        assert p.scanlines()[0].reach == pytest.approx(0.5)
    assert main(["export", str(path), str(d / "out")]) == 0
    report = json.loads((d / "out" / "summary.json").read_text())["scanlines"][0]
    assert report["length_m"] == pytest.approx(18.0) and report["reach_m"] == pytest.approx(1.0)
    assert report["groups"]["all"]["mean_spacing_m"] == pytest.approx(2.0)
    assert report["start"] == pytest.approx(list(2 * start))


@pytest.mark.parametrize("ends, more, message", [
    (((0, -5, 3), (9, 0, 3)), [], "its start lies 4.82 m or more from the mesh"),
    (((1, 0, 3), None), [], "give both ends"),
    ((None, None), ["--remove", "4"], "no scanline with id 4"),
    (((1, 0, 3), (2, 0, 3)), ["--remove", "1"], "give one of --from/--to, --levels or --remove"),
])
def test_bad_scanline_commands_name_the_problem_and_store_nothing(survey, capsys, ends, more, message):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    path = d / "p.tracemap"
    args = [word for option, end in zip(("--from", "--to"), ends) if end is not None
            for word in (option, *map(str, OFFSET + end))]
    assert main(["scanline", str(path), *args, *more]) == 2
    assert message in capsys.readouterr().err
    with Project.open(path) as p:
        assert p.scanlines() == []


def test_p32_from_scanlines_recovers_the_synthetic_sets_realised_p32():
    """Stereology end to end: eight level scanlines on each of six synthetic outcrops (true traces, true poles,
    the generating κ), P32 = P10 / E_f[|cos δ|] pooled over the metres sampled, against each set's realised P32
    (disc area per volume). Measured: set 0 1.10, 0.87, 0.90, 1.00, 1.12, 0.98 of it (pooled 0.99), set 1 0.76,
    1.11, 0.78, 0.72, 0.83, 1.10 (pooled 0.88), about 60 crossings per set and outcrop: within 20% pooled,
    where leaving out the factor (≈ 1.4 for these sets) would give about 0.7."""
    estimate, truth = np.zeros(2), np.zeros(2)
    for seed in range(1, 7):
        outcrop = make_outcrop(seed, n_cameras=1, image_size=(64, 48), mesh_spacing=0.05)
        mesh, fractures = outcrop.mesh, {f.id: f for f in outcrop.fractures}
        traces = [Trace3D(t.id, t.points - outcrop.origin, np.zeros((len(t.points), 2)), t.face,
                          np.zeros(len(t.points), int), ("x",), normal=fractures[t.fracture_id].normal,
                          set_id=fractures[t.fracture_id].set_id) for t in outcrop.traces3d]
        sets = [{"id": s.id, "normal": s.normal, "kappa": s.kappa} for s in outcrop.sets]
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        for z in np.linspace(lo[2] + 0.5, hi[2] - 0.5, 8):
            ends = [_on_rock(mesh, np.array([x, 0.0, z])) for x in (lo[0] + 0.3, hi[0] - 0.3)]
            m = measure_scanline(mesh, traces, Scanline(*ends, reach=1.5), sets=sets)
            estimate += [m.sets[k].p32 * m.sampled if k in m.sets else 0.0 for k in (0, 1)]
            truth += m.sampled * np.array([s.p32 for s in outcrop.sets])
    np.testing.assert_allclose(estimate / truth, 1.0, atol=0.2)


def test_with_the_survey_only_the_rock_a_photo_sees_is_sampled(wall):
    """One photo seeing the west part of the wall: the line is sampled where the photo sees the rock under
    it (the points of the line that project inside the photo, found here from the camera alone), and the
    traces beyond are not counted (no photo could show them)."""
    from engine.raytrace import RayTracer
    from engine.sight import Sight
    from tests.scenes import facing_camera

    camera = facing_camera("west", centre=(2.5, -5.0, 3.0), width=400, height=600, f=500.0)
    sight = Sight(wall, {"west": camera}, RayTracer(wall.vertices, wall.faces))
    line = Scanline([0.5, 0.0, 3.0], [9.5, 0.0, 3.0])
    x = np.linspace(0.5, 9.5, 9001)
    uv = camera.project(np.column_stack([x, np.zeros_like(x), np.full_like(x, 3.0)]))
    inside = x[(uv[:, 0] >= 3.0 - 0.5) & (uv[:, 0] <= camera.width - 3.5)]  # Sight's BORDER_PX
    xs = np.arange(1.1, 9.5, 0.5)  # none within a face (0.25 m) of the end of the seen rock, at x 4.47
    m = measure_scanline(wall, vertical_traces(xs), line, sight=sight)
    assert len(m.rock.runs) == 1
    np.testing.assert_allclose(m.rock.runs[0], [inside.min() - 0.5, inside.max() - 0.5], atol=0.25)  # a face
    assert m.all.n == np.count_nonzero((xs > inside.min()) & (xs < inside.max())) == 7
    assert measure_scanline(wall, [], line).sampled == pytest.approx(9.0)  # without the survey: all the rock


def test_the_default_reach_is_a_tenth_of_the_length_and_at_least_half_a_metre():
    assert Scanline([0.0, 0.0, 0.0], [18.0, 0.0, 0.0]).reach == pytest.approx(1.8)
    assert Scanline([0.0, 0.0, 0.0], [2.0, 0.0, 0.0]).reach == pytest.approx(0.5)
    assert Scanline([0.0, 0.0, 0.0], [2.0, 0.0, 0.0], reach=0.2).reach == 0.2


def test_level_scanlines_survey_the_face_at_even_heights_and_pool():
    """Four level lines on a 10 × 6 m wall, 1 m clear of its edges: heights 1, 2.33, 3.67, 5 m, each from
    x 1 to 9 on the rock; pooled, the counts add and P10 is per metre of all the lines."""
    wall = Mesh(*grid_wall(width=10.0, height=6.0, step=0.25))
    lines = level_scanlines(wall, 4, margin=1.0)
    assert [line.name for line in lines] == ["level 1", "level 2", "level 3", "level 4"]
    np.testing.assert_allclose([line.start[2] for line in lines], [1.0, 2.25, 3.75, 5.0])  # nearest vertices
    for line in lines:
        assert line.start[2] == line.end[2] and line.start[0] == pytest.approx(1.0) and line.end[0] == 9.0
    traces = vertical_traces(np.arange(1.5, 9.0, 1.0), z=(0.1, 5.9))
    measures = [measure_scanline(wall, traces, line, sets=[{"id": 0, "normal": EAST, "kappa": 1e6}])
                for line in lines]
    total = pooled(measures)
    assert total["all"]["n"] == 4 * 8 and total["all"]["sampled_m"] == pytest.approx(4 * 8.0)
    assert total["set0"]["p10_per_m"] == pytest.approx(1.0)
    assert total["set0"]["p32_per_m"] == pytest.approx(1.0, rel=1e-4)
    scaled = pooled(measures, Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((3, 3)), np.zeros(3), 0.0))
    assert scaled["all"]["sampled_m"] == pytest.approx(64.0) and scaled["all"]["p10_per_m"] == pytest.approx(0.5)
    with pytest.raises(InputError, match="narrower than twice the margin"):
        level_scanlines(wall, 3, margin=5.5)


def test_the_scanline_command_lays_a_survey_of_levels(survey, capsys):  # noqa: F811
    d, _ = survey
    assert new_project(d) == 0
    path = d / "p.tracemap"
    with Project.open(path) as p:
        p.add_traces3d(vertical_traces(np.arange(1.5, 9.0, 1.0), offset=OFFSET - p.origin, z=(0.1, 5.9)))
    assert main(["scanline", str(path), "--levels", "3", "--name", "bench"]) == 0
    out = capsys.readouterr().out
    assert "scanline 3 (bench 3): 8.00 m" in out and "all 3 scanlines: 24.00 m sampled, 24 crossings" in out
    assert main(["export", str(path), str(d / "out")]) == 0
    summary = json.loads((d / "out" / "summary.json").read_text())
    assert len(summary["scanlines"]) == 3 and summary["scanlines_pooled"]["all"]["p10_per_m"] == pytest.approx(1.0)
    assert main(["scanline", str(path), "--levels", "2", "--remove", "1"]) == 2
    assert "give one of --from/--to, --levels or --remove" in capsys.readouterr().err
    with Project.open(path) as p:
        assert len(p.scanlines()) == 3


def test_level_scanlines_follow_the_given_vertical():
    """A mesh in a frame turned 30° about y (as an unregistered model can be): with that frame's vertical, the
    levels lie level in it, at the heights of the upright wall."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    v, f = grid_wall(width=10.0, height=6.0, step=0.25)
    lines = level_scanlines(Mesh(v @ turn.T, f), 3, margin=1.0, up=turn @ [0.0, 0.0, 1.0])
    for line, height in zip(lines, (1.0, 3.0, 5.0)):
        upright = np.array([line.start, line.end]) @ turn  # back in the wall's own frame
        np.testing.assert_allclose(upright[:, 2], height, atol=1e-9)
        np.testing.assert_allclose(upright[:, 0], [1.0, 9.0], atol=1e-9)
