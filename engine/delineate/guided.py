"""Guided manual traces: a smoothing spline through clicked points, or a least-cost path between clicks.

The least-cost path works as CloudCompare's Compass trace tool does on a cloud, here on the photo: each
click snaps to the cheapest pixel near it, and consecutive clicks are joined by the path of least
accumulated cost (Dijkstra on the 8-connected pixel grid, a step costing as in skimage's MCP_Geometric),
where cost is low on the fracture: strong phase congruency, or dark against the surrounding rock.

Dijkstra visits every pixel cheaper to reach than the far click, an area growing with the square of the
clicks' distance (4–5 s for 2000 px on a 24 MP photo with skimage). So clicks farther apart than
`exact_span` are joined coarse to fine: the nearly cheapest paths are found on the cost shrunk FACTOR times
(recursively, until the span is short), and the path is searched at full resolution only near them. The
work then grows with the path's length, and the path keeps to the exact one wherever that follows a trace
(tests/test_delineate.py).
"""

from __future__ import annotations

import functools
import heapq
import math
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np
from scipy import interpolate

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
    "exact_span": Range(lo=0),
    "corridor": Range(lo=0),
    "slack": Range(lo=0),
}
"""The allowed values of the guided curves' parameters (finite, as every `Range`), by keyword."""
FACTOR = 4  # a coarse pixel of the coarse-to-fine search is FACTOR × FACTOR pixels of the finer level


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
    hat = cv2.morphologyEx(grey, cv2.MORPH_BLACKHAT, kernel)
    scale = max(_percentile_u8(hat, 99.5), 1.0)
    return np.clip(hat.astype(np.float32) / scale, 0, 1)


def trace_cost(strength: np.ndarray, *, epsilon: float = 0.05) -> np.ndarray:
    """Cost per pixel 1/(ε + s) for a strength s in [0, 1] (phase congruency, or `darkness`).

    epsilon : cost floor; the ratio of cost off and on a strong fracture is about (1 + ε)/ε.
    """
    _check(epsilon=epsilon)
    cost = np.clip(np.asarray(strength, dtype=np.float64), 0, 1)  # a new array, worked on in place: a 24 MP
    cost += epsilon  # photo's cost is 190 MB, and every temporary of that size costs 100 ms of page faults
    return np.reciprocal(cost, out=cost)


def least_cost_curve(cost: np.ndarray, clicks: np.ndarray, *, snap_radius: float = 3.0, margin: float = 32.0,
                     exact_span: float = 200.0, corridor: float = 8.0, slack: float = 80.0) -> np.ndarray:
    """A trace through clicked points (N, 2) (u, v) following the cheapest path between consecutive clicks.

    Each click first moves to the cheapest pixel within `snap_radius` px. The path between two clicks is
    searched in their bounding box widened by max(margin, half their distance) px. Clicks at most
    `exact_span` px apart get the exact least-cost path there. Farther ones get the cheapest path within
    `corridor` px of the paths found at most `slack` dearer than the cheapest on the cost shrunk `FACTOR`
    times (recursively): a click on a 24 MP photo costs milliseconds, not seconds. `slack` is in the
    cost's units times px: 80 is 80 px of path along a strong trace with `trace_cost`'s costs.
    Returns the polyline resampled at 1 px spacing.
    """
    _check(snap_radius=snap_radius, margin=margin, exact_span=exact_span, corridor=corridor, slack=slack)
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
    snapped = [np.array(_snap(cost, c, snap_radius)) for c in clicks]
    search = _Search(margin, exact_span, corridor, slack)
    legs = [_route(cost, a, b, search)[1:] for a, b in zip(snapped[:-1], snapped[1:])]
    rc = np.vstack([snapped[0], *legs]).astype(np.float64)
    return resample_polyline(rc[:, ::-1], 1.0)[0] if len(rc) > 1 else rc[:, ::-1]


@dataclass(frozen=True)
class _Search:
    """How the path between two clicks is searched (`least_cost_curve`'s keywords), at one level of detail."""

    margin: float
    exact_span: float
    corridor: float
    slack: float

    def coarser(self) -> _Search:
        """The same search FACTOR times coarser: distances and path costs are FACTOR times smaller there;
        the corridor stays in pixels of the level it widens, where it covers a coarse pixel and more."""
        return replace(self, margin=self.margin / FACTOR, slack=self.slack / FACTOR)


