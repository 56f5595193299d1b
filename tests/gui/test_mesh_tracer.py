"""The session's shared ray tracer and silhouettes: one per mesh for every tool, kept while the mesh is
unchanged, and bounded."""

import dataclasses
import os

import numpy as np

from engine.delineate import silhouette
from engine.mesh import read_mesh
from tracemap_gui.mesh_tracer import KEEP_SILHOUETTES, MeshTracer


def test_one_ray_tracer_serves_the_mesh_file_and_the_mesh_read_from_it(project_path):
    from engine.project import Project

    with Project.open(project_path) as project:
        mesh_path, origin = project.mesh_path, project.origin
    shared = MeshTracer()
    tracer = shared.tracer(mesh_path, origin)
    assert shared.tracer(mesh_path, origin) is tracer
    mesh = read_mesh(mesh_path, origin=origin)  # as the 3D viewer loads it
    assert shared.of(mesh) is tracer
    unsaved = dataclasses.replace(mesh, source=None)  # a mesh with no file is known by identity
    other = shared.of(unsaved)
    assert other is not tracer and shared.of(unsaved) is other
    assert shared.tracer(mesh_path, origin) is not other  # one held at a time: the file's again
    stat = mesh_path.stat()
    held = shared.tracer(mesh_path, origin)
    os.utime(mesh_path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # the mesh file changed
    assert shared.tracer(mesh_path, origin) is not held
    shared.clear()
    assert shared._tracer is None


def test_silhouettes_are_kept_while_the_mesh_is_unchanged_and_bounded(project_path):
    from engine.project import Project

    with Project.open(project_path) as project:
        mesh_path, origin, cameras = project.mesh_path, project.origin, project.cameras()
    shared = MeshTracer()
    camera = cameras["photo_01"]
    first = shared.silhouette(camera, 0.03, mesh_path, origin)
    assert np.array_equal(first, silhouette(camera, shared.tracer(mesh_path, origin)))
    assert shared.silhouette(camera, 0.03, mesh_path, origin) is first
    assert shared.silhouette(camera, 0.1, mesh_path, origin) is not first  # another step, another silhouette
    for k in range(KEEP_SILHOUETTES):  # the same photo seen from slightly elsewhere: other cameras
        moved = dataclasses.replace(camera, t=camera.t + [0.01 * (k + 1), 0, 0])
        shared.silhouette(moved, 0.03, mesh_path, origin)
    assert len(shared._silhouettes) == KEEP_SILHOUETTES
    assert shared.silhouette(camera, 0.03, mesh_path, origin) is not first  # dropped as the least recently used


def test_the_session_lets_the_ray_tracer_go_when_the_project_closes(session):
    tracer = session.mesh_tracer.tracer(session.project.mesh_path, session.project.origin)
    assert tracer is not None
    session.close()
    assert session.mesh_tracer._tracer is None


def test_a_silhouette_asked_for_twice_at_once_is_cast_once(project_path, monkeypatch):
    import threading
    import time

    import tracemap_gui.mesh_tracer as module
    from engine.project import Project

    with Project.open(project_path) as project:
        mesh_path, origin, camera = project.mesh_path, project.origin, project.cameras()["photo_01"]
    shared = MeshTracer()
    shared.tracer(mesh_path, origin)
    calls = []

    def slow(*args, **kwargs):
        calls.append(1)
        time.sleep(0.3)
        return silhouette(*args, **kwargs)

    monkeypatch.setattr(module, "silhouette", slow)
    found = []
    threads = [threading.Thread(target=lambda: found.append(shared.silhouette(camera, 0.03, mesh_path, origin)))
               for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(found) == 3 and all(f is found[0] for f in found)


def test_clearing_does_not_wait_for_a_ray_tracer_being_built_and_drops_it(project_path, monkeypatch):
    import threading
    import time

    import tracemap_gui.mesh_tracer as module
    from engine.project import Project

    with Project.open(project_path) as project:
        mesh_path, origin = project.mesh_path, project.origin
    built = threading.Event()

    class SlowTracer:
        def __init__(self, vertices, faces):
            time.sleep(1.0)
            built.set()

    monkeypatch.setattr(module, "RayTracer", SlowTracer)
    shared = MeshTracer()
    worker = threading.Thread(target=lambda: shared.tracer(mesh_path, origin))
    worker.start()
    time.sleep(0.2)  # the worker is building
    t0 = time.perf_counter()
    shared.clear()  # as the session does on the GUI thread when the project closes
    assert time.perf_counter() - t0 < 0.1 and not built.is_set()
    worker.join()
    assert built.is_set() and shared._tracer is None  # made for a closed project: not kept
