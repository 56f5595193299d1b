"""Where a photo sees the mesh's silhouette: its outline against what lies beyond the model (sky, ground),
and the occluding contours inside it, where the line of sight jumps from a near surface to a far one.

A dark line along a silhouette is the shadowed rim of a ledge or the shade beneath it more often than a
fracture trace, and a trace there cannot be placed in 3D anyway: rays either side of it land on different
surfaces, and `engine.extract` drops such pixels. So `autotrace` drops proposals that run along the
silhouette when it is given one (the mesh and the photo's calibrated camera give it; the photo alone
does not). Creases of the surface are not part of it: the edge of an exposed fracture face is a crease and
is exactly the trace a geologist wants.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from engine.cameras import Camera
from engine.delineate.params import check
from engine.raytrace import RayTracer

STRIDE = 4
"""Pixels between the rays of the first pass; the second casts every pixel of the cells it found mixed."""

CHUNK = 1 << 20
"""Rays cast at once: bounds the memory of the hits (about 70 bytes a ray) on 24 MP photos."""

STRIP = 256
"""Rows of the second pass at a time: with every cell mixed, a 6000 px wide photo takes about 100 MB."""


def silhouette(camera: Camera, tracer: RayTracer, *, depth_step: float = 0.03) -> np.ndarray:
    """Pixels (H, W) of the photo on the silhouette of the mesh: where the line of sight of a 4-neighbour
    meets the mesh and this pixel's does not, or both meet it at ranges differing by more than `depth_step`
    in natural log (0.03 ≈ 3%, reached only where the surface is within 2° of grazing or hidden behind a
    nearer one).

    camera : calibrated, in the ray tracer's frame (`Camera.shifted(mesh.origin)`), with a distortion that
        inverts over the image (`engine.cameras.check_invertible`, as every camera read from a file).
    Rays are cast every STRIDE px, then at every pixel of the cells whose corners disagree (one meets the
    mesh and one does not, or their ranges differ by more than `depth_step`) and of the cells round them,
    STRIP rows at a time.
    """
    check("silhouette_step", depth_step, "depth_step")
    h, w = camera.height, camera.width
    to_cast = _pixels_to_cast(camera, tracer, depth_step)
    out = np.zeros((h, w), bool)
    for r0 in range(0, h, STRIP):
        r1 = min(r0 + STRIP, h)
        a, b = max(r0 - 1, 0), min(r1 + 1, h)  # a row beyond each end: neighbours across the strip's edges
        known = to_cast(a, b)
        v, u = np.nonzero(known)
        hit = np.zeros(known.shape, bool)
        log_range = np.zeros(known.shape, np.float32)
        hit[v, u], log_range[v, u] = _cast(camera, tracer, u, v + a)
        out[r0:r1] = _contour(hit, log_range, known, depth_step)[r0 - a:r1 - a]
    return out


def _pixels_to_cast(camera: Camera, tracer: RayTracer,
                    depth_step: float) -> Callable[[int, int], np.ndarray]:
    """The first pass: a function of rows a:b giving which of their pixels the second pass casts."""
    h, w = camera.height, camera.width
    if h < 2 or w < 2:  # no cells to tell: every pixel
        return lambda a, b: np.ones((b - a, w), bool)
    rows, cols = _grid(h), _grid(w)
    hit, log_range = _cast(camera, tracer, *np.meshgrid(cols, rows))
    mixed = _mixed_cells(hit, log_range, depth_step)
    # every pixel of a mixed cell and of the cells round it: a contour on a cell's edge has pixels in both
    mixed = cv2.dilate(mixed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    row_cell = np.minimum(np.arange(h) // STRIDE, len(rows) - 2)
    col_cell = np.minimum(np.arange(w) // STRIDE, len(cols) - 2)
    return lambda a, b: mixed[row_cell[a:b, None], col_cell[None, :]]


def _grid(n: int) -> np.ndarray:
    """Pixel indices every STRIDE from 0, with the last pixel always included."""
    return np.unique(np.r_[np.arange(0, n, STRIDE), n - 1])


def _cast(camera: Camera, tracer: RayTracer, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether the line of sight of each pixel (u, v) meets the mesh, and the log of its range there."""
    shape = np.shape(u)
    u, v = np.ravel(u), np.ravel(v)
    hit = np.zeros(u.shape, bool)
    log_range = np.zeros(u.shape, np.float32)
    centre = camera.centre
    for lo in range(0, len(u), CHUNK):
        part = slice(lo, lo + CHUNK)
        hits = tracer.intersect(centre, camera.pixel_rays(np.column_stack([u[part], v[part]]).astype(float)))
        hit[part] = hits.hit
        log_range[part] = np.log(np.where(hits.hit, hits.t, 1.0))
    return hit.reshape(shape), log_range.reshape(shape)


def _mixed_cells(hit: np.ndarray, log_range: np.ndarray, depth_step: float) -> np.ndarray:
    """Cells of the coarse grid whose four corners disagree: some meet the mesh and some do not, or the
    ranges of those that do span more than `depth_step`."""
    corners = [(slice(0, -1), slice(0, -1)), (slice(0, -1), slice(1, None)),
               (slice(1, None), slice(0, -1)), (slice(1, None), slice(1, None))]
    hits = np.stack([hit[c] for c in corners])
    ranges = np.stack([np.where(hit[c], log_range[c], np.nan) for c in corners])
    some = hits.any(axis=0)
    with np.errstate(invalid="ignore"):
        span = np.nanmax(np.where(some, ranges, 0.0), axis=0) - np.nanmin(np.where(some, ranges, 0.0), axis=0)
    return (some & ~hits.all(axis=0)) | (span > depth_step)


def _contour(hit: np.ndarray, log_range: np.ndarray, known: np.ndarray, depth_step: float) -> np.ndarray:
    """Pixels of which a 4-neighbour (both cast) differs: one meets the mesh and the other does not, or
    both do at log ranges more than `depth_step` apart."""
    out = np.zeros(hit.shape, bool)
    for a, b in (((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                 ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))):
        cast = known[a] & known[b]
        edge = cast & ((hit[a] != hit[b]) | (hit[a] & hit[b] & (np.abs(log_range[a] - log_range[b]) > depth_step)))
        out[a] |= edge
        out[b] |= edge
    return out
