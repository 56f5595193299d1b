"""Fracture sets (MATHS §10, §8): axial k-means, the number of sets, Fisher statistics, Terzaghi weights,
density peaks, mesh facets, and recovery of Seers & Hodgetts (2016a) Table 1 sets on the synthetic outcrop."""

import numpy as np
import pytest
from scipy.stats import vonmises_fisher

from engine.errors import InputError
from engine.mesh import Mesh
from engine.orientation import axial_angle, dip_dipdir_to_normal, fisher_aperture, orient_traces
from engine.sets import (axial_kmeans, classify_traces, density_peaks, fit_facet, fit_mesh_facet,
                         fit_sets, kappa_mle, set_statistics, terzaghi_weights)
from engine.synthetic import DEFAULT_SETS
from engine.traces import Trace3D
from tests.scenes import grid_wall

TABLE1 = [(dip_dipdir_to_normal(d, a), k) for d, a, k, _ in DEFAULT_SETS]  # 85/137 κ 9.8, 88/232 κ 13.4


def _sample(sets, n, seed=0, flip=True):
    """Poles from axial Fisher sets [(mean, κ)], n each, with random signs (poles are axial)."""
    rng = np.random.default_rng(seed)
    poles = np.vstack([vonmises_fisher(mu, kappa).rvs(n, random_state=rng) for mu, kappa in sets])
    return poles * (rng.choice([-1.0, 1.0], (len(poles), 1)) if flip else 1.0)


def _match(model, sets):
    """For each generating set, (angle to the nearest fitted mean in degrees, fitted κ / generating κ)."""
    out = []
    for mu, kappa in sets:
        fitted = min(model.sets, key=lambda s: axial_angle(s.normal, mu))
        out.append((float(axial_angle(fitted.normal, mu)), fitted.kappa / kappa))
    return out


# ---------------------------------------------------------------------------------------------------------
# clustering and the number of sets


def test_axial_kmeans_ignores_pole_signs():
    sets = [(dip_dipdir_to_normal(85, 137), 40.0), (dip_dipdir_to_normal(88, 232), 40.0),
            (dip_dipdir_to_normal(10, 0), 40.0)]
    poles = _sample(sets, 150)
    labels, centres = axial_kmeans(poles, 3, seed=1)
    for mu, _ in sets:
        assert min(axial_angle(c, mu) for c in centres) < 2.0
    # every pole is with the centre nearest to it as an axis, and the clusters are the generating sets
    assert np.all(labels == np.argmax(np.abs(poles @ centres.T), axis=1))
    assert len(np.unique(labels[:150])) == 1 and len(np.unique(labels)) == 3


@pytest.mark.parametrize("sets, expected", [
    (TABLE1, 2),
    ([(dip_dipdir_to_normal(85, 137), 43.0), (dip_dipdir_to_normal(88, 232), 16.0)], 2),
    ([(dip_dipdir_to_normal(80, 120), 20.0), (dip_dipdir_to_normal(85, 230), 20.0),
      (dip_dipdir_to_normal(10, 0), 30.0)], 3),
    ([(dip_dipdir_to_normal(80, 120), 10.0)], 1),
    ([(dip_dipdir_to_normal(80, 120), 100.0)], 1),
])
def test_number_of_sets_by_bic(sets, expected):
    model = fit_sets(_sample(sets, 300, seed=len(sets)))
    assert model.n_sets == expected, model.bic


def test_table1_sets_recovered_from_their_poles():
    """Overlapping sets (θ99 ≈ 57° for κ 9.8, 95° apart): the mixture keeps κ unbiased where hard clusters
    would cut the tails."""
    model = fit_sets(_sample(TABLE1, 500, seed=3))
    assert model.n_sets == 2
    for angle, ratio in _match(model, TABLE1):
        assert angle < 2.0 and abs(ratio - 1) < 0.15


def test_non_systematic_poles_go_to_minus_one():
    mu = dip_dipdir_to_normal(80, 120)
    stray = np.array([dip_dipdir_to_normal(20, 300), dip_dipdir_to_normal(45, 10)])
    model = fit_sets(np.vstack([_sample([(mu, 50.0)], 200, seed=5), stray]), n_sets=1)
    assert np.all(model.labels[-2:] == -1) and np.mean(model.labels[:-2] == 0) >= 0.97  # θ99: ~1% beyond
    assert model.cutoff[0] == pytest.approx(np.degrees(fisher_aperture(model.sets[0].kappa)), rel=0.05)
    forced = fit_sets(np.vstack([_sample([(mu, 50.0)], 200, seed=5), stray]), n_sets=1, outlier_angle=5.0)
    assert np.mean(forced.labels == -1) > 0.2
    np.testing.assert_array_equal(model.assign(stray), [-1, -1])
    assert model.assign(mu[None])[0] == 0


