"""Radial distortion models that OpenCV has no term for, converted to OpenCV's rational model by fitting.

Metashape's K4 (an r⁸ term) and VisualSFM's radial model (applied to the *measured* point, i.e. an
undistortion) cannot be written exactly as OpenCV's (1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶).
Both are smooth functions d(r²) over the radii an image spans, so OpenCV's coefficients are fitted to them
on [0, r_max], r_max being the undistorted radius of the farthest image corner, and the fit is measured in
pixels: f·r·|fit(r²) - d(r²)| is how far a pixel moves. A fit worse than `MAX_FIT_ERROR_PX` anywhere up
to the corners is refused, so a converted camera is as good as the original to well under a tenth of a pixel.

Only the product f·d(r²) is observable, so the last resort also lets the fit scale the focal length
(`RadialFit.scale`): one more degree of freedom that takes wide lenses (r_max ≈ 1) from ~0.05 px to ~0.04 px.
Simpler models are tried first: polynomial k1..k3 (no denominator that could vanish), then rational, then
rational with a focal scale. The fit minimises the largest error (Lawson's algorithm), not the mean.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.errors import InputError

MAX_FIT_ERROR_PX = 0.05
MAX_RADIAL_FACTOR = 10.0
"""Largest factor by which a foreign model may scale the image corner's distance from the centre, or shrink it:
lenses stay within tens of percent (fisheyes, at 2 to 3, are not pinhole models), so a larger one is a wrong
unit or a corrupt file, and its powers of r would overflow the fit."""
_SAMPLES = 400
_LAWSON_ITERATIONS = 200

RadialModel = Callable[[np.ndarray], np.ndarray]
"""Distortion factor d(s) of a model: a point at undistorted radius r moves to radius r·d(r²)."""


@dataclass(frozen=True)
class RadialFit:
    """OpenCV radial coefficients reproducing a foreign model: d(s) ≈ scale·factor(k, s)."""

    k: np.ndarray
    """(k1, k2, k3, k4, k5, k6) in OpenCV's meaning."""
    scale: float
    """Multiply the focal lengths (and skew) by this, divide tangential coefficients by it."""
    error_px: float
    """Largest pixel displacement between the fit and the model, up to the image corners."""


def fit_radial(model: RadialModel, r_max: float, focal: float, source: Path, what: str) -> RadialFit:
    """OpenCV radial coefficients reproducing `model` to MAX_FIT_ERROR_PX up to radius r_max.

    r_max : largest undistorted normalised radius to cover (the image corners); focal : in pixels.
    """
    worst = np.inf
    for n_den, free_scale in ((0, False), (3, False), (3, True)):
        try:
            with np.errstate(all="ignore"):
                fit = _minimax_fit(model, r_max, focal, n_den, free_scale)
        except np.linalg.LinAlgError:  # powers of an absurd r_max overflow: there is no fit
            continue
        if fit.error_px <= MAX_FIT_ERROR_PX and _is_monotonic(fit.k, r_max):
            return fit
        worst = min(worst, fit.error_px)
    raise InputError(source, f"{what}: this radial distortion cannot be converted to OpenCV's model within "
                             f"{MAX_FIT_ERROR_PX} px up to the image corners (best fit is off by {worst:.3g} px)")


def radial_factor(k: np.ndarray, s: np.ndarray) -> np.ndarray:
    """OpenCV's radial factor at s = r² for coefficients (k1, k2, k3, k4, k5, k6)."""
    k1, k2, k3, k4, k5, k6 = k
    return (1 + s * (k1 + s * (k2 + s * k3))) / (1 + s * (k4 + s * (k5 + s * k6)))


