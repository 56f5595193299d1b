"""Orientation of traces (MATHS §1): eigen solution, candidate circle, component densities, the pooled
solver, the κ(K, M) table and the synthetic acceptance test of Seers & Hodgetts (2016b) Fig. 6."""

import json

import numpy as np
import pytest
from scipy.stats import vonmises_fisher

from engine.errors import InputError
from engine.kappa import calibrate_kappa_table, fit_folded_von_mises
from engine.mesh import Mesh
from engine.orientation import (GRID, SetPrior, axial_angle, candidate_circle, circle_poles, dip_dipdir_to_normal,
                                eigen_centre, eigen_orientation, fisher_aperture, folded_von_mises, half_circle_grid,
                                in_surface_fit, incidence_density, load_kappa_table, local_surface_normal, manual_orientation,
                                orient_traces, pool, probabilistic_orientation, restricted_vmf, shape_parameters,
                                surface_planes)
from engine.traces import Trace3D
from tests.outcrops import FIG6_SETS  # the figure's orientations are unknown: Table 1's steep sets
from tests.scenes import grid_wall

DPHI = np.pi / GRID


def _trace(points, id_=1):
    n = len(points)
    return Trace3D(id_, points, np.zeros((n, 2)), np.zeros(n), np.zeros(n), ("img",))


def _on_plane(normal, uv, origin=(1.0, 2.0, 3.0)):
    """Points origin + u·b1 + v·b2 on the plane with this normal."""
    normal = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    b1 = np.cross(normal, [0.3, 0.5, 0.8])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(normal, b1)
    return np.asarray(origin) + uv[:, :1] * b1 + uv[:, 1:] * b2


def _curved(n=200):
    t = np.linspace(0, 1, n)
    return np.column_stack([t, 0.3 * np.sin(2.5 * t)])


# ---------------------------------------------------------------------------------------------------------
# eigen solution and circle (MATHS §1.5 oracles)


def test_noise_free_planar_curved_trace_gives_exact_pole():
    pole = dip_dipdir_to_normal(63.0, 211.0)
    fit = eigen_orientation(_on_plane(pole, _curved()))
    assert fit.K < 0.8
    assert fit.M == np.inf  # λ3 = 0 to rounding: reported, not clamped into a number
    assert np.abs(fit.normal - pole).max() < 1e-9
    assert np.all(np.diff(fit.eigenvalues) <= 0)


def test_straight_trace_circle_contains_true_pole():
    pole = dip_dipdir_to_normal(80.0, 30.0)
    points = _on_plane(pole, np.column_stack([np.linspace(0, 3, 50), np.zeros(50)]))
    fit = eigen_orientation(points)
    assert np.isnan(fit.K) and fit.M == np.inf  # λ2 = λ3 = 0: K = 0/0 reported as NaN
    a, e1, e2 = candidate_circle(points, fit.normal)
    assert abs(pole @ a) < 1e-12
    np.testing.assert_allclose(np.stack([a, e1, e2]) @ np.stack([a, e1, e2]).T, np.eye(3), atol=1e-12)


def test_shape_parameters_degenerate_cases_are_explicit():
    K, M = shape_parameters(np.array([[4.0, 2.0, 1.0], [4.0, 1.0, 0.0], [4.0, 0.0, 0.0], [4.0, 1.0, 1.0]]))
    assert K[0] == pytest.approx(np.log(2) / np.log(2)) and M[0] == pytest.approx(np.log(4))
    assert K[1] == 0.0 and M[1] == np.inf  # exactly planar curve
    assert np.isnan(K[2]) and M[2] == np.inf  # straight line
    assert K[3] == np.inf and np.isfinite(M[3])  # a line with isotropic scatter about it


def test_resampling_removes_vertex_density_bias():
    pole = dip_dipdir_to_normal(70.0, 100.0)
    uv = _curved(400)
    rng = np.random.default_rng(3)
    noisy = _on_plane(pole, uv) + rng.normal(0, 0.004, (400, 3))
    # the first tenth of the trace photographed 20× denser (a close-up photo)
    dense = np.vstack([np.linspace(noisy[0], noisy[40], 800, endpoint=False), noisy[40:]])
    even = eigen_orientation(noisy)
    biased = eigen_orientation(dense)
    assert axial_angle(even.normal, biased.normal) < 1.0
    assert abs(even.M - biased.M) < 0.2


