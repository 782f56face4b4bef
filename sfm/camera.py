"""Spherical camera model: equirectangular pixel <-> unit bearing.

Convention (identical to COLMAP's EQUIRECTANGULAR model):
- continuous pixel coordinates, (0, 0) is the top-left corner of the top-left pixel, so the
  centre of pixel (i, j) is (j + 0.5, i + 0.5);
- lon = 2*pi*(x / W - 0.5), lat = pi*(0.5 - y / H);
- bearing = (cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon)) in the camera frame,
  x right, y down, z forward (the image centre looks along +z).

Poses follow COLMAP's naming: ``R_cam_from_world`` maps world vectors into the camera frame and
``x_cam = R_cam_from_world @ x_world + t_cam_from_world``; the centre is ``-R.T @ t``.
"""

from __future__ import annotations

import numpy as np


def pixels_to_bearings(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) equirectangular pixel coordinates -> (N, 3) unit bearings in the camera frame."""
    pixels = np.asarray(pixels, dtype=np.float64)
    lon = 2.0 * np.pi * (pixels[..., 0] / width - 0.5)
    lat = np.pi * (0.5 - pixels[..., 1] / height)
    cos_lat = np.cos(lat)
    return np.stack([cos_lat * np.sin(lon), -np.sin(lat), cos_lat * np.cos(lon)], axis=-1)


def bearings_to_pixels(bearings: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 3) bearings (any norm > 0) -> (N, 2) equirectangular pixel coordinates."""
    bearings = np.asarray(bearings, dtype=np.float64)
    norm = np.linalg.norm(bearings, axis=-1)
    lon = np.arctan2(bearings[..., 0], bearings[..., 2])
    lat = np.arcsin(np.clip(-bearings[..., 1] / norm, -1.0, 1.0))
    x = (lon / (2.0 * np.pi) + 0.5) * width
    y = (0.5 - lat / np.pi) * height
    return np.stack([np.mod(x, width), y], axis=-1)


def bearings_to_lonlat(bearings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Longitude and latitude (radians) of bearings."""
    bearings = np.asarray(bearings, dtype=np.float64)
    norm = np.linalg.norm(bearings, axis=-1)
    return np.arctan2(bearings[..., 0], bearings[..., 2]), np.arcsin(np.clip(-bearings[..., 1] / norm, -1, 1))


def pixel_grid_bearings(width: int, height: int) -> np.ndarray:
    """(H, W, 3) bearings of every pixel centre of a width x height panorama."""
    xs = np.arange(width) + 0.5
    ys = np.arange(height) + 0.5
    grid = np.stack(np.meshgrid(xs, ys), axis=-1)
    return pixels_to_bearings(grid, width, height)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix [v]x, for (3,) or (N, 3) input."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def normalize(v: np.ndarray, axis: int = -1) -> np.ndarray:
    """Unit vectors along ``axis`` (zero vectors stay zero)."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.where(n > 0, n, 1.0)