def undistorted_radius(model: RadialModel, rho: float, source: Path, what: str) -> float:
    """The undistorted radius r with r·d(r²) = rho, on the branch where the model is monotonic from 0; refused
    unless rho / r is within a factor MAX_RADIAL_FACTOR of 1."""
    r = np.linspace(0.0, MAX_RADIAL_FACTOR * rho, 20001)
    with np.errstate(all="ignore"):  # huge coefficients overflow to inf (refused below) or NaN (a fold)
        image = r * model(r * r)
        reached = np.flatnonzero(image >= rho)
        rising = np.all(np.diff(image[:reached[0] + 1 if reached.size else None]) > 0)
    if not rising:
        raise InputError(source, f"{what}: the radial distortion folds back before the image corners "
                                 "(the same pixel would see two directions); expected a monotonic model")
    if not reached.size or r[reached[0]] < rho / MAX_RADIAL_FACTOR:
        raise InputError(source, f"{what}: the radial distortion {'magnifies' if reached.size else 'shrinks'} the "
                                 f"image corner's distance from the centre more than {MAX_RADIAL_FACTOR:g} times; "
                                 "expected a lens's distortion, far less (check the coefficients and their units)")
    i = max(int(reached[0]), 1)
    return float(np.interp(rho, image[i - 1:i + 1], r[i - 1:i + 1]))


def _minimax_fit(model: RadialModel, r_max: float, focal: float, n_den: int, free_scale: bool) -> RadialFit:
    """The fit with (nearly) the smallest largest pixel error, by Lawson's reweighted least squares.

    c0 + c1·s + c2·s² + c3·s³ - d(s)·(b1·s + b2·s² + b3·s³) = d(s) is linear in the coefficients (c0 = 1
    unless the scale is free); dividing each row by the previous iterate's denominator (Sanathanan-Koerner)
    makes its residual the true error, and Lawson's weights (multiplied by each sample's error) drive the
    least-squares solution towards the minimax one. The best iterate is kept.
    """
    r = np.linspace(0.0, r_max, _SAMPLES)
    s, target, lever = r * r, model(r * r), focal * r
    powers = np.column_stack([np.ones_like(s), s, s**2, s**3])[:, (0 if free_scale else 1):]
    A0 = np.column_stack([powers, -target[:, None] * powers[:, -3:][:, :n_den]])
    rhs = target if free_scale else target - 1
    weights, den = np.full(len(s), 1.0 / len(s)), np.ones(len(s))
    best_k, best_scale, best_error = np.zeros(6), 1.0, np.inf
    for _ in range(_LAWSON_ITERATIONS):
        row = lever * np.sqrt(weights) / den
        c = np.linalg.lstsq(A0 * row[:, None], rhs * row, rcond=None)[0]
        scale, c = (float(c[0]), c[1:]) if free_scale else (1.0, c)
        k = np.concatenate([c[:3] / scale, c[3:], np.zeros(3 - n_den)])
        den = 1 + s * (k[3] + s * (k[4] + s * k[5]))
        error = lever * np.abs(scale * radial_factor(k, s) - target)
        if error.max() < best_error:
            best_k, best_scale, best_error = k, scale, error.max()
        weights = np.maximum(weights * error, 1e-300)
        weights /= weights.sum()
    return RadialFit(best_k, best_scale, _max_error_px(best_k, best_scale, model, r_max, focal))


def _max_error_px(k: np.ndarray, scale: float, model: RadialModel, r_max: float, focal: float) -> float:
    """Largest error on a grid four times finer than the fit's, so nothing between samples escapes."""
    r = np.linspace(0.0, r_max, 4 * _SAMPLES)
    with np.errstate(all="ignore"):
        error = focal * r * np.abs(scale * radial_factor(k, r * r) - model(r * r))
    return float(np.max(np.nan_to_num(error, nan=np.inf)))


def _is_monotonic(k: np.ndarray, r_max: float) -> bool:
    """r·d(r²) must increase up to the corners, or undistortion would have two answers."""
    r = np.linspace(0.0, r_max, 4 * _SAMPLES)
    s = r * r
    denominator = 1 + s * (k[3] + s * (k[4] + s * k[5]))
    return bool(np.all(denominator > 0) and np.all(np.diff(r * radial_factor(k, s)) > 0))


def opencv_distortion(radial: np.ndarray, p1: float = 0.0, p2: float = 0.0) -> np.ndarray:
    """OpenCV's coefficient order (k1, k2, p1, p2, k3, k4, k5, k6) from radial (k1..k6) and tangential terms."""
    k1, k2, k3, k4, k5, k6 = radial
    return np.array([k1, k2, p1, p2, k3, k4, k5, k6])