def test_eigen_rejects_bad_points():
    with pytest.raises(InputError, match="2 vertices"):
        eigen_orientation(np.zeros((2, 3)))
    bad = np.random.default_rng(0).normal(size=(5, 3))
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="vertex 3 is NaN"):
        eigen_orientation(bad)
    with pytest.raises(InputError, match="coincide"):
        eigen_orientation(np.ones((4, 3)))
    loop = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0]], dtype=float)
    with pytest.raises(InputError, match="end nodes coincide"):
        candidate_circle(loop, [0, 0, 1])


# ---------------------------------------------------------------------------------------------------------
# component densities (MATHS §1.3)


def test_folded_von_mises_is_normalised_and_stable():
    phi = half_circle_grid()
    for kappa in (0.0, 0.5, 5.0, 80.0, 1e5):
        g = folded_von_mises(phi, kappa)
        assert np.all(np.isfinite(g))
        assert g.sum() * DPHI == pytest.approx(1.0, abs=1e-6 if kappa < 1e4 else 1e-2)
    # κ keeps its circular meaning: s.d. ≈ 1/√κ for large κ
    g = folded_von_mises(phi, 400.0)
    assert np.sqrt((g * phi**2).sum() * DPHI) == pytest.approx(1 / np.sqrt(400.0), rel=0.01)


def test_restricted_vmf_equals_von_mises_with_kappa_cos_d():
    rng = np.random.default_rng(1)
    a = np.array([0.2, -0.3, 0.93])
    a /= np.linalg.norm(a)
    e1 = np.cross(a, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    phi = np.linspace(-np.pi / 2, np.pi / 2, 181)
    n = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    for _ in range(5):
        mu = rng.normal(size=3)
        mu /= np.linalg.norm(mu)
        kappa = rng.uniform(2, 60)
        d = np.arcsin(abs(mu @ a))
        # non-axial: log f(n(φ)) − κ cos d cos(φ − φ0) is constant on the circle
        phi0 = np.arctan2(mu @ e2, mu @ e1)
        diff = vonmises_fisher(mu, kappa).logpdf(n) - kappa * np.cos(d) * np.cos(phi - phi0)
        assert np.ptp(diff) < 1e-9
        # axial: the folded restriction is proportional to ½(f(n; μ) + f(n; −μ))
        axial = 0.5 * (vonmises_fisher(mu, kappa).pdf(n) + vonmises_fisher(-mu, kappa).pdf(n))
        ratio = np.log(restricted_vmf(phi, e1, e2, mu, kappa)) - np.log(axial)
        assert np.ptp(ratio) < 1e-9
        np.testing.assert_allclose(restricted_vmf(phi, e1, e2, mu, kappa),
                                   folded_von_mises(phi, kappa * np.cos(d), phi0), rtol=1e-12)


def test_fisher_aperture_matches_maths_table():
    table = {5: 85.4, 10: 57.4, 20: 39.7, 30: 32.2, 50: 24.8, 100: 17.5, 200: 12.3}
    for kappa, theta99 in table.items():
        assert np.degrees(fisher_aperture(kappa)) == pytest.approx(theta99, abs=0.05)
    assert np.degrees(fisher_aperture(20.0, 0.95)) == pytest.approx(31.8, abs=0.05)


def test_pool_integrates_to_one_and_renormalises():
    phi = half_circle_grid()
    e1, e2 = np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]])
    eigen = folded_von_mises(phi, np.array([[3.0]]))
    sets = restricted_vmf(phi, e1, e2, np.array([0.6, 0.8, 0.0]), 30.0)
    incidence = incidence_density(phi, e1, e2, np.array([[0.0, 1.0, 0.0]]))
    g, w = pool([eigen, sets, incidence], (0.5, 0.3, 0.2))
    assert g.sum() * DPHI == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(w, [[0.5, 0.3, 0.2]])
    g, w = pool([eigen, None, incidence * np.nan], (0.5, 0.3, 0.2))  # no live set, unknown surface
    assert g.sum() * DPHI == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(w, [[1.0, 0.0, 0.0]])


