import numpy as np
import pytest

from engine.mesh import Mesh
from engine.raytrace import RayTracer
from tests.scenes import grid_wall


@pytest.fixture(scope="module")
def wall():
    return grid_wall(step=0.5)


def test_hits_on_plane_are_exact(wall):
    v, f = wall
    tracer = RayTracer(v, f)
    rng = np.random.default_rng(0)
    targets = np.column_stack([rng.uniform(0.1, 9.9, 5000), np.zeros(5000), rng.uniform(0.1, 5.9, 5000)])
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
