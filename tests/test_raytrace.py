import numpy as np
import pytest

from engine.mesh import Mesh
from engine.raytrace import RayTracer
from tests.scenes import grid_wall


@pytest.fixture(scope="module")
def wall():
    return grid_wall(step=0.5)


def _on_wall(n: int, seed: int, margin: float = 0.0) -> np.ndarray:
    """n random points on the 10 × 6 m wall, `margin` in from its border."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(margin, 10 - margin, n), np.zeros(n), rng.uniform(margin, 6 - margin, n)])


def test_hits_on_plane_are_exact(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    targets = _on_wall(5000, 0, margin=0.1)
    origin = np.array([5.0, -8.0, 3.0])
    hits = tracer.intersect(origin, targets - origin)
    assert hits.hit.all()
    # float32 Embree: ~1e-7 of the ray length (here ≤ 10 m), micrometres
    assert np.abs(hits.points - targets).max() < 5e-6
    np.testing.assert_allclose(hits.t, np.linalg.norm(targets - origin, axis=1), rtol=1e-6)
    # the wall's normal is ±y: the cosine of incidence is the ray's y component over its length
    np.testing.assert_allclose(hits.cosine, 8.0 / np.linalg.norm(targets - origin, axis=1), rtol=1e-6)
    # the reported face contains the point
    tri = v[f[hits.face]]
    assert np.all(tri[:, :, 0].min(1) <= targets[:, 0] + 5e-6) and np.all(tri[:, :, 0].max(1) >= targets[:, 0] - 5e-6)


def test_rays_through_shared_edges_and_vertices_hit(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    # every interior grid vertex and every edge midpoint: the watertight (robust) mode must not leak
    xs, zs = np.meshgrid(np.arange(0.5, 9.6, 0.5), np.arange(0.5, 5.6, 0.5))
    vertex_targets = np.column_stack([xs.ravel(), np.zeros(xs.size), zs.ravel()])
    edge_targets = vertex_targets + [0.25, 0.0, 0.0]
    diag_targets = vertex_targets + [0.25, 0.0, 0.25]
    for targets in (vertex_targets, edge_targets, diag_targets):
        hits = tracer.intersect(targets - [0, 3.0, 0], np.tile([0.0, 1.0, 0.0], (len(targets), 1)))
        assert hits.hit.all()
        assert np.abs(hits.points - targets).max() < 5e-6


def test_misses_are_reported_not_dropped(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    origins = np.array([[5.0, -8.0, 3.0]] * 4)
    directions = np.array([[0, 1.0, 0], [0, -1.0, 0], [1.0, 0, 0], [0, 1.0, 0.1]])
    hits = tracer.intersect(origins, directions)
    assert hits.hit.tolist() == [True, False, False, True]
    assert len(hits.t) == 4 and np.isinf(hits.t[1]) and hits.face[2] == -1
    assert np.isnan(hits.points[1]).all() and np.isnan(hits.cosine[1]) and hits.n_missed == 2


def test_partial_packets_and_many_rays(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    for n in (1, 15, 16, 17, 33, 100_003):
        rng = np.random.default_rng(n)
        targets = np.column_stack([rng.uniform(0, 10, n), np.zeros(n), rng.uniform(0, 6, n)])
        hits = tracer.intersect(np.array([5.0, -8.0, 3.0]), targets - [5.0, -8.0, 3.0])
        assert hits.hit.all() and np.abs(hits.points - targets).max() < 5e-6


def test_occlusion(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    cam = np.array([5.0, -8.0, 3.0])
    on_wall = np.array([[2.0, 0.0, 2.0], [7.0, 0.0, 1.0]])
    behind = np.array([[2.0, 1.0, 2.0]])
    in_front = np.array([[2.0, -1.0, 2.0]])
    assert not tracer.occluded(cam, on_wall).any()
    assert tracer.occluded(cam, behind).all()
    assert not tracer.occluded(cam, in_front).any()


def test_utm_coordinates_keep_millimetres():
    offset = np.array([512_345.678, 6_123_456.789, 812.345])
    v, f = grid_wall(offset=offset)
    # float32 at 6e6 m has 0.5 m spacing: only the local frame makes ray tracing exact
    mesh = Mesh(v - np.round(offset), f, np.round(offset))
    tracer = RayTracer(mesh.vertices, mesh.faces)
    targets_world = offset + np.array([[1.234, 0.0, 2.345], [8.765, 0.0, 4.321]])
    origin_world = offset + np.array([5.0, -8.0, 3.0])
    hits = tracer.intersect(origin_world - mesh.origin, targets_world - origin_world)
    assert np.abs(hits.points + mesh.origin - targets_world).max() < 1e-3


def _slab(n: int = 40, step: float = 0.05, noise: float = 0.02, thickness: float = 0.5):
    """A rough slab: a front sheet facing a camera at y = -6 and a back sheet 0.5 m behind facing away,
    so the slab's faces all turn outward. Returns vertices, faces and how many faces the front sheet has."""
    rng = np.random.default_rng(0)
    xs = np.arange(n + 1) * step
    X, Z = np.meshgrid(xs, xs)
    front = np.column_stack([X.ravel(), rng.normal(0, noise, X.size), Z.ravel()])
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return (np.vstack([front, front + [0.0, thickness, 0.0]]), np.vstack([faces, faces[:, ::-1] + X.size]),
            len(faces))


