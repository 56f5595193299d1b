"""Facets: Compass-style plane fits on a mesh patch, their storage in the project (schema v2, migrated from
v1), `tracemap facet`, their export in Compass's plane columns, and their use as set seeds by `tracemap orient`."""

import csv
import json
import shutil
import sqlite3

import numpy as np
import pytest
import trimesh

from engine.cli import main
from engine.errors import InputError
from engine.exports import write_planes_csv
from engine.mesh import Mesh
from engine.orientation import axial_angle
from engine.project import SCHEMA_VERSION, Project
from engine.register import Similarity
from engine.sets import Facet, fit_mesh_facet, mesh_patch
from tests.scenes import facing_camera, stepped_wall
from tests.test_project import as_version

OFFSET = np.array([500_000.0, 4_200_000.0, 100.0])
ON_STEP = np.array([4.0, -0.3, 1.5])  # the middle of the exposed face x = 4
ON_WALL = np.array([2.0, 0.0, 1.5])


@pytest.fixture
def step_project(tmp_path):
    v, f = stepped_wall(offset=OFFSET)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "step.obj")
    with Project.create(tmp_path / "step.tracemap", mesh_path=tmp_path / "step.obj",
                        cameras={"cam": facing_camera(centre=(3.0, -8.0, 1.5), offset=OFFSET)}) as p:
        pass
    return p.path


def test_patch_on_the_exposed_face_is_accepted():
    mesh = Mesh(*stepped_wall())
    faces = mesh_patch(mesh, ON_STEP, 0.25)
    centroids = mesh.face_centroids[faces]
    assert np.all(np.linalg.norm(centroids - ON_STEP, axis=1) <= 0.25)
    assert np.allclose(centroids[:, 0], 4.0) and len(faces) > 20  # only the step, no wall face
    facet = fit_mesh_facet(mesh, faces)
    assert facet.accepted and facet.rejected_reason == ""
    assert axial_angle(facet.normal, [1.0, 0.0, 0.0]) < 1e-6
    assert facet.dip_dipdir[0] == pytest.approx(90.0)
    assert facet.planarity == pytest.approx(1.0) and facet.rms < 1e-9
    np.testing.assert_array_equal(facet.faces, faces)
    assert 0.25 <= facet.radius <= 0.25 + 0.1 * np.sqrt(2)  # face vertices reach past the centroid sphere


def test_patch_on_the_outcrop_face_is_rejected_and_a_miss_says_how_far():
    mesh = Mesh(*stepped_wall())
    facet = fit_mesh_facet(mesh, mesh_patch(mesh, ON_WALL, 0.4))
    assert not facet.accepted and "outcrop face" in facet.rejected_reason
    with pytest.raises(InputError, match=r"no mesh face within 0.2 m of the point; the nearest face centre is "
                                         r"4\.\d+ m away"):
        mesh_patch(mesh, ON_WALL + [0, -5.0, 0], 0.2)
    with pytest.raises(InputError, match="radius > 0"):
        mesh_patch(mesh, ON_WALL, 0.0)


def test_facets_round_trip_and_restore_keeps_the_id(step_project):
    with Project.open(step_project) as p:
        mesh = p.load_mesh()
        facet = fit_mesh_facet(mesh, mesh_patch(mesh, ON_STEP + OFFSET - p.origin, 0.25))
        first = p.add_facet(facet)
        second = p.add_facet(facet)
        stored = p.facets()
        assert [f.id for f in stored] == [first, second]
        back = stored[0]
        np.testing.assert_array_equal(back.normal, facet.normal)
        np.testing.assert_array_equal(back.centroid, facet.centroid)
        np.testing.assert_array_equal(back.faces, facet.faces)
        assert (back.planarity, back.rms, back.n_points, back.radius, back.accepted) == (
            facet.planarity, facet.rms, facet.n_points, facet.radius, True)
        p.remove_facet(first)
        assert [f.id for f in p.facets()] == [second]
        p.restore_facet(back)
        assert [f.id for f in p.facets()] == [first, second]


