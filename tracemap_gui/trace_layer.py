"""Graphics over the photo: the project's 2D traces, auto-trace proposals, and a stage preview.

Each layer observes the session (or the auto-trace run) and keeps one graphics item in step; none of them
edits anything. Lines use cosmetic pens, so they keep their screen width at every zoom.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from PySide6.QtCore import QByteArray, QDataStream, QObject, QPointF, QRectF, Qt, QThreadPool, QTimer, Signal
from PySide6.QtGui import QColor, QPainter, QPainterPath, QPen
from PySide6.QtWidgets import QGraphicsItem, QGraphicsScene, QStyleOptionGraphicsItem, QWidget

from engine.plots import SET_COLORS
from engine.render import KIND_COLORS
from engine.traces import Trace2D, Trace3D
from tracemap_gui import delineation
from tracemap_gui.photo_view import Pyramid, TiledImageItem
from tracemap_gui.session import Session
from tracemap_gui.workers import Task

SOURCE_COLOURS = {"manual": QColor(255, 190, 0), "auto": QColor(0, 210, 255)}
KIND_QCOLOURS = {kind: QColor(*rgb) for kind, rgb in KIND_COLORS.items()}  # the 3D viewer's colour of each kind
# every colouring tells the kinds apart by the line's pattern too: a bedding trace is dashed whatever its colour
KIND_STYLES = {"fracture": Qt.PenStyle.SolidLine, "vein": Qt.PenStyle.DotLine, "fault": Qt.PenStyle.DashDotLine,
               "bedding": Qt.PenStyle.DashLine}
SELECTED = QColor(255, 40, 200)
UNLABELLED = QColor(160, 160, 160)
# Twelve colours told apart easily (Paul Tol's "muted" and "bright" schemes) for component labels.
COMPONENT_COLOURS = [QColor(c) for c in ("#ee6677", "#228833", "#4477aa", "#ccbb44", "#66ccee", "#aa3377",
                                         "#cc6677", "#117733", "#88ccee", "#ddcc77", "#882255", "#44aa99")]
SET_QCOLOURS = [QColor(c) for c in SET_COLORS]  # the 3D viewer's and the plots' colour of each set
PROPOSED, REJECTED = QColor(120, 255, 120), QColor(150, 150, 150)
PLACED = QColor(255, 255, 255)
Z_STAGE, Z_TRACES, Z_PLACED, Z_PROPOSALS = 1, 2, 2.5, 3
READ_POLL_MS = 200  # how often the placed layer looks again while the session reads the 3D traces


def polyline_path(*polylines: np.ndarray) -> QPainterPath:
    """One path through the vertices of each polyline, built in one go: Qt reads it from its own stream
    format (big-endian count; type, x, y per element; two trailing ints), ten times faster than a lineTo
    per vertex."""
    points = np.concatenate(polylines)
    elements = np.empty(len(points), dtype=[("type", ">i4"), ("x", ">f8"), ("y", ">f8")])
    elements["type"] = 1  # LineToElement
    elements["type"][np.cumsum([0, *map(len, polylines[:-1])])] = 0  # MoveToElement: each polyline's start
    elements["x"], elements["y"] = points[:, 0], points[:, 1]
    data = QByteArray(np.array([len(points)], ">i4").tobytes() + elements.tobytes() + bytes(8))
    path = QPainterPath()
    QDataStream(data) >> path
    return path


def cosmetic_pen(colour: QColor, width: float, style: Qt.PenStyle = Qt.PenStyle.SolidLine) -> QPen:
    pen = QPen(colour, width, style)
    pen.setCosmetic(True)
    # Round caps and joins stroke three times slower, on traces with a vertex every pixel.
    pen.setCapStyle(Qt.PenCapStyle.FlatCap)
    pen.setJoinStyle(Qt.PenJoinStyle.BevelJoin)
    return pen


class PolylineSetItem(QGraphicsItem):
    """Many polylines in one graphics item, each with its own pen.

    One paint call per frame instead of one per polyline (each costs a trip into Python). Zoomed out, the
    polylines of each pen are drawn as one path simplified to within half a screen pixel (Douglas–Peucker):
    traces carry a vertex every photo pixel, thousands of segments no screen can show. Zoomed in, only
    the polylines crossing the exposed area are drawn.
    """

    def __init__(self, parent: QGraphicsItem | None = None):
        super().__init__(parent)
        self.setFlag(QGraphicsItem.GraphicsItemFlag.ItemUsesExtendedStyleOption)  # for exposedRect
        self._polylines: dict[object, np.ndarray] = {}
        self._pens: dict[object, QPen] = {}
        self._boxes = np.empty((0, 4))  # x0, y0, x1, y1 of each polyline, in `_polylines` order
        self._paths: dict[object, QPainterPath] = {}  # each polyline at full detail
        self._simplified: dict[tuple[object, int], np.ndarray] = {}  # (key, level) → simplified polyline
        self._groups: dict[int, list[tuple[QPen, QPainterPath]]] = {}  # level → one path per pen
        self._bounds = QRectF()

    def keys(self) -> list:
        return list(self._polylines)

    def pen(self, key: object) -> QPen:
        return self._pens[key]

    def set_polylines(self, polylines: dict[object, np.ndarray], pens: dict[object, QPen]) -> None:
        """Replace the polylines; the simplified paths of unchanged ones are kept."""
        kept = {k for k, p in polylines.items() if self._polylines.get(k) is p}
        self._paths = {k: path for k, path in self._paths.items() if k in kept}
        self._simplified = {(k, level): p for (k, level), p in self._simplified.items() if k in kept}
        self._polylines = dict(polylines)
        ends = [np.concatenate([p.min(axis=0), p.max(axis=0)]) for p in self._polylines.values()]
        self._boxes = np.array(ends).reshape(-1, 4)
        self.prepareGeometryChange()
        self._bounds = QRectF() if not ends else QRectF(
            QPointF(*self._boxes[:, :2].min(axis=0)), QPointF(*self._boxes[:, 2:].max(axis=0))).adjusted(-1, -1, 1, 1)
        self.set_pens(pens)

    def set_pens(self, pens: dict[object, QPen]) -> None:
        self._pens = dict(pens)
        self._groups = {}
        self.update()

    def boundingRect(self) -> QRectF:
        return self._bounds

    def paint(self, painter: QPainter, option: QStyleOptionGraphicsItem, widget: QWidget | None = None) -> None:
        scale = option.levelOfDetailFromTransform(painter.worldTransform())
        level = max(int(math.floor(math.log2(1.0 / scale))), 0) if scale > 0 else 0
        if level:
            for pen, path in self._grouped(level):
                painter.setPen(pen)
                painter.drawPath(path)
            return
        r = option.exposedRect
        seen = ((self._boxes[:, 0] <= r.right()) & (self._boxes[:, 2] >= r.left())
                & (self._boxes[:, 1] <= r.bottom()) & (self._boxes[:, 3] >= r.top()))
        keys = [k for k, shown in zip(self._polylines, seen) if shown]
        for key in sorted(keys, key=lambda k: self._pens[k].widthF()):  # the widest (selected) on top
            if key not in self._paths:
                self._paths[key] = polyline_path(self._polylines[key])
            painter.setPen(self._pens[key])
            painter.drawPath(self._paths[key])

    def _simplify(self, key: object, level: int) -> np.ndarray:
        """Polyline `key` within 2^level / 2 photo pixels: at most half a screen pixel off at that zoom."""
        if (key, level) not in self._simplified:
            points = self._polylines[key].astype(np.float32).reshape(-1, 1, 2)
            self._simplified[key, level] = cv2.approxPolyDP(points, 0.5 * 2**level, False).reshape(-1, 2)
        return self._simplified[key, level]

    def _grouped(self, level: int) -> list[tuple[QPen, QPainterPath]]:
        """One path per pen at this level, the widest pens last."""
        if level not in self._groups:
            by_style: dict[tuple, tuple[QPen, list[np.ndarray]]] = {}
            for key, pen in self._pens.items():
                style = (pen.color().rgba(), pen.widthF(), pen.style())
                by_style.setdefault(style, (pen, []))[1].append(self._simplify(key, level))
            self._groups[level] = sorted(((pen, polyline_path(*lines)) for pen, lines in by_style.values()),
                                         key=lambda pen_path: pen_path[0].widthF())
        return self._groups[level]


class TraceLayer(QObject):
    """The 2D traces of the shown photo, coloured by source, by 2D component or by the set of the 3D trace
    they became (`sets_of`), selected ones highlighted.

    Component labels are worked out on a worker thread (the engine rasterises the photo's traces) after
    every change while colouring by component; until they arrive, new traces are grey. So are traces not
    extracted yet, or whose 3D trace has no set, when colouring by set.
    """

    def __init__(self, session: Session, scene: QGraphicsScene):
        super().__init__(scene)
        self._session = session
        self._image: str | None = None
        self._size = (0, 0)
        self.item = PolylineSetItem()
        self.item.setZValue(Z_TRACES)
        scene.addItem(self.item)
        self.colour_by = "source"
        self.components: dict[int, int] = {}
        self.sets: dict[int, int] = {}  # 2D trace id → set of its 3D trace, while colouring by set
        self._poll = QTimer(self, singleShot=True, interval=READ_POLL_MS)
        self._poll.timeout.connect(self._read_sets)
        self._labelling: Task | None = None
        self._pool = QThreadPool(self)
        self._pool.setMaxThreadCount(1)
        session.traces2d_changed.connect(self._changed)
        session.selection_changed.connect(self._restyle)
        session.traces3d_changed.connect(self._read_sets)

    def shown(self) -> list[int]:
        """Ids of the traces drawn."""
        return self.item.keys()

    def show(self, image: str | None, size: tuple[int, int] = (0, 0)) -> None:
        """Draw the traces of photo `image` of `size` (width, height)."""
        self._image, self._size, self.components = image, size, {}
        self._sync()

    def set_colour_by(self, mode: str) -> None:
        """"source" (manual or auto), "component" (2D connected component), "set" (of the 3D trace) or "kind"."""
        self.colour_by = mode
        self._label()
        self._read_sets()
        self._restyle()

    def _read_sets(self) -> None:
        if self.colour_by != "set" or not self._session.is_open:
            return
        if self._session.reading_traces3d:  # coloured once read, rather than waited for here
            self._poll.start()
            return
        self.sets = sets_of(self._session.traces3d())
        self._restyle()

    def _changed(self, image: str) -> None:
        if image == self._image:
            self._sync()

    def _traces(self) -> list[Trace2D]:
        return [] if self._image is None else self._session.traces2d(self._image)

    def _sync(self) -> None:
        traces = self._traces()
        self.item.set_polylines({t.id: t.polyline for t in traces}, self._pens(traces))
        self._label()

    def _pens(self, traces: list[Trace2D]) -> dict[int, QPen]:
        selected = self._session.selected2d
        return {t.id: cosmetic_pen(SELECTED, 3.5, KIND_STYLES[t.kind]) if t.id in selected
                else cosmetic_pen(self._colour(t), 2.0, KIND_STYLES[t.kind]) for t in traces}

    def _restyle(self) -> None:
        self.item.set_pens(self._pens(self._traces()))

    def _label(self) -> None:
        if self.colour_by != "component" or self._image is None:
            return
        if self._labelling is not None:
            self._labelling.cancel()
        task = Task("2D components", delineation.components, list(self._traces()), self._size)
        task.signals.done.connect(lambda labels: self._labelled(task, labels))
        self._labelling = task
        self._pool.start(task.run)

    def _labelled(self, task: Task, labels: dict[int, int]) -> None:
        if task is self._labelling:
            self._labelling = None
            self.components = labels
            self._restyle()

    def _colour(self, trace: Trace2D) -> QColor:
        if self.colour_by == "source":
            return SOURCE_COLOURS[trace.source]
        if self.colour_by == "kind":
            return KIND_QCOLOURS[trace.kind]
        if self.colour_by == "set":
            label = self.sets.get(trace.id, -1)
            return UNLABELLED if label < 0 else SET_QCOLOURS[label % len(SET_QCOLOURS)]
        label = self.components.get(trace.id, -1)
        return UNLABELLED if label < 0 else COMPONENT_COLOURS[label % len(COMPONENT_COLOURS)]


def sets_of(traces3d: Sequence[Trace3D]) -> dict[int, int]:
    """The set of the 3D trace each 2D trace became (by `Trace3D.parents`): where its pieces went to
    different 3D traces, the set holding most of their vertices."""
    votes: dict[int, dict[int, int]] = {}
    for t in traces3d:
        for parent in t.parents:
            tally = votes.setdefault(parent, {})
            tally[t.set_id] = tally.get(t.set_id, 0) + len(t.points)
    return {parent: max(tally, key=tally.get) for parent, tally in votes.items()}


class PlacedLayer(QObject):
    """Where the 3D traces lie on the shown photo: a thin white core along the pixels whose rays were placed
    on the mesh (`Trace3D.pixel_runs`). A 2D trace without it, or with gaps, shows what extraction left out:
    rays that missed the mesh, pixels on occluding edges, slivers (engine.extract)."""

    def __init__(self, session: Session, scene: QGraphicsScene):
        super().__init__(scene)
        self._session = session
        self._image: str | None = None
        self.visible = True
        self.runs: list[np.ndarray] = []  # the pixel polylines drawn
        self.item = PolylineSetItem()
        self.item.setZValue(Z_PLACED)
        scene.addItem(self.item)
        self._poll = QTimer(self, singleShot=True, interval=READ_POLL_MS)
        self._poll.timeout.connect(self._sync)
        session.traces3d_changed.connect(self._sync)

    def show(self, image: str | None) -> None:
        self._image = image
        self._sync()

    def set_visible(self, on: bool) -> None:
        self.visible = on
        self.item.setVisible(on)
        self._sync()

    def _sync(self) -> None:
        if self._image is None or not self.visible or not self._session.is_open:
            self.runs = []
        elif self._session.reading_traces3d:  # drawn once read, rather than waited for here
            self._poll.start()
            return
        else:
            self.runs = [run for t in self._session.traces3d() for run in t.pixel_runs(self._image)]
        pen = cosmetic_pen(PLACED, 1.0)
        self.item.set_polylines(dict(enumerate(self.runs)), dict.fromkeys(range(len(self.runs)), pen))


class ProposalLayer(QObject):
    """Auto-trace proposals not yet accepted: dashed, green, or in their kind's colour when the other photos
    gave them one (bedding, a vein, a fault); a rejected one is dotted grey."""

    changed = Signal()

    def __init__(self, scene: QGraphicsScene):
        super().__init__(scene)
        self.image: str | None = None
        self.traces: list[Trace2D] = []
        self.rejected: set[int] = set()  # indices into `traces`
        self.item = PolylineSetItem()
        self.item.setZValue(Z_PROPOSALS)
        scene.addItem(self.item)

    def set(self, image: str | None, traces: Sequence[Trace2D]) -> None:
        self.image, self.traces, self.rejected = image, list(traces), set()
        self.item.set_polylines({k: t.polyline for k, t in enumerate(self.traces)}, self._pens())
        self.changed.emit()

    def clear(self) -> None:
        self.set(None, [])

    def toggle(self, index: int) -> None:
        self.rejected ^= {index}
        self.item.set_pens(self._pens())
        self.changed.emit()

    def accepted(self) -> list[Trace2D]:
        return [t for k, t in enumerate(self.traces) if k not in self.rejected]

    def _pens(self) -> dict[int, QPen]:
        proposed = {kind: cosmetic_pen(PROPOSED if kind == "fracture" else colour, 2.0, Qt.PenStyle.DashLine)
                    for kind, colour in KIND_QCOLOURS.items()}
        rejected = cosmetic_pen(REJECTED, 1.5, Qt.PenStyle.DotLine)
        return {k: rejected if k in self.rejected else proposed[t.kind] for k, t in enumerate(self.traces)}


class StageOverlay:
    """One intermediate of auto-trace over the photo: an image (tiled like the photo) or polylines."""

    def __init__(self, scene: QGraphicsScene):
        self._scene = scene
        self._item: QGraphicsItem | None = None

    @property
    def shown(self) -> bool:
        return self._item is not None

    def show_image(self, pyramid: Pyramid, origin: tuple[float, float], opacity: float = 0.85) -> None:
        item = TiledImageItem(pyramid)
        item.setPos(*origin)
        item.setOpacity(opacity)
        self._show(item)

    def show_polylines(self, polylines: Sequence[np.ndarray]) -> None:
        item = PolylineSetItem()
        item.set_polylines(dict(enumerate(polylines)), {
            k: cosmetic_pen(COMPONENT_COLOURS[k % len(COMPONENT_COLOURS)], 1.5) for k in range(len(polylines))})
        self._show(item)

    def clear(self) -> None:
        if self._item is not None:
            self._scene.removeItem(self._item)
            self._item = None

    def _show(self, item: QGraphicsItem) -> None:
        self.clear()
        item.setZValue(Z_STAGE)
        self._scene.addItem(item)
        self._item = item
