"""Tools of the image editor: each turns mouse and keys on the photo into one undoable command.

A tool sees the photo view (the shown photo, zoom, its own transient graphics) and the session (traces,
selection, `push`). The view hands it presses, moves, releases, double-clicks and keys in photo pixel
coordinates; `paint` draws what the tool is doing, in screen pixels, over everything else.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QKeyEvent, QMouseEvent, QPainter, QPolygonF
from PySide6.QtWidgets import QApplication

from engine.errors import TracemapError
from engine.traces import Trace2D
from tracemap_gui import commands, delineation, polyline_edit
from tracemap_gui.error_dialog import show_error
from tracemap_gui.photo_view import PhotoView
from tracemap_gui.session import Session
from tracemap_gui.trace_layer import ProposalLayer, cosmetic_pen
from tracemap_gui.workers import Task

DRAWING = QColor(255, 120, 0)
HANDLE = 7  # vertex handle side, screen pixels


class Tool:
    """Base: picking helpers and do-nothing event handlers."""

    name = ""
    hint = ""
    cursor = Qt.CursorShape.CrossCursor

    def __init__(self, session: Session, view: PhotoView):
        self.session, self.view = session, view

    def activate(self) -> None:
        pass

    def deactivate(self) -> None:
        self.cancel()

    def cancel(self) -> None:
        """Forget a half-done gesture."""
        self.view.viewport().update()

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        pass

    def move(self, pos: QPointF, event: QMouseEvent) -> None:
        pass

    def release(self, pos: QPointF, event: QMouseEvent) -> None:
        pass

    def double_click(self, pos: QPointF, event: QMouseEvent) -> None:
        pass

    def undone(self) -> None:
        """Undo or redo changed the project; tools re-read the traces they work on, so most keep going."""

    def key(self, event: QKeyEvent) -> bool:
        """Handle a key; False lets the view have it. Esc cancels a gesture in every tool."""
        if event.key() == Qt.Key.Key_Escape:
            self.cancel()
            return True
        return False

    def delete(self) -> None:
        """Edit → Delete: erase the selected traces."""
        chosen = [t for t in self.traces() if t.id in self.session.selected2d]
        if chosen:
            self.push(commands.RemoveTraces2D(self.session, chosen))

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        pass

    # -- helpers ------------------------------------------------------------------------------------------

    def traces(self) -> list[Trace2D]:
        return self.session.traces2d(self.view.image)

    def pick(self, pos: QPointF) -> tuple[Trace2D, polyline_edit.Hit] | None:
        """The trace passing nearest the cursor (within a few screen pixels), and where."""
        traces = self.traces()
        hit = polyline_edit.nearest([t.polyline for t in traces], (pos.x(), pos.y()), self.view.pick_radius())
        return None if hit is None else (traces[hit.index], hit)

    def inside(self, pos: QPointF) -> np.ndarray:
        """The point, moved onto the photo if the click fell outside it (traces must lie on the photo)."""
        rect = self.view.sceneRect()
        return np.array([min(max(pos.x(), rect.left()), rect.right()), min(max(pos.y(), rect.top()), rect.bottom())])

    def push(self, command: commands.ProjectCommand) -> bool:
        """Push an edit; a refusal the user can fix (TracemapError) is shown as a hint, not a dialog."""
        try:
            self.session.push(command)
        except TracemapError as exc:
            self.view.hint.emit(str(exc))
            return False
        return True

    def screen(self, points: np.ndarray) -> QPolygonF:
        transform = self.view.viewportTransform()
        return QPolygonF([transform.map(QPointF(x, y)) for x, y in points])


def draw_handles(painter: QPainter, polygon: QPolygonF, active: int | None = None) -> None:
    painter.setPen(cosmetic_pen(QColor(0, 0, 0), 1))
    for k, p in enumerate(polygon):
        painter.setBrush(DRAWING if k == active else QColor(255, 255, 255))
        painter.drawRect(QRectF(p.x() - HANDLE / 2, p.y() - HANDLE / 2, HANDLE, HANDLE))


def join_legs(legs: list[np.ndarray]) -> np.ndarray:
    """One polyline from paths that each start where the one before ends."""
    return np.vstack([legs[0], *(leg[1:] for leg in legs[1:])]) if legs else np.empty((0, 2))


class DrawPolyline(Tool):
    """Click vertices; double-click or Enter finishes, Backspace takes back the last vertex, Esc cancels."""

    name = "Draw polyline"
    hint = "Click the vertices of a trace; double-click or Enter finishes, Backspace undoes a vertex, Esc cancels"

    def __init__(self, session: Session, view: PhotoView):
        super().__init__(session, view)
        self._anchors: list[np.ndarray] = []  # the clicked points
        self._legs: list[np.ndarray] = []  # the path from each anchor to the next, both ends included
        self._cursor: np.ndarray | None = None

    def route(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The path from click a to click b: a straight line here."""
        return np.array([a, b])

    def polyline(self) -> np.ndarray:
        return join_legs(self._legs) if self._legs else np.array(self._anchors[:1]).reshape(-1, 2)

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        if event.button() != Qt.MouseButton.LeftButton:
            return
        point = self.inside(pos)
        if self._anchors and np.allclose(point, self._anchors[-1]):
            return  # the second press of a double-click
        if self._anchors:
            try:
                self._legs.append(self.route(self._anchors[-1], point))
            except TracemapError as exc:
                self.view.hint.emit(str(exc))
                return
        self._anchors.append(point)
        self.view.viewport().update()

    def move(self, pos: QPointF, event: QMouseEvent) -> None:
        self._cursor = self.inside(pos)
        if self._anchors:
            self.view.viewport().update()

    def double_click(self, pos: QPointF, event: QMouseEvent) -> None:
        self.finish()

    def key(self, event: QKeyEvent) -> bool:
        if event.key() in (Qt.Key.Key_Return, Qt.Key.Key_Enter):
            self.finish()
            return True
        if event.key() == Qt.Key.Key_Backspace and self._anchors:
            self._anchors.pop()
            if self._legs:
                self.take_back(self._legs.pop())
            self.view.viewport().update()
            return True
        return super().key(event)

    def take_back(self, leg: np.ndarray) -> None:
        """Backspace removed the last leg; nothing else refers to it here."""

    def finish(self) -> None:
        polyline = self.polyline()
        self.restart()
        self.commit(polyline)
        self.view.viewport().update()

    def commit(self, polyline: np.ndarray) -> None:
        """Add the drawn trace, one undoable command; repeated points are dropped, fewer than 2 add nothing."""
        polyline = polyline[np.any(np.diff(polyline, axis=0, prepend=np.nan) != 0, axis=1)]  # NaN: keep the first
        if len(polyline) >= 2:
            self.push(commands.AddTraces2D(self.session, [Trace2D(0, self.view.image, polyline, "manual",
                                                                  kind=self.session.kind)]))

    def restart(self) -> None:
        """Forget the clicks: the next one starts a new trace."""
        self._anchors, self._legs = [], []

    def cancel(self) -> None:
        self.restart()
        super().cancel()

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        if not self._anchors:
            return
        points = self.polyline()
        if self._cursor is not None:
            points = np.vstack([points, self._cursor])
        polygon = self.screen(points)
        painter.setPen(cosmetic_pen(DRAWING, 2))
        painter.drawPolyline(polygon)
        draw_handles(painter, self.screen(np.array(self._anchors)))