def test_a_version_1_project_opens_and_gains_the_facets_table(step_project):
    as_version(step_project, 1)
    with Project.open(step_project) as p:
        assert p.facets() == []
        mesh = p.load_mesh()
        p.add_facet(fit_mesh_facet(mesh, mesh_patch(mesh, ON_STEP + OFFSET - p.origin, 0.25)))
        assert len(p.facets()) == 1
    db = sqlite3.connect(step_project)
    assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    db.close()
    backup = step_project.with_name("step.v1.bak.tracemap")
    db = sqlite3.connect(backup)  # the untouched original
    assert db.execute("PRAGMA user_version").fetchone()[0] == 1
    assert "facets" not in {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    db.close()


def test_facet_command_stores_accepted_and_refuses_the_outcrop_face(step_project, capsys):
    point = [str(x) for x in ON_STEP + OFFSET]
    assert main(["facet", str(step_project), "--point", *point, "--radius", "0.25"]) == 0
    out = capsys.readouterr().out
    assert "facet 1: dip 90.0°" in out and "planarity 1.000" in out
    with Project.open(step_project) as p:
        (facet,) = p.facets()
        assert axial_angle(facet.normal, [1.0, 0.0, 0.0]) < 1e-6
        np.testing.assert_allclose(facet.centroid + p.origin, ON_STEP + OFFSET, atol=0.05)
    wall = [str(x) for x in ON_WALL + OFFSET]
    assert main(["facet", str(step_project), "--point", *wall, "--radius", "0.4"]) == 2
    err = capsys.readouterr().err
    assert "was not stored" in err and "outcrop face" in err and "step.tracemap" in err
    with pytest.raises(SystemExit) as exit_:  # refused by the option's own check, before the project opens
        main(["facet", str(step_project), "--point", *point, "--radius", "-1"])
    assert exit_.value.code == 2 and "argument --radius: expected a number > 0, got '-1'" in capsys.readouterr().err
    with Project.open(step_project) as p:
        assert len(p.facets()) == 1


def test_export_writes_the_facets_in_compass_plane_columns(step_project, tmp_path):
    assert main(["export", str(step_project), str(tmp_path / "none")]) == 0
    assert not (tmp_path / "none" / "planes.csv").exists()  # no facets, no planes file
    early = json.loads((tmp_path / "none" / "summary.json").read_text())  # nothing analysed: null, not absent
    assert early["sets"] is early["nodes"] is early["kaplan_meier"] is early["intensity"] is None
    point = [str(x) for x in ON_STEP + OFFSET]
    assert main(["facet", str(step_project), "--point", *point, "--radius", "0.25"]) == 0
    assert main(["export", str(step_project), str(tmp_path / "out")]) == 0
    with open(tmp_path / "out" / "planes.csv", newline="") as f:
        header, *rows = list(csv.reader(f))
    assert header == ["Name", "Strike", "Dip", "Dip_Dir", "Cx", "Cy", "Cz", "Nx", "Ny", "Nz", "Sample_Radius", "RMS"]
    (row,) = rows
    values = dict(zip(header, row))
    assert values["Name"] == "facet1"
    # the step's face looks east (+x): a vertical plane dipping 90° towards 090, striking 000
    assert [float(values[k]) for k in ("Strike", "Dip", "Dip_Dir")] == pytest.approx([0.0, 90.0, 90.0], abs=1e-6)
    np.testing.assert_allclose([float(values[k]) for k in ("Nx", "Ny", "Nz")], [1.0, 0.0, 0.0], atol=1e-6)
    # world coordinates: the UTM-sized offset is back, to the 0.1 mm the file keeps
    np.testing.assert_allclose([float(values[k]) for k in ("Cx", "Cy", "Cz")], ON_STEP + OFFSET, atol=0.05)
    with Project.open(step_project) as p:
        (facet,) = p.facets()
        np.testing.assert_allclose([float(values[k]) for k in ("Cx", "Cy", "Cz")], facet.centroid + p.origin,
                                   atol=1e-4)
        assert float(values["Sample_Radius"]) == pytest.approx(facet.radius, abs=1e-4)
    assert float(values["RMS"]) == pytest.approx(0.0, abs=1e-5)


def test_planes_csv_turns_and_scales_with_the_registration(tmp_path):
    facet = Facet(normal=np.array([0.0, -0.6, 0.8]), centroid=np.array([1.0, 2.0, 3.0]), planarity=0.9, rms=0.01,
                  n_points=50, radius=0.5, id=7)  # dips 36.87° towards 180
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° anticlockwise about z
    sim = Similarity(2.0, quarter, np.array([10.0, 0.0, 0.0]), np.zeros((0, 3)), np.zeros(0), 0.0)
    path = write_planes_csv(tmp_path / "planes.csv", [facet], np.array([100.0, 0.0, 0.0]), similarity=sim)
    with open(path, newline="") as f:
        header, row = list(csv.reader(f))
    values = dict(zip(header, row))
    # the normal (0, −0.6, 0.8) turns to (0.6, 0, 0.8): the dip direction goes from 180 to 090
    assert [float(values[k]) for k in ("Strike", "Dip", "Dip_Dir")] == pytest.approx([0.0, 36.87, 90.0], abs=0.01)
    np.testing.assert_allclose([float(values[k]) for k in ("Cx", "Cy", "Cz")], [6.0, 202.0, 6.0], atol=1e-4)
    assert (float(values["Sample_Radius"]), float(values["RMS"])) == pytest.approx((1.0, 0.02))
    assert values["Name"] == "facet7"


def test_orient_seeds_the_sets_with_the_stored_facets(quick_demo, tmp_path, monkeypatch):
    import engine.sets

    shutil.copytree(quick_demo, tmp_path / "demo")
    project = tmp_path / "demo" / "demo.tracemap"
    with Project.open(project) as p:
        mesh = p.load_mesh()
        centre = mesh.vertices[np.argmin(np.linalg.norm(mesh.vertices - mesh.vertices.mean(axis=0), axis=1))]
        facet = fit_mesh_facet(mesh, mesh_patch(mesh, centre, 0.5), min_planarity=0.0, max_outcrop_angle=0.0,
                               max_relative_rms=np.inf)
        p.add_facet(facet)
    seen = {}
    original = engine.sets.fit_sets

    def spy(poles, **options):
        seen["seeds"] = options["seed_poles"]
        return original(poles, **options)

    monkeypatch.setattr(engine.sets, "fit_sets", spy)
    monkeypatch.setattr("engine.analysis.orient_traces", lambda traces, *a, **k: None)  # keep stored poles
    assert main(["orient", str(project)]) == 0
    assert np.any(np.all(np.isclose(seen["seeds"], facet.normal), axis=1))
