"""Brightness across a line: is a chain of edge pixels a fracture trace, or the edge of a face?

A fracture trace is a thin dark line on continuous rock: darker than both sides, and the dip is symmetric.
The crease where a face steps back (its side face seen edge-on), the skyline and the foot of the wall are also
dark lines in phase congruency terms, but they are edges between two surfaces: the dip has a sharp edge on one
side and a shading ramp or a step on the other. Only the photo is used.

The photo is read as log brightness. Brightness is rock albedo × shading × (1 − darkening of the trace), so in
log units a trace darkens the rock by the same amount in sun and in shade, and shading adds a smooth trend.
Across each point of a chain the profile is sampled every half pixel. Each point's profile is recentred on its
darkest sample within half a trace width, because the skeleton can be a pixel off the centre of the line.
Then the median over the chain is taken, so texture that varies along the chain averages out. Two numbers
judge the median profile. Distances are in units of `trace_width` w, the widest trace expected:
* contrast: how much brighter than the centre the darker side is, averaged over 1–5/3 w. A dark line has
  contrast > 0. A step edge has contrast ≈ 0, because recentring moves its centre onto the dark side.
* asymmetry: take the straight line through the profile at ±4/3 w, so shading trends drop out. Measure the dip
  below that line at ±2/3 w, and divide the difference of the two dips by the dip at the centre. A trace is
  symmetric, even on a shading boundary (median 0.04 on the synthetic outcrop). A crease's sharp-edge-and-ramp
  dip is asymmetric (0.18–0.5). A faint trace (contrast < 0.3) may be more asymmetric: mottling beside it
  skews its dip, and the creases are strong.
Chains are judged on the denoised photo. One it rejects may still pass on the photo before denoising with a
higher contrast (`raw_contrast`), its profiles recentred where the denoised photo has the dip: non-local
means flattens a faint trace in shade, where the sensor noise is as deep as the trace.
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np
from scipy import ndimage

from engine.errors import InputError

LOG_255 = math.log(255.0)
STEP = 0.5  # sample spacing across the line, px
ALONG = 3  # points: a chain's tangent at a point runs from the point this far before it to the one as far after
# distances from the centre, in trace widths
RECENTRE, INNER, TREND, SIDE = 0.5, 2 / 3, 4 / 3, (1.0, 5 / 3)


def log_brightness(image: np.ndarray) -> np.ndarray:
    """ln of an 8-bit grey photo's levels (float32, 0 … ln 255), with 0 counted as 1 so black stays finite."""
    return np.log(np.maximum(np.asarray(image, np.float32), 1.0))


