"""The offscreen 3D view: frames drawn on the render thread match what pyvista draws, follow every change of
the scene, and never hold up the GUI thread."""

import time

import numpy as np
import pytest
import pyvista as pv
from PySide6.QtCore import QPoint, QPointF, Qt, QTimer
from PySide6.QtGui import QImage, QWheelEvent

from tests.gui.flows import shown_scene_view

SIZE = (400, 300)


def build(plotter: pv.Plotter) -> None:
    """A scene with what the viewer draws: a mesh with colours, a mesh with a map and its scalar bar,
    lines drawn as tubes, points as spheres, and a textured mesh."""
    plotter.set_background("white")
    grid = pv.Plane(i_resolution=40, j_resolution=20, i_size=4, j_size=2).triangulate()
    grid.point_data["rgb"] = np.tile(np.array([200, 120, 60], np.uint8), (grid.n_points, 1))
    plotter.add_mesh(grid, scalars="rgb", rgb=True, name="mesh", render=False)
    mapped = pv.Plane(center=(0, 0, -0.01), i_size=4, j_size=2).translate((0, 2.2, 0))
    mapped.point_data["p21"] = mapped.points[:, 0]
    plotter.add_mesh(mapped, scalars="p21", cmap="viridis", name="map", render=False,
                     scalar_bar_args={"title": "P21 (1/m)", "render": False})
    line = pv.PolyData(np.array([[-1.5, -0.5, 0.05], [1.5, 0.5, 0.05]]), lines=[2, 0, 1])
    plotter.add_mesh(line, color="magenta", line_width=6, render_lines_as_tubes=True, name="traces", render=False)
    plotter.add_points(np.array([[1.5, -0.8, 0.05]]), color="blue", point_size=20, render_points_as_spheres=True,
                       name="nodes", render=False)
    photo = pv.Plane(center=(0, -2.2, 0), i_size=4, j_size=2)
    checker = (np.indices((64, 64)).sum(axis=0) // 8 % 2 * 255).astype(np.uint8)
    plotter.add_mesh(photo, texture=pv.Texture(np.dstack([checker] * 3)), name="drape", render=False)
    plotter.camera_position = [(0, 0, 9), (0, 0, 0), (0, 1, 0)]


@pytest.fixture
def view(qtbot):
    view = shown_scene_view(qtbot, SIZE)
    build(view.plotter)
    yield view
    view.close_scene()


def reference(size) -> np.ndarray:
    """The same scene as pyvista itself draws it on this thread."""
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        build(plotter)
        return plotter.screenshot(None, return_img=True)[..., :3].astype(int)
    finally:
        plotter.close()


def share(frame: np.ndarray, colour: tuple[bool, bool, bool]) -> float:
    """Share of pixels of a shaded colour: each channel bright (True) or dark (False)."""
    return float(np.mean(np.all((frame > 150) == colour, axis=2) & np.all((frame < 100) == np.logical_not(colour),
                                                                            axis=2)))


MAGENTA, GREEN = (True, False, True), (False, True, False)


def differing(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels whose colour differs by more than 40 in a channel."""
    return float(np.mean(np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 40))


def test_frames_match_what_pyvista_draws(view):
    frame = view.frame()
    assert frame.shape == (view._canvas.height(), view._canvas.width(), 3)
    assert differing(frame, reference(frame.shape[1::-1])) < 0.01
    assert share(frame, MAGENTA) > 0.003  # the tube is there


def test_frames_follow_changes_of_the_scene(view):
    before = view.frame()
    rows, cols = np.nonzero(np.all((before > 150) == MAGENTA, axis=2) & (before[..., 1] < 100))
    tube = np.s_[rows.min():rows.max() + 1, cols.min():cols.max() + 1]  # the brown plane's part with the tube
    view.plotter.actors["traces"].GetProperty().SetColor(0.0, 1.0, 0.0)
    after = view.frame()
    assert share(before[tube], GREEN) == 0.0
    assert share(after[tube], GREEN) == pytest.approx(share(before[tube], MAGENTA), rel=0.1)
    assert share(after[tube], MAGENTA) == 0.0
    view.plotter.remove_actor("traces", render=False)
    assert share(view.frame()[tube], GREEN) == 0.0
    view.plotter.camera.Azimuth(40)
    assert differing(view.frame(), after) > 0.05


def test_unchanged_actors_keep_their_copies(view):
    view.frame()
    mirrors = {key: (m.actor, m.state) for key, m in view._canvas.frames._mirrors.items()}
    view.plotter.camera.Zoom(1.3)
    view.frame()
    assert {key: (m.actor, m.state) for key, m in view._canvas.frames._mirrors.items()} == mirrors
    view.plotter.actors["mesh"].GetProperty().SetOpacity(0.5)
    view.frame()
    changed = view._canvas.frames._mirrors[id(view.plotter.actors["mesh"])]
    assert changed.state is not mirrors[id(view.plotter.actors["mesh"])][1]


def test_the_gui_thread_runs_while_a_frame_is_drawn(view, qtbot):
    """A frame of a big mesh takes a second without a GPU; the event loop must keep turning meanwhile."""
    big = pv.Plane(i_size=8, j_size=8, i_resolution=500, j_resolution=500).triangulate()  # 500k faces
    big.point_data["height"] = np.random.default_rng(0).random(big.n_points)
    for layer in range(4):  # 2M faces in all, one behind the other
        actor = view.plotter.add_mesh(big, scalars="height", name=f"big{layer}", render=False,
                                      show_scalar_bar=False)
        actor.SetPosition(0.0, 0.0, -0.1 * layer)
    view.resize(1600, 1200)  # the whole view full of small triangles, multisampled
    qtbot.waitUntil(lambda: view._canvas.width() >= 1500)
    view.frame()  # the frames asked for so far are drawn …
    qtbot.wait(50)  # … and shown
    view.plotter.camera.Azimuth(5)
    beats = []
    heart = QTimer(interval=10)
    heart.timeout.connect(lambda: beats.append(time.perf_counter()))
    heart.start()
    shown = []
    view._canvas.frames.signals.drawn.connect(lambda image: shown.append(time.perf_counter()))
    start = time.perf_counter()
    view.refresh()
    qtbot.waitUntil(lambda: bool(shown), timeout=60_000)
    heart.stop()
    took = shown[0] - start
    gaps = np.diff([start, *[b for b in beats if b < shown[0]]])
    assert took > 0.1  # a real frame of millions of faces …
    assert gaps.max() < max(0.1, took / 3)  # … while the heartbeat kept ticking


def test_drags_draw_quick_frames_then_a_still_one(view, qtbot, monkeypatch):
    asked = []
    request = view._canvas.frames.request
    monkeypatch.setattr(view._canvas.frames, "request", lambda interactive=False: asked.append(interactive)
                        or request(interactive))
    canvas = view._canvas
    camera = view.plotter.camera_position
    qtbot.mousePress(canvas, Qt.MouseButton.LeftButton, pos=QPoint(100, 100))
    for x in (120, 140, 160):
        qtbot.mouseMove(canvas, QPoint(x, 100))
    qtbot.mouseRelease(canvas, Qt.MouseButton.LeftButton, pos=QPoint(160, 100))
    assert view.plotter.camera_position != camera  # the drag orbited
    assert asked[-1] is False and asked[:-1] and all(asked[:-1])
    # quick frames are drawn without multisampling, the still ones with the plotter's
    assert view._canvas.frames._snapshot(True).samples == 0
    assert view._canvas.frames._snapshot(False).samples == view.plotter.render_window.GetMultiSamples() > 0
    asked.clear()
    qtbot.wait(50)
    canvas.wheelEvent(_wheel(canvas))
    assert asked == [True]
    qtbot.waitUntil(lambda: asked == [True, False], timeout=2000)  # the still frame after the wheel


def test_saved_frame_is_the_picture(view, tmp_path):
    view.save_frame(str(tmp_path / "shot.png"))
    saved = QImage(str(tmp_path / "shot.png")).convertToFormat(QImage.Format.Format_RGB888)
    pixels = np.frombuffer(saved.constBits(), np.uint8).reshape(saved.height(), saved.bytesPerLine())
    pixels = pixels[:, :3 * saved.width()].reshape(saved.height(), saved.width(), 3)
    assert differing(pixels, view.frame()) == 0.0
    with pytest.raises(OSError, match="shot.xyz"):
        view.save_frame(str(tmp_path / "shot.xyz"))


def _wheel(canvas) -> QWheelEvent:
    """One notch of the mouse wheel over the middle of the canvas."""
    centre = QPointF(canvas.width() / 2, canvas.height() / 2)
    return QWheelEvent(centre, canvas.mapToGlobal(centre), QPoint(0, 0), QPoint(0, 120), Qt.MouseButton.NoButton,
                       Qt.KeyboardModifier.NoModifier, Qt.ScrollPhase.NoScrollPhase, False)
