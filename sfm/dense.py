"""Dense reconstruction from pairs of equirectangular panoramas by spherical rectification.

The report's method, done carefully:

1. **Rectify** (``rectify_pair``): both cameras are rotated into one shared frame whose pole is the baseline
   direction ``e = (c_j − c_i) / |c_j − c_i|``. In that frame every epipolar plane contains the pole, so epipolar
   great circles are meridians. Each panorama is resampled to a rectified equirectangular grid in which the
   meridians are image columns, and the result is transposed so that **rows are epipolar planes** (row ↔ plane
   angle φ ∈ [−π, π)) and **columns are the angle θ from the epipole** (column ↔ θ ∈ [0, π], linear).
   Concretely the rectified frame has its −y axis along ``e``, so it is an ordinary ``fullview.sfm.camera``
   equirectangular camera (of width ``n_phi`` and height ``n_theta``) whose top pole looks at camera j; with
   continuous pixel coordinates (u, v) = (column, row) of the transposed image:
   ``θ = π u / n_theta`` and ``φ = 2π (v / n_phi − 0.5)``.
2. **Disparity** (``compute_disparity``): a scene point P seen at ``θ_i`` from camera i is seen at
   ``θ_j = θ_i + d`` from camera j, where ``d = ∠O_i P O_j ≥ 0`` (triangle angle sum, see
   ``depth_from_disparity``). OpenCV's StereoSGBM expects the match of left-image column x at ``x − d`` in the right
   image, so the rectified images are flipped along columns (θ → π − θ) before matching i (left) against
   j (right); the right-to-left disparity for the consistency check is then SGBM(left = j, right = i) unflipped.
3. **Depth** (``depth_from_disparity``): law of sines, ``|O_i P| = T sin(θ_j) / sin(d)``.
4. **Back to the panorama** (``range_map_to_panorama``) and **fusion** (``fuse_depth_maps``, ``clean_point_cloud``).

Ranges (distances from the camera centre) rather than z-depths are used throughout; invalid ranges are NaN.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from fullview.sfm.camera import bearings_to_pixels, normalize, pixel_grid_bearings, pixels_to_bearings

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------- rectification
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


def camera_center(R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray) -> np.ndarray:
    """Camera centre ``C = −Rᵀ t``."""
    return -np.asarray(R_cam_from_world, dtype=np.float64).T @ np.asarray(t_cam_from_world, dtype=np.float64)


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


def _grid_bearings_f32(width: int, height: int) -> np.ndarray:
    """float32 (height, width, 3) pixel-centre bearings (same as ``pixel_grid_bearings``, separable and fast)."""
    lon = (2 * np.pi * ((np.arange(width) + 0.5) / width - 0.5)).astype(np.float32)
    lat = (np.pi * (0.5 - (np.arange(height) + 0.5) / height)).astype(np.float32)
    out = np.empty((height, width, 3), np.float32)
    out[..., 0] = np.cos(lat)[:, None] * np.sin(lon)[None, :]
    out[..., 1] = -np.sin(lat)[:, None]
    out[..., 2] = np.cos(lat)[:, None] * np.cos(lon)[None, :]
    return out


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
    lon = np.arctan2(b_cam[..., 0], b_cam[..., 2])
    lat = np.arctan2(-b_cam[..., 1], np.hypot(b_cam[..., 0], b_cam[..., 2]))  # well conditioned at the poles
    map_x = lon * np.float32(width / (2 * np.pi)) + np.float32(width / 2 - 0.5 + _PAD)
    map_y = lat * np.float32(-height / np.pi) + np.float32(height / 2 - 0.5 + _PAD)
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
    grid = _grid_bearings_f32(n_phi, n_theta).transpose(1, 0, 2)
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


# --------------------------------------------------------------------------------------------- disparity
@dataclass(kw_only=True)
class SgbmParams:
    block_size: int = 5  # matching window side (odd)
    p1_factor: int = 8  # P1 = p1_factor · block_size² (small disparity change penalty)
    p2_factor: int = 32  # P2 = p2_factor · block_size² (large disparity change penalty)
    uniqueness_ratio: int = 10  # percent margin of the best cost over the second best
    speckle_window_size: int = 100  # max size of disparity blobs considered speckles (0 disables)
    speckle_range: int = 2  # max disparity variation (pixels) within a connected component
    pre_filter_cap: int = 63  # clip of the x-derivative prefilter
    mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY  # OpenCV SGBM mode (3WAY: fast, multithreaded)
    min_texture_std: float = 2.0  # grey-level std over the texture window below which a pixel is untextured
    texture_window: int = 9  # side of the window for the texture test (odd)


@dataclass(kw_only=True)
class DisparityResult:
    disparity_i: np.ndarray  # (n_phi, n_theta) float32 angular disparity d (radians) on camera i's grid; NaN invalid
    disparity_j: np.ndarray  # (n_phi, n_theta) float32 angular disparity d (radians) on camera j's grid; NaN invalid
    valid_i: np.ndarray  # (n_phi, n_theta) bool: LR-consistent, textured, away from the epipoles
    valid_j: np.ndarray  # (n_phi, n_theta) bool: LR-consistent, textured, away from the epipoles
    num_disparities: int  # SGBM search range used (pixels, multiple of 16)
    pixel_angle: float  # radians per rectified column (π / n_theta)


def theta_of_columns(n_theta: int) -> np.ndarray:
    """(n_theta,) angle from the epipole at each rectified column centre."""
    return (np.arange(n_theta) + 0.5) * (np.pi / n_theta)


def disparity_search_range(n_theta: int, min_depth_ratio: float, min_disparity: int = 0) -> int:
    """SGBM ``numDisparities`` (multiple of 16) covering points down to ``min_depth_ratio`` · baseline.

    A point at distance r ≥ T from the baseline subtends at most asin(T / r) (law of sines), which is converted to
    rectified pixels (π / n_theta radians each) and rounded up.
    """
    if min_depth_ratio <= 0:
        raise ValueError(f"min_depth_ratio must be > 0, got {min_depth_ratio}")
    max_angle = math.asin(min(1.0, 1.0 / min_depth_ratio))
    pixels = max_angle / (math.pi / n_theta) - min_disparity + 1
    return int(16 * math.ceil(max(pixels, 1) / 16))


def _pad_theta(image: np.ndarray, before: int, after: int) -> np.ndarray:
    """Extend rectified rows beyond θ = 0 / π using spherical continuity (exact, no resampling).

    Column −1−k of row r is column k of row r + n_phi/2 (the meridian continues across the pole into the plane
    φ + π); likewise column n_theta + k is column n_theta − 1 − k of that row.
    """
    half = image.shape[0] // 2
    parts = []
    if before:
        parts.append(np.roll(image[:, :before][:, ::-1], -half, axis=0))
    parts.append(image)
    if after:
        parts.append(np.roll(image[:, image.shape[1] - after :][:, ::-1], -half, axis=0))
    return np.ascontiguousarray(np.concatenate(parts, axis=1))


def _to_gray_u8(image: np.ndarray) -> np.ndarray:
    """uint8 single-channel version of an image (BGR/RGB treated alike)."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.shape[2] == 3 else image[..., 0]
    if image.dtype != np.uint8:
        scale = 255.0 if image.dtype.kind == "f" and image.max() <= 1.0 else 255.0 / max(float(image.max()), 1.0)
        image = np.clip(image.astype(np.float32) * scale, 0, 255).astype(np.uint8)
    return image


