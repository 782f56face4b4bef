"""Pose algebra of the registration: relative poses from absolute ones, rotations about the vertical (yaw).

The world y axis points down, as in the camera frame, so a level camera's ``R_cam_from_world`` is ``R_y(θ)``.
"""

from __future__ import annotations

import numpy as np

from fullview.sfm.camera import normalize


def relative_from_absolute(
    R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, i, j
) -> tuple[np.ndarray, np.ndarray]:
    """``(R_j_from_i, t_j_from_i / |t_j_from_i|)`` of images i, j (ints or index arrays)."""
    R = np.asarray(R_cam_from_world, dtype=np.float64)
    t = np.asarray(t_cam_from_world, dtype=np.float64)
    R_rel = R[j] @ np.swapaxes(R[i], -1, -2)
    t_rel = t[j] - np.einsum("...ab,...b->...a", R_rel, t[i])
    return R_rel, normalize(t_rel)


def yaw_rotation(theta: np.ndarray) -> np.ndarray:
    """``R_y(θ)`` (rotation about the y axis, world y pointing down), batched: (...,) -> (..., 3, 3)."""
    theta = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(theta.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 2], R[..., 1, 1], R[..., 2, 0], R[..., 2, 2] = c, s, 1.0, -s, c
    return R


def rotation_yaw(R: np.ndarray) -> np.ndarray:
    """Angle of the rotation about y closest to ``R`` (exact for ``yaw_rotation`` output), batched."""
    R = np.asarray(R, dtype=np.float64)
    return np.arctan2(R[..., 0, 2] - R[..., 2, 0], R[..., 0, 0] + R[..., 2, 2])
