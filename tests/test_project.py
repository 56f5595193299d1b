import io
import re
import sqlite3
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
import trimesh

from engine.errors import ProjectError
from engine.project import MIGRATIONS, SCHEMA_VERSION, Project, file_digest
from engine.traces import Trace2D, Trace3D
from tests.scenes import facing_camera, grid_wall

OFFSET = np.array([500_000.0, 4_200_000.0, 100.0])


@pytest.fixture
def scene(tmp_path):
    v, f = grid_wall(offset=OFFSET)
    mesh_path = tmp_path / "wall.obj"
    trimesh.Trimesh(v, f, process=False).export(mesh_path)
    photo = tmp_path / "cam.png"
    photo.write_bytes(b"not really a png, only hashed")
    return mesh_path, {"cam": facing_camera(offset=OFFSET)}, {"cam": photo}


@pytest.fixture
def project(tmp_path, scene):
    mesh_path, cameras, images = scene
    with Project.create(tmp_path / "p.tracemap", mesh_path=mesh_path, cameras=cameras, images=images) as p:
        yield p


def test_create_open_and_frames(tmp_path, project, scene):
    np.testing.assert_allclose(project.origin, OFFSET + [5.0, 0.0, 3.0])
    world = project.cameras(local=False)["cam"]
    local = project.cameras()["cam"]
    np.testing.assert_allclose(local.centre + project.origin, world.centre, atol=1e-9)
    mesh = project.load_mesh()
    assert np.abs(mesh.vertices).max() < 10
    assert project.image_path("cam") == scene[2]["cam"].resolve()
    with pytest.raises(ProjectError, match="exists"):
        Project.create(project.path, mesh_path=scene[0], cameras=scene[1])
    missing = tmp_path / "nowhere" / "p.tracemap"
    with pytest.raises(ProjectError, match=r"the folder .*nowhere does not exist; create it first"):
        Project.create(missing, mesh_path=scene[0], cameras=scene[1])
    assert not missing.parent.exists()


def test_traces_round_trip(project):
    ids = project.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]], "auto"),
                                Trace2D(0, "cam", [[5.0, 5.0], [6.0, 7.0], [8.0, 9.0]])])
    assert ids == [1, 2]
    t2 = project.traces2d()
    assert [t.source for t in t2] == ["auto", "manual"]
    np.testing.assert_array_equal(t2[1].polyline, [[5, 5], [6, 7], [8, 9]])
    pts = np.random.default_rng(0).normal(size=(5, 3))
    t3 = Trace3D(0, pts, np.zeros((5, 2)), np.arange(5), np.zeros(5), ("cam",), parents=(2,),
                 normal=np.array([0.0, 0.0, 1.0]), method="eigen", K=0.5, term_end="C", extra={"note": 1})
    (tid,) = project.add_traces3d([t3])
    back = project.traces3d()[0]
    assert back.id == tid and back.parents == (2,) and back.term_end == "C" and back.censored
    np.testing.assert_array_equal(back.points, pts)
    assert back.K == 0.5 and np.isnan(back.M) and back.extra == {"note": 1}
    back.M = np.inf  # exactly planar: M = ln(λ1/λ3) is infinite, and must stay so
    project.update_traces3d([back])
    assert project.traces3d()[0].M == np.inf


def test_failed_edit_changes_nothing(project):
    project.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]])])
    with pytest.raises(RuntimeError):
        with project.transaction() as db:
            project.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]])], db)
            raise RuntimeError("killed half-way")
    assert len(project.traces2d()) == 1


