"""The scale bar and north arrow of figures: length, place, directions, registered frames."""

import numpy as np
import pytest
from PIL import Image

from engine.cli import main
from engine.errors import InputError
from engine.project import Project
from engine.scale_bar import round_length, scale_bar


@pytest.mark.parametrize("target, expected", [(4.0, 2.0), (1.0, 1.0), (0.37, 0.2), (99.0, 50.0), (10.0, 10.0),
                                              (7.3e3, 5e3)])
def test_round_lengths(target, expected):
    assert round_length(target) == pytest.approx(expected)


@pytest.fixture(scope="module")
def scene(quick_demo):
    with Project.open(quick_demo / "demo.tracemap") as p:
        return p.load_mesh(), p.cameras()


def test_the_bar_lies_at_the_foot_in_front_of_the_photo_reading_left_to_right(scene):
    mesh, cameras = scene
    camera = cameras["photo_02"]
    bar = scale_bar(mesh, toward=camera.centre)
    v = mesh.vertices
    extent = np.ptp(v @ bar.along)
    assert np.linalg.norm(bar.end - bar.start) == pytest.approx(bar.length_m)
    assert extent / 12.5 < bar.length_m <= extent / 5  # 1, 2 or 5 × 10ⁿ: within a factor 2.5 of a fifth
    assert bar.label == f"{bar.length_m:g} m"
    assert bar.start[2] == pytest.approx(v[:, 2].min()) and bar.end[2] == pytest.approx(v[:, 2].min())
    assert min(bar.start @ bar.out, bar.end @ bar.out) > (v @ bar.out).max()  # clear of the rock
    assert (camera.centre - v.mean(axis=0)) @ bar.out > 0  # on the photos' side
    assert 0.5 * (bar.start + bar.end) @ bar.along == pytest.approx(camera.centre @ bar.along, abs=1e-9)
    assert camera.R[0] @ bar.along > 0.5  # along the photo's rows, left to right: the label reads
    np.testing.assert_allclose(np.cross(bar.along, bar.up), bar.out, atol=1e-12)
    base, tip = bar.arrow
    np.testing.assert_allclose((tip - base) / np.linalg.norm(tip - base), [0, 1, 0], atol=1e-12)
    assert min(base @ bar.out, tip @ bar.out) > (v @ bar.out).max()  # pointing into the rock, it stands out


def test_the_bar_measures_and_points_in_the_registered_frame(scene):
    """A registration of scale 2 turned 30° about z: one mesh unit is 2 m, north is the frame's."""
    mesh, cameras = scene
    toward = np.mean([c.centre for c in cameras.values()], axis=0)
    turn = np.radians(30)
    north = np.array([np.sin(turn), np.cos(turn), 0.0])
    bar = scale_bar(mesh, toward=toward, north=north, metres_per_unit=2.0)
    plain = scale_bar(mesh, toward=toward)
    assert bar.length_m == round_length(2 * np.ptp(mesh.vertices @ bar.along) / 5)
    assert np.linalg.norm(bar.end - bar.start) == pytest.approx(bar.length_m / 2)
    assert bar.length_m > plain.length_m
    base, tip = bar.arrow
    np.testing.assert_allclose((tip - base) / np.linalg.norm(tip - base), north, atol=1e-12)
    with pytest.raises(InputError, match="north on the horizontal plane has no direction"):
        scale_bar(mesh, toward=toward, north=np.array([0.0, 0.0, 1.0]))


def test_render_draws_the_bar_when_asked(quick_demo, tmp_path):
    shots = {}
    for name, extra in (("bar", ["--scale-bar"]), ("none", [])):
        shots[name] = tmp_path / f"{name}.png"
        assert main(["render", str(quick_demo / "demo.tracemap"), "-o", str(shots[name]), "--size", "800", "500",
                     "--no-legend", *extra]) == 0
    black = {n: np.sum(np.all(np.asarray(Image.open(p).convert("RGB")) < 30, axis=-1)) for n, p in shots.items()}
    assert black["bar"] > black["none"] + 300, black  # the bar, its ticks, its label, the arrow and "N"
