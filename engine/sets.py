"""Fracture sets: axial clustering of poles, Fisher statistics, density peaks and mesh facets (MATHS §10, §8).

Poles are axial (n ≡ −n). `fit_sets`:

1. axial spherical k-means (|n·μ| form, k-means++ starts, best of several; Dhillon & Modha 2001), started
   from a k-means of the best-constrained poles: high-quality traces (K < 2, M > 6, Seers & Hodgetts
   2016a) and fracture-plane facets measured on the mesh (`fit_facet`, `fit_mesh_facet`);
2. an EM fit of a mixture of k axial Fisher sets plus a uniform background from those clusters, so sets
   that overlap (Table 1's do: θ99 ≈ 57° for κ = 9.8, 95° apart) do not truncate each other's tails, and
   scattered poles (badly constrained traces, strays) widen no set: the background is the non-systematic
   class;
3. the number of sets, unless given (DECISION): the smallest k in 1..max_sets whose Bayesian information
   criterion, BIC = −2 ln L + 4k ln N (a mean, a κ and a share per set), is within BIC_MARGIN of the lowest,
   among the fits whose every component holds at least MIN_SET_SHARE of the poles. The margin asks for
   "very strong" evidence (Kass & Raftery 1995) before adding a set: real sets are not exactly Fisher, and
   with ~1000 poles a skewed set is otherwise cut in two. A component as tight as KAPPA_MAX is a clump, not
   a set: its poles are non-systematic;
4. poles most probably from the background, or beyond their set's 99% aperture (or a given angle), are
   non-systematic, set −1;
5. per set: Fisher mean (dip, dip direction), κ (MLE, and Fisher's (N − 1)/(N − R)), α95, θ99, optionally
   with Terzaghi (1965) weights w = min(1/sin ρ, 10) against the local outcrop normal (MATHS §8); the
   spread from a subset of measured poles when given (`classify_traces` DECISION);
6. density peaks of an exponential-Kamb (Fisher-kernel) density.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numba
import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import vonmises_fisher

from engine.errors import InputError
from engine.mesh import Mesh
from engine.orientation import (HIGH_QUALITY, axial_angle, fisher_aperture, local_surface_normal,
                                normal_to_dip_dipdir, upward)
from engine.traces import Trace3D

W_MAX = 10.0
"""Cap of the Terzaghi weight 1/sin ρ (MATHS §8 DECISION; a blind zone of about 5.7°)."""

MIN_SET_SHARE = 0.03
"""Smallest share of the poles a set found automatically may hold."""

KAPPA_MAX = 500.0
"""κ cap of the mixture (θ99 ≈ 7.8°). Natural sets are looser: components reaching it on the synthetic outcrop
were clumps of near-identical poles (pieces of one occluded fracture extracted in parts; nearly straight
traces whose eigen plane is forced perpendicular to the outcrop by its relief), so they make no set."""

MIN_SEEDS = 5
"""Fewest high-quality poles from which `classify_traces` chooses the number of sets (as the priors do)."""

BIC_MARGIN = 10.0
"""A BIC within this of the lowest is as good: the smallest such number of sets is chosen."""


@dataclass(frozen=True)
class FractureSetStats:
    """One fracture set (MATHS §10). Angles in degrees.

    id; n: members; normal: upward Fisher mean pole, with its dip and dip_direction; kappa: MLE
    (coth κ − 1/κ = R̄); kappa_fisher: (N − 1)/(N − R); alpha95: confidence cone of the mean; theta99: cone
    holding 99% of the poles (the aperture of the orientation prior); resultant: R̄; weighted: Terzaghi
    weights were used (then R and N are the weighted sums scaled to the member count).
    """

    id: int
    n: int
    normal: np.ndarray
    dip: float
    dip_direction: float
    kappa: float
    kappa_fisher: float
    alpha95: float
    theta99: float
    resultant: float
    weighted: bool = False


@dataclass(frozen=True)
class DensityPeak:
    """A local maximum of the pole density: upward pole, dip, dip direction (degrees), density in multiples
    of a uniform distribution."""

    normal: np.ndarray
    dip: float
    dip_direction: float
    density: float


@dataclass(frozen=True)
class SetModel:
    """Sets fitted to poles. labels (N,): set id of each pole, −1 non-systematic; peaks: density maxima,
    highest first; bic: the criterion per number of sets tried (empty when the number was given; a k whose
    fit broke the MIN_SET_SHARE rule is absent unless every k did); cutoff: the angle (degrees) beyond which a pole
    is non-systematic, per set; background: the share of poles the mixture gives the non-systematic class."""

    sets: tuple[FractureSetStats, ...]
    labels: np.ndarray
    peaks: tuple[DensityPeak, ...]
    bic: dict[int, float]
    cutoff: tuple[float, ...]
    background: float

    @property
    def n_sets(self) -> int:
        return len(self.sets)

    def assign(self, poles: np.ndarray) -> np.ndarray:
        """Set id of new poles (N, 3): the nearest set mean, −1 beyond that set's cutoff."""
        if not self.sets:
            return np.full(len(poles), -1)
        angle = axial_angle(np.asarray(poles)[:, None], np.array([s.normal for s in self.sets])[None])
        best = np.argmin(angle, axis=1)
        return np.where(angle[np.arange(len(best)), best] <= np.array(self.cutoff)[best], best, -1)


