"""Rotation matrices from the forms camera files store them in (unit quaternions, printed 3×3 matrices).

Files print rotations with a few significant digits, or in float32; `nearest_rotation` restores exact
orthonormality (which `Camera` checks to 1e-6) but refuses matrices that are not rotations at all, so a
transposed or scaled matrix is reported instead of silently "fixed".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.errors import InputError

ROTATION_TOLERANCE = 1e-4
"""Largest |RᵀR - I| entry accepted as rounding (7-digit printing gives ~1e-7)."""


def quaternion_to_matrix(q: np.ndarray, source: Path, where: str) -> np.ndarray:
    """Rotation matrix of the quaternion (w, x, y, z), Hamilton convention as COLMAP and VisualSFM use."""
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) < 1e-3:
        raise InputError(source, f"{where}: quaternion {q.tolist()} has norm {norm:.6g}, expected 1")
    w, x, y, z = np.asarray(q, dtype=float) / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def nearest_rotation(matrix: np.ndarray, source: Path, where: str) -> np.ndarray:
    """The rotation closest to `matrix` (SVD), or InputError if it is not a rotation up to rounding."""
    m = np.asarray(matrix, dtype=float).reshape(3, 3)
    deviation = np.abs(m.T @ m - np.eye(3)).max()
    if not (deviation < ROTATION_TOLERANCE and np.linalg.det(m) > 0):
        raise InputError(source, f"{where}: not a rotation matrix (|RᵀR - I| = {deviation:.3g}, "
                                 f"det = {np.linalg.det(m):.6g}); expected an orthonormal matrix with det +1")
    u, _, vt = np.linalg.svd(m)
    return u @ vt
