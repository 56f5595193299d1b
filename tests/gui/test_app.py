"""The application: `tracemap gui`, two windows on one session, File menu, window places, error dialogs."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from PySide6.QtCore import QSettings
from PySide6.QtWidgets import QMessageBox

from engine import cli
from engine.errors import TracemapError
from tracemap_gui import app
from tracemap_gui.app import Application, check_display, recent_projects, undo_memory_setting
from tracemap_gui.error_dialog import install_excepthook
from tracemap_gui.undo_memory import UNDO_MEMORY


def dialog_text(widget) -> str:
    box = widget.findChild(QMessageBox, "error-dialog")
    assert box is not None, "no error dialog"
    text = f"{box.text()}\n{box.informativeText()}"
    box.close()
    return text


@pytest.fixture
def gui(qtbot):
    application = Application()
    for window in application.windows:
        qtbot.addWidget(window)
    yield application
    application.session.close()


def test_two_windows_share_one_session_and_a_file_menu(gui, project_path, qtbot):
    assert gui.open(project_path)
    assert [type(w).__name__ for w in gui.windows] == ["ImageEditor", "Viewer3D"]
    for window in gui.windows:
        assert window.menuBar().actions()[0].text() == "&File"
        assert window.session is gui.session
    assert project_path.resolve() in recent_projects()


def test_the_viewer_shows_a_2d_trace_on_its_photo(gui, project_path, qtbot):
    gui.open(project_path)
    trace = gui.session.traces2d("photo_03")[0]
    gui.viewer.reveal2d.emit("photo_03", trace.id)
    assert gui.editor.view.image == "photo_03" and gui.session.selected2d == {trace.id}


def test_the_editor_has_the_viewer_look_from_its_photo(gui, project_path, qtbot):
    gui.open(project_path)
    gui.editor.show_photo("photo_03")
    qtbot.waitUntil(lambda: gui.viewer.mesh is not None, timeout=60_000)
    gui.editor.look3d_action.trigger()
    np.testing.assert_allclose(gui.viewer.view.plotter.camera.position, gui.session.cameras()["photo_03"].centre,
                               atol=1e-9)


def test_show_on_photo_finds_the_photo_of_a_merged_traces_parent(gui, project_path, qtbot):
    """A merged 3D trace lists its parents by id, not by photo: the one shown is on the photo that gave most
    of its vertices, and it is that photo's 2D trace that is selected."""
    gui.open(project_path)
    merged = next(t for t in gui.session.traces3d() if len(set(t.images)) > 1 and len(t.parents) > 1)
    photo = merged.images[int(np.argmax(np.bincount(merged.image_index)))]
    gui.session.select3d([merged.id])
    gui.viewer.reveal_action.trigger()
    (shown,) = gui.session.selected2d
    assert gui.editor.view.image == photo and shown in merged.parents
    assert shown in {t.id for t in gui.session.traces2d(photo)}


def test_window_places_are_restored_on_reopening(gui, project_path, qtbot):
    gui.open(project_path)
    gui.editor.show()
    gui.editor.resize(720, 520)
    gui.editor.move(30, 40)
    qtbot.wait(700)  # stored shortly after the window stops moving
    gui.session.close()
    gui.editor.resize(400, 300)
    gui.open(project_path)
    assert (gui.editor.width(), gui.editor.height()) == (720, 520)


def test_a_file_that_is_no_project_gives_a_dialog_not_a_traceback(gui, tmp_path):
    bogus = tmp_path / "notes.tracemap"
    bogus.write_text("hello")
    assert not gui.open(bogus)
    text = dialog_text(gui.editor)
    assert "not a tracemap project" in text and "Traceback" not in text
    assert not gui.session.is_open


def test_unexpected_errors_become_one_line_dialogs(qapp, monkeypatch):
    monkeypatch.setattr(sys, "excepthook", sys.excepthook)
    install_excepthook()
    try:
        raise KeyError("oops")
    except KeyError:
        sys.excepthook(*sys.exc_info())
    box = next(w for w in qapp.topLevelWidgets() if isinstance(w, QMessageBox) and w.isVisible())
    assert "internal error" in box.informativeText() and "tracemap-error.log" in box.informativeText()
    assert "Traceback" not in box.informativeText()
    box.close()


def test_main_headless_opens_and_closes(project_path, tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "excepthook", sys.excepthook)  # main installs its own
    assert app.main(str(project_path), headless=True) == 0
    assert app.main(str(tmp_path / "missing.tracemap"), headless=True) == 2


def test_no_display_is_a_message(monkeypatch):
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("QT_QPA_PLATFORM", "xcb")
    if sys.platform.startswith("linux"):
        with pytest.raises(TracemapError, match="no display"):
            check_display()


def test_the_gui_command(monkeypatch, project_path):
    opened = []
    monkeypatch.setattr(app, "main", lambda project=None, **_: opened.append(project) or 0)
    assert cli.main(["gui", str(project_path)]) == 0
    assert cli.main(["gui"]) == 0
    assert opened == [str(project_path), None]


def test_a_mesh_moved_away_is_said_by_the_viewer(gui, project_path, qtbot):
    (project_path.parent / "data" / "mesh.ply").rename(project_path.parent / "mesh-elsewhere.ply")
    gui.open(project_path)
    qtbot.waitUntil(lambda: gui.viewer.findChild(QMessageBox, "error-dialog") is not None, timeout=10_000)
    text = dialog_text(gui.viewer)
    assert "Loading the mesh" in text and "mesh.ply" in text
    assert gui.viewer.statusBar().currentMessage() != "loading the mesh…"


@pytest.mark.parametrize("value, budget", [(None, UNDO_MEMORY), (64, 64 * 2**20), ("0.5", 2**19), ("lots", UNDO_MEMORY),
                                           (-1, UNDO_MEMORY), ("inf", UNDO_MEMORY)])
def test_the_undo_memory_budget_is_a_user_setting(value, budget):
    settings = QSettings()
    if value is None:
        settings.remove("undo_memory_mb")
    else:
        settings.setValue("undo_memory_mb", value)
    try:
        assert undo_memory_setting() == budget
    finally:
        settings.remove("undo_memory_mb")


def test_file_menu_sets_the_undo_memory_at_once_and_for_later_sessions(gui, project_path, monkeypatch):
    def answer(dialog):
        dialog.megabytes.setValue(64)
        dialog.accept()
        return True

    monkeypatch.setattr(app.UndoMemoryDialog, "exec", answer)
    gui.open(project_path)
    (action,) = [a for a in gui.editor.file_menu.actions() if a.text() == "&Undo memory…"]
    try:
        action.trigger()
        assert gui.session.undo_memory.budget == 64 * 2**20 and undo_memory_setting() == 64 * 2**20
    finally:
        QSettings().remove("undo_memory_mb")


def test_the_undo_memory_dialog_shows_the_budget_in_mb(qapp):
    dialog = app.UndoMemoryDialog(3 * 2**20)
    assert dialog.megabytes.value() == 3 and dialog.parse() == 3 * 2**20
