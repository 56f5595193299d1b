import inspect

import numpy as np
import pytest
from lifelines import KaplanMeierFitter
from lifelines.utils import median_survival_times, restricted_mean_survival_time
from scipy import stats

from engine.errors import InputError
from engine.lengths import (LengthTable, analyse_lengths, anderson_darling, by_set, fit_lengths, fit_power_law,
                            kaplan_meier, length_table)
from engine.traces import Trace3D


def _censored_sample(rng, n, draw, window):
    """Lengths seen through a window: traces longer than a random window size are cut there (censored)."""
    true = draw(rng, n)
    cut = rng.uniform(0, window, n)
    return np.minimum(true, cut), true > cut


def _lifelines_fit(x, c):
    return KaplanMeierFitter().fit(x, event_observed=~c, alpha=0.05)


@pytest.mark.parametrize("ties", [False, True])
def test_kaplan_meier_equals_lifelines(ties):
    rng = np.random.default_rng(7)
    x, c = _censored_sample(rng, 250, lambda r, n: r.lognormal(0.4, 0.8, n), 6.0)
    if ties:  # lengths rounded to centimetres: tied events and censorings
        x = np.round(x, 1) + 0.1
    km = kaplan_meier(x, c)
    ref = _lifelines_fit(x, c)
    sf = ref.survival_function_.iloc[1:, 0]  # lifelines starts its timeline at 0 with S = 1
    ci = ref.confidence_interval_.iloc[1:]
    np.testing.assert_array_equal(km.times, sf.index.to_numpy())
    np.testing.assert_allclose(km.survival, sf.to_numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(km.ci_low, ci.iloc[:, 0].to_numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(km.ci_high, ci.iloc[:, 1].to_numpy(), rtol=0, atol=1e-12)
    assert km.median == ref.median_survival_time_
    median_ci = median_survival_times(ref.confidence_interval_).to_numpy().ravel()
    assert km.median_ci == pytest.approx(tuple(median_ci), abs=1e-12)
    rmst = restricted_mean_survival_time(ref, t=km.horizon)
    assert km.rmst == pytest.approx(rmst, abs=1e-12)
    table = ref.event_table.iloc[1:]
    np.testing.assert_array_equal(km.n_at_risk, table["at_risk"].to_numpy())
    np.testing.assert_array_equal(km.n_events, table["observed"].to_numpy())


def test_linear_interval_is_plain_greenwood_not_lifelines():
    rng = np.random.default_rng(2)
    x, c = _censored_sample(rng, 120, lambda r, n: r.exponential(2.0, n), 5.0)
    linear = kaplan_meier(x, c, ci_method="linear")
    loglog = kaplan_meier(x, c)
    # by hand: S ± z S √G, G = Σ d/(n(n − d))
    n, d = linear.n_at_risk, linear.n_events
    greenwood = np.cumsum(np.where(n > d, d / (n * np.maximum(n - d, 1)), 0.0))
    half = stats.norm.ppf(0.975) * linear.survival * np.sqrt(greenwood)
    inside = (linear.survival > 0) & (linear.survival < 1)
    np.testing.assert_allclose(linear.ci_low[inside], np.clip(linear.survival - half, 0, 1)[inside], atol=1e-12)
    np.testing.assert_allclose(linear.ci_high[inside], np.clip(linear.survival + half, 0, 1)[inside], atol=1e-12)
    ref = _lifelines_fit(x, c).confidence_interval_.iloc[1:, 0].to_numpy()
    assert np.abs(linear.ci_low - ref).max() > 1e-3 and np.abs(loglog.ci_low - ref).max() < 1e-12


def test_restricted_mean_standard_error_matches_its_spread():
    rng = np.random.default_rng(11)
    estimates, errors = [], []
    for _ in range(300):
        x, c = _censored_sample(rng, 80, lambda r, n: r.exponential(1.5, n), 6.0)
        km = kaplan_meier(x, c, horizon=3.0)
        estimates.append(km.rmst)
        errors.append((km.rmst_ci[1] - km.rmst_ci[0]) / (2 * stats.norm.ppf(0.975)))
    truth = 1.5 * (1 - np.exp(-3.0 / 1.5))  # ∫₀³ exp(-t/1.5) dt
    assert np.mean(estimates) == pytest.approx(truth, rel=0.02)
    assert np.mean(errors) == pytest.approx(np.std(estimates), rel=0.12)


def test_median_undefined_when_survival_stays_above_half():
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    km = kaplan_meier(x, np.array([False, True, True, True, True]))
    assert km.median == np.inf and km.median_ci[1] == np.inf
    assert km.rmst == pytest.approx(1.0 + 0.8 * 4.0)  # S = 1 to 1, then 0.8 to the largest length


@pytest.mark.parametrize("model, draw, truth", [
    ("lognorm", lambda r, n: r.lognormal(np.log(1.65), 0.8, n), {"s": 0.8, "scale": 1.65}),
    ("weibull_min", lambda r, n: 2.0 * r.weibull(1.5, n), {"c": 1.5, "scale": 2.0}),
    ("expon", lambda r, n: r.exponential(2.0, n), {"scale": 2.0}),
])
def test_censored_mle_recovers_known_parameters(model, draw, truth):
    rng = np.random.default_rng(5)
    x, c = _censored_sample(rng, 3000, draw, 8.0)
    assert 0.2 < c.mean() < 0.6
    fit, = fit_lengths(x, c, models=(model,), n_bootstrap=0)
    for name, value in truth.items():
        assert fit.params[name] == pytest.approx(value, rel=0.05), name
    naive = getattr(stats, model).fit(x, floc=0)  # censoring ignored: biased towards short traces
    assert abs(naive[-1] - truth["scale"]) > 3 * abs(fit.params["scale"] - truth["scale"])
    assert fit.n_censored == c.sum() and fit.n_complete == (~c).sum() and np.isnan(fit.ad_pvalue)


def test_power_law_alpha_is_the_closed_form():
    rng = np.random.default_rng(3)
    x = 0.5 * (1 - rng.random(400)) ** (-1 / 1.4)  # Pareto: alpha = 2.4, x_min = 0.5
    complete = np.zeros(len(x), dtype=bool)
    law = fit_power_law(x, complete, x_min=0.5)
    assert law.alpha == pytest.approx(1 + len(x) / np.log(x / 0.5).sum(), rel=1e-12)
    assert law.alpha_se == pytest.approx((law.alpha - 1) / np.sqrt(len(x)), rel=1e-12)
    censored = rng.random(len(x)) < 0.3
    law = fit_power_law(x, censored, x_min=0.5)  # censored MLE: complete count over all log-ratios
    assert law.alpha == pytest.approx(1 + (~censored).sum() / np.log(x / 0.5).sum(), rel=1e-12)


def test_power_law_x_min_found_by_ks_minimisation():
    rng = np.random.default_rng(0)
    body = rng.lognormal(0, 0.5, 600)
    tail = 2 * (1 - rng.random(400)) ** (-1 / 1.5)  # alpha = 2.5 above x_min = 2
    x = np.r_[body[body < 2], tail]
    law = fit_power_law(x, np.zeros(len(x), dtype=bool))
    assert law.x_min == pytest.approx(2.0, rel=0.05) and law.alpha == pytest.approx(2.5, abs=0.1)
    tail_x = x[x >= law.x_min]
    assert law.alpha == pytest.approx(1 + len(tail_x) / np.log(tail_x / law.x_min).sum(), rel=1e-12)
    # the KS distance it minimised: sup |ECDF − F| over the tail
    assert law.ks_distance == pytest.approx(stats.kstest(tail_x, stats.pareto(law.alpha - 1,
                                                                              scale=law.x_min).cdf).statistic)


def _anderson(x, dist):
    # SciPy ≥ 1.17 warns unless a p-value method is chosen; the statistic does not depend on it
    method = {"method": "interpolate"} if "method" in inspect.signature(stats.anderson).parameters else {}
    return stats.anderson(x, dist, **method).statistic


def test_anderson_darling_equals_scipy_on_complete_data():
    rng = np.random.default_rng(1)
    complete = np.zeros(60, dtype=bool)
    x = rng.exponential(2.0, 60)
    assert anderson_darling(x, complete, stats.expon(scale=x.mean()).cdf) == pytest.approx(
        _anderson(x, "expon"), rel=1e-12)
    y = rng.lognormal(0.3, 0.7, 60)
    m, s = np.log(y).mean(), np.log(y).std(ddof=1)  # `anderson(log y, 'norm')` uses ddof = 1
    assert anderson_darling(y, complete, stats.lognorm(s, scale=np.exp(m)).cdf) == pytest.approx(
        _anderson(np.log(y), "norm"), rel=1e-12)
    result = stats.goodness_of_fit(stats.lognorm, y, known_params={"loc": 0}, n_mc_samples=9, random_state=0)
    assert anderson_darling(y, complete, stats.lognorm(*result.fit_result.params).cdf) == pytest.approx(
        result.statistic, rel=1e-12)


def test_censored_anderson_darling_ranks_the_true_model_first():
    rng = np.random.default_rng(4)
    x, c = _censored_sample(rng, 400, lambda r, n: r.lognormal(0.5, 0.7, n), 8.0)
    fits = fit_lengths(x, c, models=("lognorm", "expon", "weibull_min"), n_bootstrap=49, seed=1)
    assert min(fits, key=lambda f: f.censored_ad_distance).model == "lognorm"
    assert min(fits, key=lambda f: f.aic).model == "lognorm"
    expon = fits[1]
    assert expon.ad_pvalue <= 0.05 and 0 < fits[0].ad_pvalue <= 1  # exponential rejected on complete traces
    again = fit_lengths(x, c, models=("lognorm", "expon", "weibull_min"), n_bootstrap=49, seed=1)
    assert [f.ad_pvalue for f in again] == [f.ad_pvalue for f in fits]  # seeded


def test_fit_lengths_with_power_law_reports_the_tail():
    rng = np.random.default_rng(8)
    x = 0.3 * (1 - rng.random(300)) ** (-1 / 1.2)
    c = rng.random(300) < 0.2
    fits = {f.model: f for f in fit_lengths(x, c, n_bootstrap=19)}
    law = fits["powerlaw"]
    assert law.x_min == law.params["x_min"] and law.n_fit == np.count_nonzero(x >= law.x_min)
    assert law.params["alpha"] == pytest.approx(2.2, abs=0.25)
    assert np.isfinite(law.ad_statistic) and np.isfinite(law.censored_ad_distance)
    few = fit_lengths(x[:8], c[:8], models=("powerlaw",), n_bootstrap=0)[0]
    assert np.isnan(few.aic) and "at least 10 complete traces" in few.note


def test_bad_length_data_gives_clear_messages():
    with pytest.raises(InputError, match="empty"):
        kaplan_meier([], [])
    with pytest.raises(InputError, match="all 3 traces are censored"):
        kaplan_meier([1.0, 2.0, 3.0], [True, True, True])
    with pytest.raises(InputError, match=r"length -1 \(trace 1\) must be a positive number"):
        kaplan_meier([1.0, -1.0], [False, False])
    with pytest.raises(InputError, match="only 1 of 3 traces are complete"):
        fit_lengths([1.0, 2.0, 3.0], [False, True, True])
    with pytest.raises(InputError, match="unknown length model"):
        fit_lengths([1.0, 2.0, 3.0], [False, False, False], models=("gamma",))
    result = analyse_lengths([1.0, 2.0], [True, True], label="set 3")
    assert result.kaplan_meier is None and result.message.startswith("set 3: all 2 traces are censored")


def test_length_table_and_by_set():
    def trace(i, points, set_id, ends):
        n = len(points)
        return Trace3D(i, points, np.zeros((n, 2)), np.zeros(n), np.zeros(n), ("a",), set_id=set_id,
                       term_start=ends[0], term_end=ends[1])

    bent = np.array([[0.0, 0, 0], [3, 4, 0], [6, 0, 0]])
    table = length_table([trace(1, bent, 0, ("B", "C")), trace(2, bent[:2], 1, ("C", "C")),
                          trace(3, bent[1:], 0, ("T", "B"))])
    np.testing.assert_allclose(table.surface, [10.0, 5.0, 5.0])
    np.testing.assert_allclose(table.chord, [6.0, 5.0, 5.0])
    assert table.n_censored_ends.tolist() == [1, 2, 0] and table.censored.tolist() == [True, True, False]
    rng = np.random.default_rng(0)
    n = 60
    big = LengthTable(np.arange(n), np.repeat([0, 1], n // 2), rng.uniform(1, 2, n), rng.uniform(1, 3, n),
                      np.r_[rng.integers(0, 2, n // 2), np.full(n // 2, 1)])
    groups = by_set(big, models=("expon",), n_bootstrap=0)
    assert set(groups) == {"0", "1"} and groups["0"].kaplan_meier is not None
    assert "all 30 traces are censored" in groups["1"].message
    with pytest.raises(InputError, match="length 'area' must be one of surface, chord"):
        big.lengths("area")


def test_the_bootstraps_weibull_fit_is_the_maximum_likelihood_estimate():
    """The Weibull fit of the goodness-of-fit bootstrap (loc fixed at 0) solves the likelihood equation:
    at least as likely as scipy's own fit on 200 random samples (5–300 lengths, shapes 0.3–5), within
    2e-4 of it, and the same A² p-value; other calls go to scipy's fit."""
    from engine.lengths import _WEIBULL

    rng = np.random.default_rng(3)
    for _ in range(200):
        x = stats.weibull_min.rvs(rng.uniform(0.3, 5), scale=rng.uniform(0.01, 50), size=rng.integers(5, 300),
                                  random_state=rng)
        theirs, ours = stats.weibull_min.fit(x, floc=0), _WEIBULL.fit(x, floc=0)
        assert ours[1] == 0.0 and np.allclose([ours[0], ours[2]], [theirs[0], theirs[2]], rtol=2e-4)
        loglik = [stats.weibull_min.logpdf(x, c, 0, s).sum() for c, _, s in (theirs, ours)]
        assert loglik[1] >= loglik[0] - 1e-9 * abs(loglik[0])
        c, _, s = ours  # the shape's likelihood equation holds
        assert np.sum(x**c * np.log(x)) / np.sum(x**c) - 1 / c - np.mean(np.log(x)) == pytest.approx(0, abs=1e-9)
        assert s == pytest.approx(np.mean(x**c) ** (1 / c), rel=1e-9)
    x = stats.weibull_min.rvs(1.3, scale=2.0, size=60, random_state=1)
    p = [stats.goodness_of_fit(d, x, known_params={"loc": 0}, statistic="ad", n_mc_samples=199,
                               random_state=1).pvalue for d in (stats.weibull_min, _WEIBULL)]
    assert p[1] == pytest.approx(p[0], abs=0.01)
    assert _WEIBULL.fit(x) == pytest.approx(stats.weibull_min.fit(x), rel=1e-6)  # loc free: scipy's own
