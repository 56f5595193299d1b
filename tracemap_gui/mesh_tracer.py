"""The project mesh's ray tracer and its silhouettes in the photos, built on a worker on first use and kept
while the mesh file is unchanged: extraction and auto-trace share them."""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from engine.cameras import Camera
from engine.delineate import silhouette
from engine.errors import Progress, report
from engine.mesh import read_mesh
from engine.raytrace import RayTracer

KEEP_SILHOUETTES = 4
"""Silhouettes kept, the most recently used (24 MB each at 24 MP): the photo being traced and the last few."""


class MeshTracer:
    """Called from worker threads, possibly two at once (an extraction and an auto-trace): a lock keeps them
    from building the same ray tracer twice."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._mesh: tuple[Path, float] | None = None
        self._tracer: RayTracer | None = None
        self._silhouettes: OrderedDict[tuple, np.ndarray] = OrderedDict()

    def tracer(self, mesh_path: Path, origin: np.ndarray, *, progress: Progress | None = None) -> RayTracer:
        """The ray tracer of the mesh at `mesh_path`, in the frame shifted to `origin`."""
        key = (mesh_path, mesh_path.stat().st_mtime)
        with self._lock:
            if key != self._mesh:
                report(progress, 0.0, f"loading the mesh {mesh_path.name}")
                mesh = read_mesh(mesh_path, origin=origin)
                report(progress, 0.5, "building the ray tracer")
                self._tracer, self._mesh = RayTracer(mesh.vertices, mesh.faces), key
            return self._tracer

    def silhouette(self, camera: Camera, depth_step: float, mesh_path: Path, origin: np.ndarray, *,
                   progress: Progress | None = None) -> np.ndarray:
        """The mesh's silhouette in the photo of `camera` (local frame), as `engine.delineate.silhouette`."""
        tracer = self.tracer(mesh_path, origin, progress=progress)
        key = (mesh_path, mesh_path.stat().st_mtime, camera.name, camera.width, camera.height,
               *(a.tobytes() for a in (camera.K, camera.distortion, camera.R, camera.t)), depth_step)
        with self._lock:
            found = self._silhouettes.get(key)
        if found is None:
            report(progress, 0.9, "the mesh's silhouette")
            found = silhouette(camera, tracer, depth_step=depth_step)
        with self._lock:
            self._silhouettes[key] = found
            self._silhouettes.move_to_end(key)
            while len(self._silhouettes) > KEEP_SILHOUETTES:
                self._silhouettes.popitem(last=False)
        return found
