"""The seam between the GUI and `engine.delineate` (auto-trace and guided curves): the only module that calls it.

The engine's delineation package is being written stage by stage. The GUI needs three things from it:
  * the parameters: `engine.delineate.params.DelineationParams` (every field, its range, unit and meaning);
  * `autotrace(image, params, progress=...)` returning the intermediates named in `RESULT_FIELDS` and the
    traces (a list of (N, 2) pixel polylines);
  * `guided_curve(image, a, b)`: the least-cost path between two pixels along a fracture, (N, 2).
Until `autotrace` exists, the stages the engine already offers run here one by one (today phase congruency)
and the others are reported as missing, so the panel previews what there is and says what is not there yet.
Everything returned is ready to draw: images become display pyramids on the worker thread.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from engine.delineate.params import DelineationParams
from engine.errors import Progress, TracemapError
from tracemap_gui.photo_view import Pyramid

STAGES = ("denoised", "phase congruency", "edges", "segments")
RESULT_FIELDS = {"denoised": "denoised", "phase congruency": "phase", "edges": "edges", "segments": "segments"}
"""Preview stage → attribute of the engine's autotrace result."""
PHASE_FIELDS = ("nscale", "norient", "min_wavelength", "mult", "sigma_onf", "k", "cutoff", "g", "tile", "overlap")
MONO_FIELDS = ("nscale", "min_wavelength", "mult", "sigma_onf", "k", "cutoff", "g", "deviation_gain", "tile",
               "overlap")


@dataclass(frozen=True, eq=False)
class Stage:
    """One intermediate as drawn: a display image (pyramid) or polylines, in photo pixels from `origin`."""

    name: str
    image: Pyramid | None = None
    polylines: tuple[np.ndarray, ...] = ()


@dataclass(frozen=True, eq=False)
class AutotraceRun:
    """What one run made on photo `image`, over the region whose top-left pixel is `origin` (x, y)."""

    image: str
    origin: tuple[int, int]
    stages: dict[str, Stage]
    proposals: list[np.ndarray]  # photo pixel coordinates
    missing: tuple[str, ...]  # stages (or "traces") the engine cannot compute yet


def _engine(name: str) -> Callable | None:
    """`engine.delineate.<name>` if the engine has it yet."""
    return getattr(importlib.import_module("engine.delineate"), name, None)


def can_autotrace() -> bool:
    return _engine("autotrace") is not None


def can_guide() -> bool:
    return _engine("guided_curve") is not None


def guided_curve(pixels: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The engine's path along the fracture from pixel a to pixel b (both included)."""
    function = _engine("guided_curve")
    if function is None:
        raise TracemapError("guided curves need engine.delineate.guided_curve, which this version lacks")
    return np.asarray(function(pixels, a, b), dtype=np.float64).reshape(-1, 2)


def run_autotrace(image: str, pixels: np.ndarray, params: DelineationParams, origin: tuple[int, int] = (0, 0),
                  *, progress: Progress) -> AutotraceRun:
    """Auto-trace `pixels` (the photo, or the region of it at `origin`) and prepare every stage for display."""
    autotrace = _engine("autotrace")
    if autotrace is None:
        return _run_available_stages(image, pixels, params, origin, progress)
    result = autotrace(pixels, params, progress=lambda f, m: progress(0.95 * f, m))
    progress(0.95, "preparing the previews")
    stages = {name: _stage(name, getattr(result, field), origin)
              for name, field in RESULT_FIELDS.items() if getattr(result, field, None) is not None}
    proposals = [np.asarray(p, np.float64) + origin for p in result.traces]
    missing = tuple(name for name in STAGES if name not in stages)
    return AutotraceRun(image, origin, stages, proposals, missing)


def _run_available_stages(image: str, pixels: np.ndarray, params: DelineationParams, origin: tuple[int, int],
                          progress: Progress) -> AutotraceRun:
    from engine.delineate.phase import phase_congruency, phase_congruency_mono

    values = dataclasses.asdict(params)
    if params.pc_method == "oriented":
        phase = phase_congruency(pixels, progress=progress, **{f: values[f] for f in PHASE_FIELDS})
    else:
        phase = phase_congruency_mono(pixels, progress=progress, **{f: values[f] for f in MONO_FIELDS})
    stages = {"phase congruency": _stage("phase congruency", phase, origin)}
    missing = tuple(name for name in STAGES if name not in stages) + ("traces",)
    return AutotraceRun(image, origin, stages, [], missing)


def _stage(name: str, value: object, origin: tuple[int, int]) -> Stage:
    """Turn an engine intermediate into something drawable: maps into colour images, lines into polylines."""
    if hasattr(value, "edge"):  # a PhaseCongruency result: show the edge strength
        value = value.edge
    if isinstance(value, np.ndarray):
        return Stage(name, image=Pyramid(display_image(value)))
    return Stage(name, polylines=tuple(np.asarray(p, np.float64) + origin for p in value))


def display_image(value: np.ndarray) -> np.ndarray:
    """8-bit image for a stage: a mask as opaque red on transparent, a float map in the inferno colour map."""
    if value.dtype == bool:
        out = np.zeros((*value.shape, 4), np.uint8)
        out[value] = (40, 40, 255, 255)  # BGRA
        return out
    if value.dtype == np.uint8:
        return value
    finite = np.nan_to_num(value.astype(np.float32), nan=0.0)
    hi = float(finite.max()) or 1.0
    scaled = np.clip(finite / hi * 255, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO) if value.ndim == 2 else scaled
