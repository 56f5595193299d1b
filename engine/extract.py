"""2D traces to 3D: cast one ray per trace pixel onto the mesh (Seers & Hodgetts 2016a §3.2, the ray tree).

Each 2D polyline is sampled at ≤ 1 px spacing, keeping its vertices, so a 3D trace is as dense as the photo
allows. Rays that miss the mesh, and jumps in depth where the line of sight slides off a ledge onto a surface
behind it, split the trace; the ends cut there are censored (C), since the fracture continues out of view.
Pieces of a split trace shorter than `min_run` rays (25) are dropped: along an occluding edge the rays of
mixed pixels land on either surface, and such slivers, 10–40 rays long, lie 2–30 cm off the fracture and
merge with nothing (measured on the synthetic outcrop with 2 mm mesh noise: with 10, automatic merging left
114 traces for 105 visible pieces on seed 1 and 126 for 114 on seed 0; with 25, 110 and 114).
Before that, a piece's cut ends are trimmed back past rays that graze the face they hit (more than GRAZING
from its normal): along the silhouette a ray skims the noisy surface and lands centimetres off along its
line (measured, undulating fractures on 2 mm of noise: vertices at 85–90° incidence lie a median 13–28 mm
off the true trace against 1 mm below 60°). Trimming them left fewer slivers to merge: on seeds 1 and 4,
merged traces 111 → 108 and 91 → 85, and the one merge there of two fractures was gone; planar seeds 0, 1,
4 unchanged (80° trimmed too much: seed 0 92 → 97).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.raytrace import RayTracer
from engine.traces import Trace2D, Trace3D, first_outside

GRAZING = 85.0
"""Degrees between a ray and the normal of the face it hits beyond which the hit is trimmed off a cut end."""


@dataclass(frozen=True)
class Extraction:
    """3D traces made from a batch of 2D traces, with the ray counts behind them."""

    traces: list[Trace3D]
    n_rays: int
    n_missed: int
    n_split: int
    n_dropped: int  # slivers shorter than `min_run` rays cut off by a split


def sample_polyline(polyline: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """Points along a polyline at most `spacing` apart (pixels), keeping every vertex."""
    polyline = np.asarray(polyline, dtype=np.float64)
    if len(polyline) < 2:
        return polyline.copy()
    seg = np.diff(polyline, axis=0)
    counts = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / spacing).astype(int), 1)
    starts = np.repeat(polyline[:-1], counts, axis=0)
    fractions = np.concatenate([np.arange(c) / c for c in counts])
    points = starts + fractions[:, None] * np.repeat(seg, counts, axis=0)
    return np.vstack([points, polyline[-1:]])


def check_in_image(trace: Trace2D, camera: Camera) -> None:
    """Raise if any vertex lies outside the photo (pixel centres run from 0 to size - 1)."""
    k = first_outside(trace.polyline, camera.width, camera.height)
    if k is not None:
        uv = trace.polyline
        raise InputError(None, f"trace {trace.id} on image {trace.image!r}: vertex {k} at "
                               f"({uv[k, 0]:.1f}, {uv[k, 1]:.1f}) is outside the "
                               f"{camera.width}×{camera.height} photo")


def extract_traces(traces: Sequence[Trace2D], cameras: dict[str, Camera], tracer: RayTracer, *,
                   spacing: float = 1.0, max_jump: float = 10.0, min_run: int = 25,
                   progress: Progress | None = None) -> Extraction:
    """Ray-trace 2D traces onto the mesh.

    cameras : in the mesh's local frame (`Camera.shifted(origin)`).
    spacing : ray spacing along each 2D trace, pixels (≤ 1 gives one ray per trace pixel).
    max_jump : a step between neighbouring 3D vertices longer than `max_jump` pixel footprints is a depth
        discontinuity (occlusion edge); the trace is split there and both cut ends are censored.
    min_run : pieces of a split trace with fewer rays than this are dropped (module docstring); a 2D trace
        hit whole is kept however short.
    Returns 3D traces with id 0 (the project assigns ids), one per unbroken run of ≥ 2 hits.
    """
    if not 0 < spacing <= 1.0:
        raise InputError(None, f"spacing must be in (0, 1] pixel, got {spacing}")
    if min_run < 2:
        raise InputError(None, f"min_run must be at least 2 rays, got {min_run}")
    by_image: dict[str, list[Trace2D]] = {}
    for trace in traces:
        if trace.image not in cameras:
            raise InputError(None, f"trace {trace.id}: image {trace.image!r} has no camera in the project")
        check_in_image(trace, cameras[trace.image])
        by_image.setdefault(trace.image, []).append(trace)
    out: list[Trace3D] = []
    counts = np.zeros(4, dtype=int)  # rays, missed, split, dropped
    for done, (image, group) in enumerate(by_image.items()):
        report(progress, done / len(by_image), f"ray tracing {image}")
        made, *image_counts = _extract_image(group, cameras[image], tracer, spacing, max_jump, min_run)
        out += made
        counts += image_counts
    report(progress, 1.0, "ray tracing done")
    return Extraction(out, *map(int, counts))


def _extract_image(group: list[Trace2D], camera: Camera, tracer: RayTracer, spacing: float, max_jump: float,
                   min_run: int) -> tuple[list[Trace3D], int, int, int, int]:
    samples = [sample_polyline(t.polyline, spacing) for t in group]
    uv = np.vstack(samples)
    rays = camera.pixel_rays(uv)
    hits = tracer.intersect(camera.centre, rays)
    grazing = _grazing(tracer, hits.face, rays)
    footprint = hits.t / camera.K[0, 0]  # metres per pixel along each ray
    made: list[Trace3D] = []
    n_split = n_dropped = 0
    start = 0
    for trace, pts in zip(group, samples):
        stop = start + len(pts)
        runs = _unbroken_runs(hits.hit[start:stop], hits.points[start:stop], footprint[start:stop], max_jump)
        n_split += len(runs) > 1
        if runs != [(0, len(pts))]:
            runs = [_trimmed(lo, hi, len(pts), grazing[start:stop]) for lo, hi in runs]
            kept = [(lo, hi) for lo, hi in runs if hi - lo >= min_run]
            n_dropped += len(runs) - len(kept)
            runs = kept
        for lo, hi in runs:
            sl = slice(start + lo, start + hi)
            made.append(Trace3D(0, hits.points[sl], uv[sl], hits.face[sl], np.zeros(hi - lo), (camera.name,),
                                parents=(trace.id,), term_start="C" if lo > 0 else "",
                                term_end="C" if hi < len(pts) else ""))
        start = stop
    return made, len(uv), hits.n_missed, n_split, n_dropped


def _grazing(tracer: RayTracer, face: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """True where a ray hits its face more than GRAZING degrees from the face normal (misses: False)."""
    out = np.zeros(len(face), dtype=bool)
    hit = np.flatnonzero(face >= 0)
    a, b, c = (tracer.vertices[tracer.faces[face[hit], k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    cosine = np.abs(np.einsum("ij,ij->i", normal, rays[hit]))
    cosine /= np.linalg.norm(normal, axis=1) * np.linalg.norm(rays[hit], axis=1)
    out[hit] = cosine < np.cos(np.radians(GRAZING))
    return out


def _trimmed(lo: int, hi: int, n: int, grazing: np.ndarray) -> tuple[int, int]:
    """The run lo:hi of a trace of n rays without the grazing hits at its cut ends (not at the trace's own)."""
    if lo > 0:
        while lo < hi and grazing[lo]:
            lo += 1
    if hi < n:
        while hi > lo and grazing[hi - 1]:
            hi -= 1
    return lo, hi


def _unbroken_runs(hit: np.ndarray, points: np.ndarray, footprint: np.ndarray,
                   max_jump: float) -> list[tuple[int, int]]:
    """Half-open index ranges of consecutive hits with no depth jump, each of ≥ 2 vertices."""
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    limit = max_jump * np.fmin(footprint[:-1], footprint[1:])
    joined = hit[:-1] & hit[1:] & (step <= limit)  # NaN steps (misses) compare False
    breaks = np.flatnonzero(~joined) + 1
    bounds = np.concatenate([[0], breaks, [len(hit)]])
    return [(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi - lo >= 2]
