"""A widget showing a pyvista scene, with or without an OpenGL widget.

Where Qt can make OpenGL widgets (a real display) the scene lives in a pyvistaqt `QtInteractor`. Under
`QT_QPA_PLATFORM=offscreen` there is none, so VTK renders offscreen (EGL/OSMesa), on a thread of its own
(`render_thread`: without a GPU a frame takes seconds), and the widget shows the frames as images, turning
mouse drags into camera moves itself: the same window then runs headless, in tests and on servers. Either
way the view reports plain clicks (not drags) as `clicked(x, y, additive)` in VTK display coordinates
(origin bottom-left), for picking.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from PySide6.QtCore import QEvent, QObject, QPoint, QRect, Qt, QTimer, Signal
from PySide6.QtGui import QColor, QGuiApplication, QImage, QMouseEvent, QPainter, QPen, QPolygon, QWheelEvent
from PySide6.QtWidgets import QRubberBand, QVBoxLayout, QWidget

from engine.render import max_texture_size
from tracemap_gui.error_dialog import show_error
from tracemap_gui.render_thread import RenderThread

CLICK_SLOP = 4  # pixels a press may move and still be a click
STILL_AFTER_MS = 300  # after the last wheel notch: the full-quality frame replaces the quick ones
ORBIT_DEG_PER_PX = 0.4
ZOOM_PER_NOTCH = 1.15


def has_opengl_widgets() -> bool:
    return QGuiApplication.platformName() not in ("offscreen", "minimal", "vnc")


class SceneView(QWidget):
    """The 3D canvas: `plotter` to draw into, `refresh()` after changing it, `clicked` for picks, and with
    `set_select_mode("box" or "lasso")` left drags draw a rubber band or a free outline, reported as
    `outlined(polygon, additive)` (an (N, 2) array of display coordinates, origin bottom-left) instead of
    turning the camera. `resized(width, height)` tells the scene's new size, for what is laid out in
    pixels (the legend)."""

    clicked = Signal(int, int, bool)
    outlined = Signal(object, bool)
    resized = Signal(int, int)

    def __init__(self, parent: QWidget | None = None, *, offscreen: bool | None = None):
        super().__init__(parent)
        offscreen = not has_opengl_widgets() if offscreen is None else offscreen
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        if offscreen:
            self._canvas = _ImageCanvas(self)
            self.plotter = self._canvas.plotter
        else:
            from pyvistaqt import QtInteractor

            self._canvas = QtInteractor(self)
            self.plotter = self._canvas
            self.plotter.iren.add_observer("LeftButtonPressEvent", self._gl_press)
            self.plotter.iren.add_observer("LeftButtonReleaseEvent", self._gl_release)
            self._press: tuple[int, int] | None = None
        layout.addWidget(self._canvas)
        self.offscreen = offscreen
        if offscreen:
            self._canvas.clicked.connect(self.clicked)
        self._box = _OutlineDrag(self)
        self._refresh_timer = QTimer(self, singleShot=True, interval=0)
        self._refresh_timer.timeout.connect(self._draw)

    def resizeEvent(self, event) -> None:
        super().resizeEvent(event)
        self.resized.emit(event.size().width(), event.size().height())

    def set_select_mode(self, mode: str | None) -> None:
        """Left drags outline a "box" or a "lasso" to select in, or turn the camera (None)."""
        self._canvas.removeEventFilter(self._box)
        self._box.shape = mode
        if mode is not None:
            self._canvas.installEventFilter(self._box)

    def refresh(self) -> None:
        """Draw the scene again soon (after actors or the camera changed): once per pass of the event loop
        however many changes asked for it, since a frame of a big mesh takes a second without a GPU."""
        self._refresh_timer.start()

    def _draw(self) -> None:
        if self.offscreen:
            self._canvas.redraw()
        else:
            self.plotter.render()

    def line_of_sight(self, x: int, y: int) -> tuple[np.ndarray, np.ndarray]:
        """The line of sight through display position (x, y) (origin bottom-left): its point on the near
        clipping plane and its direction (scene frame), for picking the mesh under a click."""
        renderer = self.plotter.renderer
        ends = []
        for depth in (0.0, 1.0):  # the near and the far clipping planes
            renderer.SetDisplayPoint(x, y, depth)
            renderer.DisplayToWorld()
            world = np.array(renderer.GetWorldPoint())
            ends.append(world[:3] / world[3])
        return ends[0], ends[1] - ends[0]

    def frame(self) -> np.ndarray:
        """The scene drawn now, as an (H, W, 3) uint8 array (waits for the frame)."""
        if self.offscreen:
            return self._canvas.frames.frame()
        self.plotter.render()
        return np.asarray(self.plotter.screenshot(None, return_img=True))[..., :3]

    def max_texture_size(self) -> int | None:
        """The longest texture side the view's OpenGL context takes (the render thread's, offscreen); None
        until a frame was drawn."""
        return self._canvas.frames.max_texture_size if self.offscreen else max_texture_size(self.plotter)

    def save_frame(self, path: str) -> None:
        """Save the scene drawn now as an image file (PNG, JPEG: by the suffix of `path`)."""
        rgb = np.ascontiguousarray(self.frame())
        h, w, _ = rgb.shape
        if not QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888).save(path):
            raise OSError(f"{path}: could not write the image (expected a .png or .jpg path)")

    def close_scene(self) -> None:
        self._refresh_timer.stop()
        if self.offscreen:
            self._canvas.frames.stop(wait=True)
        self.plotter.close()

    def _gl_press(self, interactor, _event) -> None:
        self._press = interactor.GetEventPosition()

    def _gl_release(self, interactor, _event) -> None:
        x, y = interactor.GetEventPosition()
        if self._press is not None and abs(x - self._press[0]) + abs(y - self._press[1]) <= CLICK_SLOP:
            self.clicked.emit(x, y, bool(interactor.GetShiftKey() or interactor.GetControlKey()))
        self._press = None


class _OutlineDrag(QObject):
    """Event filter on the canvas that turns left drags into a box or a lasso outline (and plain clicks into
    clicks), before the canvas or VTK can use them to turn the camera."""

    def __init__(self, view: SceneView):
        super().__init__(view)
        self._view = view
        self.shape: str | None = None  # "box" or "lasso"
        self._band: QRubberBand | None = None
        self._lasso: _LassoOverlay | None = None
        self._path: list[QPoint] = []

    def eventFilter(self, canvas: QObject, event: QEvent) -> bool:
        kind = event.type()
        if kind == QEvent.Type.MouseButtonPress and event.button() == Qt.MouseButton.LeftButton:
            self._path = [event.position().toPoint()]
            return True
        if kind == QEvent.Type.MouseMove and self._path:
            self._path.append(event.position().toPoint())
            self._show(canvas)
            return True
        if kind == QEvent.Type.MouseButtonRelease and self._path:
            self._path.append(event.position().toPoint())
            self._released(canvas, event)
            return True
        return False

    def _show(self, canvas: QWidget) -> None:
        if self.shape == "box":
            self._band = self._band or QRubberBand(QRubberBand.Shape.Rectangle, canvas)
            self._band.setGeometry(QRect(self._path[0], self._path[-1]).normalized())
            self._band.show()
        else:
            self._lasso = self._lasso or _LassoOverlay(canvas)
            self._lasso.show_path(self._path)

    def _released(self, canvas: QWidget, event: QMouseEvent) -> None:
        additive = bool(event.modifiers() & (Qt.KeyboardModifier.ShiftModifier | Qt.KeyboardModifier.ControlModifier))
        path, h = self._path, canvas.height()
        self._path = []
        for overlay in (self._band, self._lasso):
            if overlay is not None:
                overlay.hide()
        press, pos = path[0], path[-1]
        if max((p - press).manhattanLength() for p in path) <= CLICK_SLOP:
            self._view.clicked.emit(pos.x(), h - 1 - pos.y(), additive)
            return
        if self.shape == "box":
            path = [press, QPoint(pos.x(), press.y()), pos, QPoint(press.x(), pos.y())]
        # VTK display coordinates start at the bottom-left corner
        self._view.outlined.emit(np.array([(p.x(), h - 1 - p.y()) for p in path], dtype=float), additive)


class _LassoOverlay(QWidget):
    """The lasso's outline drawn over the canvas; it lets the mouse through."""

    def __init__(self, canvas: QWidget):
        super().__init__(canvas)
        self.setAttribute(Qt.WidgetAttribute.WA_TransparentForMouseEvents)
        self._polygon = QPolygon()

    def show_path(self, path: list[QPoint]) -> None:
        self.setGeometry(self.parentWidget().rect())
        self._polygon = QPolygon(path)
        self.show()
        self.update()

    def paintEvent(self, _event) -> None:
        painter = QPainter(self)
        painter.setPen(QPen(QColor(255, 0, 255), 2, Qt.PenStyle.DashLine))
        painter.drawPolygon(self._polygon)