def test_second_process_is_refused(project):
    code = textwrap.dedent(f"""
        from engine.project import Project
        from engine.errors import ProjectError
        try:
            Project.open({str(project.path)!r})
        except ProjectError as e:
            print(e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "open in process" in out


def test_changed_or_moved_inputs_are_reported(project, scene):
    mesh_path, _, images = scene
    project.close()
    images["cam"].write_bytes(b"another photo with other bytes")
    with Project.open(project.path) as p:
        with pytest.raises(ProjectError, match="changed since it was added"):
            p.image_path("cam")
        mesh_path.rename(mesh_path.with_suffix(".moved"))
        with pytest.raises(ProjectError, match="moved or deleted"):
            p.load_mesh()


def test_touched_but_identical_file_is_accepted(project, scene):
    import os

    mesh_path = scene[0]
    os.utime(mesh_path, (1, 1))
    assert project.mesh_path == mesh_path.resolve()


def test_a_touched_input_is_hashed_once_per_session_not_at_every_use(project, scene, monkeypatch):
    """A copied project's mesh has a new modification time: the editor asks for it at every auto-trace
    preview, and a multi-gigabyte mesh must not be read each time."""
    import os

    import engine.project as module

    hashed = []
    monkeypatch.setattr(module, "file_digest", lambda path: hashed.append(path) or original(path))
    original = file_digest
    os.utime(scene[0], (1, 1))
    for _ in range(3):
        assert project.mesh_path == scene[0].resolve()
    assert len(hashed) == 1
    scene[0].write_bytes(scene[0].read_bytes()[:-1] + b"x")  # the same size, changed content, new time
    with pytest.raises(ProjectError, match="changed since it was added"):
        project.mesh_path


def test_newer_schema_is_refused_and_junk_is_not_a_project(tmp_path, project):
    project.close()
    db = sqlite3.connect(project.path)
    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    db.close()
    with pytest.raises(ProjectError, match="newer tracemap"):
        Project.open(project.path)
    junk = tmp_path / "junk.tracemap"
    junk.write_bytes(b"hello" * 100)
    with pytest.raises(ProjectError, match="not a tracemap project"):
        Project.open(junk)


def as_version(path, version: int) -> None:
    """Make the project file what schema `version` wrote: the tables and columns the later versions' upgrades
    add dropped (`engine.project.MIGRATIONS`), the version set back."""
    db = sqlite3.connect(path)
    for v in range(version, SCHEMA_VERSION):
        for table in re.findall(r"CREATE TABLE (\w+)", MIGRATIONS[v]):
            db.execute(f"DROP TABLE {table}")
        for table, column in re.findall(r"ALTER TABLE (\w+) ADD COLUMN (\w+)", MIGRATIONS[v]):
            db.execute(f"ALTER TABLE {table} DROP COLUMN {column}")
    db.execute(f"PRAGMA user_version = {version}")
    db.commit()
    db.close()


def test_an_older_schema_is_upgraded_by_the_first_edit_after_a_backup(project):
    project.close()
    as_version(project.path, 1)
    backup = project.path.with_name("p.v1.bak.tracemap")
    with Project.open(project.path) as p:
        assert p.facets() == [] and not backup.exists()  # read as it is
        with pytest.raises(RuntimeError), p.transaction() as db:  # a failed edit: no upgrade, no backup
            db.execute("INSERT INTO meta VALUES ('x', 'y')")
            raise RuntimeError("the command failed")
        assert not backup.exists()
    assert sqlite3.connect(project.path).execute("PRAGMA user_version").fetchone()[0] == 1
    with Project.open(project.path) as p:
        p.set_setting("k", 1)
        assert p.setting("k") == 1 and p.facets() == []
    assert sqlite3.connect(project.path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert sqlite3.connect(backup).execute("PRAGMA user_version").fetchone()[0] == 1


def test_an_older_schema_upgraded_by_another_handle_is_read_by_all_and_keeps_its_backup(project):
    from engine.sets import Facet

    project.close()
    as_version(project.path, 1)
    backup = project.path.with_name("p.v1.bak.tracemap")
    with Project.open(project.path) as p:
        worker = p.for_thread()
        with pytest.raises(RuntimeError), worker.transaction():  # one handle's failed edit
            raise RuntimeError("the command failed")
        assert not backup.exists()
        worker.add_facet(Facet(np.array([0.0, 0.0, 1.0]), np.zeros(3), 1.0, 0.0, 10))  # the other upgrades
        worker.close()
        assert len(p.facets()) == 1  # seen by the first handle too
    assert sqlite3.connect(backup).execute("PRAGMA user_version").fetchone()[0] == 1
    assert not list(project.path.parent.glob("*.writing"))


def test_a_backup_cut_short_is_not_taken_for_the_original(project, monkeypatch):
    project.close()
    as_version(project.path, 1)
    backup = project.path.with_name("p.v1.bak.tracemap")

    def full(src, dst):
        raise OSError(28, "No space left on device", str(dst))

    with Project.open(project.path) as p:
        monkeypatch.setattr("engine.project.os.replace", full)
        with pytest.raises(OSError):
            p.set_setting("k", 1)
        monkeypatch.undo()
        assert not backup.exists() and not list(project.path.parent.glob("*.writing"))
        p.set_setting("k", 1)
    assert sqlite3.connect(backup).execute("PRAGMA user_version").fetchone()[0] == 1


@pytest.mark.parametrize("damage, message", [
    ("UPDATE images SET camera = '{'", "its cameras cannot be read (JSONDecodeError"),
    ("UPDATE images SET camera = '{}'", "its cameras cannot be read (KeyError: 'name')"),
    ("DROP TABLE traces3d", "table 'traces3d' missing"),
    ("ALTER TABLE traces2d DROP COLUMN component", "column(s) component of table 'traces2d' missing"),
    ("PRAGMA user_version = 0", "schema version 0, expected 1 to"),
    ("UPDATE meta SET value = '[1, 2]' WHERE key = 'origin'", "its origin is '[1, 2]', expected three numbers"),
    ("INSERT INTO results VALUES ('sets', '{')", "its result 'sets' cannot be read"),
    ("INSERT INTO traces2d (image, polyline, source) VALUES ('cam', x'93', 'manual')", "its traces2d cannot be read"),
    ("INSERT INTO traces2d (image, polyline, source) VALUES ('cam', x'', 'manual')", "its traces2d cannot be read"),
])
def test_a_damaged_project_file_is_reported_as_damaged(project, damage, message):
    project.close()
    db = sqlite3.connect(project.path)
    db.execute(damage)
    db.commit()
    db.close()
    with pytest.raises(ProjectError, match="the project file is damaged") as error, Project.open(project.path) as p:
        p.cameras(), p.traces2d(), p.result("sets")
    assert message in str(error.value) and str(project.path) in str(error.value)


def test_opening_what_is_no_project_leaves_no_lock_file(tmp_path):
    for name, content in (("junk.tracemap", b"hello" * 100), ("empty.tracemap", b"")):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ProjectError, match="not a tracemap project"):
            Project.open(tmp_path / name)
    other = sqlite3.connect(tmp_path / "other.tracemap")  # SQLite, but not ours
    other.execute("CREATE TABLE t (x)")
    other.commit()
    other.close()
    with pytest.raises(ProjectError, match="no meta table"):
        Project.open(tmp_path / "other.tracemap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.tracemap", "junk.tracemap", "other.tracemap"]


def test_edit_remove_restore_keep_ids(project):
    a, b = project.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]]),
                                 Trace2D(0, "cam", [[5.0, 5.0], [6.0, 7.0]])])
    edited = project.traces2d()[0]
    edited.polyline = np.array([[0.0, 0.0], [9.0, 9.0], [10.0, 3.0]])
    edited.component = 4
    project.update_traces2d([edited])
    removed = [t for t in project.traces2d() if t.id == b]
    project.remove_traces2d([b])
    assert [t.id for t in project.traces2d()] == [a]
    project.restore_traces2d(removed)
    back = project.traces2d()
    assert [t.id for t in back] == [a, b] and back[0].component == 4 and len(back[0].polyline) == 3
    t3 = Trace3D(0, np.eye(3), np.zeros((3, 2)), [0, 1, 2], [0, 0, 0], ("cam",), parents=(a,))
    (i,) = project.add_traces3d([t3])
    t3 = project.traces3d()[0]
    t3.term_start, t3.set_id = "T", 2
    project.update_traces3d([t3])
    project.remove_traces3d([i])
    assert project.traces3d() == []
    project.restore_traces3d([t3])
    again = project.traces3d()[0]
    assert again.id == i and again.term_start == "T" and again.set_id == 2


def test_settings_persist(project, tmp_path):
    project.set_setting("view/camera", {"zoom": 2.5, "centre": [1, 2]})
    project.close()
    with Project.open(project.path) as p:
        assert p.setting("view/camera") == {"zoom": 2.5, "centre": [1, 2]}
        assert p.setting("missing", 7) == 7


def test_vertex_maps(project):
    values = np.linspace(0, 1, 10)
    project.set_vertex_maps({"p21": values, "p21:set0": values * 2}, {"radius": 0.25})
    got, info = project.vertex_map("p21:set0")
    np.testing.assert_array_equal(got, values * 2)
    assert info == {"radius": 0.25} and project.map_names() == ["p21", "p21:set0"]
    assert project.map_info("p21") == {"radius": 0.25}
    for read in (project.vertex_map, project.map_info):
        with pytest.raises(ProjectError, match="no map named 'p32'.*available: p21, p21:set0"):
            read("p32")


def test_results_and_gcps(project):
    project.set_result("sets", [{"id": 0, "normal": np.array([0.0, 0.0, 1.0]), "kappa": np.float64(12.5)}])
    assert project.result("sets") == [{"id": 0, "normal": [0.0, 0.0, 1.0], "kappa": 12.5}]
    assert project.result("missing") is None
    project.set_gcp("A", [500001.0, 4200002.0, 103.0], {"cam": [100.5, 200.25]})
    assert project.gcps() == {"A": {"world": [500001.0, 4200002.0, 103.0], "observations": {"cam": [100.5, 200.25]}}}
    project.remove_gcp("A")
    assert project.gcps() == {}


def npy(array) -> bytes:
    """What `np.save` writes: the blobs of every project made so far."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


@pytest.mark.parametrize("array", [np.random.default_rng(0).normal(size=(40, 3)), np.arange(7), np.zeros((0, 3)),
                                   np.ones((2, 2), bool), np.arange(6, dtype=">i4"), np.array(["ab", "c"]),
                                   np.arange(6.0).reshape(2, 3).T, np.zeros(2, [("x", "f8"), ("n", "i4")])])
def test_blobs_stay_npy_both_ways(array):
    """Blobs are read by their header (fast path) or np.load (anything else), and written as np.save does."""
    from engine.project import from_blob, to_blob

    for blob in (npy(array), to_blob(array)):
        back = from_blob(blob)
        assert back.dtype == array.dtype and back.shape == array.shape and np.array_equal(back, array)
        assert back.flags.writeable  # callers may edit what they read
        np.testing.assert_array_equal(np.load(io.BytesIO(blob)), array)
    if array.flags.c_contiguous and array.dtype.fields is None:
        assert to_blob(array) == npy(array)


def test_a_damaged_blob_is_refused_with_its_sizes():
    from engine.project import from_blob

    blob = npy(np.zeros((10, 3)))
    with pytest.raises(ProjectError, match=r"damaged: 200 bytes, expected 368 for shape \(10, 3\)"):
        from_blob(blob[:200])


def test_traces2d_of_chosen_photos_and_the_counts(project):
    project.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]]), Trace2D(0, "cam", [[5.0, 5.0], [6.0, 7.0]])])
    assert [t.id for t in project.traces2d(["cam"])] == [t.id for t in project.traces2d()] == [1, 2]
    assert project.traces2d([]) == [] and project.traces2d(["no such photo"]) == []
    assert project.traces2d_counts() == {"cam": 2}