def test_incidence_only_principal_direction_is_in_surface_and_perpendicular_to_axis():
    points = np.column_stack([np.linspace(0, 2, 30), np.zeros(30), 0.2 * np.linspace(0, 2, 30)])  # on y = 0
    s = np.array([0.0, -1.0, 0.0])
    a = (points[-1] - points[0]) / np.linalg.norm(points[-1] - points[0])
    expected = np.cross(s, a)
    result = probabilistic_orientation(points, surface_normal=s, weights=(0, 0, 1), n_draws=20000, seed=4)
    assert axial_angle(result.normal, expected) < 1.0
    assert axial_angle(result.mode, expected) < 0.1
    assert result.weights == (0.0, 0.0, 1.0)


def test_draws_reproduce_under_a_seed():
    rng = np.random.default_rng(5)
    points = _on_plane(dip_dipdir_to_normal(85, 140), np.column_stack([np.linspace(0, 2, 60), np.zeros(60)]))
    points += rng.normal(0, 0.003, points.shape)
    sets = [SetPrior(dip_dipdir_to_normal(85, 137), 43.0, 50), SetPrior(dip_dipdir_to_normal(88, 232), 16.0, 40)]
    one = probabilistic_orientation(points, surface_normal=[0, -1, 0], sets=sets, seed=11)
    two = probabilistic_orientation(points, surface_normal=[0, -1, 0], sets=sets, seed=11)
    other = probabilistic_orientation(points, surface_normal=[0, -1, 0], sets=sets, seed=12)
    np.testing.assert_array_equal(one.normal, two.normal)
    assert not np.array_equal(one.normal, other.normal)
    assert one.density.sum() * DPHI == pytest.approx(1.0, abs=1e-9)
    assert 0.0 <= one.dispersion <= 1.0 and one.spread > 0 and one.n_sets >= 1
    assert abs(one.normal @ one.axis) < 1e-12  # on the circle


def test_collinear_trace_recovers_pole_with_a_set_prior():
    """A strongly collinear trace (the MATHS §1.4 prototype: K ≫ 1) is set by the prior and the eigen pole."""
    pole = dip_dipdir_to_normal(84.0, 140.0)
    rng = np.random.default_rng(6)
    uv = np.column_stack([np.linspace(0, 3, 200), 0.002 * np.sin(np.linspace(0, 7, 200))])
    points = _on_plane(pole, uv) + rng.normal(0, 0.002, (200, 3))
    prior = [SetPrior(dip_dipdir_to_normal(85.0, 137.0), 43.0, 100)]
    result = probabilistic_orientation(points, sets=prior, seed=1)
    assert result.K > 5
    assert axial_angle(result.normal, pole) < 4.0


# ---------------------------------------------------------------------------------------------------------
# traces: orient_traces, manual override, local surface normal


def test_local_surface_normal_on_a_wall():
    v, f = grid_wall(step=0.25)
    mesh = Mesh(v, f)
    points = np.array([[2.0, 0.0, 1.0], [3.0, 0.0, 2.0], [4.0, 0.0, 2.5]])
    np.testing.assert_allclose(local_surface_normal(mesh, points, 0.5), [0, -1, 0], atol=1e-12)
    assert np.all(np.isnan(local_surface_normal(mesh, points + [0, 5.0, 0], 0.5)))


