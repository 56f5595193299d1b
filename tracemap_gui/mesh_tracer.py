"""The open project's ray tracer, survey and the mesh's silhouettes in the photos, shared by every tool.

A ray tracer of a 3M-face mesh takes about 0.2 GB and half a second to build, and the editor (extraction,
auto-trace, GCPs) and the 3D viewer (photo drape, merge suggestions, intensity maps) all need one of the
same mesh: the session keeps one (`Session.mesh_tracer`), built on a worker by the first tool that asks,
and lets it go when the project closes. Meshes are told apart by their file (path, modification time) and
local origin, so the viewer's loaded mesh and a mesh the editor reads from the same file share it.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from engine.cameras import Camera
from engine.delineate import silhouette
from engine.errors import Progress, report
from engine.mesh import Mesh, read_mesh
from engine.raytrace import RayTracer
from engine.sight import Sight

KEEP_SILHOUETTES = 4
"""Silhouettes kept, the most recently used (24 MB each at 24 MP): the photo being traced and the last few."""


class MeshTracer:
    """Called from worker threads, possibly several at once (an extraction and an auto-trace). One ray tracer
    is built at a time and a silhouette asked for twice at once is cast once; `clear` (on the GUI thread)
    never waits for either, and what they make after it is dropped."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # guards the fields below; held only briefly
        self._building = threading.Lock()  # held while a ray tracer is built
        self._generation = 0  # bumped by clear(): work started before it is not kept
        self._key: tuple | None = None
        self._tracer: RayTracer | None = None
        self._mesh: weakref.ref | None = None  # a mesh without a file is known by identity
        self._silhouettes: OrderedDict[tuple, Future] = OrderedDict()

    def tracer(self, mesh_path: Path, origin: np.ndarray, *, progress: Progress | None = None) -> RayTracer:
        """The ray tracer of the mesh file at `mesh_path`, in the frame shifted to `origin` (read if needed)."""
        return self._get(_file_key(mesh_path, origin), lambda: read_mesh(mesh_path, origin=origin), progress)

    def of(self, mesh: Mesh, *, progress: Progress | None = None) -> RayTracer:
        """The ray tracer of a mesh already in memory."""
        if mesh.source is not None and Path(mesh.source).is_file():
            return self._get(_file_key(Path(mesh.source), mesh.origin), lambda: mesh, progress)
        return self._get(("memory", id(mesh)), lambda: mesh, progress, keep=mesh)

    def silhouette(self, camera: Camera, depth_step: float, mesh_path: Path, origin: np.ndarray, *,
                   progress: Progress | None = None) -> np.ndarray:
        """The mesh's silhouette in the photo of `camera` (local frame), as `engine.delineate.silhouette`."""
        tracer = self.tracer(mesh_path, origin, progress=progress)
        key = (_file_key(mesh_path, origin), camera.name, camera.width, camera.height,
               *(a.tobytes() for a in (camera.K, camera.distortion, camera.R, camera.t)), depth_step)
        with self._lock:
            pending = self._silhouettes.get(key)
            mine = pending is None
            if mine:
                pending = self._silhouettes[key] = Future()
                while len(self._silhouettes) > KEEP_SILHOUETTES:
                    self._silhouettes.popitem(last=False)
            self._silhouettes.move_to_end(key)
        if mine:
            report(progress, 0.9, "the mesh's silhouette")
            try:
                pending.set_result(silhouette(camera, tracer, depth_step=depth_step))
            except BaseException as exc:
                with self._lock:
                    self._silhouettes.pop(key, None)  # the next caller tries again
                pending.set_exception(exc)
        return pending.result()

    def clear(self) -> None:
        """Let the ray tracer and silhouettes go (the project closed)."""
        with self._lock:
            self._generation += 1
            self._key = self._tracer = self._mesh = None
            self._silhouettes.clear()

    def _get(self, key: tuple, load: Callable[[], Mesh], progress: Progress | None, *,
             keep: Mesh | None = None) -> RayTracer:
        """The ray tracer for `key`, built from `load()` unless it is the one held; a mesh known only by its
        identity (`keep`) is held by a weak reference, since an id may be reused once it is gone."""
        with self._building:
            with self._lock:
                if key == self._key and (keep is None or (self._mesh is not None and self._mesh() is keep)):
                    return self._tracer
                self._key = self._tracer = self._mesh = None  # the old one goes before the new one is built
                generation = self._generation
            report(progress, 0.0, "loading the mesh")
            mesh = load()
            report(progress, 0.5, "building the ray tracer")
            tracer = RayTracer(mesh.vertices, mesh.faces)
            with self._lock:
                if generation == self._generation:
                    self._key, self._tracer = key, tracer
                    self._mesh = None if keep is None else weakref.ref(keep)
            return tracer


def _file_key(path: Path, origin: np.ndarray) -> tuple:
    path = Path(path).resolve()
    return path, path.stat().st_mtime_ns, tuple(np.asarray(origin, float).tolist())


def survey(mesh: Mesh | None, cameras: dict[str, Camera], known: Sight | None, tracers: MeshTracer,
           progress: Callable[[float, str], None]) -> Sight | None:
    """The survey of `mesh` for hidden-gap bridges: `known` if it is that mesh's (a project's mesh and cameras
    change together), else a new one on the session's ray tracer of the mesh (built, if no tool has yet, in
    a few hundred ms per million faces: on a worker)."""
    if mesh is None:
        return None
    if known is not None and known.mesh is mesh:
        return known
    return Sight(mesh, cameras, tracers.of(mesh, progress=lambda f, m: progress(0.1 * f, m)))
