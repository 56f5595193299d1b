"""Orientation of planes and of fracture traces (MATHS.md §1; Seers & Hodgetts 2016a, 2016b).

Poles are axial unit vectors. Dip is in [0, 90] degrees and dip direction in [0, 360), both read from the
upward normal n: dip = acos(n_z), dip direction = atan2(n_x, n_y) mod 360 (x east, y north, z up).

A trace is oriented by its best-fit plane (the eigen solution, §1.1, after uniform arc-length resampling)
unless it is too collinear (K > 0.8), in which case the probabilistic solver of Seers & Hodgetts (2016b)
picks the pole on the great circle of planes containing its end-node axis (§1.2); so does a trace whose
best-fit plane is the outcrop surface's own (`surface_planes`, DECISION), with a uniform eigen component.
The solver pools (§1.4, linear opinion pool, weights (eigen, sets, incidence) = (0.5, 0.3, 0.2)) three
densities on that half-circle (§1.3): a folded von Mises about the in-surface fit (below; the eigen pole
when there is no mesh) with κ(K, M) from a calibration table (`engine.kappa`), von Mises–Fisher set priors restricted to the circle (sets whose 99%
aperture reaches it), and the incidence likelihood sin ρ against the local outcrop normal; 1000 seeded
inverse-CDF draws give the pole as their principal direction, with the pooled mode and the draws'
dispersion beside it.

κ convention (every κ here and in the κ table): the *folded* von Mises on the half-circle,
g(φ) = cosh(κ cos φ) / (π I0(κ)), φ ∈ [−π/2, π/2), so κ keeps its circular meaning (s.d. ≈ 1/√κ rad).

DECISION (set priors, beyond MATHS §1.4): by default the set weight goes wholly to the live set the trace
most probably belongs to (member count × overlap of the set's density with the eigen × incidence
density), not split ∝ member counts. With steep sets on a steep outcrop both sets lie on most circles,
and the count split leaves the principal direction between them; `set_shares="counts"` restores MATHS's
rule. Measured on the synthetic Fig. 6 outcrops: tests/test_orientation.py.

DECISION (eigen component, beyond MATHS §1.3a): where the outcrop surface under the trace is known, the
eigen component is centred on the in-surface fit (`in_surface_fit`), not on the eigen pole. A trace
wanders within the outcrop surface — a digitising error moves a ray's hit along the surface, and an
undulating fracture shifts where it crosses the wall — so its misfit lies in the surface, across the
trace. The eigen fit counts misfit in every direction alike, and misfit in the surface is best explained
by the surface's own plane: it pulls collinear traces' poles toward the outcrop normal. Measured on the
Table 1 outcrops with undulating fractures (tests/test_sets.py, seeds 21–24, per set): the eigen poles
of the solver's traces lie 6.7–8.6° nearer the outcrop normal than their fractures' mean poles (on
average); the solver's poles 3.8–7.0° with the eigen pole as centre, 0.4–2.3° with the in-surface fit,
which brought the Table 1 set means from 1.9–6.0° to within 2.8°. How much misfit lies off the surface
is a choice the data cannot make: OFF_SURFACE_VARIANCE.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import i0e

from engine.errors import InputError, Progress, report
from engine.mesh import Mesh
from engine.traces import Trace3D, polyline_length, resample_polyline

GRID = 3600
"""Nodes on the half-circle of candidate poles (0.05° apart), MATHS §1.3."""

RELATIVE_EPS = 1e-15
"""Eigenvalues at or below this × λ1 are treated as zero (MATHS §1.1 pitfalls)."""

DEFAULT_WEIGHTS = (0.5, 0.3, 0.2)
"""Pool weights (eigen, set priors, incidence), MATHS §1.4 DECISION: eigen > set prior > sampling bias."""

SET_SHARES = ("map", "counts")
"""How the set-prior weight goes to the live sets: all to the most probable set (default) or ∝ member counts."""

HIGH_QUALITY = (2.0, 6.0)
"""Traces with K < 2 and M > 6 define the set priors (Seers & Hodgetts 2016a)."""

OFF_SURFACE_VARIANCE = 0.1
"""η of `in_surface_fit`: variance of a trace's misfit off the outcrop surface relative to its misfit within
it, across the trace (DECISION). The data cannot tell η (the residuals of a plane have one component, and
both kinds of misfit put variance into it), so it is chosen on the calibration generator (`engine.kappa`:
ray-cast traces, undulation 0–3 %, mesh noise 3–30 mm; seed 1, 2959 traces with K > 0.8): the centre's
median error is 7.52° at η = 0, 7.38° at 0.1, 7.35° at 0.2, 7.50° at 0.3, 8.00° at 1 (the eigen fit on
the circle); for K > 5, 15.5°, 15.4°, 15.1°, 15.3°, 22.3°. On ray-cast traces of planar fractures, whose
misfit is mostly depth along the rays, η = 0 pulled the poles of traces with K = 2–5 7° away from the
outcrop normal (η = 0.1: 6°, η = 1: 0.4°); and, calibrated on the generator's earlier noise model, η = 0
(with a 1° floor) left a Table 1 set of planar fractures 3.4° off (tests/test_sets.py; 2.9° at 0.1),
η = 0.3 one of undulating fractures 4.2° off."""

SURFACE_PLANE_ANGLE = 10.0
"""Degrees: a trace whose eigen plane is closer than this to the surface under its median vertex has the
outcrop surface's plane, not a fracture's (`surface_planes`)."""


# ---------------------------------------------------------------------------------------------------------
# dip and dip direction


def dip_dipdir_to_normal(dip: np.ndarray | float, dipdir: np.ndarray | float) -> np.ndarray:
    """Upward unit normals (..., 3) of planes with `dip` and dip direction `dipdir` (degrees, broadcast)."""
    d, a = np.radians(dip), np.radians(dipdir)
    return np.stack(np.broadcast_arrays(np.sin(d) * np.sin(a), np.sin(d) * np.cos(a), np.cos(d)), axis=-1)


def normal_to_dip_dipdir(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dip and dip direction (degrees) of planes with normals `n` (..., 3), any length and either sign.

    Poles are axial, so a downward normal is flipped first; a horizontal one (vertical plane) is kept
    as given, so its dip direction is the direction the normal points.
    """
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(n[..., 2:3] < 0, -n, n)
    dip = np.degrees(np.arccos(np.clip(n[..., 2], -1.0, 1.0)))
    dipdir = np.degrees(np.arctan2(n[..., 0], n[..., 1])) % 360.0
    return dip, np.where(dipdir >= 360.0, 0.0, dipdir)  # -1e-17 % 360 rounds to 360