def test_adding_or_replacing_2d_traces_relabels_the_components_of_their_photo(project):
    left, right = [[10.0, 10.0], [100.0, 10.0]], [[300.0, 10.0], [400.0, 10.0]]
    project.add_traces2d([Trace2D(0, "cam", left), Trace2D(0, "cam", right)])
    assert [t.component for t in project.traces2d()] == [0, 1]
    project.add_traces2d([Trace2D(0, "cam", [[100.0, 10.0], [300.0, 10.0]], "auto")])  # joins them
    assert [t.component for t in project.traces2d()] == [0, 0, 0]
    with project.transaction() as db:  # as `tracemap autotrace` replaces a photo's auto traces
        assert project.delete_traces2d("cam", "auto", db) == [3]
    assert [t.component for t in project.traces2d()] == [0, 1]
    project.add_traces2d([Trace2D(0, "cam", [[5.0, 50.0], [9.0, 50.0]], component=7)], relabel=False)  # the editor
    assert [t.component for t in project.traces2d()] == [0, 1, 7]


def test_a_worker_thread_writes_through_its_own_handle(project):
    """`for_thread` gives a worker its own connection under the project's lock: what it commits is read by
    the project's connection at once, and closing it leaves the project open and locked."""

    def work():
        handle = project.for_thread()
        try:
            done.append(handle.add_traces2d([Trace2D(0, "cam", [[1.0, 2.0], [3.0, 4.5]])]))
        finally:
            handle.close()

    done = []
    worker = threading.Thread(target=work)
    worker.start()
    worker.join()
    assert done == [[1]] and [t.id for t in project.traces2d()] == [1]
    project.set_setting("still", "open")
    with pytest.raises(ProjectError, match="open in process"):
        Project.open(project.path)
