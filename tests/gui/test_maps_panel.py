import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QMessageBox, QPushButton

from tests.gui.flows import actor_data, register


def mesh_scalars(viewer, name):
    return actor_data(viewer._actors["mesh"]).point_data[name]


def stored(viewer, name):
    return viewer.session.project.vertex_map(name)


def choose(panel, quantity, subset=None):
    panel.quantity_box.setCurrentText(quantity)
    if subset is not None:
        panel.subset_box.setCurrentText(subset)


def test_compute_maps_with_a_new_radius(viewer, qtbot):
    panel = viewer.maps_panel
    assert panel.map_name is None and not viewer.view.plotter.scalar_bars.keys()
    before = stored(viewer, "p21")[0]
    terminations = [(t.id, t.term_start, t.term_end) for t in viewer.session.project.traces3d()]
    panel.radius_box.setValue(1.0)
    qtbot.mouseClick(panel.compute_button, Qt.MouseButton.LeftButton)
    assert not panel.compute_button.isEnabled()
    qtbot.waitUntil(lambda: panel.compute_button.isEnabled(), timeout=60_000)

    values, info = stored(viewer, "p21")
    assert info == {"radius": 1.0}
    assert all(stored(viewer, n)[1] == {"radius": 1.0} for n in ("p21:set0", "p32", "p32:set1"))
    finite = np.isfinite(values) & np.isfinite(before)
    assert np.abs(values[finite] - before[finite]).max() > 0.5  # another sphere: another map
    # the new map is shown, as stored, with its scalar bar and units
    assert panel.map_name == "p21"
    np.testing.assert_array_equal(mesh_scalars(viewer, "p21"), values)
    assert list(viewer.view.plotter.scalar_bars.keys()) == ["P21 (1/m)"]
    assert panel.info.text().startswith("radius 1 m, ") and "m⁻¹" in panel.info.text()
    # only the maps were stored: the hand-editable terminations are untouched
    assert [(t.id, t.term_start, t.term_end) for t in viewer.session.project.traces3d()] == terminations


def test_switch_sets_quantity_and_colour_range(viewer, qtbot):
    panel = viewer.maps_panel
    choose(panel, "P21", "set 1")
    assert panel.map_name == "p21:set1"
    np.testing.assert_array_equal(mesh_scalars(viewer, "p21:set1"), stored(viewer, "p21:set1")[0])
    assert list(viewer.view.plotter.scalar_bars.keys()) == ["P21 set 1 (1/m)"]

    choose(panel, "P32")  # keeps the set
    assert panel.map_name == "p32:set1" and panel.subset_box.currentText() == "set 1"
    values = stored(viewer, "p32:set1")[0]
    np.testing.assert_array_equal(mesh_scalars(viewer, "p32:set1"), values)
    assert list(viewer.view.plotter.scalar_bars.keys()) == ["P32 set 1 (m²/m³ = 1/m)"]
    mapper = viewer._actors["mesh"].GetMapper()
    np.testing.assert_allclose(mapper.GetScalarRange(), (np.nanmin(values), np.nanmax(values)))
    assert np.isnan(values).any()  # unimaged vertices: neutral grey
    np.testing.assert_allclose(mapper.GetLookupTable().GetNanColor()[:3], [0.827] * 3, atol=0.01)

    panel.range_box.setCurrentText("5–95 %")
    np.testing.assert_allclose(viewer._actors["mesh"].GetMapper().GetScalarRange(),
                               np.nanpercentile(values, [5, 95]))
    viewer.session.select3d({viewer.session.traces3d()[0].id})  # any redraw keeps the map
    np.testing.assert_array_equal(mesh_scalars(viewer, "p32:set1"), values)

    choose(panel, "None")
    assert panel.map_name is None and not viewer.view.plotter.scalar_bars.keys()
    assert "p32:set1" not in actor_data(viewer._actors["mesh"]).point_data
    assert viewer.session.setting("viewer3d/map") is None


def test_map_choice_is_remembered(viewer, qtbot, project_path):
    choose(viewer.maps_panel, "P32", "all sets")
    viewer.session.close()
    viewer.session.open(project_path)
    qtbot.waitUntil(lambda: viewer.mesh is not None, timeout=20_000)
    assert viewer.maps_panel.map_name == "p32"
    np.testing.assert_array_equal(mesh_scalars(viewer, "p32"), stored(viewer, "p32")[0])


def test_radius_below_the_mesh_spacing_is_refused(viewer, qtbot):
    panel = viewer.maps_panel
    assert "mesh spacing 0.125 m" in panel.hint.text()
    panel.radius_box.setValue(0.05)
    qtbot.mouseClick(panel.compute_button, Qt.MouseButton.LeftButton)
    box = next(b for b in panel.findChildren(QMessageBox) if b.objectName() == "error-dialog")
    assert "radius 0.05 m is below the mesh spacing (0.125 m" in box.informativeText()
    assert "at least 0.125 m" in box.informativeText()
    assert not any(t.title.startswith("Intensity maps") for t in viewer.session.jobs.running)
    assert stored(viewer, "p21")[1] == {"radius": 0.5}
    box.close()


def test_cancel_keeps_the_stored_maps(viewer, qtbot):
    panel = viewer.maps_panel
    before = stored(viewer, "p21")[0]
    panel.radius_box.setValue(1.0)
    qtbot.mouseClick(panel.compute_button, Qt.MouseButton.LeftButton)
    cancel = viewer.statusBar().findChild(QPushButton, "cancel-task")
    assert cancel.isVisible()
    qtbot.mouseClick(cancel, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: not viewer.session.jobs.running, timeout=30_000)
    assert panel.compute_button.isEnabled()
    values, info = stored(viewer, "p21")
    assert info == {"radius": 0.5}
    np.testing.assert_array_equal(values, before)


def test_values_and_radius_are_in_the_registered_frame(viewer, qtbot):
    register(viewer.session.project, 2.0)
    panel = viewer.maps_panel
    panel.radius_box.setValue(2.0)  # metres of the registered frame: 1 m on the mesh
    qtbot.mouseClick(panel.compute_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: panel.compute_button.isEnabled(), timeout=60_000)
    values, info = stored(viewer, "p21")
    assert info == {"radius": 1.0}  # stored in the mesh's units
    intensity = viewer.session.project.result("intensity")  # what summary.json reports goes with the maps
    assert intensity["radius_m"] == 1.0 and intensity["maps"]["p21"]["median"] == np.nanmedian(values)
    np.testing.assert_allclose(mesh_scalars(viewer, "p21"), values / 2)  # shown per metre of the GCPs' frame
    assert panel.info.text().startswith("radius 2 m, ")
