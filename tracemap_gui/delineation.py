"""The GUI's side of `engine.delineate`: auto-trace runs, guided curves and 2D components, ready to draw.

The only module of the GUI that calls the delineation engine. Photos arrive here as the photo view holds
them (8-bit grey, BGR or BGRA, as OpenCV reads them) and are handed to the engine as grey or RGB.
Everything returned is drawable: stage images become display pyramids on the worker thread.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from engine.cameras import Camera
from engine.delineate import (DelineationParams, autotrace, carried_traces, darkness, kinds_traced_elsewhere,
                              label_components, least_cost_curve, spline_curve, supported_traces, trace_cost)
from engine.delineate.segments import simplify_polyline
from engine.errors import Progress, TracemapError, report
from engine.raytrace import RayTracer
from engine.traces import Trace2D
from tracemap_gui.photo_view import Pyramid

STAGES = ("denoised", "phase congruency", "line filter", "edges", "segments", "silhouette")  # the last when it ran
GUIDE_MARGIN = 32.0  # px: least_cost_curve searches the clicks' bounding box widened by this (or more)
GUIDE_SNAP = 3.0  # px: a click moves to the cheapest pixel this near
GUIDE_LINE_WIDTH = 7  # px: `darkness` compares a pixel with a square this wide around it
SPLINE_SIGMA = 1.0  # px: how far a click may be off the fracture, for the smoothing spline


@dataclass(frozen=True, eq=False)
class Stage:
    """One intermediate as drawn: a display image (pyramid) or polylines, in photo pixels."""

    image: Pyramid | None = None
    polylines: tuple[np.ndarray, ...] = ()


@dataclass(frozen=True, eq=False)
class AutotraceRun:
    """What one run made on photo `image`, over the region whose top-left pixel is `origin` (x, y)."""

    image: str
    origin: tuple[int, int]
    stages: dict[str, Stage]
    proposals: list[Trace2D]  # photo pixel coordinates, source "auto", 2D component of the run
    note: str = ""  # why the run went without the mesh, if it was asked for and could not be had
    supported: int = 0  # proposals kept on the support of the other photos' traces, or carried from them


def engine_pixels(pixels: np.ndarray) -> np.ndarray:
    """8-bit grey or RGB, as the engine takes photos."""
    if pixels.ndim == 2:
        return pixels
    return cv2.cvtColor(pixels, cv2.COLOR_BGRA2RGB if pixels.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def run_autotrace(image: str, pixels: np.ndarray, params: DelineationParams, origin: tuple[int, int] = (0, 0),
                  silhouette_of: Callable[..., np.ndarray] | None = None,
                  support_of: Callable[..., list[np.ndarray]] | None = None,
                  kinds_of: Callable[..., list[Trace2D]] | None = None, *, progress: Progress) -> AutotraceRun:
    """Auto-trace `pixels` (the photo, or the region of it at `origin`) and prepare every stage for display.

    silhouette_of : gives the mesh's silhouette in the whole photo (`MeshTracer.silhouette`), if known.
    support_of : gives, of the segments the run turned down, its traces (photo pixels) and its skeleton, the
        segments the other photos support and their traces carried into the region (`support_in_photo`),
        if the mesh is known.
    kinds_of : gives the proposals (photo pixels) the kinds the other photos' traces of them have
        (`kinds_in_photo`), if the mesh is known.
    """
    silhouette, notes = None, []
    if silhouette_of is not None:
        h, w = pixels.shape[:2]
        try:
            whole = silhouette_of(progress=lambda f, m: progress(0.1 * f, m))
            silhouette = whole[origin[1]:origin[1] + h, origin[0]:origin[0] + w]
        except TracemapError as exc:  # an unreadable mesh: the photo can still be traced
            notes.append(f"without the mesh's silhouette: {exc}")
    result = autotrace(engine_pixels(pixels), params=params, image_name=image, silhouette=silhouette,
                       progress=lambda f, m: progress(0.1 + 0.7 * f, m))
    shift = np.asarray(origin, np.float64)
    traces, supported = result.traces, []
    if support_of is not None:
        try:
            supported = support_of([c + shift for c in result.segments.rejected],
                                   [t.polyline + shift for t in traces], (result.skeleton, origin),
                                   progress=lambda f, m: progress(0.8 + 0.1 * f, m))
        except TracemapError as exc:
            notes.append(f"without support from the other photos: {exc}")
    if supported:  # the run's 2D components, with the supported segments among its traces
        added = [Trace2D(0, image, line - shift, "auto") for line in supported]
        traces = label_components([*traces, *added], pixels.shape[:2])[0]
    proposals = [replace(t, polyline=t.polyline + shift) for t in traces]
    if kinds_of is not None and proposals:
        try:
            proposals = kinds_of(proposals, progress=lambda f, m: progress(0.85 + 0.05 * f, m))
        except TracemapError as exc:
            notes.append(f"without the kinds the other photos give: {exc}")
    progress(0.9, "preparing the previews")
    stages = {
        "denoised": Stage(image=Pyramid(result.denoised)),
        "phase congruency": Stage(image=Pyramid(colour_map(result.phase.edge))),
        **({} if result.lines is None else {"line filter": Stage(image=Pyramid(colour_map(result.lines.strength)))}),
        "edges": Stage(image=Pyramid(mask_image(result.skeleton))),
        "segments": Stage(polylines=tuple(p + shift for p in result.segments.polylines)),
        **({} if result.silhouette is None else {"silhouette": Stage(image=Pyramid(mask_image(result.silhouette)))}),
    }
    return AutotraceRun(image, origin, stages, proposals, "; ".join(notes), len(supported))


def kinds_in_photo(image: str, traces: list[Trace2D], cameras: dict[str, Camera], params: DelineationParams,
                   tracer_of: Callable[..., RayTracer], proposals: list[Trace2D], *,
                   progress: Progress) -> list[Trace2D]:
    """The proposals of photo `image`, each of the kind the other photos' `traces` of it have
    (`engine.delineate.kinds_traced_elsewhere`: bedding traced in one photo is proposed as bedding here)."""
    tracer = tracer_of(progress=lambda f, m: progress(0.5 * f, m))
    progress(0.5, "kinds from the other photos")
    return kinds_traced_elsewhere(proposals, image, traces, cameras, tracer, tolerance=params.support_tolerance,
                                  share=params.support_share)


def support_in_photo(image: str, kept: dict[str, list[np.ndarray]], cameras: dict[str, Camera],
                     params: DelineationParams, tracer_of: Callable[..., RayTracer], rejected: list[np.ndarray],
                     own: list[np.ndarray], skeleton: tuple[np.ndarray, tuple[int, int]], *,
                     progress: Progress) -> list[np.ndarray]:
    """The segments of photo `image` it turned down (`rejected`) that the other photos' traces support, and
    with `params.carry` the other photos' traces it sees where its skeleton lies along them, within the
    region traced (photo pixels; `engine.delineate.supported_traces` and `carried_traces`). kept : the
    traces of every photo that stay, by name (for `image` its manual ones); own : the run's traces;
    skeleton : the run's skeleton and the region's top-left pixel. tracer_of : gives the mesh's ray tracer
    (`MeshTracer.tracer`), in the cameras' frame."""
    tracer = tracer_of(progress=lambda f, m: progress(0.5 * f, m))
    progress(0.5, "support from the other photos")
    traces = {**kept, image: [*kept.get(image, []), *own]}
    supported = supported_traces({image: rejected}, traces, cameras, tracer, min_length=params.support_min_length,
                                 tolerance=params.support_tolerance, share=params.support_share,
                                 simplify=params.simplify)[image]
    if not params.carry:
        return supported
    progress(0.75, "traces carried from the other photos")
    region, (x, y) = skeleton
    camera = cameras[image]
    whole = np.zeros((camera.height, camera.width), bool)
    whole[y:y + region.shape[0], x:x + region.shape[1]] = region
    traces[image] = [*traces[image], *supported]
    carried = carried_traces(traces, cameras, tracer, {image: whole}, tolerance=params.support_tolerance,
                             share=params.support_share, evidence=params.carry_evidence,
                             min_length=params.carry_min_length, simplify=0.0)[image]
    inside = [piece for line in carried for piece in _within(line, (x, y), region.shape, params.carry_min_length)]
    return supported + [simplify_polyline(piece, params.simplify) for piece in inside]


