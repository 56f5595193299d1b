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

A trace pixel on an occluding edge is dropped first: where a side ray, `edge_px` to either side across
the trace, meets the mesh more than `max_jump` footprints nearer or farther than the pixel's own ray (or
misses). Which surface such a ray meets depends on sub-pixel detail of the mesh at the silhouette, which
photogrammetric noise decides: on the synthetic outcrops with 2 mm of mesh noise, every extracted vertex
more than 3 cm off the true trace (108–497 per outcrop, up to 31 cm off, in runs along silhouettes that no
jump split) was such a pixel, and none is left. Dropped pixels do not split a trace: the hits either side
stay joined when they lie within `max_jump` footprints per ray skipped (a trace wrapping round the corner
of a ledge), and a trace that only loses edge pixels is kept however short, down to MIN_VERTICES hits;
`min_run` still drops slivers cut off by a miss or a jump. It costs about one more ray per trace pixel
(two side rays at a quarter of them, and at every pixel near an edge).
How far across to look is set by the mesh, not the photo: the side rays look EDGE_SPACING (0.4) of the
mesh's mean edge length across, at least 2 px. Measured, every photo's true traces of the noisy synthetic
outcrops (mean edge 11 cm) at 1600×1200 (footprint 9.6 mm): with 0.2, vertices 4–7 cm off the truth on 3
of 12 held-out outcrops (10, 7 and 1 of them) and 2.5–10% of the rays given up; with 0.3, 4 cm on one;
with 0.4, none 3 cm off on all 19 outcrops (worst 25 mm) and 4–18% given up. Fixed 2 px, as before
session 6, left vertices up to 25 mm off at 3200×2400 on outcrops where 1600×1200 stayed within 19 mm.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.mesh import mean_edge_length
from engine.raytrace import RayTracer
from engine.traces import Trace2D, Trace3D, first_outside

MIN_VERTICES = 3
"""Fewest hits a 3D trace is made of: merging and orientation need three vertices (a piece of two, a pixel
or so of a trace whose other rays missed or fell on an edge, is a point to every later step)."""

GRAZING = 85.0
"""Degrees between a ray and the normal of the face it hits beyond which the hit is trimmed off a cut end."""

EDGE_SCREEN = 4
"""Stride (rays) of the first look for occluding edges along the traces (`_on_occluding_edge`)."""

EDGE_SPACING = 0.4
"""Automatic `edge_px`: side rays land at least this many mesh spacings (mean edge length) across the trace,
and never nearer than EDGE_MIN_PX (measured: module docstring)."""

EDGE_MIN_PX = 2.0
EDGE_MAX_PX = 20.0

EDGE_PX_KEY = "edge_px"
"""`Trace3D.extra` key: {photo: the `edge_px` its pixels were extracted with, None for automatic}, kept
through merges, so that what a photo would show along a gap (engine.sight.Sight.shows) is judged as its
traces were extracted (`extracted_edge_px`)."""


@dataclass(frozen=True)
class Extraction:
    """3D traces made from a batch of 2D traces, with the ray counts behind them."""

    traces: list[Trace3D]
    n_rays: int
    n_missed: int
    n_split: int
    n_dropped: int  # slivers shorter than `min_run` rays cut off by a split, and pieces under MIN_VERTICES hits
    n_edge: int  # trace pixels on occluding edges, not placed on the mesh


def sample_polyline(polyline: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """Points along a polyline at most `spacing` apart (pixels), keeping every vertex."""
    return sample_polylines([polyline], spacing)[0]


def sample_polylines(polylines: Sequence[np.ndarray], spacing: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """`sample_polyline` of each polyline (at least one vertex each), stacked (M, 2), and how many points each
    has: one pass over all segments, as a photo's traces are hundreds of polylines of pixel-spaced vertices."""
    lines = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in polylines]
    sizes = np.array([len(p) for p in lines])
    if not len(lines) or not sizes.sum():
        return np.zeros((0, 2)), sizes
    stacked = np.vstack(lines)
    seg = np.diff(stacked, axis=0)
    last = np.cumsum(sizes) - 1  # the last vertex of each polyline: its "segment" to the next is none
    counts = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / spacing).astype(int), 1)
    counts = np.append(counts, 1)
    counts[last] = 1  # the step from one polyline to the next is no segment
    first = np.repeat(np.cumsum(counts) - counts, counts)  # index of each segment's first sample
    fractions = (np.arange(counts.sum()) - first) / np.repeat(counts, counts)
    seg = np.vstack([seg, np.zeros((1, 2))])
    points = np.repeat(stacked, counts, axis=0) + fractions[:, None] * np.repeat(seg, counts, axis=0)
    return points, np.add.reduceat(counts, np.cumsum(sizes) - sizes)


