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

On the outcrop (`mesh_scan_circle`, `tracemap scan-circle`) the circle is the rock within r of a point on
it (a disc where the rock is flat): m counts where traces cross the sphere of radius r, n their ends inside
it. Ends the traces were cut at (C: the mesh's edge, an occlusion) are not fracture tips and are not counted
in n but told apart, as is the share of the window's rock no photo sees: a window is only unbiased where it
is wholly seen and holds no cut ends.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from engine.errors import InputError
from engine.intensity import subtriangle_centroids
from engine.mesh import Mesh, contour_segments
from engine.sight import Sight
from engine.traces import Trace3D

SIDES = 720
"""Sides of the polygon a scan circle is clipped with: its edge lies within r(1 − cos(π/720)) ≈ 1e-5 r of the
circle."""
ROUND = 0.01
"""An area polygon whose vertices all lie within this fraction of their mean distance from its centroid, that
distance within it of the radius of a circle of the polygon's area, is taken for a circle (fractopo's
`circular_target_area`); its radius is then that of the circle of its area, as fractopo's."""
MIN_SIDES = 16
WINDOW_SUBDIVISION = 16
"""Sub-triangles per edge of a face the window's edge crosses, for the area inside it (as the P21 map's
reference area, `tests/benchmarks/bench_intensity.py`)."""


@dataclass(frozen=True)
class Mauldon:
    """The counts of a scan circle of `radius` at `centre` (map units): `ends` inside, `cuts` of its edge."""

    centre: np.ndarray
    radius: float
    ends: int
    cuts: int
    censored: int = 0  # ends inside that traces were cut at (on the outcrop), not counted in `ends`
    seen: float = 1.0  # share of the window's rock area some photo sees (on the outcrop)
    area: float | None = None  # the window's area and edge length: a disc's, πr² and 2πr, unless given
    perimeter: float | None = None

    @property
    def p21(self) -> float:
        """Trace length per unit area: π m / (2 L) for a window of edge length L, m / (4r) for a disc
        (isotropic traces cross an edge of length L (2/π) P21 L times)."""
        return np.pi * self.cuts / (2.0 * self._perimeter)

    @property
    def p20(self) -> float:
        """Traces per unit area: n / (2A) (each trace has two ends), n / (2πr²) for a disc."""
        return self.ends / (2.0 * self._area)

    @property
    def mean_length(self) -> float:
        """Mean trace length P21 / P20, (πr / 2) · m / n for a disc; NaN without an end inside."""
        return self.p21 / self.p20 if self.ends else np.nan

    @property
    def _area(self) -> float:
        return np.pi * self.radius**2 if self.area is None else self.area

    @property
    def _perimeter(self) -> float:
        return 2.0 * np.pi * self.radius if self.perimeter is None else self.perimeter

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "radius": self.radius, "ends_inside": self.ends,
                "edge_cuts": self.cuts, "P21": self.p21, "P20": self.p20, "mean_length": self.mean_length,
                "censored_ends_inside": self.censored, "seen_share": self.seen, "window_area": self._area,
                "window_perimeter": self._perimeter}


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


def mesh_scan_circle(mesh: Mesh, traces: Sequence[Trace3D], centre: np.ndarray, radius: float, *,
                     sight: Sight | None = None) -> Mauldon:
    """Mauldon's counts of the window of rock within `radius` (m) of `centre` (local frame, on the rock):
    traces' crossings of the sphere (a segment with both ends outside that dips into it crosses twice) and
    their ends inside it, censored (C) ends apart; the window's mesh area and edge length (where the sphere
    cuts the mesh), which rough rock makes larger than a disc's; with the survey, the share of its area seen."""
    centre = np.asarray(centre, dtype=float).reshape(3)
    circle_ring(centre[:2], radius)  # checks the radius
    faces, area = _window_faces(mesh, centre, radius)
    if len(faces) == 0:
        raise InputError(None, f"scan circle: no rock within {radius:g} m of its centre; expected a centre on "
                               f"the mesh")
    seen = 1.0 if sight is None else float(area[sight.seen(mesh.face_centroids[faces],
                                                           2.0 * mesh.mean_edge_length)].sum() / area.sum())
    perimeter = _sphere_section_length(mesh, centre, radius)
    ends = cuts = censored = 0
    for trace in traces:
        inside = np.linalg.norm(trace.points - centre, axis=1) <= radius
        cuts += int(np.count_nonzero(inside[1:] != inside[:-1])) + 2 * _dips(trace.points, inside, centre, radius)
        for k, code in ((0, trace.term_start), (-1, trace.term_end)):
            if inside[k]:
                censored, ends = (censored + 1, ends) if code == "C" else (censored, ends + 1)
    return Mauldon(centre, float(radius), ends, cuts, censored, seen, float(area.sum()), perimeter)


def _window_faces(mesh: Mesh, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The faces with rock within the sphere and the area of each inside it: whole faces inside, and the
    share of the WINDOW_SUBDIVISION² sub-triangles inside of the faces its edge crosses."""
    near = np.flatnonzero(np.linalg.norm(mesh.face_centroids - centre, axis=1) <= radius + mesh.face_reach.max())
    inside = np.linalg.norm(mesh.vertices[mesh.faces[near]] - centre, axis=2) <= radius
    whole, edge = near[inside.all(axis=1)], near[inside.any(axis=1) & ~inside.all(axis=1)]
    bary = subtriangle_centroids(WINDOW_SUBDIVISION)
    sub = np.einsum("sk,fkj->fsj", bary, mesh.vertices[mesh.faces[edge]])
    share = (np.linalg.norm(sub - centre, axis=2) <= radius).mean(axis=1)
    faces = np.concatenate([whole, edge[share > 0]])
    return faces, np.concatenate([mesh.face_areas[whole], (mesh.face_areas[edge] * share)[share > 0]])


def _sphere_section_length(mesh: Mesh, centre: np.ndarray, radius: float) -> float:
    """Length of the window's edge: where the sphere cuts the mesh (`engine.mesh.contour_segments` of the
    distance from the centre less the radius)."""
    near = np.flatnonzero(np.linalg.norm(mesh.face_centroids - centre, axis=1) <= radius + mesh.face_reach.max())
    corners = mesh.faces[near]
    ends = contour_segments(mesh.vertices, corners, np.linalg.norm(mesh.vertices[corners] - centre, axis=2) - radius)
    return float(np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).sum())


def _dips(points: np.ndarray, inside: np.ndarray, centre: np.ndarray, radius: float) -> int:
    """Segments with both ends outside the sphere whose closest point to the centre lies inside it."""
    a, b = points[:-1], points[1:]
    outside = ~inside[:-1] & ~inside[1:]
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", centre - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
    closest = np.linalg.norm(a + t[:, None] * d - centre, axis=1)
    return int(np.count_nonzero(outside & (closest <= radius)))
