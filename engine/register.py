"""Registration: the similarity that takes the model (photogrammetric) frame to the world (MATHS §11).

Ground control points (GCPs) are picked in the photos; each pick is ray-traced onto the mesh and the hits of
one GCP are averaged (`gcp_from_pixels`). Horn's (1987) closed-form quaternion solution then fits
world = s·R·model + t (`horn_similarity`), with the least-squares (asymmetric) scale, which is Umeyama's
(1991): DECISION of MATHS §11, so it agrees with `skimage.transform.SimilarityTransform`. Exports use
`to_world`, which adds the project's local origin back and applies the registration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from engine.cameras import Camera
from engine.errors import InputError
from engine.raytrace import RayTracer

COLLINEAR = 1e-6
"""GCPs whose second principal spread is below COLLINEAR × the first are collinear: rotation about their line
is undetermined."""


@dataclass(frozen=True)
class Similarity:
    """world = scale · R · model + t. `residuals` (N, 3) world − fitted position of each GCP (m), `errors`
    (N,) their lengths and `rmse` the (weighted) root mean square error."""

    scale: float
    R: np.ndarray
    t: np.ndarray
    residuals: np.ndarray
    errors: np.ndarray
    rmse: float


@dataclass(frozen=True)
class GcpPick:
    """A GCP on the mesh: `point` (3,) the mean of the ray hits `hits` (K, 3) from `images`, and `spread`
    the RMS distance of the hits from their mean (m): large when the picks disagree."""

    point: np.ndarray
    hits: np.ndarray
    images: tuple[str, ...]
    spread: float


def horn_similarity(model_points: np.ndarray, world_points: np.ndarray,
                    weights: np.ndarray | None = None) -> Similarity:
    """The similarity minimising Σ w‖world − (s R model + t)‖² (Horn 1987, MATHS §11).

    model_points, world_points : (N, 3) matching GCPs, N ≥ 3, not collinear.
    weights : (N,) non-negative GCP weights (default equal); they weight the centroids and the cross-covariance.
    """
    a, b, w = _check_gcps(model_points, world_points, weights)
    wn = w / w.sum()
    a_mean, b_mean = wn @ a, wn @ b
    a0, b0 = a - a_mean, b - b_mean
    S = (a0 * w[:, None]).T @ b0  # S_xy = Σ w a'_x b'_y
    N = np.array([
        [S[0, 0] + S[1, 1] + S[2, 2], S[1, 2] - S[2, 1], S[2, 0] - S[0, 2], S[0, 1] - S[1, 0]],
        [S[1, 2] - S[2, 1], S[0, 0] - S[1, 1] - S[2, 2], S[0, 1] + S[1, 0], S[2, 0] + S[0, 2]],
        [S[2, 0] - S[0, 2], S[0, 1] + S[1, 0], -S[0, 0] + S[1, 1] - S[2, 2], S[1, 2] + S[2, 1]],
        [S[0, 1] - S[1, 0], S[2, 0] + S[0, 2], S[1, 2] + S[2, 1], -S[0, 0] - S[1, 1] + S[2, 2]]])
    _, vectors = np.linalg.eigh(N)
    R = _quaternion_matrix(vectors[:, -1])  # the eigenvector of the largest eigenvalue
    rotated = a0 @ R.T
    scale = float((w * np.einsum("ij,ij->i", b0, rotated)).sum() / (w * np.einsum("ij,ij->i", a0, a0)).sum())
    t = b_mean - scale * R @ a_mean
    residuals = b - (scale * a @ R.T + t)
    errors = np.linalg.norm(residuals, axis=1)
    return Similarity(scale, R, t, residuals, errors, float(np.sqrt(wn @ errors**2)))


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    q0, qx, qy, qz = q / np.linalg.norm(q)
    return np.array([
        [q0 * q0 + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - q0 * qz), 2 * (qx * qz + q0 * qy)],
        [2 * (qy * qx + q0 * qz), q0 * q0 - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - q0 * qx)],
        [2 * (qz * qx - q0 * qy), 2 * (qz * qy + q0 * qx), q0 * q0 - qx * qx - qy * qy + qz * qz]])


def _check_gcps(model, world, weights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(model, dtype=float)
    b = np.asarray(world, dtype=float)
    if a.ndim != 2 or a.shape[1:] != (3,) or a.shape != b.shape:
        raise InputError(None, f"GCPs: model points {a.shape} and world points {b.shape} must both be (N, 3)")
    if len(a) < 3:
        raise InputError(None, f"GCPs: {len(a)} given; a similarity needs at least 3 that are not collinear")
    for name, p in (("model", a), ("world", b)):
        bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
        if len(bad):
            raise InputError(None, f"GCP {int(bad[0])}: its {name} coordinates are NaN or infinite")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(a),) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
        raise InputError(None, f"GCP weights: expected {len(a)} finite values ≥ 0, not all zero")
    used = w > 0
    for name, p in (("model", a), ("world", b)):
        spread = np.linalg.svd(p[used] - p[used].mean(axis=0), compute_uv=False)
        if len(spread) < 2 or spread[1] <= COLLINEAR * spread[0]:
            raise InputError(None, f"GCPs: the {int(used.sum())} weighted {name} points are collinear (or "
                                   "coincide); at least 3 GCPs off one line are needed")
    return a, b, w


def apply_similarity(points: np.ndarray, similarity: Similarity) -> np.ndarray:
    """s R p + t for points (..., 3)."""
    p = np.asarray(points, dtype=float)
    return similarity.scale * p @ similarity.R.T + similarity.t


def to_world(points: np.ndarray, origin: np.ndarray, similarity: Similarity | None = None) -> np.ndarray:
    """Local (mesh-frame) points in the export frame: local + origin, then the registration if there is one."""
    model = np.asarray(points, dtype=float) + np.asarray(origin, dtype=float)
    return model if similarity is None else apply_similarity(model, similarity)


def rotate_directions(directions: np.ndarray, similarity: Similarity | None = None) -> np.ndarray:
    """Directions (normals, poles) (..., 3) in the export frame: rotated by the registration, if any."""
    d = np.asarray(directions, dtype=float)
    return d if similarity is None else d @ similarity.R.T


def gcp_from_pixels(observations: Mapping[str, tuple[float, float]], cameras: Mapping[str, Camera],
                    tracer: RayTracer) -> GcpPick:
    """A GCP from its pixel (u, v) in one or more photos: each pixel's ray hits the mesh, hits are averaged.

    cameras : in the frame of `tracer` (the mesh's local frame: `Camera.shifted(origin)`); the point is
    returned in that frame. Raises InputError naming the photo when it is unknown or its ray misses.
    """
    if not observations:
        raise InputError(None, "GCP: no observations; expected {photo: (u, v)} for at least one photo")
    names = tuple(observations)
    origins, directions = [], []
    for name in names:
        if name not in cameras:
            raise InputError(None, f"GCP: photo {name!r} has no camera in the project")
        uv = np.asarray(observations[name], dtype=float).reshape(1, 2)
        camera = cameras[name]
        if not np.all(np.isfinite(uv)):
            raise InputError(None, f"GCP on photo {name!r}: pixel {uv[0].tolist()} is not finite")
        origins.append(camera.centre)
        directions.append(camera.pixel_rays(uv)[0])
    hits = tracer.intersect(np.array(origins), np.array(directions))
    if not hits.hit.all():
        k = int(np.argmin(hits.hit))
        raise InputError(None, f"GCP on photo {names[k]!r}: the ray through pixel {tuple(observations[names[k]])} "
                               "misses the mesh")
    point = hits.points.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((hits.points - point) ** 2, axis=1))))
    return GcpPick(point, hits.points, names, spread)
