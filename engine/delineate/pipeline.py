"""The auto-trace pipeline: denoise → phase congruency → edges (+ line filter) → segments → growing → components.

Phase congruency is taken of log brightness (by default). Brightness is albedo × shading × (1 − trace darkening),
so in log units a trace darkens shaded rock as much as sunlit rock. Phase congruency is contrast invariant only
above its noise threshold, a fixed energy for the whole photo. On linear brightness, faint traces in shadowed
strips fall below it. Segments are judged on the same log brightness (`line_profile`).
The oriented line filter (`line_filter`) adds the faint traces phase congruency breaks up: its lines and the
edge skeleton are thinned together, so where both see a trace one chain follows it. It runs on the photo
before denoising, which smooths faint traces with the texture; the filter itself averages along the line.
Given the mesh's silhouette in the photo (`silhouette`), traces that run along it are dropped.
Every intermediate is returned, so an editor can preview each stage with the parameters of the run.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from skimage.morphology import skeletonize

from engine.cameras import Camera
from engine.delineate.components import label_components
from engine.delineate.denoise import denoise
from engine.delineate.edges import EdgeMap, detect_edges
from engine.delineate.grow import grow_traces
from engine.delineate.line_filter import LineMap, line_filter
from engine.delineate.line_profile import LOG_255, log_brightness
from engine.delineate.params import DelineationParams
from engine.delineate.phase import PhaseCongruency, phase_congruency, phase_congruency_mono
from engine.delineate.segments import Segments, find_segments
from engine.errors import InputError, Progress, report
from engine.traces import Trace2D, resample_polyline


@dataclass(frozen=True, eq=False)
class AutoTrace:
    """Everything `autotrace` made: each stage's output, and the traces (source "auto", component set)."""

    params: DelineationParams
    grey: np.ndarray
    denoised: np.ndarray
    phase: PhaseCongruency
    edges: EdgeMap
    lines: LineMap | None  # None when the line filter is off
    skeleton: np.ndarray  # the edge skeleton with the filter's lines: what segments were found in
    segments: Segments
    silhouette: np.ndarray | None  # the band along the mesh's silhouette that traces were dropped in, if given
    traces: list[Trace2D]
    components: np.ndarray


def autotrace(image: np.ndarray, *, params: DelineationParams | None = None, image_name: str = "",
              silhouette: np.ndarray | None = None, progress: Progress | None = None) -> AutoTrace:
    """Propose fracture traces on a photo (8-bit grey or RGB); an empty list is a valid result.

    image_name : the `image` of the returned traces. Parameters, their units and ranges: DelineationParams.
    silhouette : pixels (H, W) on the mesh's silhouette in this photo (`engine.delineate.silhouette`); traces
        with more than `silhouette_share` of their length within `silhouette_band` px of it are dropped.
    """
    p = params or DelineationParams()
    grey = _grey(image)
    if silhouette is not None and np.shape(silhouette) != grey.shape:
        raise InputError(None, f"the silhouette is {np.shape(silhouette)} px but the photo {grey.shape}")
    report(progress, 0.0, "denoising")
    denoised = denoise(grey, h=p.nlm_h, template_window=p.nlm_template, search_window=p.nlm_search) \
        if p.denoise else grey
    report(progress, 0.3, "phase congruency")
    pc = _phase(log_brightness(denoised) / LOG_255 if p.log_brightness else denoised, p, progress)
    report(progress, 0.8, "edges")
    edges = detect_edges(pc, low=p.low, high=p.high, nms_radius=p.nms_radius)
    lines, skeleton, feature_type = None, edges.skeleton, pc.feature_type
    if p.line_filter and p.feature != "any":
        report(progress, 0.82, "line filter")
        lines, skeleton, feature_type = _with_lines(grey, edges, pc.feature_type, p)
    report(progress, 0.85, "segments")
    segments = find_segments(skeleton, feature_type, image=denoised, feature=p.feature,
                             line_phase=p.line_phase, line_contrast=p.line_contrast,
                             line_asymmetry=p.line_asymmetry, faint_asymmetry=p.faint_asymmetry,
                             faint_contrast=p.faint_contrast, photo=grey if p.denoise else None,
                             raw_contrast=p.raw_contrast, trace_width=p.trace_width,
                             spur_length=p.spur_length, junction_angle=p.junction_angle,
                             direction_length=p.direction_length, simplify=p.simplify)
    report(progress, 0.95, "line growing")
    grown = grow_traces(segments, link_distance=p.link_distance, link_angle=p.link_angle,
                        link_buffer=p.link_buffer, link_weight=p.link_weight,
                        direction_length=p.direction_length, min_length=p.min_length)
    band = None
    if silhouette is not None and p.silhouette:
        band = _dilate(np.asarray(silhouette, bool), p.silhouette_band)
        grown = [line for line in grown if _share_in(line, band) <= p.silhouette_share]
    traces, components = label_components([Trace2D(0, image_name, line, "auto") for line in grown], grey.shape)
    report(progress, 1.0, f"done: {len(traces)} traces")
    return AutoTrace(p, grey, denoised, pc, edges, lines, skeleton, segments, band, traces, components)


