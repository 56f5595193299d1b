"""Fracture intensity maps on the mesh: P21 in a sphere at every vertex, and P21 → P32 (MATHS §8).

P21(x) = Σ length(trace ∩ B(x, r)) / Area(imaged mesh ∩ B(x, r)), at every mesh vertex x, for all traces and
per set. Trace lengths are clipped exactly to the sphere, segment by segment. The area is the true mesh area
in the ball, counting only faces some camera saw (`imaged_faces`): unimaged rock holds no traces and would
bias P21 low.

Area elements (DECISION, MATHS §8 "faces whose centroid is inside; subdivide when faces are large"): the
mesh area is carried by small elements, counted by where they lie.
* Fine meshes (mean edge ≤ r/8): one element per vertex, holding a third of each adjacent imaged face
  (the same partition of the area as face centroids, at half the cost: a mesh has twice as many faces as
  vertices). About 200 elements per ball at r/8.
* Coarser meshes: every face is cut into n² equal sub-triangles (n = ⌈12·edge/r⌉, fewer if that would
  make more than 8 million), one element at each sub-triangle centroid. On the QUICK synthetic outcrop
  (r = 5 edges) the area error in the ball is 1.7 % at most, 0.05 % typically.
* An element at distance d counts with weight clip(½ + (r − d)/h, 0, 1) over the element spacing h: an
  antialiased centroid rule. Counting only d ≤ r aliases with a regular mesh (2 % area error on a grid at
  r = 10 spacings); the ramp brings it to 0.2 %, and 0.18 % against the exact area on the benchmark wall
  (the plain face-centroid rule: 0.9 %).

Speed (tests/benchmarks/bench_intensity.py): points are cut into compact chunks, the leaves of a balanced
k-d tree (≤ 16 points; runs of 4 sibling leaves for the kernel centres). Chunk pairs wholly inside a ball
are summed per chunk (one sparse product); for the pairs on the sphere every centre–element pair is weighed
in compiled loops over the chunks' padded slabs (numba, without the GIL: the GUI thread runs freely while a
map is computed). Trace segments are clipped the same way. Runs of query chunks with equal shares of the
pairs run on a thread pool, and the k-d trees of the segments are built while the area is computed.

P32 = Σ_sets C(κ, θ_m) · P21_set, with C = 1/E_f[sin ρ] for a Fisher set whose mean pole makes θ_m with
the local surface normal (the area-weighted mean normal of the imaged mesh in the ball). The paper calls C
"C13 (Wang 2005)"; θ_m is measured from the surface *normal* (θ_m = 90° is a set perpendicular to the
outcrop, C → 1).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
from scipy.interpolate import CubicSpline
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.mesh import Mesh, mean_edge_length
from engine.raytrace import RayTracer
from engine.traces import Trace3D, network

ELEMENTS_PER_RADIUS = 8
"""The vertices carry the area when the mean edge is at most radius / ELEMENTS_PER_RADIUS (module docstring)."""

SUBDIVISION_PER_RADIUS = 12
"""Coarser meshes: faces are cut until their sub-triangles are about radius / SUBDIVISION_PER_RADIUS ..."""

MAX_ELEMENTS = 8_000_000
"""... but into no more than MAX_ELEMENTS sub-triangles in all (memory)."""

CHUNK = 16  # points per k-d leaf: the source chunks (area elements, segments)
QUERY_LEAVES = 4  # leaves per query chunk: wider query chunks share the cost of gathering their sources
PAIR_GROUP = 4  # source chunks searched together when pairing chunks
JOBS = 100  # runs of query chunks per ball sum, on the pool: progress and Cancel every 1 %
_FAR = 1.0e6  # position of padding points, metres: far outside every ball
SPACING_SAMPLE = 100_000


@dataclass(frozen=True)
class IntensityMap:
    """P21 at every mesh vertex (m⁻¹), NaN where the imaged area in the ball is below `min_area` (m²).

    `p21` counts all traces, `p21_by_set[k]` the traces of set k. `length` (m) is the trace length in the
    ball (all traces), `area` (m²) the imaged mesh area in it, and `normal` (V, 3) the unit area-weighted
    mean normal of that area (NaN where there is none): the sampling-plane normal of P21 → P32.
    """

    radius: float
    p21: np.ndarray
    p21_by_set: dict[int, np.ndarray]
    length: np.ndarray
    area: np.ndarray
    normal: np.ndarray
    min_area: float

    def scalars(self) -> dict[str, np.ndarray]:
        """Per-vertex arrays named for export: p21, p21_set<k>, kernel_area."""
        out = {"p21": self.p21}
        out.update({f"p21_set{k}": v for k, v in sorted(self.p21_by_set.items())})
        out["kernel_area"] = self.area
        return out


@dataclass(frozen=True)
class P32Map:
    """P32 (m²/m³ = m⁻¹) at every vertex: the sum over sets, each set's share, and each set's factor C."""

    p32: np.ndarray
    p32_by_set: dict[int, np.ndarray]
    factor_by_set: dict[int, np.ndarray]

    def scalars(self) -> dict[str, np.ndarray]:
        """Per-vertex arrays named for export: p32, p32_set<k>."""
        out = {"p32": self.p32}
        out.update({f"p32_set{k}": v for k, v in sorted(self.p32_by_set.items())})
        return out


# ---------------------------------------------------------------------------------------------------------
# P21


def p21_map(mesh: Mesh, traces: Sequence[Trace3D], *, radius: float, imaged_faces: np.ndarray | None = None,
            sets: Iterable[int] | None = None, min_area_fraction: float = 0.5, threads: int | None = None,
            progress: Progress | None = None) -> IntensityMap:
    """P21 in a sphere of `radius` (m) at every vertex of `mesh`, for all traces and per set (MATHS §8).

    traces : in the mesh's local frame. Traces of a set not in `sets` count only in the total; bedding
        traces count nowhere (`engine.traces.network`).
    imaged_faces : boolean mask (F,) or face indices of the area that was imaged and interpreted
        (`imaged_faces(mesh, cameras, tracer)`); default every face.
    sets : set ids to map; default every set id ≥ 0 among the traces.
    min_area_fraction : P21 is NaN where the imaged area in the ball is below this fraction of πr².
    threads : worker threads (default min(2, CPU count)).
    """
    radius = _check_radius(mesh, radius)
    if not 0.0 <= min_area_fraction <= 1.0:
        raise InputError(None, f"min_area_fraction={min_area_fraction!r}: expected a number in [0, 1]")
    mask = _face_mask(mesh, imaged_faces)
    segments = _segments(network(traces))
    set_ids = sorted({int(s) for s in segments.set_id if s >= 0} if sets is None else {int(s) for s in sets})
    threads = threads or min(2, os.cpu_count() or 1)

    columns = _set_columns(segments.set_id, set_ids)
    lengths = np.zeros((len(mesh.vertices), columns.shape[1]))
    with ThreadPoolExecutor(threads) as pool:
        report(progress, 0.0, "area elements")
        # k-d tree code releases the GIL: the segments are prepared while the area elements are
        tracks = pool.submit(_Tracks.build, segments, columns) if len(columns) else None
        vertices, elements, ramp = _area_chunks(mesh, mask, radius, pool)
        if tracks is not None:
            track_pairs = pool.submit(lambda: _chunk_pairs(vertices, tracks.result().chunks, radius, radius))
        report(progress, 0.1, "imaged area in the kernel")
        pairs = _chunk_pairs(vertices, elements, radius - ramp / 2, radius + ramp / 2)
        area_normal = _ball_sums(vertices, elements, pairs, radius, ramp, pool, progress, (0.1, 0.7))
        report(progress, 0.7, "trace length in the kernel")
        if tracks is not None:
            lengths = _clipped_lengths(vertices, tracks.result(), track_pairs.result(), radius, pool, progress,
                                       (0.7, 1.0))

    area = area_normal[:, 0]
    min_area = min_area_fraction * np.pi * radius**2
    valid = area >= min_area
    with np.errstate(invalid="ignore", divide="ignore"):
        p21 = np.where(valid[:, None], lengths / area[:, None], np.nan)
        normal = area_normal[:, 1:]
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    report(progress, 1.0, "P21 done")
    return IntensityMap(radius, p21[:, 0], {k: p21[:, 1 + i] for i, k in enumerate(set_ids)}, lengths[:, 0],
                        area, normal, min_area)


def _spacing(mesh: Mesh) -> float:
    """Mean edge length, from at most SPACING_SAMPLE faces spread over the mesh (all of them is slow)."""
    return mean_edge_length(mesh.vertices, mesh.faces, most=SPACING_SAMPLE)


def _check_radius(mesh: Mesh, radius: float) -> float:
    spacing = _spacing(mesh)
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(None, f"radius={radius!r}: expected a positive number of metres")
    if radius < spacing:
        raise InputError(None, f"radius={radius:g} m is below the mesh spacing (mean edge length {spacing:.3g} m): "
                               f"expected radius ≥ {spacing:.3g} m, ideally ≥ {10 * spacing:.3g} m")
    return float(radius)


def _face_mask(mesh: Mesh, imaged: np.ndarray | None) -> np.ndarray:
    n = len(mesh.faces)
    if imaged is None:
        return np.ones(n, dtype=bool)
    imaged = np.asarray(imaged)
    if imaged.dtype == bool:
        if imaged.shape != (n,):
            raise InputError(None, f"imaged_faces: a boolean mask must have one entry per face ({n}), "
                                   f"got shape {imaged.shape}")
        return imaged
    if imaged.size and (imaged.min() < 0 or imaged.max() >= n):
        raise InputError(None, f"imaged_faces: face indices must lie in [0, {n - 1}]")
    mask = np.zeros(n, dtype=bool)
    mask[imaged.astype(np.int64)] = True
    return mask


def _set_columns(set_id: np.ndarray, set_ids: list[int]) -> np.ndarray:
    """(S, 1 + n_sets) 0/1: column 0 every segment, column 1 + i the segments of set_ids[i]."""
    ids = np.asarray(set_ids, dtype=np.int64)
    member = np.flatnonzero(np.isin(set_id, ids))
    columns = np.zeros((len(set_id), 1 + len(ids)))
    columns[:, 0] = 1.0
    columns[member, 1 + np.searchsorted(ids, set_id[member])] = 1.0
    return columns


def _area_chunks(mesh: Mesh, mask: np.ndarray, radius: float,
                 pool: ThreadPoolExecutor) -> tuple[_Chunks, _Chunks, float]:
    """Query chunks of the vertices, chunks of the area elements and the element spacing (m)."""
    edge = _spacing(mesh)
    runs = pool.submit(_kd_runs, mesh.vertices)
    if edge * ELEMENTS_PER_RADIUS <= radius:  # fine mesh: the vertices carry the area, one k-d tree serves both
        weights, ramp = _vertex_elements(mesh, mask)
        elements = _Chunks.build(mesh.vertices, weights, runs.result())
        return elements.grouped(QUERY_LEAVES), elements, ramp
    n = int(np.clip(np.ceil(edge * SUBDIVISION_PER_RADIUS / radius), 1, np.sqrt(MAX_ELEMENTS / len(mesh.faces))))
    positions, weights = _face_elements(mesh, mask, n)
    elements = _Chunks.build(positions, weights, _kd_runs(positions))
    leaves = _Chunks.build(mesh.vertices, np.zeros((len(mesh.vertices), 0)), runs.result())
    return leaves.grouped(QUERY_LEAVES), elements, float(np.sqrt(mesh.face_areas.mean())) / n


def _vertex_elements(mesh: Mesh, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-vertex (V, 4) area, area × unit normal (a third of each adjacent imaged face), and the vertex
    spacing √(mesh area / V)."""
    v, f = mesh.vertices, mesh.faces
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # 2 × area × unit normal
    double_area = np.linalg.norm(cross, axis=1)
    per_face = np.column_stack([double_area, cross]) * (mask / 6.0)[:, None]
    corners = f.ravel()
    weights = np.column_stack([np.bincount(corners, np.repeat(per_face[:, k], 3), minlength=len(v)) for k in range(4)])
    return weights, float(np.sqrt(0.5 * double_area.sum() / len(v)))


