"""Click an end node in the 3D viewer to set its termination: blind, abutting, crossing or censored (B/T/X/C;
Seers & Hodgetts 2016a §3.5, MATHS §6). The automatic classification gets most nodes right; this is for
the rest, one click and one key each, undoable like every edit."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from PySide6.QtCore import QObject, QPoint
from PySide6.QtGui import QAction
from PySide6.QtWidgets import QMenu

from engine.traces import TERMINATIONS, Trace3D
from tracemap_gui.scene_view import nearest_point

if TYPE_CHECKING:
    from tracemap_gui.viewer3d import Viewer3D

NODE_PICK_PX = 8  # how near (display pixels) a click must fall to an end node
NAMES = {"B": "blind", "T": "abutting", "X": "crossing", "C": "censored"}


class TerminationTool(QObject):
    """While on, a click near an end node selects its trace and opens a menu of the four codes."""

    def __init__(self, viewer: Viewer3D):
        super().__init__(viewer)
        self.viewer = viewer
        self.action = viewer.add_tool("Terminations", "E", "Click an end node to set its termination (B/T/X/C)")
        self.menu = QMenu(viewer)
        self.menu.setObjectName("termination-menu")
        for code in TERMINATIONS:
            item = self.menu.addAction(f"&{code}  {NAMES[code]}")
            item.setData(code)
        self.menu.triggered.connect(self._chosen)
        self.target: tuple[int, str] | None = None  # (trace id, "start" or "end") the menu is for

    def node_at(self, x: float, y: float) -> tuple[Trace3D, str] | None:
        """The trace and end ("start"/"end") whose end node is drawn nearest (x, y), within NODE_PICK_PX."""
        traces = [t for t in self.viewer.session.traces3d() if len(t.points) >= 2]
        if not traces:
            return None
        ends = np.vstack([t.points[[0, -1]] for t in traces])
        k = nearest_point(self.viewer.view.plotter.renderer, ends, x, y, NODE_PICK_PX)
        return None if k is None else (traces[k // 2], ("start", "end")[k % 2])

    def handle_click(self, x: int, y: int, additive: bool) -> bool:
        if not self.action.isChecked() or additive:
            return False
        found = self.node_at(x, y)
        if found is None:
            return False  # not on a node: an ordinary selection click
        trace, end = found
        self.target = (trace.id, end)
        self.viewer.session.select3d({trace.id})
        view = self.viewer.view
        self.menu.setTitle(f"Trace {trace.id}, {end} node")
        self.menu.popup(view.mapToGlobal(QPoint(int(x), view.height() - 1 - int(y))))
        return True

    def _chosen(self, item: QAction) -> None:
        if self.target is None:
            return
        trace_id, end = self.target
        self.target = None
        if self.viewer.session.selected3d == frozenset({trace_id}):
            self.viewer.set_termination(end, item.data())
