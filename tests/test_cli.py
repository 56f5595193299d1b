import csv
import json
import os
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest
import trimesh

from engine.cli import main
from engine.merge import suggest_merges
from engine.orientation import axial_angle, dip_dipdir_to_normal
from engine.project import Project
from engine.raytrace import RayTracer
from engine.sight import Sight
from tests.scenes import facing_camera, grid_wall, wall_point

OFFSET = np.array([500_000.0, 4_200_000.0, 100.0])


@pytest.fixture
def survey(tmp_path):
    """A wall mesh at UTM coordinates, two cameras (native JSON), their photos and a traces CSV."""
    v, f = grid_wall(step=0.25, offset=OFFSET)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "wall.obj")
    cams = [facing_camera("left", centre=(3.0, -8.0, 3.0), offset=OFFSET),
            facing_camera("right", centre=(7.0, -8.0, 3.0), offset=OFFSET, distortion=(-0.2, 0.05))]
    (tmp_path / "images").mkdir()
    for c in cams:
        cv2.imwrite(str(tmp_path / "images" / f"{c.name}.png"), np.zeros((c.height, c.width, 3), np.uint8))
    (tmp_path / "cameras.json").write_text(json.dumps(
        {"format": "tracemap-cameras", "version": 1, "cameras": [c.to_dict() for c in cams]}))
    rows = [("left", 1, 100, 100), ("left", 1, 300, 250.5), ("left", 1, 500, 260),
            ("left", 2, 700, 50), ("left", 2, 650, 500), ("right", "a", 20, 300), ("right", "a", 780, 310)]
    write_rows(tmp_path / "traces.csv", ("image", "trace", "u", "v"), rows)
    return tmp_path, {c.name: c for c in cams}


def write_rows(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def new_project(d):
    return main(["new", str(d / "p.tracemap"), "--mesh", str(d / "wall.obj"), "--cameras", str(d / "cameras.json"),
                 "--images", str(d / "images")])


def test_every_command_prints_its_help(capsys):
    """`tracemap COMMAND --help` prints the options and exits 0: help texts are %-formatted by argparse, and a
    parameter's doc with a percent sign ("0.08 ≈ 8%") once made `autotrace --help` a traceback."""
    from engine.cli import build_parser

    commands = build_parser()._subparsers._group_actions[0].choices
    assert {"new", "extract", "autotrace", "merge", "orient", "analyse", "export"} <= set(commands)
    for name in commands:
        with pytest.raises(SystemExit) as exit_:
            main([name, "--help"])
        assert exit_.value.code == 0, name
        assert "usage: tracemap " + name in capsys.readouterr().out
    main_help = subprocess.run([sys.executable, "-m", "engine.cli", "autotrace", "--help"], capture_output=True,
                               text=True, check=False)
    assert main_help.returncode == 0 and "--line-low X" in main_help.stdout and "≈ a line 7% darker" in \
        " ".join(main_help.stdout.split()), main_help.stderr[-500:]
    from engine.delineate.params import SECTIONS
    headings = [main_help.stdout.index(f"delineation: {title}:") for title in SECTIONS.values()]
    assert headings == sorted(headings)  # one group per stage, in pipeline order
    text = main_help.stdout
    group = text[text.index("delineation: line filter:"):text.index("delineation: segments:")]
    assert "--line-sigma X" in group and "--low X" not in group


def test_pipeline_round_trips_world_coordinates(survey, capsys):
    d, cams = survey
    assert new_project(d) == 0
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")]) == 0
    assert main(["extract", str(d / "p.tracemap")]) == 0
    assert main(["export", str(d / "p.tracemap"), str(d / "out")]) == 0
    out = capsys.readouterr().out
    assert "imported 3 2D traces" in out and "extracted 3 3D traces" in out
    with open(d / "out" / "trace_vertices.csv") as f:
        rows = list(csv.DictReader(f))
    xyz = np.array([[float(r[k]) for k in "xyz"] for r in rows])
    uv = np.array([[float(r["u"]), float(r["v"])] for r in rows])
    images = np.array([r["image"] for r in rows])
    for name, cam in cams.items():
        sel = images == name
        expected = wall_point(cam, uv[sel], wall_y=OFFSET[1])
        assert np.abs(xyz[sel] - expected).max() < 1e-3  # millimetres at UTM scale
    summary = json.loads((d / "out" / "summary.json").read_text())
    assert summary["traces3d"]["total"] == 3 and summary["traces2d"]["total"] == 3
    with open(d / "out" / "traces2d.csv") as f:
        assert len(list(csv.DictReader(f))) == 7
    with open(d / "out" / "traces.csv") as f:
        t = list(csv.DictReader(f))
    assert float(t[0]["surface_length"]) >= float(t[0]["chord_length"]) > 0


def test_re_extracting_replaces_rather_than_duplicates(survey):
    d, _ = survey
    new_project(d)
    main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")])
    main(["extract", str(d / "p.tracemap")])
    main(["extract", str(d / "p.tracemap"), "--image", "left"])
    with Project.open(d / "p.tracemap") as p:
        assert len(p.traces3d()) == 3


def test_import_traces_labels_the_2d_components_of_the_photos_it_adds_to(survey):
    d, _ = survey
    new_project(d)
    crossing = [("left", "a", 100, 100), ("left", "a", 300, 300), ("left", "b", 100, 300), ("left", "b", 300, 100)]
    apart = [("left", "c", 500, 400), ("left", "c", 700, 500), ("right", "d", 10, 10), ("right", "d", 90, 10)]
    write_rows(d / "first.csv", ("image", "trace", "u", "v"), crossing + apart)
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "first.csv")]) == 0
    with Project.open(d / "p.tracemap") as p:
        assert [(t.image, t.component) for t in p.traces2d()] == [("left", 0), ("left", 0), ("left", 1),
                                                                  ("right", 0)]
    # a later import joining c to a and b relabels the traces already stored on that photo
    write_rows(d / "bridge.csv", ("image", "trace", "u", "v"), [("left", "e", 300, 300), ("left", "e", 600, 450)])
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "bridge.csv")]) == 0
    with Project.open(d / "p.tracemap") as p:
        assert [t.component for t in p.traces2d()] == [0, 0, 0, 0, 0]


