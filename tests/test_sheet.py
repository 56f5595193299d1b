import numpy as np

from engine.raytrace.adjacency import MANY_FACES, NO_FACE, edge_neighbours
from engine.raytrace.sheet import main_sheet
from tests.scenes import grid_wall


def test_faces_across_the_edges_of_a_grid():
    v, f = grid_wall(width=2.0, height=1.0, step=0.5)  # 4 × 2 cells; cell i's triangles are i and i + 8
    across, alike = edge_neighbours(f, len(v))
    assert not alike.any()
    # the first cell's lower triangle (a, b, c) meets its upper one across (c, a) and the bottom border
    # below (a, b); its right side (b, c) is the next cell's upper triangle
    assert across[0].tolist() == [NO_FACE, 9, 8]
    assert np.count_nonzero(across == NO_FACE) == 2 * (4 + 2)  # one per border edge
    symmetric = [(g, f_) for f_ in range(len(f)) for g in across[f_] if g >= 0]
    assert all(f_ in across[g] for g, f_ in symmetric)


def test_the_main_sheet_is_the_largest_piece():
    v1, f1 = grid_wall(width=2.0, height=2.0, step=0.5)
    v2, f2 = grid_wall(width=1.0, height=1.0, step=0.5, offset=(0.0, -1.0, 0.0))  # a loose block in front
    v, f = np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])
    sheet = main_sheet(*edge_neighbours(f, len(v)))
    assert sheet[:len(f1)].all() and not sheet[len(f1):].any()


def test_a_face_wound_against_the_sheet_or_on_a_fin_is_left_out():
    v, f = grid_wall(width=2.0, height=2.0, step=0.5)
    flipped = f.copy()
    flipped[5] = flipped[5, ::-1]
    across, alike = edge_neighbours(flipped, len(v))
    assert alike[5].all() and not alike[~np.isin(np.arange(len(f)), [5, *across[5]])].any()
    assert np.flatnonzero(~main_sheet(across, alike)).tolist() == [5]
    fin = np.vstack([f, [f[0, 2], f[0, 0], len(v)]])  # a third face on the edge (c, a) of cell 0: faces 0, 16
    across, alike = edge_neighbours(fin, len(v) + 1)
    assert across[0, 2] == MANY_FACES
    assert np.flatnonzero(~main_sheet(across, alike)).tolist() == [0, 16, len(f)]
