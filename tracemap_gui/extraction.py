"""2D → 3D from the editor: ray tracing on a worker, stored as one undoable command (as `tracemap extract`),
itself written on a worker (`Session.push_in_background`): hundreds of traces are tens of MB of blobs."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.cameras import Camera
from engine.errors import Progress, report
from engine.extract import Extraction, extract_traces
from engine.traces import Trace2D
from tracemap_gui.commands import ReplaceTraces3D
from tracemap_gui.mesh_tracer import MeshTracer
from tracemap_gui.session import Session


class Extractor:
    """Ray-traces 2D traces onto the mesh with the ray tracer of `mesh_tracer` (the session's).

    Called on a worker thread, one run at a time (the editor disables extraction while one runs).
    """

    def __init__(self, mesh_tracer: MeshTracer | None = None) -> None:
        self._mesh_tracer = mesh_tracer or MeshTracer()

    def __call__(self, traces: list[Trace2D], cameras: dict[str, Camera], mesh_path: Path, origin: np.ndarray,
                 *, progress: Progress) -> Extraction:
        tracer = self._mesh_tracer.tracer(mesh_path, origin, progress=lambda f, m: report(progress, 0.2 * f, m))
        return extract_traces(traces, cameras, tracer, progress=lambda f, m: report(progress, 0.2 + 0.8 * f, m))


def extraction_command(session: Session, parents: list[Trace2D], result: Extraction) -> ReplaceTraces3D:
    """Store an extraction: the new 3D traces replace those made earlier from the same 2D traces."""
    ids = {t.id for t in parents}
    old = [t for t in session.traces3d() if ids.intersection(t.parents)]
    return ReplaceTraces3D(session, old, result.traces, f"Extract {len(result.traces)} 3D traces")