def test_scattered_poles_go_to_the_background_not_into_a_set():
    """20% of the poles uniform on the sphere (badly constrained traces): the uniform component takes them,
    so the set keeps its mean and κ, and no spurious set is made of them."""
    mu = dip_dipdir_to_normal(80, 120)
    rng = np.random.default_rng(11)
    stray = rng.normal(size=(100, 3))
    model = fit_sets(np.vstack([_sample([(mu, 30.0)], 400, seed=12), stray]))
    assert model.n_sets == 1 and model.background == pytest.approx(0.2, abs=0.05)
    (angle, ratio), = _match(model, [(mu, 30.0)])
    assert angle < 1.5 and abs(ratio - 1) < 0.15
    assert np.mean(model.labels[400:] == -1) > 0.75 and np.mean(model.labels[:400] == 0) > 0.95


def test_a_tight_clump_of_near_identical_poles_is_not_a_set():
    """Pieces of one fracture give near-identical poles: a clump tighter than KAPPA_MAX is not a set."""
    sets = [(dip_dipdir_to_normal(80, 120), 20.0), (dip_dipdir_to_normal(85, 230), 20.0)]
    clump = _sample([(dip_dipdir_to_normal(10, 0), 5000.0)], 30, seed=13)
    model = fit_sets(np.vstack([_sample(sets, 250, seed=14), clump]))
    assert model.n_sets == 2 and all(angle < 3 for angle, _ in _match(model, sets)), model.bic


def _oriented(poles, eigen, K, **extra):
    """Traces already oriented: final poles, eigen poles and K (M = 8), with `extra` on every trace."""
    return [Trace3D(i + 1, np.zeros((3, 3)), np.zeros((3, 2)), np.zeros(3), np.zeros(3), ("a",), normal=n, K=k,
                    M=8.0, extra={"eigen_normal": e.tolist(), **extra})
            for i, (n, e, k) in enumerate(zip(poles, eigen, K))]


def test_set_spread_from_measured_poles_not_from_poles_pulled_to_the_prior():
    """Half the traces are collinear: the solver pulls their poles 40% of the way to the set mean (a linear
    pool's principal direction between eigen and prior, MATHS §1.4), and their eigen poles are noise. The
    set's mean comes from all poles, its κ from the measured (K < 2, M > 6) eigen poles."""
    mu, kappa = dip_dipdir_to_normal(80, 120), 20.0
    true = _sample([(mu, kappa)], 600, seed=15, flip=False)
    pulled = true + 0.4 * (mu - true)
    pulled /= np.linalg.norm(pulled, axis=1, keepdims=True)
    noise = np.random.default_rng(16).normal(size=(300, 3))
    traces = _oriented(np.vstack([true[:300], pulled[300:]]), np.vstack([true[:300], noise]),
                       np.r_[np.full(300, 0.5), np.full(300, 5.0)])
    model = classify_traces(traces, n_sets=1)
    (angle, ratio), = _match(model, [(mu, kappa)])
    stats, measured = model.sets[0], set_statistics(true[:300])
    assert angle < 1.5 and stats.n > 570  # all poles count (a few beyond θ99 are non-systematic)
    assert stats.kappa == pytest.approx(measured.kappa, rel=0.01) and abs(ratio - 1) < 0.2  # sampling: ×1.16
    (_, pooled), = _match(fit_sets(np.array([t.normal for t in traces]), n_sets=1), [(mu, kappa)])
    assert pooled > 1.3 * ratio  # what all the poles would say
    assert stats.theta99 == pytest.approx(np.degrees(fisher_aperture(stats.kappa)), rel=1e-9)
    assert stats.alpha95 == pytest.approx(140 / np.sqrt(stats.kappa_fisher * stats.n), rel=0.05)


