"""Small analytic scenes with exact answers, shared by the tests."""

from __future__ import annotations

import numpy as np

from engine.cameras import Camera


def grid_wall(width: float = 10.0, height: float = 6.0, step: float = 0.5, *, hole: tuple | None = None,
              offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A vertical wall in the plane y = offset_y, x ∈ [0, width], z ∈ [0, height], facing −y (south).

    `hole` = (x0, x1, z0, z1) removes the faces whose centroid lies inside that rectangle.
    """
    xs = np.arange(0.0, width + step / 2, step)
    zs = np.arange(0.0, height + step / 2, step)
    X, Z = np.meshgrid(xs, zs)
    vertices = np.column_stack([X.ravel(), np.zeros(X.size), Z.ravel()]) + np.asarray(offset)
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    # vertex order gives normals toward −y, out of the wall
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    if hole is not None:
        centroid = vertices[faces].mean(axis=1) - np.asarray(offset)
        x0, x1, z0, z1 = hole
        inside = (centroid[:, 0] > x0) & (centroid[:, 0] < x1) & (centroid[:, 2] > z0) & (centroid[:, 2] < z1)
        faces = faces[~inside]
    return vertices, faces


def facing_camera(name: str = "cam", *, centre=(5.0, -8.0, 3.0), width: int = 800, height: int = 600,
                  f: float = 700.0, distortion=(), offset=(0.0, 0.0, 0.0)) -> Camera:
    """A camera at `centre` (+offset) looking north (+y) at the wall, image x east, image y down."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # rows: cam x=E, cam y=-up, cam z=N
    C = np.asarray(centre, dtype=float) + np.asarray(offset, dtype=float)
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(name, width, height, K, np.asarray(distortion, dtype=float), R, -R @ C)


def wall_point(camera: Camera, uv: np.ndarray, wall_y: float = 0.0) -> np.ndarray:
    """Exact intersection of the pixel rays with the plane y = wall_y."""
    d = camera.pixel_rays(uv)
    c = camera.centre
    t = (wall_y - c[1]) / d[:, 1]
    return c + t[:, None] * d


def stepped_wall(step_x: float = 4.0, depth: float = 0.6, width: float = 10.0, height: float = 3.0,
                 spacing: float = 0.1, offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A south-facing wall (y = 0 for x < step_x, y = −depth beyond) whose step is an exposed fracture face
    in the plane x = step_x, facing −x; every part meshed at about `spacing` m, normals out of the rock."""
    corners = np.array([[0.0, 0.0], [step_x, 0.0], [step_x, -depth], [width, -depth]])
    profile = [corners[:1]]
    for a, b in zip(corners[:-1], corners[1:]):
        n = max(int(round(np.linalg.norm(b - a) / spacing)), 1)
        profile.append(a + np.outer(np.arange(1, n + 1) / n, b - a))
    profile = np.vstack(profile)
    zs = np.linspace(0.0, height, int(round(height / spacing)) + 1)
    P, Z = np.repeat(profile[None], len(zs), axis=0), np.repeat(zs[:, None], len(profile), axis=1)
    vertices = np.column_stack([P[..., 0].ravel(), P[..., 1].ravel(), Z.ravel()]) + np.asarray(offset)
    idx = np.arange(Z.size).reshape(Z.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return vertices, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def wavy_wall_with_post(spacing: float = 0.02, surface=None) -> tuple[np.ndarray, np.ndarray, Camera]:
    """A rough south-facing wall (y = WAVY(x, z), or `surface`(x, z), x ∈ [0, 6], z ∈ [0, 4]) with a post
    standing 1–1.2 m in front of it (x ∈ [2.8, 3.3]), and a camera 8 m out that sees the wall except the
    strip behind the post (about x ∈ [2.77, 3.36]); one mesh of both, every `spacing` m on the wall."""
    surface = wavy if surface is None else surface
    xs, zs = np.arange(0.0, 6.0 + spacing / 2, spacing), np.arange(0.0, 4.0 + spacing / 2, spacing)
    X, Z = np.meshgrid(xs, zs)
    vertices = np.column_stack([X.ravel(), surface(X.ravel(), Z.ravel()), Z.ravel()])
    idx = np.arange(X.size).reshape(X.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    lo, hi = np.array([2.8, -1.2, -1.0]), np.array([3.3, -1.0, 5.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    box = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                    [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    vertices = np.vstack([vertices, corners])
    faces = np.vstack([faces, box + len(vertices) - 8])
    return vertices, faces, facing_camera(centre=(3.0, -8.0, 2.0), width=1600, height=1200, f=1400.0)


def wavy(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The rough wall's y (m) at (x, z)."""
    return 0.08 * np.sin(2 * np.pi * x / 1.3) + 0.06 * np.sin(2 * np.pi * z / 0.9 + 1.0)


FOLD = 3.06  # m: the folded wall's edge, behind the post


def folded(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """A wall of two flat faces (y, m, at (x, z)): y = 0 up to x = FOLD, then receding at 40° (a bench edge
    seen end on). Fractures cut each face in a straight trace, bending at the fold."""
    return np.where(x > FOLD, (x - FOLD) * np.tan(np.radians(40.0)), 0.0) + 0.0 * z


def plane_on_wavy_wall(point, normal, x: np.ndarray, surface=None) -> np.ndarray:
    """Exact points (N, 3) where the plane through `point` with `normal` cuts the wavy wall (or `surface`),
    at each x (fixed-point iteration on z; it contracts while the plane is steeper than the wall's slopes)."""
    surface = wavy if surface is None else surface
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    p = np.asarray(point, dtype=float)
    z = np.full(len(x), p[2])
    for _ in range(60):
        z = p[2] - (n[0] * (x - p[0]) + n[1] * (surface(x, z) - p[1])) / n[2]
    return np.column_stack([x, surface(x, z), z])
