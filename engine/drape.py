"""A photo draped on the mesh as a projective texture: the paper's Fig. 5A, where a photo's 2D traces lie on
the 3D traces extracted from them.

Every mesh vertex gets the texture coordinate of its pixel in the photo (`Camera.project`, lens distortion
included). Only the faces the camera saw are textured: the face centroid is in front of the camera, in its
field of view and not hidden by other rock (a ray from the camera centre, as `engine.intensity.imaged_faces`),
and all three vertices project inside the photo, so no face is stretched over the photo's edge. The others
keep the mesh colours.

Texture coordinates follow DESIGN.md's pixel convention, pixel (0, 0) being the centre of the top-left
pixel, and VTK's texture origin at the bottom-left: s = (u + ½)/W, t = 1 − (v + ½)/H. They are exact at the
vertices; inside a face the renderer interpolates them linearly on the face rather than projectively, an
error of a small fraction of a pixel while faces are small compared with their distance to the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from engine.cameras import Camera
from engine.errors import InputError, Progress, report
from engine.intensity import imaged_faces
from engine.mesh import Mesh
from engine.raytrace import RayTracer


@dataclass(frozen=True, eq=False)
class Drape:
    """A photo ready to drape (compared by identity, so a renderer can cache its texture).

    image : the photo's name. texture : (h, w, 3) uint8 RGB, the photo itself or, beyond the graphics
    card's texture size, a reduction by `scale` (texture pixels per photo pixel). uv : (V, 2) float32
    texture coordinates of every mesh vertex (0 at vertices of no seen face). seen : (F,) bool, the
    textured faces.
    """

    image: str
    texture: np.ndarray
    uv: np.ndarray
    seen: np.ndarray
    scale: float = 1.0


def texture_coordinates(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(N, 2) texture coordinates (s, t) of points in the photo of `camera`; NaN behind it."""
    uv = camera.project(points)
    return np.column_stack([(uv[:, 0] + 0.5) / camera.width, 1.0 - (uv[:, 1] + 0.5) / camera.height])


def drape_photo(mesh: Mesh, camera: Camera, photo: np.ndarray, tracer: RayTracer, *,
                max_size: int | None = None, progress: Progress | None = None) -> Drape:
    """Drape `photo` (H, W, 3 uint8 RGB, the photo of `camera`) on `mesh` (see module docstring).

    camera and tracer : in the mesh's local frame. max_size : the largest texture side the renderer
    takes (None: no limit); a larger photo is reduced to fit.
    """
    photo = np.asarray(photo)
    if photo.dtype != np.uint8 or photo.shape != (camera.height, camera.width, 3):
        raise InputError(None, f"photo of {camera.name!r}: expected {camera.width}×{camera.height} 8-bit RGB "
                               f"pixels, got {photo.dtype} {photo.shape}")
    report(progress, 0.0, f"faces seen from {camera.name}")
    seen = imaged_faces(mesh, {camera.name: camera}, tracer)
    report(progress, 0.6, "texture coordinates")
    st = texture_coordinates(camera, mesh.vertices)
    with np.errstate(invalid="ignore"):
        inside = np.all((st >= 0.0) & (st <= 1.0), axis=1)  # s, t in [0, 1] ⇔ inside the photo's outer edge
    seen &= inside[mesh.faces].all(axis=1)
    uv = np.zeros(st.shape, np.float32)
    uv[inside] = st[inside]
    report(progress, 0.8, "texture")
    texture, scale = fit_texture(photo, max_size)
    report(progress, 1.0, "done")
    return Drape(camera.name, texture, uv, seen, scale)


def fit_texture(photo: np.ndarray, max_size: int | None) -> tuple[np.ndarray, float]:
    """The photo, or its area-average reduction whose longer side is `max_size`; and the scale applied.

    Texture coordinates are fractions of the image, so they hold for the reduction too.
    """
    h, w = photo.shape[:2]
    if max_size is None or max(h, w) <= max_size:
        return photo, 1.0
    scale = max_size / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(photo, size, interpolation=cv2.INTER_AREA), scale