# ---------------------------------------------------------------------------------------------------------
# clustering


def axial_kmeans(poles: np.ndarray, k: int, *, init: np.ndarray | None = None, n_init: int = 10, seed: int = 0,
                 max_iter: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Axial spherical k-means (MATHS §10): labels (N,) and upward centres (k, 3).

    Assign by max |n·μ|; update μ to the principal eigenvector of Σ n nᵀ over the members. Starts from
    `init` (k, 3) if given, else the best of `n_init` k-means++ starts (distance 1 − |n·μ|) by Σ|n·μ|.
    """
    poles = _unit_poles(poles)
    _check_k(k, len(poles))
    rng = np.random.default_rng(seed)
    starts = [np.asarray(init, dtype=float)] if init is not None else [_kmeans_pp(poles, k, rng)
                                                                       for _ in range(n_init)]
    best = None
    for centres in starts:
        labels, centres = _lloyd(poles, upward(centres), max_iter)
        score = np.abs(np.sum(poles * centres[labels], axis=1)).sum()
        if best is None or score > best[0]:
            best = (score, labels, centres)
    return best[1], best[2]


def _kmeans_pp(poles, k, rng):
    centres = [poles[rng.integers(len(poles))]]
    for _ in range(1, k):
        d = 1.0 - np.abs(poles @ np.array(centres).T).max(axis=1)
        p = d**2
        pick = rng.choice(len(poles), p=p / p.sum()) if p.sum() > 0 else rng.integers(len(poles))
        centres.append(poles[pick])
    return np.array(centres)


def _lloyd(poles, centres, max_iter):
    labels = np.argmax(np.abs(poles @ centres.T), axis=1)
    for _ in range(max_iter):
        for j in range(len(centres)):
            members = poles[labels == j]
            if len(members):
                centres[j] = upward(np.linalg.eigh(members.T @ members)[1][:, -1])
        new = np.argmax(np.abs(poles @ centres.T), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
    return labels, centres


@dataclass(frozen=True)
class Mixture:
    """An axial Fisher mixture with a uniform background: upward centres (k, 3), κ (k,), shares (k + 1,; the
    last is the background's), responsibilities (N, k + 1) and the (weighted) log-likelihood."""

    centres: np.ndarray
    kappa: np.ndarray
    shares: np.ndarray
    resp: np.ndarray
    loglik: float

    def bic(self, n: float) -> float:
        """Bayesian information criterion for n poles: a mean (2), a κ and a share per set."""
        return -2.0 * self.loglik + 4 * len(self.centres) * np.log(n)


def axial_mixture(poles: np.ndarray, centres: np.ndarray, *, weights: np.ndarray | None = None,
                  background: bool = True, iterations: int = 200) -> Mixture:
    """EM for a mixture of axial Fisher sets, C(κ) cosh(κ μ·n), and a uniform 1/4π, from initial centres (k, 3).

    With overlapping sets, hard clusters cut each set's tail at the bisector and overstate κ (by about 12%
    for the two sets of Seers & Hodgetts 2016a Table 1); the responsibilities do not. A pole's sign is a
    latent variable with E[sign] = tanh(κ μ·n). weights: per-pole weights (e.g. Terzaghi) in the M-step and
    the likelihood. background False: no uniform component (its share stays 0). κ is capped at KAPPA_MAX.
    The iterations are compiled and release the GIL: in Python their many small steps kept the 3D viewer's
    thread waiting for it while sets were fitted.
    """
    poles = _unit_poles(poles)
    w = np.ones(len(poles)) if weights is None else np.asarray(weights, dtype=float)
    centres = upward(np.asarray(centres, dtype=float)).copy()
    k = len(centres)
    nearest = np.eye(k + 1)[np.argmax(np.abs(poles @ centres.T), axis=1)]
    resp = np.ascontiguousarray(0.9 * nearest + 0.1 * np.eye(k + 1)[k] if background else nearest)
    kappa = np.ones(k)
    shares = np.zeros(k + 1)
    loglik = _em(np.ascontiguousarray(poles), np.ascontiguousarray(w), centres, kappa, resp, shares,
                 int(iterations), KAPPA_MAX)
    return Mixture(centres, kappa, shares, resp, loglik)


@numba.njit("float64(float64, float64)", nogil=True, cache=True)
def _log_axial_fisher(cos: float, kappa: float) -> float:
    """log of the axial Fisher density C(κ) cosh(κ μ·n) on the sphere from cos = μ·n; overflow-free."""
    kappa = max(kappa, 1e-12)
    t = kappa * abs(cos)
    log_cosh = t + np.log1p(np.exp(-2.0 * t)) - np.log(2.0)
    log_c = np.log(kappa) - np.log(2.0 * np.pi) - kappa - np.log1p(-np.exp(-2.0 * kappa))  # κ / (4π sinh κ)
    return log_c + log_cosh


def kappa_mle(rbar: float) -> float:
    """Fisher κ with coth κ − 1/κ = R̄ (the MLE on S², MATHS §10); 0 for R̄ ≤ 0."""
    return float(_kappa_mle(float(rbar)))


@numba.njit("float64(float64)", nogil=True, cache=True)
def _kappa_mle(rbar: float) -> float:
    """`kappa_mle` by bisection on coth κ − 1/κ (increasing in κ) to a relative 1e-13; series below κ = 1e-3,
    where the difference cancels."""
    if rbar <= 1e-12:
        return 0.0
    if rbar >= 1 - 1e-12:
        return 1e12
    lo, hi = 1e-9, 1.0 / (1.0 - rbar) + 10.0
    while hi - lo > 1e-13 * hi:
        mid = 0.5 * (lo + hi)
        f = mid / 3.0 - mid ** 3 / 45.0 if mid < 1e-3 else 1.0 / np.tanh(mid) - 1.0 / mid
        if f < rbar:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# compiled when this module is imported (or loaded from numba's cache), not at the first fit on a worker
# thread, where compiling would hold the GIL for seconds
@numba.njit("float64(float64[:, ::1], float64[::1], float64[:, ::1], float64[::1], float64[:, ::1], float64[::1], "
            "int64, float64)", nogil=True, cache=True)
def _em(poles: np.ndarray, w: np.ndarray, centres: np.ndarray, kappa: np.ndarray, resp: np.ndarray,
        shares: np.ndarray, iterations: int, kappa_max: float) -> float:
    """`axial_mixture`'s iterations, updating centres, kappa, resp and shares in place; the log-likelihood."""
    n, k = poles.shape[0], centres.shape[0]
    log_p = np.empty(k + 1)
    previous, loglik = -np.inf, -np.inf
    for _ in range(iterations):
        shares[:] = 0.0
        for i in range(n):
            for j in range(k + 1):
                shares[j] += resp[i, j] * w[i]
        shares /= shares.sum()
        for j in range(k):  # M-step: each set's mean and κ, the sign of each pole weighed by tanh(κ μ·n)
            total, sx, sy, sz = 0.0, 0.0, 0.0, 0.0
            for i in range(n):
                weight = resp[i, j] * w[i]
                c = poles[i, 0] * centres[j, 0] + poles[i, 1] * centres[j, 1] + poles[i, 2] * centres[j, 2]
                sign = weight * np.tanh(kappa[j] * c)
                total += weight
                sx, sy, sz = sx + sign * poles[i, 0], sy + sign * poles[i, 1], sz + sign * poles[i, 2]
            length = np.sqrt(sx * sx + sy * sy + sz * sz)
            if total > 0 and length > 0:
                up = 1.0 if sz >= 0 else -1.0
                centres[j, 0], centres[j, 1], centres[j, 2] = up * sx / length, up * sy / length, up * sz / length
                kappa[j] = min(_kappa_mle(min(length / total, 1.0 - 1e-12)), kappa_max)
        loglik = 0.0
        for i in range(n):  # E-step
            for j in range(k):
                c = poles[i, 0] * centres[j, 0] + poles[i, 1] * centres[j, 1] + poles[i, 2] * centres[j, 2]
                log_p[j] = _log_axial_fisher(c, kappa[j]) + np.log(max(shares[j], 1e-300))
            log_p[k] = -np.log(4.0 * np.pi) + np.log(max(shares[k], 1e-300))
            top = log_p.max()
            total = 0.0
            for j in range(k + 1):
                resp[i, j] = np.exp(log_p[j] - top)
                total += resp[i, j]
            loglik += w[i] * (top + np.log(total))
            for j in range(k + 1):
                resp[i, j] /= total
        if loglik - previous <= 1e-9 * n:
            break
        previous = loglik
    return loglik


# ---------------------------------------------------------------------------------------------------------
# statistics


def set_statistics(poles: np.ndarray, *, weights: np.ndarray | None = None, membership: np.ndarray | None = None,
                   set_id: int = 0, confidence: float = 0.95, aperture: float = 0.99) -> FractureSetStats:
    """Fisher statistics of one set of axial poles (N, 3) (MATHS §10).

    Poles are flipped toward the principal axis first. weights : relative weights, e.g. `terzaghi_weights`.
    membership : the share (0–1) of each pole that belongs to the set (a mixture's responsibilities);
    the set then counts N = Σ membership poles. κ is the MLE: `scipy.stats.vonmises_fisher.fit` on the
    flipped poles when neither is given, else the same equation coth κ − 1/κ = R̄ with the weights.
    """
    poles = _unit_poles(poles)
    share = np.ones(len(poles)) if membership is None else np.asarray(membership, dtype=float)
    n = float(share.sum())
    if n < 2:
        raise InputError(None, f"set {set_id}: {n:g} poles; statistics need at least 2")
    w = share if weights is None else share * np.asarray(weights, dtype=float)
    w = w * n / w.sum()  # weighted sums scaled to the member count, so N − R keeps its meaning
    axis = np.linalg.eigh((poles * w[:, None]).T @ poles)[1][:, -1]
    flipped = np.where((poles @ axis)[:, None] < 0, -poles, poles)
    resultant = w @ flipped
    R = float(np.linalg.norm(resultant))
    mean = upward(resultant)
    if weights is None and membership is None:
        kappa = float(vonmises_fisher.fit(flipped)[1])
    else:
        kappa = kappa_mle(R / n)
    dip, dipdir = normal_to_dip_dipdir(mean)
    return _with_spread(FractureSetStats(set_id, int(round(n)), mean, float(dip), float(dipdir), kappa, 0.0, 0.0,
                                         0.0, 0.0, weights is not None), n, R / n, kappa, confidence, aperture)


def _with_spread(stats: FractureSetStats, n: float, rbar: float, kappa: float, confidence: float,
                 aperture: float) -> FractureSetStats:
    """`stats` with the dispersion of n poles of mean resultant length R̄ and MLE κ: κ, κ_Fisher, α95, θ99."""
    R = n * rbar
    cos_alpha = 1.0 - (n - R) / R * ((1.0 / (1.0 - confidence)) ** (1.0 / (n - 1)) - 1.0)
    return replace(stats, kappa=kappa, kappa_fisher=float((n - 1) / (n - R) if n > R else np.inf),
                   alpha95=float(np.degrees(np.arccos(np.clip(cos_alpha, -1.0, 1.0)))),
                   theta99=float(np.degrees(fisher_aperture(kappa, aperture))), resultant=rbar)


def measured_spread(sets: Sequence[FractureSetStats], spread_poles: np.ndarray, *, weights: np.ndarray | None = None,
                    confidence: float = 0.95, aperture: float = 0.99) -> tuple[FractureSetStats, ...]:
    """Sets whose dispersion (κ, κ_Fisher, α95, θ99, R̄) is that of the measured poles: the finite rows of
    `spread_poles` (N, 3), NaN where a pole was inferred (`classify_traces` DECISION); means and counts stay.

    The measured poles get their own mixture (`axial_mixture`, started at the sets' means, `weights` as in
    `fit_sets`), so that their tails are not cut where the sets' κ from all poles would put the background.
    A set with fewer than 2 measured poles' worth keeps its dispersion.
    """
    rows = np.isfinite(spread_poles).all(axis=1)
    if not sets or rows.sum() < 2:
        return tuple(sets)
    w = np.ones(len(spread_poles)) if weights is None else np.asarray(weights, dtype=float)
    measured = _unit_poles(spread_poles[rows])
    mixture = axial_mixture(measured, np.array([s.normal for s in sets]), weights=w[rows])
    out = []
    for j, s in enumerate(sets):
        share = mixture.resp[:, j]
        if share.sum() < 2:
            out.append(s)
            continue
        weighted = share * w[rows]
        flipped = np.where((measured @ mixture.centres[j])[:, None] < 0, -measured, measured)
        rbar = float(np.linalg.norm(weighted @ flipped) / weighted.sum())
        out.append(_with_spread(s, s.n, rbar, kappa_mle(rbar), confidence, aperture))
    return tuple(out)


def terzaghi_weights(poles: np.ndarray, surface_normals: np.ndarray, *, w_max: float = W_MAX) -> np.ndarray:
    """Terzaghi (1965) weights w = 1/sin ρ for planar sampling, capped at `w_max` (MATHS §8).

    ρ is the angle between each pole and its outcrop normal (N, 3); an unknown normal (NaN) gives w = 1.
    """
    s = np.asarray(surface_normals, dtype=float)
    sin_rho = np.linalg.norm(np.cross(_unit_poles(poles), s / np.linalg.norm(s, axis=1, keepdims=True)), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.minimum(1.0 / sin_rho, w_max)
    return np.where(np.isfinite(sin_rho), w, 1.0)


def density_peaks(poles: np.ndarray, *, weights: np.ndarray | None = None, kappa: float | None = None,
                  separation: float = 20.0, min_fraction: float = 0.4,
                  n_grid: int = 20000) -> tuple[DensityPeak, ...]:
    """Maxima of a Fisher-kernel pole density on the sphere (exponential Kamb, Vollmer 1995), highest first.

    kappa : kernel concentration, default 2(1 + N/9) (Vollmer's k with σ = 3) capped at 100 (about 6° of
        smoothing), so that the peaks of a thousand poles are not sampling noise. Density in multiples of
    uniform, on a Fibonacci grid of `n_grid` axes (about 1.4° apart for the default); a peak is the
    highest point within `separation` degrees and at least `min_fraction` of the highest density.
    """
    poles = _unit_poles(poles)
    w = np.ones(len(poles)) if weights is None else np.asarray(weights, dtype=float)
    kappa = min(2.0 * (1.0 + len(poles) / 9.0), 100.0) if kappa is None else float(kappa)
    grid = _fibonacci_hemisphere(n_grid)
    # 4π C(κ) cosh(κ t) relative to the uniform 1/4π, t = |x·n|: the sum of e^{κ(x·m − 1)} over m = ±n,
    # taken over the pairs closer than where e^{κ(cos − 1)} < e^{-25} (the rest is negligible)
    both, wb = np.vstack([poles, -poles]), np.concatenate([w, w])
    reach = np.sqrt(2.0 * min(25.0 / kappa, 2.0)) + 1e-9  # chord length
    pairs = cKDTree(grid).sparse_distance_matrix(cKDTree(both), reach, output_type="coo_matrix")
    terms = wb[pairs.col] * np.exp(-0.5 * kappa * pairs.data**2)  # 1 − cos = chord²/2
    density = np.bincount(pairs.row, terms, minlength=len(grid)) * kappa / -np.expm1(-2 * kappa) / w.sum()
    # local maxima among the nearest grid axes (antipodes included: neighbours across the equator), then
    # the lower of two maxima closer than `separation` is dropped
    neighbours = cKDTree(np.vstack([grid, -grid])).query(grid, k=9)[1] % len(grid)
    candidates = np.flatnonzero((density >= density[neighbours].max(axis=1))
                                & (density >= min_fraction * density.max()))
    peaks = []
    for i in candidates[np.argsort(-density[candidates])]:
        if not peaks or axial_angle(grid[i], grid[peaks]).min() >= separation:
            peaks.append(i)
    dip, dipdir = normal_to_dip_dipdir(grid[peaks]) if peaks else ([], [])
    return tuple(DensityPeak(grid[i], float(a), float(b), float(density[i])) for i, a, b in zip(peaks, dip, dipdir))


def _fibonacci_hemisphere(n: int) -> np.ndarray:
    """n nearly uniform unit vectors with z ≥ 0 (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    r = np.sqrt(1.0 - z**2)
    theta = np.pi * (1 + 5**0.5) * k
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), z])


# ---------------------------------------------------------------------------------------------------------
# set model


def fit_sets(poles: np.ndarray, *, n_sets: int | None = None, max_sets: int = 6,
             seed_poles: np.ndarray | None = None, weights: np.ndarray | None = None,
             outlier_angle: float | None = None, aperture: float = 0.99, n_init: int = 10, seed: int = 0,
             find_peaks: bool = True, spread_poles: np.ndarray | None = None) -> SetModel:
    """Fracture sets of axial poles (N, 3) (module docstring, steps 1–6).

    n_sets : number of sets; default chosen by BIC among 1..`max_sets` (step 3).
    seed_poles : the best-constrained poles (high-quality traces, facets); the clusters start from an
        axial k-means of these, so noisier poles cannot pull the set centres at the start.
    weights : per-pole weights (`terzaghi_weights`) for the mixture and the set statistics.
    outlier_angle : degrees from its set mean beyond which a pole is non-systematic (−1); default each
        set's `aperture` cone (θ99 of its κ).
    find_peaks : also locate the density peaks (`density_peaks`; orientation priors skip them).
    spread_poles : (N, 3) the poles that measure the sets' spread, NaN where not (`measured_spread`).
    """
    poles = _unit_poles(poles)
    if len(poles) < 2:
        raise InputError(None, f"poles: {len(poles)} given; sets need at least 2")
    w = np.ones(len(poles)) if weights is None else np.asarray(weights, dtype=float)
    w = w * len(poles) / w.sum()  # the likelihood counts N poles whatever the weights' scale
    if n_sets is not None:
        _check_k(n_sets, len(poles))
    seeds = poles if seed_poles is None or len(seed_poles) == 0 else _unit_poles(seed_poles)
    tried = [n_sets] if n_sets is not None else list(range(1, min(max_sets, len(poles) - 1) + 1))
    fits = {}
    for k in tried:
        start = axial_kmeans(seeds, k, n_init=n_init, seed=seed)[1] if len(seeds) >= k else None
        fits[k] = axial_mixture(poles, axial_kmeans(poles, k, init=start, n_init=n_init, seed=seed)[1], weights=w)
    bic = {} if n_sets is not None else {j: m.bic(len(poles)) for j, m in fits.items() if _plausible(m)} or \
        {j: m.bic(len(poles)) for j, m in fits.items()}  # none plausible: BIC alone
    k = tried[0] if n_sets is not None else min(j for j in bic if bic[j] <= min(bic.values()) + BIC_MARGIN)
    mixture = fits[k]
    cutoff = np.full(k, float(outlier_angle)) if outlier_angle is not None else np.degrees(
        fisher_aperture(mixture.kappa, aperture))
    labels = np.argmax(mixture.resp, axis=1)
    in_set = (labels < k) & (mixture.kappa[np.minimum(labels, k - 1)] < KAPPA_MAX)  # a clump is no set
    labels = np.where(in_set, labels, -1)
    beyond = in_set & (axial_angle(poles, mixture.centres[np.minimum(labels, k - 1)]) > cutoff[np.minimum(labels, k - 1)])
    labels[beyond] = -1
    membership = mixture.resp[:, :k] * (labels >= 0)[:, None]  # non-systematic poles belong to no set
    fewest = 2 if n_sets is not None else max(2, MIN_SET_SHARE * len(poles))  # chosen sets hold their share
    members = np.bincount(labels[labels >= 0], minlength=k)
    keep = [j for j in range(k) if members[j] >= fewest and membership[:, j].sum() >= 2]
    if n_sets is not None and len(keep) < n_sets:  # a number asked for is kept, or refused: never fewer silently
        raise InputError(None, f"{n_sets} sets asked for, but only {len(keep)} of them gather 2 or more members; "
                               "ask for fewer sets, or let the number be chosen")
    # n: the poles each set holds (the mixture's shares still weigh κ and α95)
    sets = tuple(replace(set_statistics(poles, weights=None if weights is None else w, membership=membership[:, j],
                                        set_id=i, aperture=aperture), n=int(members[j])) for i, j in enumerate(keep))
    if spread_poles is not None:
        sets = measured_spread(sets, np.asarray(spread_poles, dtype=float), weights=w, aperture=aperture)
    relabel = np.full(k + 1, -1)
    relabel[keep] = np.arange(len(keep))
    peaks = density_peaks(poles, weights=w) if find_peaks else ()
    return SetModel(sets, relabel[labels], peaks, bic, tuple(float(cutoff[j]) for j in keep),
                    float(mixture.shares[-1]))


def _plausible(mixture: Mixture) -> bool:
    """Every component holds at least MIN_SET_SHARE of the poles (step 3)."""
    return bool(np.all(mixture.shares[:-1] >= MIN_SET_SHARE))


def classify_traces(traces: Sequence[Trace3D], *, n_sets: int | None = None, facets: Sequence[Facet] = (),
                    terzaghi: bool = False, w_max: float = W_MAX, **fit_options) -> SetModel:
    """Fit sets to oriented traces and write each trace's `set_id` (−1 non-systematic).

    The measured poles, the eigen poles of the high-quality traces (K < 2, M > 6; Seers & Hodgetts 2016a)
    and the accepted `facets`, seed the clusters and, unless `n_sets` is given, choose the number of sets
    (BIC, `fit_sets`; the model's `bic` is theirs), as they chose the orientation priors
    (`engine.orientation.orient_traces`). The sets' means and members come from all poles.
    DECISION (beyond MATHS §10): the probabilistic solver pulls a collinear trace's pole toward its set
    prior (a linear pool's principal direction lies between its components, MATHS §1.4), so those poles
    crowd the set means: their spread understates the sets' (κ 10–30% high on the synthetic Table 1
    outcrops, tests/test_sets.py), and a mixture fitted to them can find a tight core and a broad skirt
    in one set. So the number of sets comes from the measured poles, and each set's spread (κ, α95, θ99)
    from the high-quality traces' eigen poles (`measured_spread`).
    Traces whose eigen plane is the outcrop surface's (extra["surface_plane"],
    `engine.orientation.surface_planes`) show no plane of their own: they count in no set (−1).
    With `terzaghi`, poles are weighted by 1/sin ρ against the trace's extra["surface_normal"] (from
    `orient_traces`). Other options as in `fit_sets`.
    """
    if n_sets is not None and not 1 <= n_sets <= len(traces):
        raise InputError(None, f"{n_sets} sets asked for, but there are only {len(traces)} traces; "
                               f"expected 1 to {len(traces)} sets")
    missing = [t.id for t in traces if t.normal is None]
    if missing:
        raise InputError(None, f"trace {missing[0]} has no orientation ({len(missing)} such traces); "
                               "orient the traces first")
    rows = [i for i, t in enumerate(traces) if not t.extra.get("surface_plane")]
    counted = [traces[i] for i in rows]
    if len(counted) < 2:
        raise InputError(None, f"{len(counted)} of {len(traces)} traces show a plane of their own (the others "
                               "lie in the outcrop surface's plane); sets need at least 2")
    poles = np.array([t.normal for t in counted], dtype=float)
    eigen = np.array([t.extra.get("eigen_normal", t.normal) for t in counted], dtype=float)
    measured = np.array([t.K < HIGH_QUALITY[0] and t.M > HIGH_QUALITY[1] for t in counted])
    surface = np.array([t.extra.get("surface_normal") or [np.nan] * 3 for t in counted], dtype=float)
    accepted = np.array([f.normal for f in facets if f.accepted], dtype=float).reshape(-1, 3)
    seeds = np.vstack([eigen[measured], accepted])
    weights = terzaghi_weights(poles, surface, w_max=w_max) if terzaghi else None
    bic = {}
    if n_sets is None and len(seeds) >= MIN_SEEDS:
        chosen = fit_sets(seeds, seed_poles=seeds, find_peaks=False,
                          **{k: v for k, v in fit_options.items() if k in ("max_sets", "n_init", "seed")})
        if chosen.n_sets:  # else every seed cluster was a clump: the number of sets is chosen on all poles
            n_sets, bic = chosen.n_sets, chosen.bic
    if n_sets is not None and n_sets > len(counted):
        raise InputError(None, f"{n_sets} sets asked for, but only {len(counted)} of the {len(traces)} traces show "
                               f"a plane of their own; expected 1 to {len(counted)} sets")
    model = fit_sets(poles, n_sets=n_sets, seed_poles=seeds, weights=weights,
                     spread_poles=np.where(measured[:, None], eigen, np.nan), **fit_options)
    labels = np.full(len(traces), -1)
    labels[rows] = model.labels
    for t, label in zip(traces, labels):
        t.set_id = int(label)
    return replace(model, labels=labels, bic=bic or model.bic)


def _unit_poles(poles: np.ndarray) -> np.ndarray:
    p = np.asarray(poles, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(None, f"poles: expected an (N, 3) array, got shape {p.shape}")
    length = np.linalg.norm(p, axis=1)
    bad = np.flatnonzero(~np.isfinite(length) | (length == 0))
    if len(bad):
        raise InputError(None, f"poles: pole {bad[0]} is NaN, infinite or zero ({len(bad)} such poles)")
    return p / length[:, None]


def _check_k(k: int, n: int) -> None:
    if not 1 <= k <= n:
        raise InputError(None, f"{k} sets asked for, but there are only {n} poles; expected 1 to {n} sets")


# ---------------------------------------------------------------------------------------------------------
# facets


@dataclass(frozen=True)
class Facet:
    """A fracture plane measured on the mesh: upward normal, centroid, planarity 1 − λ3/λ2, rms distance of
    the points to the plane (m), point count, why it was rejected ("" when accepted), radius (m: the
    farthest point from the centroid, Compass's sample radius), the mesh `faces` it was fitted to (when
    fitted on a mesh) and its `id` once stored in a project (0 before)."""

    normal: np.ndarray
    centroid: np.ndarray
    planarity: float
    rms: float
    n_points: int
    rejected_reason: str = ""
    radius: float = 0.0
    faces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    id: int = 0

    @property
    def accepted(self) -> bool:
        return not self.rejected_reason

    @property
    def dip_dipdir(self) -> tuple[float, float]:
        """Dip and dip direction (degrees) of the upward normal."""
        dip, dipdir = normal_to_dip_dipdir(self.normal)
        return float(dip), float(dipdir)


def fit_facet(points: np.ndarray, *, outcrop_normal: np.ndarray | None = None, min_planarity: float = 0.75,
              max_outcrop_angle: float = 10.0, max_relative_rms: float = 0.04) -> Facet:
    """Plane through points (N, 3) of an exposed fracture face, with the checks Compass applies and one more.

    Rejected (reason given) when the planarity 1 − λ3/λ2 < `min_planarity` (not a plane); when the RMS
    distance of the points from the plane exceeds `max_relative_rms` × the patch radius (DECISION: a patch
    of rough outcrop, curved like a shallow bowl, passes the planarity test at any size — seen on the
    synthetic wall: rms 28 mm at 0.3 m radius, 9% — while a fracture face under 2 mm of mesh noise fits
    within 1–2%); or when its pole is within `max_outcrop_angle` degrees of `outcrop_normal` (the patch
    is the outcrop face itself).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) < 3 or not np.all(np.isfinite(p)):
        raise InputError(None, f"facet: expected at least 3 finite points, got {len(p)}")
    centroid = p.mean(axis=0)
    lam, vec = np.linalg.eigh((p - centroid).T @ (p - centroid) / len(p))
    if lam[1] <= 1e-12 * lam[2]:
        raise InputError(None, f"facet: the {len(p)} points are collinear; a plane needs a 2D patch")
    normal = upward(vec[:, 0])
    planarity = 1.0 - max(lam[0], 0.0) / lam[1]
    rms, radius = float(np.sqrt(max(lam[0], 0.0))), float(np.linalg.norm(p - centroid, axis=1).max())
    reason = ""
    if planarity < min_planarity:
        reason = f"planarity {planarity:.2f} < {min_planarity}: the patch is not a plane"
    elif rms > max_relative_rms * radius:
        reason = (f"the points lie {rms * 1000:.1f} mm RMS from the plane, over {max_relative_rms:.0%} of the "
                  f"patch radius {radius:.3f} m: the patch is rough rock, not a fracture face")
    elif outcrop_normal is not None and axial_angle(normal, outcrop_normal) < max_outcrop_angle:
        reason = (f"pole within {axial_angle(normal, outcrop_normal):.1f}° of the outcrop normal: the patch is "
                  "the outcrop face, not a fracture plane")
    return Facet(normal, centroid, float(planarity), rms, len(p), reason, radius)


def fit_mesh_facet(mesh: Mesh, faces: np.ndarray, *, outcrop_radius: float | None = None, **options) -> Facet:
    """`fit_facet` on the vertices of the mesh faces a user picked; the outcrop normal is the area-weighted
    mesh normal within `outcrop_radius` m of the patch centroid (default 3 × the patch radius)."""
    faces = np.unique(np.asarray(faces, dtype=np.int64))
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(mesh.faces):
        raise InputError(mesh.source, f"facet: face ids must be in [0, {len(mesh.faces) - 1}]")
    points = mesh.vertices[np.unique(mesh.faces[faces])]
    centroid = points.mean(axis=0)
    radius = 3.0 * np.linalg.norm(points - centroid, axis=1).max() if outcrop_radius is None else outcrop_radius
    outcrop = local_surface_normal(mesh, centroid[None], radius)
    return replace(fit_facet(points, outcrop_normal=outcrop, **options), faces=faces)


def mesh_patch(mesh: Mesh, point: np.ndarray, radius: float) -> np.ndarray:
    """Ids of the mesh faces whose centroid lies within `radius` m of `point` (3,): the patch a facet is
    fitted to when a user picks a point on the mesh (as Compass's plane tool samples a sphere)."""
    point = np.asarray(point, dtype=float).reshape(3)
    if not (np.isfinite(radius) and radius > 0) or not np.all(np.isfinite(point)):
        raise InputError(mesh.source, f"facet: expected a finite point and a radius > 0 m (radius {radius})")
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    gap = float(np.max(np.maximum(low - point, point - high)))
    if gap > max(radius, 1e3 * float(np.max(high - low))):  # the k-d tree overflows on a point far out (1e200 m)
        raise InputError(mesh.source, f"facet: the point is {gap:.4g} m or more outside the mesh's bounding box; "
                                      "expected a point on the mesh, in the mesh file's coordinates")
    faces = np.sort(mesh.face_tree.query_ball_point(point, radius)).astype(np.int64)
    if len(faces) == 0:
        nearest = float(mesh.face_tree.query(point)[0])
        raise InputError(mesh.source, f"facet: no mesh face within {radius:g} m of the point; the nearest face "
                                      f"centre is {nearest:.3f} m away")
    return faces
