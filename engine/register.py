"""Registration: the similarity that takes the model (photogrammetric) frame to the world (MATHS §11).

Ground control points (GCPs) are picked in the photos; each pick is ray-traced onto the mesh and the hits of
one GCP are averaged (`gcp_from_pixels`). Horn's (1987) closed-form quaternion solution then fits
world = s·R·model + t (`horn_similarity`), with the least-squares (asymmetric) scale, which is Umeyama's
(1991): DECISION of MATHS §11, so it agrees with `skimage.transform.SimilarityTransform`. `register_gcps`
does both for a project's GCPs (`read_gcps_csv` reads them from a CSV) and returns the `Registration` that
`tracemap register` stores. Exports use `to_world`, which adds the project's local origin back and applies
the registration.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.cameras import Camera
from engine.csvfile import csv_number, read_csv
from engine.errors import InputError
from engine.raytrace import RayTracer

COLLINEAR = 1e-6
"""GCPs whose second principal spread is below COLLINEAR × the first are collinear: rotation about their line
is undetermined."""
MAX_COORDINATE = 1e9
"""Largest |x|, |y|, |z| of a GCP (m): geocentric coordinates stay under 7e6 m and projected ones under 1e7 m,
so a larger value is a typo or a wrong unit; the bound also keeps the fit's sums of squares far from overflow,
which would make any GCPs look collinear."""


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
        far = np.flatnonzero(np.abs(p).max(axis=1) > MAX_COORDINATE)
        if len(far):
            raise InputError(None, f"GCP {int(far[0])}: its {name} coordinates {p[far[0]].tolist()} are beyond "
                                   f"±{MAX_COORDINATE:g} m, expected a place on Earth")
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(a),) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
        raise InputError(None, f"GCP weights: expected {len(a)} finite values ≥ 0, not all zero")
    used = w > 0
    for name, p in (("model", a), ("world", b)):
        if collinear(p[used]):
            raise InputError(None, f"GCPs: the {int(used.sum())} weighted {name} points are collinear (or "
                                   "coincide); at least 3 GCPs off one line are needed")
    return a, b, w


def collinear(points: np.ndarray) -> bool:
    """True when points (N, 3) lie on one line or coincide (or are fewer than 3): the rotation about that
    line is then undetermined."""
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) < 3:
        return True
    spread = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    return bool(spread[1] <= COLLINEAR * spread[0])


def apply_similarity(points: np.ndarray, similarity: Similarity) -> np.ndarray:
    """s R p + t for points (..., 3)."""
    p = np.asarray(points, dtype=float)
    return similarity.scale * p @ similarity.R.T + similarity.t


def to_world(points: np.ndarray, origin: np.ndarray, similarity: Similarity | None = None) -> np.ndarray:
    """Local (mesh-frame) points in the export frame: local + origin, then the registration if there is one."""
    model = np.asarray(points, dtype=float) + np.asarray(origin, dtype=float)
    return model if similarity is None else apply_similarity(model, similarity)


def length_scale(similarity: Similarity | None = None) -> float:
    """How much longer a length is in the export frame than on the mesh: the registration's scale, or 1.
    Areas scale by its square; intensities (P21, P32: length per area or volume) by its inverse."""
    return 1.0 if similarity is None else float(similarity.scale)


def rotate_directions(directions: np.ndarray, similarity: Similarity | None = None) -> np.ndarray:
    """Directions (normals, poles) (..., 3) in the export frame: rotated by the registration, if any."""
    d = np.asarray(directions, dtype=float)
    return d if similarity is None else d @ similarity.R.T


def model_directions(directions: np.ndarray, similarity: Similarity | None = None) -> np.ndarray:
    """Directions (..., 3) given in the export frame, back in the mesh's: the inverse of `rotate_directions`."""
    d = np.asarray(directions, dtype=float)
    return d if similarity is None else d @ similarity.R


def gcp_from_pixels(observations: Mapping[str, tuple[float, float]], cameras: Mapping[str, Camera],
                    tracer: RayTracer, *, name: str = "") -> GcpPick:
    """A GCP from its pixel (u, v) in one or more photos: each pixel's ray hits the mesh, hits are averaged.

    cameras : in the frame of `tracer` (the mesh's local frame: `Camera.shifted(origin)`); the point is
    returned in that frame. Raises InputError naming the GCP (`name`) and the photo when the photo is
    unknown or its ray misses.
    """
    gcp = f"GCP {name!r}" if name else "GCP"
    if not observations:
        raise InputError(None, f"{gcp}: no observations; expected {{photo: (u, v)}} for at least one photo")
    names = tuple(observations)
    origins, directions = [], []
    for photo in names:
        if photo not in cameras:
            raise InputError(None, f"{gcp}: photo {photo!r} has no camera in the project")
        uv = np.asarray(observations[photo], dtype=float).reshape(1, 2)
        camera = cameras[photo]
        if not np.all(np.isfinite(uv)):
            raise InputError(None, f"{gcp} on photo {photo!r}: pixel {uv[0].tolist()} is not finite")
        origins.append(camera.centre)
        directions.append(camera.pixel_rays(uv)[0])
    hits = tracer.intersect(np.array(origins), np.array(directions))
    if not hits.hit.all():
        k = int(np.argmin(hits.hit))
        u, v = np.asarray(observations[names[k]], dtype=float).reshape(2)
        raise InputError(None, f"{gcp} on photo {names[k]!r}: the ray through pixel ({u:.1f}, {v:.1f}) misses the mesh")
    point = hits.points.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((hits.points - point) ** 2, axis=1))))
    return GcpPick(point, hits.points, names, spread)



