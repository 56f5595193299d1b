"""Oriented line filter: a second detector of thin dark lines, for the faint traces phase congruency misses.

Phase congruency is local: its filters span a few wavelengths, so on mottled rock a faint trace falls below
its noise threshold in places and the skeleton breaks, or follows the brighter rock beside the trace. A trace
is long, so a filter elongated along it sees it better: a Gaussian along the line (σ `length`) times the
second derivative of a Gaussian across it (σ `sigma`): the oriented matched filter of thin dark lines
(Chaudhuri et al. 1989, IEEE TMI 8(3)), a ridge detector (Steger 1998, IEEE PAMI 20(2)) elongated along the
line, at `norient` orientations. It
runs on log brightness, as phase congruency does (`pipeline`), so a trace darkens shaded rock as much as
sunlit rock. Mottling is dark too, but broad: the same filter with a wider cross-section (σ `wide`) answers to
it as much as the thin one, and a pixel counts as line only where the thin response is at least `ratio` of
the wide one. The responses are thinned across the line and thresholded with hysteresis, and the lines join
the phase-congruency skeleton before chains are judged (`segments`, `line_profile`), so what makes a
trace is decided in one place.

The filters are built in the frequency domain: a Gaussian's transform is a Gaussian, and the second
derivative multiplies it by −ω². They reach a few σ, so the photo is filtered in tiles with a margin of
`MARGIN` σ along (reflected at the photo's border), on worker threads, and memory stays bounded on 24 MP
photos. Both filters are evaluated at every pixel and orientation: the wide one on a half-resolution grid,
interpolated back, was off by up to 0.13 beside the skyline, where its response changes that much from one
pixel to the next; and at every other orientation it was up to 27% low (at 15° from a line it answers 73–83%).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import scipy.fft as sfft

from engine.delineate.edges import non_maximum_suppression
from engine.delineate.params import check
from engine.errors import InputError

# each lobe of a unit Gaussian's second derivative across, times a unit Gaussian along, sums to
# 2 e^(-1/2) / (σ² √(2π)): dividing by it, a dip of depth d that fills the centre lobe answers d
LOBE = 2.0 * math.exp(-0.5) / math.sqrt(2.0 * math.pi)
TILE = 1024  # px: core of a tile; with its margins its transforms stay in cache
MARGIN = 4.0  # σ along: a tile's margin (the filter's tail there is e^-8 of its peak)
NMS_RADIUS = 1.0  # px: the thin response falls off within a pixel across a line, so lines 2 px apart stay two


@dataclass(frozen=True, eq=False)
class LineMap:
    """The line-filter stage (H, W): the thin-line strength where it peaks across the line (ln brightness;
    float32, 0 elsewhere and where the wide filter answers as much) and its hysteresis mask (bool; lines one
    or two pixels wide, thinned with the edges in `autotrace`)."""

    strength: np.ndarray
    mask: np.ndarray


def line_filter(log_image: np.ndarray, *, sigma: float = 1.0, length: float = 5.0, norient: int = 12,
                wide: float = 2.5, ratio: float = 0.8, low: float = 0.07, high: float = 0.12,
                workers: int | None = None) -> LineMap:
    """Thin dark lines in a log-brightness image (H, W) (`line_profile.log_brightness`; negate it for bright lines).

    sigma : cross-section σ of the line filter, px (a trace about 2σ wide answers most).
    length : σ along the line, px: texture is averaged over about 2·length.
    norient : orientations over 180°.
    wide : cross-section σ of the wide filter, px; ratio : least ratio of the thin response to the wide one.
    low, high : hysteresis thresholds on the thin response, ln brightness (0.07 ≈ a line 7% darker).
    workers : threads (default: the CPUs this process may use).
    """
    for field_name, name, value in (("line_sigma", "sigma", sigma), ("line_length", "length", length),
                                    ("line_norient", "norient", norient), ("line_wide", "wide", wide),
                                    ("line_ratio", "ratio", ratio), ("line_low", "low", low),
                                    ("line_high", "high", high)):
        check(field_name, value, name)
    if wide <= sigma:
        raise InputError(None, f"wide={wide!r} must exceed sigma={sigma!r}")
    if low > high:
        raise InputError(None, f"low={low!r} must not exceed high={high!r}")
    image = np.asarray(log_image, np.float32)
    if image.ndim != 2 or min(image.shape) < 2:
        raise InputError(None, f"line filter: expected a 2D image, got shape {image.shape}")
    bank = _Bank(float(sigma), float(length), int(norient), float(wide), float(ratio))
    strength = _tiled(image, bank, low, workers)
    return LineMap(strength, _hysteresis(strength, low, high))


def _tiled(image: np.ndarray, bank: _Bank, floor: float, workers: int | None) -> np.ndarray:
    """`bank.respond` over the photo in square tiles of one fast FFT size, reflected at the photo's border."""
    height, width = image.shape
    margin = math.ceil(MARGIN * max(bank.length, bank.wide))
    fit = max(math.ceil(n / math.ceil(n / TILE)) for n in (height, width))  # the fewest tiles, evenly cut
    side = sfft.next_fast_len(fit + 2 * margin, real=True)
    core = side - 2 * margin
    n_rows, n_cols = math.ceil(height / core), math.ceil(width / core)
    padded = cv2.copyMakeBorder(image, margin, margin + n_rows * core - height, margin,
                                margin + n_cols * core - width, cv2.BORDER_REFLECT_101)
    strength = np.zeros((n_rows * core, n_cols * core), np.float32)

    def run(corner: tuple[int, int]) -> None:
        r, c = corner
        inner = (slice(margin, side - margin), slice(margin, side - margin))
        strength[r:r + core, c:c + core] = bank.respond(padded[r:r + side, c:c + side], floor)[inner]

    with ThreadPoolExecutor(workers or len(os.sched_getaffinity(0))) as pool:
        list(pool.map(run, [(r * core, c * core) for r in range(n_rows) for c in range(n_cols)]))
    return strength[:height, :width]


