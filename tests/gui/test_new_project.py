"""File → New project…: the form's checks, the project made on a worker and opened, and failures said."""

from __future__ import annotations

import pytest
from PySide6.QtGui import QKeySequence

from tests.gui.test_app import dialog_text, gui  # noqa: F401 - the application fixture
from tracemap_gui.app import recent_projects
from tracemap_gui.image_editor import NO_PROJECT
from tracemap_gui.new_project import NewProject, NewProjectDialog


def fill(dialog: NewProjectDialog, **fields: str) -> None:
    for name, text in fields.items():
        getattr(dialog, name).edit.setText(str(text))


@pytest.fixture
def demo_data(quick_demo):
    return quick_demo / "data"


def test_the_form_names_what_is_missing_or_wrong(qtbot, demo_data, tmp_path):
    dialog = NewProjectDialog()
    qtbot.addWidget(dialog)
    dialog.accept()
    assert dialog.values is None and "Mesh: expected a mesh file" in dialog.message.text()
    fill(dialog, mesh=tmp_path / "nowhere.ply")
    dialog.accept()
    assert "nowhere.ply: Mesh: no such file" in dialog.message.text()
    fill(dialog, mesh=demo_data / "mesh.ply")
    dialog.mesh.edit.editingFinished.emit()  # the project is named after the mesh until named otherwise
    assert dialog.project.text == str(demo_data / "mesh.tracemap")
    dialog.accept()
    assert "Cameras: expected a camera file or a COLMAP model folder" in dialog.message.text()
    (tmp_path / "notes.txt").write_text("not cameras")
    fill(dialog, cameras=tmp_path / "notes.txt")
    dialog.accept()
    assert "notes.txt: unrecognised camera file; expected" in dialog.message.text()
    fill(dialog, cameras=demo_data / "cameras.json", images=tmp_path / "no photos", project=tmp_path / "site")
    dialog.accept()
    assert "Photos folder: no such folder" in dialog.message.text()
    fill(dialog, images=demo_data / "images")
    dialog.width_box.setValue(640)
    dialog.accept()
    assert "Photo size: expected both the width and the height, or neither" in dialog.message.text()
    dialog.height_box.setValue(480)
    dialog.accept()
    assert "Photo size: a tracemap file gives the size of every photo" in dialog.message.text()
    dialog.width_box.setValue(0)
    dialog.height_box.setValue(0)
    (tmp_path / "taken.tracemap").write_text("")
    fill(dialog, project=tmp_path / "taken.tracemap")
    dialog.accept()
    assert "a file of that name exists" in dialog.message.text()
    fill(dialog, project=tmp_path / "site")
    dialog.accept()
    assert dialog.result() == NewProjectDialog.DialogCode.Accepted
    assert dialog.values == NewProject(tmp_path / "site.tracemap", demo_data / "mesh.ply", demo_data / "cameras.json",
                                       demo_data / "images")


def test_a_new_project_is_made_and_opened(gui, qtbot, demo_data, tmp_path):  # noqa: F811
    actions = {a.text(): a for a in gui.editor.file_menu.actions()}
    assert actions["&New project…"].shortcut() == QKeySequence(QKeySequence.StandardKey.New)
    assert gui.editor.hint.text() == NO_PROJECT  # an empty application says how to begin
    path = tmp_path / "site.tracemap"
    gui.create(NewProject(path, demo_data / "mesh.ply", demo_data / "cameras.json", demo_data / "images"))
    qtbot.waitUntil(lambda: gui.session.is_open, timeout=30_000)
    assert gui.session.project.path == path and len(gui.session.cameras()) == 3
    for name in gui.session.cameras():  # the photos linked
        assert gui.session.project.image_path(name) == (demo_data / "images" / f"{name}.png").resolve()
    assert path in recent_projects() and gui.editor.hint.text() != NO_PROJECT
    assert [w.windowTitle() for w in gui.windows] == ["tracemap: image editor: site.tracemap",
                                                      "tracemap: 3D viewer: site.tracemap"]
    actions["&Close project"].trigger()  # and closed again: the windows say how to begin
    assert not gui.session.is_open and gui.editor.hint.text() == NO_PROJECT
    assert [w.windowTitle() for w in gui.windows] == ["tracemap: image editor", "tracemap: 3D viewer"]


def test_a_project_that_cannot_be_made_is_said_and_nothing_is_written(gui, qtbot, demo_data, tmp_path):  # noqa: F811
    bogus = tmp_path / "cameras.xml"
    bogus.write_text("<document><chunk></chunk></document>")
    path = tmp_path / "site.tracemap"
    task = gui.create(NewProject(path, demo_data / "mesh.ply", bogus))
    failed = []
    task.signals.failed.connect(failed.append)
    qtbot.waitUntil(lambda: bool(failed), timeout=30_000)
    text = dialog_text(gui.editor)
    assert str(bogus) in text and "Traceback" not in text
    assert not path.exists() and not gui.session.is_open