def _within(line: np.ndarray, origin: tuple[int, int], shape: tuple[int, ...], min_length: float) -> list[np.ndarray]:
    """The pieces of a polyline sampled every pixel inside the region at `origin` of `shape`, at least
    `min_length` samples long (a run traces only its region)."""
    x, y = origin
    inside = (line[:, 0] >= x - 0.5) & (line[:, 0] < x + shape[1] - 0.5) & \
        (line[:, 1] >= y - 0.5) & (line[:, 1] < y + shape[0] - 0.5)
    index = np.flatnonzero(inside)
    runs = np.split(index, np.flatnonzero(np.diff(index) > 1) + 1)
    return [line[run] for run in runs if len(run) >= max(min_length, 2)]


def colour_map(values: np.ndarray) -> np.ndarray:
    """A [0, 1] map in the inferno colour map (BGR), full scale at the map's maximum."""
    top = float(np.nanmax(values)) or 1.0
    scaled = np.clip(np.nan_to_num(values / top) * 255, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)


def mask_image(mask: np.ndarray) -> np.ndarray:
    """A mask as opaque red (BGRA) on transparent, to lay over the photo."""
    out = np.zeros((*mask.shape, 4), np.uint8)
    out[mask] = (40, 40, 255, 255)
    return out


def guided_curve(pixels: np.ndarray, a: np.ndarray, b: np.ndarray, *, progress: Progress | None = None) -> np.ndarray:
    """The darkest path from near a to near b (the engine's least-cost curve), (N, 2) photo pixels.

    The cost is worked out only on the window the engine's search can reach. Clicks 2000 px apart on a
    24 MP photo take a few hundred ms, so the guided-curve tool calls this on a worker (`progress` may
    cancel it between the stages).
    """
    report(progress, 0.0, "weighing the pixels")
    reach = max(GUIDE_MARGIN, 0.5 * float(np.hypot(*(b - a)))) + GUIDE_SNAP + GUIDE_LINE_WIDTH
    h, w = pixels.shape[:2]
    x0, y0 = max(int(math.floor(min(a[0], b[0]) - reach)), 0), max(int(math.floor(min(a[1], b[1]) - reach)), 0)
    x1, y1 = min(int(math.ceil(max(a[0], b[0]) + reach)), w - 1), min(int(math.ceil(max(a[1], b[1]) + reach)), h - 1)
    window = engine_pixels(pixels[y0:y1 + 1, x0:x1 + 1])
    cost = trace_cost(darkness(window, line_width=GUIDE_LINE_WIDTH))
    report(progress, 0.5, "following the fracture")
    offset = np.array([x0, y0], np.float64)
    return least_cost_curve(cost, np.array([a, b]) - offset, snap_radius=GUIDE_SNAP, margin=GUIDE_MARGIN) + offset


def spline(clicks: np.ndarray) -> np.ndarray:
    """The engine's smoothing spline through clicked points, a vertex every pixel."""
    return spline_curve(clicks, sigma=SPLINE_SIGMA, spacing=1.0)


def components(traces: Sequence[Trace2D], size: tuple[int, int], *, progress: Progress) -> dict[int, int]:
    """The 2D connected component of each trace of one photo of `size` (width, height), by trace id."""
    if not traces:
        return {}
    labelled, _ = label_components(traces, (size[1], size[0]))
    return {t.id: t.component for t in labelled}