def _check(**values: float) -> None:
    for name, value in values.items():
        check_range(name, value, RANGES[name])


def _snap(cost: np.ndarray, click: np.ndarray, radius: float) -> tuple[int, int]:
    """(row, col) of the cheapest pixel within `radius` px of the click (the nearest on ties)."""
    u, v = np.rint(click).astype(int)
    r = math.floor(radius)
    rows = np.arange(max(v - r, 0), min(v + r, cost.shape[0] - 1) + 1)
    cols = np.arange(max(u - r, 0), min(u + r, cost.shape[1] - 1) + 1)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    d2 = (rr - click[1]) ** 2 + (cc - click[0]) ** 2
    within = d2 <= radius**2 + 1e-9
    if not within.any():
        return int(v), int(u)
    order = np.lexsort((d2[within], cost[rr[within], cc[within]]))
    return int(rr[within][order[0]]), int(cc[within][order[0]])


def _route(cost: np.ndarray, a: np.ndarray, b: np.ndarray, search: _Search) -> np.ndarray:
    """Least-cost 8-connected pixel path (K, 2) from a to b (row, col) inside their widened bounding box:
    exact up to `exact_span` px apart, else within `corridor` px of the nearly cheapest coarse paths."""
    lo, searched = _searched(cost, a, b, search)
    start, stop = (int(np.ravel_multi_index(tuple(p - lo), searched.shape)) for p in (a, b))
    _, previous = _dijkstra(searched, start, stop)
    chain = [stop]
    while chain[-1] != start:
        chain.append(int(previous[chain[-1]]))
    return np.column_stack(np.unravel_index(chain[::-1], searched.shape)) + lo


def _nearly_cheapest(cost: np.ndarray, a: np.ndarray, b: np.ndarray,
                     search: _Search) -> tuple[np.ndarray, np.ndarray]:
    """The top-left (row, col) and a mask of the pixels there on every path from a to b at most `slack`
    dearer than the cheapest: those whose cheapest paths to a and to b add up to no more."""
    lo, searched = _searched(cost, a, b, search)
    there, back = (_dijkstra(searched, int(np.ravel_multi_index(tuple(p - lo), searched.shape)), -1)[0]
                   for p in (a, b))
    through = (there + back).reshape(searched.shape)
    return lo, through <= through[tuple(b - lo)] + search.slack


def _searched(cost: np.ndarray, a: np.ndarray, b: np.ndarray, search: _Search) -> tuple[np.ndarray, np.ndarray]:
    """The top-left (row, col) and a contiguous copy of the part of `cost` where a path from a to b is
    searched: the window (`_window`) if they are at most `exact_span` apart, else the `_region` in it,
    cropped to its bounding box, with infinite cost outside."""
    lo, window = _window(cost, a, b, search.margin)
    if math.dist(a, b) <= search.exact_span:
        return lo, np.ascontiguousarray(window)
    region = _region(window, a - lo, b - lo, search)
    (r0, r1), (c0, c1) = (np.flatnonzero(region.any(axis=k))[[0, -1]] for k in (1, 0))
    box = (slice(r0, r1 + 1), slice(c0, c1 + 1))
    return lo + (r0, c0), np.where(region[box], window[box], np.inf)


