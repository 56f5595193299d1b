"""Fracture intensity maps on the mesh: P21 in a sphere at every vertex, and P21 → P32 (MATHS §8).

P21(x) = Σ length(trace ∩ B(x, r)) / Area(imaged mesh ∩ B(x, r)), at every mesh vertex x, for all traces and
per set. Trace lengths are clipped exactly to the sphere, segment by segment. The area is the true mesh area
in the ball, counting only faces some camera saw (`imaged_faces`): unimaged rock holds no traces and would
bias P21 low.

Area elements (DECISION, MATHS §8 "faces whose centroid is inside; subdivide when faces are large"): the
mesh area is carried by small elements and an element counts when its position is inside the ball.
* Fine meshes (mean edge ≤ r/8): one element per vertex, holding a third of each adjacent imaged face
  (the same partition of the area as face centroids, at half the cost, since a mesh has twice as many
  faces as vertices). About 200 elements per ball at r/8, so the boundary error is ~0.5 %.
* Coarser meshes: every face is cut into n² equal sub-triangles (n = ⌈8·edge/r⌉), one element at each
  sub-triangle centroid.

Speed (tests/benchmarks/bench_intensity.py): vertices and elements are cut into spatial chunks of ≤ 16
points; for each vertex chunk the element chunks within reach are gathered as contiguous slabs and every
vertex–element pair is decided by one batched float32 matrix product (|x − e|² − r² as an inner product of
augmented coordinates, in chunk-relative coordinates so float32 keeps micrometres). Trace segments are
clipped the same way. Batches run on two threads.

P32 = Σ_sets C(κ, θ_m) · P21_set, with C = 1/E_f[sin ρ] for a Fisher set whose mean pole makes θ_m with
the local surface normal (the area-weighted mean normal of the imaged mesh in the ball). The paper calls C
"C13 (Wang 2005)"; θ_m is measured from the surface *normal* (θ_m = 90° is a set perpendicular to the
outcrop, C → 1).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.mesh import Mesh
from engine.raytrace import RayTracer
from engine.traces import Trace3D

ELEMENTS_PER_RADIUS = 8
"""Area elements are at most radius / ELEMENTS_PER_RADIUS apart (module docstring)."""

CHUNK = 16  # points per k-d leaf: the source chunks (area elements, segments)
QUERY_LEAVES = 4  # leaves per query chunk: wider query chunks share the cost of gathering their sources
BATCH_ENTRIES = 1 << 18  # point pairs per batched product: each float32 temporary stays within ~1 MB of cache
_FAR = 1.0e6  # position of padding points, metres: far outside every ball


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

    traces : in the mesh's local frame. Traces of a set not in `sets` count only in the total.
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
    segments = _segments(traces)
    set_ids = sorted({int(s) for s in segments.set_id if s >= 0} if sets is None else {int(s) for s in sets})
    threads = threads or min(2, os.cpu_count() or 1)

    report(progress, 0.0, "area elements")
    n = int(np.ceil(mesh.mean_edge_length * ELEMENTS_PER_RADIUS / radius))
    order, bounds = _kd_runs(mesh.vertices)
    query_runs = (order, np.append(bounds[:-1:QUERY_LEAVES], bounds[-1]))
    if n == 1:  # fine mesh: the area sits at the vertices, one k-d tree serves both sides
        weights = _vertex_elements(mesh, mask)
        vertices = _Chunks.build(mesh.vertices, weights[:, :0], query_runs)
        elements = _Chunks.build(mesh.vertices, weights, (order, bounds))
        spacing = np.sqrt(mesh.face_areas.sum() / len(mesh.vertices))
    else:
        vertices = _Chunks.build(mesh.vertices, np.zeros((len(mesh.vertices), 0)), query_runs)
        positions, weights = _face_elements(mesh, mask, n)
        elements = _Chunks.build(positions, weights, _kd_runs(positions))
        spacing = np.sqrt(mesh.face_areas.mean()) / n
    report(progress, 0.1, "imaged area in the kernel")
    area_normal = _ball_sums(vertices, elements, radius, spacing, threads, progress, (0.1, 0.7))

    ids = np.asarray(set_ids, dtype=np.int64)
    member = np.flatnonzero(np.isin(segments.set_id, ids))
    columns = np.zeros((len(segments.set_id), 1 + len(ids)))
    columns[:, 0] = 1.0  # column 0: all traces
    columns[member, 1 + np.searchsorted(ids, segments.set_id[member])] = 1.0
    report(progress, 0.7, "trace length in the kernel")
    lengths = _clipped_lengths(vertices, segments, columns, radius, threads, progress, (0.7, 1.0))

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


def _check_radius(mesh: Mesh, radius: float) -> float:
    spacing = mesh.mean_edge_length
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


def _vertex_elements(mesh: Mesh, mask: np.ndarray) -> np.ndarray:
    """Per-vertex (V, 4) area, area × unit normal: a third of each adjacent imaged face."""
    area = mesh.face_areas * mask
    per_face = np.column_stack([area, area[:, None] * mesh.face_normals]) / 3
    return np.column_stack([np.bincount(mesh.faces.ravel(), np.repeat(per_face[:, k], 3), minlength=len(mesh.vertices))
                            for k in range(4)])


def _face_elements(mesh: Mesh, mask: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (F·n², 3) and weights (area, area × unit normal) of the n² sub-triangles of each imaged face."""
    tri = mesh.vertices[mesh.faces[mask]]
    area = mesh.face_areas[mask]
    bary = _subtriangle_centroids(n)
    positions = np.einsum("sk,fkj->fsj", bary, tri).reshape(-1, 3)
    per_face = np.column_stack([area, area[:, None] * mesh.face_normals[mask]]) / n**2
    return positions, np.repeat(per_face, len(bary), axis=0)


