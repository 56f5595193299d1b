import cv2
import numpy as np
from scipy.spatial import cKDTree

from engine.delineate import read_photo
from engine.raytrace import RayTracer
from engine.render import max_texture_size
from tests.gui.flows import actor_data

PHOTO = "photo_01"


def drape(viewer, qtbot, name=PHOTO):
    panel = viewer.drape_panel
    panel.photo_box.setCurrentText(name)
    qtbot.waitUntil(lambda: panel.drape is not None and panel.drape.image == name, timeout=30_000)
    return panel.drape


def actor_mesh(viewer, name):
    return actor_data(viewer._actors[name])


def actor_faces(viewer, name):
    return set(map(tuple, actor_mesh(viewer, name).regular_faces.tolist()))


def display(renderer, points):
    out = []
    for p in points:
        renderer.SetWorldPoint(*p, 1.0)
        renderer.WorldToDisplay()
        out.append(renderer.GetDisplayPoint()[:2])
    return np.array(out)


def test_texture_coordinates_are_the_camera_projection(viewer, qtbot):
    mesh, camera = viewer.mesh, viewer.session.camera(PHOTO)
    result = drape(viewer, qtbot)
    poly = actor_mesh(viewer, "drape")
    used = np.unique(mesh.faces[result.seen])
    uv = camera.project(mesh.vertices[used])
    expected = np.column_stack([(uv[:, 0] + 0.5) / camera.width, 1 - (uv[:, 1] + 0.5) / camera.height])
    np.testing.assert_allclose(np.asarray(poly.active_texture_coordinates)[used], expected, atol=1e-6)
    assert 0.3 < result.seen.mean() < 0.9 and result.texture.shape == (camera.height, camera.width, 3)

    # textured faces: the seen ones; the mesh actor keeps the rest, with the mesh colours
    seen = set(map(tuple, mesh.faces[result.seen].tolist()))
    assert actor_faces(viewer, "drape") == seen
    rest = actor_faces(viewer, "mesh")
    assert not rest & seen and len(rest) + len(seen) == len(mesh.faces)
    assert "rgb" in actor_mesh(viewer, "mesh").point_data
    # faces inside the photo but hidden from it by other rock stay untextured
    px = camera.project(mesh.face_centroids)
    inside = (px[:, 0] > 0) & (px[:, 0] < camera.width - 1) & (px[:, 1] > 0) & (px[:, 1] < camera.height - 1)
    hidden = RayTracer(mesh.vertices, mesh.faces).occluded(camera.centre, mesh.face_centroids,
                                                           tolerance=mesh.mean_edge_length)
    assert (inside & hidden).sum() > 100 and not result.seen[inside & hidden].any()
    assert f"{PHOTO} on {result.seen.sum():,} of 32,000 faces" in viewer.drape_panel.info.text()


def test_rendered_drape_shows_the_photo(viewer, qtbot):
    """Seen from the photo's own camera, the draped mesh shows the photo's colours where it shows rock."""
    result = drape(viewer, qtbot)
    camera, plotter = viewer.session.camera(PHOTO), viewer.view.plotter
    vtk_camera = plotter.camera
    vtk_camera.position = tuple(camera.centre)
    vtk_camera.focal_point = tuple(camera.centre + camera.R[2])  # the optical axis
    vtk_camera.up = tuple(-camera.R[1])  # image y points down
    vtk_camera.view_angle = float(np.degrees(2 * np.arctan(camera.height / 2 / camera.K[1, 1])))
    plotter.renderer.ResetCameraClippingRange()

    def colours():
        frame = viewer.view.frame()
        h, w = frame.shape[:2]
        rng = np.random.default_rng(1)
        points = viewer.mesh.face_centroids[rng.choice(np.flatnonzero(result.seen), 300, replace=False)]
        xy = display(plotter.renderer, points)
        lines = display(plotter.renderer, np.vstack([t.points for t in viewer.session.traces3d()]))
        clear = cKDTree(lines).query(xy)[0] > 10  # away from the trace lines drawn over the rock
        clear &= np.all((xy > 5) & (xy < [w - 5, h - 5]), axis=1)
        assert clear.sum() > 100
        x, y = np.round(xy[clear]).astype(int).T
        rendered = frame[h - 1 - y, x].astype(float)
        photo = read_photo(viewer.session.project.image_path(PHOTO), camera).astype(np.float32)
        pixels = camera.project(points[clear])
        expected = np.array([cv2.getRectSubPix(photo, (1, 1), (float(u), float(v)))[0, 0] for u, v in pixels])
        return np.abs(rendered - expected).max(axis=1)

    error = colours()
    assert np.median(error) < 5 and np.percentile(error, 90) < 15
    viewer.drape_panel.photo_box.setCurrentText("None")  # the mesh's own (lit, coarser) colours differ
    bare = colours()
    assert np.median(bare) > 2 * np.median(error) and "drape" not in viewer._actors


def test_drape_survives_redraws_and_none_removes_it(viewer, qtbot):
    result = drape(viewer, qtbot)
    viewer.session.select3d({viewer.session.traces3d()[0].id})  # any redraw keeps the drape
    assert viewer.drape_panel.drape is result and actor_faces(viewer, "drape")
    viewer.maps_panel.quantity_box.setCurrentText("P21")  # a map colours the unseen faces
    assert "p21" in actor_mesh(viewer, "mesh").point_data
    assert viewer.view.plotter.actors["drape"] is viewer._actors["drape"]
    viewer.drape_panel.photo_box.setCurrentText("None")
    assert viewer.drape_panel.drape is None and "drape" not in viewer.view.plotter.actors
    assert len(actor_faces(viewer, "mesh")) == len(viewer.mesh.faces)


def test_texture_limit_comes_from_the_context_that_draws(viewer):
    """Offscreen the GUI's plotter never draws: the limit is the render thread's, known after its first frame."""
    viewer.view.frame()
    assert viewer.view.offscreen and max_texture_size(viewer.view.plotter) is None
    limit = viewer.view.max_texture_size()
    assert isinstance(limit, int) and limit >= 1024


def test_photo_beyond_the_texture_limit_is_reduced(viewer, qtbot, monkeypatch):
    monkeypatch.setattr(type(viewer.view), "max_texture_size", lambda view: 256)
    result = drape(viewer, qtbot, "photo_02")
    assert result.texture.shape == (192, 256, 3) and result.scale == 0.4
    assert "reduced to 256×192 px" in viewer.statusBar().currentMessage()
    assert "texture reduced to 256×192 px" in viewer.drape_panel.info.text()
