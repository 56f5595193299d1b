"""The application on a project in a process of its own, for tests that kill it or need a real X display.

    python tests/gui/editor_process.py PROJECT [--draw] [--zoom F] [--screenshot PNG] [--viewer-screenshot PNG]
                                       [--hold]

Draws DRAWN with the polyline tool (mouse clicks and Enter) and zooms if asked, waits until the view and
window settings are stored, saves screenshots (QWidget.grab, and the screen under the window; of the 3D
viewer, its drawn frame and the screen under it), then prints one JSON line with where the photo is shown
and the trace colours the 3D viewer uses. With --hold it keeps running until killed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from PySide6.QtCore import QPointF, Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication

from tracemap_gui.app import Application

DRAWN = [(100.0, 100.0), (220.0, 170.0), (330.0, 140.0)]
SETTLE = 1.0  # seconds: longer than the delays before the view and window places are stored


def wait(app: QApplication, condition, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("the photo did not appear")
        app.processEvents()
        time.sleep(0.01)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("project")
    parser.add_argument("--draw", action="store_true")
    parser.add_argument("--zoom", type=float)
    parser.add_argument("--screenshot")
    parser.add_argument("--viewer-screenshot")
    parser.add_argument("--hold", action="store_true")
    args = parser.parse_args()

    app = QApplication([sys.argv[0]])
    gui = Application()
    gui.show()
    if not gui.open(args.project):
        return 2
    editor, view = gui.editor, gui.editor.view
    editor.raise_()
    wait(app, lambda: view.pyramid is not None)
    if args.draw:
        editor.set_tool("Draw polyline")
        for x, y in DRAWN:
            QTest.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, Qt.KeyboardModifier.NoModifier,
                             view.mapFromScene(QPointF(x, y)))
        QTest.keyClick(view, Qt.Key.Key_Return)
    if args.zoom:
        view.zoom(args.zoom)
        view.centerOn(QPointF(*DRAWN[1]))
    end = time.monotonic() + SETTLE
    wait(app, lambda: time.monotonic() > end)
    if args.screenshot:
        editor.grab().save(args.screenshot)
        editor.screen().grabWindow(editor.winId()).save(args.screenshot.replace(".png", "-screen.png"))
    colours = viewer_screenshots(app, gui, args.viewer_screenshot) if args.viewer_screenshot else []
    corner = view.viewport().mapTo(editor, view.viewport().rect().topLeft())
    origin = view.mapToScene(view.viewport().rect().topLeft())
    print(json.dumps({"photo": view.image, "scale": view.scale_factor, "viewport": [corner.x(), corner.y()],
                      "scene_origin": [origin.x(), origin.y()], "traces": len(editor.traces.shown()),
                      "trace_colours": colours}), flush=True)
    if args.hold:
        return app.exec()
    gui.session.close()
    return 0


def viewer_screenshots(app: QApplication, gui: Application, path: str) -> list[list[int]]:
    """Show the 3D viewer, wait for its mesh and traces, save its frame and the screen under it; returns the
    RGB colours its traces are drawn in."""
    from engine.render import trace_colors

    viewer = gui.viewer
    viewer.show()
    viewer.raise_()
    wait(app, lambda: viewer.mesh is not None and not gui.session.reading_traces3d, timeout=60)
    end = time.monotonic() + SETTLE
    wait(app, lambda: time.monotonic() > end)
    viewer.view.save_frame(path)
    viewer.screen().grabWindow(viewer.winId()).save(path.replace(".png", "-screen.png"))
    used = {tuple(int(v) for v in c) for c in trace_colors(gui.session.traces3d(), viewer.style.color_by)}
    return [list(c) for c in sorted(used)]


if __name__ == "__main__":
    sys.exit(main())