@pytest.mark.parametrize("rows, message", [
    ([("image", "trace", "u")], "missing column(s) v"),
    ([("image", "trace", "u", "v"), ("left", 1, "abc", 3), ("left", 1, 4, 5)], "line 2: column u is 'abc'"),
    ([("image", "trace", "u", "v"), ("left", 1, 1, 3), ("left", 1, 4, 5, 6)],
     "line 3: 5 fields, expected 4 as in the header (image,trace,u,v)"),
    ([("image", "trace", "u", "v"), ("left", 1, 1, 3), ("left", 1, 900, 5)], "outside the 800×600 photo"),
    ([("image", "trace", "u", "v"), ("nope", 1, 1, 3), ("nope", 1, 4, 5)], "image 'nope' is not in the project"),
    ([("image", "trace", "u", "v"), ("left", 1, 1, 3)], "at least 2 needed"),
])
def test_bad_trace_csv(survey, capsys, rows, message):
    d, _ = survey
    new_project(d)
    write_rows(d / "bad.csv", rows[0], rows[1:])
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.csv" in err and "Traceback" not in err
    with Project.open(d / "p.tracemap") as p:
        assert p.traces2d() == []


def test_bad_inputs_to_new(survey, capsys):
    d, _ = survey
    assert main(["new", str(d / "p.tracemap"), "--mesh", str(d / "missing.ply"),
                 "--cameras", str(d / "cameras.json")]) == 2
    assert "missing.ply" in capsys.readouterr().err
    cv2.imwrite(str(d / "images" / "left.png"), np.zeros((10, 20, 3), np.uint8))
    assert new_project(d) == 2
    err = capsys.readouterr().err
    assert "left.png" in err and "800" in err
    assert not (d / "p.tracemap").exists()


def test_project_in_use_is_refused(survey, capsys):
    d, _ = survey
    new_project(d)
    with Project.open(d / "p.tracemap"):
        code = textwrap.dedent(f"""
            import sys
            from engine.cli import main
            sys.exit(main(["extract", {str(d / "p.tracemap")!r}]))
        """)
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 2 and "open in process" in done.stderr


