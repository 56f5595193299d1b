"""Mauldon's circular scan windows: trace intensity, density and mean length from two counts.

Mauldon, Dunne & Rohrbaugh (2001, J. Struct. Geol. 23, 247–258) and Rohrbaugh, Dunne & Mauldon (2002, AAPG
Bull. 86, 2089–2104): in a circle of radius r on a trace map, the n trace ends inside it and the m points
where traces cross its edge estimate

    P21 = m / (4r),   P20 = n / (2πr²),   mean trace length μ = (πr / 2) · m / n,

whatever the traces' lengths and however many run beyond the circle: no trace need be measured, so the
estimates carry neither the censoring nor the length bias of a window's measured lengths (the bias
Kaplan–Meier corrects in `engine.lengths`). fractopo gives the same three for a circular target area, with
n = I + Y nodes and m = E nodes (`fractopo.analysis.parameters`); `tracemap analyse-map` does both: its
sampling area when that is a circle, and any scan circles the user places inside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.errors import InputError

SIDES = 720
"""Sides of the polygon a scan circle is clipped with: its edge lies within r(1 − cos(π/720)) ≈ 1e-5 r of the
circle."""
ROUND = 0.01
"""An area polygon whose vertices all lie within this fraction of their mean distance from its centroid, that
distance within it of the radius of a circle of the polygon's area, is taken for a circle (fractopo's
`circular_target_area`); its radius is then that of the circle of its area, as fractopo's."""
MIN_SIDES = 16


@dataclass(frozen=True)
class Mauldon:
    """The counts of a scan circle of `radius` at `centre` (map units): `ends` inside, `cuts` of its edge."""

    centre: np.ndarray
    radius: float
    ends: int
    cuts: int

    @property
    def p21(self) -> float:
        """Trace length per unit area: m / (4r)."""
        return self.cuts / (4.0 * self.radius)

    @property
    def p20(self) -> float:
        """Traces per unit area: n / (2πr²) (each trace has two ends)."""
        return self.ends / (2.0 * np.pi * self.radius**2)

    @property
    def mean_length(self) -> float:
        """Mean trace length (πr / 2) · m / n; NaN without an end inside."""
        return np.pi * self.radius / 2.0 * self.cuts / self.ends if self.ends else np.nan

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "radius": self.radius, "ends_inside": self.ends,
                "edge_cuts": self.cuts, "P21": self.p21, "P20": self.p20, "mean_length": self.mean_length}


def circle_ring(centre: np.ndarray, radius: float, sides: int = SIDES) -> np.ndarray:
    """The closed polygon (sides + 1, 2), anticlockwise, whose vertices lie on the circle."""
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(None, f"scan circle radius {radius!r}: expected a positive length in map units")
    t = np.linspace(0.0, 2.0 * np.pi, sides + 1)
    return np.asarray(centre, dtype=float) + radius * np.column_stack([np.cos(t), np.sin(t)])


def as_circle(polygons: list[list[np.ndarray]]) -> tuple[np.ndarray, float] | None:
    """(centre, radius) if the area is one polygon without holes that is a circle (`ROUND`), else None."""
    if len(polygons) != 1 or len(polygons[0]) != 1:
        return None
    ring = polygons[0][0]
    ring = ring[:-1] if np.array_equal(ring[0], ring[-1]) else ring
    if len(ring) < MIN_SIDES:
        return None
    local = ring - ring.mean(axis=0)  # a local origin keeps UTM-sized maps exact
    x, y = local[:, 0], local[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = 0.5 * cross.sum()
    centre = (((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()) / (6.0 * area)
    distance = np.linalg.norm(local - centre, axis=1)
    mean = float(distance.mean())
    radius = float(np.sqrt(abs(area) / np.pi))  # fractopo's: the circle of the polygon's area
    if np.abs(distance - mean).max() > ROUND * mean or abs(radius / mean - 1) > ROUND:
        return None
    return ring.mean(axis=0) + np.asarray(centre), radius
