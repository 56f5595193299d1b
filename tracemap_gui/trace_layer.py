"""Graphics over the photo: the project's 2D traces, auto-trace proposals, and a stage preview.

Each layer observes the session (or the auto-trace run) and keeps its graphics items in step; none of
them edits anything. Lines use cosmetic pens, so they keep their screen width at every zoom.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from PySide6.QtCore import QObject, QPointF, Qt, Signal
from PySide6.QtGui import QColor, QPainterPath, QPen
from PySide6.QtWidgets import QGraphicsItem, QGraphicsPathItem, QGraphicsScene

from engine.traces import Trace2D
from tracemap_gui.photo_view import Pyramid, TiledImageItem
from tracemap_gui.session import Session

SOURCE_COLOURS = {"manual": QColor(255, 190, 0), "auto": QColor(0, 210, 255)}
SELECTED = QColor(255, 40, 200)
UNLABELLED = QColor(160, 160, 160)
# Twelve colours told apart easily (Paul Tol's "muted" and "bright" schemes) for component labels.
COMPONENT_COLOURS = [QColor(c) for c in ("#ee6677", "#228833", "#4477aa", "#ccbb44", "#66ccee", "#aa3377",
                                         "#cc6677", "#117733", "#88ccee", "#ddcc77", "#882255", "#44aa99")]
PROPOSED, REJECTED = QColor(120, 255, 120), QColor(150, 150, 150)
Z_STAGE, Z_TRACES, Z_PROPOSALS = 1, 2, 3


def polyline_path(polyline: np.ndarray) -> QPainterPath:
    path = QPainterPath(QPointF(*polyline[0]))
    for x, y in polyline[1:]:
        path.lineTo(x, y)
    return path


def cosmetic_pen(colour: QColor, width: float, style: Qt.PenStyle = Qt.PenStyle.SolidLine) -> QPen:
    pen = QPen(colour, width, style)
    pen.setCosmetic(True)
    pen.setCapStyle(Qt.PenCapStyle.RoundCap)
    pen.setJoinStyle(Qt.PenJoinStyle.RoundJoin)
    return pen


def trace_colour(trace: Trace2D, colour_by: str) -> QColor:
    if colour_by == "component":
        return UNLABELLED if trace.component < 0 else COMPONENT_COLOURS[trace.component % len(COMPONENT_COLOURS)]
    return SOURCE_COLOURS[trace.source]


class TraceLayer(QObject):
    """The 2D traces of the shown photo, coloured by source or by 2D component, selected ones highlighted."""

    def __init__(self, session: Session, scene: QGraphicsScene):
        super().__init__(scene)
        self._session, self._scene = session, scene
        self._image: str | None = None
        self._items: dict[int, QGraphicsPathItem] = {}
        self._shown: dict[int, np.ndarray] = {}  # the polyline each item draws
        self.colour_by = "source"
        session.traces2d_changed.connect(self._changed)
        session.selection_changed.connect(self._restyle)

    @property
    def items(self) -> dict[int, QGraphicsPathItem]:
        return dict(self._items)

    def show(self, image: str | None) -> None:
        for item in self._items.values():
            self._scene.removeItem(item)
        self._items, self._shown = {}, {}
        self._image = image
        if image is not None:
            self._sync()

    def set_colour_by(self, mode: str) -> None:
        self.colour_by = mode
        self._restyle()

    def _changed(self, image: str) -> None:
        if image == self._image:
            self._sync()

    def _sync(self) -> None:
        traces = {t.id: t for t in self._session.traces2d(self._image)}
        for gone in set(self._items) - set(traces):
            self._scene.removeItem(self._items.pop(gone))
            del self._shown[gone]
        for id_, trace in traces.items():
            item = self._items.get(id_)
            if item is None:
                item = self._items[id_] = QGraphicsPathItem()
                item.setZValue(Z_TRACES)
                item.setData(0, id_)
                self._scene.addItem(item)
            if id_ not in self._shown or not np.array_equal(self._shown[id_], trace.polyline):
                item.setPath(polyline_path(trace.polyline))
                self._shown[id_] = trace.polyline
        self._restyle()

    def _restyle(self) -> None:
        if self._image is None:
            return
        selected = self._session.selected2d
        for trace in self._session.traces2d(self._image):
            chosen = trace.id in selected
            colour = SELECTED if chosen else trace_colour(trace, self.colour_by)
            self._items[trace.id].setPen(cosmetic_pen(colour, 3.5 if chosen else 2.0))


class ProposalLayer(QObject):
    """Auto-trace proposals not yet accepted: dashed; a rejected one is dotted grey."""

    changed = Signal()

    def __init__(self, scene: QGraphicsScene):
        super().__init__(scene)
        self._scene = scene
        self.image: str | None = None
        self.polylines: list[np.ndarray] = []
        self.rejected: set[int] = set()
        self._items: list[QGraphicsPathItem] = []

    def set(self, image: str | None, polylines: Sequence[np.ndarray]) -> None:
        for item in self._items:
            self._scene.removeItem(item)
        self.image, self.polylines, self.rejected = image, list(polylines), set()
        self._items = []
        for polyline in self.polylines:
            item = QGraphicsPathItem(polyline_path(polyline))
            item.setZValue(Z_PROPOSALS)
            self._scene.addItem(item)
            self._items.append(item)
        self._restyle()

    def clear(self) -> None:
        self.set(None, [])

    def toggle(self, index: int) -> None:
        self.rejected ^= {index}
        self._restyle()

    def accepted(self) -> list[np.ndarray]:
        return [p for k, p in enumerate(self.polylines) if k not in self.rejected]

    def _restyle(self) -> None:
        for k, item in enumerate(self._items):
            rejected = k in self.rejected
            item.setPen(cosmetic_pen(REJECTED if rejected else PROPOSED, 1.5 if rejected else 2.0,
                                     Qt.PenStyle.DotLine if rejected else Qt.PenStyle.DashLine))
        self.changed.emit()


class StageOverlay:
    """One intermediate of auto-trace over the photo: an image (tiled like the photo) or polylines."""

    def __init__(self, scene: QGraphicsScene):
        self._scene = scene
        self._items: list[QGraphicsItem] = []

    def show_image(self, pyramid: Pyramid, origin: tuple[float, float], opacity: float = 0.85) -> None:
        self.clear()
        item = TiledImageItem(pyramid)
        item.setPos(*origin)
        item.setOpacity(opacity)
        self._add(item)

    def show_polylines(self, polylines: Sequence[np.ndarray]) -> None:
        self.clear()
        for k, polyline in enumerate(polylines):
            item = QGraphicsPathItem(polyline_path(polyline))
            item.setPen(cosmetic_pen(COMPONENT_COLOURS[k % len(COMPONENT_COLOURS)], 1.5))
            self._add(item)

    def clear(self) -> None:
        for item in self._items:
            self._scene.removeItem(item)
        self._items = []

    def _add(self, item: QGraphicsItem) -> None:
        item.setZValue(Z_STAGE)
        self._scene.addItem(item)
        self._items.append(item)