def _textured(gray: np.ndarray, params: SgbmParams) -> np.ndarray:
    """Pixels whose local grey-level standard deviation (after a σ = 1 px blur) reaches ``params.min_texture_std``
    (SGBM output on untextured areas is an extrapolation that can pass the left-right check)."""
    if params.min_texture_std <= 0:
        return np.ones(gray.shape, dtype=bool)
    size = (params.texture_window, params.texture_window)
    g = cv2.GaussianBlur(gray.astype(np.float32), (5, 5), 1.0)  # sensor noise is not texture
    mean = cv2.boxFilter(g, -1, size, borderType=cv2.BORDER_REFLECT)
    mean_sq = cv2.boxFilter(g * g, -1, size, borderType=cv2.BORDER_REFLECT)
    return mean_sq - mean * mean >= params.min_texture_std**2


def _make_sgbm(num_disparities: int, min_disparity: int, channels: int, p: SgbmParams) -> cv2.StereoSGBM:
    area = channels * p.block_size**2
    return cv2.StereoSGBM.create(
        minDisparity=min_disparity,
        numDisparities=num_disparities,
        blockSize=p.block_size,
        P1=p.p1_factor * area,
        P2=p.p2_factor * area,
        disp12MaxDiff=-1,  # our own LR check below
        preFilterCap=p.pre_filter_cap,
        uniquenessRatio=p.uniqueness_ratio,
        speckleWindowSize=p.speckle_window_size,
        speckleRange=p.speckle_range,
        mode=p.mode,
    )


