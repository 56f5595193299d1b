import numpy as np
import pytest

from engine.drape import drape_photo, fit_texture, texture_coordinates
from engine.errors import InputError
from engine.mesh import Mesh
from engine.raytrace import RayTracer
from tests.scenes import facing_camera, grid_wall, wall_point

DISTORTED = (-0.12, 0.03, 0.001, -0.0005, 0.0)


def test_texture_coordinates_follow_the_pixel_convention():
    camera = facing_camera(distortion=DISTORTED)
    w, h = camera.width, camera.height
    # the photo's outer corners and the centre of its top-left pixel, through the (distorted) lens
    pixels = np.array([[-0.5, -0.5], [w - 0.5, h - 0.5], [0.0, 0.0], [w / 2 - 0.5, h / 2 - 0.5]])
    st = texture_coordinates(camera, wall_point(camera, pixels))
    np.testing.assert_allclose(st, [[0, 1], [1, 0], [0.5 / w, 1 - 0.5 / h], [0.5, 0.5]], atol=1e-9)
    behind = texture_coordinates(camera, camera.centre - [0.0, 1.0, 0.0])
    assert np.isnan(behind).all()


def scene():
    """A wall seen by a camera, with a panel in front of it (its shadow on the wall is hidden) and one
    behind the camera."""
    wall = grid_wall(10.0, 6.0, 0.25)
    occluder = grid_wall(2.0, 2.0, 0.25, offset=(4.0, -2.0, 2.0))
    behind = grid_wall(2.0, 2.0, 0.25, offset=(4.0, -10.0, 2.0))
    parts = [wall, occluder, behind]
    starts = np.cumsum([0] + [len(v) for v, _ in parts])
    vertices = np.vstack([v for v, _ in parts])
    faces = np.vstack([f + s for (_, f), s in zip(parts, starts)])
    part = np.repeat([0, 1, 2], [len(f) for _, f in parts])
    return Mesh(vertices, faces), part


def test_drape_textures_only_the_faces_the_camera_saw():
    mesh, part = scene()
    camera = facing_camera(distortion=DISTORTED)
    photo = np.zeros((camera.height, camera.width, 3), np.uint8)
    drape = drape_photo(mesh, camera, photo, RayTracer(mesh.vertices, mesh.faces))

    st = texture_coordinates(camera, mesh.vertices)
    with np.errstate(invalid="ignore"):
        inside = np.all((st >= 0) & (st <= 1), axis=1)[mesh.faces].all(axis=1)
    centroid = mesh.face_centroids
    # the panel's shadow on the wall, seen from the camera centre (5, -8, 3): x 4..6, z 2..4 at y = -2
    sx = 5 + (centroid[:, 0] - 5) * 6 / 8
    sz = 3 + (centroid[:, 2] - 3) * 6 / 8
    margin = 0.2  # faces straddling the shadow's edge may go either way
    shadowed = (sx > 4 + margin) & (sx < 6 - margin) & (sz > 2 + margin) & (sz < 4 - margin)
    lit = (sx < 4 - margin) | (sx > 6 + margin) | (sz < 2 - margin) | (sz > 4 + margin)
    wall = part == 0
    assert shadowed[wall].sum() > 50 and (wall & inside).sum() > 1000
    assert not drape.seen[wall & shadowed].any()
    assert drape.seen[wall & lit & inside].all()
    assert not drape.seen[wall & ~inside].any()  # outside the photo: x < 0.43 or x > 9.57 at the wall
    assert (~inside[wall]).sum() > 20
    assert drape.seen[part == 1].all()  # the panel itself faces the camera
    assert not drape.seen[part == 2].any()  # behind the camera
    used = np.unique(mesh.faces[drape.seen])
    np.testing.assert_allclose(drape.uv[used], st[used], atol=1e-6)
    assert drape.texture is photo and drape.scale == 1.0


def test_photo_must_match_its_camera():
    mesh, _ = scene()
    camera = facing_camera()
    with pytest.raises(InputError, match=r"'cam': expected 800×600 8-bit RGB pixels, got uint8 \(600, 799, 3\)"):
        drape_photo(mesh, camera, np.zeros((600, 799, 3), np.uint8), RayTracer(mesh.vertices, mesh.faces))


def test_fit_texture_reduces_only_beyond_the_limit():
    photo = np.zeros((60, 100, 3), np.uint8)
    photo[:, 50:] = (200, 100, 50)  # right half
    assert fit_texture(photo, None)[0] is photo and fit_texture(photo, 100)[0] is photo
    small, scale = fit_texture(photo, 50)
    assert small.shape == (30, 50, 3) and scale == 0.5
    # texture coordinates are fractions of the image: the right half stays the right half
    assert (small[:, 25:] == (200, 100, 50)).all() and (small[:, :25] == 0).all()


def test_render_drapes_the_photo_where_the_camera_saw():
    """Headless scene from the photo's own viewpoint: the seen wall shows the photo's quadrant colours, the
    panel's shadow on the wall (hidden from the camera) does not."""
    import pyvista as pv

    from engine.render import SceneStyle, add_scene, max_texture_size

    mesh, part = scene()
    camera = facing_camera(width=400, height=300, f=350.0)
    photo = np.zeros((300, 400, 3), np.uint8)
    quadrants = {(0, 0): (230, 30, 30), (0, 1): (30, 230, 30), (1, 0): (30, 30, 230), (1, 1): (230, 230, 30)}
    for (i, j), rgb in quadrants.items():
        photo[150 * i:150 * (i + 1), 200 * j:200 * (j + 1)] = rgb
    drape = drape_photo(mesh, camera, photo, RayTracer(mesh.vertices, mesh.faces))
    plotter = pv.Plotter(off_screen=True, window_size=[400, 300])
    try:
        actors = add_scene(plotter, mesh, [], SceneStyle(), drape=drape)
        assert set(actors) == {"mesh", "drape"}
        plotter.camera.position = tuple(camera.centre)
        plotter.camera.focal_point = tuple(camera.centre + camera.R[2])
        plotter.camera.up = tuple(-camera.R[1])
        plotter.camera.view_angle = float(np.degrees(2 * np.arctan(150 / 350)))
        image = plotter.screenshot(None, return_img=True)[..., :3].astype(int)
        assert max_texture_size(plotter) >= 1024  # known once a frame was drawn
    finally:
        plotter.close()
    # rendered from the camera, a pixel shows what the photo has there: the window is the photo
    for (i, j), rgb in quadrants.items():
        v, u = 150 * i + 40, 200 * j + 60  # well inside the quadrant, clear of the panel's shadow
        assert np.abs(image[v, u] - rgb).max() <= 3, (i, j, image[v, u])
    # the photo's centre shows the panel, so the wall behind it is left untextured
    behind = wall_point(camera, np.array([[200.0, 150.0]]))
    hidden = (part == 0) & (np.linalg.norm(mesh.face_centroids - behind, axis=1) < 0.5)
    assert hidden.sum() > 5 and not drape.seen[hidden].any()
    assert not set(map(tuple, mesh.faces[hidden])) & set(map(tuple, pv.wrap(
        actors["drape"].GetMapper().GetInput()).regular_faces.tolist()))
