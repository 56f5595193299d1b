import numpy as np
import pytest
from scipy.spatial import Delaunay

from engine.raytrace.adjacency import edge_neighbours
from engine.raytrace.quads import NONE, pair_triangles
from tests.scenes import grid_wall


def _pair(faces, vertices, **kwargs):
    return pair_triangles(faces, vertices, edge_neighbours(faces, len(vertices))[0], **kwargs)


def _check(faces: np.ndarray, quads: np.ndarray, lookup: np.ndarray) -> None:
    """Every face in exactly one quad, as the quad's triangle (v0, v1, v3) or (v2, v3, v1), each of its
    vertices in the slot its code names."""
    ids = lookup & 0xFFFFFFFF
    listed = ids[ids != NONE]
    assert np.array_equal(np.sort(listed), np.arange(len(faces)))
    for j, corners in ((0, [0, 1, 3]), (1, [2, 3, 1])):
        rows = np.flatnonzero(ids[:, j] != NONE)
        face = faces[ids[rows, j]]
        assert np.array_equal(np.sort(face, axis=1), np.sort(quads[rows][:, corners].astype(np.int64), axis=1))
        for k in range(3):
            slot = (lookup[rows, j] >> (32 + 2 * k)) & 3
            assert np.array_equal(quads[rows, slot], face[:, k])


def test_a_grid_pairs_into_its_cells():
    v, f = grid_wall(step=0.5)
    quads, lookup = _pair(f, v)
    _check(f, quads, lookup)
    assert len(quads) == len(f) // 2
    cells = {tuple(sorted(pair)) for pair in (lookup & 0xFFFFFFFF).tolist()}
    half = len(f) // 2  # grid_wall lists the cells' two triangles half the faces apart
    assert cells == {(i, i + half) for i in range(half)}


def test_a_grid_pairs_into_its_cells_even_when_rough():
    # rough as tests/benchmarks/bench_raytrace.py's wall (noise 0.6 of the spacing across the wall): pairing
    # by the smallest box face by face would push most faces off their cell; mutual choices keep 95%
    v, f = grid_wall(width=20.0, height=20.0, step=0.5)
    v = v + np.random.default_rng(0).normal(0, 0.3, len(v))[:, None] * [0.0, 1.0, 0.0]
    quads, lookup = _pair(f, v)
    _check(f, quads, lookup)
    half = len(f) // 2
    pairs = {tuple(sorted(pair)) for pair in (lookup & 0xFFFFFFFF).tolist()}
    assert np.mean([(i, i + half) in pairs for i in range(half)]) > 0.9


def test_an_irregular_mesh_pairs_almost_whole():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 10, (3000, 2))
    f = Delaunay(xy).simplices.astype(np.int64)
    v = np.column_stack([xy, 0.1 * rng.normal(size=len(xy))])
    quads, lookup = _pair(f, v)
    _check(f, quads, lookup)
    assert len(quads) < 0.55 * len(f)  # under one face in ten left alone (8% here)


def test_odd_faces_stay_alone_and_the_rest_still_pair():
    v, f = grid_wall(width=2.0, height=2.0, step=0.5)
    odd = np.array([[0, 0, 1],          # a repeated vertex
                    f[0], f[0][::-1],   # the same triangle twice, once turned over
                    [0, 1, len(v) - 1]])  # a third face on the edge (0, 1)
    f = np.vstack([f, odd])
    f[3] = f[3][::-1]  # a face wound the other way from its neighbours
    quads, lookup = _pair(f, v)
    _check(f, quads, lookup)
    alone = (lookup[:, 1] & 0xFFFFFFFF) == NONE
    assert len(f) - 4 in (lookup[alone, 0] & 0xFFFFFFFF)  # the degenerate face found no partner


@pytest.mark.parametrize("pool", [None, "threads"])
def test_pairing_is_the_same_on_threads(pool):
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 10, (2000, 2))
    f = Delaunay(xy).simplices.astype(np.int64)
    v = np.column_stack([xy, 0.1 * rng.normal(size=len(xy))])
    one = _pair(f, v)
    with ThreadPoolExecutor(2) as threads:
        other = _pair(f, v, pool=threads if pool else None)
    assert all(np.array_equal(a, b) for a, b in zip(one, other))