def upward(n: np.ndarray) -> np.ndarray:
    """Unit axial vectors (..., 3) flipped so that n_z ≥ 0."""
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(n[..., 2:3] < 0, -n, n)


def axial_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between axes a and b (..., 3), in [0, 90]."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c = np.abs(np.sum(a * b, axis=-1)) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def fisher_aperture(kappa: np.ndarray | float, p: float = 0.99) -> np.ndarray:
    """Semi-angle (radians) of the cone about the mean holding probability `p` of a Fisher(κ) distribution.

    cos θ_p = 1 + ln(1 − p(1 − e^{−2κ}))/κ (Fisher, Lewis & Embleton 1987; MATHS §1.3b); π when κ = 0.
    This is a dispersion cone (θ99 of the set priors), not the α95 confidence cone of the mean.
    """
    kappa = np.asarray(kappa, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = 1.0 + np.log1p(-p * -np.expm1(-2.0 * kappa)) / kappa
    return np.where(kappa > 0, np.arccos(np.clip(c, -1.0, 1.0)), np.pi)


# ---------------------------------------------------------------------------------------------------------
# eigen solution, §1.1


@dataclass(frozen=True)
class EigenFit:
    """Best-fit plane of a trace's vertices (resampled at uniform arc length).

    normal: upward pole, the eigenvector of the smallest eigenvalue.
    K: collinearity ln(λ1/λ2)/ln(λ2/λ3); NaN for a straight line (λ2 = λ3 = 0), inf when λ2 = λ3 > 0,
       0 for an exactly planar curve (λ3 = 0 < λ2).
    M: coplanarity ln(λ1/λ3); inf when λ3 = 0.
    eigenvalues: λ1 ≥ λ2 ≥ λ3 of the scatter matrix XᵀX/N (m²); centroid: mean of the resampled vertices.
    """

    normal: np.ndarray
    K: float
    M: float
    eigenvalues: np.ndarray
    centroid: np.ndarray


def shape_parameters(eigenvalues: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Woodcock (1977)/Fernández (2005) K and M from eigenvalues (..., 3) sorted λ1 ≥ λ2 ≥ λ3 ≥ 0.

    Degenerate cases are reported, never clamped into ordinary numbers: a λ ≤ 1e-15 λ1 counts as zero,
    giving M = inf (λ3 = 0), K = 0 (λ3 = 0 < λ2), K = NaN (λ2 = λ3 = 0, a straight line; or λ1 = λ2 = λ3),
    K = inf (λ2 = λ3 > 0).
    """
    lam = np.asarray(eigenvalues, dtype=float)
    l1, l2, l3 = lam[..., 0], lam[..., 1], lam[..., 2]
    zero2, zero3 = l2 <= RELATIVE_EPS * l1, l3 <= RELATIVE_EPS * l1
    with np.errstate(divide="ignore", invalid="ignore"):
        M = np.where(zero3, np.inf, np.log(l1 / l3))
        K = np.where(zero2, np.nan, np.where(zero3, 0.0, np.log(l1 / l2) / np.log(l2 / l3)))
    return K, M


def eigen_orientation(points: np.ndarray, *, spacing: float | None = None) -> EigenFit:
    """Best-fit plane of a 3D trace (MATHS §1.1), after resampling at uniform arc length.

    points : (N, 3) vertices in order, N ≥ 3, metres.
    spacing : resampling step (m); default the mean vertex spacing, so a dense patch (a close or oblique
        photo) does not dominate the fit.
    """
    p = _checked_points(points, "points")
    q = _resampled(p, spacing, "points")
    centroid = q.mean(axis=0)
    x = q - centroid
    lam, vec = np.linalg.eigh(x.T @ x / len(x))  # eigh: real, ascending; eig may go complex
    lam = np.clip(lam[::-1], 0.0, None)
    K, M = shape_parameters(lam)
    return EigenFit(upward(vec[:, 0]), float(K), float(M), lam, centroid)


def _checked_points(points: np.ndarray, label: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(None, f"{label}: expected an (N, 3) array of vertices, got shape {p.shape}")
    if len(p) < 3:
        raise InputError(None, f"{label}: {len(p)} vertices; an orientation needs at least 3")
    bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
    if len(bad):
        raise InputError(None, f"{label}: vertex {bad[0]} is NaN or infinite ({len(bad)} such vertices)")
    return p


def _resampled(p: np.ndarray, spacing: float | None, label: str) -> np.ndarray:
    length = polyline_length(p)
    if length == 0.0:
        raise InputError(None, f"{label}: all {len(p)} vertices coincide")
    step = length / (len(p) - 1) if spacing is None else min(float(spacing), length / 2)
    return resample_polyline(p, step)[0]


# ---------------------------------------------------------------------------------------------------------
# candidate great circle, §1.2


def candidate_circle(points: np.ndarray, eigen_normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The great circle of poles ⟂ the end-node axis: (axis a, e1, e2), n(φ) = cos φ e1 + sin φ e2.

    e1 is the eigen pole projected onto the circle (φ = 0 is the eigen solution); e2 = a × e1.
    Raises InputError when the end nodes coincide (a closed or looping trace has no axis).
    """
    p = _checked_points(points, "points")
    return _circle(p, np.asarray(eigen_normal, dtype=float), "points")


def _circle(p: np.ndarray, n: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    chord = p[-1] - p[0]
    length = np.linalg.norm(chord)
    if not _has_axis(p):
        raise InputError(None, f"{label}: the end nodes coincide (chord {length:.3g} m), so the end-node axis "
                               "is undefined; split closed or looping traces")
    a = chord / length
    e1 = n - (n @ a) * a
    if np.linalg.norm(e1) < 1e-9:  # eigen pole along the axis: any pole ⟂ a will do
        e1 = np.cross(a, np.eye(3)[np.argmin(np.abs(a))])
    e1 /= np.linalg.norm(e1)
    return a, e1, np.cross(a, e1)


# ---------------------------------------------------------------------------------------------------------
# the in-surface fit: centre of the eigen component where the outcrop surface is known (DECISION above)


def in_surface_fit(points: np.ndarray, surface_normals: np.ndarray, e1: np.ndarray, e2: np.ndarray, *,
                   eta: float = OFF_SURFACE_VARIANCE, coarse: int = 180) -> float:
    """φ on the candidate circle n(φ) = cos φ e1 + sin φ e2 of the plane nearest the trace when distances
    are measured within the outcrop surface, across the trace.

    points : (N, 3) trace vertices (resampled at uniform arc length). surface_normals : (N, 3) unit outcrop
    normals under them (`vertex_surface_normals`). The across direction at vertex i is c_i = s_i × a
    (a = e1 × e2, the end-node axis), and o_i = a × c_i is the outcrop normal's part ⟂ a. With misfit of
    variance σ² along c_i and ησ² along o_i (`eta`, default OFF_SURFACE_VARIANCE), the squared Mahalanobis
    distance of p_i from the plane (n, d) is (n·p_i − d)² / ((n·c_i)² + η (n·o_i)²) / σ²: η = 1 is the best
    plane on the circle by ordinary distances, η = 0 the distance along c_i within the surface. Their sum
    is minimised over φ and d (d in closed form for each φ) on a `coarse` grid of the half-circle, and the
    parabola through the least node and its neighbours places the minimum between nodes. Returns φ in
    [−π/2, π/2), radians. A vertex whose outcrop normal is parallel to a has no across direction: give
    only vertices with ‖s_i × a‖ > 0 (`eigen_centre` keeps those above 0.2).
    """
    if not eta >= 0:
        raise InputError(None, f"eta={eta}: expected a variance ratio ≥ 0")
    x = points - points.mean(axis=0)
    axis = np.cross(e1, e2)
    across = np.cross(surface_normals, axis)
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    off = np.cross(axis, across)

    def misfit(phi: np.ndarray) -> np.ndarray:
        n = circle_poles(np.atleast_1d(phi), e1, e2)
        # the floor only matters for η = 0, where a plane containing some c_i would divide by zero
        r, w = n @ x.T, 1.0 / np.maximum((n @ across.T) ** 2 + eta * (n @ off.T) ** 2, 1e-12)
        d = np.sum(w * r, axis=1, keepdims=True) / np.sum(w, axis=1, keepdims=True)
        return np.sum(w * (r - d) ** 2, axis=1)

    phi = half_circle_grid(coarse)
    f = misfit(phi)
    k = int(np.argmin(f))
    below, at, above = f[k - 1], f[k], f[(k + 1) % coarse]  # the half-circle wraps: poles are axes
    curvature = below - 2.0 * at + above
    shift = 0.5 * (below - above) / curvature if curvature > 0 else 0.0
    return float((phi[k] + shift * np.pi / coarse + 0.5 * np.pi) % np.pi - 0.5 * np.pi)


def eigen_centre(points: np.ndarray, normals: np.ndarray | None, e1: np.ndarray, e2: np.ndarray, *,
                 spacing: float | None = None) -> float:
    """φ on the candidate circle of the eigen component's mean: `in_surface_fit` of the trace resampled as
    `eigen_orientation` does (step `spacing`), each resampled vertex with the outcrop normal of the nearest
    input vertex (`normals`, (N, 3)). Vertices with no normal (NaN) or one within 11.5° of the end-node axis
    (‖s × a‖ ≤ 0.2: the trace climbs a step face-on there, with no across direction) are left out; 0, the
    eigen pole, without normals or with fewer than 3 vertices left."""
    if normals is None:
        return 0.0
    p = np.asarray(points, dtype=float)
    length = polyline_length(p)
    step = length / (len(p) - 1) if spacing is None else min(float(spacing), length / 2)
    q, at = resample_polyline(p, step)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    nearest = np.clip(np.searchsorted(s, at), 1, len(s) - 1)
    nearest -= at - s[nearest - 1] < s[nearest] - at
    n = normals[nearest]
    with np.errstate(invalid="ignore"):
        ok = np.linalg.norm(np.cross(n, np.cross(e1, e2)), axis=1) > 0.2  # False for NaN
    return in_surface_fit(q[ok], n[ok], e1, e2) if ok.sum() >= 3 else 0.0


def vertex_surface_normals(mesh: Mesh, points: Sequence[np.ndarray], radius: float) -> list[np.ndarray]:
    """Outcrop normal under every vertex of each polyline: `local_surface_normal` over a `radius` m ball,
    evaluated half a radius apart along the polyline and taken from the nearest such sample (NaN rows
    where no face is that close)."""
    samples, index = [], []
    for p in points:
        step = polyline_length(p) / max(len(p) - 1, 1)
        stride = max(1, int(0.5 * radius / step)) if step > 0 else len(p)
        at = np.unique(np.r_[np.arange(0, len(p), stride), len(p) - 1])
        samples.append(p[at])
        index.append(np.clip(np.searchsorted(at, np.arange(len(p)) - 0.5 * stride), 0, len(at) - 1))
    if not samples:
        return []
    ring = _ring_normals(mesh, np.vstack(samples), radius)
    length = np.linalg.norm(ring, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = np.where(length > 0, ring / length, np.nan)
    out, start = [], 0
    for q, k in zip(samples, index):
        out.append(normals[start:start + len(q)][k])
        start += len(q)
    return out


def _ring_normals(mesh: Mesh, points: np.ndarray, radius: float) -> np.ndarray:
    """Area-weighted sums of the normals of the faces whose centroid is within `radius` of each point (P, 3);
    zero rows where none is."""
    pairs = cKDTree(points).sparse_distance_matrix(mesh.face_tree, radius, output_type="coo_matrix")
    weighted = mesh.face_normals[pairs.col] * mesh.face_areas[pairs.col, None]
    return np.column_stack([np.bincount(pairs.row, weighted[:, k], minlength=len(points)) for k in range(3)])


# ---------------------------------------------------------------------------------------------------------
# component densities on the half-circle, §1.3 (all broadcast over leading axes; last axis is the grid)


def half_circle_grid(n: int = GRID) -> np.ndarray:
    """Cell centres φ_k = −π/2 + (k + ½)π/n (radians) of the half-circle of axial poles."""
    return -0.5 * np.pi + (np.arange(n) + 0.5) * np.pi / n


def circle_poles(phi: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Poles n(φ) = cos φ e1 + sin φ e2, shape (..., len(phi), 3) for e1, e2 of shape (..., 3)."""
    phi = np.asarray(phi, dtype=float)[..., None]
    return np.cos(phi) * np.asarray(e1)[..., None, :] + np.sin(phi) * np.asarray(e2)[..., None, :]


def folded_von_mises(phi: np.ndarray, kappa: np.ndarray | float, mu: np.ndarray | float = 0.0) -> np.ndarray:
    """cosh(κ cos(φ − μ)) / (π I0(κ)): a von Mises folded onto the half-circle of axes (MATHS §1.3a).

    kappa and mu broadcast against phi; evaluated as ½(e^{κ(|c|−1)} + e^{−κ(|c|+1)}) / (π i0e(κ)) so large
    κ cannot overflow.
    """
    kappa = np.asarray(kappa, dtype=float)
    c = np.abs(np.cos(np.asarray(phi, dtype=float) - mu))
    return 0.5 * (np.exp(kappa * (c - 1.0)) + np.exp(-kappa * (c + 1.0))) / (np.pi * i0e(kappa))


def restricted_vmf(phi: np.ndarray, e1: np.ndarray, e2: np.ndarray, mean: np.ndarray,
                   kappa: np.ndarray | float) -> np.ndarray:
    """An axial Fisher(mean, κ) set restricted to the circle (e1, e2): folded VM with κ cos d about φ0.

    exp(κ μ·n(φ)) = exp(κ cos d · cos(φ − φ0)), cos d = ‖(μ·e1, μ·e2)‖, φ0 = atan2(μ·e2, μ·e1)
    (MATHS §1.3b, exact). e1, e2 (..., 3), mean (..., 3) and kappa (...) broadcast; returns
    (..., len(phi)).
    """
    u = np.sum(np.asarray(mean) * e1, axis=-1)
    v = np.sum(np.asarray(mean) * e2, axis=-1)
    kappa_eff = np.asarray(kappa) * np.hypot(u, v)
    return folded_von_mises(phi, kappa_eff[..., None], np.arctan2(v, u)[..., None])


def incidence_density(phi: np.ndarray, e1: np.ndarray, e2: np.ndarray, surface_normal: np.ndarray) -> np.ndarray:
    """Likelihood that a surface with normal s shows a fracture with pole n(φ): ∝ ‖n × s‖ = sin ρ (§1.3c).

    Normalised on the grid `phi` (assumed the cells of `half_circle_grid`); NaN where s is NaN (unknown).
    """
    s = np.asarray(surface_normal, dtype=float)
    ns = np.cos(phi) * np.sum(e1 * s, axis=-1)[..., None] + np.sin(phi) * np.sum(e2 * s, axis=-1)[..., None]
    g = np.sqrt(np.clip(1.0 - ns**2, 0.0, None))
    return g / (g.sum(axis=-1, keepdims=True) * np.pi / phi.shape[-1])


def pool(densities: Sequence[np.ndarray | None], weights: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Linear opinion pool Σ w_j g_j (Stone 1961) over the components present (MATHS §1.4).

    densities : each (..., G) normalised on the half-circle grid, or None / NaN rows when the component is
        absent for that trace (no live set; unknown surface normal). Weights are renormalised over the
        components present, per trace. Returns the pooled density (..., G) and the weights used (..., J).
    """
    shape = next(d for d in densities if d is not None).shape
    present = np.stack([np.zeros(shape[:-1], bool) if d is None else np.isfinite(d).all(axis=-1)
                        for d in densities], axis=-1)
    w = np.where(present, np.asarray(weights, dtype=float), 0.0)
    total = w.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise InputError(None, f"weights {tuple(weights)}: no component with a positive weight is present")
    w = w / total
    g = sum(w[..., j, None] * np.nan_to_num(d) for j, d in enumerate(densities) if d is not None)
    return g, w


# ---------------------------------------------------------------------------------------------------------
# the κ(K, M) table, §1.6


@dataclass(frozen=True)
class KappaTable:
    """κ of the folded von Mises of eigen-pole errors, per (K, M) cell: own calibration (`engine.kappa`).

    k_edges (nK + 1,), m_edges (nM + 1,) bin edges (last may be inf); kappa, count, median_error (nK, nM),
    median_error in degrees; parameters: how the table was made (seed, generator settings).
    Not the published Seers & Hodgetts (2016b) table, whose values are not available (MATHS §0).
    """

    k_edges: np.ndarray
    m_edges: np.ndarray
    kappa: np.ndarray
    count: np.ndarray
    median_error: np.ndarray
    parameters: dict

    def lookup(self, K: np.ndarray | float, M: np.ndarray | float) -> np.ndarray:
        """κ for shape parameters K, M (broadcast). K = NaN (straight line) takes the most collinear row;
        values beyond the edges take the outermost cells."""
        K = np.where(np.isnan(K), np.inf, K)
        M = np.where(np.isnan(M), 0.0, M)
        i = np.clip(np.searchsorted(self.k_edges, K, side="right") - 1, 0, len(self.k_edges) - 2)
        j = np.clip(np.searchsorted(self.m_edges, M, side="right") - 1, 0, len(self.m_edges) - 2)
        return self.kappa[i, j]

    def write(self, path: str | Path) -> None:
        """CSV, one row per cell, with the provenance as '#' header lines (read by `load_kappa_table`)."""
        header = ["# tracemap kappa(K, M) table: OWN CALIBRATION, not the published Seers & Hodgetts (2016b) table",
                  "# kappa: folded von Mises cosh(kappa cos phi)/(pi I0(kappa)) of the error phi along the candidate "
                  "circle of the eigen component's centre: the in-surface fit where the outcrop is known, else the "
                  "eigen pole (MATHS 1.3a, 1.6; engine.orientation)",
                  "# regenerate: " + self.parameters.get("command", "python -m engine.kappa"),
                  "# parameters: " + json.dumps(self.parameters, sort_keys=True),
                  "K_min,K_max,M_min,M_max,kappa,count,median_error_deg"]
        rows = [f"{self.k_edges[i]:g},{self.k_edges[i + 1]:g},{self.m_edges[j]:g},{self.m_edges[j + 1]:g},"
                f"{self.kappa[i, j]:.6g},{self.count[i, j]},{self.median_error[i, j]:.4g}"
                for i in range(len(self.k_edges) - 1) for j in range(len(self.m_edges) - 1)]
        Path(path).write_text("\n".join(header + rows) + "\n", encoding="utf-8")


def load_kappa_table(path: str | Path | None = None) -> KappaTable:
    """Read a κ(K, M) table CSV (`KappaTable.write` layout); default the shipped engine/data/kappa_table.csv.

    Pass the path of another table (for instance the published one, when available) to replace it.
    """
    if path is None:
        return _shipped_kappa_table()
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "kappa table not found")
    return _read_kappa_table(path.read_text(encoding="utf-8"), path)


@lru_cache(maxsize=1)
def _shipped_kappa_table() -> KappaTable:
    text = resources.files("engine").joinpath("data/kappa_table.csv").read_text(encoding="utf-8")
    return _read_kappa_table(text, "engine/data/kappa_table.csv")


def _read_kappa_table(text: str, source) -> KappaTable:
    lines = text.splitlines()
    parameters = {}
    for line in lines:
        if line.startswith("# parameters: "):
            parameters = json.loads(line[len("# parameters: "):])
    body = [line for line in lines if line and not line.startswith("#")]
    expected = "K_min,K_max,M_min,M_max,kappa,count,median_error_deg"
    if not body or body[0].replace(" ", "") != expected:
        raise InputError(source, f"kappa table: expected the header line {expected!r}")
    try:
        data = np.array([[float(x) for x in line.split(",")] for line in body[1:]])
        k_edges = np.unique(data[:, :2])
        m_edges = np.unique(data[:, 2:4])
        shape = (len(k_edges) - 1, len(m_edges) - 1)
        i = np.searchsorted(k_edges, data[:, 0])
        j = np.searchsorted(m_edges, data[:, 2])
        grid = np.full((3, *shape), np.nan)
        grid[:, i, j] = data[:, 4:7].T
    except (ValueError, IndexError) as exc:
        raise InputError(source, f"kappa table: malformed row ({exc})") from exc
    if data.shape[0] != shape[0] * shape[1] or not np.all(np.isfinite(grid[0])) or np.any(grid[0] < 0):
        raise InputError(source, "kappa table: expected one row with a finite kappa ≥ 0 for every (K, M) cell")
    return KappaTable(k_edges, m_edges, grid[0], grid[1].astype(np.int64), grid[2], parameters)


# ---------------------------------------------------------------------------------------------------------
# the probabilistic solver, §1.3–1.4


@dataclass(frozen=True)
class SetPrior:
    """A fracture set as a prior: upward mean pole, Fisher κ, member count (`engine.sets.FractureSetStats`
    has the same fields and can be passed wherever a SetPrior is expected)."""

    normal: np.ndarray
    kappa: float
    n: int


@dataclass(frozen=True)
class OrientationResult:
    """The pole of one trace and how it was found.

    normal: upward pole; for "probabilistic" the principal direction of the draws (MATHS §1.4).
    method: "eigen", "probabilistic" or "manual". K, M: shape parameters of the eigen fit.
    mode: pole at the maximum of the pooled density (= normal for "eigen").
    dispersion: λ2/λ1 of the draw tensor on the circle, 0 (all draws equal) to 1 (uniform); NaN for "eigen".
    spread: axial circular s.d. of the draws, ½√(−2 ln R̄₂), degrees; NaN for "eigen".
    eigen_normal: the best-fit-plane pole; axis: end-node axis a; kappa_eigen: κ(K, M) of the eigen
    component (folded form; 0 when the eigen plane is the outcrop surface's, `surface_planes`);
    weights: (w_E, w_C, w_I) after renormalisation over the components present;
    n_sets: set priors whose 99% aperture reaches the circle; density: the pooled density on
    `half_circle_grid(len(density))` with n(φ) from `candidate_circle` (only from `probabilistic_orientation`).
    """

    normal: np.ndarray
    method: str
    K: float
    M: float
    mode: np.ndarray
    dispersion: float
    spread: float
    eigen_normal: np.ndarray
    axis: np.ndarray
    kappa_eigen: float
    weights: tuple[float, float, float]
    n_sets: int
    density: np.ndarray | None = None


@dataclass(frozen=True)
class _Batch:
    """Candidate circles of T traces, the inputs of the pooled density."""

    axis: np.ndarray  # (T, 3)
    e1: np.ndarray
    e2: np.ndarray
    K: np.ndarray  # (T,)
    M: np.ndarray
    surface: np.ndarray  # (T, 3), NaN where unknown
    keys: np.ndarray  # (T,) per-trace seed keys, so a trace's draws do not depend on its batch
    surface_plane: np.ndarray  # (T,) bool: the eigen plane is the outcrop's, so the eigen component is uniform
    centre: np.ndarray  # (T,) φ of the eigen component's mean: the in-surface fit, or 0 (the eigen pole)


def probabilistic_orientation(points: np.ndarray, *, surface_normal: np.ndarray | None = None,
                              vertex_normals: np.ndarray | None = None,
                              sets: Sequence[SetPrior] = (), kappa_table: KappaTable | None = None,
                              weights: Sequence[float] = DEFAULT_WEIGHTS, set_shares: str = "map",
                              n_draws: int = 1000, seed: int = 0, spacing: float | None = None,
                              aperture: float = 0.99, grid: int = GRID) -> OrientationResult:
    """Pole of one trace by the probabilistic solver of Seers & Hodgetts (2016b), MATHS §1.2–1.4.

    points : (N, 3) vertices, metres. surface_normal : local outcrop normal s (`local_surface_normal`);
        None drops the incidence component. vertex_normals : (N, 3) outcrop normal under each vertex
        (`vertex_surface_normals`); centres the eigen component on `in_surface_fit`, None on the eigen
        pole. sets : set priors (mean pole, κ, member count), each used
        only if its `aperture` cone (default 99%) reaches the circle. kappa_table : κ(K, M) of the eigen
        component, default the shipped own calibration. weights : (eigen, sets, incidence) pool weights,
        renormalised over the components present. set_shares : "map" gives the whole set weight to the
        live set the trace most probably belongs to (count × overlap with the eigen and incidence
        densities); "counts" splits it among the live sets ∝ member counts (MATHS §1.4). n_draws, seed :
        inverse-CDF draws from a seeded generator. spacing : arc-length resampling step of the eigen fit
        (m). grid : nodes on the half-circle.
    """
    p = _checked_points(points, "points")
    fit = eigen_orientation(p, spacing=spacing)
    a, e1, e2 = _circle(p, fit.normal, "points")
    s = np.full(3, np.nan) if surface_normal is None else np.asarray(surface_normal, dtype=float)
    normals = None if vertex_normals is None else np.asarray(vertex_normals, dtype=float).reshape(p.shape)
    batch = _Batch(a[None], e1[None], e2[None], np.array([fit.K]), np.array([fit.M]), s[None], np.array([0]),
                   np.zeros(1, bool), np.array([eigen_centre(p, normals, e1, e2, spacing=spacing)]))
    return _solve(batch, [fit.normal], sets=sets, kappa_table=kappa_table, weights=weights,
                  set_shares=set_shares, n_draws=n_draws, seed=seed, aperture=aperture, grid=grid,
                  keep_density=True)[0]


def _solve(batch: _Batch, eigen_normals, *, sets, kappa_table, weights, set_shares, n_draws, seed, aperture,
           grid, keep_density=False) -> list[OrientationResult]:
    """Pool, draw and summarise a batch of traces at once (the vectorised core of the solver)."""
    if len(weights) != 3 or min(weights) < 0:
        raise InputError(None, f"weights {tuple(weights)}: expected three non-negative numbers "
                               "(eigen, sets, incidence)")
    if n_draws < 2:
        raise InputError(None, f"n_draws={n_draws}: expected at least 2")
    if set_shares not in SET_SHARES:
        raise InputError(None, f"set_shares={set_shares!r}: expected one of {', '.join(SET_SHARES)}")
    table = load_kappa_table() if kappa_table is None else kappa_table
    phi = half_circle_grid(grid)
    kappa_e = np.where(batch.surface_plane, 0.0, table.lookup(batch.K, batch.M))
    eigen = folded_von_mises(phi, kappa_e[:, None], batch.centre[:, None])
    incidence = incidence_density(phi, batch.e1, batch.e2, batch.surface)
    evidence = eigen * np.nan_to_num(incidence, nan=1.0) if set_shares == "map" else None
    sets_density, n_live = _set_density(phi, batch, sets, aperture, evidence)
    g, w = pool([eigen, sets_density, incidence], weights)
    drawn = _draw(g, batch.keys, n_draws, seed)
    c2, s2 = np.cos(2 * drawn).mean(axis=1), np.sin(2 * drawn).mean(axis=1)
    principal = 0.5 * np.arctan2(s2, c2)
    r2 = np.hypot(c2, s2)
    with np.errstate(divide="ignore"):
        spread = np.degrees(0.5 * np.sqrt(-2.0 * np.log(r2)))
    normal = upward(circle_poles(principal[:, None], batch.e1, batch.e2)[:, 0])
    mode = upward(circle_poles(phi[np.argmax(g, axis=1)][:, None], batch.e1, batch.e2)[:, 0])
    return [OrientationResult(normal[t], "probabilistic", float(batch.K[t]), float(batch.M[t]), mode[t],
                              float((1 - r2[t]) / (1 + r2[t])), float(spread[t]), eigen_normals[t],
                              batch.axis[t], float(kappa_e[t]), tuple(float(x) for x in w[t]), int(n_live[t]),
                              g[t] if keep_density else None)
            for t in range(len(normal))]


def _set_density(phi, batch: _Batch, sets: Sequence[SetPrior], aperture: float, evidence: np.ndarray | None):
    """The set-prior component on each circle from the live sets; NaN rows where none is live.

    With `evidence` (the eigen × incidence density; set_shares "map"), the whole component is the live set
    with the highest posterior membership c_j ∫ g_Cj · evidence dφ: a trace belongs to one set, and two sets
    live on one circle would otherwise put the principal direction between them (MATHS §1.4 pitfall).
    Without it ("counts"), the mixture of the live sets with shares ∝ member counts c_j (MATHS §1.4).
    """
    n_live = np.zeros(len(batch.axis), dtype=int)
    if not sets:
        return None, n_live
    acc = np.zeros((len(batch.axis), len(phi)))
    # the total of the member counts ("counts"), or the best membership so far ("map")
    score = np.zeros(len(batch.axis)) if evidence is None else np.full(len(batch.axis), -np.inf)
    for s in sets:
        mean = upward(s.normal)
        d = np.arcsin(np.clip(np.abs(batch.axis @ mean), 0.0, 1.0))  # angular distance of ±μ from the circle
        live = np.flatnonzero(d <= fisher_aperture(s.kappa, aperture))
        if not len(live):
            continue
        n_live[live] += 1
        g = restricted_vmf(phi, batch.e1[live], batch.e2[live], mean, s.kappa)
        if evidence is None:
            acc[live] += s.n * g
            score[live] += s.n
        else:
            membership = s.n * np.mean(g * evidence[live], axis=1)
            better = membership > score[live]
            acc[live[better]] = g[better]
            score[live[better]] = membership[better]
    if evidence is None:
        with np.errstate(invalid="ignore", divide="ignore"):
            acc /= score[:, None]
    return np.where(n_live[:, None] > 0, acc, np.nan), n_live


def _draw(g: np.ndarray, keys: np.ndarray, n_draws: int, seed: int) -> np.ndarray:
    """Inverse-CDF draws (T, n_draws) of φ from densities g (T, G) on the half-circle cells.

    Trace t uses its own generator seeded by (seed, keys[t]), so its draws repeat whatever batch it is in.
    """
    edges = np.linspace(-0.5 * np.pi, 0.5 * np.pi, g.shape[1] + 1)
    cdf = np.concatenate([np.zeros((len(g), 1)), np.cumsum(g, axis=1)], axis=1)
    cdf /= cdf[:, -1:]
    out = np.empty((len(g), n_draws))
    for t, key in enumerate(keys):
        u = np.random.default_rng([seed, int(key)]).random(n_draws)
        out[t] = np.interp(u, cdf[t], edges)
    return out


# ---------------------------------------------------------------------------------------------------------
# traces


def local_surface_normal(mesh: Mesh, points: np.ndarray, radius: float) -> np.ndarray:
    """Area-weighted mean unit normal of the mesh faces whose centroid is within `radius` m of the trace.

    The outcrop normal s of the incidence likelihood (MATHS §1.3c) and of Terzaghi weights (§8). Returns
    NaNs when no face is that close.
    """
    return _surface_normals(mesh, [np.asarray(points, dtype=float).reshape(-1, 3)], radius)[0]


def _surface_normals(mesh: Mesh, traces: Sequence[np.ndarray], radius: float) -> np.ndarray:
    """`local_surface_normal` of many traces (T, 3) in one neighbour search."""
    if not traces:
        return np.zeros((0, 3))
    samples = [_every(p, 0.5 * radius) for p in traces]  # queries half a radius apart cover the buffer
    owner = np.repeat(np.arange(len(traces)), [len(p) for p in samples])
    pairs = cKDTree(np.vstack(samples)).sparse_distance_matrix(mesh.face_tree, radius, output_type="coo_matrix")
    n_faces = len(mesh.faces)
    trace, face = np.divmod(np.unique(owner[pairs.row] * n_faces + pairs.col), n_faces)
    weighted = mesh.face_normals[face] * mesh.face_areas[face, None]
    total = np.column_stack([np.bincount(trace, weighted[:, k], minlength=len(traces)) for k in range(3)])
    length = np.linalg.norm(total, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(length > 0, total / length, np.nan)


def _every(p: np.ndarray, spacing: float) -> np.ndarray:
    """Vertices of a polyline about `spacing` apart along it (every k-th, and the last)."""
    if len(p) < 3:
        return p
    step = polyline_length(p) / (len(p) - 1)
    stride = max(1, int(spacing / step)) if step > 0 else len(p)
    return p[np.unique(np.r_[np.arange(0, len(p), stride), len(p) - 1])]


def orient_traces(traces: Sequence[Trace3D], mesh: Mesh | None, *, sets: Sequence[SetPrior] | None = None,
                  n_sets: int | None = None, k_threshold: float = 0.8, kappa_table: KappaTable | None = None,
                  weights: Sequence[float] = DEFAULT_WEIGHTS, set_shares: str = "map", n_draws: int = 1000,
                  seed: int = 0, spacing: float | None = None, surface_radius: float | None = None,
                  aperture: float = 0.99, grid: int = GRID, chunk: int = 128,
                  progress: Progress | None = None) -> list[OrientationResult]:
    """Orient traces in place: eigen solution, and the probabilistic solver where K > `k_threshold` or where
    the eigen plane is the outcrop surface's own (`surface_planes`; its eigen component is then uniform).

    Sets on each trace: normal (upward), method, K, M, dispersion (NaN for eigen), and in `extra`:
    "eigen_normal", "surface_normal" (for Terzaghi weights; null when unknown), "surface_plane" (true when
    the eigen plane is the surface's), and for probabilistic solutions "mode", "spread_deg" and
    "kappa_eigen". K = NaN (a straight trace) counts as collinear.

    mesh : for the local outcrop normal (incidence component) and the surface under the traces
        (`surface_planes`); None drops both.
    sets : set priors; default fitted (`engine.sets.fit_sets`, `n_sets` sets or chosen automatically) to
        the eigen poles of the high-quality traces (K < 2, M > 6, eigen plane not the surface's), none if
        fewer than 5 such traces or if they cannot make `n_sets` sets; pass () for no set priors.
    surface_radius : buffer (m) of `local_surface_normal`; default 3 mean mesh edge lengths.
    chunk : traces pooled at once (bounds memory: chunk × grid doubles per component).
    Other parameters as in `probabilistic_orientation`; trace t draws with seed (seed, trace id).
    Raises InputError naming the trace when one has < 3 vertices or NaNs, or when a trace that needs the
    solver has coincident end nodes (a closed loop with K ≤ k_threshold keeps its eigen solution).
    """
    report(progress, 0.0, "eigen solutions")
    points = [_checked_points(t.points, f"trace {t.id}") for t in traces]
    fits = [eigen_orientation(p, spacing=spacing) for p in points]
    surface = _outcrop_normals(traces, mesh, surface_radius)
    on_surface = surface_planes(points, fits, mesh, spacing=spacing)
    if sets is None:
        sets = _fitted_priors([f for f, flat in zip(fits, on_surface) if not flat], n_sets, seed)
    table = load_kappa_table() if kappa_table is None else kappa_table
    results: list[OrientationResult | None] = [None] * len(traces)
    for i, fit in enumerate(fits):
        # False for NaN: a straight trace goes to the solver; so does a curve in the surface's plane, unless
        # it is a closed loop (no end-node axis)
        if fit.K <= k_threshold and not (on_surface[i] and _has_axis(points[i])):
            results[i] = OrientationResult(fit.normal, "eigen", fit.K, fit.M, fit.normal, np.nan, np.nan,
                                           fit.normal, _chord_axis(points[i]), float(table.lookup(fit.K, fit.M)),
                                           (1.0, 0.0, 0.0), 0)
    todo = [i for i, r in enumerate(results) if r is None]
    # only the solver needs the end-node axis, so only its traces must have distinct end nodes
    circles = {i: _circle(points[i], fits[i].normal, f"trace {traces[i].id}") for i in todo}
    normals = (vertex_surface_normals(mesh, [points[i] for i in todo], _surface_radius(mesh, surface_radius))
               if mesh is not None else [None] * len(todo))
    centres = {i: eigen_centre(points[i], n, *circles[i][1:], spacing=spacing) for i, n in zip(todo, normals)}
    for start in range(0, len(todo), chunk):
        report(progress, 0.1 + 0.9 * start / len(todo), "probabilistic solutions")
        idx = todo[start:start + chunk]
        batch = _Batch(*(np.array([circles[i][k] for i in idx]) for k in range(3)),
                       np.array([fits[i].K for i in idx]), np.array([fits[i].M for i in idx]), surface[idx],
                       np.array([traces[i].id for i in idx]), on_surface[idx], np.array([centres[i] for i in idx]))
        solved = _solve(batch, [fits[i].normal for i in idx], sets=sets, kappa_table=table, weights=weights,
                        set_shares=set_shares, n_draws=n_draws, seed=seed, aperture=aperture, grid=grid)
        for i, r in zip(idx, solved):
            results[i] = r
    for t, r, s, flat in zip(traces, results, surface, on_surface):  # only now: a cancelled run changes nothing
        _store(t, r, s, bool(flat))
    report(progress, 1.0, "orientation done")
    return results


def _chord_axis(p: np.ndarray) -> np.ndarray:
    chord = p[-1] - p[0]
    length = np.linalg.norm(chord)
    return chord / length if length > 0 else np.full(3, np.nan)


def _has_axis(p: np.ndarray) -> bool:
    return bool(np.linalg.norm(p[-1] - p[0]) > 1e-9 * np.ptp(p, axis=0).max())


def _outcrop_normals(traces: Sequence[Trace3D], mesh: Mesh | None, radius: float | None) -> np.ndarray:
    if mesh is None:
        return np.full((len(traces), 3), np.nan)
    return _surface_normals(mesh, [t.points for t in traces], _surface_radius(mesh, radius))


def _surface_radius(mesh: Mesh, radius: float | None) -> float:
    return 3.0 * mesh.mean_edge_length if radius is None else float(radius)


def surface_planes(points: Sequence[np.ndarray], fits: Sequence[EigenFit], mesh: Mesh | None, *,
                   spacing: float | None = None) -> np.ndarray:
    """Which traces have the outcrop surface's own plane as their eigen plane, (T,) bool; none without a mesh.

    A fracture shows a trace only where it crosses the surface, so along a real trace the surface is
    inclined to the fracture plane (the incidence angle ρ of MATHS §1.3c, taken pointwise), even where
    the wall's mean normal is parallel to it. A curve whose eigen plane lies within SURFACE_PLANE_ANGLE
    of the surface under its median vertex is a curve drawn on a flat patch (such as a piece of a 2D
    trace ray-cast onto an occluding rib): its plane is the surface's whatever K and M say, and tells
    nothing of a fracture (DECISION, beyond MATHS §1.1). The surface under a vertex is taken two ways,
    and either may show the flat patch: the face nearest the vertex, and the area-weighted mean of the
    faces within 1.5 mean edge lengths (about its ring of faces), where mesh noise averages out but a
    narrow patch's neighbours join in. Measured on the synthetic outcrops of the tests: 1–2% of the
    traces of the Table 1 outcrops, 4–5% of the Fig. 6 ones, 15% of the demo's (mostly pieces of
    occluded traces); 104 of the 111 had eigen poles ≥ 15° off; left in, those of the Fig. 6 outcrop of
    seed 1 made a set prior at the outcrop face (tests/test_orientation.py).
    points : the traces' vertices (resampled as `eigen_orientation` does, step `spacing`); fits : their
    `eigen_orientation`.
    """
    if mesh is None or not len(points):
        return np.zeros(len(points), dtype=bool)
    tree = mesh.face_tree
    samples = [_resampled(p, spacing, "points") for p in points]
    vertices = np.vstack(samples)
    poles = np.repeat([f.normal for f in fits], [len(q) for q in samples], axis=0)
    face_angle = axial_angle(mesh.face_normals[tree.query(vertices)[1]], poles)
    ring = _ring_normals(mesh, vertices, 1.5 * mesh.mean_edge_length)
    with np.errstate(invalid="ignore"):  # a vertex with no face near it has no ring normal (NaN): not counted
        ring_angle = axial_angle(ring, poles)
    split = np.cumsum([len(q) for q in samples])[:-1]
    flat = np.zeros(len(points), dtype=bool)
    for t, (a, b) in enumerate(zip(np.split(face_angle, split), np.split(ring_angle, split))):
        b = b[np.isfinite(b)]
        flat[t] = min(np.median(a), np.median(b) if len(b) else np.inf) < SURFACE_PLANE_ANGLE
    return flat


def _fitted_priors(fits: Sequence[EigenFit], n_sets: int | None, seed: int) -> list[SetPrior]:
    from engine.sets import fit_sets  # engine.sets builds on this module, so it is imported late

    good = [f.normal for f in fits if f.K < HIGH_QUALITY[0] and f.M > HIGH_QUALITY[1]]
    if len(good) < 5 or (n_sets is not None and len(good) < 2 * n_sets):
        return []
    try:
        return list(fit_sets(np.array(good), n_sets=n_sets, seed=seed, find_peaks=False).sets)
    except InputError:  # the few well-measured traces cannot make the sets asked for: no priors beats wrong ones
        return []


def _store(trace: Trace3D, r: OrientationResult, surface: np.ndarray, surface_plane: bool) -> None:
    trace.normal, trace.method, trace.K, trace.M, trace.dispersion = r.normal, r.method, r.K, r.M, r.dispersion
    trace.extra["eigen_normal"] = r.eigen_normal.tolist()
    trace.extra["surface_normal"] = surface.tolist() if np.all(np.isfinite(surface)) else None
    _forget_solver(trace)
    if surface_plane:
        trace.extra["surface_plane"] = True
    if r.method == "probabilistic":
        trace.extra.update(mode=r.mode.tolist(), spread_deg=r.spread, kappa_eigen=r.kappa_eigen)


def _forget_solver(trace: Trace3D) -> None:
    for key in ("mode", "spread_deg", "kappa_eigen", "surface_plane"):
        trace.extra.pop(key, None)


def unoriented(trace: Trace3D) -> Trace3D:
    """A copy of `trace` without orientation (pole, method, K, M, dispersion and the solver's extras), for a
    trace whose vertices changed, such as a trimmed one: its old pole no longer belongs to it."""
    extra = {k: v for k, v in trace.extra.items() if k not in ("eigen_normal", "surface_normal")}
    copy = replace(trace, normal=None, method="", K=np.nan, M=np.nan, dispersion=np.nan, extra=extra)
    _forget_solver(copy)
    return copy


def manual_orientation(trace: Trace3D, *, pole: np.ndarray | None = None, angle: float | None = None,
                       spacing: float | None = None) -> np.ndarray:
    """Set a trace's pole by hand, on its candidate great circle; returns the upward pole.

    pole : any vector; its projection onto the circle ⟂ the end-node axis is used (a point clicked on the
        circle of a stereonet). angle : degrees along the circle from the eigen pole, toward a × e1.
    Give exactly one. K, M and extra["eigen_normal"] are refreshed; method becomes "manual".
    """
    if (pole is None) == (angle is None):
        raise InputError(None, f"trace {trace.id}: give exactly one of pole and angle")
    label = f"trace {trace.id}"
    p = _checked_points(trace.points, label)
    fit = eigen_orientation(p, spacing=spacing)
    a, e1, e2 = _circle(p, fit.normal, label)
    if pole is not None:
        v = np.asarray(pole, dtype=float)
        n = v - (v @ a) * a
        if not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9 * np.linalg.norm(v):
            raise InputError(None, f"{label}: pole {v.tolist()} is along the end-node axis, not near the circle")
    else:
        n = np.cos(np.radians(angle)) * e1 + np.sin(np.radians(angle)) * e2
    trace.normal, trace.method, trace.K, trace.M, trace.dispersion = upward(n), "manual", fit.K, fit.M, np.nan
    trace.extra["eigen_normal"] = fit.normal.tolist()
    _forget_solver(trace)
    return trace.normal
