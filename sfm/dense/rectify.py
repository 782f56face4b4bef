"""Spherical rectification of a pair of panoramas: rows are epipolar planes, columns the angle from the epipole.

Owns the rectified frame (its −y axis along the baseline), the rectified grid (row ↔ plane angle φ ∈ [−π, π),
column ↔ θ ∈ [0, π]) and the resampling of both panoramas onto it. The rectified frame is an ordinary equirectangular
camera of width ``n_phi`` and height ``n_theta`` (``fullview.sfm.camera``), transposed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fullview.sfm.camera import (bearings_to_pixels, bearings_to_pixels_f32, camera_center, normalize,
                                 pixel_grid_bearings)


@dataclass(kw_only=True)
class RectifiedPair:
    rect_i: np.ndarray  # (n_phi, n_theta[, C]) camera i resampled: row = epipolar plane, column = angle from epipole
    rect_j: np.ndarray  # (n_phi, n_theta[, C]) camera j resampled on the same grid
    R_rect_from_world: np.ndarray  # (3, 3) shared rectified frame; its −y axis is the baseline direction
    R_rect_from_cam_i: np.ndarray  # (3, 3) rotation taking camera i bearings into the rectified frame
    R_rect_from_cam_j: np.ndarray  # (3, 3) rotation taking camera j bearings into the rectified frame
    center_i: np.ndarray  # (3,) camera i centre in world
    center_j: np.ndarray  # (3,) camera j centre in world
    baseline: float  # |c_j − c_i| in world units
    map_i: tuple[np.ndarray, np.ndarray] | None = None  # cv2.remap maps (x, y) rect -> padded source i, if kept
    map_j: tuple[np.ndarray, np.ndarray] | None = None  # cv2.remap maps (x, y) rect -> padded source j, if kept

    @property
    def n_phi(self) -> int:
        """Number of rows (epipolar planes), spanning 2π."""
        return self.rect_i.shape[0]

    @property
    def n_theta(self) -> int:
        """Number of columns (angle from the epipole), spanning π."""
        return self.rect_i.shape[1]


def rectifying_rotation(
    center_i: np.ndarray, center_j: np.ndarray, R_cam_from_world_i: np.ndarray
) -> np.ndarray:
    """``R_rect_from_world`` whose −y axis is the baseline direction (c_j − c_i).

    The remaining freedom (rotation about the baseline) is fixed by keeping the rectified +z axis as close as
    possible to camera i's optical axis (+z), falling back to its x or y axis when that is nearly parallel to the
    baseline. Rows of the result are the rectified axes expressed in world coordinates.
    """
    b = np.asarray(center_j, dtype=np.float64) - np.asarray(center_i, dtype=np.float64)
    norm = np.linalg.norm(b)
    if not np.isfinite(norm) or norm <= 0:
        raise ValueError(f"camera centres coincide (baseline = {norm}); cannot rectify")
    y_axis = -b / norm
    world_from_cam = np.asarray(R_cam_from_world_i, dtype=np.float64).T
    for k in (2, 0, 1):  # candidate forward axes: camera z, x, y (in world)
        z = world_from_cam[:, k] - (world_from_cam[:, k] @ y_axis) * y_axis
        if np.linalg.norm(z) > 0.1:
            break
    z_axis = normalize(z)
    x_axis = np.cross(y_axis, z_axis)
    return np.stack([x_axis, y_axis, z_axis])


def theta_of_columns(n_theta: int) -> np.ndarray:
    """(n_theta,) angle from the epipole at each rectified column centre."""
    return (np.arange(n_theta) + 0.5) * (np.pi / n_theta)


def rectified_grid_bearings(n_phi: int, n_theta: int) -> np.ndarray:
    """(n_phi, n_theta, 3) rectified-frame bearings of the pixel centres of the (transposed) rectified grid."""
    return pixel_grid_bearings(n_phi, n_theta).transpose(1, 0, 2)


def bearings_to_rectified(bearings: np.ndarray, R_rect_from_cam: np.ndarray, n_phi: int, n_theta: int) -> np.ndarray:
    """(..., 3) camera bearings -> (..., 2) continuous rectified pixels (u = column ∝ θ, v = row ∝ φ)"""
    b_rect = np.asarray(bearings, dtype=np.float64) @ np.asarray(R_rect_from_cam, dtype=np.float64).T
    xy = bearings_to_pixels(b_rect, n_phi, n_theta)  # x ∝ φ (longitude), y ∝ θ (colatitude from the −y pole)
    return xy[..., ::-1].copy()


def _pad_equirect(image: np.ndarray, pad: int) -> np.ndarray:
    """Pad an equirectangular image by ``pad`` pixels: across the poles (rows mirrored, shifted by W/2) and wrapped
    in longitude, so that bilinear/bicubic sampling is continuous everywhere on the sphere."""
    width = image.shape[1]
    top = np.roll(image[:pad][::-1], width // 2, axis=1)
    bottom = np.roll(image[-pad:][::-1], width // 2, axis=1)
    tall = np.concatenate([top, image, bottom], axis=0)
    return np.concatenate([tall[:, -pad:], tall, tall[:, :pad]], axis=1)


_PAD = 4  # source padding (pixels) used by the rectification remap; enough for bicubic/Lanczos support


def _rectification_maps(
    R_rect_from_cam: np.ndarray, source_shape: tuple[int, int], grid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps (float32, index space of the padded source) for the rectified grid of one camera."""
    height, width = source_shape
    b_cam = grid @ R_rect_from_cam.astype(np.float32)  # row-vector form of R_rect_from_camᵀ b
    # remap indexes pixel centres at integers (hence −0.5), in the source padded by _PAD pixels
    map_x, map_y = bearings_to_pixels_f32(b_cam, width, height, offset=_PAD - 0.5)
    return np.ascontiguousarray(map_x, np.float32), np.ascontiguousarray(map_y, np.float32)