def _corrugated_wall_trace(pole, *, relief=0.03, wander=0.0, seed=0, n=300):
    """The trace of the plane through the origin with this pole on the wall y = h(x) = relief·sin(2πx/3)
    (outcrop normal (h', −1, 0)/‖·‖), x ∈ [0, 3] m, each vertex moved by `wander` m (s.d.) within the wall
    across the end-node axis, as a digitising error or an undulating fracture moves it. Returns (points,
    outcrop normals under them)."""
    x = np.linspace(0.0, 3.0, n)
    h, dh = relief * np.sin(2 * np.pi * x / 3), relief * 2 * np.pi / 3 * np.cos(2 * np.pi * x / 3)
    points = np.column_stack([x, h, -(pole[0] * x + pole[1] * h) / pole[2]])
    normals = np.column_stack([dh, -np.ones(n), np.zeros(n)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    axis = (points[-1] - points[0]) / np.linalg.norm(points[-1] - points[0])
    across = np.cross(normals, axis)
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    return points + np.random.default_rng(seed).normal(0.0, wander, (n, 1)) * across, normals


def test_in_surface_fit_is_exact_on_a_clean_trace_and_unbiased_by_wander_in_the_surface():
    """Misfit within the outcrop surface (DECISION in engine.orientation). A nearly straight trace (K ≈ 2.3)
    on a gently rippled wall that wanders 2 cm in the wall: its eigen pole is pulled toward the wall's
    normal on every one of 40 draws; the fit for misfit in the surface alone (η = 0) is not pulled either
    way, and the default η = 0.1 (which allows some misfit off the surface) is pulled a little."""
    pole = dip_dipdir_to_normal(70.0, 200.0)  # 35° from the wall's mean normal (0, −1, 0)
    wall = np.array([0.0, -1.0, 0.0])
    clean, normals = _corrugated_wall_trace(pole)
    _, e1, e2 = candidate_circle(clean, eigen_orientation(clean).normal)
    for eta in (0.0, 0.1, 1.0):
        # exact up to the parabolic step between grid nodes 1° apart
        assert axial_angle(circle_poles(in_surface_fit(clean, normals, e1, e2, eta=eta), e1, e2), pole) < 0.03
    toward = {"eigen": [], 0.0: [], 0.1: []}
    off = {"eigen": [], 0.0: [], 0.1: []}
    for seed in range(40):
        points, normals = _corrugated_wall_trace(pole, wander=0.02, seed=seed)
        fit = eigen_orientation(points)
        _, e1, e2 = candidate_circle(points, fit.normal)
        found = {"eigen": fit.normal, 0.0: circle_poles(in_surface_fit(points, normals, e1, e2, eta=0.0), e1, e2),
                 0.1: circle_poles(eigen_centre(points, normals, e1, e2), e1, e2)}
        for key, n in found.items():
            toward[key].append(axial_angle(pole, wall) - axial_angle(n, wall))
            off[key].append(axial_angle(n, pole))
    # measured: eigen 6.9° toward the wall's normal (5.7° at least), median error 6.9°; η = 0: −0.5° ± 4.6°
    # (s.d.; the mean within 2 standard errors, 1.4°, of no pull), 2.3°; η = 0.1: +0.8°, 2.9°
    assert min(toward["eigen"]) > 4.0 and abs(np.mean(toward[0.0])) < 1.5 and np.mean(toward[0.1]) < 2.0
    assert np.median(off[0.0]) < 0.4 * np.median(off["eigen"]) and np.median(off[0.1]) < 0.5 * np.median(off["eigen"])
    # no normals, or too few usable ones (NaN, or along the end-node axis): the eigen pole (φ = 0)
    assert eigen_centre(points, None, e1, e2) == 0.0
    axis = np.cross(e1, e2)
    useless = np.where(np.arange(len(points))[:, None] % 2 == 0, np.nan, axis)
    assert eigen_centre(points, useless, e1, e2) == 0.0
    # a few such vertices are left out, not fatal
    some = normals.copy()
    some[::10] = axis
    some[5::10] = np.nan
    assert np.isfinite(eigen_centre(points, some, e1, e2))
    with pytest.raises(InputError, match="eta=-1"):
        in_surface_fit(points, normals, e1, e2, eta=-1)


def test_orient_traces_sets_method_fields_and_json_extras():
    v, f = grid_wall(step=0.25)
    mesh = Mesh(v, f)
    pole = dip_dipdir_to_normal(80.0, 120.0)
    curved = _trace(_on_plane(pole, _curved(80), origin=(2.0, 0.0, 2.0)), 1)
    along = np.cross(pole, [0.0, -1.0, 0.0])  # the straight trace lies on the wall y = 0
    straight_pts = [5.0, 0.0, 2.0] + np.linspace(0, 2, 80)[:, None] * along / np.linalg.norm(along)
    straight = _trace(straight_pts + np.random.default_rng(0).normal(0, 1e-3, (80, 3)), 2)
    loop = _trace(_on_plane(pole, np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 50)),
                                                   np.sin(np.linspace(0, 2 * np.pi, 50))])), 3)
    prior = [SetPrior(pole, 30.0, 20)]
    results = orient_traces([curved, straight, loop], mesh, sets=prior, seed=2)
    assert [t.method for t in (curved, straight, loop)] == ["eigen", "probabilistic", "eigen"]
    assert axial_angle(curved.normal, pole) < 1e-6 and np.isnan(curved.dispersion)
    # a straight line with 1 mm noise on a flat wall: its eigen component is uniform (κ = 0), so the prior
    # and the incidence decide (6.1° off; the κ table before session 10 gave this cell 0.64)
    assert axial_angle(straight.normal, pole) < 8.0 and 0 <= straight.dispersion <= 1
    assert straight.extra["eigen_normal"] == pytest.approx(results[1].eigen_normal.tolist())
    assert straight.extra["surface_normal"] == pytest.approx([0, -1, 0])
    assert set(straight.extra) >= {"mode", "spread_deg", "kappa_eigen"}
    json.dumps([t.extra for t in (curved, straight, loop)])  # the project stores extra as JSON
    # a trace's draws depend on (seed, id) only, not on the batch it is solved in
    again = _trace(straight.points, 2)
    orient_traces([again], mesh, sets=prior, seed=2)
    np.testing.assert_array_equal(again.normal, straight.normal)