def _window(cost: np.ndarray, a: np.ndarray, b: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The top-left (row, col) and the view of `cost` in which a path from a to b is searched: their
    bounding box widened by max(margin, half their distance), room for the detours a trace makes."""
    widen = math.ceil(max(margin, 0.5 * math.dist(a, b)))
    lo = np.maximum(np.minimum(a, b) - widen, 0)
    hi = np.minimum(np.maximum(a, b) + widen, np.array(cost.shape) - 1)
    return lo, cost[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1]


def _region(window: np.ndarray, a: np.ndarray, b: np.ndarray, search: _Search) -> np.ndarray:
    """Where to search from a to b in `window` (a mask): within `corridor` px of every path that is at most
    `slack` dearer than the cheapest on the window shrunk FACTOR times. Keeping the nearly cheapest ones,
    not only the cheapest, lets the full resolution decide where the coarse cost cannot (a faint trace
    against a shortcut over shaded rock)."""
    coarse = _shrink(window)
    lo, near = _nearly_cheapest(coarse, a // FACTOR, b // FACTOR, search.coarser())
    mask = np.zeros(coarse.shape, np.uint8)
    mask[lo[0]:lo[0] + near.shape[0], lo[1]:lo[1] + near.shape[1]] = near
    fine = np.repeat(np.repeat(mask, FACTOR, axis=0), FACTOR, axis=1)[:window.shape[0], :window.shape[1]]
    reach = math.ceil(search.corridor)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    return cv2.dilate(fine, disc).astype(bool)


_STEPS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)], dtype=np.int64)
_LENGTHS = np.hypot(_STEPS[:, 0], _STEPS[:, 1])


# compiled (or loaded from numba's cache) at import, and run without the GIL: skimage's and scipy's
# Dijkstra hold it throughout, and the GUI thread would wait for every search a worker makes
@numba.njit("Tuple((float64[::1], int64[::1]))(float64[:, ::1], int64, int64)", nogil=True, cache=True)
def _dijkstra(cost: np.ndarray, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Dijkstra on the 8-connected pixel grid from flat index `start`, until `stop` is settled (never if
    negative): the cost of the cheapest path to each pixel (inf where not reached) and the flat index of the
    pixel before it. A step costs the mean cost of its two pixels times its length, as in skimage's
    MCP_Geometric; infinite cost is impassable."""
    height, width = cost.shape
    flat = cost.ravel()
    dist = np.full(flat.size, np.inf)
    previous = np.full(flat.size, -1, np.int64)
    dist[start] = 0.0
    heap = [(0.0, start)]
    while heap:
        d, i = heapq.heappop(heap)
        if d > dist[i]:
            continue  # a stale entry: i was reached more cheaply since
        if i == stop:
            break
        row, col = divmod(i, width)
        for k in range(8):
            r, c = row + _STEPS[k, 0], col + _STEPS[k, 1]
            if r < 0 or r >= height or c < 0 or c >= width:
                continue
            j = r * width + c
            step = 0.5 * (flat[i] + flat[j]) * _LENGTHS[k]
            if d + step < dist[j]:  # never true for infinite cost
                dist[j] = d + step
                previous[j] = i
                heapq.heappush(heap, (d + step, j))
    return dist, previous


def _shrink(cost: np.ndarray) -> np.ndarray:
    """The cost of crossing each FACTOR × FACTOR block, per pixel, as the coarse search's cost.

    The cheaper of crossing the block left to right or top to bottom, taking the cheapest pixel of each
    column (row) on the way: a trace 1 px wide keeps its cost at any slope, where a block mean would
    dilute it FACTOR times, and the rock's texture is averaged over FACTOR pixels, where a block minimum
    would make its darkest speck a shortcut. The edge is padded with the last row and column.
    """
    rows, cols = (-(-n // FACTOR) * FACTOR for n in cost.shape)
    padded = np.pad(cost, ((0, rows - cost.shape[0]), (0, cols - cost.shape[1])), mode="edge")
    # strided views, not a (rows, FACTOR, cols, FACTOR) reshape: numpy reduces short inner axes slowly
    column_min = functools.reduce(np.minimum, (padded[i::FACTOR] for i in range(FACTOR)))
    row_min = functools.reduce(np.minimum, (padded[:, i::FACTOR] for i in range(FACTOR)))
    across = functools.reduce(np.add, (column_min[:, i::FACTOR] for i in range(FACTOR)))
    down = functools.reduce(np.add, (row_min[i::FACTOR] for i in range(FACTOR)))
    return np.minimum(across, down) / FACTOR


def _percentile_u8(values: np.ndarray, q: float) -> float:
    """np.percentile(values, q) of 8-bit values, from their histogram: 10 ms on 8 MP, where sorting takes 90."""
    counts = np.cumsum(np.bincount(values.ravel(), minlength=256))
    position = q / 100 * (counts[-1] - 1)
    below = math.floor(position)
    # the k-th smallest value (from 0) is the first whose cumulative count exceeds k
    lo, hi = np.searchsorted(counts, [below, min(below + 1, counts[-1] - 1)], side="right")
    return float(lo + (position - below) * (hi - lo))


def _grey_u8(image: np.ndarray) -> np.ndarray:
    """8-bit grey from an 8-bit grey or RGB photo, or from a float one in [0, 1]."""
    image = np.asarray(image)
    if image.dtype.kind == "f":
        image = np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(None, f"darkness needs a grey (H, W) or RGB (H, W, 3) photo, 8-bit or float in [0, 1]; "
                               f"got {image.dtype} {image.shape}")
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
