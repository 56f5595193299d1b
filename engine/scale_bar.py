"""A scale bar and a north arrow for figures of an outcrop (`tracemap render --scale-bar`, the 3D viewer).

They stand in the scene, not on the screen: a view of an outcrop is a perspective, so a length drawn on the
screen holds at one depth only, and the bar stands at the outcrop's foot, where a geologist would lay a
tape. The bar runs along the outcrop (the main axis of its footprint on the horizontal plane), in front of
the rock on the side the photos were taken from and of the point it is seen from, at the level of the
rock's lowest point; its length is the
longest 1, 2 or 5 × 10ⁿ m within a fifth of the outcrop's length. The arrow stands right of the bar and
points north on the horizontal plane. North, up and metres are the registered frame's when the
project is registered (passed in the mesh's frame), else the mesh's +y, +z and unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine.errors import InputError
from engine.mesh import Mesh
from engine.register import Similarity, length_scale, model_directions


@dataclass(frozen=True)
class ScaleBar:
    """Where the bar and the arrow go (mesh frame) and what the bar says.

    start, end : the bar's ends; length_m : its length in metres (`label`). along, out, up : unit vectors
    along the bar, out of the rock toward the photos, and up. arrow : (base, tip) of the north arrow.
    """

    start: np.ndarray
    end: np.ndarray
    length_m: float
    label: str
    along: np.ndarray
    out: np.ndarray
    up: np.ndarray
    arrow: tuple[np.ndarray, np.ndarray]


def round_length(target: float) -> float:
    """The largest 1, 2 or 5 × 10ⁿ not above `target` (> 0)."""
    exponent = math.floor(math.log10(target))
    return max(m * 10.0**exponent for m in (1, 2, 5) if m * 10.0**exponent <= target * (1 + 1e-12))


def scale_bar(mesh: Mesh, *, toward: np.ndarray, north: np.ndarray = np.array([0.0, 1.0, 0.0]),
              up: np.ndarray = np.array([0.0, 0.0, 1.0]), metres_per_unit: float = 1.0) -> ScaleBar:
    """The scale bar and north arrow of `mesh` (module docstring), in front of it as seen from `toward`
    (a point: the photos' mean centre, or the photo a view is from). north, up : directions in the mesh frame; metres_per_unit : how many
    metres one mesh unit is (a registration's scale)."""
    up = _unit(up, "up")
    north = _unit(north - (north @ up) * up, "north on the horizontal plane")
    points = mesh.vertices
    flat = points - np.outer(points @ up, up)
    centred = flat - flat.mean(axis=0)
    along = np.linalg.svd(centred, full_matrices=False)[2][0]  # the footprint's main axis
    out = np.cross(along, up)  # so that, seen from outside (looking along -out), `along` runs left to right
    if (np.asarray(toward, float) - points.mean(axis=0)) @ out < 0:
        out, along = -out, -along
    extent = float(np.ptp(points @ along))
    length_m = round_length(extent * metres_per_unit / 5)
    length = length_m / metres_per_unit
    depth = float(np.ptp(points @ out))
    # centred in front of `toward` (within the outcrop's length), at the foot, just clear of the rock
    lo, hi = (points @ along).min(), (points @ along).max()
    middle = float(np.clip(np.asarray(toward, float) @ along, lo + 0.5 * length, hi - 0.5 * length))
    start = (middle - 0.5 * length) * along \
        + ((points @ out).max() + 0.05 * max(depth, 0.1 * extent)) * out + (points @ up).min() * up
    arrow = 0.6 * length * north
    # an arrow pointing into the rock stands out far enough for its tip and the "N" beyond it to stay in front
    arrow_base = start + (length + 0.05 * extent) * along + max(0.0, -1.4 * float(arrow @ out)) * out
    return ScaleBar(start, start + length * along, length_m, _label(length_m), along, out, up,
                    (arrow_base, arrow_base + arrow))


def registered_scale_bar(mesh: Mesh, toward: np.ndarray, similarity: Similarity | None) -> ScaleBar:
    """`scale_bar` in the frame a project reports in: the registration's north, up and metres, if any."""
    north, up = model_directions(np.eye(3)[1:], similarity)
    return scale_bar(mesh, toward=toward, north=north, up=up, metres_per_unit=length_scale(similarity))


def _label(length_m: float) -> str:
    if length_m >= 1000:
        return f"{length_m / 1000:g} km"
    return f"{length_m:g} m" if length_m >= 1 else f"{length_m * 100:g} cm"


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    norm = float(np.linalg.norm(v))
    if not norm > 1e-9:
        raise InputError(None, f"scale bar: {what} has no direction (expected a non-zero 3D vector)")
    return v / norm
