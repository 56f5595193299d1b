"""The photo under the traces: a tiled image pyramid in a QGraphicsView that pans and zooms at 24 MP.

Scene coordinates are the engine's pixel coordinates: (0, 0) is the centre of the top-left pixel, so a
W × H photo covers [-0.5, W - 0.5] × [-0.5, H - 0.5]. The photo is read and its pyramid (successive half
sizes) built on a worker thread; painting converts only the visible tiles of the one level whose pixels are
no smaller than the screen's, and keeps recent tiles as pixmaps. A frame converts at most TILES_PER_FRAME
tiles (2–3 ms each): zooming into a new level would need 12–20 at once, 40–60 ms, so the rest are drawn from
a coarser cached tile, enlarged, and made in the frames that follow.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from PySide6.QtCore import QPoint, QPointF, QRectF, Qt, QThreadPool, QTimer, Signal
from PySide6.QtGui import (QColor, QImage, QKeyEvent, QMouseEvent, QPainter, QPixmap, QResizeEvent, QTransform,
                           QWheelEvent)
from PySide6.QtWidgets import QGraphicsItem, QGraphicsScene, QGraphicsView, QStyleOptionGraphicsItem, QWidget

from engine.errors import InputError
from tracemap_gui.workers import Task

if TYPE_CHECKING:
    from tracemap_gui.tools import Tool

TILE = 512  # pixels per tile side, at every level
TILE_CACHE_BYTES = 256 << 20
TILES_PER_FRAME = 4
REFINE_MS = 10  # after a frame that drew stand-ins, the next one comes this much later (input goes first)
ZOOM_STEP = 1.25
MAX_SCALE = 32.0  # screen pixels per photo pixel
PICK_PIXELS = 6  # how near (screen pixels) a click must be to pick a trace or vertex


def read_photo(path: Path) -> np.ndarray:
    """The photo's stored pixel grid (no EXIF rotation, as the cameras): 8-bit grey, BGR or BGRA."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise InputError(path, "cannot read the photo (unknown format or damaged file)")
    if image.dtype != np.uint8:  # 16-bit or float photos: stretch to 8 bits for display
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return image


