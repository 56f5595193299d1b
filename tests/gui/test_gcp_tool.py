"""The image editor's GCP tool and dock, clicked: GCPs picked on the quick demo's photos with their world
coordinates, a second photo's observation of a GCP, Register with residuals, undo, and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QDialogButtonBox, QMessageBox
from scipy.spatial.transform import Rotation

from engine.raytrace import RayTracer
from engine.register import Similarity, apply_similarity, gcp_from_pixels, register_gcps
from tests.gui.flows import click

KNOWN = Similarity(0.8, Rotation.from_euler("z", 25.0, degrees=True).as_matrix(), np.array([431_000.0, 6_512_000.0,
                                                                                             240.0]),
                   np.zeros((0, 3)), np.zeros(0), 0.0)
TARGETS = [(400, 240), (560, 200), (240, 400), (480, 400)]  # photo pixels on the rock of photo_01


@pytest.fixture
def tracer(editor):
    mesh = editor.session.project.load_mesh()
    return RayTracer(mesh.vertices, mesh.faces)


def world_of(editor, tracer, image, pixel):
    """The world point the known similarity gives the mesh point under `pixel`."""
    session = editor.session
    model = gcp_from_pixels({image: pixel}, session.cameras(), tracer).point + session.project.origin
    return apply_similarity(model, KNOWN)


def pick(qtbot, editor, x, y, name, world=None):
    """Click with the GCP tool, then fill the dialog (world None: keep what choosing the name filled in)."""
    click(qtbot, editor.view, x, y)
    dialog = editor.tools["GCP"].dialog
    qtbot.waitUntil(dialog.isVisible)
    dialog.name.setCurrentText(name)
    if world is not None:
        for edit, value in zip(dialog.coordinates, world):
            edit.setText(f"{value:.4f}")
    qtbot.mouseClick(dialog.buttons.button(QDialogButtonBox.StandardButton.Ok), Qt.MouseButton.LeftButton)
    return dialog


def residual_column(editor):
    tree = editor.gcps.tree
    return {tree.topLevelItem(i).text(0): tree.topLevelItem(i).text(1) for i in range(tree.topLevelItemCount())}


def test_pick_gcps_on_two_photos_register_and_undo(qtbot, editor, tracer):
    editor.activateWindow()
    editor.view.setFocus()
    qtbot.keyClick(editor.view, Qt.Key.Key_K)
    assert editor.view.tool.name == "GCP"
    session = editor.session
    for k, (x, y) in enumerate(TARGETS, start=1):
        click(qtbot, editor.view, x, y)
        dialog = editor.tools["GCP"].dialog
        assert dialog.name.currentText() == f"GCP{k}"  # a fresh name is offered
        dialog.reject()
        pick(qtbot, editor, x, y, f"G{k}", world_of(editor, tracer, "photo_01", dialog.pixel))
        stored = session.project.gcps()[f"G{k}"]
        np.testing.assert_allclose(stored["observations"]["photo_01"], (x, y), atol=1 / editor.view.scale_factor + 0.5)
        np.testing.assert_allclose(stored["world"], world_of(editor, tracer, "photo_01", dialog.pixel), atol=1e-4)
    assert editor.gcps.tree.topLevelItemCount() == 4

    # G1 seen again on photo_02: choose its name, the coordinates fill in
    g1 = session.project.gcps()["G1"]
    model = gcp_from_pixels(g1["observations"], session.cameras(), tracer).point
    editor.show_photo("photo_02")
    qtbot.waitUntil(lambda: editor.view.pyramid is not None, timeout=10_000)
    u, v = session.camera("photo_02").project(model[None])[0]
    dialog = pick(qtbot, editor, u, v, "G1")
    assert [float(e.text()) for e in dialog.coordinates] == pytest.approx(g1["world"], abs=1e-4)
    observations = session.project.gcps()["G1"]["observations"]
    assert set(observations) == {"photo_01", "photo_02"}
    assert editor.gcps.tree.topLevelItem(0).childCount() == 2

    qtbot.mouseClick(editor.gcps.register_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: session.project.registration() is not None, timeout=20_000)
    registration = session.project.registration()
    expected = register_gcps(session.project.gcps(), session.cameras(), tracer, session.project.origin)
    np.testing.assert_allclose(registration.similarity.errors, expected.similarity.errors, atol=1e-9)
    assert registration.similarity.scale == pytest.approx(KNOWN.scale, rel=1e-3)
    np.testing.assert_allclose(registration.similarity.R, KNOWN.R, atol=1e-3)
    assert registration.similarity.rmse < 0.05  # G1's two picks agree to a pixel or so
    shown = residual_column(editor)
    assert shown == {n: f"{e:.4f}" for n, e in zip(registration.names, registration.similarity.errors)}
    assert f"RMS error {registration.similarity.rmse:.4f} m" in editor.gcps.summary.text()

    told = []  # the readouts in the registered frame hear of each change, undo included
    session.registration_changed.connect(lambda: told.append(session.project.registration() is not None))
    session.undo_stack.undo()  # the registration
    assert session.project.registration() is None and set(residual_column(editor).values()) == {""}
    assert told == [False]
    session.undo_stack.undo()  # G1 on photo_02
    assert set(session.project.gcps()["G1"]["observations"]) == {"photo_01"}
    session.undo_stack.redo()
    session.undo_stack.redo()
    assert session.project.registration() is not None and "changed since" not in editor.gcps.summary.text()
    assert told == [False, True]


def test_bad_coordinates_keep_the_dialog_open_and_store_nothing(qtbot, editor):
    editor.set_tool("GCP")
    click(qtbot, editor.view, *TARGETS[0])
    dialog = editor.tools["GCP"].dialog
    dialog.coordinates[0].setText("abc")
    for edit in dialog.coordinates[1:]:
        edit.setText("1.0")
    qtbot.mouseClick(dialog.buttons.button(QDialogButtonBox.StandardButton.Ok), Qt.MouseButton.LeftButton)
    assert dialog.isVisible() and "X 'abc': expected a number" in dialog.message.text()
    assert editor.session.project.gcps() == {}
    dialog.reject()


def test_register_with_two_gcps_says_three_are_needed_then_remove(qtbot, editor):
    editor.set_tool("GCP")
    pick(qtbot, editor, *TARGETS[0], "A", (1.0, 2.0, 3.0))
    pick(qtbot, editor, *TARGETS[1], "B", (5.0, 2.0, 3.0))
    qtbot.mouseClick(editor.gcps.register_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: editor.gcps.findChild(QMessageBox, "error-dialog") is not None, timeout=20_000)
    box = editor.gcps.findChild(QMessageBox, "error-dialog")
    assert "Registration failed" in box.text() and "at least 3" in box.informativeText()
    box.close()
    assert editor.session.project.registration() is None
    editor.gcps.tree.setCurrentItem(editor.gcps.tree.topLevelItem(0))
    qtbot.mouseClick(editor.gcps.remove_button, Qt.MouseButton.LeftButton)
    assert set(editor.session.project.gcps()) == {"B"}
    editor.session.undo_stack.undo()
    assert set(editor.session.project.gcps()) == {"A", "B"}
