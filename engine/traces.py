"""Fracture traces: 2D polylines on photos and 3D polylines on the mesh (DESIGN.md data model)."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np

from engine.errors import InputError

SOURCES = ("manual", "auto")
TERMINATIONS = ("B", "T", "X", "C")  # blind, abutting, crossing, censored (Seers & Hodgetts 2016a)
METHODS = ("eigen", "probabilistic", "manual")
KINDS = ("fracture", "vein", "fault", "bedding")
"""What a trace is. Fractures, veins and faults make the network the statistics measure (`NETWORK_KINDS`);
bedding (a parting or a bed boundary) is traced to bound them: a fracture ending on it abuts it (T), but it is
no fracture, so it is left out of the sets, lengths, topology counts and intensities."""
NETWORK_KINDS = ("fracture", "vein", "fault")


T = TypeVar("T", "Trace2D", "Trace3D")


@dataclass(eq=False)
class Trace2D:
    """A trace on one photo: polyline (N, 2) in pixels, (0, 0) the centre of the top-left pixel; `kind` one
    of KINDS."""

    id: int
    image: str
    polyline: np.ndarray
    source: str = "manual"
    component: int = -1
    kind: str = "fracture"

    def __post_init__(self) -> None:
        self.polyline = np.asarray(self.polyline, dtype=np.float64).reshape(-1, 2)
        check_kind(self.kind)

    @property
    def length(self) -> float:
        """Length in pixels."""
        return polyline_length(self.polyline)


@dataclass(eq=False)
class Trace3D:
    """A trace on the mesh, in the project's local frame, with the provenance of every vertex.

    Vertex k came from pixel `uv[k]` of photo `images[image_index[k]]` and lies on mesh face `face[k]`.
    `term_start`/`term_end` are one of TERMINATIONS or "" while unclassified; extraction marks the ends it
    cut where the trace ran off the mesh as "C" (censored). `kind` is one of KINDS, its 2D traces' kind.
    """

    id: int
    points: np.ndarray
    uv: np.ndarray
    face: np.ndarray
    image_index: np.ndarray
    images: tuple[str, ...]
    parents: tuple[int, ...] = ()
    component: int = -1
    normal: np.ndarray | None = None
    method: str = ""
    K: float = np.nan
    M: float = np.nan
    dispersion: float = np.nan
    set_id: int = -1
    term_start: str = ""
    term_end: str = ""
    extra: dict = field(default_factory=dict)
    kind: str = "fracture"

    def __post_init__(self) -> None:
        check_kind(self.kind)
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = len(self.points)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(n, 2)
        self.face = np.asarray(self.face, dtype=np.int64).reshape(n)
        self.image_index = np.asarray(self.image_index, dtype=np.int32).reshape(n)
        self.images = tuple(self.images)
        self.parents = tuple(int(p) for p in self.parents)

    @property
    def chord_length(self) -> float:
        """Straight-line distance between the end nodes, metres."""
        return float(np.linalg.norm(self.points[-1] - self.points[0])) if len(self.points) > 1 else 0.0

    @property
    def surface_length(self) -> float:
        """Length along the mesh (sum of segment lengths), metres."""
        return polyline_length(self.points)

    @property
    def censored(self) -> bool:
        return "C" in (self.term_start, self.term_end)

    @property
    def vertex_images(self) -> np.ndarray:
        """Image name of every vertex (N,); "" for vertices no photo saw (spline bridges of a merge)."""
        names = np.asarray((*self.images, ""), dtype=object)
        return names[np.where(self.image_index >= 0, self.image_index, len(self.images))]

    def pixel_runs(self, image: str, *, max_gap: float = 1.5) -> list[np.ndarray]:
        """The pixels (u, v) of the vertices that came from photo `image`, in order, as polylines (N ≥ 2, 2)
        split where consecutive ones lie more than `max_gap` px apart: where this trace lies on that photo.
        The gaps are what extraction left off the mesh (misses, occluding edges, slivers). In a merged trace
        the vertices of other photos come in between (averaged parts) and do not split a run."""
        if image not in self.images:
            return []
        uv = self.uv[self.image_index == self.images.index(image)]
        apart = np.linalg.norm(np.diff(uv, axis=0), axis=1) > max_gap
        return [run for run in np.split(uv, np.flatnonzero(apart) + 1) if len(run) >= 2]


def check_kind(kind: str, where: str | None = None) -> str:
    """`kind` if it is one of KINDS, else InputError naming `where` (a file, a field) and the kinds known."""
    if kind not in KINDS:
        raise InputError(where, f"unknown trace kind {kind!r}; expected one of {', '.join(KINDS)}")
    return kind


def network(traces: Iterable[T]) -> list[T]:
    """The traces the fracture statistics measure: those of NETWORK_KINDS (bedding left out)."""
    return [t for t in traces if t.kind in NETWORK_KINDS]


def kind_edit(kind: str, traces2d: Iterable[Trace2D], traces3d: Iterable[Trace3D], *, ids2d: Iterable[int] = (),
              ids3d: Iterable[int] = ()) -> tuple[list[Trace2D], list[Trace3D]]:
    """Copies of the traces whose kind changes when the 2D traces `ids2d` and the 3D traces `ids3d` become
    `kind`, with every trace linked to them by extraction (the 3D traces made from a 2D trace, the 2D traces
    a 3D trace was made from, and so on): a 3D trace has its photos' kind, so a new extraction keeps the
    edit. The 2D traces become manual, as a trace edited by hand does, so a new auto-trace run (which
    replaces a photo's auto traces) keeps them. Traces already of `kind` are left out.
    """
    check_kind(kind)
    traces2d, traces3d = list(traces2d), list(traces3d)
    ids2d, ids3d = set(ids2d), set(ids3d)
    while True:
        more3d = {t.id for t in traces3d if t.id not in ids3d and ids2d.intersection(t.parents)}
        more2d = {p for t in traces3d if t.id in ids3d | more3d for p in t.parents} - ids2d
        if not more3d and not more2d:
            break
        ids2d, ids3d = ids2d | more2d, ids3d | more3d
    return ([replace(t, kind=kind, source="manual") for t in traces2d if t.id in ids2d and t.kind != kind],
            [replace(t, kind=kind) for t in traces3d if t.id in ids3d and t.kind != kind])


def first_outside(polyline: np.ndarray, width: int, height: int) -> int | None:
    """Index of the first vertex outside a width × height photo (pixel centres 0 … size − 1), or None.

    A vertex up to half a pixel beyond the outer pixel centres is still on the photo; NaN is outside.
    """
    uv = np.asarray(polyline, dtype=np.float64)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= height - 0.5)
    return None if inside.all() else int(np.argmin(inside))


def polyline_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def resample_polyline(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points at uniform arc-length `spacing` (the last segment may be shorter), keeping both ends.

    Returns the points (M, D) and their arc-length positions (M,). Zero-length steps are ignored.
    """
    points = np.asarray(points, dtype=np.float64)
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    total = s[-1]
    if total == 0.0:
        return points[:1].copy(), np.zeros(1)
    n = int(np.ceil(total / spacing)) + 1
    targets = np.linspace(0.0, total, n)
    keep = np.concatenate([[True], steps > 0])
    out = np.column_stack([np.interp(targets, s[keep], points[keep, k]) for k in range(points.shape[1])])
    return out, targets


def traces_digest(traces: Sequence[Trace3D], fields: Sequence[str] = ()) -> str:
    """A digest of the 3D traces' ids and vertices and of the named fields (e.g. "normal", "set_id"): what a
    stored result was computed on, so that a later merge, trim or edit shows the result is out of date.
    A "kind" counts only where it is not "fracture", so results stored before traces had kinds (all
    fractures) keep their digest."""
    h = hashlib.sha256()
    for t in sorted(traces, key=lambda t: t.id):
        h.update(np.int64(t.id).tobytes())
        h.update(np.ascontiguousarray(t.points, dtype=np.float64).tobytes())
        for name in fields:
            if name == "kind" and t.kind == "fracture":
                continue
            value = getattr(t, name)
            h.update(repr(None if value is None else np.asarray(value).tolist()).encode())
    return h.hexdigest()[:16]
