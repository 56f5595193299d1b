"""Guided manual traces: a smoothing spline through clicked points, or a least-cost path between clicks.

The least-cost path works as CloudCompare's Compass trace tool does on a cloud, here on the photo: each
click snaps to the cheapest pixel near it, and consecutive clicks are joined by the path of least
accumulated cost (Dijkstra on the 8-connected pixel grid, skimage.graph.route_through_array), where cost is
low on the fracture: strong phase congruency, or dark against the surrounding rock.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import interpolate
from skimage.graph import route_through_array

from engine.delineate.params import Range, check_range
from engine.errors import InputError
from engine.traces import polyline_length, resample_polyline

RANGES = {
    "sigma": Range(lo=0),
    "spacing": Range(lo=0, lo_open=True),
    "line_width": Range(lo=1, integer=True),
    "epsilon": Range(lo=0, lo_open=True),
    "snap_radius": Range(lo=0),
    "margin": Range(lo=0),
}
"""The allowed values of the guided curves' parameters (finite, as every `Range`), by keyword."""


def spline_curve(points: np.ndarray, *, sigma: float = 1.0, spacing: float = 1.0) -> np.ndarray:
    """Smoothing cubic spline through clicked points (N, 2), sampled every `spacing` px along it.

    sigma : expected error of a click, in the units of the points (px). The smoothing is s = m·σ² for m
    points (MATHS §5): never scipy's default s = m − √(2m), which is in the points' squared units
    and, on coordinates of another scale, flattens real waviness. Repeated clicks are dropped; two points
    give a straight line.
    """
    _check(sigma=sigma, spacing=spacing)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(points)):
        raise InputError(None, "spline_curve: the points must be finite")
    keep = np.concatenate([[True], np.any(np.diff(points, axis=0) != 0, axis=1)])
    points = points[keep]  # splprep refuses repeated consecutive points
    if len(points) < 2:
        raise InputError(None, f"spline_curve needs at least 2 distinct points; got {len(points)}")
    if len(points) == 2:
        return resample_polyline(points, spacing)[0]
    m = len(points)
    tck, _ = interpolate.splprep(points.T, s=m * sigma**2, k=min(3, m - 1))
    # evaluate densely (≥ 4 samples per `spacing` of chord), then space evenly by arc length
    samples = 4 * math.ceil(polyline_length(points) / spacing) + 2
    dense = np.column_stack(interpolate.splev(np.linspace(0, 1, samples), tck))
    return resample_polyline(dense, spacing)[0]


def darkness(image: np.ndarray, *, line_width: int = 7) -> np.ndarray:
    """How much darker than its surroundings each pixel is, in [0, 1] (black top-hat, robustly scaled).

    image : 8-bit grey or RGB, or float in [0, 1]. line_width : side (px) of the square the surroundings are
    taken from; lines narrower than it stand out. Scaled by the 99.5th percentile, so one black speck does
    not flatten the rest.
    """
    _check(line_width=line_width)
    grey = _grey_u8(image)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (int(line_width), int(line_width)))
    hat = cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel).astype(np.float32)
    scale = max(float(np.percentile(hat, 99.5)), 1.0)
    return np.clip(hat / scale, 0, 1)


def trace_cost(strength: np.ndarray, *, epsilon: float = 0.05) -> np.ndarray:
    """Cost per pixel 1/(ε + s) for a strength s in [0, 1] (phase congruency, or `darkness`).

    epsilon : cost floor; the ratio of cost off and on a strong fracture is about (1 + ε)/ε.
    """
    _check(epsilon=epsilon)
    return 1.0 / (epsilon + np.clip(np.asarray(strength, dtype=np.float64), 0, 1))


