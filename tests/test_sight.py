"""What the photos see of the mesh (engine.sight) on analytic scenes."""

from dataclasses import replace

import numpy as np

from engine.mesh import Mesh
from engine.raytrace import RayTracer
from engine.sight import Sight
from scenes import facing_camera, grid_wall, wavy, wavy_wall_with_post


def post_scene() -> Sight:
    vertices, faces, camera = wavy_wall_with_post()
    return Sight(Mesh(vertices, faces), {camera.name: camera}, RayTracer(vertices, faces))


def test_a_point_behind_the_post_or_off_the_surface_is_not_seen():
    sight = post_scene()

    def on_wall(x, z):
        return [x, wavy(np.array([x]), np.array([z]))[0], z]

    points = np.array([on_wall(1.0, 2.0), on_wall(3.05, 2.0), on_wall(5.0, 1.0),
                       [1.0, -0.3, 2.0],  # in the air in front of the wall: the wall behind it is hit first
                       on_wall(9.0, 2.0)])  # off the mesh and outside the photo
    assert sight.seen(points, 0.01).tolist() == [True, False, True, False, False]


def test_the_strip_hidden_by_the_post_has_the_width_of_its_shadow():
    sight = post_scene()
    x = np.arange(2.0, 4.0, 0.001)
    z = np.full_like(x, 2.0)
    hidden = x[~sight.seen(np.column_stack([x, wavy(x, z), z]), 0.01)]
    # the post's edges x = 2.8 and 3.3 at 1.0–1.2 m from the wall, seen from x = 3 at 8 m: its shadow
    # on the wall (y ≈ wavy) begins and ends where the rays past the edges meet it
    for edge, end, y_post in ((2.8, hidden.min(), -1.2), (3.3, hidden.max(), -1.2)):
        y_wall = wavy(np.array([end]), np.array([2.0]))[0]
        expected = 3.0 + (edge - 3.0) * (y_wall + 8.0) / (y_post + 8.0)
        assert abs(end - expected) < 0.005, (edge, end, expected)


def test_plane_path_on_a_flat_wall_is_the_line_of_the_plane_between_the_points():
    vertices, faces = grid_wall(step=0.1)
    sight = Sight(Mesh(vertices, faces), {}, RayTracer(vertices, faces))
    normal = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)  # the plane x + z = 5.03, clear of the grid's vertices
    start, end = np.array([1.5, 0.0, 3.53]), np.array([3.5, 0.0, 1.53])
    path = sight.plane_path(np.array([2.5, 0.0, 2.53]), normal, start, end, 2.0, 0.1)
    assert np.allclose(path[:, 0] + path[:, 2], 5.03) and np.allclose(path[:, 1], 0.0)
    assert np.all(np.diff(path[:, 0]) > 0)  # in order from start to end
    assert np.linalg.norm(path[0] - start) < 0.1 and np.linalg.norm(path[-1] - end) < 0.1
    assert np.linalg.norm(np.diff(path, axis=0), axis=1).max() < 0.1 * np.sqrt(2) + 1e-9  # an edge per face
    assert sight.plane_path(np.array([2.5, 0.0, 2.53]), normal, start + [0, 0, 1], end, 2.0, 0.1) is None


def test_plane_path_follows_only_the_curve_that_joins_the_points():
    """The level z = 2 cuts the wavy wall in one curve (behind the post too) and the post in a loop: wall to
    wall is joined, wall to post is not."""
    sight = post_scene()
    level = np.array([0.0, 0.0, 1.0])
    on_wall = [np.array([x, wavy(np.array([x]), np.array([2.0]))[0], 2.0]) for x in (1.0, 5.0)]
    path = sight.plane_path(np.array([0.0, 0.0, 2.0]), level, *on_wall, 4.5, 0.05)
    assert np.allclose(path[:, 2], 2.0) and path[:, 1].max() < 0.15  # on the wall, not round the post
    assert path[:, 0].min() < 1.05 and path[:, 0].max() > 4.95
    on_post = np.array([3.05, -1.2, 2.0])
    assert sight.plane_path(np.array([0.0, 0.0, 2.0]), level, on_wall[0], on_post, 4.5, 0.05) is None


def test_rock_seen_edge_on_is_not_seen():
    """A wall turned about the vertical through (5, 0, 3), where the camera's axis meets it: a line of sight
    meeting it more than SEEN_INCIDENCE (75°) from its normal shows no trace, so the point is not seen."""
    vertices, faces = grid_wall(step=0.25)
    camera = facing_camera()
    seen = []
    for turn in (60.0, 74.0, 76.0, 85.0):
        a = np.radians(turn)
        rotation = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        turned = (vertices - [5.0, 0.0, 0.0]) @ rotation.T + [5.0, 0.0, 0.0]
        sight = Sight(Mesh(turned, faces), {camera.name: camera}, RayTracer(turned, faces))
        seen.append(bool(sight.seen(np.array([[5.0, 0.0, 3.0]]), 0.01)[0]))
    assert seen == [True, True, False, False]


def test_a_path_along_an_occluding_edge_is_seen_but_would_show_no_trace():
    """engine.extract drops a trace's pixels where side rays across it land at other depths: along the
    post's front edge (x = 2.8, the wall 1 m behind) the photo sees the rock but cannot show a trace on it.
    Side rays land 2 px (1 cm here) across, so a path 5 mm inside the edge is on it and one 10 cm inside
    is not."""
    sight = post_scene()
    z = np.linspace(1.5, 2.5, 21)

    def on_post(x):
        return np.column_stack([np.full_like(z, x), np.full_like(z, -1.2), z])

    assert sight.seen(on_post(2.805), 0.01).all()
    assert not sight.shows(on_post(2.805), 0.01).any()
    assert sight.shows(on_post(2.9), 0.01).all()
    x = np.linspace(1.0, 2.0, 21)
    on_wall = np.column_stack([x, wavy(x, np.full_like(x, 2.0)), np.full_like(x, 2.0)])
    assert sight.shows(on_wall, 0.01).all()
    behind = np.column_stack([np.full_like(z, 3.05), wavy(np.full_like(z, 3.05), z), z])
    assert not sight.shows(behind, 0.01).any()


def test_a_photo_shows_what_its_edge_px_lets_extraction_place():
    """The post's front edge as above, judged with the `edge_px` the photo's traces were extracted with:
    0 places trace pixels on occluding edges, so there seeing is showing; 8 px (4 cm) puts a path 2 cm
    inside the edge on it, which the automatic 2 px (1 cm) does not."""
    sight = post_scene()
    (name,) = sight.cameras
    z = np.linspace(1.5, 2.5, 21)

    def on_post(x):
        return np.column_stack([np.full_like(z, x), np.full_like(z, -1.2), z])

    assert replace(sight, edge_px={name: 0}).shows(on_post(2.805), 0.01).all()
    assert sight.shows(on_post(2.82), 0.01).all()
    assert replace(sight, edge_px={name: None}).shows(on_post(2.82), 0.01).all()
    assert not replace(sight, edge_px={name: 8.0}).shows(on_post(2.82), 0.01).any()