def rectify_pair(
    image_i: np.ndarray,
    image_j: np.ndarray,
    R_cam_from_world_i: np.ndarray,
    t_cam_from_world_i: np.ndarray,
    R_cam_from_world_j: np.ndarray,
    t_cam_from_world_j: np.ndarray,
    *,
    height: int | None = None,
    width: int | None = None,
    interpolation: int = cv2.INTER_LINEAR,
    keep_maps: bool = False,
) -> RectifiedPair:
    """Resample two equirectangular panoramas onto the shared rectified grid (rows = epipolar planes).

    ``height`` is the number of θ samples (columns of the returned images, spanning [0, π]; default: the source
    height) and ``width`` the number of epipolar planes (rows, spanning 2π; default 2·height, must be even so that
    the plane φ + π is a row too). Pixel (row r, column c) has its centre at θ = π (c + 0.5) / height and
    φ = 2π ((r + 0.5) / width − 0.5). Longitude wrap-around and the poles are handled by padding the sources.
    """
    for name, img in (("image_i", image_i), ("image_j", image_j)):
        if img.ndim not in (2, 3) or img.shape[1] != 2 * img.shape[0]:
            raise ValueError(f"{name} must be a 2:1 equirectangular image, got shape {img.shape}")
    n_theta = int(height or image_i.shape[0])
    n_phi = int(width or 2 * n_theta)
    if n_phi % 2:
        raise ValueError(f"rectified width (number of epipolar planes) must be even, got {n_phi}")
    c_i = camera_center(R_cam_from_world_i, t_cam_from_world_i)
    c_j = camera_center(R_cam_from_world_j, t_cam_from_world_j)
    R_rect_from_world = rectifying_rotation(c_i, c_j, R_cam_from_world_i)
    R_rect_from_cam_i = R_rect_from_world @ np.asarray(R_cam_from_world_i, dtype=np.float64).T
    R_rect_from_cam_j = R_rect_from_world @ np.asarray(R_cam_from_world_j, dtype=np.float64).T
    grid = pixel_grid_bearings(n_phi, n_theta, np.float32).transpose(1, 0, 2)
    rects, maps = [], []
    for img, R in ((image_i, R_rect_from_cam_i), (image_j, R_rect_from_cam_j)):
        map_x, map_y = _rectification_maps(R, img.shape[:2], grid)
        rects.append(cv2.remap(_pad_equirect(img, _PAD), map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE))
        maps.append((map_x, map_y) if keep_maps else None)
    return RectifiedPair(
        rect_i=rects[0],
        rect_j=rects[1],
        R_rect_from_world=R_rect_from_world,
        R_rect_from_cam_i=R_rect_from_cam_i,
        R_rect_from_cam_j=R_rect_from_cam_j,
        center_i=c_i,
        center_j=c_j,
        baseline=float(np.linalg.norm(c_j - c_i)),
        map_i=maps[0],
        map_j=maps[1],
    )
