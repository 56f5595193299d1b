"""The render thread shares nothing the GUI thread changes: 2D props are drawn from copies, and switching maps
while frames are drawn, then closing the view, never crashes the process.

    python tests/gui/test_render_thread.py [RUNS] [SWITCHES]

runs the stress program RUNS times (default 20, SWITCHES 150), each in a process of its own, and prints
the exit codes: the old code, which drew the GUI's own scalar bar, crashed (SIGSEGV) in 5 of 10 runs.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv

ROOT = Path(__file__).resolve().parents[2]
SIZE = (400, 300)
COLOURMAPS = ("viridis", "plasma", "magma", "cividis")
STRESS_SWITCHES = 150  # maps shown per stress run: ~10 s


def mapped_plane(k: int) -> pv.PolyData:
    """A plane of ~80k faces with a map that differs with k, as the maps panel replaces the mesh."""
    plane = pv.Plane(i_resolution=200, j_resolution=200, i_size=4, j_size=2).triangulate()
    plane.point_data[f"p21:set{k % 3}"] = np.sin(plane.points[:, 0] * (k % 5 + 1))
    return plane


def show_map(plotter: pv.Plotter, k: int) -> None:
    """What the viewer does when another map, colour range or radius is chosen: the mesh and its scalar bar
    replaced (pyvista then removes the old bar and makes a new one), sometimes a text, sometimes no bar."""
    plane = mapped_plane(k)
    name = plane.array_names[0]
    if k % 7 == 6:
        plotter.add_mesh(plane, color="tan", name="mesh", render=False)
    else:
        plotter.add_mesh(plane, scalars=name, cmap=COLOURMAPS[k % 4], clim=(-1 + 0.1 * (k % 3), 1.0),
                         scalar_bar_args={"title": f"P21 {name} (1/m)", "render": False}, name="mesh",
                         render=False)
    if k % 5 == 0:
        plotter.add_text(f"radius {k}", name="note", render=False)
    for bar in plotter.scalar_bars.values():  # the range and title change in place too
        bar.GetLookupTable().SetRange(-1.0, 1.0 + k % 4)
        bar.SetTitle(f"P21 {k}")


def stress(switches: int) -> None:
    """Switch maps `switches` times while asking for frames, then close the view with frames in flight and
    let the process end (the render thread's exit path)."""
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    import tracemap_gui  # noqa: F401 - its PySide6 work-round first
    from tracemap_gui.scene_view import SceneView

    app = QApplication.instance() or QApplication([])
    view = SceneView(offscreen=True)
    view.resize(*SIZE)
    view.show()
    for k in range(switches):
        show_map(view.plotter, k)
        view.plotter.camera.Azimuth(7)
        view._canvas.redraw(interactive=k % 2 == 1)
        app.processEvents()
    view.plotter.clear()  # the project closed
    view._canvas.redraw()
    view.deleteLater()  # the window closed: the canvas stops its thread without waiting
    app.processEvents()


def run_stress(runs: int, switches: int) -> list[int]:
    """Exit codes of `runs` stress processes."""
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": str(ROOT)}
    command = [sys.executable, __file__, "--child", str(switches)]
    return [subprocess.run(command, check=False, env=env, cwd=ROOT, capture_output=True, timeout=300).returncode
            for _ in range(runs)]


@pytest.fixture
def view(qtbot):
    from tests.gui.flows import shown_scene_view

    view = shown_scene_view(qtbot, SIZE)
    view.plotter.camera_position = [(0, 0, 6), (0, 0, 0), (0, 1, 0)]
    yield view
    view.close_scene()


def drawn_props(view):
    """The snapshot's 2D props (GUI prop → the copy the render thread draws)."""
    frames = view._canvas.frames
    snapshot = frames._snapshot(False)
    return {source.GetClassName(): (source, copy) for source, _, copy in frames._props.values()
            if any(copy is prop for prop, _ in snapshot.props)}


def test_2d_props_are_drawn_from_copies(view):
    show_map(view.plotter, 0)  # a scalar bar and a text
    props = drawn_props(view)
    bar, bar_copy = props["vtkScalarBarActor"]
    text, text_copy = props["vtkCornerAnnotation"]
    assert bar_copy is not bar and text_copy is not text
    for name in ("LookupTable", "TitleTextProperty", "LabelTextProperty", "Property"):
        assert getattr(bar_copy, f"Get{name}")() is not getattr(bar, f"Get{name}")()
    assert text_copy.GetTextProperty() is not text.GetTextProperty()
    assert bar_copy.GetTitle() == "P21 0" and bar_copy.GetLookupTable().GetRange() == (-1.0, 1.0)
    # unchanged: the same copy (its OpenGL resources stay); changed: a new copy, the GUI's change not in the old
    assert drawn_props(view)["vtkScalarBarActor"][1] is bar_copy
    bar.GetLookupTable().SetRange(0.0, 5.0)
    bar.GetTitleTextProperty().SetColor(1.0, 0.0, 0.0)
    new = drawn_props(view)["vtkScalarBarActor"][1]
    assert new is not bar_copy and new.GetLookupTable().GetRange() == (0.0, 5.0)
    assert new.GetTitleTextProperty().GetColor() == (1.0, 0.0, 0.0)
    assert bar_copy.GetLookupTable().GetRange() == (-1.0, 1.0)
    assert bar_copy.GetTitleTextProperty().GetColor() != (1.0, 0.0, 0.0)


def test_scalar_bar_shows_in_frames_and_goes(view):
    """The copied bar is drawn (dark title and labels at the right), and gone once the GUI removes it."""
    show_map(view.plotter, 1)
    with_bar = view.frame()
    view.plotter.remove_scalar_bar()
    without = view.frame()
    changed = np.abs(with_bar.astype(int) - without.astype(int)).sum(axis=2) > 60
    rows, cols = np.nonzero(changed)
    assert changed.sum() > 500  # the bar's colours and text
    assert rows.min() > SIZE[1] * 0.6 and cols.min() > SIZE[0] * 0.2  # pyvista's bar sits at the bottom
    assert not drawn_props(view)


def test_a_stopped_thread_is_waited_for_at_exit(view):
    """A canvas deleted stops its thread without waiting; the interpreter's exit must still wait for it (a
    thread drawing while Qt and the driver are torn down crashes), so it stays listed until it has ended."""
    from tracemap_gui import render_thread

    frames = view._canvas.frames
    show_map(view.plotter, 2)
    frames.request()
    frames.stop()
    assert frames in render_thread._LIVE or not frames._thread.is_alive()
    render_thread._stop_all()
    assert not frames._thread.is_alive() and frames not in render_thread._LIVE


def test_switching_maps_then_closing_never_crashes():
    """The stress program in a process of its own must end normally (a crash: a negative code). With the
    GUI's own scalar bar drawn, half such runs crashed (SIGSEGV); `python tests/gui/test_render_thread.py`
    runs it 20 times."""
    assert run_stress(runs=1, switches=STRESS_SWITCHES) == [0]


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        stress(int(sys.argv[2]))
    else:
        numbers = [int(arg) for arg in sys.argv[1:3]]
        codes = run_stress(*numbers, *(20, STRESS_SWITCHES)[len(numbers):])
        print("exit codes:", codes, "crashes:", sum(c != 0 for c in codes))
        sys.exit(any(codes))
