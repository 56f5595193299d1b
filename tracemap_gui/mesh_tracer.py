"""The project mesh's ray tracer and its silhouettes in the photos, built on a worker on first use and kept
while the mesh file is unchanged: extraction and auto-trace share them."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from engine.cameras import Camera
from engine.delineate import silhouette
from engine.errors import Progress, report
from engine.mesh import read_mesh
from engine.raytrace import RayTracer


class MeshTracer:
    """Called from worker threads, possibly two at once (an extraction and an auto-trace): a lock keeps them
    from building the same ray tracer twice."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._mesh: tuple[Path, float] | None = None
        self._tracer: RayTracer | None = None
        self._silhouettes: dict[tuple[str, float], np.ndarray] = {}

    def tracer(self, mesh_path: Path, origin: np.ndarray, *, progress: Progress | None = None) -> RayTracer:
        """The ray tracer of the mesh at `mesh_path`, in the frame shifted to `origin`."""
        key = (mesh_path, mesh_path.stat().st_mtime)
        with self._lock:
            if key != self._mesh:
                report(progress, 0.0, f"loading the mesh {mesh_path.name}")
                mesh = read_mesh(mesh_path, origin=origin)
                report(progress, 0.5, "building the ray tracer")
                self._tracer, self._mesh, self._silhouettes = RayTracer(mesh.vertices, mesh.faces), key, {}
            return self._tracer

    def silhouette(self, camera: Camera, depth_step: float, mesh_path: Path, origin: np.ndarray, *,
                   progress: Progress | None = None) -> np.ndarray:
        """The mesh's silhouette in the photo of `camera` (local frame), as `engine.delineate.silhouette`."""
        tracer = self.tracer(mesh_path, origin, progress=progress)
        key = (camera.name, depth_step)
        if key not in self._silhouettes:
            report(progress, 0.9, "the mesh's silhouette")
            self._silhouettes[key] = silhouette(camera, tracer, depth_step=depth_step)
        return self._silhouettes[key]
