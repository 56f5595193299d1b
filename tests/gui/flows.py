"""What a user does with the mouse, and what another process would read from the project file."""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

import numpy as np
from PySide6.QtCore import QPoint, QPointF, Qt

from engine.project import from_blob
from engine.register import Registration, Similarity


def screen_point(view, x: float, y: float) -> QPoint:
    """Viewport position of photo pixel (x, y)."""
    return view.mapFromScene(QPointF(x, y))


def click(qtbot, view, x: float, y: float, button=Qt.MouseButton.LeftButton, modifier=Qt.KeyboardModifier.NoModifier):
    qtbot.mouseClick(view.viewport(), button, modifier, screen_point(view, x, y))


def drag(qtbot, view, start: tuple[float, float], end: tuple[float, float]) -> None:
    viewport = view.viewport()
    qtbot.mousePress(viewport, Qt.MouseButton.LeftButton, pos=screen_point(view, *start))
    for f in np.linspace(0.25, 1.0, 4):
        qtbot.mouseMove(viewport, screen_point(view, start[0] + f * (end[0] - start[0]),
                                               start[1] + f * (end[1] - start[1])))
    qtbot.mouseRelease(viewport, Qt.MouseButton.LeftButton, pos=screen_point(view, *end))


def stored_traces2d(project_path: Path, image: str | None = None):
    """The 2D traces as another process would read them from the file now (a read-only connection)."""
    db = sqlite3.connect(f"file:{project_path}?mode=ro", uri=True)
    try:
        rows = db.execute("SELECT id, image, polyline, source FROM traces2d ORDER BY id").fetchall()
    finally:
        db.close()
    return {i: (im, from_blob(p), s) for i, im, p, s in rows if image is None or im == image}


def stored_traces3d_parents(project_path: Path) -> dict[int, tuple[int, ...]]:
    db = sqlite3.connect(f"file:{project_path}?mode=ro", uri=True)
    try:
        return {i: tuple(json.loads(p)) for i, p in db.execute("SELECT id, parents FROM traces3d ORDER BY id")}
    finally:
        db.close()


def shown_scene_view(qtbot, size: tuple[int, int]):
    """An offscreen `SceneView` of `size`, shown and exposed."""
    from tracemap_gui.scene_view import SceneView

    view = SceneView(offscreen=True)
    qtbot.addWidget(view)
    view.resize(*size)
    view.show()
    qtbot.waitExposed(view)
    return view


def open_viewer(qtbot, session, size=(900, 600)):
    """The 3D viewer on `session`, shown offscreen, once its mesh is loaded."""
    from tracemap_gui.viewer3d import Viewer3D

    window = Viewer3D(session, offscreen=True)
    qtbot.addWidget(window)
    window.resize(*size)
    window.show()
    qtbot.waitUntil(lambda: window.mesh is not None, timeout=60_000)  # the machine may be busy
    return window


def actor_data(actor):
    """The dataset an actor draws, as pyvista sees it; brought up to date first, since the view renders
    once per pass of the event loop and a test may look before that."""
    mapper = actor.GetMapper()
    mapper.Update()
    import pyvista as pv

    return pv.wrap(mapper.GetInput())


QUARTER_TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90° anticlockwise about z


def register(project, scale: float, rotation: np.ndarray | None = None) -> None:
    """Store a registration world = scale · rotation · model (no GCPs behind it: the readouts only need it)."""
    similarity = Similarity(scale, np.eye(3) if rotation is None else rotation, np.zeros(3), np.zeros((3, 3)),
                            np.zeros(3), 0.0)
    project.set_registration(Registration(("a", "b", "c"), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3),
                                          ((), (), ()), similarity))


def assert_responsive(ticks: list[tuple[float, float]], *, min_gaps: int = 5) -> None:
    """The GUI thread ticked while work ran: `ticks` are (wall, thread CPU) times of a 10 ms timer. No gap
    of 100 ms of the GUI thread's own work; nor of wall time unless others load the machine beyond its
    cores (the OS then gives the time to them). Gaps count from the first tick: setting off the work is not
    a stall."""
    gaps = np.diff(np.array(ticks[1:]), axis=0)
    assert len(gaps) > min_gaps
    wall, cpu = gaps.max(axis=0)
    assert cpu < 0.1, f"the GUI thread worked {cpu * 1000:.0f} ms without returning to the event loop"
    if os.getloadavg()[0] < os.cpu_count():
        assert wall < 0.1, f"longest GUI-thread stall {wall * 1000:.0f} ms"