def _hysteresis(strength: np.ndarray, low: float, high: float) -> np.ndarray:
    """Pixels above `low` 8-connected to one above `high`. skimage's `apply_hysteresis_threshold` takes
    about 20 bytes a pixel (0.5 GB on a 24 MP photo) whatever the lines, this about 6."""
    count, labels = cv2.connectedComponents((strength > low).view(np.uint8), connectivity=8)
    keep = np.zeros(count, bool)
    keep[labels[strength > high]] = True
    keep[0] = False
    return keep[labels]


@dataclass(frozen=True)
class _Bank:
    """The thin and wide filters at every orientation, applied to one tile at a time."""

    sigma: float
    length: float
    norient: int
    wide: float
    ratio: float

    def respond(self, tile: np.ndarray, floor: float) -> np.ndarray:
        """The strongest thin response over orientations where it beats `ratio` × the strongest wide one and
        its neighbours across the line (non-maximum suppression of pixels above `floor`), 0 elsewhere."""
        side = tile.shape[0]  # square (`line_filter`)
        spectrum = sfft.rfft2(tile, workers=1)
        thin_filters, wide_filters = _filters(side, self.sigma, self.length, self.norient, self.wide)
        best = np.full((side, side), -np.inf, np.float32)
        index = np.zeros((side, side), np.uint8)
        better = np.empty((side, side), bool)
        broad = np.zeros((side, side), np.float32)
        for k in range(self.norient):
            thin = sfft.irfft2(spectrum * thin_filters[k], s=(side, side), workers=1)
            np.greater(thin, best, out=better)
            np.copyto(best, thin, where=better)
            np.copyto(index, k, where=better)
            np.maximum(broad, sfft.irfft2(spectrum * wide_filters[k], s=(side, side), workers=1), out=broad)
        best[best < self.ratio * broad] = 0.0
        normal = -(index * np.float32(math.pi / self.norient) + np.float32(math.pi / 2))  # anticlockwise, y up
        return non_maximum_suppression(best, normal, radius=NMS_RADIUS, floor=floor)


@lru_cache(maxsize=2)
def _filters(side: int, sigma: float, length: float, norient: int, wide: float) -> tuple[list, list]:
    """The thin and the wide filters of a square tile at every orientation (about 55 MB for a whole tile; two
    sets are kept, for the photo and a preview of part of it)."""
    angles = [math.pi * k / norient for k in range(norient)]
    return ([_filter(side, theta, sigma, length) for theta in angles],
            [_filter(side, theta, wide, length) for theta in angles])


def _filter(side: int, theta: float, sigma: float, length: float) -> np.ndarray:
    """rfft2-shaped transfer function (float32) of the line filter along direction theta (x right, y down) for
    a square tile, normalised by LOBE / σ²."""
    wy = 2 * math.pi * sfft.fftfreq(side)[:, None]
    wx = 2 * math.pi * sfft.rfftfreq(side)[None, :]
    w_along = wx * math.cos(theta) + wy * math.sin(theta)
    w_across = -wx * math.sin(theta) + wy * math.cos(theta)
    gain = -(sigma ** 2 / LOBE) * w_across ** 2 * np.exp(-0.5 * ((length * w_along) ** 2 + (sigma * w_across) ** 2))
    return gain.astype(np.float32)