def test_a_curve_in_the_surface_plane_is_not_a_fracture_trace():
    """One curve in the plane y = 0.05, on two walls: the trace of that plane on a rippled wall, whose faces
    cross the plane at 16–43° (kept, eigen pole), or a curve drawn on the flat wall y = 0.05, whose plane
    is the surface's own (flagged, solved with a uniform eigen component: the pole comes from the set
    prior and the incidence likelihood)."""
    z = np.linspace(0.0, 1.2, 60)
    curve = np.column_stack([np.arcsin(0.05 / (0.3 * np.cos(np.pi * z / 3))) / np.pi, np.full(60, 0.05), z])
    v, f = grid_wall(width=3.0, height=3.0, step=0.05, offset=(-1.0, 0.0, 0.0))
    v[:, 1] = 0.3 * np.sin(np.pi * v[:, 0]) * np.cos(np.pi * v[:, 2] / 3)
    rippled = Mesh(v, f)
    flat = Mesh(*grid_wall(width=3.0, height=3.0, step=0.05, offset=(-1.0, 0.05, 0.0)))
    fit = eigen_orientation(curve)
    assert axial_angle(fit.normal, [0, 1, 0]) < 1e-6 and fit.K < 0.8
    assert not surface_planes([curve], [fit], rippled)[0] and surface_planes([curve], [fit], flat)[0]
    assert not surface_planes([curve], [fit], None)[0]  # no mesh, no surface to compare with

    prior = [SetPrior(dip_dipdir_to_normal(90.0, 90.0), 30.0, 20)]  # 6° from the curve's circle
    on_ripples, on_flat = _trace(curve, 1), _trace(curve, 2)
    orient_traces([on_ripples], rippled, sets=prior)
    (result,) = orient_traces([on_flat], flat, sets=prior)
    assert on_ripples.method == "eigen" and "surface_plane" not in on_ripples.extra
    assert axial_angle(on_ripples.normal, [0, 1, 0]) < 1e-6
    assert on_flat.method == "probabilistic" and on_flat.extra["surface_plane"] is True
    assert result.kappa_eigen == 0.0 and axial_angle(on_flat.normal, prior[0].normal) < 10.0  # circle: 6°
    manual_orientation(on_flat, angle=10.0)  # a pole set by hand is the user's: the flag goes
    assert "surface_plane" not in on_flat.extra