def test_traces_in_the_surface_plane_count_in_no_set():
    """Traces flagged by orientation as lying in the outcrop surface's plane (their only plane is the
    wall's) are non-systematic and do not move the sets; the number of sets comes from the measured poles."""
    sets = [(dip_dipdir_to_normal(80, 120), 30.0), (dip_dipdir_to_normal(85, 230), 30.0)]
    poles = _sample(sets, 150, seed=17)
    wall = _sample([(np.array([0.0, -1.0, 0.0]), 200.0)], 40, seed=18)  # 40 curves drawn on the face
    traces = _oriented(poles, poles, np.full(300, 0.5)) + _oriented(wall, wall, np.full(40, 0.5), surface_plane=True)
    model = classify_traces(traces)
    assert model.n_sets == 2 and all(angle < 3 for angle, _ in _match(model, sets))
    assert np.all(model.labels[300:] == -1) and [t.set_id for t in traces] == model.labels.tolist()
    assert np.mean(model.labels[:300] >= 0) > 0.97
    everything = fit_sets(np.vstack([poles, wall]))
    assert everything.n_sets == 3  # unflagged, the face's poles make a set of their own
    with pytest.raises(InputError, match="1 of 41 traces show a plane of their own"):
        classify_traces(traces[:1] + traces[300:])


# ---------------------------------------------------------------------------------------------------------
# statistics


def test_set_statistics_against_scipy_and_fisher():
    mu = dip_dipdir_to_normal(60, 45)
    poles = _sample([(mu, 25.0)], 60, seed=6)
    stats = set_statistics(poles)
    flipped = np.where((poles @ mu)[:, None] < 0, -poles, poles)
    mu_hat, kappa_hat = vonmises_fisher.fit(flipped)
    assert stats.kappa == pytest.approx(kappa_hat, rel=1e-9)
    assert axial_angle(stats.normal, mu_hat) < 1e-9
    R = np.linalg.norm(flipped.sum(axis=0))
    assert stats.kappa_fisher == pytest.approx(59 / (60 - R), rel=1e-12)
    assert stats.resultant == pytest.approx(R / 60, rel=1e-12)
    assert stats.theta99 == pytest.approx(np.degrees(fisher_aperture(stats.kappa)), rel=1e-12)
    # the same equation with (equal) weights; α95 ≈ 140°/√(κN) (Fisher 1953)
    weighted = set_statistics(poles, weights=np.full(60, 3.0))
    assert weighted.kappa == pytest.approx(stats.kappa, rel=1e-8) and weighted.weighted
    assert kappa_mle(R / 60) == pytest.approx(kappa_hat, rel=1e-8)
    assert stats.alpha95 == pytest.approx(140 / np.sqrt(stats.kappa_fisher * 60), rel=0.05)
    assert stats.dip_direction == pytest.approx(45, abs=6) and stats.dip == pytest.approx(60, abs=6)


def test_terzaghi_weights_correct_the_sampling_bias():
    """Keep poles with probability sin ρ (a planar outcrop with normal −y sees fractures ∝ sin ρ, MATHS §8):
    the unweighted mean is pushed away from the outcrop normal, the Terzaghi-weighted one is not."""
    rng = np.random.default_rng(7)
    mu = dip_dipdir_to_normal(85, 150)  # ≈ 30° from the outcrop normal
    poles = vonmises_fisher(mu, 10.0).rvs(40000, random_state=rng)
    outcrop = np.array([0.0, -1.0, 0.0])
    sin_rho = np.linalg.norm(np.cross(poles, outcrop), axis=1)
    seen = poles[rng.random(len(poles)) < sin_rho]
    w = terzaghi_weights(seen, np.tile(outcrop, (len(seen), 1)))
    assert w.max() <= 10.0 and w.min() >= 1.0
    biased, corrected = set_statistics(seen), set_statistics(seen, weights=w)
    assert axial_angle(biased.normal, mu) > 3.0
    assert axial_angle(corrected.normal, mu) < 1.0
    assert corrected.kappa == pytest.approx(10.0, rel=0.1)
    unknown = terzaghi_weights(seen[:3], np.full((3, 3), np.nan))
    np.testing.assert_array_equal(unknown, 1.0)


def test_density_peaks_at_the_set_means():
    sets = [(dip_dipdir_to_normal(85, 137), 43.0), (dip_dipdir_to_normal(30, 20), 16.0)]
    poles = _sample(sets, 300, seed=8)
    peaks = density_peaks(poles, min_fraction=0.2)  # the broad set peaks at a third of the tight one
    assert len(peaks) == 2 and peaks[0].density > peaks[1].density > 1
    assert axial_angle(peaks[0].normal, sets[0][0]) < 3.0
    assert axial_angle(peaks[1].normal, sets[1][0]) < 10.0  # a sharp kernel on a broad set of 300 poles
    assert peaks[0].dip == pytest.approx(85, abs=3)