def check_in_image(trace: Trace2D, camera: Camera) -> None:
    """Raise if any vertex lies outside the photo (pixel centres run from 0 to size - 1)."""
    k = first_outside(trace.polyline, camera.width, camera.height)
    if k is not None:
        uv = trace.polyline
        raise InputError(None, f"trace {trace.id} on image {trace.image!r}: vertex {k} at "
                               f"({uv[k, 0]:.1f}, {uv[k, 1]:.1f}) is outside the "
                               f"{camera.width}×{camera.height} photo")


def extract_traces(traces: Sequence[Trace2D], cameras: dict[str, Camera], tracer: RayTracer, *,
                   spacing: float = 1.0, max_jump: float = 10.0, min_run: int = 25, edge_px: float | None = None,
                   progress: Progress | None = None) -> Extraction:
    """Ray-trace 2D traces onto the mesh.

    cameras : in the mesh's local frame (`Camera.shifted(origin)`).
    spacing : ray spacing along each 2D trace, pixels (≤ 1 gives one ray per trace pixel).
    max_jump : a step between neighbouring 3D vertices longer than `max_jump` pixel footprints is a depth
        discontinuity (occlusion edge); the trace is split there and both cut ends are censored.
    min_run : pieces of a split trace with fewer rays than this are dropped (module docstring); a 2D trace
        hit whole is kept however short, down to MIN_VERTICES hits.
    edge_px : pixels either side across the trace at which side rays look for an occluding edge; trace pixels
        on one are dropped (module docstring). None (automatic): EDGE_SPACING mesh spacings at each pixel's
        footprint, at least EDGE_MIN_PX and at most EDGE_MAX_PX. 0 keeps them all (one ray per pixel).
    Returns 3D traces with id 0 (the project assigns ids), one per unbroken run of ≥ MIN_VERTICES hits.
    """
    if not 0 < spacing <= 1.0:
        raise InputError(None, f"spacing must be in (0, 1] pixel, got {spacing}")
    if min_run < MIN_VERTICES:
        raise InputError(None, f"min_run must be at least {MIN_VERTICES} rays, got {min_run}")
    if edge_px is not None and not 0 <= edge_px <= EDGE_MAX_PX:
        raise InputError(None, f"edge_px must be in [0, {EDGE_MAX_PX:g}] pixels, got {edge_px}")
    by_image: dict[str, list[Trace2D]] = {}
    for trace in traces:
        if trace.image not in cameras:
            raise InputError(None, f"trace {trace.id}: image {trace.image!r} has no camera in the project")
        check_in_image(trace, cameras[trace.image])
        by_image.setdefault(trace.image, []).append(trace)
    # 10k faces give the mean within 0.2% in 3 ms; 100k took 34 ms of a 0.26 s photo at 3.2M faces
    mesh_spacing = mean_edge_length(tracer.vertices, tracer.faces, most=10_000) if edge_px is None else 0.0
    out: list[Trace3D] = []
    counts = np.zeros(5, dtype=int)  # rays, missed, split, dropped, on edges
    for done, (image, group) in enumerate(by_image.items()):
        report(progress, done / len(by_image), f"ray tracing {image}")
        made, *image_counts = _extract_image(group, cameras[image], tracer, spacing, max_jump, min_run, edge_px,
                                                 mesh_spacing)
        out += made
        counts += image_counts
    report(progress, 1.0, "ray tracing done")
    return Extraction(out, *map(int, counts))


