"""The application in a process of its own: killed mid-session it loses nothing; on a real X display it shows
the photo and the traces (Xvfb; required in CI, skipped only where no X server can be started)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.gui.editor_process import DRAWN
from tests.gui.flows import stored_traces2d

ROOT = Path(__file__).resolve().parents[2]
HELPER = Path(__file__).with_name("editor_process.py")
MANUAL = (0, 190, 255)  # BGR of hand-drawn traces (trace_layer.SOURCE_COLOURS["manual"])


def start(project: Path, *args: str, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(HELPER), str(project), *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "QT_QPA_PLATFORM": "offscreen", **(env or {})})


def report(process: subprocess.Popen, timeout: float = 120) -> dict:
    """The helper's JSON line, once it has shown the photo and stored what it was asked to do."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if line.startswith("{"):
            return json.loads(line)
        if not line and process.poll() is not None:
            break
    process.kill()
    pytest.fail(f"the editor process did not get ready: {process.stderr.read()[-2000:]}")


def test_killing_the_program_loses_nothing_shown(qtbot, project_path):
    before = stored_traces2d(project_path, "photo_01")
    process = start(project_path, "--draw", "--zoom", "2", "--hold")
    shown = report(process)
    process.send_signal(signal.SIGKILL)  # no chance to save anything more
    process.wait(30)

    (new,) = set(stored_traces2d(project_path, "photo_01")) - set(before)
    assert np.allclose(stored_traces2d(project_path)[new][1], DRAWN, atol=1.0)
    from tracemap_gui.image_editor import ImageEditor
    from tracemap_gui.session import Session

    session = Session()
    session.open(project_path)  # the dead process's lock went with it
    editor = ImageEditor(session)
    qtbot.addWidget(editor)
    editor.show()
    qtbot.waitUntil(lambda: editor.view.pyramid is not None, timeout=10_000)
    try:
        assert editor.view.image == shown["photo"] and new in editor.traces.shown()
        assert editor.view.scale_factor == pytest.approx(shown["scale"])
        assert editor.view.tool.name == "Draw polyline"
    finally:
        session.close()


@pytest.fixture(scope="module")
def x_display():
    """A private Xvfb display; skips only when no X server can be started here."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (CI installs it: .ci/run)")
    number = next(n for n in range(90, 400) if not Path(f"/tmp/.X11-unix/X{n}").exists()
                  and not Path(f"/tmp/.X{n}-lock").exists())
    server = subprocess.Popen(["Xvfb", f":{number}", "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 15
    while not Path(f"/tmp/.X11-unix/X{number}").exists():
        if server.poll() is not None or time.monotonic() > deadline:
            server.kill()
            pytest.skip(f"Xvfb could not start: {server.stderr.read().decode()[-500:]}")
        time.sleep(0.05)
    yield f":{number}"
    server.terminate()
    server.wait(10)


def test_real_window_shows_photo_and_traces(x_display, project_path, tmp_path):
    shot = tmp_path / "editor.png"
    process = start(project_path, "--draw", "--screenshot", str(shot),
                    env={"QT_QPA_PLATFORM": "xcb", "DISPLAY": x_display})
    shown = report(process)
    assert process.wait(60) == 0, process.stderr.read()[-2000:]
    photo = cv2.imread(str(project_path.parent / "data" / "images" / f"{shown['photo']}.png"))
    for path in (shot, tmp_path / "editor-screen.png"):  # Qt's rendering, and what the X server shows
        screenshot = cv2.imread(str(path))
        assert screenshot is not None and screenshot.shape[0] > 400, path
        # the ~50 traces drawn over the photo take some of the correlation: 0.8999 under PySide6 6.12, whose
        # pens are a little wider; a photo not drawn, or drawn elsewhere, scores near 0
        assert photo_on_screen(screenshot, photo, shown) > 0.85, path
        manual = np.all(np.abs(screenshot.astype(int) - MANUAL) <= 30, axis=2)
        assert manual.sum() > 200, path  # the hand-drawn traces, the new one among them


def test_real_window_shows_the_mesh_and_traces_in_3d(x_display, project_path, tmp_path):
    """The 3D viewer on a real X display (OpenGL through the X server, not the offscreen render thread)."""
    shot = tmp_path / "viewer.png"
    process = start(project_path, "--viewer-screenshot", str(shot), env={"QT_QPA_PLATFORM": "xcb", "DISPLAY": x_display})
    shown = report(process)
    assert process.wait(90) == 0, process.stderr.read()[-2000:]
    assert len(shown["trace_colours"]) >= 2
    for path in (shot, tmp_path / "viewer-screen.png"):  # VTK's frame, and what the X server shows
        screenshot = cv2.imread(str(path))
        assert screenshot is not None and screenshot.shape[0] > 200, path
        rgb = screenshot[..., ::-1].astype(int)
        assert np.mean(rgb[..., 0] > rgb[..., 2] + 20) > 0.05, path  # the orange-brown rock
        for colour in shown["trace_colours"]:  # every set's colour drawn somewhere
            assert np.mean(np.all(np.abs(rgb - colour) <= 12, axis=-1)) > 2e-3, (path, colour)


def photo_on_screen(screenshot: np.ndarray, photo: np.ndarray, shown: dict) -> float:
    """Correlation of the screenshot, where the view shows the photo, with the photo scaled as shown."""
    scale = shown["scale"]
    scaled = cv2.resize(photo, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    x0, y0 = shown["viewport"]
    u0, v0 = shown["scene_origin"]  # photo pixel at the viewport's top-left corner
    dx, dy = round(-(u0 + 0.5) * scale), round(-(v0 + 0.5) * scale)  # where the photo starts in the viewport
    left, top = x0 + max(dx, 0), y0 + max(dy, 0)
    h = min(scaled.shape[0] - max(-dy, 0), screenshot.shape[0] - top)
    w = min(scaled.shape[1] - max(-dx, 0), screenshot.shape[1] - left)
    on_screen = cv2.cvtColor(screenshot[top:top + h, left:left + w], cv2.COLOR_BGR2GRAY).astype(np.float32)
    expected = cv2.cvtColor(scaled[max(-dy, 0):max(-dy, 0) + h, max(-dx, 0):max(-dx, 0) + w],
                            cv2.COLOR_BGR2GRAY).astype(np.float32)
    search = cv2.copyMakeBorder(on_screen, 3, 3, 3, 3, cv2.BORDER_REPLICATE)  # a pixel or two of rounding
    return float(cv2.matchTemplate(search, expected[3:-3, 3:-3], cv2.TM_CCOEFF_NORMED).max())