def _face_elements(mesh: Mesh, mask: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (F·n², 3) and weights (area, area × unit normal) of the n² sub-triangles of each imaged face."""
    tri = mesh.vertices[mesh.faces[mask]]
    area = mesh.face_areas[mask]
    bary = subtriangle_centroids(n)
    positions = np.einsum("sk,fkj->fsj", bary, tri).reshape(-1, 3)
    per_face = np.column_stack([area, area[:, None] * mesh.face_normals[mask]]) / n**2
    return positions, np.repeat(per_face, len(bary), axis=0)


def subtriangle_centroids(n: int) -> np.ndarray:
    """Barycentric centroids (n², 3) of the n² equal triangles of a triangle cut n times along each edge."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    up = (i + j) <= n - 1
    down = (i + j) <= n - 2
    b = np.concatenate([np.column_stack([i[up] + 1 / 3, j[up] + 1 / 3]),
                        np.column_stack([i[down] + 2 / 3, j[down] + 2 / 3])]) / n
    return np.column_stack([1 - b.sum(axis=1), b])


@dataclass(frozen=True)
class _Segments:
    p0: np.ndarray
    p1: np.ndarray
    set_id: np.ndarray


def _segments(traces: Sequence[Trace3D]) -> _Segments:
    p0, p1, set_id = [], [], []
    for t in traces:
        bad = ~np.isfinite(t.points).all(axis=1)
        if bad.any():
            raise InputError(None, f"trace {t.id}: {int(bad.sum())} of its {len(t.points)} vertices are NaN or "
                                   "infinite; expected finite coordinates (metres, mesh frame)")
        step = np.linalg.norm(np.diff(t.points, axis=0), axis=1) > 0
        p0.append(t.points[:-1][step])
        p1.append(t.points[1:][step])
        set_id.append(np.full(int(step.sum()), t.set_id))
    if not p0:
        return _Segments(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    return _Segments(np.concatenate(p0), np.concatenate(p1), np.concatenate(set_id).astype(np.int64))


# ---------------------------------------------------------------------------------------------------------
# P32


def p32_factor(kappa: float, theta_m: np.ndarray | float, *, nodes: int = 128) -> np.ndarray:
    """C(κ, θ_m) = 1 / E_f[sin ρ]: P32 = C · P21 for a Fisher set sampled by a plane (MATHS §8).

    kappa : Fisher concentration κ ≥ 0 of the set's poles (0: uniform, C = 4/π; κ → ∞: C → 1/sin θ_m).
    theta_m : angle(s) in degrees between the set's mean pole and the sampling-plane normal (axial, so
        θ and 180° − θ agree); vectorised.
    nodes : Gauss–Legendre nodes in the pole's colatitude; the azimuth takes nodes / 2 midpoints.
    """
    return 1.0 / _fisher_mean(lambda cos_rho: np.sqrt(np.clip(1.0 - cos_rho**2, 0.0, None)), kappa, theta_m, nodes)


def p10_p32_factor(kappa: float, delta_m: np.ndarray | float, *, nodes: int = 128) -> np.ndarray:
    """1 / E_f[|cos δ|]: P32 = factor · P10 for a Fisher set sampled by a line (MATHS §8, linear sampling).

    kappa : Fisher concentration κ ≥ 0 (0: uniform, factor 2; κ → ∞: 1/|cos δ_m|).
    delta_m : angle(s) in degrees between the set's mean pole and the scanline; vectorised.
    """
    return 1.0 / _fisher_mean(np.abs, kappa, delta_m, nodes)


def _fisher_mean(f, kappa: float, theta_m: np.ndarray | float, nodes: int) -> np.ndarray:
    """E_f[f(cos ρ)] over Fisher poles about a mean at θ_m (degrees) from a fixed axis.

    cos ρ = cos θ cos θ_m + sin θ sin θ_m cos φ. The colatitude is sampled through its inverse CDF,
    cos θ = 1 + log(1 − v(1 − e^{−2κ}))/κ with v = s², so the density (stable for any κ) is absorbed and the
    cusp of f at the mean pole is smoothed; Gauss–Legendre in s, midpoints in φ (f is even in φ: [0, π]).
    """
    if not (np.isfinite(kappa) and kappa >= 0):
        raise InputError(None, f"kappa={kappa!r}: expected a finite concentration ≥ 0")
    theta = np.radians(np.asarray(theta_m, dtype=float))
    if not np.all(np.isfinite(theta)):
        raise InputError(None, "theta_m: expected finite angles in degrees")
    x, weight = np.polynomial.legendre.leggauss(nodes)
    s = 0.5 * (x + 1.0)
    v = s * s
    dv = s * weight  # 2s · (weight / 2): the Jacobian of v = s² on [0, 1]
    w = 1.0 - 2.0 * v if kappa < 1e-12 else 1.0 + np.log1p(-v * -np.expm1(-2.0 * kappa)) / kappa
    w = np.clip(w, -1.0, 1.0)
    phi = (np.arange(nodes // 2) + 0.5) * np.pi / (nodes // 2)
    t = theta.reshape(-1)[:, None, None]
    cos_rho = w[:, None] * np.cos(t) + np.sqrt(1.0 - w * w)[:, None] * np.sin(t) * np.cos(phi)
    return (f(cos_rho).mean(axis=2) @ dv).reshape(theta.shape)


def p32_map(p21_by_set: Mapping[int, np.ndarray], set_means: Mapping[int, np.ndarray],
            set_kappas: Mapping[int, float], vertex_normals: np.ndarray) -> P32Map:
    """P32 = Σ_sets C(κ, θ_m) · P21_set at every vertex (MATHS §8: multiple sets).

    p21_by_set : `IntensityMap.p21_by_set`. set_means : mean pole (3,) of each set (any sign, any length).
    set_kappas : Fisher κ of each set. vertex_normals (V, 3) : the sampling-plane normal at each vertex;
        pass `IntensityMap.normal`, the mean normal of the imaged mesh in the kernel. θ_m is the angle
        between it and the set's mean pole. C is interpolated (cubic, 0.25° steps) from `p32_factor`.
    Traces without a set carry no orientation distribution and are left out of P32.
    """
    normals = np.asarray(vertex_normals, dtype=float)
    out, factors = {}, {}
    grid = np.linspace(0.0, 90.0, 361)
    for k, p21 in p21_by_set.items():
        if k not in set_means or k not in set_kappas:
            raise InputError(None, f"set {k}: P32 needs its mean pole and κ (set_means and set_kappas)")
        mean = np.asarray(set_means[k], dtype=float).reshape(3)
        if not (np.all(np.isfinite(mean)) and np.linalg.norm(mean) > 0):
            raise InputError(None, f"set {k}: mean pole {mean.tolist()} is not a direction")
        if np.shape(p21) != (len(normals),):
            raise InputError(None, f"set {k}: {np.size(p21)} P21 values for {len(normals)} vertex normals")
        with np.errstate(invalid="ignore"):
            cos_m = np.abs(normals @ (mean / np.linalg.norm(mean)))
        theta = np.degrees(np.arccos(np.clip(cos_m, 0.0, 1.0)))
        factors[k] = CubicSpline(grid, p32_factor(float(set_kappas[k]), grid))(theta)
        out[k] = factors[k] * np.asarray(p21, dtype=float)
    total = np.sum(list(out.values()), axis=0) if out else np.full(len(normals), np.nan)
    return P32Map(total, out, factors)


# ---------------------------------------------------------------------------------------------------------
# imaged area


def imaged_faces(mesh: Mesh, cameras: Mapping[str, Camera], tracer: RayTracer, *,
                 tolerance: float | None = None, progress: Progress | None = None) -> np.ndarray:
    """Faces (F,) bool seen by at least one camera: the face centroid projects inside the photo, in front
    of the camera and within its field of view, and the ray from the camera centre reaches it unblocked.

    cameras : in the mesh's local frame (`Camera.shifted(origin)`), like `tracer`.
    tolerance : a surface this close (m) in front of the centroid does not hide it (rays graze the
        neighbouring faces); default half the mean edge length.
    """
    tol = 0.5 * _spacing(mesh) if tolerance is None else float(tolerance)
    centroids = mesh.face_centroids
    seen = np.zeros(len(centroids), dtype=bool)
    for k, camera in enumerate(cameras.values()):
        report(progress, k / max(len(cameras), 1), f"faces seen from {camera.name}")
        candidate = np.flatnonzero(~seen)
        candidate = candidate[_in_view(camera, centroids[candidate])]
        if len(candidate):
            seen[candidate] = ~tracer.occluded(camera.centre, centroids[candidate], tolerance=tol)
    report(progress, 1.0, "imaged faces done")
    return seen


def _in_view(camera: Camera, points: np.ndarray) -> np.ndarray:
    """In front of the camera, within its field of view (so lens distortion cannot fold outside points in)
    and projecting inside the photo."""
    xc = points @ camera.R.T + camera.t
    ahead = xc[:, 2] > 0
    corners = np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5], [-0.5, camera.height - 0.5],
                        [camera.width - 0.5, camera.height - 0.5]])
    fov = 1.05 * np.abs(camera.undistort_normalised(corners)).max(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = xc[:, :2] / xc[:, 2:]
    inside = ahead & np.all(np.abs(xn) <= fov, axis=1)
    uv = camera.project(points[inside])
    inside[inside] = ((uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
                      & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5))
    return inside


# ---------------------------------------------------------------------------------------------------------
# chunked ball sums


@dataclass(frozen=True)
class _Chunks:
    """Points cut into compact chunks (the leaves of a k-d tree), stored as padded slabs.

    `members` (C, L) indexes the points (−1 for padding); `slabs` (C, L, 3) their positions (padding sits
    at _FAR); `values` (C, L, k) float32 per-point values (zero for padding) and `sums` (C, k) their chunk
    totals; `centre` (C, 3) and `reach` (C,) a bounding sphere of each chunk.
    """

    members: np.ndarray
    slabs: np.ndarray
    values: np.ndarray
    sums: np.ndarray
    centre: np.ndarray
    reach: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, values: np.ndarray, runs: tuple[np.ndarray, np.ndarray], *,
              extent: np.ndarray | None = None) -> _Chunks:
        """Chunks of `points` (N, 3) carrying `values` (N, k): `runs` = (order, bounds), chunk i holds
        points[order[bounds[i]:bounds[i + 1]]]. `extent` (N,) widens each point's bounding radius (a
        segment's half length)."""
        order, bounds = runs
        p = points[order]
        count = np.diff(bounds)
        width = int(count.max())
        centre = np.add.reduceat(p, bounds[:-1]) / count[:, None]
        spread = np.linalg.norm(p - np.repeat(centre, count, axis=0), axis=1)
        if extent is not None:
            spread += extent[order]
        chunk = np.repeat(np.arange(len(count)), count)
        slot = np.arange(len(p)) - np.repeat(bounds[:-1], count)
        members = np.full((len(count), width), -1, dtype=np.int64)
        members[chunk, slot] = order
        slabs = np.full((len(count), width, 3), _FAR)
        slabs[chunk, slot] = p
        packed = np.zeros((len(count), width, values.shape[1]), dtype=np.float32)
        packed[chunk, slot] = values[order]
        return cls(members, slabs, packed, packed.sum(axis=1, dtype=np.float64), centre,
                   np.maximum.reduceat(spread, bounds[:-1]))

    def grouped(self, n: int) -> _Chunks:
        """Chunks of n consecutive chunks (siblings in the k-d tree, so still compact), without values."""
        pad = -len(self) % n
        width = self.members.shape[1]
        members = np.vstack([self.members, np.full((pad, width), -1)]).reshape(-1, n * width)
        slabs = np.concatenate([self.slabs, np.full((pad, width, 3), _FAR)]).reshape(-1, n * width, 3)
        count = np.append((self.members >= 0).sum(axis=1), np.zeros(pad, dtype=int)).reshape(-1, n)
        centres = np.vstack([self.centre, np.zeros((pad, 3))]).reshape(-1, n, 3)
        centre = (centres * count[..., None]).sum(axis=1) / count.sum(axis=1, keepdims=True)
        reach = np.append(self.reach, np.zeros(pad)).reshape(-1, n) + np.linalg.norm(centres - centre[:, None], axis=2)
        return _Chunks(members, slabs, np.zeros((len(members), n * width, 0), dtype=np.float32),
                       np.zeros((len(members), 0)), centre, np.where(count > 0, reach, 0.0).max(axis=1))

    def __len__(self) -> int:
        return len(self.members)


def _kd_runs(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, bounds): the points in k-d tree order and where each leaf of ≤ CHUNK points starts (and the
    end). Leaves are compact groups of points, siblings next to each other."""
    order, starts = _kd_leaves(np.ascontiguousarray(points, dtype=np.float64), CHUNK)
    return order, np.append(starts, len(points))


# compiled (or loaded from numba's cache) when this module is imported, not on a worker, and run without the
# GIL: scipy's k-d tree gives its leaves only as Python node objects, whose walk held the GIL ~120 ms at 256k
# points and, beside the other threads of `p21_map`, kept the GUI thread waiting for it 150–500 ms
@numba.njit("void(float64[:, ::1], int64[::1], int64, int64, int64, int64)", nogil=True, cache=True)
def _select(points: np.ndarray, order: np.ndarray, lo: int, hi: int, k: int, axis: int) -> None:
    """Reorder points[lo:hi] (and `order` alike) so that point k is the (k − lo)-th along `axis`, none after
    it lower and none before it higher (quickselect, Hoare partition around a median of three: ties split
    evenly)."""
    left, right = lo, hi - 1
    while left < right:
        a, b, c = points[left, axis], points[(left + right) // 2, axis], points[right, axis]
        pivot = max(min(a, b), min(max(a, b), c))
        i, j = left, right
        while i <= j:
            while points[i, axis] < pivot:
                i += 1
            while points[j, axis] > pivot:
                j -= 1
            if i <= j:
                for d in range(points.shape[1]):
                    points[i, d], points[j, d] = points[j, d], points[i, d]
                order[i], order[j] = order[j], order[i]
                i += 1
                j -= 1
        if k <= j:
            right = j
        elif k >= i:
            left = i
        else:
            return


@numba.njit("Tuple((int64[::1], int64[::1]))(float64[:, ::1], int64)", nogil=True, cache=True)
def _kd_leaves(points: np.ndarray, leaf_size: int) -> tuple[np.ndarray, np.ndarray]:
    """A balanced k-d tree's leaves (as cKDTree's: median splits across the widest extent of each node's
    points): the point order, and the start of each leaf of ≤ leaf_size points in it, ascending."""
    points = points.copy()  # kept in the order of `order`: contiguous reads
    n, dims = points.shape
    order = np.arange(n)
    starts = np.empty(n // ((leaf_size + 1) // 2) + 1, dtype=np.int64)  # a split leaves ≥ ⌈leaf_size/2⌉ a side
    stack = np.empty((130, 2), dtype=np.int64)  # depth ≤ log2(n) + 1, one pending sibling per level
    stack[0, 0], stack[0, 1] = 0, n
    top, leaves = 1, 0
    while top > 0:
        top -= 1
        lo, hi = stack[top, 0], stack[top, 1]
        if hi - lo <= leaf_size:
            starts[leaves] = lo
            leaves += 1
            continue
        widest, axis = -1.0, 0
        for d in range(dims):
            low, high = np.inf, -np.inf
            for i in range(lo, hi):
                low, high = min(low, points[i, d]), max(high, points[i, d])
            if high - low > widest:
                widest, axis = high - low, d
        mid = (lo + hi) // 2
        _select(points, order, lo, hi, mid, axis)
        stack[top, 0], stack[top, 1] = mid, hi  # the upper half waits: leaves come out in order
        stack[top + 1, 0], stack[top + 1, 1] = lo, mid
        top += 2
    return order, starts[:leaves]


@dataclass(frozen=True)
class _Pairs:
    """Chunk pairs within reach: `whole` (Q, S) sparse 0/1, source chunks entirely inside the ball of every
    query point; `indptr`/`ids` (CSR over query chunks) the chunk pairs on the sphere, decided per point."""

    whole: csr_matrix
    indptr: np.ndarray
    ids: np.ndarray


def _chunk_pairs(queries: _Chunks, sources: _Chunks, inner: float, outer: float) -> _Pairs:
    """Source chunks wholly within `inner` of every point of a query chunk, and those partly within `outer`.

    Runs of PAIR_GROUP consecutive source chunks (siblings in the k-d tree) are searched first, which finds
    the same pairs from a quarter of the candidates.
    """
    starts = np.arange(0, len(sources), PAIR_GROUP)
    size = np.diff(np.append(starts, len(sources)))
    group_centre = np.add.reduceat(sources.centre, starts) / size[:, None]
    group_reach = np.maximum.reduceat(np.linalg.norm(sources.centre - np.repeat(group_centre, size, axis=0), axis=1)
                                      + sources.reach, starts)
    bound = outer + queries.reach.max() + group_reach.max()
    found = cKDTree(queries.centre).sparse_distance_matrix(cKDTree(group_centre), bound, output_type="ndarray")
    q, g = found["i"].astype(np.int64), found["j"].astype(np.int64)
    near = found["v"] <= outer + queries.reach[q] + group_reach[g]
    q, g = q[near], g[near]
    n = size[g]
    s = np.repeat(starts[g] - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))
    q = np.repeat(q, n)
    d = np.linalg.norm(queries.centre[q] - sources.centre[s], axis=1)
    span = queries.reach[q] + sources.reach[s]
    whole = d + span <= inner
    band = (d - span <= outer) & ~whole
    order = np.argsort(q[band], kind="stable")
    indptr = np.concatenate([[0], np.cumsum(np.bincount(q[band], minlength=len(queries)))])
    return _Pairs(csr_matrix((np.ones(int(whole.sum())), (q[whole], s[whole])), shape=(len(queries), len(sources))),
                  indptr, s[band][order])


def _jobs(pairs: _Pairs) -> list[tuple[int, int]]:
    """JOBS runs (first, end) of consecutive query chunks holding about equal shares of the band pairs."""
    cuts = np.searchsorted(pairs.indptr, np.linspace(0, pairs.indptr[-1], JOBS + 1)[1:-1])
    edges = np.unique(np.concatenate([[0], cuts, [len(pairs.indptr) - 1]]))
    return list(zip(edges[:-1].tolist(), edges[1:].tolist()))


def _run(jobs: list, work, pool: ThreadPoolExecutor, progress: Progress | None, span: tuple[float, float]) -> None:
    """work(*job) for every job on the pool; progress is reported from this thread, and a callback that
    raises (Cancelled) stops the jobs not yet started."""
    lo, hi = span
    stop = threading.Event()

    def step(job):
        if not stop.is_set():
            work(*job)

    try:
        for k, _ in enumerate(pool.map(step, jobs)):
            report(progress, lo + (hi - lo) * (k + 1) / len(jobs), "intensity")
    except BaseException:
        stop.set()
        raise


def _scatter(out: np.ndarray, queries: _Chunks, chunk_values: np.ndarray) -> None:
    """Add per-chunk values (Q, k) to every member point of each query chunk."""
    filled = queries.members >= 0
    out[queries.members[filled]] += np.broadcast_to(chunk_values[:, None, :], (*queries.members.shape,
                                                                                 chunk_values.shape[1]))[filled]


def _ball_sums(queries: _Chunks, sources: _Chunks, pairs: _Pairs, radius: float, ramp: float,
               pool: ThreadPoolExecutor, progress: Progress | None, span: tuple[float, float]) -> np.ndarray:
    """Σ weight · values of the source points near each query point (N_q, k).

    The weight of a source at distance d is clip(½ + (r − d)/ramp, 0, 1), with r − d linearised as
    (r² − d²)/2r: an antialiased ball. Counting only d ≤ r makes the area alias with a regular mesh (2 %
    error on a grid at r = 10 spacings); a ramp one element spacing wide brings it to 0.2 %.
    """
    out = np.zeros((int(queries.members.max()) + 1, sources.values.shape[2]))
    _scatter(out, queries, pairs.whole @ sources.sums)
    c = 1.0 / (2.0 * radius * ramp)
    _run(_jobs(pairs), lambda first, end: _ball_kernel(first, end, queries.slabs, queries.members, sources.slabs,
                                                       sources.values, pairs.indptr, pairs.ids, radius, c, out),
         pool, progress, span)
    return out


@numba.njit(inline="always")
def _load_chunk(q_slabs: np.ndarray, qc: int, x: np.ndarray) -> None:
    """Query chunk qc into x, coordinate-major: the kernels' inner loops then run over contiguous memory."""
    for i in range(q_slabs.shape[1]):
        for d in range(3):
            x[d, i] = q_slabs[qc, i, d]