def _extract_image(group: list[Trace2D], camera: Camera, tracer: RayTracer, spacing: float, max_jump: float,
                   min_run: int, edge_px: float | None,
                   mesh_spacing: float) -> tuple[list[Trace3D], int, int, int, int, int]:
    uv, lengths = sample_polylines([t.polyline for t in group], spacing)
    rays = camera.pixel_rays(uv)
    hits = tracer.intersect(camera.centre, rays)
    footprint = hits.t / camera.K[0, 0]  # metres per pixel along each ray
    edge = np.zeros(len(uv), dtype=bool) if edge_px == 0 else _on_occluding_edge(
        camera, tracer, uv, lengths, hits.t, max_jump * footprint, _side_offsets(footprint, edge_px, mesh_spacing))
    grazing = hits.cosine < np.cos(np.radians(GRAZING))  # misses: NaN, False
    made: list[Trace3D] = []
    n_split = n_dropped = 0
    starts = np.cumsum(lengths) - lengths
    missed = np.add.reduceat(~hits.hit, starts) > 0
    pieces = _pieces(hits.hit, edge, hits.points, footprint, max_jump, lengths)
    for trace, start, n, runs, miss in zip(group, starts, lengths, pieces, missed):
        sl = slice(start, start + n)
        if not (len(runs) == 1 and len(runs[0]) == n):
            runs = [_trimmed(run, n, grazing[sl]) for run in runs]
        if len(runs) > 1 or miss:  # cut by a miss or a jump: slivers go
            kept = [run for run in runs if len(run) >= min_run]
            n_split, n_dropped, runs = n_split + 1, n_dropped + len(runs) - len(kept), kept
        n_dropped += sum(len(run) < MIN_VERTICES for run in runs)
        for run in (run for run in runs if len(run) >= MIN_VERTICES):
            k = start + run
            made.append(Trace3D(0, hits.points[k], uv[k], hits.face[k], np.zeros(len(k)), (camera.name,),
                                parents=(trace.id,), term_start="C" if run[0] > 0 else "",
                                term_end="C" if run[-1] < n - 1 else "", extra={EDGE_PX_KEY: {camera.name: edge_px}},
                                kind=trace.kind))
    return made, len(uv), hits.n_missed, n_split, n_dropped, int(np.count_nonzero(edge & hits.hit))


def _side_offsets(footprint: np.ndarray, edge_px: float | None, mesh_spacing: float) -> np.ndarray:
    """Pixels across the trace (N,) at which each pixel's side rays look: `edge_px`, or if None EDGE_SPACING
    mesh spacings at the pixel's footprint (m per px; inf for a miss) within [EDGE_MIN_PX, EDGE_MAX_PX]."""
    if edge_px is not None:
        return np.full(len(footprint), float(edge_px))
    return np.clip(EDGE_SPACING * mesh_spacing / footprint, EDGE_MIN_PX, EDGE_MAX_PX)