def test_killed_extract_leaves_project_as_it_was(survey):
    d, _ = survey
    new_project(d)
    main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")])
    main(["extract", str(d / "p.tracemap"), "--image", "right"])
    code = textwrap.dedent(f"""
        import os
        from engine import project
        from engine.cli import main
        real = project.Project.add_traces3d
        def dying(self, traces, db=None):
            real(self, list(traces)[:1], db)  # half the work is written, then the process is killed
            os._exit(9)
        project.Project.add_traces3d = dying
        main(["extract", {str(d / "p.tracemap")!r}])
    """)
    done = subprocess.run([sys.executable, "-c", code])
    assert done.returncode == 9
    with Project.open(d / "p.tracemap") as p:
        traces = p.traces3d()
    assert len(traces) == 1 and traces[0].images == ("right",)


def test_disk_full_during_export_writes_nothing(survey, capsys, monkeypatch):
    import errno

    import engine.io

    d, _ = survey
    new_project(d)
    main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")])
    real = engine.io.write_json

    def full(path, data):
        real(path, data)
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(engine.io, "write_json", full)
    assert main(["export", str(d / "p.tracemap"), str(d / "out")]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert not (d / "out").exists()  # the folder made for the export is removed with it


def test_export_clears_the_scratch_folder_a_killed_export_left(survey):
    d, _ = survey
    new_project(d)
    (d / "out" / ".tracemap-999999999-x1").mkdir(parents=True)  # no such process: killed mid-export
    (d / "out" / ".tracemap-999999999-x1" / "traces.csv").write_text("partial")
    alive = d / "out" / f".tracemap-{os.getpid()}-x2"  # an export still running here: left alone
    alive.mkdir()
    assert main(["export", str(d / "p.tracemap"), str(d / "out")]) == 0
    assert sorted(p.name for p in (d / "out").iterdir() if p.name.startswith(".")) == [alive.name]


def fill_disk(monkeypatch):
    """From now on every project opened is full: SQLite may not grow it by a page (SQLITE_FULL)."""
    import engine.project

    real = engine.project._connect

    def connect(path):
        db = real(path)
        pages = db.execute("PRAGMA page_count").fetchone()[0]
        db.execute(f"PRAGMA max_page_count = {pages}")
        return db

    monkeypatch.setattr(engine.project, "_connect", connect)


def test_disk_full_during_import_traces_is_a_clear_error(survey, capsys, monkeypatch):
    d, _ = survey
    new_project(d)
    long_trace = [("left", 1, u / 10, 300) for u in range(7000)]  # a 112 kB blob: more pages than the file has
    write_rows(d / "long.csv", ("image", "trace", "u", "v"), long_trace)
    capsys.readouterr()
    fill_disk(monkeypatch)
    assert main(["import-traces", str(d / "p.tracemap"), str(d / "long.csv")]) == 2
    err = capsys.readouterr().err
    assert "p.tracemap: the disk is full" in err and "project is unchanged" in err
    assert "internal error" not in err and "cannot rollback" not in err
    monkeypatch.undo()
    with Project.open(d / "p.tracemap") as p:
        assert p.traces2d() == []


def test_disk_full_during_extract_keeps_the_earlier_3d_traces(survey, capsys, monkeypatch):
    d, _ = survey
    new_project(d)
    main(["import-traces", str(d / "p.tracemap"), str(d / "traces.csv")])
    main(["extract", str(d / "p.tracemap"), "--image", "right"])
    with Project.open(d / "p.tracemap") as p:
        before = p.traces3d()
    capsys.readouterr()
    fill_disk(monkeypatch)
    assert main(["extract", str(d / "p.tracemap")]) == 2
    err = capsys.readouterr().err
    assert "p.tracemap: the disk is full" in err and "project is unchanged" in err and "internal error" not in err
    monkeypatch.undo()
    with Project.open(d / "p.tracemap") as p:
        after = p.traces3d()
    assert [t.id for t in after] == [t.id for t in before] and len(after) == 1 and after[0].images == ("right",)
    np.testing.assert_array_equal(after[0].points, before[0].points)


def test_analyse_map_command(tmp_path, capsys):
    def feature(coords, kind="LineString"):
        return {"type": "Feature", "properties": {}, "geometry": {"type": kind, "coordinates": coords}}

    # a cross (X), a T and a line leaving the area (E), in a 10 × 10 square
    lines = [[[1, 5], [9, 5]], [[5, 1], [5, 9]], [[2, 2], [2, 5]], [[8, 8], [12, 8]]]
    (tmp_path / "traces.geojson").write_text(json.dumps(
        {"type": "FeatureCollection", "features": [feature(c) for c in lines]}))
    (tmp_path / "area.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        feature([[[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]]], "Polygon")]}))
    assert main(["analyse-map", str(tmp_path / "traces.geojson"), str(tmp_path / "area.geojson"),
                 "-o", str(tmp_path / "out"), "--bootstrap", "0"]) == 0
    out = capsys.readouterr().out
    assert "1 X" in out and "1 E" in out and "1 Y" in out
    assert (tmp_path / "out" / "summary.json").is_file()
    assert main(["analyse-map", str(tmp_path / "traces.geojson"), str(tmp_path / "area.geojson"),
                 "-o", str(tmp_path / "circle"), "--bootstrap", "0", "--scan-circle", "3", "5", "1.5"]) == 0
    assert "Mauldon, scan circle 1 (r 1.5): 1 ends inside, 3 edge cuts: P21 0.5," in capsys.readouterr().out
    circles = json.loads((tmp_path / "circle" / "summary.json").read_text())["scan_circles"]
    assert circles[0]["edge_cuts"] == 3 and circles[0]["mean_length"] == pytest.approx(3 * 1.5 * np.pi / 2)
    assert main(["analyse-map", str(tmp_path / "traces.geojson"), str(tmp_path / "area.geojson"),
                 "-o", str(tmp_path / "beyond"), "--scan-circle", "9", "9", "3"]) == 2
    assert "reaches beyond the sampling area" in capsys.readouterr().err and not (tmp_path / "beyond").exists()
    assert main(["analyse-map", str(tmp_path / "traces.geojson"), "-o", str(tmp_path / "out2")]) == 2
    assert "no sampling area given" in capsys.readouterr().err
    assert not (tmp_path / "out2").exists()


def test_orient_and_analyse_commands(quick_demo, tmp_path, capsys):
    import shutil

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    assert main(["orient", project]) == 0
    out = capsys.readouterr().out
    assert "probabilistic" in out and "set 0:" in out
    assert main(["analyse", project, "--radius", "0.5", "--bootstrap", "9"]) == 0
    out = capsys.readouterr().out
    assert "terminations:" in out and "Kaplan–Meier median" in out and "p32" in out
    with Project.open(project) as p:
        traces = p.traces3d()
        assert all(t.term_start in "BTXC" and t.term_start for t in traces)
        assert p.result("sets") and p.result("topology")["nodes"]["N_L"] > 0
        p21, info = p.vertex_map("p21")
        assert info == {"radius": 0.5} and np.nanmax(p21) > 0
    assert main(["render", project, "-o", str(tmp_path / "p32.png"), "--color-by", "p32", "--size", "320", "200"]) == 0
    assert main(["orient", project, "--sets", "100000"]) == 2
    assert "sets asked for" in capsys.readouterr().err


def test_summary_json_carries_sets_nodes_km_medians_and_p21_in_the_export_frame(quick_demo, tmp_path):
    import shutil

    from engine.intensity import imaged_faces
    from engine.io import summary
    from engine.register import Similarity

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    assert main(["orient", project]) == 0
    assert main(["analyse", project, "--radius", "0.5", "--bootstrap", "9"]) == 0
    assert main(["export", project, str(tmp_path / "out")]) == 0
    made = json.loads((tmp_path / "out" / "summary.json").read_text())
    with Project.open(project) as p:
        traces, sets = p.traces3d(), p.result("sets")
        topology, lengths = p.result("topology"), p.result("lengths")
        mesh = p.load_mesh()
        imaged = imaged_faces(mesh, p.cameras(), RayTracer(mesh.vertices, mesh.faces))
        p21_map = p.vertex_map("p21")[0]
        registered = summary(p, p.traces2d(), traces, Similarity(2.0, np.eye(3), np.zeros(3), np.zeros((0, 3)),
                                                                 np.zeros(0), 0.0))
    assert [s["traces"] for s in made["sets"]["sets"]] == [sum(t.set_id == s["id"] for t in traces) for s in sets]
    assert made["sets"]["non_systematic"] == sum(t.set_id == -1 for t in traces)
    peaks = made["sets"]["density_peaks"]  # the pole density's maxima, each near a set mean here
    assert peaks and peaks[0]["density"] >= peaks[-1]["density"] > 1
    assert min(axial_angle(dip_dipdir_to_normal(peaks[0]["dip"], peaks[0]["dip_direction"]), s["normal"])
               for s in sets) < 10
    assert {k: made["nodes"][k] for k in "BTXC"} == {k: topology["nodes"][k] for k in "BTXC"}
    assert made["nodes"]["C_L"] == pytest.approx(topology["nodes"]["C_L"])
    assert made["kaplan_meier"]["all"]["median_m"] == pytest.approx(lengths["all"]["kaplan_meier"]["median"])
    assert {k for k in made["kaplan_meier"] if k != "all"} <= {"non_systematic", *(f"set{s['id']}" for s in sets)}
    # the outcrop's P21: every trace's surface length over the area the photos see (an independent sum)
    area = float(mesh.face_areas[imaged].sum())
    intensity = made["intensity"]
    assert intensity["imaged_area_m2"] == pytest.approx(area, rel=1e-9) and intensity["radius_m"] == 0.5
    assert intensity["p21_outcrop"]["all"] == pytest.approx(sum(t.surface_length for t in traces) / area, rel=1e-9)
    assert intensity["maps"]["p21"]["median"] == pytest.approx(np.nanmedian(p21_map), rel=1e-6)
    # registered at scale 2: lengths double, areas quadruple, intensities halve
    assert registered["kaplan_meier"]["all"]["median_m"] == pytest.approx(2 * made["kaplan_meier"]["all"]["median_m"])
    assert registered["traces3d"]["total_surface_length_m"] == pytest.approx(
        2 * made["traces3d"]["total_surface_length_m"])
    assert registered["intensity"]["imaged_area_m2"] == pytest.approx(4 * area, rel=1e-9)
    assert registered["intensity"]["p21_outcrop"]["all"] == pytest.approx(intensity["p21_outcrop"]["all"] / 2)
    assert registered["intensity"]["maps"]["p32"]["mean"] == pytest.approx(intensity["maps"]["p32"]["mean"] / 2)
    assert registered["intensity"]["radius_m"] == 1.0


def test_merge_pairs_in_a_chain_and_refuses_a_trace_with_itself(quick_demo, tmp_path, capsys):
    import shutil

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    with Project.open(project) as p:
        before = p.traces3d()
    a, b, c = [t.id for t in before if len(t.points) >= 3][:3]
    assert main(["merge", project, "--pair", str(a), str(a)]) == 2
    assert f"--pair {a} {a}: a trace cannot be merged with itself" in capsys.readouterr().err
    assert main(["merge", project, "--pair", str(a), str(b), "--pair", str(b), str(a)]) == 2
    assert "already merged by an earlier --pair" in capsys.readouterr().err
    with Project.open(project) as p:  # refused commands change nothing
        assert [t.id for t in p.traces3d()] == [t.id for t in before]
    assert main(["merge", project, "--pair", str(a), str(b), "--pair", str(b), str(c)]) == 0
    assert f"merged 3 3D traces into 1; {len(before) - 2} traces now" in capsys.readouterr().out
    with Project.open(project) as p:
        after = p.traces3d()
    assert len(after) == len(before) - 2 and {a, b, c}.isdisjoint({t.id for t in after})
    (made,) = [t for t in after if t.id not in {u.id for u in before}]
    assert made.extra["merged_from"] == sorted([a, b, c])


def test_merge_and_export_formats(quick_demo, tmp_path, capsys):
    import shutil

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    with Project.open(project) as p:
        before = p.traces3d()
    a, b = [t.id for t in before if len(t.points) >= 3][:2]
    assert main(["merge", project, "--pair", str(a), str(b)]) == 0
    with Project.open(project) as p:
        after = p.traces3d()
    assert len(after) == len(before) - 1 and {a, b}.isdisjoint({t.id for t in after})
    capsys.readouterr()
    with Project.open(project) as p:
        listed = p.traces3d()
    assert main(["merge", project, "--list"]) == 0  # lists, merges nothing
    out = capsys.readouterr().out
    with Project.open(project) as p:
        assert [t.id for t in p.traces3d()] == [t.id for t in listed]
    assert "reason" in out.splitlines()[0] and "suggestions the rules are sure of" in out.splitlines()[-1]
    assert main(["merge", project, "--list", "--auto"]) == 2
    assert "--list only lists" in capsys.readouterr().err
    assert main(["merge", project, "--auto"]) == 0
    out = capsys.readouterr().out
    with Project.open(project) as p:  # what is left apart that might be one trace is counted for the user
        mesh = p.load_mesh()
        sight = Sight(mesh, p.cameras(), RayTracer(mesh.vertices, mesh.faces))
        review = suggest_merges(p.traces3d(), tolerance=0.03, sight=sight, review=True)
    assert not [s for s in review if s.kind != "candidate"]  # nothing sure is left
    assert (f"{len(review)} pairs of pieces may continue" in out) == bool(review)
    assert main(["merge", project, "--auto"]) == 0  # a second run has nothing left to merge
    assert "merged 0 3D traces into 0" in capsys.readouterr().out
    assert main(["merge", project, "--pair", "99999", str(a)]) == 2
    assert "no 3D trace with id 99999" in capsys.readouterr().err
    with Project.open(project) as p:  # without the mesh, duplicates still merge; hidden gaps are not bridged
        mesh = p.mesh_path
    mesh.rename(mesh.with_suffix(".moved"))
    c, d = [t.id for t in after if len(t.points) >= 3][:2]
    assert main(["merge", project, "--pair", str(c), str(d)]) == 0
    out = capsys.readouterr().out
    assert "warning:" in out and "moved or deleted" in out and "not bridged" in out
    mesh.with_suffix(".moved").rename(mesh)
    assert main(["export", project, str(tmp_path / "out"), "--format", "csv,ply,gpkg,vtp"]) == 0
    names = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"traces.csv", "connectivity.ply", "intensity.ply", "traces.gpkg", "traces.vtp", "sets.csv"} <= names
    assert main(["export", project, str(tmp_path / "out3"), "--format", "xyz"]) == 2
    assert "unknown format(s) xyz" in capsys.readouterr().err


def test_merge_relabels_components_and_marks_earlier_results_out_of_date(quick_demo, tmp_path, capsys):
    import shutil

    from engine.merge import relabel_components

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    assert main(["orient", project]) == 0
    assert main(["analyse", project, "--radius", "0.5", "--bootstrap", "9"]) == 0
    assert main(["export", project, str(tmp_path / "before")]) == 0
    assert json.loads((tmp_path / "before" / "summary.json").read_text())["out_of_date"] == []
    assert "warning" not in capsys.readouterr().out
    with Project.open(project) as p:
        before = p.traces3d()
    # two traces of different connected groups: their merge joins the groups
    a = next(t for t in before if len(t.points) >= 3)
    b = next(t for t in before if len(t.points) >= 3 and t.component != a.component)
    assert main(["merge", project, "--pair", str(a.id), str(b.id)]) == 0
    with Project.open(project) as p:
        after = p.traces3d()
    expected = relabel_components(after, 0.03)  # the default tolerance of `merge`
    assert [t.component for t in after] == [t.component for t in expected] and min(t.component for t in after) == 0
    capsys.readouterr()
    assert main(["export", project, str(tmp_path / "after")]) == 0
    assert set(json.loads((tmp_path / "after" / "summary.json").read_text())["out_of_date"]) == {
        "sets", "nodes", "kaplan_meier", "intensity"}
    assert ("warning: summary.json's sets, nodes, kaplan_meier, intensity (listed under out_of_date) were computed "
            "before the 3D traces last changed" in capsys.readouterr().out)
    assert main(["plot", project, "-o", str(tmp_path / "plots")]) == 0
    assert "warning: the plotted sets, density_peaks, topology, lengths, intensity were computed before the 3D " \
           "traces last changed; run `tracemap orient` again" in capsys.readouterr().out
    assert main(["orient", project]) == 0
    assert main(["analyse", project, "--radius", "0.5", "--bootstrap", "9"]) == 0
    assert main(["export", project, str(tmp_path / "again")]) == 0
    assert json.loads((tmp_path / "again" / "summary.json").read_text())["out_of_date"] == []


def test_orient_sets_asked_for_are_kept_or_refused_and_sets_csv_counts_the_member_traces(quick_demo, tmp_path,
                                                                                         capsys):
    import shutil

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = str(tmp_path / "demo" / "demo.tracemap")
    with Project.open(project) as p:
        n_traces, sets_before = len(p.traces3d()), p.result("sets")
    assert main(["orient", project, "--sets", str(n_traces + 1)]) == 2
    assert f"but there are only {n_traces} traces" in capsys.readouterr().err
    assert main(["orient", project, "--sets", "20"]) == 2  # more sets than the poles gather
    assert "ask for fewer sets, or let the number be chosen" in capsys.readouterr().err
    with Project.open(project) as p:
        assert p.result("sets") == sets_before  # a refused command changes nothing
    assert main(["orient", project, "--sets", "2"]) == 0
    assert main(["export", project, str(tmp_path / "out")]) == 0
    with open(tmp_path / "out" / "sets.csv", newline="") as f:
        n = {int(r["set"]): int(r["n"]) for r in csv.DictReader(f)}
    with open(tmp_path / "out" / "traces.csv", newline="") as f:
        members = [int(r["set"]) for r in csv.DictReader(f)]
    assert len(n) == 2 and n == {k: members.count(k) for k in n}


def test_new_refuses_cameras_in_another_frame_than_the_mesh(survey, capsys):
    """A georeferenced Metashape chunk gives geocentric camera positions beside a UTM mesh: none sees it."""
    d, cams = survey
    far = [facing_camera(c.name, centre=(3.0, -8.0, 3.0), offset=OFFSET + [0.0, 0.0, 4.0e6]) for c in cams.values()]
    (d / "far.json").write_text(json.dumps(
        {"format": "tracemap-cameras", "version": 1, "cameras": [c.to_dict() for c in far]}))
    code = main(["new", str(d / "p.tracemap"), "--mesh", str(d / "wall.obj"), "--cameras", str(d / "far.json")])
    err = capsys.readouterr().err
    assert code == 2 and "far.json" in err and "none of the 2 cameras sees the mesh" in err
    assert "3,999,99" in err  # the gap, in metres (4,000 km less the camera height above the wall top)
    assert not (d / "p.tracemap").exists()


def test_new_takes_a_bundler_image_list_and_size_when_the_photos_are_not_at_hand(survey, capsys):
    """Bundler v0.3 of the survey's left camera twice (f, k1, k2; R and t with y up and z backwards)."""
    d, _ = survey
    flip = np.diag([1.0, -1.0, -1.0])
    lines = ["# Bundle file v0.3", "2 0"]
    for name, x in (("a", 3.0), ("b", 7.0)):
        c = facing_camera(name, centre=(x, -8.0, 3.0), offset=OFFSET)
        lines += [f"{c.K[0, 0]} 0 0", *(" ".join(map(str, row)) for row in flip @ c.R), " ".join(map(str, flip @ c.t))]
    (d / "bundle.out").write_text("\n".join(lines) + "\n")
    (d / "photos.txt").write_text("a.jpg\nb.jpg\n")
    args = ["new", str(d / "p.tracemap"), "--mesh", str(d / "wall.obj"), "--cameras", str(d / "bundle.out")]
    assert main(args) == 2
    assert "--image-size W H" in capsys.readouterr().err  # no list.txt beside it, no photos: said how to give them
    assert main([*args, "--image-list", str(d / "photos.txt"), "--image-size", "800", "600"]) == 0
    with Project.open(d / "p.tracemap") as p:
        made = p.cameras(local=False)
    assert sorted(made) == ["a.jpg", "b.jpg"] and all((c.width, c.height) == (800, 600) for c in made.values())
    np.testing.assert_allclose(made["b.jpg"].centre, OFFSET + [7.0, -8.0, 3.0], atol=1e-6)