@numba.njit(inline="always")
def _add_chunk(q_members: np.ndarray, qc: int, acc: np.ndarray, out: np.ndarray) -> None:
    """A chunk's sums into the rows of its points (padded points, member −1, are not written)."""
    for i in range(q_members.shape[1]):
        if q_members[qc, i] >= 0:
            for m in range(acc.shape[1]):
                out[q_members[qc, i], m] += acc[i, m]


@numba.njit("void(int64, int64, float64[:, :, ::1], int64[:, ::1], float64[:, :, ::1], float32[:, :, ::1], int64[::1], "
            "int64[::1], float64, float64, float64[:, ::1])", nogil=True, cache=True, fastmath=True)
def _ball_kernel(first: int, end: int, q_slabs: np.ndarray, q_members: np.ndarray, s_slabs: np.ndarray,
                 s_values: np.ndarray, indptr: np.ndarray, ids: np.ndarray, radius: float, c: float,
                 out: np.ndarray) -> None:
    """`_ball_sums` over the band pairs of query chunks first..end − 1, added to `out` (c = 1 / (2 r ramp)).
    Padding weighs nothing: padded sources sit at _FAR with zero values, padded query points are not written.
    Chunks are distinct points, so jobs on other chunks never write the same row."""
    n_query, n_source, k = q_slabs.shape[1], s_slabs.shape[1], s_values.shape[2]
    x = np.empty((3, n_query))
    acc = np.empty((n_query, k))
    r2 = radius * radius
    for qc in range(first, end):
        _load_chunk(q_slabs, qc, x)
        acc[:] = 0.0
        for pair in range(indptr[qc], indptr[qc + 1]):
            sc = ids[pair]
            for j in range(n_source):
                ex, ey, ez = s_slabs[sc, j, 0], s_slabs[sc, j, 1], s_slabs[sc, j, 2]
                for i in range(n_query):
                    dx, dy, dz = x[0, i] - ex, x[1, i] - ey, x[2, i] - ez
                    w = min(max(0.5 + (r2 - (dx * dx + dy * dy + dz * dz)) * c, 0.0), 1.0)
                    for m in range(k):
                        acc[i, m] += w * s_values[sc, j, m]
        _add_chunk(q_members, qc, acc, out)


