"""Horn's absolute orientation against exact similarities and scikit-image's Umeyama; GCPs from pixels."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from skimage.transform import SimilarityTransform

from engine.errors import InputError
from engine.raytrace import RayTracer
from engine.register import (Similarity, apply_similarity, gcp_from_pixels, horn_similarity, read_gcps_csv,
                             rotate_directions, to_world)
from tests.scenes import facing_camera, grid_wall, wall_point

UTM = np.array([512345.0, 4212345.0, 210.0])


def random_similarity(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    return rng.uniform(0.2, 5.0), R, rng.uniform(-100, 100, 3)


@pytest.mark.parametrize("seed", range(5))
def test_horn_recovers_a_random_similarity_exactly(seed):
    scale, R, t = random_similarity(seed)
    model = np.random.default_rng(seed + 10).uniform(-20, 20, (6, 3))
    world = scale * model @ R.T + t + UTM
    fit = horn_similarity(model, world)
    assert fit.scale == pytest.approx(scale, rel=1e-10)  # world points at UTM size: 1e-9 m rounding
    np.testing.assert_allclose(fit.R, R, atol=1e-10)
    np.testing.assert_allclose(fit.t, t + UTM, atol=1e-6)
    assert np.linalg.det(fit.R) == pytest.approx(1.0) and fit.rmse < 1e-7 and fit.errors.max() < 1e-7
    np.testing.assert_allclose(apply_similarity(model, fit), world, atol=1e-7)


def umeyama(model: np.ndarray, world: np.ndarray) -> np.ndarray:
    """scikit-image's Umeyama similarity (4 × 4): `from_estimate` since 0.26, `estimate` before (0.24 is the
    lowest version tracemap supports)."""
    if hasattr(SimilarityTransform, "from_estimate"):
        return SimilarityTransform.from_estimate(model, world).params
    transform = SimilarityTransform(dimensionality=3)
    assert transform.estimate(model, world)
    return transform.params


def test_horn_matches_umeyama_with_noise():
    scale, R, t = random_similarity(42)
    rng = np.random.default_rng(3)
    model = rng.uniform(-10, 10, (12, 3))
    world = scale * model @ R.T + t + rng.normal(0, 0.05, (12, 3))
    fit = horn_similarity(model, world)
    matrix = umeyama(model, world)
    ref_scale = np.cbrt(np.linalg.det(matrix[:3, :3]))
    assert fit.scale == pytest.approx(ref_scale, rel=1e-10)
    np.testing.assert_allclose(fit.R, matrix[:3, :3] / ref_scale, atol=1e-10)
    np.testing.assert_allclose(fit.t, matrix[:3, 3], atol=1e-8)
    # residuals are world minus fitted, one per GCP, and the RMSE is their root mean square
    np.testing.assert_allclose(fit.residuals, world - apply_similarity(model, fit), atol=1e-12)
    assert fit.rmse == pytest.approx(np.sqrt(np.mean(fit.errors**2)))
    assert 0.02 < fit.rmse < 0.1


def test_weights_act_like_repeated_gcps():
    scale, R, t = random_similarity(7)
    rng = np.random.default_rng(5)
    model = rng.uniform(-10, 10, (5, 3))
    world = scale * model @ R.T + t + rng.normal(0, 0.1, (5, 3))
    weighted = horn_similarity(model, world, weights=[1, 3, 1, 2, 1])
    repeated = horn_similarity(np.repeat(model, [1, 3, 1, 2, 1], axis=0), np.repeat(world, [1, 3, 1, 2, 1], axis=0))
    assert weighted.scale == pytest.approx(repeated.scale, rel=1e-12)
    np.testing.assert_allclose(weighted.R, repeated.R, atol=1e-12)
    np.testing.assert_allclose(weighted.t, repeated.t, atol=1e-9)
    assert weighted.rmse == pytest.approx(repeated.rmse, rel=1e-9)


def test_exports_frame_adds_the_origin_and_applies_the_registration():
    sim = Similarity(2.0, Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.array([1.0, 2.0, 3.0]),
                     np.zeros((3, 3)), np.zeros(3), 0.0)
    local = np.array([[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(to_world(local, UTM), local + UTM)
    np.testing.assert_allclose(to_world(local, [1.0, 0, 0], sim), [[1.0, 6.0, 3.0]], atol=1e-12)
    np.testing.assert_allclose(rotate_directions([[1.0, 0, 0]], sim), [[0.0, 1.0, 0.0]], atol=1e-12)


def test_degenerate_gcps_are_refused():
    model = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3.0]])
    with pytest.raises(InputError, match="collinear"):
        horn_similarity(model, model * 2)
    with pytest.raises(InputError, match="2 given; a similarity needs at least 3"):
        horn_similarity(model[:2], model[:2])
    square = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    bad = square.copy()
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match="GCP 2: its world coordinates are NaN"):
        horn_similarity(square, bad)
    with pytest.raises(InputError, match="weights"):
        horn_similarity(square, square, weights=[1, -1, 1, 1])
    with pytest.raises(InputError, match="collinear"):  # weight 0 leaves three points on a line
        horn_similarity(np.vstack([square[:2], [2, 0, 0], [0, 5, 0]]), square, weights=[1, 1, 1, 0])


def test_gcp_from_pixels_averages_the_ray_hits():
    v, f = grid_wall(step=0.25)
    tracer = RayTracer(v, f)
    cams = {"left": facing_camera("left", centre=(3.0, -8.0, 3.0)),
            "right": facing_camera("right", centre=(7.0, -9.0, 2.5))}
    target = np.array([5.2, 0.0, 3.7])
    picks = {name: tuple(cam.project(target[None])[0]) for name, cam in cams.items()}
    pick = gcp_from_pixels(picks, cams, tracer)
    np.testing.assert_allclose(pick.point, target, atol=1e-5)
    assert pick.spread < 1e-5 and pick.images == ("left", "right") and pick.hits.shape == (2, 3)
    off = dict(picks, right=(picks["right"][0] + 10, picks["right"][1]))  # a careless pick, 10 px off
    spread = gcp_from_pixels(off, cams, tracer).spread
    expected = np.linalg.norm(wall_point(cams["right"], np.array([off["right"]]))[0] - target) / 2
    assert spread == pytest.approx(expected, rel=1e-3)
    with pytest.raises(InputError, match="photo 'left': the ray through pixel .* misses the mesh"):
        gcp_from_pixels({"left": (0.0, 0.0)}, {"left": facing_camera("left", centre=(-30.0, -8.0, 3.0))}, tracer)
    with pytest.raises(InputError, match="photo 'nope' has no camera"):
        gcp_from_pixels({"nope": (1.0, 1.0)}, cams, tracer)


@pytest.mark.parametrize("column, value, expected", [
    ("x", "1e300", "column x is '1e300', expected a coordinate within ±1e\\+09 m"),
    ("y", "-2e9", "column y is '-2e9', expected a coordinate within ±1e\\+09 m"),
    ("z", "inf", "column z is 'inf', expected a finite number"),
    ("x", "nan", "column x is 'nan', expected a finite number"),
    ("u", "nan", "column u is 'nan', expected a finite number"),
    ("v", "-inf", "column v is '-inf', expected a finite number"),
    ("u", "1e300", "pixel \\(1e\\+300, 300\\) is outside the 800×600 photo 'cam'"),
])
def test_gcp_csv_refuses_absurd_numbers_naming_line_and_column(tmp_path, column, value, expected):
    rows = [{"name": n, "x": x, "y": "4212345.0", "z": z, "image": "cam", "u": "400", "v": "300"}
            for n, x, z in (("A", "512345.0", "210"), ("B", "512355.0", "210"), ("C", "512345.0", "220"))]
    rows[1][column] = value
    path = tmp_path / "gcps.csv"
    path.write_text("name,x,y,z,image,u,v\n" + "".join(",".join(r.values()) + "\n" for r in rows))
    with pytest.raises(InputError, match=f"gcps\\.csv: line 3: {expected}"):
        read_gcps_csv(path, {"cam": facing_camera()})
    rows[1][column] = {"x": "512355.0", "y": "4212345.0", "z": "210", "u": "400", "v": "300"}[column]
    path.write_text("name,x,y,z,image,u,v\n" + "".join(",".join(r.values()) + "\n" for r in rows))
    assert sorted(read_gcps_csv(path, {"cam": facing_camera()})) == ["A", "B", "C"]


def test_horn_refuses_coordinates_beyond_the_earth():
    square = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    far = square.copy()
    far[1, 0] = 1e300  # finite, but its squares overflow: the points would look collinear
    with pytest.raises(InputError, match=r"GCP 1: its world coordinates \[1e\+300, 0\.0, 0\.0\] are beyond ±1e\+09 m"):
        horn_similarity(square, far)