@dataclass(eq=False)
class _Search:
    """The search for the path between two clicks: the legs of the trace it is for, the straight segment
    standing in for the path there until it arrives, and the photo's pixels."""

    legs: list[np.ndarray]
    stand_in: np.ndarray
    pixels: np.ndarray


class GuidedCurve(DrawPolyline):
    """As DrawPolyline, but between clicks the line follows the fracture (the engine's least-cost path).

    The path between two clicks is searched on a worker, a straight segment standing in for it meanwhile,
    so a click returns at once however far apart the clicks are (a 2000 px path on a 24 MP photo takes
    a few hundred ms). The searches run one at a time, in click order. A trace finished before all its
    paths arrived is added when they have, as one command. Esc, undo, another tool or another photo
    cancel every search pending, and the traces waiting for them. A search that fails, or is cancelled
    from the progress panel, leaves its straight segment.
    """

    name = "Guided curve"
    hint = "Click along a fracture: the line snaps to it between clicks; double-click or Enter finishes"

    def __init__(self, session: Session, view: PhotoView):
        super().__init__(session, view)
        self._queue: deque[_Search] = deque()  # in click order; the first one's task is running
        self._task: Task | None = None
        self._finished: list[list[np.ndarray]] = []  # the legs of traces finished, in order, not yet added

    def route(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if self.view.pyramid is None:
            raise TracemapError("the photo is still loading; click again in a moment")
        stand_in = np.array([a, b])
        self._queue.append(_Search(self._legs, stand_in, self.view.pyramid.levels[0]))
        self._start_next()
        return stand_in

    def _start_next(self) -> None:
        if self._task is not None or not self._queue:
            return
        search = self._queue[0]
        task = Task("Guided curve", delineation.guided_curve, search.pixels, *search.stand_in)
        task.signals.done.connect(lambda path: self._ended(task, path))
        task.signals.failed.connect(lambda exc: self._ended(task, error=exc))
        task.signals.cancelled.connect(lambda: self._ended(task))
        self._task = task
        self.session.jobs.start(task)

    def _ended(self, task: Task, path: np.ndarray | None = None, error: BaseException | None = None) -> None:
        if task is not self._task:
            return  # cancelled by this tool, and off the queue already
        search = self._advance()
        if path is not None:
            search.legs[next(k for k, leg in enumerate(search.legs) if leg is search.stand_in)] = path
        self._add_finished()
        self.view.viewport().update()
        if error is not None:
            show_error(self.view, "Following the fracture", error)

    def _advance(self) -> _Search:
        """Take the first search off the queue (its task is over) and start the next."""
        self._task = None
        search = self._queue.popleft()
        self._start_next()
        return search

    def _add_finished(self) -> None:
        """Add the finished traces whose paths have all arrived, in the order they were finished."""
        while self._finished and not any(search.legs is self._finished[0] for search in self._queue):
            self.commit(join_legs(self._finished.pop(0)))

    def take_back(self, leg: np.ndarray) -> None:
        search = next((s for s in self._queue if s.stand_in is leg), None)
        if search is None:
            return  # its path had arrived
        if search is self._queue[0]:
            self._task.cancel()
            self._advance()
        else:
            self._queue.remove(search)

    def finish(self) -> None:
        self._finished.append(self._legs)
        self.restart()
        self._add_finished()
        self.view.viewport().update()

    def cancel(self) -> None:
        if self._task is not None:
            self._task.cancel()
            self._task = None
        self._queue.clear()
        self._finished.clear()
        super().cancel()

    def undone(self) -> None:
        self.cancel()  # as Esc: the trace being drawn, or waiting for its paths, is not on the undo stack yet

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        painter.setPen(cosmetic_pen(DRAWING, 2))
        for legs in self._finished:  # still waiting for paths
            painter.drawPolyline(self.screen(join_legs(legs)))
        super().paint(painter, view)


class SplineCurve(DrawPolyline):
    """As DrawPolyline, but the trace is a smooth curve through the clicks (the engine's smoothing spline)."""

    name = "Spline curve"
    hint = "Click along a fracture: a smooth curve follows the clicks; double-click or Enter finishes"

    def polyline(self) -> np.ndarray:
        clicks = np.array(self._anchors).reshape(-1, 2)
        if len(clicks) < 2:
            return clicks
        rect = self.view.sceneRect()  # a spline may swing out past a click near the photo's edge
        return np.clip(delineation.spline(clicks), (rect.left(), rect.top()), (rect.right(), rect.bottom()))


class EditVertices(Tool):
    """Drag a vertex to move it; click a segment to insert one; Delete removes the active vertex."""

    name = "Edit vertices"
    hint = "Drag a vertex to move it, click a line to add a vertex, Delete removes the highlighted vertex"

    def __init__(self, session: Session, view: PhotoView):
        super().__init__(session, view)
        self._id: int | None = None  # the trace being edited
        self._vertex: int | None = None
        self._moved: np.ndarray | None = None  # its polyline while a vertex is dragged

    def _trace(self) -> Trace2D | None:
        """The trace being edited as stored now (an undo may have changed or removed it)."""
        trace = next((t for t in self.traces() if t.id == self._id), None)
        if trace is None or self._vertex is not None and self._vertex >= len(trace.polyline):
            self._vertex = None
        return trace

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        if event.button() != Qt.MouseButton.LeftButton:
            return
        trace = self._trace()
        if trace is not None:
            vertex, distance = polyline_edit.nearest_vertex(trace.polyline, (pos.x(), pos.y()))
            if distance <= self.view.pick_radius():
                self._vertex, self._moved = vertex, trace.polyline
                self.view.viewport().update()
                return
        picked = self.pick(pos)
        if picked is not None and trace is not None and picked[0].id == trace.id:
            hit = picked[1]
            polyline = polyline_edit.insert_vertex(trace.polyline, hit.segment, hit.t)
            if self.push(commands.EditTrace2D(self.session, trace, polyline, "Add vertex")):
                self._vertex = hit.segment + 1
        else:
            self._id, self._vertex = (None if picked is None else picked[0].id), None
            self.session.select2d([] if picked is None else [picked[0].id])
        self.view.viewport().update()

    def move(self, pos: QPointF, event: QMouseEvent) -> None:
        if self._moved is not None and self._vertex is not None:
            self._moved = polyline_edit.move_vertex(self._moved, self._vertex, self.inside(pos))
            self.view.viewport().update()

    def release(self, pos: QPointF, event: QMouseEvent) -> None:
        moved, self._moved = self._moved, None
        trace = self._trace()
        if moved is not None and trace is not None and not np.array_equal(moved, trace.polyline):
            self.push(commands.EditTrace2D(self.session, trace, moved, "Move vertex"))
        self.view.viewport().update()

    def delete(self) -> None:
        trace = self._trace()
        if trace is None or self._vertex is None:
            super().delete()
            return
        try:
            polyline = polyline_edit.delete_vertex(trace.polyline, self._vertex)
        except TracemapError as exc:
            self.view.hint.emit(str(exc))
            return
        if self.push(commands.EditTrace2D(self.session, trace, polyline, "Delete vertex")):
            self._vertex = None
        self.view.viewport().update()

    def cancel(self) -> None:
        self._id = self._vertex = self._moved = None
        super().cancel()

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        trace = self._trace()
        if trace is None:
            return
        polygon = self.screen(trace.polyline if self._moved is None else self._moved)
        if self._moved is not None:
            painter.setPen(cosmetic_pen(DRAWING, 2))
            painter.drawPolyline(polygon)
        draw_handles(painter, polygon, self._vertex)


class Split(Tool):
    """Click on a trace to cut it in two there."""

    name = "Split"
    hint = "Click on a trace where it should be cut in two"
    cursor = Qt.CursorShape.PointingHandCursor

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        picked = self.pick(pos)
        if event.button() == Qt.MouseButton.LeftButton and picked is not None:
            trace, hit = picked
            try:
                command = commands.SplitTrace2D(self.session, trace, hit.segment, hit.t)
            except TracemapError as exc:
                self.view.hint.emit(str(exc))
                return
            self.push(command)


class Join(Tool):
    """Click two traces: they become one, joined at their nearest ends."""

    name = "Join"
    hint = "Click the first trace, then the second: they are joined at their nearest ends"
    cursor = Qt.CursorShape.PointingHandCursor

    def __init__(self, session: Session, view: PhotoView):
        super().__init__(session, view)
        self._first: int | None = None  # id of the trace clicked first

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        picked = self.pick(pos)
        if event.button() != Qt.MouseButton.LeftButton or picked is None:
            return
        trace = picked[0]
        first = next((t for t in self.traces() if t.id == self._first), None)  # as stored now
        if first is None or first.id == trace.id:
            self._first = trace.id
            self.session.select2d([trace.id])
            self.view.hint.emit("Now click the trace to join it to")
            return
        self._first = None
        if first.kind != trace.kind:  # one trace has one kind: say so rather than pick one
            self.session.select2d([])
            self.view.hint.emit(f"Not joined: one trace is {first.kind}, the other {trace.kind}; give them one kind "
                                "first (Traces → Make selected traces)")
            return
        if self.push(commands.JoinTraces2D(self.session, first, trace)):
            self.session.select2d([])
            self.view.hint.emit(self.hint)

    def cancel(self) -> None:
        self._first = None
        super().cancel()


class Erase(Tool):
    """Click on a trace to erase it."""

    name = "Erase"
    hint = "Click on a trace to erase it"
    cursor = Qt.CursorShape.PointingHandCursor

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        picked = self.pick(pos)
        if event.button() == Qt.MouseButton.LeftButton and picked is not None:
            self.push(commands.RemoveTraces2D(self.session, [picked[0]], "Erase trace"))


class Select(Tool):
    """Click a trace (Shift adds or removes) or drag a rectangle; click a proposal to reject or restore it."""

    name = "Select"
    hint = ("Click a trace or drag a box to select (Shift adds); Delete erases the selection; "
            "click an auto-trace proposal to reject or restore it")
    cursor = Qt.CursorShape.ArrowCursor

    def __init__(self, session: Session, view: PhotoView, proposals: ProposalLayer):
        super().__init__(session, view)
        self._proposals = proposals
        self._start: QPointF | None = None
        self._end: QPointF | None = None

    def press(self, pos: QPointF, event: QMouseEvent) -> None:
        if event.button() == Qt.MouseButton.LeftButton:
            self._start = self._end = pos

    def move(self, pos: QPointF, event: QMouseEvent) -> None:
        if self._start is not None:
            self._end = pos
            self.view.viewport().update()

    def release(self, pos: QPointF, event: QMouseEvent) -> None:
        if self._start is None:
            return
        start, self._start = self._start, None
        adding = bool(event.modifiers() & Qt.KeyboardModifier.ShiftModifier)
        dragged = self.view.viewportTransform().map(pos) - self.view.viewportTransform().map(start)
        if dragged.manhattanLength() >= QApplication.startDragDistance():
            box = QRectF(start, pos).normalized()
            lo, hi = (box.left(), box.top()), (box.right(), box.bottom())
            ids = {t.id for t in self.traces() if polyline_edit.crosses_rect(t.polyline, lo, hi)}
            self.session.select2d(self.session.selected2d | ids if adding else ids)
        elif not self._toggle_proposal(pos):
            self._click(pos, adding)
        self.view.viewport().update()

    def _toggle_proposal(self, pos: QPointF) -> bool:
        if self._proposals.image != self.view.image:
            return False
        hit = polyline_edit.nearest([t.polyline for t in self._proposals.traces], (pos.x(), pos.y()),
                                    self.view.pick_radius())
        if hit is not None:
            self._proposals.toggle(hit.index)
        return hit is not None

    def _click(self, pos: QPointF, adding: bool) -> None:
        picked = self.pick(pos)
        if picked is None:
            ids = self.session.selected2d if adding else frozenset()
        elif adding:
            ids = self.session.selected2d ^ {picked[0].id}
        else:
            ids = {picked[0].id}
        self.session.select2d(ids)

    def key(self, event: QKeyEvent) -> bool:
        if event.key() == Qt.Key.Key_Escape:
            self.session.select2d([])
        return super().key(event)

    def cancel(self) -> None:
        self._start = None
        super().cancel()

    def paint(self, painter: QPainter, view: PhotoView) -> None:
        if self._start is None or self._end is None:
            return
        transform = view.viewportTransform()
        painter.setPen(cosmetic_pen(QColor(255, 255, 255), 1, Qt.PenStyle.DashLine))
        painter.setBrush(QColor(255, 255, 255, 40))
        painter.drawRect(QRectF(transform.map(self._start), transform.map(self._end)).normalized())