@dataclass(frozen=True)
class _Tracks:
    """Trace segments as chunks (by midpoint; values: length per one-hot column, reach including the half
    length) with slabs of each segment's start p0, d/a and 1/a (d = p1 − p0, a = d·d)."""

    chunks: _Chunks
    start: np.ndarray
    unit: np.ndarray
    inv_a: np.ndarray

    @classmethod
    def build(cls, segments: _Segments, columns: np.ndarray) -> _Tracks:
        step = segments.p1 - segments.p0
        a = np.einsum("ij,ij->i", step, step)
        mid = segments.p0 + 0.5 * step
        chunks = _Chunks.build(mid, columns * np.sqrt(a)[:, None], _kd_runs(mid), extent=0.5 * np.sqrt(a))
        return cls(chunks, _slab_values(chunks, segments.p0, _FAR), _slab_values(chunks, step / a[:, None], 0.0),
                   np.ascontiguousarray(_slab_values(chunks, 1.0 / a[:, None], 0.0)[..., 0]))


def _clipped_lengths(queries: _Chunks, tracks: _Tracks, pairs: _Pairs, radius: float, pool: ThreadPoolExecutor,
                     progress: Progress | None, span: tuple[float, float]) -> np.ndarray:
    """Length of the segments inside the ball of each query point (N_q, k), per column of the tracks' values.

    Exact clipping (MATHS §8): with d = p1 − p0, solve ‖p0 + t d − x‖² = r² and keep t ∈ [0, 1].
    """
    out = np.zeros((int(queries.members.max()) + 1, tracks.chunks.values.shape[2]))
    _scatter(out, queries, pairs.whole @ tracks.chunks.sums)
    _run(_jobs(pairs), lambda first, end: _length_kernel(first, end, queries.slabs, queries.members, tracks.start,
                                                         tracks.unit, tracks.inv_a, tracks.chunks.values,
                                                         pairs.indptr, pairs.ids, radius, out),
         pool, progress, span)
    return out


