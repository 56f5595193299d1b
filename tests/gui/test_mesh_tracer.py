"""The editor's shared ray tracer and silhouettes: reused while the mesh is unchanged, and bounded."""

import os

import numpy as np

from engine.delineate import silhouette
from tracemap_gui.mesh_tracer import KEEP_SILHOUETTES, MeshTracer


def test_silhouettes_are_kept_while_the_mesh_is_unchanged_and_bounded(project_path):
    from engine.project import Project

    with Project.open(project_path) as project:
        mesh_path, origin, cameras = project.mesh_path, project.origin, project.cameras()
    shared = MeshTracer()
    tracer = shared.tracer(mesh_path, origin)
    assert shared.tracer(mesh_path, origin) is tracer
    camera = cameras["photo_01"]
    first = shared.silhouette(camera, 0.03, mesh_path, origin)
    assert np.array_equal(first, silhouette(camera, tracer))
    assert shared.silhouette(camera, 0.03, mesh_path, origin) is first
    assert shared.silhouette(camera, 0.1, mesh_path, origin) is not first  # another step, another silhouette
    for k in range(KEEP_SILHOUETTES):  # the same photo seen from slightly elsewhere: other cameras
        moved = type(camera)(camera.name, camera.width, camera.height, camera.K, camera.distortion, camera.R,
                             camera.t + [0.01 * (k + 1), 0, 0])
        shared.silhouette(moved, 0.03, mesh_path, origin)
    assert len(shared._silhouettes) == KEEP_SILHOUETTES
    assert shared.silhouette(camera, 0.03, mesh_path, origin) is not first  # dropped as the least recently used
    stat = mesh_path.stat()
    os.utime(mesh_path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # the mesh file changed
    assert shared.tracer(mesh_path, origin) is not tracer
