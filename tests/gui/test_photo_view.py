"""The tiled photo view: pyramid levels, tiles painted where they belong, zoom about a point, view state."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from PySide6.QtCore import QPointF, Qt
from PySide6.QtGui import QColor

from engine.errors import InputError
from tracemap_gui.photo_view import TILE, PhotoView, Pyramid, read_photo


def pattern(h: int, w: int) -> np.ndarray:
    """A BGR photo whose every pixel tells where it is (blue = column, green = row, mod 256)."""
    v, u = np.mgrid[0:h, 0:w]
    return np.dstack([u % 256, v % 256, np.full((h, w), 128)]).astype(np.uint8)


def test_pyramid_halves_down_to_one_tile():
    pyramid = Pyramid(np.zeros((1500, 2000, 3), np.uint8))
    assert [level.shape[:2] for level in pyramid.levels] == [(1500, 2000), (750, 1000), (375, 500)]
    assert pyramid.level_for(1.0) == pyramid.level_for(4.0) == 0
    assert pyramid.level_for(0.5) == 1 and pyramid.level_for(0.3) == 1 and pyramid.level_for(0.01) == 2
    assert pyramid.factor(1) == (2.0, 2.0)
    assert pyramid.tile_grid(0) == (3, 4)


def test_tiles_are_the_photo_pixels(qapp):
    photo = pattern(700, 900)
    tile = Pyramid(photo).tile_pixmap(0, 1, 1).toImage()
    assert (tile.width(), tile.height()) == (900 - TILE, 700 - TILE)
    b, g, r = photo[TILE + 10, TILE + 20]
    assert tile.pixelColor(20, 10) == QColor(int(r), int(g), int(b))


def test_unreadable_and_16_bit_photos(tmp_path):
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not a photo")
    with pytest.raises(InputError, match="cannot read"):
        read_photo(bad)
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), (np.arange(64 * 64).reshape(64, 64) * 16).astype(np.uint16))
    assert read_photo(deep).dtype == np.uint8 and read_photo(deep).max() == 255


def shown(qtbot, photo: np.ndarray, tmp_path) -> PhotoView:
    path = tmp_path / "photo.png"
    cv2.imwrite(str(path), photo)
    view = PhotoView()
    qtbot.addWidget(view)
    view.resize(600, 400)
    view.show()
    with qtbot.waitSignal(view.photo_loaded, timeout=10_000):
        view.show_photo("p", (photo.shape[1], photo.shape[0]), path)
    return view


def test_the_view_paints_each_photo_pixel_under_its_scene_position(qtbot, tmp_path):
    view = shown(qtbot, pattern(1200, 1700), tmp_path)
    for scale in (1.0, 3.0, 0.3):  # at 0.3 the painting comes from level 1, a quarter of the pixels
        view.zoom(scale / view.scale_factor, QPointF(850, 600))
        view.centerOn(850, 600)
        frame = view.viewport().grab().toImage()
        u, v = 850 + 7, 600 - 5
        where = view.mapFromScene(QPointF(u, v))
        colour = frame.pixelColor(where)
        tolerance = 1 if scale >= 1 else 6  # the reduced level averages neighbours
        assert abs(colour.blue() - u % 256) <= tolerance and abs(colour.green() - v % 256) <= tolerance, scale


def test_zoom_keeps_the_point_under_the_cursor(qtbot, tmp_path):
    view = shown(qtbot, pattern(1200, 1700), tmp_path)
    view.zoom(2.0)
    anchor = QPointF(700, 500)
    before = view.mapFromScene(anchor)
    view.zoom(1.6, anchor)
    assert (view.mapFromScene(anchor) - before).manhattanLength() <= 2


def test_wheel_and_middle_button(qtbot, tmp_path):
    view = shown(qtbot, pattern(1200, 1700), tmp_path)
    view.zoom(4.0)
    scale = view.scale_factor
    centre = view.view_state()["centre"]
    viewport = view.viewport()
    qtbot.mousePress(viewport, Qt.MouseButton.MiddleButton, pos=viewport.rect().center())
    qtbot.mouseMove(viewport, viewport.rect().center() + viewport.rect().topLeft() + QPointF(40, 0).toPoint())
    qtbot.mouseRelease(viewport, Qt.MouseButton.MiddleButton)
    assert view.view_state()["centre"][0] == pytest.approx(centre[0] - 40 / scale, abs=1)


def test_view_state_round_trip(qtbot, tmp_path):
    view = shown(qtbot, pattern(1200, 1700), tmp_path)
    view.zoom(3.3)
    view.centerOn(400, 300)
    state = view.view_state()
    view.fit()
    view.restore_view_state(state)
    assert view.scale_factor == pytest.approx(state["scale"])
    assert view.view_state()["centre"] == pytest.approx(state["centre"], abs=1)


def test_a_fitted_photo_stays_fitted_as_the_window_resizes_until_zoomed(qtbot, tmp_path):
    view = shown(qtbot, pattern(1200, 1700), tmp_path)
    view.resize(900, 700)
    qtbot.waitUntil(lambda: view.scale_factor == pytest.approx(view.viewport().width() / 1700, rel=0.02))
    view.zoom(2.0)
    zoomed = view.scale_factor
    view.resize(500, 400)
    qtbot.wait(50)
    assert view.scale_factor == zoomed


def test_a_frame_makes_few_tiles_and_a_coarser_level_stands_in_for_the_rest(qtbot, tmp_path):
    """Zooming to 1:1 on a 1600×1000 view needs 12–20 new tiles (40–60 ms); one frame makes TILES_PER_FRAME of
    them and draws the others from the coarsest level, enlarged; the frames that follow make the rest."""
    from tracemap_gui.photo_view import TILES_PER_FRAME

    view = shown(qtbot, pattern(3000, 4000), tmp_path)
    view.resize(1600, 1000)
    view.fit()
    qtbot.wait(100)
    item = view._photo_item
    points = [QPointF(u, v) for u in (1307, 1707, 2107, 2607) for v in (1105, 1405, 1805)]  # in 8 tiles

    def exact() -> int:
        """How many points show their own pixel (±1) in a frame painted now."""
        frame = view.viewport().grab().toImage()
        colours = [frame.pixelColor(view.mapFromScene(p)) for p in points]
        return sum(abs(c.blue() - int(p.x()) % 256) <= 1 and abs(c.green() - int(p.y()) % 256) <= 1
                   for c, p in zip(colours, points))

    def fine() -> int:
        return sum(key[0] == 0 for key in item._tiles)

    view.zoom(1.0 / view.scale_factor, QPointF(2000, 1500))
    view.centerOn(2000, 1500)
    first = view.viewport().grab().toImage()
    assert 0 < fine() <= TILES_PER_FRAME
    qtbot.waitUntil(lambda: fine() >= 12, timeout=5000)  # the 4 × 3 tiles the view shows at least
    assert exact() == len(points)
    # the first frame drew most of the view from level 1 enlarged (the fitted view's tiles), not the photo
    assert view.viewport().grab().toImage() != first