@numba.njit("void(int64, int64, float64[:, :, ::1], int64[:, ::1], float64[:, :, ::1], float64[:, :, ::1], "
            "float64[:, ::1], float32[:, :, ::1], int64[::1], int64[::1], float64, float64[:, ::1])",
            nogil=True, cache=True, fastmath=True)
def _length_kernel(first: int, end: int, q_slabs: np.ndarray, q_members: np.ndarray, start: np.ndarray,
                   unit: np.ndarray, inv_a: np.ndarray, values: np.ndarray, indptr: np.ndarray, ids: np.ndarray,
                   radius: float, out: np.ndarray) -> None:
    """`_clipped_lengths` over the band pairs of query chunks first..end − 1, added to `out`. With a = d·d,
    the ball holds t ∈ [t_c − w, t_c + w]: t_c = d·(x − p0)/a, w² = t_c² − (‖p0 − x‖² − r²)/a (padding
    segments: d = 0, 1/a = 0, so w = 0 and nothing is added)."""
    n_query, n_source, k = q_slabs.shape[1], start.shape[1], values.shape[2]
    x = np.empty((3, n_query))
    acc = np.empty((n_query, k))
    r2 = radius * radius
    for qc in range(first, end):
        _load_chunk(q_slabs, qc, x)
        acc[:] = 0.0
        for pair in range(indptr[qc], indptr[qc + 1]):
            sc = ids[pair]
            for j in range(n_source):
                px, py, pz = start[sc, j, 0], start[sc, j, 1], start[sc, j, 2]
                ux, uy, uz, ia = unit[sc, j, 0], unit[sc, j, 1], unit[sc, j, 2], inv_a[sc, j]
                for i in range(n_query):
                    dx, dy, dz = x[0, i] - px, x[1, i] - py, x[2, i] - pz
                    centre = ux * dx + uy * dy + uz * dz
                    w2 = centre * centre - (dx * dx + dy * dy + dz * dz - r2) * ia
                    if w2 > 0.0:
                        w = np.sqrt(w2)
                        inside = min(centre + w, 1.0) - max(centre - w, 0.0)
                        if inside > 0.0:
                            for m in range(k):
                                acc[i, m] += inside * values[sc, j, m]
        _add_chunk(q_members, qc, acc, out)


def _slab_values(chunks: _Chunks, values: np.ndarray, pad: float) -> np.ndarray:
    """Per-point `values` (N, k) laid out like the chunks' slabs (C, width, k), `pad` elsewhere."""
    out = np.full((len(chunks), chunks.members.shape[1], values.shape[1]), pad)
    filled = chunks.members >= 0
    out[filled] = values[chunks.members[filled]]
    return out
