"""2D connectivity: which traces of one photo touch, as connected components of the rasterised trace map.

Each trace is drawn as an 8-connected digital line and the map is labelled with 8-connectivity (OpenCV's
two-pass algorithm), so two traces that cross or touch, even only diagonally, share a label.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from engine.errors import InputError
from engine.traces import Trace2D


def trace_map(traces: Sequence[Trace2D], shape: tuple[int, int]) -> np.ndarray:
    """Binary (H, W) map of the traces: pixels whose centres the rasterised polylines pass through."""
    canvas = np.zeros(shape, np.uint8)
    lines = [np.rint(t.polyline).astype(np.int32).reshape(-1, 1, 2) for t in traces if len(t.polyline)]
    cv2.polylines(canvas, lines, False, 1, thickness=1, lineType=cv2.LINE_8)
    return canvas.astype(bool)


def label_components(traces: Sequence[Trace2D], shape: tuple[int, int]) -> tuple[list[Trace2D], np.ndarray]:
    """Label the connected components of the photo's trace map (8-connected, two-pass).

    Returns copies of the traces with `component` set (labels 0 … n − 1), and the label image (H, W) int32
    with −1 off the traces. All traces must be on one photo.
    """
    if len({t.image for t in traces}) > 1:
        raise InputError(None, "label_components: the traces lie on more than one photo; label each photo alone")
    binary = trace_map(traces, shape).astype(np.uint8)
    _, labels = cv2.connectedComponents(binary, connectivity=8, ltype=cv2.CV_32S)
    labels -= 1
    out = []
    for t in traces:
        u, v = np.clip(np.rint(t.polyline[0]).astype(int), 0, [shape[1] - 1, shape[0] - 1])
        out.append(replace(t, component=int(labels[v, u])))
    return out, labels
