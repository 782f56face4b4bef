"""Spherical camera model: equirectangular pixel <-> lon/lat <-> unit bearing, and small pose formulas.

Every equirectangular formula of the package lives here (the float32 variants too, so that fast paths elsewhere do
not re-derive them).

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


# --------------------------------------------------------------------------------------------- pixel <-> lon / lat
def pixel_longitude(x, width: int):
    """Longitude (radians) of continuous pixel column coordinates ``x``."""
    return 2.0 * np.pi * (x / width - 0.5)


def pixel_latitude(y, height: int):
    """Latitude (radians) of continuous pixel row coordinates ``y``."""
    return np.pi * (0.5 - y / height)


def pixel_grid_lonlat(width: int, height: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """(W,) longitudes of the pixel-centre columns and (H,) latitudes of the pixel-centre rows, computed in float64 and
    cast to ``dtype`` (a float32 grid is then evaluated separably by the callers, for speed)."""
    lon = pixel_longitude(np.arange(width) + 0.5, width).astype(dtype)
    lat = pixel_latitude(np.arange(height) + 0.5, height).astype(dtype)
    return lon, lat


# --------------------------------------------------------------------------------------------- pixel <-> bearing
def pixels_to_bearings(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) equirectangular pixel coordinates -> (N, 3) unit bearings in the camera frame."""
    pixels = np.asarray(pixels, dtype=np.float64)
    lon = pixel_longitude(pixels[..., 0], width)
    lat = pixel_latitude(pixels[..., 1], height)
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


def rays_to_remap_coords(rays: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap source coordinates (integer = pixel centre, x wrapped into [0, W)) of (..., 3) rays of any length,
    in the rays' dtype: where each ray meets a width x height panorama."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    lon = np.arctan2(x, z)  # unnormalised rays: the angles need no unit length
    lat = np.arctan2(-y, np.hypot(x, z))
    # continuous pixel coordinates, then remap's convention: minus 0.5
    map_x = np.mod((lon / (2 * np.pi) + 0.5) * width, width) - 0.5
    map_y = (0.5 - lat / np.pi) * height - 0.5
    return map_x, map_y


def pixel_grid_bearings(width: int, height: int, dtype=np.float64) -> np.ndarray:
    """(H, W, 3) bearings of every pixel centre of a width x height panorama.

    float64: per pixel with ``pixels_to_bearings``. float32: evaluated separably (trigonometry per row and per
    column only), the fast path of the resampling code; equal to the float64 grid up to float32 rounding.
    """
    if np.dtype(dtype) == np.float64:
        xs = np.arange(width) + 0.5
        ys = np.arange(height) + 0.5
        grid = np.stack(np.meshgrid(xs, ys), axis=-1)
        return pixels_to_bearings(grid, width, height)
    lon, lat = pixel_grid_lonlat(width, height, dtype)
    out = np.empty((height, width, 3), dtype)
    out[..., 0] = np.cos(lat)[:, None] * np.sin(lon)[None, :]
    out[..., 1] = -np.sin(lat)[:, None]
    out[..., 2] = np.cos(lat)[:, None] * np.cos(lon)[None, :]
    return out


def bearings_to_pixels_f32(bearings: np.ndarray, width: int, height: int, *, offset: float = 0.0,
                           from_pole: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """float32 pixel coordinates ``(x + offset, y + offset)`` of (..., 3) float32 bearings, for remap tables.

    Unlike ``bearings_to_pixels`` x is not wrapped into [0, W) and the bearings' dtype is kept. The polar angle is
    taken with arctan2, well conditioned everywhere: from the latitude ``atan2(−y, hypot(x, z))`` or, with
    ``from_pole``, from the colatitude ``atan2(hypot(x, z), −y)`` (angle from the top pole, most accurate near it).
    """
    b = bearings
    lon = np.arctan2(b[..., 0], b[..., 2])
    # one float32 constant per axis (offset folded in): the same roundings as the original remap-table code
    x = lon * np.float32(width / (2 * np.pi)) + np.float32(width / 2 + offset)
    if from_pole:
        colat = np.arctan2(np.hypot(b[..., 0], b[..., 2]), -b[..., 1])
        y = colat * np.float32(height / np.pi)
        return x, (y + np.float32(offset) if offset else y)
    lat = np.arctan2(-b[..., 1], np.hypot(b[..., 0], b[..., 2]))
    return x, lat * np.float32(-height / np.pi) + np.float32(height / 2 + offset)


# --------------------------------------------------------------------------------------------- vectors and poses
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


def tangent_basis(z: np.ndarray) -> np.ndarray:
    """(K, 2, 3) orthonormal rows spanning the plane orthogonal to each unit vector z (K, 3)."""
    helper = np.where((np.abs(z[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    e1 = normalize(np.cross(z, helper))
    return np.stack([e1, np.cross(z, e1)], axis=1)


def camera_center(R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centre ``C = −Rᵀ t``: (3, 3), (3,) -> (3,), or batched (N, 3, 3), (N, 3) -> (N, 3)."""
    return -np.einsum("...ji,...j->...i", np.asarray(R_cam_from_world, dtype=np.float64),
                      np.asarray(t_cam_from_world, dtype=np.float64))


def camera_up(R_cam_from_world: np.ndarray) -> np.ndarray:
    """Mean world direction of the cameras' up axis (−y in the camera frame), unit length (zero if undefined).

    Panoramas are taken roughly level, so this is the scene's up direction."""
    up = -np.asarray(R_cam_from_world)[:, 1, :].sum(0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.zeros(3)