@dataclass(frozen=True)
class Registration:
    """The result of `register_gcps`: per GCP its `names`, `model` point (N, 3: mesh-file frame, local +
    origin), `world` point (N, 3), ray-hit `spread` (N,) (m) and photos (`images`); and the `similarity`
    world ≈ s R model + t with its residuals. What `tracemap register` stores and exports apply."""

    names: tuple[str, ...]
    model: np.ndarray
    world: np.ndarray
    spread: np.ndarray
    images: tuple[tuple[str, ...], ...]
    similarity: Similarity

    def to_dict(self) -> dict:
        """JSON-ready form (the project's "registration" result)."""
        sim = self.similarity
        return {"scale": sim.scale, "R": sim.R.tolist(), "t": sim.t.tolist(), "rmse": sim.rmse,
                "gcps": [{"name": n, "model": m.tolist(), "world": w.tolist(), "residual": r.tolist(),
                          "error": float(e), "spread": float(s), "images": list(i)}
                         for n, m, w, r, e, s, i in zip(self.names, self.model, self.world, sim.residuals,
                                                        sim.errors, self.spread, self.images)]}

    @classmethod
    def from_dict(cls, d: Mapping) -> Registration:
        gcps = d["gcps"]

        def column(key: str) -> np.ndarray:
            return np.array([g[key] for g in gcps], dtype=float).reshape(len(gcps), -1)

        sim = Similarity(float(d["scale"]), np.array(d["R"], dtype=float), np.array(d["t"], dtype=float),
                         column("residual"), column("error")[:, 0], float(d["rmse"]))
        return cls(tuple(g["name"] for g in gcps), column("model"), column("world"), column("spread")[:, 0],
                   tuple(tuple(g["images"]) for g in gcps), sim)


def register_gcps(gcps: Mapping[str, Mapping], cameras: Mapping[str, Camera], tracer: RayTracer,
                  origin: np.ndarray) -> Registration:
    """Ray-trace each GCP's pixels (`gcp_from_pixels`) and fit the similarity to their world points (Horn).

    gcps : name → {"world": [x, y, z], "observations": {photo: [u, v]}} (`Project.gcps()`).
    cameras, tracer : in the mesh's local frame; origin : the local origin, added back to the model points.
    """
    names = tuple(gcps)
    if len(names) < 3:
        raise InputError(None, f"GCPs: {len(names)} given ({', '.join(names) or 'none'}); a registration needs "
                               "at least 3 that are not on one line")
    picks = [gcp_from_pixels(gcps[name]["observations"], cameras, tracer, name=name) for name in names]
    model = np.array([p.point for p in picks]) + np.asarray(origin, dtype=float)
    world = np.array([gcps[n]["world"] for n in names], dtype=float)
    return Registration(names, model, world, np.array([p.spread for p in picks]),
                        tuple(p.images for p in picks), horn_similarity(model, world))


GCP_CSV_COLUMNS = ("name", "x", "y", "z", "image", "u", "v")


def read_gcps_csv(path: str | Path, cameras: Mapping[str, Camera]) -> dict[str, dict]:
    """GCPs from a CSV with columns name,x,y,z,image,u,v: one row per observation (several rows of one GCP
    for several photos, each repeating its world x, y, z). Returns the `Project.gcps()` form.

    Raises InputError naming the row when a value is missing or malformed, a photo unknown, a pixel off the
    photo or a GCP's world point differs between its rows; and when fewer than 3 GCPs off one line remain.
    """
    path = Path(path)
    rows = read_csv(path, GCP_CSV_COLUMNS)
    gcps: dict[str, dict] = {}
    first_row: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):
        name, image = (row["name"] or "").strip(), (row["image"] or "").strip()
        if not name:
            raise InputError(path, f"line {line}: the GCP has no name")
        world = [_coordinate(path, line, c, row[c]) for c in ("x", "y", "z")]
        uv = [csv_number(path, line, c, row[c]) for c in ("u", "v")]
        if image not in cameras:
            raise InputError(path, f"line {line}: image {image!r} is not in the project")
        camera = cameras[image]
        if not (-0.5 <= uv[0] <= camera.width - 0.5 and -0.5 <= uv[1] <= camera.height - 0.5):
            raise InputError(path, f"line {line}: pixel ({uv[0]:g}, {uv[1]:g}) is outside the "
                                   f"{camera.width}×{camera.height} photo {image!r}")
        gcp = gcps.setdefault(name, {"world": world, "observations": {}})
        first_row.setdefault(name, line)
        if not np.allclose(gcp["world"], world, rtol=0, atol=1e-9):
            raise InputError(path, f"line {line}: GCP {name!r} has world point {world}, but line "
                                   f"{first_row[name]} gave {gcp['world']}")
        if image in gcp["observations"]:
            raise InputError(path, f"line {line}: GCP {name!r} is already picked on photo {image!r}")
        gcp["observations"][image] = uv
    if len(gcps) < 3 or collinear(np.array([g["world"] for g in gcps.values()])):
        listed = ", ".join(f"{n} (line {r})" for n, r in first_row.items()) or "none"
        raise InputError(path, f"{len(gcps)} GCPs: {listed}; a registration needs at least 3 GCPs whose world "
                               "points are not on one line")
    return gcps


def _coordinate(path: Path, line: int, column: str, text: str | None) -> float:
    """A GCP's world coordinate in a CSV cell: a finite number within ±MAX_COORDINATE."""
    value = csv_number(path, line, column, text)
    if abs(value) > MAX_COORDINATE:
        raise InputError(path, f"line {line}: column {column} is {text!r}, expected a coordinate within "
                               f"±{MAX_COORDINATE:g} m (no place on Earth is farther)")
    return value