def _on_occluding_edge(camera: Camera, tracer: RayTracer, uv: np.ndarray, lengths: np.ndarray, depth: np.ndarray,
                       limit: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """True where the pixel straddles an occluding edge: a ray `offset` (px) to either side across its trace
    meets the mesh more than `limit` (m) nearer or farther than the pixel's own ray, or misses it.

    Every EDGE_SCREEN-th pixel is looked at first, and every pixel within EDGE_SCREEN of one found on an
    edge. Measured against looking at every pixel, on the noisy synthetic outcrops: 0.5–1.5% of the edge
    pixels (5–15 per photo, on stretches shorter than the stride) are missed, none of them 3 cm off the
    truth, and the merge counts are unchanged; a paper-scale photo costs 0.33 s instead of 0.48 s."""
    screen = np.arange(0, len(uv), EDGE_SCREEN)
    found = np.zeros(len(uv), dtype=bool)
    found[screen] = _straddles(camera, tracer, uv[screen], offset[screen, None] * _across(uv, lengths, screen),
                               depth[screen], limit[screen])
    # "full" and centred by hand: "same" returns the kernel's length when the photo has fewer samples
    near = np.convolve(found, np.ones(2 * EDGE_SCREEN + 1))[EDGE_SCREEN:EDGE_SCREEN + len(found)]
    look = np.flatnonzero(near > 0)
    edge = np.zeros(len(uv), dtype=bool)
    edge[look] = _straddles(camera, tracer, uv[look], offset[look, None] * _across(uv, lengths, look), depth[look],
                            limit[look])
    return edge


def extracted_edge_px(traces: Iterable[Trace3D]) -> dict[str, float | None]:
    """The `edge_px` each photo's traces were extracted with (`EDGE_PX_KEY`): where they differ (extracted
    at different times), the value most of them carry. Photos of no recorded trace are left out (automatic)."""
    votes: dict[str, Counter] = {}
    for t in traces:
        for image, px in t.extra.get(EDGE_PX_KEY, {}).items():
            votes.setdefault(image, Counter())[px] += 1
    return {image: count.most_common(1)[0][0] for image, count in votes.items()}


def on_occluding_edge(camera: Camera, tracer: RayTracer, uv: np.ndarray, across: np.ndarray, *,
                      mesh_spacing: float, max_jump: float = 10.0, edge_px: float | None = None) -> np.ndarray:
    """Which pixels uv (N, 2) of a line running across unit image normals `across` (N, 2) straddle an occluding
    edge, as `extract_traces` with these parameters judges a trace's pixels (every pixel looked at): the
    test for anything that asks whether a trace drawn there would reach the mesh (engine.sight)."""
    depth = tracer.intersect(camera.centre, camera.pixel_rays(uv)).t
    footprint = depth / camera.K[0, 0]
    offset = _side_offsets(footprint, edge_px, mesh_spacing)
    return _straddles(camera, tracer, uv, offset[:, None] * across, depth, max_jump * footprint)


def _straddles(camera: Camera, tracer: RayTracer, uv: np.ndarray, across: np.ndarray, depth: np.ndarray,
               limit: np.ndarray) -> np.ndarray:
    """The test of `_on_occluding_edge` on pixels uv (N, 2), `across` (N, 2) being the side offset."""
    edge = np.zeros(len(uv), dtype=bool)
    for side in (across, -across):
        t = tracer.intersect(camera.centre, camera.pixel_rays(uv + side)).t
        with np.errstate(invalid="ignore"):  # misses: inf - inf
            edge |= ~(np.abs(t - depth) <= limit)  # a side ray or the pixel's own ray missing counts
    return edge


def _across(uv: np.ndarray, lengths: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Unit image normals (len(at), 2) at samples `at` of the polylines stacked in `uv`, from central
    differences within each polyline (one-sided at its ends; zero for a single point)."""
    ends = np.cumsum(lengths)
    first = np.repeat(ends - lengths, lengths)[at]
    last = np.repeat(ends - 1, lengths)[at]
    tangent = uv[np.minimum(at + 1, last)] - uv[np.maximum(at - 1, first)]
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return np.column_stack([-tangent[:, 1], tangent[:, 0]])


def _trimmed(run: np.ndarray, n: int, grazing: np.ndarray) -> np.ndarray:
    """A piece (ray indices) of a trace of n rays without the grazing hits at its cut ends (not at the trace's
    own ends)."""
    lo, hi = 0, len(run)
    if run[0] > 0:
        while lo < hi and grazing[run[lo]]:
            lo += 1
    if run[-1] < n - 1:
        while hi > lo and grazing[run[hi - 1]]:
            hi -= 1
    return run[lo:hi]


def _pieces(hit: np.ndarray, edge: np.ndarray, points: np.ndarray, footprint: np.ndarray, max_jump: float,
            lengths: np.ndarray) -> list[list[np.ndarray]]:
    """For each of the traces stacked in the arrays (`lengths` rays each), the ray indices (from its first
    ray) of its pieces of ≥ 2 vertices: the hits off occluding edges, split at misses and at depth jumps. A
    stretch of edge rays is stepped over where the hits either side of it lie within `max_jump` footprints
    per ray skipped (a trace wrapping round the corner of a ledge)."""
    starts = np.cumsum(lengths) - lengths
    owner = np.repeat(np.arange(len(lengths)), lengths)
    pieces: list[list[np.ndarray]] = [[] for _ in range(len(lengths))]
    keep = np.flatnonzero(hit & ~edge)
    if len(keep) < 2:
        return pieces
    step = np.linalg.norm(np.diff(points[keep], axis=0), axis=1)
    limit = max_jump * np.fmin(footprint[keep[:-1]], footprint[keep[1:]]) * np.diff(keep)
    misses = np.concatenate([[0], np.cumsum(~hit)])
    joined = ((step <= limit) & (misses[keep[1:]] == misses[keep[:-1] + 1])  # no miss between them
              & (owner[keep[1:]] == owner[keep[:-1]]))
    for run in np.split(keep, np.flatnonzero(~joined) + 1):
        if len(run) >= 2:
            pieces[owner[run[0]]].append(run - starts[owner[run[0]]])
    return pieces