def test_orient_traces_bad_input_names_the_trace():
    short = _trace(np.zeros((2, 3)), 7)
    with pytest.raises(InputError, match="trace 7: 2 vertices"):
        orient_traces([short], None, sets=())
    nan = _trace(np.column_stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)]), 8)
    nan.points[2, 0] = np.nan
    with pytest.raises(InputError, match="trace 8: vertex 2 is NaN"):
        orient_traces([nan], None, sets=())
    out = np.column_stack([np.linspace(0, 2, 20), np.zeros(20), np.zeros(20)])
    back_and_forth = _trace(np.vstack([out, out[-2::-1]]) + np.random.default_rng(1).normal(0, 1e-3, (39, 3)), 9)
    back_and_forth.points[-1] = back_and_forth.points[0]
    with pytest.raises(InputError, match="trace 9: the end nodes coincide"):
        orient_traces([back_and_forth], None, sets=())
    assert orient_traces([], None) == []


def test_manual_orientation_on_the_circle():
    pole = dip_dipdir_to_normal(75.0, 40.0)
    t = _trace(_on_plane(pole, _curved(50)))
    fit = eigen_orientation(t.points)
    a, e1, e2 = candidate_circle(t.points, fit.normal)
    t.extra["mode"] = [0.0, 0.0, 1.0]  # left by an earlier probabilistic solution
    n = manual_orientation(t, angle=30.0)
    assert t.method == "manual" and abs(n @ a) < 1e-12 and "mode" not in t.extra
    assert axial_angle(n, fit.normal) == pytest.approx(30.0, abs=1e-9)
    n = manual_orientation(t, pole=e2 + 0.4 * a)
    assert axial_angle(n, e2) < 1e-9
    with pytest.raises(InputError, match="along the end-node axis"):
        manual_orientation(t, pole=a)
    with pytest.raises(InputError, match="exactly one"):
        manual_orientation(t)


# ---------------------------------------------------------------------------------------------------------
# the κ(K, M) table (MATHS §1.6)


def test_shipped_kappa_table_is_labelled_and_usable(tmp_path):
    table = load_kappa_table()
    assert table.parameters["generator"] in ("outcrop", "plane") and table.count.sum() > 1000
    text = (tmp_path / "t.csv")
    table.write(text)
    assert "OWN CALIBRATION, not the published Seers & Hodgetts (2016b)" in text.read_text()
    again = load_kappa_table(text)
    np.testing.assert_allclose(again.kappa, table.kappa, rtol=1e-5)
    assert again.parameters == table.parameters
    # lookup: a straight trace (K = NaN) takes the most collinear row; M = inf the most coplanar column
    assert table.lookup(np.nan, 7.0) == table.kappa[-1, np.searchsorted(table.m_edges, 7.0) - 1]
    assert table.lookup(0.1, np.inf) == table.kappa[0, -1]
    with pytest.raises(InputError, match="not found"):
        load_kappa_table(tmp_path / "missing.csv")


def test_fit_folded_von_mises_recovers_kappa():
    rng = np.random.default_rng(2)
    for kappa in (0.8, 4.0, 40.0):
        x = rng.vonmises(0.0, kappa, 20000)
        folded = (x + np.pi / 2) % np.pi - np.pi / 2
        assert fit_folded_von_mises(folded) == pytest.approx(kappa, rel=0.05)
    assert fit_folded_von_mises(rng.uniform(-np.pi / 2, np.pi / 2, 5000)) < 0.2


def test_kappa_calibration_is_deterministic_and_follows_the_law():
    """Regenerate a small "plane" table (MATHS §1.6 verbatim) twice: same seed, same table; κ falls with
    K and rises with M (compared over the populated cells of K < 3 and M ≥ 6)."""
    edges = dict(k_edges=(0, 1, 3, np.inf), m_edges=(0, 6, 9, np.inf), min_count=20)
    one = calibrate_kappa_table(7, 2500, generator="plane", **edges)
    two = calibrate_kappa_table(7, 2500, generator="plane", **edges)
    np.testing.assert_array_equal(one.kappa, two.kappa)
    np.testing.assert_array_equal(one.count, two.count)
    k = one.kappa
    assert k[0, 1] > k[1, 1] > k[2, 1] and k[0, 2] > k[1, 2]  # falls with K
    assert k[0, 2] > k[0, 1] > k[0, 0] and k[1, 2] > k[1, 1]  # rises with M
    assert one.parameters["seed"] == 7 and one.parameters["generator"] == "plane"


