"""Orientation of planes: poles as axial unit vectors, dip and dip direction (DESIGN.md conventions).

Dip is in [0, 90] degrees and dip direction in [0, 360), both read from the upward normal n:
dip = acos(n_z), dip direction = atan2(n_x, n_y) mod 360 (x east, y north, z up).
"""

from __future__ import annotations

import numpy as np


def dip_dipdir_to_normal(dip: np.ndarray | float, dipdir: np.ndarray | float) -> np.ndarray:
    """Upward unit normals (..., 3) of planes with `dip` and dip direction `dipdir` (degrees, broadcast)."""
    d, a = np.radians(dip), np.radians(dipdir)
    return np.stack(np.broadcast_arrays(np.sin(d) * np.sin(a), np.sin(d) * np.cos(a), np.cos(d)), axis=-1)


def normal_to_dip_dipdir(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dip and dip direction (degrees) of planes with normals `n` (..., 3), any length and either sign.

    Poles are axial, so a downward normal is flipped first; a horizontal one (vertical plane) is kept
    as given, so its dip direction is the direction the normal points.
    """
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(n[..., 2:3] < 0, -n, n)
    dip = np.degrees(np.arccos(np.clip(n[..., 2], -1.0, 1.0)))
    dipdir = np.degrees(np.arctan2(n[..., 0], n[..., 1])) % 360.0
    return dip, np.where(dipdir >= 360.0, 0.0, dipdir)  # -1e-17 % 360 rounds to 360
