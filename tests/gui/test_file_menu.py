"""The File menu's Export results… (the form, the export on a worker, failures said) and Project status…."""

from __future__ import annotations

import csv

from tests.gui.test_app import dialog_text, gui  # noqa: F401 - the application fixture
from tracemap_gui.export_dialog import ExportDialog, ExportRequest


def test_the_form_names_what_is_missing(qtbot, tmp_path):
    dialog = ExportDialog()
    qtbot.addWidget(dialog)
    assert [n for n, box in dialog.formats.items() if box.isChecked()] == ["csv", "ply"]
    dialog.accept()
    assert dialog.values is None and "Folder: expected where to write the files" in dialog.message.text()
    (tmp_path / "a file").write_text("")
    dialog.folder.edit.setText(str(tmp_path / "a file"))
    dialog.accept()
    assert "Folder: is a file" in dialog.message.text()
    dialog.folder.edit.setText(str(tmp_path / "out"))
    for box in dialog.formats.values():
        box.setChecked(False)
    dialog.accept()
    assert "Formats: expected at least one of csv, ply, gpkg, vtp" in dialog.message.text()
    dialog.formats["gpkg"].setChecked(True)
    dialog.accept()
    assert dialog.values == ExportRequest(tmp_path / "out", ("gpkg",))


def test_results_are_exported_in_the_background(gui, qtbot, project_path, tmp_path):  # noqa: F811
    assert "&Export results…" in [a.text() for a in gui.editor.file_menu.actions()]
    assert gui.open(project_path)
    out = tmp_path / "out"
    task = gui.export(ExportRequest(out, ("csv", "gpkg")))
    done = []
    task.signals.done.connect(done.append)
    qtbot.waitUntil(lambda: bool(done), timeout=60_000)
    with open(out / "traces.csv") as f:
        assert len(list(csv.DictReader(f))) == len(gui.session.traces3d()) > 10
    assert (out / "traces.gpkg").is_file() and (out / "summary.json").is_file() and not (out / "traces.vtp").exists()
    assert gui.editor.statusBar().currentMessage().startswith(f"wrote {len(done[0].files)} files to {out}")
    assert gui.session.setting("export") == {"folder": str(out), "formats": ["csv", "gpkg"]}  # offered next time


def test_an_export_that_fails_is_said(gui, qtbot, project_path, tmp_path):  # noqa: F811
    assert gui.open(project_path)
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the folder would go")
    task = gui.export(ExportRequest(blocked, ("csv",)))
    failed = []
    task.signals.failed.connect(failed.append)
    qtbot.waitUntil(lambda: bool(failed), timeout=30_000)
    text = dialog_text(gui.editor)
    assert f"{blocked}: is a file; the output must go to a folder" in text and "Traceback" not in text
    assert blocked.read_text() == "a file where the folder would go"


def test_project_status_reports_the_open_project(gui, qtbot, project_path):  # noqa: F811
    from PySide6.QtWidgets import QDialog, QTextBrowser

    actions = {a.text(): a for a in gui.editor.file_menu.actions()}
    actions["Project &status…"].trigger()
    dialog = gui.editor.findChild(QDialog, "project-status-dialog")
    assert "no project is open" in dialog.findChild(QTextBrowser).toPlainText()
    dialog.close()
    assert gui.open(project_path)
    actions["Project &status…"].trigger()
    text = gui.editor.findChildren(QDialog, "project-status-dialog")[-1].findChild(QTextBrowser).toPlainText()
    assert f"3D traces: {len(gui.session.traces3d())}," in text and "next: tracemap export" in text