@pytest.mark.parametrize("turned_over", [False, True])
def test_rays_through_the_edges_of_a_rough_surface_meet_it(turned_over):
    # aimed at points on the interior edges of the front sheet: Embree's fast (not watertight) test lets
    # about one in ten of these through the crack between two triangles (1,002 of 9,600 in session 13, 759
    # of them to the back sheet); every one must meet the front sheet, at or before its target
    v, f, n_front = _slab()
    if turned_over:  # a mesh wound the other way: its faces turn inward, toward the camera's back
        f = f[:, ::-1]
    edges = np.concatenate([f[:n_front][:, [0, 1]], f[:n_front][:, [1, 2]], f[:n_front][:, [2, 0]]])
    ends = v[edges]
    side = 40 * 0.05  # the sheet is 2 m square
    on_border = np.zeros(len(edges), dtype=bool)
    for axis in (0, 2):
        for value in (0.0, side):
            on_border |= np.all(np.isclose(ends[:, :, axis], value), axis=1)
    edges = edges[~on_border]
    s = np.random.default_rng(1).uniform(0.05, 0.95, len(edges))[:, None]
    targets = v[edges[:, 0]] * (1 - s) + v[edges[:, 1]] * s
    centre = np.array([1.0, -6.0, 1.0])
    hits = RayTracer(v, f).intersect(centre, targets - centre)
    assert len(targets) > 9000
    assert hits.hit.all() and (hits.face < n_front).all()
    assert np.all(hits.t <= np.linalg.norm(targets - centre, axis=1) + 1e-5)


def test_faces_and_barycentric_coordinates_of_an_irregular_mesh():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    xz = rng.uniform(0, 10, (4000, 2))
    f = Delaunay(xz).simplices.astype(np.int64)
    f[::2] = f[::2, ::-1]  # winding mixed: faces, cosines and barycentric coordinates hold either way round
    v = np.column_stack([xz[:, 0], 0.05 * rng.normal(size=len(xz)), xz[:, 1]])
    targets = np.column_stack([rng.uniform(1, 9, 20000), np.zeros(20000), rng.uniform(1, 9, 20000)])
    origin = np.array([5.0, -8.0, 5.0])
    hits = RayTracer(v, f).intersect(origin, targets - origin)
    assert hits.hit.all()
    tri = v[f[hits.face]]
    b = hits.barycentric
    assert b.min() > -1e-5 and (b.sum(axis=1) < 1 + 1e-5).all()
    back = (1 - b.sum(axis=1))[:, None] * tri[:, 0] + b[:, :1] * tri[:, 1] + b[:, 1:] * tri[:, 2]
    assert np.abs(back - hits.points).max() < 1e-5
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ray = (hits.points - origin) / hits.t[:, None]
    cosine = np.abs(np.sum(normal * ray, axis=1)) / np.linalg.norm(normal, axis=1)
    np.testing.assert_allclose(hits.cosine, cosine, atol=1e-4)


def test_one_origin_for_many_rays_and_shapes_that_do_not_fit(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    targets = _on_wall(100, 4)
    origin = np.array([5.0, -8.0, 3.0])
    one = tracer.intersect(origin, targets - origin)
    many = tracer.intersect(np.tile(origin, (100, 1)), targets - origin)
    assert np.array_equal(one.face, many.face) and np.array_equal(one.t, many.t)
    assert tracer.intersect(origin, np.zeros((0, 3))).hit.shape == (0,)
    assert tracer.intersect(origin, np.zeros((1, 3))).hit.tolist() == [False]  # no direction, no hit
    assert tracer.occluded(origin, origin).tolist() == [False]
    frozen = targets - origin
    frozen.flags.writeable = False  # read-only input (a memory map, a broadcast view) is traced as any other
    assert np.array_equal(tracer.intersect(np.broadcast_to(origin, (1, 3)), frozen).t, one.t)
    assert tracer.occluded(np.broadcast_to(origin, (1, 3)), targets[:1]).tolist() == [False]
    with pytest.raises(ValueError):
        tracer.intersect(np.zeros((3, 3)), np.ones((4, 3)))
