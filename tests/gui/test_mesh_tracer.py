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