def test_bad_inputs():
    poles = _sample(TABLE1, 3)
    with pytest.raises(InputError, match="7 sets asked for, but there are only 6 poles"):
        fit_sets(poles, n_sets=7)
    with pytest.raises(InputError, match="pole 1 is NaN"):
        fit_sets(np.array([[0, 0, 1.0], [np.nan, 0, 1], [1, 0, 0]]))
    trace = Trace3D(5, np.zeros((3, 3)), np.zeros((3, 2)), np.zeros(3), np.zeros(3), ("a",))
    with pytest.raises(InputError, match="trace 5 has no orientation"):
        classify_traces([trace])
    trace.normal = np.array([0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="3 sets asked for, but there are only 1 traces"):
        classify_traces([trace], n_sets=3)
    with pytest.raises(InputError, match="sets need at least 2"):
        fit_sets(poles[:1])


def test_a_number_of_sets_asked_for_is_kept_or_refused_and_counts_are_members():
    """Two sets of 40 poles and 4 scattered ones: asking for 2 sets gives 2 whose n are their member poles
    (the mixture's soft shares used to be rounded instead); asking for 12 is refused, never quietly fewer."""
    rng = np.random.default_rng(5)
    poles = np.vstack([_sample(TABLE1, 40, seed=5), rng.normal(size=(4, 3))])
    model = fit_sets(poles, n_sets=2)
    assert [s.n for s in model.sets] == [int(np.sum(model.labels == k)) for k in range(2)]
    assert sum(s.n for s in model.sets) + int(np.sum(model.labels == -1)) == len(poles)
    with pytest.raises(InputError, match="12 sets asked for, but only [0-9]+ of them gather 2 or more members"):
        fit_sets(poles, n_sets=12)


# ---------------------------------------------------------------------------------------------------------
# facets (Compass-style plane fits on the mesh)


def test_fit_facet_planarity_and_outcrop_rejection():
    rng = np.random.default_rng(9)
    normal = dip_dipdir_to_normal(70, 120)
    b1 = np.cross(normal, [0, 0, 1.0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(normal, b1)
    uv = rng.uniform(-0.5, 0.5, (200, 2))
    patch = uv[:, :1] * b1 + uv[:, 1:] * b2 + rng.normal(0, 0.002, (200, 1)) * normal
    facet = fit_facet(patch, outcrop_normal=[0, -1, 0])
    assert facet.accepted and axial_angle(facet.normal, normal) < 1.0
    assert facet.planarity > 0.95 and facet.rms == pytest.approx(0.002, rel=0.2)
    folded = np.column_stack([uv, np.abs(uv[:, 0])])  # a V-shaped patch: not one plane
    assert "planarity" in fit_facet(folded).rejected_reason
    face = fit_facet(patch, outcrop_normal=normal + [0.05, 0, 0])
    assert not face.accepted and "outcrop face" in face.rejected_reason
    with pytest.raises(InputError, match="collinear"):
        fit_facet(np.outer(np.linspace(0, 1, 5), [1.0, 2.0, 3.0]))


def test_fit_facet_rejects_a_rough_bowl_that_passes_the_planarity_test():
    """A shallow bowl of rock 0.6 m across with 7 cm of sag: planar enough by 1 − λ3/λ2, but 2–3 cm RMS
    from any plane, where a fracture face under mesh noise fits within millimetres."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(-0.3, 0.3, (400, 2))
    xy = xy[np.hypot(*xy.T) <= 0.3]
    bowl = np.column_stack([xy, 0.8 * (xy**2).sum(axis=1)])
    facet = fit_facet(bowl)
    assert facet.planarity > 0.75 and facet.rms > 0.04 * facet.radius
    assert "rough rock" in facet.rejected_reason
    assert fit_facet(bowl, max_relative_rms=1.0).accepted


def test_fit_mesh_facet_on_a_step():
    """A wall with an exposed fracture face (a step): the face is accepted, the wall itself rejected."""
    v, f = grid_wall(step=0.25)
    step = np.array([[4.0, 0.0, 1.0], [4.0, -0.6, 1.0], [4.0, -0.6, 2.0], [4.0, 0.0, 2.0]])  # plane x = 4
    mesh = Mesh(np.vstack([v, step]), np.vstack([f, len(v) + np.array([[0, 1, 2], [0, 2, 3]])]))
    facet = fit_mesh_facet(mesh, [len(f), len(f) + 1], outcrop_radius=3.0)
    assert facet.accepted and axial_angle(facet.normal, [1, 0, 0]) < 1e-6 and facet.planarity == pytest.approx(1)
    wall = fit_mesh_facet(mesh, np.arange(20))
    assert not wall.accepted and "outcrop face" in wall.rejected_reason
    with pytest.raises(InputError, match="face ids"):
        fit_mesh_facet(mesh, [len(mesh.faces)])


# ---------------------------------------------------------------------------------------------------------
# acceptance: Table 1 sets through the whole chain on the synthetic outcrop


def table1_traces(seed: int, *, density: float = 3.0, noise: float = 0.01, fracture_model: str = "planar"):
    """Traces of Table 1 fractures on the synthetic wall as a noisy mesh shows them.

    The exact traces (`engine.synthetic.mesh_traces`) are densified to 2.5 cm vertices and moved with the
    mesh noise interpolated on their faces (what a ray hitting the noisy mesh gives, without photos, so
    that ~1000 traces take seconds); the longest open trace of each fracture stands for it, with its
    fracture's pole in extra["true_normal"].
    """
    from engine.kappa import _densified
    from engine.mesh import barycentric
    from engine.synthetic import mesh_traces, sample_fractures, wall_mesh

    rng = np.random.default_rng(seed)
    v, f = wall_mesh(rng, width=20.0, height=8.0, spacing=0.1, roughness=0.15, hurst=0.75, relief=0.6)
    fractures, _ = sample_fractures(rng, (v.min(axis=0) - 2.5, v.max(axis=0) + 2.5), sets=DEFAULT_SETS,
                                    density=density, radius_max=2.5, fracture_model=fracture_model)
    shift = rng.normal(0.0, noise, v.shape)
    longest = {}
    for t in mesh_traces(v, f, fractures):
        if not t.closed and (t.fracture_id not in longest or t.length > longest[t.fracture_id].length):
            longest[t.fracture_id] = t
    traces = []
    for t in longest.values():
        p, face = _densified(t.points, t.face, 0.025)
        p = p + np.einsum("ij,ijk->ik", barycentric(p, v[f[face]]), shift[f[face]])
        if len(p) < 3:  # a tip of a few millimetres: nothing to orient
            continue
        traces.append(Trace3D(len(traces) + 1, p, np.zeros((len(p), 2)), face, np.zeros(len(p)), ("synthetic",),
                              extra={"true_normal": fractures[t.fracture_id].normal.tolist()}))
    return Mesh(v + shift, f), traces


@pytest.mark.parametrize("fracture_model", ["planar", "undulating"])
@pytest.mark.parametrize("seed", [21, 22, 23, 24])
def test_table1_sets_recovered_through_orientation(seed, fracture_model):
    """~1000 traces of Table 1 fractures (planar, or undulating with RMS 2% of the radius: the issue's
    setting) through a 1 cm-noise mesh: orient (eigen + probabilistic), cluster with Terzaghi weights; set
    means within 3° and κ within 25% of the generating values.

    Measured (session 10): planar ≤ 2.9°, κ × 0.86–1.11; undulating ≤ 2.9°, κ × 0.78–1.15. Held out (seeds
    25–28, not tested): planar ≤ 2.6° but 4.5° on seed 27 (3.4° before session 10; its true poles' own
    weighted mean is 3.0° off); undulating ≤ 2.7°, κ × 0.77–0.98. Before the solver's eigen component was centred on the in-surface fit, undulating
    fractures gave 1.9–6.0° (4.0–6.4° held out): the eigen poles of their collinear traces lie 6–9° nearer
    the outcrop normal than the fractures' (engine.orientation, DECISION on the eigen component).
    """
    mesh, traces = table1_traces(seed, fracture_model=fracture_model)
    assert len(traces) > 900
    orient_traces(traces, mesh, seed=1)
    model = classify_traces(traces, terzaghi=True)
    assert model.n_sets == 2
    for angle, ratio in _match(model, TABLE1):
        assert angle <= 3.0 and abs(ratio - 1) <= 0.25, _match(model, TABLE1)
    # a trace measures its fracture's local plane, so more poles of undulating fractures fall beyond their
    # set's 99% cone: in a set 97.0–98.3% (planar), 94.3–96.3% (undulating, held out included)
    assert np.mean([t.set_id >= 0 for t in traces]) > (0.97 if fracture_model == "planar" else 0.93)