def _subtriangle_centroids(n: int) -> np.ndarray:
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

    E[sin ρ] = ∫∫ √(1 − (cos θ cos θ_m + sin θ sin θ_m cos φ)²) f(θ) dφ dθ. The colatitude is sampled through
    its inverse CDF, cos θ = 1 + log(1 − v(1 − e^{−2κ}))/κ with v = s², so the density (stable for any κ)
    is absorbed and the √-cusp of sin ρ at the mean pole is smoothed; Gauss–Legendre in s, midpoints in φ.
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
    phi = (np.arange(nodes // 2) + 0.5) * np.pi / (nodes // 2)  # sin ρ is even in φ: [0, π] suffices
    t = theta.reshape(-1)[:, None, None]
    cos_rho = w[:, None] * np.cos(t) + np.sqrt(1.0 - w * w)[:, None] * np.sin(t) * np.cos(phi)
    mean_sin = np.sqrt(np.clip(1.0 - cos_rho**2, 0.0, None)).mean(axis=2) @ dv
    return (1.0 / mean_sin).reshape(theta.shape)


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
                 tolerance: float | None = None) -> np.ndarray:
    """Faces (F,) bool seen by at least one camera: the face centroid projects inside the photo, in front
    of the camera and within its field of view, and the ray from the camera centre reaches it unblocked.

    cameras : in the mesh's local frame (`Camera.shifted(origin)`), like `tracer`.
    tolerance : a surface this close (m) in front of the centroid does not hide it (rays graze the
        neighbouring faces); default half the mean edge length.
    """
    tol = 0.5 * mesh.mean_edge_length if tolerance is None else float(tolerance)
    centroids = mesh.face_centroids
    seen = np.zeros(len(centroids), dtype=bool)
    for camera in cameras.values():
        candidate = np.flatnonzero(~seen & _in_view(camera, centroids))
        if len(candidate):
            seen[candidate] = ~tracer.occluded(camera.centre, centroids[candidate], tolerance=tol)
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

    `members` (C, L) indexes the points (−1 for padding); `slabs` (C + 1, L, 3) their positions (padding,
    and the extra last chunk that pads candidate lists, sit at _FAR); `values` (C + 1, L, k) float32
    per-point values (zero for padding) and `sums` (C, k) their chunk totals; `centre` (C, 3) and `reach`
    (C,) a bounding sphere of each chunk.
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
        slabs = np.full((len(count) + 1, width, 3), _FAR)
        slabs[chunk, slot] = p
        packed = np.zeros((len(count) + 1, width, values.shape[1]), dtype=np.float32)
        packed[chunk, slot] = values[order]
        return cls(members, slabs, packed, packed[:-1].sum(axis=1, dtype=np.float64), centre,
                   np.maximum.reduceat(spread, bounds[:-1]))

    def __len__(self) -> int:
        return len(self.members)


def _kd_runs(points: np.ndarray, leaves: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(order, bounds): the points in k-d tree order, cut into runs of `leaves` consecutive leaves of ≤ CHUNK
    points. Leaves are compact, and consecutive leaves are siblings, so runs are compact too."""
    # median splits give leaves of equal size (little padding) unless coordinates tie, as on grid meshes:
    # a jitter far below any distance that matters breaks the ties
    jitter = np.random.default_rng(0).normal(0.0, 1e-9 * max(float(np.ptp(points)), 1.0), points.shape)
    tree = cKDTree(points + jitter, leafsize=CHUNK)
    bounds = _leaf_bounds(tree)
    return tree.indices, np.append(bounds[:-1:leaves], bounds[-1])


def _leaf_bounds(tree: cKDTree) -> np.ndarray:
    """Start of each leaf in `tree.indices`, and the end: leaves of a k-d tree are compact groups."""
    starts, stack = [], [tree.tree]
    while stack:
        node = stack.pop()
        if node.split_dim == -1:
            starts.append(node.start_idx)
        else:
            stack += (node.lesser, node.greater)
    return np.sort(np.append(starts, tree.n))


@dataclass(frozen=True)
class _Pairs:
    """Chunk pairs within reach: `whole` (Q, S) sparse 0/1, source chunks entirely inside the ball of every
    query point; `indptr`/`ids` (CSR over query chunks) the chunk pairs on the sphere, decided per point."""

    whole: csr_matrix
    indptr: np.ndarray
    ids: np.ndarray


def _chunk_pairs(queries: _Chunks, sources: _Chunks, inner: float, outer: float) -> _Pairs:
    """Source chunks wholly within `inner` of every point of a query chunk, and those partly within `outer`."""
    bound = outer + queries.reach.max() + sources.reach.max()
    pairs = cKDTree(queries.centre).sparse_distance_matrix(cKDTree(sources.centre), bound, output_type="ndarray")
    q, s, d = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"]
    span = queries.reach[q] + sources.reach[s]
    whole = d + span <= inner
    band = (d - span <= outer) & ~whole
    order = np.lexsort((s[band], q[band]))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(q[band], minlength=len(queries)))])
    return _Pairs(csr_matrix((np.ones(int(whole.sum())), (q[whole], s[whole])), shape=(len(queries), len(sources))),
                  indptr, s[band][order])


def _batches(pairs: _Pairs, queries: _Chunks, sources: _Chunks) -> list[tuple[np.ndarray, np.ndarray]]:
    """Query chunks grouped by their number of band source chunks, each batch with a padded (B, S) table of
    source chunks (padding: the sentinel last chunk of `sources`), holding about BATCH_ENTRIES point pairs."""
    pair_entries = queries.members.shape[1] * sources.members.shape[1]
    count = np.diff(pairs.indptr)
    order = np.argsort(-count, kind="stable")  # widest first, so each batch is sized by its first row
    order = order[count[order] > 0]
    out = []
    start = 0
    while start < len(order):
        width = int(count[order[start]])
        rows = order[start:start + max(1, BATCH_ENTRIES // (pair_entries * width))]
        col = np.arange(width)
        fill = col[None, :] < count[rows][:, None]
        table = np.full((len(rows), width), len(sources), dtype=np.int64)
        table[fill] = pairs.ids[(pairs.indptr[rows][:, None] + col[None, :])[fill]]
        out.append((rows, table))
        start += len(rows)
    return out


def _run(jobs: list, work, threads: int, progress: Progress | None, span: tuple[float, float]) -> None:
    lo, hi = span

    def step(item):
        k, job = item
        work(*job)
        report(progress, lo + (hi - lo) * (k + 1) / len(jobs), "intensity")

    if threads > 1 and len(jobs) > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(step, enumerate(jobs)))
    else:
        for item in enumerate(jobs):
            step(item)


def _scatter(out: np.ndarray, queries: _Chunks, chunk_values: np.ndarray) -> None:
    """Add per-chunk values (Q, k) to every member point of each query chunk."""
    filled = queries.members >= 0
    out[queries.members[filled]] += np.broadcast_to(chunk_values[:, None, :], (*queries.members.shape,
                                                                                 chunk_values.shape[1]))[filled]


def _ball_sums(queries: _Chunks, sources: _Chunks, radius: float, ramp: float, threads: int,
               progress: Progress | None, span: tuple[float, float]) -> np.ndarray:
    """Σ weight · values of the source points near each query point (N_q, k).

    The weight of a source at distance d is clip(½ + (r − d)/ramp, 0, 1), with r − d linearised as
    (r² − d²)/2r: an antialiased ball. Counting only d ≤ r makes the area alias with a regular mesh (2 %
    error on a grid at r = 10 spacings); a ramp one element spacing wide brings it to 0.2 %.
    """
    pairs = _chunk_pairs(queries, sources, radius - ramp / 2, radius + ramp / 2)
    k = sources.values.shape[2]
    out = np.zeros((int(queries.members.max()) + 1, k))
    _scatter(out, queries, pairs.whole @ sources.sums)
    scale = -1.0 / (2.0 * radius * ramp)

    def work(rows: np.ndarray, table: np.ndarray) -> None:
        origin = queries.centre[rows]
        x = (queries.slabs[rows] - origin[:, None]).astype(np.float32)
        e = (sources.slabs[table] - origin[:, None, None]).reshape(len(rows), -1, 3)
        xa = np.concatenate([x, (x * x).sum(axis=2, keepdims=True), np.ones_like(x[..., :1])], axis=2)
        ea = np.empty((len(rows), 5, e.shape[1]), dtype=np.float32)  # contiguous: 4× faster products
        ea[:, :3] = -2 * scale * e.transpose(0, 2, 1)
        ea[:, 3] = scale
        ea[:, 4] = ((e * e).sum(axis=2) - radius * radius) * scale + 0.5
        weight = xa @ ea  # ½ + (r² − ‖x − e‖²)/(2 r ramp) for every pair
        np.clip(weight, 0.0, 1.0, out=weight)
        sums = weight @ sources.values[table].reshape(len(rows), -1, k)
        members = queries.members[rows]
        filled = members >= 0
        out[members[filled]] += sums[filled]  # rows are distinct chunks, so no two jobs write one point

    _run(_batches(pairs, queries, sources), work, threads, progress, span)
    return out


def _clipped_lengths(queries: _Chunks, segments: _Segments, columns: np.ndarray, radius: float, threads: int,
                     progress: Progress | None, span: tuple[float, float]) -> np.ndarray:
    """Length of the segments inside the ball of each query point (N_q, k): column j sums the segments
    whose row of `columns` (S, k) is 1 there.

    Exact clipping (MATHS §8): with d = p1 − p0, solve ‖p0 + t d − x‖² = r² and keep t ∈ [0, 1].
    """
    out = np.zeros((int(queries.members.max()) + 1, columns.shape[1]))
    if len(segments.p0) == 0:
        return out
    step = segments.p1 - segments.p0
    length = np.linalg.norm(step, axis=1)
    mid = segments.p0 + 0.5 * step
    chunks = _Chunks.build(mid, columns * length[:, None], _kd_runs(mid), extent=0.5 * length)
    start = _slab_values(chunks, segments.p0, _FAR)
    inv_a = _slab_values(chunks, 1.0 / length[:, None] ** 2, 0.0)[..., 0]
    unit = _slab_values(chunks, step / length[:, None] ** 2, 0.0)  # d / a
    pairs = _chunk_pairs(queries, chunks, radius, radius)
    _scatter(out, queries, pairs.whole @ chunks.sums)
    r2 = radius * radius

    def work(rows: np.ndarray, table: np.ndarray) -> None:
        # With a = d·d, the ball holds t ∈ [t_c − w, t_c + w]: t_c = d·(x − p0)/a, w² = t_c² − (‖p0 − x‖² − r²)/a.
        # Both t_c and the last term are inner products of [x, ‖x‖², 1] with per-segment rows: one product.
        origin = queries.centre[rows]
        x = (queries.slabs[rows] - origin[:, None]).astype(np.float32)
        p0 = (start[table] - origin[:, None, None]).reshape(len(rows), -1)
        p0 = p0.reshape(len(rows), -1, 3)
        ia = inv_a[table].reshape(len(rows), -1)
        u = unit[table].reshape(len(rows), -1, 3)
        m = p0.shape[1]
        rows_ = np.empty((len(rows), 5, 2 * m), dtype=np.float32)
        rows_[:, :3, :m] = u.transpose(0, 2, 1)
        rows_[:, 3, :m] = 0.0
        rows_[:, 4, :m] = -np.einsum("bsk,bsk->bs", u, p0)
        rows_[:, :3, m:] = -2 * (p0 * ia[..., None]).transpose(0, 2, 1)
        rows_[:, 3, m:] = ia
        rows_[:, 4, m:] = ((p0 * p0).sum(axis=2) - r2) * ia
        xa = np.concatenate([x, (x * x).sum(axis=2, keepdims=True), np.ones_like(x[..., :1])], axis=2)
        both = xa @ rows_
        centre, w = both[..., :m], both[..., m:]
        np.negative(w, out=w)
        w += centre * centre
        np.maximum(w, 0.0, out=w)  # w² < 0: the line misses the ball (padding segments: t_c = 0, w = 0)
        np.sqrt(w, out=w)
        hi = np.minimum(centre + w, 1.0)
        centre -= w
        np.maximum(centre, 0.0, out=centre)
        hi -= centre
        np.maximum(hi, 0.0, out=hi)
        sums = hi @ chunks.values[table].reshape(len(rows), -1, columns.shape[1])
        members = queries.members[rows]
        filled = members >= 0
        out[members[filled]] += sums[filled]

    _run(_batches(pairs, queries, chunks), work, threads, progress, span)
    return out


def _slab_values(chunks: _Chunks, values: np.ndarray, pad: float) -> np.ndarray:
    """Per-point `values` (N, k) laid out like the chunks' slabs (C + 1, width, k), `pad` elsewhere."""
    out = np.full((len(chunks) + 1, chunks.members.shape[1], values.shape[1]), pad)
    filled = chunks.members >= 0
    out[:-1][filled] = values[chunks.members[filled]]
    return out
