"""Edges from phase congruency: non-maximum suppression, hysteresis, thinning.

Kovesi's post-processing of phasecong3 (MATHS §2.1): `nonmaxsup(M, ori, 1.5)`, `hysthresh(nm, T1, T2)`,
then thinning. Suppression runs across the principal axis of phase congruency rather than Kovesi's `ori`,
which comes from the odd responses alone: those vanish at the centre of a line, so `ori` is noisy exactly on
the thin dark lines fractures make, and the suppressed lines break into dashes. Feature type (dark line,
bright line, step) is judged per segment (`find_segments`), where the median over many pixels is steady.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.filters import apply_hysteresis_threshold
from skimage.morphology import skeletonize

from engine.delineate.params import check
from engine.delineate.phase import PhaseCongruency
from engine.errors import InputError


@dataclass(frozen=True, eq=False)
class EdgeMap:
    """The edge stage (H, W): suppressed strength (float32), hysteresis mask and one-pixel skeleton (bool)."""

    strength: np.ndarray
    mask: np.ndarray
    skeleton: np.ndarray


def detect_edges(pc: PhaseCongruency, *, low: float = 0.03, high: float = 0.1,
                 nms_radius: float = 1.5) -> EdgeMap:
    """Thin edges from phase congruency.

    low, high : hysteresis thresholds on edge strength (max moment M, in [0, 1]).
    nms_radius : distance (px) along the feature normal at which a pixel must beat its neighbours.
    """
    for name, value in (("low", low), ("high", high), ("nms_radius", nms_radius)):
        check(name, value)
    if low > high:
        raise InputError(None, f"low={low!r} must not exceed high={high!r}")
    strength = non_maximum_suppression(pc.edge, pc.axis, radius=nms_radius, floor=low)
    mask = apply_hysteresis_threshold(strength, low, high)
    return EdgeMap(strength, mask, skeletonize(mask))


def non_maximum_suppression(strength: np.ndarray, orientation: np.ndarray, *, radius: float = 1.5,
                            floor: float = 0.0) -> np.ndarray:
    """Keep pixels stronger than both neighbours at ±radius along the feature normal (Kovesi's nonmaxsup).

    orientation : feature-normal angle in radians, anticlockwise with the image y axis up.
    Only pixels above `floor` are examined (the rest are zero in the result); neighbours are interpolated
    bilinearly.
    """
    out = np.zeros_like(strength)
    rows, cols = np.nonzero(strength > floor)
    if len(rows) == 0:
        return out
    theta = orientation[rows, cols].astype(np.float64)
    dx, dy = radius * np.cos(theta), radius * np.sin(theta)
    value = strength[rows, cols]
    ahead = ndimage.map_coordinates(strength, [rows - dy, cols + dx], order=1, mode="nearest")
    behind = ndimage.map_coordinates(strength, [rows + dy, cols - dx], order=1, mode="nearest")
    keep = (value > ahead) & (value > behind)
    out[rows[keep], cols[keep]] = value[keep]
    return out