def _sgbm_pixels(matcher: cv2.StereoSGBM, left: np.ndarray, right: np.ndarray, min_disparity: int) -> np.ndarray:
    """Float disparity in pixels (NaN invalid) from OpenCV's 1/16-pixel fixed-point output."""
    raw = matcher.compute(left, right)
    disp = raw.astype(np.float32) / cv2.StereoMatcher_DISP_SCALE
    disp[raw < min_disparity * cv2.StereoMatcher_DISP_SCALE] = np.nan
    return disp


def _lr_consistent(disp: np.ndarray, other: np.ndarray, sign: int, max_diff: float) -> np.ndarray:
    """Pixels whose match (column + sign·disp) in the other view carries a disparity within ``max_diff``."""
    n_theta = disp.shape[1]
    cols = np.arange(n_theta, dtype=np.float32)[None, :] + sign * np.nan_to_num(disp, nan=-1e6)
    idx = np.rint(cols)
    inside = (idx >= 0) & (idx < n_theta)
    matched = np.take_along_axis(other, np.clip(idx, 0, n_theta - 1).astype(np.intp), axis=1)
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(matched - disp) <= max_diff)


def compute_disparity(
    rect_i: np.ndarray,
    rect_j: np.ndarray,
    *,
    min_depth_ratio: float = 2.0,
    min_epipole_angle_deg: float = 8.0,
    lr_max_diff_px: float = 1.0,
    min_disparity: int = 0,
    params: SgbmParams | None = None,
) -> DisparityResult:
    """Angular disparity ``d = θ_j − θ_i`` on both rectified grids with SGBM and a left-right check.

    - ``min_depth_ratio``: nearest plausible scene distance divided by the baseline; sets the search range
      (``disparity_search_range``).
    - Direction: θ_j = θ_i + d with d ≥ 0, i.e. a point sits at a *larger* column in j than in i. SGBM finds the
      left pixel x at x − d in the right image, so i → j is computed on column-flipped images (left = flip(i),
      right = flip(j)) and j → i on the unflipped pair (left = j, right = i).
    - Both images are extended past θ = 0 and θ = π by ``_pad_theta`` so that SGBM's blind border (the first
      ``num_disparities`` columns of the left image) falls outside the real grid.
    - Pixels are invalid where SGBM found no match, where the two directions disagree by more than
      ``lr_max_diff_px``, closer than ``min_epipole_angle_deg`` to the epipole or the anti-epipole, or untextured
      (``SgbmParams.min_texture_std``).
    """
    params = params or SgbmParams()
    if rect_i.shape != rect_j.shape:
        raise ValueError(f"rectified images differ in shape: {rect_i.shape} vs {rect_j.shape}")
    n_phi, n_theta = rect_i.shape[:2]
    if n_phi % 2:
        raise ValueError(f"number of rectified rows must be even, got {n_phi}")
    num = disparity_search_range(n_theta, min_depth_ratio, min_disparity)
    pad = min(num + max(min_disparity, 0) + params.block_size, n_theta)
    gray_i, gray_j = _to_gray_u8(rect_i), _to_gray_u8(rect_j)
    matcher = _make_sgbm(num, min_disparity, 1, params)
    t0 = time.perf_counter()
    left = np.ascontiguousarray(_pad_theta(gray_i, 0, pad)[:, ::-1])
    right = np.ascontiguousarray(_pad_theta(gray_j, 0, pad)[:, ::-1])
    disp_i = _sgbm_pixels(matcher, left, right, min_disparity)[:, ::-1][:, :n_theta]
    disp_j = _sgbm_pixels(matcher, _pad_theta(gray_j, pad, 0), _pad_theta(gray_i, pad, 0), min_disparity)[:, pad:]
    log.debug("SGBM %dx%d, %d disparities: %.2fs", n_phi, n_theta, num, time.perf_counter() - t0)
    ok_i = _lr_consistent(disp_i, disp_j, +1, lr_max_diff_px)
    ok_j = _lr_consistent(disp_j, disp_i, -1, lr_max_diff_px)
    theta = theta_of_columns(n_theta)
    margin = np.radians(min_epipole_angle_deg)
    away = ((theta >= margin) & (theta <= np.pi - margin))[None, :]
    pixel_angle = np.pi / n_theta
    valid_i = ok_i & away & (disp_i > 0) & _textured(gray_i, params)
    valid_j = ok_j & away & (disp_j > 0) & _textured(gray_j, params)
    return DisparityResult(
        disparity_i=np.where(valid_i, disp_i * np.float32(pixel_angle), np.nan).astype(np.float32),
        disparity_j=np.where(valid_j, disp_j * np.float32(pixel_angle), np.nan).astype(np.float32),
        valid_i=valid_i,
        valid_j=valid_j,
        num_disparities=num,
        pixel_angle=pixel_angle,
    )


