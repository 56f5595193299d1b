"""Hand-editing geometry against cases worked out by hand."""

import numpy as np
import pytest

from engine.errors import TracemapError
from tracemap_gui import polyline_edit as pe

L = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])


def test_closest_point_and_nearest_polyline():
    hit = pe.closest_point(L, (4.0, 3.0))
    assert (hit.segment, hit.t, hit.distance) == (0, 0.4, 3.0)
    far = L + 100
    assert pe.nearest([far, L], (11.0, 5.0), radius=2).index == 1
    assert pe.nearest([far, L], (15.0, 5.0), radius=2) is None


def test_split_inside_a_segment_and_at_a_vertex():
    a, b = pe.split(L, 0, 0.5)
    assert np.array_equal(a, [[0, 0], [5, 0]]) and np.array_equal(b, [[5, 0], [10, 0], [10, 10]])
    a, b = pe.split(L, 0, 1.0)
    assert np.array_equal(a, L[:2]) and np.array_equal(b, L[1:])
    with pytest.raises(TracemapError):
        pe.split(L, 1, 1.0)


def test_join_turns_pieces_to_meet_at_their_nearest_ends():
    a, b = L[:2], np.array([[10.0, 10.0], [10.0, 0.5]])
    joined = pe.join_nearest_ends(a[::-1], b)  # a runs backwards; b's end is nearest a's end
    assert np.array_equal(joined, [[0, 0], [10, 0], [10, 0.5], [10, 10]])
    touching = pe.join_nearest_ends(L[:2], L[1:])
    assert np.array_equal(touching, L)


def test_vertex_edits():
    assert np.array_equal(pe.insert_vertex(L, 1, 0.5), [[0, 0], [10, 0], [10, 5], [10, 10]])
    assert np.array_equal(pe.move_vertex(L, 1, (9, 1))[1], [9, 1])
    assert np.array_equal(pe.delete_vertex(L, 1), L[[0, 2]])
    with pytest.raises(TracemapError):
        pe.delete_vertex(L[:2], 0)
    assert pe.nearest_vertex(L, (9.0, 9.0)) == (2, pytest.approx(np.sqrt(2)))


@pytest.mark.parametrize("lo, hi, expected", [
    ((2, -1), (3, 1), True),  # a segment crosses the box, no vertex inside
    ((-1, -1), (1, 1), True),  # a vertex inside
    ((2, 2), (8, 8), False),  # inside the corner, touching nothing
    ((11, 2), (12, 3), False),  # beside the vertical segment
    ((9, 4), (11, 6), True),
])
def test_crosses_rect(lo, hi, expected):
    assert pe.crosses_rect(L, lo, hi) is expected