def cross_profiles(log_image: np.ndarray, chains: list[np.ndarray], trace_width: float, *,
                   centre_on: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (px) and, for each chain ((N ≥ 2, 2) points (u, v) about 1 px apart), the median of its recentred
    profiles across the line relative to the centre: (offsets (K,), profiles (n, K), 0 at the centre).

    centre_on : an image of the same grid whose darkest sample each profile is recentred on (default
        `log_image`). On a noisy photo its own darkest sample is as often noise as the line, and recentring
        there makes noise look like a dip; a denoised copy says where the line is.
    """
    if centre_on is not None and np.shape(centre_on) != np.shape(log_image):
        raise InputError(None, f"cross_profiles: centre_on is {np.shape(centre_on)} but the image "
                               f"{np.shape(log_image)}; they must be the same photo")
    half = math.ceil((RECENTRE + SIDE[1]) * trace_width / STEP)
    offsets = STEP * np.arange(-half, half + 1)
    if not chains:
        return offsets, np.empty((0, len(offsets)))
    points = np.vstack(chains).astype(np.float64)
    bounds = np.cumsum([0] + [len(c) for c in chains])
    normal = _normals(points, bounds)
    rows = points[:, 1, None] + offsets * normal[:, 1, None]
    cols = points[:, 0, None] + offsets * normal[:, 0, None]
    samples = _sample(log_image, rows, cols)
    guide = samples if centre_on is None else _sample(centre_on, rows, cols)
    shift_max = int(RECENTRE * trace_width / STEP)
    shift = np.argmin(guide[:, half - shift_max:half + shift_max + 1], axis=1) - shift_max
    index = np.clip(np.arange(len(offsets)) + shift[:, None], 0, len(offsets) - 1)
    samples = np.take_along_axis(samples, index, axis=1)
    samples -= samples[:, half:half + 1]
    return offsets, np.array([np.median(samples[a:b], axis=0) for a, b in pairwise(bounds)])


def line_measures(offsets: np.ndarray, profiles: np.ndarray, trace_width: float) -> tuple[np.ndarray, np.ndarray]:
    """(contrast, asymmetry) of each median profile (n, K) from `cross_profiles`; see the module docstring."""
    def at(d: float) -> np.ndarray:  # every profile at d trace widths, interpolated linearly
        x = (d * trace_width - offsets[0]) / STEP
        i = min(int(x), len(offsets) - 2)
        return profiles[:, i] + (x - i) * (profiles[:, i + 1] - profiles[:, i])

    side = (offsets >= SIDE[0] * trace_width) & (offsets <= SIDE[1] * trace_width)
    left, right = profiles[:, ::-1][:, side], profiles[:, side]  # the mirrored profile holds the left side
    contrast = np.minimum(left.mean(axis=1), right.mean(axis=1))
    lo, hi = at(-TREND), at(TREND)
    centre_dip = 0.5 * (lo + hi)  # the trend line through ±TREND at the centre, where the profile is 0
    slope = 0.5 * (INNER / TREND) * (hi - lo)  # the trend line's rise from the centre to +INNER
    dip_left, dip_right = centre_dip - slope - at(-INNER), centre_dip + slope - at(INNER)
    with np.errstate(divide="ignore", invalid="ignore"):
        asymmetry = np.where(centre_dip > 0, np.abs(dip_left - dip_right) / centre_dip, np.inf)
    return contrast, asymmetry


def are_lines(log_image: np.ndarray, chains: list[np.ndarray], *, trace_width: float, contrast: float,
              asymmetry: float, faint_asymmetry: float | None = None, faint_contrast: float = 0.0,
              raw_log_image: np.ndarray | None = None, raw_contrast: float = math.inf) -> np.ndarray:
    """(n,) bool: which chains are dark lines at least `contrast` (ln units) darker than both sides, with a dip
    no more asymmetric than `asymmetry` (fracture traces rather than creases or steps), or than
    `faint_asymmetry` (default: `asymmetry`) for chains less than `faint_contrast` darker: texture beside a
    weak trace skews its dip, and creases are strong.

    raw_log_image : the photo before denoising (`log_image` being the denoised one); a chain at least
        `raw_contrast` darker on it, measured where the denoised photo has its dip, with the same asymmetry
        limits, is a line too. Denoising flattens faint traces in shade, where the noise is as deep as they are.
    """
    faint = asymmetry if faint_asymmetry is None else faint_asymmetry

    def passes(measured: tuple[np.ndarray, np.ndarray], least: float) -> np.ndarray:
        limit = np.where(measured[0] < faint_contrast, faint, asymmetry)
        return (measured[0] >= least) & (measured[1] <= limit)

    keep = passes(line_measures(*cross_profiles(log_image, chains, trace_width), trace_width), contrast)
    rest = np.flatnonzero(~keep)
    if raw_log_image is not None and len(rest) and math.isfinite(raw_contrast):
        again = [chains[k] for k in rest]
        measured = line_measures(*cross_profiles(raw_log_image, again, trace_width, centre_on=log_image), trace_width)
        keep[rest] = passes(measured, raw_contrast)
    return keep


def _sample(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    return ndimage.map_coordinates(image, [rows.ravel(), cols.ravel()], order=1, mode="nearest").reshape(rows.shape)


def _normals(points: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """Unit normals (N, 2) of chains stacked in `points`, chain k being points[bounds[k]:bounds[k + 1]]."""
    first = np.repeat(bounds[:-1], np.diff(bounds))
    last = np.repeat(bounds[1:] - 1, np.diff(bounds))
    index = np.arange(len(points))
    tangent = points[np.minimum(index + ALONG, last)] - points[np.maximum(index - ALONG, first)]
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return np.column_stack([-tangent[:, 1], tangent[:, 0]])