# --------------------------------------------------------------------------------------------- depth
def depth_from_disparity(theta_i: np.ndarray, disparity_angle: np.ndarray, baseline: float) -> np.ndarray:
    """Range ``|O_i P|`` from the angle θ_i (at O_i, from the epipole) and the angular disparity d (radians).

    Derivation (the report's law of sines). In the triangle O_i O_j P with |O_i O_j| = T:
    - the angle at O_i is θ_i (between the baseline direction O_i→O_j and the ray O_i→P);
    - camera j sees P at θ_j from the same direction O_i→O_j, so the interior angle at O_j is π − θ_j;
    - the angle at P is d = ∠O_i P O_j. Angle sum: θ_i + (π − θ_j) + d = π  ⇒  θ_j = θ_i + d.
    The law of sines gives |O_i P| / sin(π − θ_j) = T / sin(d), hence ``|O_i P| = T sin(θ_i + d) / sin(d)``.
    (By symmetry, |O_j P| = T sin(θ_i) / sin(d) = depth_from_disparity(π − θ_j, d, T).)
    Non-positive disparities give NaN.
    """
    theta_i = np.asarray(theta_i, dtype=np.float64)
    d = np.asarray(disparity_angle, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = baseline * np.sin(theta_i + d) / np.sin(d)
        return np.where((d > 0) & (r > 0), r, np.nan)


def rectified_range_maps(disparity: DisparityResult, baseline: float) -> tuple[np.ndarray, np.ndarray]:
    """(range_i, range_j): float32 ranges on the rectified grids of cameras i and j (NaN invalid)."""
    theta = theta_of_columns(disparity.disparity_i.shape[1])[None, :]
    range_i = depth_from_disparity(theta, disparity.disparity_i, baseline)
    range_j = depth_from_disparity(np.pi - theta, disparity.disparity_j, baseline)
    return range_i.astype(np.float32), range_j.astype(np.float32)


# --------------------------------------------------------------------------------------------- back to the panorama
def _sample_edge_aware(
    values: np.ndarray, u: np.ndarray, v: np.ndarray, edge_tol: float, *, wrap_rows: bool
) -> np.ndarray:
    """Bilinear sample of a range map at continuous pixel coordinates (u = column, v = row).

    ``wrap_rows``: rows are periodic and columns clamped (rectified grid); otherwise columns are periodic and rows
    clamped (equirectangular panorama). Where one of the four neighbours is invalid (NaN) or they span a relative
    range larger than ``edge_tol`` (a depth edge), the nearest neighbour is taken instead, so values are never
    blended across discontinuities.
    """
    n_rows, n_cols = values.shape
    x = np.asarray(u, dtype=np.float32) - np.float32(0.5)
    y = np.asarray(v, dtype=np.float32) - np.float32(0.5)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    xi, yi = x0.astype(np.int64), y0.astype(np.int64)
    if wrap_rows:
        c0, c1 = np.clip(xi, 0, n_cols - 1), np.clip(xi + 1, 0, n_cols - 1)
        r0, r1 = np.mod(yi, n_rows), np.mod(yi + 1, n_rows)
    else:
        c0, c1 = np.mod(xi, n_cols), np.mod(xi + 1, n_cols)
        r0, r1 = np.clip(yi, 0, n_rows - 1), np.clip(yi + 1, 0, n_rows - 1)
    flat = np.ascontiguousarray(values, dtype=np.float32).ravel()
    r0 *= n_cols
    r1 *= n_cols
    v00, v01, v10, v11 = flat.take(r0 + c0), flat.take(r0 + c1), flat.take(r1 + c0), flat.take(r1 + c1)
    lo = np.fmin(np.fmin(v00, v01), np.fmin(v10, v11))
    hi = np.fmax(np.fmax(v00, v01), np.fmax(v10, v11))
    top = v00 + (v01 - v00) * fx
    bilinear = top + (v10 + (v11 - v10) * fx - top) * fy
    right, below = fx >= 0.5, fy >= 0.5
    near = np.where(below, np.where(right, v11, v10), np.where(right, v01, v00))
    with np.errstate(invalid="ignore"):
        smooth = np.isfinite(bilinear) & (hi - lo <= np.float32(edge_tol) * lo)
    return np.where(smooth, bilinear, near)


def range_map_to_panorama(
    range_rect: np.ndarray,
    R_rect_from_cam: np.ndarray,
    *,
    width: int,
    height: int | None = None,
    interpolation: str = "edge_aware",
    edge_tol: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a rectified range map into the camera's own equirectangular frame.

    ``range_rect`` is (n_phi, n_theta) on the rectified grid of that camera (NaN invalid); ``R_rect_from_cam`` is
    the camera's ``RectifiedPair.R_rect_from_cam_*``. Output size ``width`` × ``height`` (default width / 2).
    ``interpolation``: ``"nearest"`` or ``"edge_aware"`` (bilinear except across depth edges / invalid pixels; see
    ``_sample_edge_aware``). Returns (range float32 (H, W) with NaN invalid, valid bool (H, W)).
    """
    if interpolation not in ("nearest", "edge_aware"):
        raise ValueError(f"interpolation must be 'nearest' or 'edge_aware', got {interpolation!r}")
    height = int(height or width // 2)
    n_phi, n_theta = range_rect.shape
    b_rect = _grid_bearings_f32(width, height) @ np.asarray(R_rect_from_cam, np.float32).T
    u = np.arctan2(np.hypot(b_rect[..., 0], b_rect[..., 2]), -b_rect[..., 1]) * np.float32(n_theta / np.pi)
    v = np.arctan2(b_rect[..., 0], b_rect[..., 2]) * np.float32(n_phi / (2 * np.pi)) + np.float32(n_phi / 2)
    values = np.asarray(range_rect, dtype=np.float32)
    if interpolation == "nearest":
        col = np.clip(np.floor(u), 0, n_theta - 1).astype(np.intp)
        row = np.mod(np.floor(v), n_phi).astype(np.intp)
        out = values[row, col]
    else:
        out = _sample_edge_aware(values, u, v, edge_tol, wrap_rows=True)
    valid = np.isfinite(out) & (out > 0)
    return np.where(valid, out, np.nan).astype(np.float32), valid


# --------------------------------------------------------------------------------------------- one pair end to end
@dataclass(kw_only=True)
class PairDepth:
    range_i: np.ndarray  # (H, W) float32 range map of camera i in its panorama frame, NaN invalid
    range_j: np.ndarray  # (H, W) float32 range map of camera j in its panorama frame, NaN invalid
    valid_i: np.ndarray  # (H, W) bool validity of range_i
    valid_j: np.ndarray  # (H, W) bool validity of range_j
    timings: dict[str, float] = field(default_factory=dict)  # seconds per step


def densify_pair(
    image_i: np.ndarray,
    image_j: np.ndarray,
    R_cam_from_world_i: np.ndarray,
    t_cam_from_world_i: np.ndarray,
    R_cam_from_world_j: np.ndarray,
    t_cam_from_world_j: np.ndarray,
    *,
    rect_height: int | None = None,
    out_width: int | None = None,
    min_depth_ratio: float = 2.0,
    min_epipole_angle_deg: float = 8.0,
    params: SgbmParams | None = None,
) -> PairDepth:
    """Rectify, match (with LR check), triangulate and map back to both panoramas (size ``out_width`` ×
    ``out_width/2``, default the source size)."""
    t = [time.perf_counter()]
    pair = rectify_pair(
        image_i, image_j, R_cam_from_world_i, t_cam_from_world_i, R_cam_from_world_j, t_cam_from_world_j,
        height=rect_height,
    )
    t.append(time.perf_counter())
    disp = compute_disparity(
        pair.rect_i, pair.rect_j, min_depth_ratio=min_depth_ratio, min_epipole_angle_deg=min_epipole_angle_deg,
        params=params,
    )
    t.append(time.perf_counter())
    range_i, range_j = rectified_range_maps(disp, pair.baseline)
    width = int(out_width or image_i.shape[1])
    pano_i, valid_i = range_map_to_panorama(range_i, pair.R_rect_from_cam_i, width=width)
    pano_j, valid_j = range_map_to_panorama(range_j, pair.R_rect_from_cam_j, width=width)
    t.append(time.perf_counter())
    timings = {"rectify": t[1] - t[0], "disparity": t[2] - t[1], "depth_and_backmap": t[3] - t[2]}
    log.debug("densify_pair timings: %s", timings)
    return PairDepth(range_i=pano_i, range_j=pano_j, valid_i=valid_i, valid_j=valid_j, timings=timings)


# --------------------------------------------------------------------------------------------- fusion
def _pixel_centers(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of a strided pixel grid."""
    rows, cols = np.mgrid[0:height:stride, 0:width:stride]
    return rows.ravel(), cols.ravel()


def _valid_range(values: np.ndarray) -> np.ndarray:
    """Finite and positive."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(values) & (values > 0)


def _sample_colors(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N, 3) uint8 colours of ``image`` at range-map pixels (rows, cols) of a map of ``shape`` (nearest)."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[..., :3]
    if img.dtype != np.uint8:
        img = np.clip(img * (255.0 if img.dtype.kind == "f" and img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    y = np.minimum(((rows + 0.5) * img.shape[0] / shape[0]).astype(np.intp), img.shape[0] - 1)
    x = np.minimum(((cols + 0.5) * img.shape[1] / shape[1]).astype(np.intp), img.shape[1] - 1)
    return img[y, x]


def _support(
    points: np.ndarray, range_map: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
    rel_tol: float,
) -> np.ndarray:
    """Whether each world point agrees (relative range difference ≤ rel_tol) with another view's range map, read
    with the edge-aware bilinear sampler at the point's projection."""
    x_cam = points @ R_cam_from_world.T + t_cam_from_world
    r_pred = np.linalg.norm(x_cam, axis=1)
    height, width = range_map.shape
    pix = bearings_to_pixels(x_cam, width, height)
    observed = _sample_edge_aware(range_map, pix[:, 0], pix[:, 1], max(2 * rel_tol, 0.02), wrap_rows=False)
    with np.errstate(invalid="ignore"):
        return _valid_range(observed) & (np.abs(observed - r_pred) <= rel_tol * r_pred)


def fuse_depth_maps(
    range_maps: Sequence[np.ndarray],
    images: Sequence[np.ndarray],
    R_cam_from_world: np.ndarray,
    t_cam_from_world: np.ndarray,
    *,
    min_consistent: int = 1,
    rel_tol: float = 0.02,
    stride: int = 1,
    neighbors: Sequence[Sequence[int]] | None = None,
    views: Sequence[int] | None = None,
    return_sources: bool = False,
):
    """Back-project per-panorama range maps to world points and keep the multi-view consistent ones.

    - ``range_maps[k]``: (H_k, W_k) range (distance from the centre) in camera k's equirectangular frame; NaN or
      ≤ 0 is invalid. ``images[k]``: that panorama (any size; grey or 3-channel, colours keep its channel order).
    - A point from view i is kept if at least ``min_consistent`` other views (``neighbors[i]``, default all) have a
      valid range at its projection within ``rel_tol`` (relative) of its predicted range. Views with no valid range
      there neither support nor veto it.
    - ``stride`` subsamples the pixels of every map.
    - ``views``: back-project only these views (default all); every map still supports the others' points. Fusing
      one view at a time bounds the memory to one view's points.
    Returns (points (N, 3) float64, colours (N, 3) uint8[, source view index (N,) int]).
    """
    R_all = np.asarray(R_cam_from_world, dtype=np.float64)
    t_all = np.asarray(t_cam_from_world, dtype=np.float64)
    n_views = len(range_maps)
    if len(images) != n_views or len(R_all) != n_views or len(t_all) != n_views:
        raise ValueError(
            f"range_maps ({n_views}), images ({len(images)}), R_cam_from_world ({len(R_all)}) and "
            f"t_cam_from_world ({len(t_all)}) must have the same length"
        )
    maps = [np.asarray(m, dtype=np.float32) for m in range_maps]
    all_pts, all_cols, all_src = [], [], []
    for i in range(n_views) if views is None else views:
        rmap = maps[i]
        rows, cols = _pixel_centers(*rmap.shape, stride)
        ranges = rmap[rows, cols]
        keep = _valid_range(ranges)
        rows, cols, ranges = rows[keep], cols[keep], ranges[keep]
        pix = np.stack([cols + 0.5, rows + 0.5], axis=1)
        x_cam = pixels_to_bearings(pix, rmap.shape[1], rmap.shape[0]) * ranges[:, None]
        pts = (x_cam - t_all[i]) @ R_all[i]  # world = Rᵀ (x_cam − t)
        count = np.zeros(len(pts), dtype=np.int32)
        others = neighbors[i] if neighbors is not None else range(n_views)
        for k in others:
            if k != i:
                count += _support(pts, maps[k], R_all[k], t_all[k], rel_tol)
        ok = count >= min_consistent
        log.debug("fusion: view %d keeps %d / %d points", i, ok.sum(), len(ok))
        all_pts.append(pts[ok])
        all_cols.append(_sample_colors(images[i], rows[ok], cols[ok], rmap.shape))
        all_src.append(np.full(ok.sum(), i, dtype=np.int64))
    points = np.concatenate(all_pts) if all_pts else np.zeros((0, 3))
    colors = np.concatenate(all_cols) if all_cols else np.zeros((0, 3), np.uint8)
    if return_sources:
        return points, colors, (np.concatenate(all_src) if all_src else np.zeros(0, np.int64))
    return points, colors


def clean_point_cloud(
    points: np.ndarray,
    colors: np.ndarray,
    *,
    voxel_size: float,
    nb_neighbors: int = 20,
    std_ratio: float = 2.0,
    normal_radius: float | None = None,
    viewpoint: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel down-sampling, statistical outlier removal and normal estimation with open3d.

    ``colors`` are uint8 (N, 3) (returned as uint8) or floats in [0, 1] (returned as float64). Normals are estimated
    from neighbours within ``normal_radius`` (default 3 · voxel_size, at most 30) and, if ``viewpoint`` (3,) is given,
    oriented towards it. Returns (points (M, 3), colours (M, 3), normals (M, 3)).
    """
    import open3d as o3d

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = np.asarray(colors)
    if len(cols) != len(pts):
        raise ValueError(f"colors has {len(cols)} rows but points has {len(pts)}")
    is_u8 = cols.dtype == np.uint8
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(cols.astype(np.float64) / (255.0 if is_u8 else 1.0))
    if voxel_size > 0:
        pcd = pcd.voxel_down_sample(voxel_size)
    if nb_neighbors > 0 and len(pcd.points) > nb_neighbors:
        pcd, _ = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    radius = normal_radius or 3.0 * voxel_size
    if len(pcd.points) >= 3:
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30) if radius > 0 else (
            o3d.geometry.KDTreeSearchParamKNN(30)
        )
        pcd.estimate_normals(search)
        if viewpoint is not None:
            pcd.orient_normals_towards_camera_location(np.asarray(viewpoint, dtype=np.float64))
    out_cols = np.asarray(pcd.colors)
    out_cols = np.clip(np.rint(out_cols * 255), 0, 255).astype(np.uint8) if is_u8 else out_cols
    normals = np.asarray(pcd.normals) if pcd.has_normals() else np.zeros((len(pcd.points), 3))
    log.info("clean_point_cloud: %d -> %d points", len(pts), len(pcd.points))
    return np.asarray(pcd.points), out_cols, normals


# --------------------------------------------------------------------------------------------- pair selection
def select_stereo_pairs(
    centers: np.ndarray,
    inlier_counts: np.ndarray,
    *,
    k: int,
    min_triangulation_angle_deg: float,
    max_triangulation_angle_deg: float = 60.0,
    target_triangulation_angle_deg: float = 10.0,
    min_inliers: int = 50,
    scene_depths: np.ndarray | None = None,
) -> np.ndarray:
    """Union over cameras of each camera's ``k`` best dense-stereo partners, as (M, 2) pairs (i < j), sorted.

    The triangulation angle of a pair is ``2·atan(B / (2·depth))`` with B the baseline and depth the mean of the two
    cameras' ``scene_depths`` (e.g. median sparse-point distance; default: the median camera-to-camera distance, a
    rough scene scale). Candidates need ``min_inliers`` matches and an angle within [min, max]; they are ranked by
    ``inliers · min(1, angle / target_angle)``: inlier count, discounted for baselines shorter than the target.
    """
    centers = np.asarray(centers, dtype=np.float64)
    inliers = np.asarray(inlier_counts, dtype=np.float64)
    n = len(centers)
    if inliers.shape != (n, n):
        raise ValueError(f"inlier_counts must be ({n}, {n}) for {n} centers, got {inliers.shape}")
    inliers = np.maximum(inliers, inliers.T)  # symmetric
    baseline = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    if scene_depths is None:
        off = baseline[~np.eye(n, dtype=bool)]
        scene_depths = np.full(n, np.median(off) if off.size else 1.0)
    depth = 0.5 * (np.asarray(scene_depths, dtype=np.float64)[:, None] + np.asarray(scene_depths)[None])
    angle = np.degrees(2 * np.arctan2(baseline, 2 * depth))
    ok = (
        (inliers >= min_inliers)
        & (angle >= min_triangulation_angle_deg)
        & (angle <= max_triangulation_angle_deg)
        & ~np.eye(n, dtype=bool)
    )
    score = np.where(ok, inliers * np.minimum(1.0, angle / target_triangulation_angle_deg), -np.inf)
    best = np.argsort(-score, axis=1, kind="stable")[:, :k]
    i_idx = np.repeat(np.arange(n), best.shape[1])
    j_idx = best.ravel()
    good = np.isfinite(score[i_idx, j_idx])
    pairs = np.sort(np.stack([i_idx[good], j_idx[good]], axis=1), axis=1)
    return np.unique(pairs, axis=0) if len(pairs) else np.zeros((0, 2), dtype=np.intp)