class Pyramid:
    """An image (grey, BGR or BGRA uint8) and its successive half-size reductions down to one tile."""

    def __init__(self, image: np.ndarray):
        if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.ndim == 3 and image.shape[2] not in (3, 4):
            raise InputError(None, f"expected an 8-bit grey, BGR or BGRA image, got {image.dtype} {image.shape}")
        self.levels = [image]
        while max(self.levels[-1].shape[:2]) > TILE:
            h, w = self.levels[-1].shape[:2]
            self.levels.append(cv2.resize(self.levels[-1], ((w + 1) // 2, (h + 1) // 2),
                                          interpolation=cv2.INTER_AREA))

    @property
    def width(self) -> int:
        return self.levels[0].shape[1]

    @property
    def height(self) -> int:
        return self.levels[0].shape[0]

    def level_for(self, scale: float) -> int:
        """The coarsest level whose pixels are no larger than a screen pixel at `scale` (screen px per px)."""
        if scale >= 1.0:
            return 0
        return min(int(math.floor(math.log2(1.0 / scale))), len(self.levels) - 1)

    def factor(self, level: int) -> tuple[float, float]:
        """Photo pixels per level pixel, in x and y."""
        h, w = self.levels[level].shape[:2]
        return self.width / w, self.height / h

    def tile_grid(self, level: int) -> tuple[int, int]:
        h, w = self.levels[level].shape[:2]
        return math.ceil(h / TILE), math.ceil(w / TILE)

    def tile_pixmap(self, level: int, row: int, col: int) -> QPixmap:
        block = np.ascontiguousarray(self.levels[level][row * TILE:(row + 1) * TILE, col * TILE:(col + 1) * TILE])
        channels = 1 if block.ndim == 2 else block.shape[2]
        fmt = {1: QImage.Format.Format_Grayscale8, 3: QImage.Format.Format_BGR888,
               4: QImage.Format.Format_ARGB32}[channels]  # ARGB32 is B, G, R, A in memory (little-endian)
        image = QImage(block.data, block.shape[1], block.shape[0], block.strides[0], fmt)
        return QPixmap.fromImage(image)  # copies, so `block` may go


def load_pyramid(path: Path, *, progress: Callable[[float, str], None]) -> Pyramid:
    """Read a photo and build its pyramid (a worker-thread function)."""
    progress(0.0, f"reading {path.name}")
    image = read_photo(path)
    progress(0.7, "building zoom levels")
    return Pyramid(image)


class TiledImageItem(QGraphicsItem):
    """Paints the visible tiles of a pyramid at the level that suits the current zoom."""

    def __init__(self, pyramid: Pyramid, parent: QGraphicsItem | None = None):
        super().__init__(parent)
        self.pyramid = pyramid
        self.setFlag(QGraphicsItem.GraphicsItemFlag.ItemUsesExtendedStyleOption)  # for exposedRect
        self._tiles: OrderedDict[tuple[int, int, int], QPixmap] = OrderedDict()
        self._bytes = 0

    def boundingRect(self) -> QRectF:
        return QRectF(-0.5, -0.5, self.pyramid.width, self.pyramid.height)

    def paint(self, painter: QPainter, option: QStyleOptionGraphicsItem, widget: QWidget | None = None) -> None:
        scale = option.levelOfDetailFromTransform(painter.worldTransform())
        level = self.pyramid.level_for(scale)
        fx, fy = self.pyramid.factor(level)
        # Smoothing only helps when level pixels shrink on screen; zoomed in, users want to see pixels.
        painter.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform, scale * fx < 1.0)
        exposed = option.exposedRect
        rows, cols = self.pyramid.tile_grid(level)
        span = TILE * fx, TILE * fy
        c0, c1 = self._range(exposed.left(), exposed.right(), span[0], cols)
        r0, r1 = self._range(exposed.top(), exposed.bottom(), span[1], rows)
        budget, behind = TILES_PER_FRAME, False
        for row in range(r0, r1):
            for col in range(c0, c1):
                pixmap = self._cached(level, row, col)
                if pixmap is None and budget > 0:
                    pixmap, budget = self._made(level, row, col), budget - 1
                h, w = (min(TILE, n - k * TILE) for n, k in zip(self.pyramid.levels[level].shape[:2], (row, col)))
                target = QRectF(col * span[0] - 0.5, row * span[1] - 0.5, w * fx, h * fy)
                if pixmap is not None:
                    painter.drawPixmap(target, pixmap, QRectF(pixmap.rect()))
                elif stand_in := self._stand_in(level, target):
                    behind = True
                    painter.drawPixmap(target, *stand_in)
        if behind and (scene := self.scene()) is not None:  # the scene as context: no call after it is gone
            QTimer.singleShot(REFINE_MS, scene, self.update)

    @staticmethod
    def _range(lo: float, hi: float, span: float, count: int) -> tuple[int, int]:
        return max(0, int((lo + 0.5) // span)), min(count, int(math.ceil((hi + 0.5) / span)))

    def _cached(self, level: int, row: int, col: int) -> QPixmap | None:
        key = (level, row, col)
        pixmap = self._tiles.get(key)
        if pixmap is not None:
            self._tiles.move_to_end(key)
        return pixmap

    def _made(self, level: int, row: int, col: int) -> QPixmap:
        pixmap = self._tiles[level, row, col] = self.pyramid.tile_pixmap(level, row, col)
        self._bytes += pixmap.width() * pixmap.height() * 4
        while self._bytes > TILE_CACHE_BYTES:
            _, old = self._tiles.popitem(last=False)
            self._bytes -= old.width() * old.height() * 4
        return pixmap

    def _stand_in(self, level: int, target: QRectF) -> tuple[QPixmap, QRectF] | None:
        """The part of a coarser level's tile covering `target` (scene), from the cache or, at the coarsest
        level (one small tile), made: (pixmap, source rectangle)."""
        top = len(self.pyramid.levels) - 1
        for coarse in range(level + 1, top + 1):
            fx, fy = self.pyramid.factor(coarse)
            left, upper = (target.left() + 0.5) / fx, (target.top() + 0.5) / fy
            row, col = int(upper // TILE), int(left // TILE)
            pixmap = self._cached(coarse, row, col) or (self._made(coarse, row, col) if coarse == top else None)
            if pixmap is not None:
                source = QRectF(left - col * TILE, upper - row * TILE, target.width() / fx, target.height() / fy)
                return pixmap, source
        return None


class PhotoView(QGraphicsView):
    """A zoomable, pannable view of one photo; mouse and keys go to the active tool first.

    Wheel zooms about the cursor; the middle button, or Space with the left button, pans.
    """

    photo_loaded = Signal(str)  # the photo's pixels are in the scene
    photo_failed = Signal(str, object)  # image name, exception
    view_changed = Signal()  # zoom or pan
    cursor_moved = Signal(QPointF)  # photo pixel coordinates under the cursor
    hint = Signal(str)  # what the active tool expects next

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.setScene(QGraphicsScene(self))
        self.setTransformationAnchor(QGraphicsView.ViewportAnchor.AnchorUnderMouse)
        self.setResizeAnchor(QGraphicsView.ViewportAnchor.AnchorViewCenter)
        self.setViewportUpdateMode(QGraphicsView.ViewportUpdateMode.SmartViewportUpdate)
        self.setOptimizationFlag(QGraphicsView.OptimizationFlag.DontSavePainterState)
        self.setBackgroundBrush(QColor(48, 48, 48))
        self.setMouseTracking(True)
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.image: str | None = None
        self.pyramid: Pyramid | None = None
        self.tool: Tool | None = None
        self._photo_item: TiledImageItem | None = None
        self._pan_from: QPoint | None = None
        self._fitted_scale = 0.0
        self._space = False
        self._pool = QThreadPool(self)  # its own thread: a photo never queues behind long engine work
        self._pool.setMaxThreadCount(1)
        self._loading: Task | None = None
        self.horizontalScrollBar().valueChanged.connect(self.view_changed)
        self.verticalScrollBar().valueChanged.connect(self.view_changed)

    # -- the photo ------------------------------------------------------------------------------------

    def show_photo(self, image: str | None, size: tuple[int, int] = (0, 0), path: Path | None = None) -> None:
        """Show photo `image` of `size` (width, height); its pixels arrive from a worker (`photo_loaded`)."""
        if self._loading is not None:
            self._loading.cancel()
            self._loading = None
        if self._photo_item is not None:
            self.scene().removeItem(self._photo_item)
            self._photo_item = None
        self.image, self.pyramid = image, None
        self.setSceneRect(QRectF(-0.5, -0.5, *size) if image else QRectF())
        self.fit()
        if image is None or path is None:
            return
        task = Task(f"loading {image}", load_pyramid, path)
        task.signals.done.connect(lambda pyramid: self._loaded(task, pyramid))
        task.signals.failed.connect(lambda exc: self.photo_failed.emit(image, exc))
        self._loading = task
        self._pool.start(task.run)

    def _loaded(self, task: Task, pyramid: Pyramid) -> None:
        if task is not self._loading:  # another photo was asked for meanwhile
            return
        self._loading = None
        self.pyramid = pyramid
        self._photo_item = TiledImageItem(pyramid)
        self._photo_item.setZValue(-1)
        self.scene().addItem(self._photo_item)
        self.photo_loaded.emit(self.image)

    # -- zoom and pan ---------------------------------------------------------------------------------

    @property
    def scale_factor(self) -> float:
        """Screen pixels per photo pixel."""
        return self.transform().m11()

    def fit(self) -> None:
        """The whole photo in view; it stays fitted as the window resizes until the user zooms."""
        if not self.sceneRect().isEmpty():
            self.fitInView(self.sceneRect(), Qt.AspectRatioMode.KeepAspectRatio)
            self._fitted_scale = self.scale_factor

    def zoom(self, factor: float, anchor: QPointF | None = None) -> None:
        """Zoom by `factor` about `anchor` (photo pixels; default the view centre), within sensible limits."""
        rect = self.sceneRect()
        if rect.isEmpty():
            return
        lowest = 0.5 * min(self.viewport().width() / rect.width(), self.viewport().height() / rect.height())
        target = min(max(self.scale_factor * factor, lowest), MAX_SCALE)
        centre = self.mapToScene(self.viewport().rect().center())
        anchor = centre if anchor is None else anchor
        # Keep `anchor` fixed on screen: the new centre lies on the line from the anchor to the old centre.
        new_centre = anchor + (centre - anchor) * (self.scale_factor / target)
        self.setTransform(QTransform.fromScale(target, target))
        self.centerOn(new_centre)
        self.view_changed.emit()

    def view_state(self) -> dict:
        centre = self.mapToScene(self.viewport().rect().center())
        return {"scale": self.scale_factor, "centre": [centre.x(), centre.y()]}

    def restore_view_state(self, state: dict) -> None:
        scale = float(state["scale"])
        if not 0 < scale <= MAX_SCALE:
            return
        self.setTransform(QTransform.fromScale(scale, scale))
        self.centerOn(QPointF(*state["centre"]))

    def pick_radius(self) -> float:
        """PICK_PIXELS screen pixels in photo pixels."""
        return PICK_PIXELS / self.scale_factor

    def scene_pos(self, event: QMouseEvent) -> QPointF:
        return self.mapToScene(event.position().toPoint())

    # -- events: panning here, everything else to the tool ------------------------------------------------

    def set_tool(self, tool: Tool | None) -> None:
        if self.tool is not None:
            self.tool.deactivate()
        self.tool = tool
        if tool is not None:
            tool.activate()
            self.viewport().setCursor(tool.cursor)
            self.hint.emit(tool.hint)
        self.viewport().update()

    def resizeEvent(self, event: QResizeEvent) -> None:
        super().resizeEvent(event)
        if self.scale_factor == self._fitted_scale:  # not zoomed since it was fitted
            self.fit()

    def wheelEvent(self, event: QWheelEvent) -> None:
        steps = event.angleDelta().y() / 120
        if steps:
            self.zoom(ZOOM_STEP ** steps, self.mapToScene(event.position().toPoint()))
        event.accept()

    def mousePressEvent(self, event: QMouseEvent) -> None:
        left = event.button() == Qt.MouseButton.LeftButton
        if event.button() == Qt.MouseButton.MiddleButton or (left and self._space):
            self._pan_from = event.position().toPoint()
            self.viewport().setCursor(Qt.CursorShape.ClosedHandCursor)
        elif self.tool is not None and self.image is not None:
            self.tool.press(self.scene_pos(event), event)
        event.accept()

    def mouseMoveEvent(self, event: QMouseEvent) -> None:
        if self._pan_from is not None:
            delta = event.position().toPoint() - self._pan_from
            self._pan_from = event.position().toPoint()
            self.horizontalScrollBar().setValue(self.horizontalScrollBar().value() - delta.x())
            self.verticalScrollBar().setValue(self.verticalScrollBar().value() - delta.y())
        else:
            pos = self.scene_pos(event)
            self.cursor_moved.emit(pos)
            if self.tool is not None and self.image is not None:
                self.tool.move(pos, event)
        event.accept()

    def mouseReleaseEvent(self, event: QMouseEvent) -> None:
        if self._pan_from is not None:
            self._pan_from = None
            self.viewport().setCursor(self.tool.cursor if self.tool else Qt.CursorShape.ArrowCursor)
        elif self.tool is not None and self.image is not None:
            self.tool.release(self.scene_pos(event), event)
        event.accept()

    def mouseDoubleClickEvent(self, event: QMouseEvent) -> None:
        # Qt sends this instead of the second press: tools see the press, then the double-click.
        self.mousePressEvent(event)
        if self.tool is not None and self.image is not None and event.button() == Qt.MouseButton.LeftButton:
            self.tool.double_click(self.scene_pos(event), event)

    def keyPressEvent(self, event: QKeyEvent) -> None:
        if event.key() == Qt.Key.Key_Space and not event.isAutoRepeat():
            self._space = True
        elif self.tool is None or self.image is None or not self.tool.key(event):
            super().keyPressEvent(event)

    def keyReleaseEvent(self, event: QKeyEvent) -> None:
        if event.key() == Qt.Key.Key_Space and not event.isAutoRepeat():
            self._space = False
        super().keyReleaseEvent(event)

    def drawForeground(self, painter: QPainter, rect: QRectF) -> None:
        # The tool's transient graphics (rubber lines, handles) in screen pixels, so they keep their size.
        if self.tool is not None and self.image is not None:
            painter.save()
            painter.resetTransform()
            self.tool.paint(painter, self)
            painter.restore()