def test_outcrop_calibration_is_deterministic():
    one = calibrate_kappa_table(3, 150, generator="outcrop", density=0.3)
    two = calibrate_kappa_table(3, 150, generator="outcrop", density=0.3)
    np.testing.assert_array_equal(one.kappa, two.kappa)
    assert one.count.sum() == 150


# ---------------------------------------------------------------------------------------------------------
# acceptance: Seers & Hodgetts (2016b) Fig. 6 setting on the synthetic outcrop


K_BINS = (0.8, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, np.inf)


def extracted_scene(seed: int, *, sets, noise: float = 0.01, fracture_model: str = "undulating", density=1.0):
    """Traces as tracemap would extract them: the true 2D traces of each photo ray-cast onto the NOISY mesh
    (`engine.extract`), one per fracture (its longest run, as merging would give), with the fracture's
    mean pole as truth. Returns (noisy mesh, traces, true poles)."""
    from engine.extract import extract_traces
    from engine.raytrace import RayTracer
    from engine.synthetic import QUICK, make_outcrop
    from engine.traces import Trace2D

    o = make_outcrop(seed, **QUICK, fracture_model=fracture_model, mesh_noise=noise, density=density, sets=sets)
    truth = {t.id: t.fracture_id for runs in o.traces2d.values() for t in runs}
    runs = [Trace2D(t.id, t.image, t.polyline) for runs in o.traces2d.values() for t in runs]
    extracted = extract_traces(runs, o.local_cameras(), RayTracer(o.noisy_mesh.vertices, o.noisy_mesh.faces))
    best = {}
    for t in extracted.traces:
        fracture = truth[t.parents[0]]
        if len(t.points) >= 3 and np.linalg.norm(t.points[-1] - t.points[0]) > 0 and (
                fracture not in best or t.surface_length > best[fracture].surface_length):
            best[fracture] = t
    traces = []
    for k, (fracture, t) in enumerate(sorted(best.items())):
        t.id = k + 1
        traces.append(t)
    poles = np.array([o.fractures[f].normal for f in sorted(best)])
    return o.noisy_mesh, traces, poles


@pytest.fixture(scope="module")
def fig6():
    """Two undulating-fracture outcrops seen through a 1 cm-noise mesh (≈ half a pixel footprint)."""
    out = []
    for seed in (1, 2):
        mesh, traces, poles = extracted_scene(seed, sets=FIG6_SETS)
        results = orient_traces(traces, mesh, seed=seed)
        out += [(r.K, axial_angle(r.eigen_normal, p), axial_angle(r.normal, p)) for r, p in zip(results, poles)]
    return np.array(out)


def test_fig6_probabilistic_beats_eigen(fig6):
    K = np.where(np.isnan(fig6[:, 0]), np.inf, fig6[:, 0])
    eigen, prob = fig6[:, 1], fig6[:, 2]
    lines = []
    for lo, hi in zip(K_BINS[:-1], K_BINS[1:]):
        s = (K > lo) & (K <= hi)
        lines.append(f"K {lo}-{hi}: n={s.sum()} eigen {np.median(eigen[s]):.1f}° prob {np.median(prob[s]):.1f}°")
        assert np.median(prob[s]) <= 1.1 * np.median(eigen[s]), lines[-1]
    print("\n".join(lines))
    collinear, very = K > 0.8, K > 5
    assert collinear.sum() > 500 and very.sum() > 80
    # measured 0.68 and 0.44 (0.65 and 0.44 while the eigen component was centred on the eigen pole; 0.78
    # and 0.54 while traces in the outcrop surface's plane fed the priors)
    assert np.median(prob[collinear]) <= 0.75 * np.median(eigen[collinear])
    assert np.median(prob[very]) <= 0.55 * np.median(eigen[very])