def least_cost_curve(cost: np.ndarray, clicks: np.ndarray, *, snap_radius: float = 3.0,
                     margin: float = 32.0) -> np.ndarray:
    """A trace through clicked points (N, 2) (u, v) following the cheapest path between consecutive clicks.

    Each click first moves to the cheapest pixel within `snap_radius` px. The path between two clicks is
    searched in their bounding box widened by max(margin, half their distance) px, so a click on a 24 MP
    photo costs milliseconds. Returns the polyline resampled at 1 px spacing.
    """
    _check(snap_radius=snap_radius, margin=margin)
    cost = np.asarray(cost, dtype=np.float64)
    clicks = np.asarray(clicks, dtype=np.float64).reshape(-1, 2)
    if cost.ndim != 2 or not np.all(np.isfinite(cost)) or cost.min() < 0:
        raise InputError(None, "least_cost_curve: cost must be a finite, non-negative (H, W) array")
    if len(clicks) < 2:
        raise InputError(None, f"least_cost_curve needs at least 2 clicks; got {len(clicks)}")
    height, width = cost.shape
    inside = (clicks[:, 0] >= -0.5) & (clicks[:, 0] <= width - 0.5) & (clicks[:, 1] >= -0.5) \
        & (clicks[:, 1] <= height - 0.5)
    if not inside.all():
        raise InputError(None, f"click {int(np.argmin(inside))} lies outside the {width}×{height} photo")
    snapped = [_snap(cost, c, snap_radius) for c in clicks]
    path = [snapped[0]]
    for a, b in zip(snapped[:-1], snapped[1:]):
        path.extend(_route(cost, a, b, margin)[1:])
    rc = np.array(path, dtype=np.float64)
    return resample_polyline(rc[:, ::-1], 1.0)[0] if len(rc) > 1 else rc[:, ::-1]


def _check(**values: float) -> None:
    for name, value in values.items():
        check_range(name, value, RANGES[name])


def _snap(cost: np.ndarray, click: np.ndarray, radius: float) -> tuple[int, int]:
    """(row, col) of the cheapest pixel within `radius` px of the click (the nearest on ties)."""
    u, v = np.rint(click).astype(int)
    r = int(math.floor(radius))
    rows = np.arange(max(v - r, 0), min(v + r, cost.shape[0] - 1) + 1)
    cols = np.arange(max(u - r, 0), min(u + r, cost.shape[1] - 1) + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    d2 = (rr - click[1]) ** 2 + (cc - click[0]) ** 2
    within = d2 <= radius**2 + 1e-9
    if not within.any():
        return int(v), int(u)
    order = np.lexsort((d2[within], cost[rr[within], cc[within]]))
    return int(rr[within][order[0]]), int(cc[within][order[0]])


def _route(cost: np.ndarray, a: tuple[int, int], b: tuple[int, int], margin: float) -> list[tuple[int, int]]:
    """Least-cost 8-connected pixel path from a to b (row, col) inside their widened bounding box."""
    widen = int(math.ceil(max(margin, 0.5 * math.dist(a, b))))
    r0, c0 = max(min(a[0], b[0]) - widen, 0), max(min(a[1], b[1]) - widen, 0)
    r1, c1 = min(max(a[0], b[0]) + widen, cost.shape[0] - 1), min(max(a[1], b[1]) + widen, cost.shape[1] - 1)
    window = cost[r0:r1 + 1, c0:c1 + 1]
    path, _ = route_through_array(window, (a[0] - r0, a[1] - c0), (b[0] - r0, b[1] - c0),
                                  fully_connected=True, geometric=True)
    return [(r + r0, c + c0) for r, c in path]


def _grey_u8(image: np.ndarray) -> np.ndarray:
    """8-bit grey from an 8-bit grey or RGB photo, or from a float one in [0, 1]."""
    image = np.asarray(image)
    if image.dtype.kind == "f":
        image = np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(None, f"darkness needs a grey (H, W) or RGB (H, W, 3) photo, 8-bit or float in [0, 1]; "
                               f"got {image.dtype} {image.shape}")
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