def _with_lines(grey: np.ndarray, edges: EdgeMap, feature_type: np.ndarray,
                p: DelineationParams) -> tuple[LineMap, np.ndarray, np.ndarray]:
    """The line filter's lines (of the wanted polarity), the skeleton of them and the edges together, and the
    feature type with the pixels only the filter found marked as lines of that polarity: the filter finds
    nothing else, and phase congruency's type is unsteady where it saw no edge."""
    sign = 1.0 if p.feature == "dark" else -1.0
    lines = line_filter(sign * log_brightness(grey), sigma=p.line_sigma, length=p.line_length,
                        norient=p.line_norient, wide=p.line_wide, ratio=p.line_ratio, low=p.line_low,
                        high=p.line_high)
    skeleton = skeletonize(lines.mask | edges.skeleton)
    near_edges = cv2.dilate(edges.skeleton.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    feature_type = np.where(skeleton & ~near_edges, np.float32(-sign * np.pi / 2), feature_type)
    return lines, skeleton, feature_type


def _dilate(mask: np.ndarray, radius: float) -> np.ndarray:
    """`mask` widened by `radius` px (to the nearest pixel) each way, by an elliptical element."""
    r = int(radius + 0.5)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(mask.astype(np.uint8), disk).astype(bool)


def _share_in(line: np.ndarray, mask: np.ndarray) -> float:
    """Share of a polyline's length (sampled every pixel) in `mask`."""
    uv = np.rint(resample_polyline(line, 1.0)[0]).astype(np.int64)
    u = uv[:, 0].clip(0, mask.shape[1] - 1)
    v = uv[:, 1].clip(0, mask.shape[0] - 1)
    return float(mask[v, u].mean())


def read_photo(path: str | Path, camera: Camera | None = None) -> np.ndarray:
    """An 8-bit RGB photo (H, W, 3) as stored, checked to be the size of its camera if one is given.

    An EXIF Orientation tag is ignored: photogrammetry tools calibrate the stored pixel grid, and the size
    check of the photos (`engine.cameras.check_images`) and the editor read that grid too.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "photo not found")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise InputError(path, "OpenCV cannot read this file as an image")
    if camera is not None and (image.shape[1], image.shape[0]) != (camera.width, camera.height):
        raise InputError(path, f"the photo is {image.shape[1]}×{image.shape[0]} px but camera "
                               f"{camera.name!r} is {camera.width}×{camera.height}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _grey(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(None, f"autotrace needs an 8-bit grey (H, W) or RGB (H, W, 3) photo; got "
                               f"{image.dtype} {image.shape}")
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def _phase(grey: np.ndarray, p: DelineationParams, progress: Progress | None) -> PhaseCongruency:
    """Phase congruency of `grey` (8-bit, or float in [0, 1]) with the parameters' method and filters."""
    common = {k: v for k, v in asdict(p).items() if k in ("nscale", "min_wavelength", "mult", "sigma_onf", "k",
                                                          "cutoff", "g", "tile", "overlap", "border")}
    sub = None if progress is None else (lambda f, m: report(progress, 0.3 + 0.5 * f, m))
    if p.pc_method == "monogenic":
        return phase_congruency_mono(grey, deviation_gain=p.deviation_gain, progress=sub, **common)
    return phase_congruency(grey, norient=p.norient, progress=sub, **common)