class _ImageCanvas(QWidget):
    """Offscreen VTK frames painted as images; drags orbit (left) and pan (right/middle), the wheel zooms.

    The plotter is the scene the tools edit and pick in; it is never rendered here: `frames` draws copies of
    it on the render thread and the canvas paints the latest picture when it arrives.
    """

    clicked = Signal(int, int, bool)

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self.setMinimumSize(160, 120)
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.plotter = pv.Plotter(off_screen=True, window_size=[640, 480])
        self.frames = RenderThread(self.plotter)
        self.frames.signals.drawn.connect(self._show)
        self.frames.signals.failed.connect(lambda exc: show_error(self, "Drawing the 3D view", exc))
        frames = self.frames  # not self: the slot runs after the canvas is gone
        self.destroyed.connect(lambda: frames.stop())
        self._still = QTimer(self, singleShot=True, interval=STILL_AFTER_MS)
        self._still.timeout.connect(self.redraw)
        self._image = QImage()
        self._press: QPoint | None = None
        self._last: QPoint | None = None
        self._dragged = False

    def redraw(self, interactive: bool = False) -> None:
        """Ask the render thread for a frame of the scene as it is now, at the canvas's size (`interactive`:
        a quick one while the camera moves)."""
        if self.plotter.render_window is None:  # closed (`close_scene`)
            return
        # the plotter's size, not only the frame's: picks map display coordinates through it
        self.plotter.render_window.SetSize(max(self.width(), 16), max(self.height(), 16))
        self.frames.request(interactive)

    def _show(self, rgb: np.ndarray) -> None:
        h, w, _ = rgb.shape
        self._image = QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888).copy()
        self.update()

    def paintEvent(self, _event) -> None:
        painter = QPainter(self)
        painter.drawImage(self.rect(), self._image)

    def resizeEvent(self, _event) -> None:
        self.redraw()

    def mousePressEvent(self, event: QMouseEvent) -> None:
        self._press = self._last = event.position().toPoint()
        self._dragged = False

    def mouseMoveEvent(self, event: QMouseEvent) -> None:
        if self._last is None:
            return
        pos = event.position().toPoint()
        delta = pos - self._last
        self._last = pos
        if (pos - self._press).manhattanLength() > CLICK_SLOP:
            self._dragged = True
        if not self._dragged:
            return
        if event.buttons() & Qt.MouseButton.LeftButton and not event.modifiers() & Qt.KeyboardModifier.ShiftModifier:
            self._orbit(delta.x(), delta.y())
        else:
            self._pan(delta.x(), delta.y())
        self.redraw(interactive=True)

    def mouseReleaseEvent(self, event: QMouseEvent) -> None:
        if self._press is not None and not self._dragged and event.button() == Qt.MouseButton.LeftButton:
            additive = bool(event.modifiers() & (Qt.KeyboardModifier.ShiftModifier
                                                 | Qt.KeyboardModifier.ControlModifier))
            pos = event.position().toPoint()
            # VTK display coordinates start at the bottom-left corner
            self.clicked.emit(pos.x(), self.height() - 1 - pos.y(), additive)
        elif self._dragged:
            self.redraw()  # the still frame where the drag ended
        self._press = self._last = None

    def wheelEvent(self, event: QWheelEvent) -> None:
        notches = event.angleDelta().y() / 120.0
        self.plotter.camera.Zoom(ZOOM_PER_NOTCH ** notches)
        self.redraw(interactive=True)
        self._still.start()

    def _orbit(self, dx: int, dy: int) -> None:
        camera = self.plotter.camera
        camera.Azimuth(-dx * ORBIT_DEG_PER_PX)
        camera.Elevation(dy * ORBIT_DEG_PER_PX)
        camera.OrthogonalizeViewUp()
        self.plotter.renderer.ResetCameraClippingRange()

    def _pan(self, dx: int, dy: int) -> None:
        camera = self.plotter.camera
        position, focal = np.array(camera.position), np.array(camera.focal_point)
        distance = np.linalg.norm(position - focal)
        scale = 2 * distance * np.tan(np.radians(camera.view_angle) / 2) / max(self.height(), 1)
        up = np.array(camera.up)
        right = np.cross(focal - position, up)
        right /= np.linalg.norm(right)
        shift = (-dx * right + dy * up) * scale
        camera.position = tuple(position + shift)
        camera.focal_point = tuple(focal + shift)


def display_coordinates(renderer, points: np.ndarray) -> np.ndarray:
    """VTK display coordinates (N, 2), origin bottom-left, of world points (N, 3); NaN behind the camera.

    One projection matrix for all points: `renderer.WorldToDisplay` per point takes seconds on long traces.
    """
    width, height = renderer.GetSize()
    matrix = renderer.GetActiveCamera().GetCompositeProjectionTransformMatrix(renderer.GetTiledAspectRatio(),
                                                                            -1, 1)
    m = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
    clip = np.column_stack([points, np.ones(len(points))]) @ m.T
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = np.where(clip[:, 3:4] > 0, clip[:, :2] / clip[:, 3:4], np.nan)
    return np.array(renderer.GetOrigin()) + (ndc + 1.0) * 0.5 * np.array([width, height])


def nearest_point(renderer, points: np.ndarray, x: float, y: float, radius: float) -> int | None:
    """Index of the point (N, 3) drawn nearest display position (x, y), or None if none is within `radius` px."""
    shown = display_coordinates(renderer, points)
    distance = np.hypot(shown[:, 0] - x, shown[:, 1] - y)
    if not np.isfinite(distance).any():
        return None
    k = int(np.nanargmin(distance))
    return k if distance[k] <= radius else None
