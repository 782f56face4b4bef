"""Angles between rotations and between directions, accurate near 0° and 180°."""

from __future__ import annotations

import numpy as np


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray | None = None) -> np.ndarray:
    """Angle (degrees) of ``R_a @ R_bᵀ`` (of ``R_a`` alone when ``R_b`` is None), batched over leading axes."""
    M = np.asarray(R_a, dtype=np.float64)
    if R_b is not None:
        M = M @ np.swapaxes(np.asarray(R_b, dtype=np.float64), -1, -2)
    vee = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    sin2 = np.linalg.norm(vee, axis=-1)  # 2 sin(angle)
    cos2 = np.trace(M, axis1=-2, axis2=-1) - 1.0  # 2 cos(angle)
    return np.degrees(np.arctan2(sin2, cos2))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) between vectors (any norm > 0), batched over leading axes."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))
