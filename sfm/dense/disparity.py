"""Angular disparity on the rectified grid: OpenCV SGBM with its left-right check, carried over to the other view.

A point seen at ``θ_i`` from camera i is seen at ``θ_j = θ_i + d`` (``d ≥ 0``) from camera j; SGBM expects the match
of a left column x at ``x − d``, hence the column flips in ``compute_disparity``. Rows are extended past the poles
(``pad_theta``) so that SGBM's blind border falls outside the grid; untextured pixels are rejected.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import cv2
import numpy as np

from fullview.sfm.options import DensifyOptions

from fullview.sfm.dense.rectify import theta_of_columns

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class SgbmParams:
    block_size: int = DensifyOptions.block_size  # matching window side (odd); default from the settings
    p1_factor: int = 8  # P1 = p1_factor · block_size² (small disparity change penalty)
    p2_factor: int = 32  # P2 = p2_factor · block_size² (large disparity change penalty)
    uniqueness_ratio: int = 10  # percent margin of the best cost over the second best
    speckle_window_size: int = 100  # max size of disparity blobs considered speckles (0 disables)
    speckle_range: int = 2  # max disparity variation (pixels) within a connected component
    pre_filter_cap: int = 63  # clip of the x-derivative prefilter
    mode: int = cv2.STEREO_SGBM_MODE_SGBM_3WAY  # OpenCV SGBM mode (3WAY: fast, multithreaded)
    min_texture_std: float = DensifyOptions.min_texture_std  # grey-level std over the texture window below which a
    # pixel is untextured; default from the settings
    texture_window: int = 9  # side of the window for the texture test (odd)


@dataclass(kw_only=True)
class DisparityResult:
    disparity_i: np.ndarray  # (n_phi, n_theta) float32 angular disparity d (radians) on camera i's grid; NaN invalid
    disparity_j: np.ndarray  # (n_phi, n_theta) float32 angular disparity d (radians) on camera j's grid; NaN invalid
    valid_i: np.ndarray  # (n_phi, n_theta) bool: LR-consistent, textured, away from the epipoles
    valid_j: np.ndarray  # (n_phi, n_theta) bool: LR-consistent, textured, away from the epipoles
    num_disparities: int  # SGBM search range used (pixels, multiple of 16)
    pixel_angle: float  # radians per rectified column (π / n_theta)


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


def pad_theta(image: np.ndarray, before: int, after: int) -> np.ndarray:
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


def _make_sgbm(num_disparities: int, min_disparity: int, channels: int, p: SgbmParams,
               lr_max_diff_px: float) -> cv2.StereoSGBM:
    area = channels * p.block_size**2
    return cv2.StereoSGBM.create(
        minDisparity=min_disparity,
        numDisparities=num_disparities,
        blockSize=p.block_size,
        P1=p.p1_factor * area,
        P2=p.p2_factor * area,
        disp12MaxDiff=max(int(round(lr_max_diff_px)), 0),  # SGBM's own left-right check, from its cost volume
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


def _forward_warp(disp: np.ndarray) -> np.ndarray:
    """Camera j's disparity map from camera i's: a point at column x of i lies at column x + d of j (θ_j = θ_i + d),
    the nearest point (largest disparity) winning where several land on one pixel; NaN where none lands (occluded
    from i)."""
    n_phi, n_theta = disp.shape
    flat = np.flatnonzero(np.isfinite(disp))  # flat indices, not np.nonzero's (rows, cols): a quarter less CPU
    d = disp.ravel()[flat]
    cols = flat % n_theta
    target = np.rint(cols + d).astype(np.intp)
    inside = (target >= 0) & (target < n_theta)
    out = np.full(n_phi * n_theta, -np.inf, np.float32)
    np.maximum.at(out, (flat - cols + target)[inside], d[inside])
    return np.where(np.isfinite(out), out, np.nan).reshape(n_phi, n_theta)


def compute_disparity(
    rect_i: np.ndarray,
    rect_j: np.ndarray,
    *,
    min_depth_ratio: float = 2.0,
    min_epipole_angle_deg: float = DensifyOptions.epipole_margin_deg,
    lr_max_diff_px: float = 1.0,
    min_disparity: int = 0,
    params: SgbmParams | None = None,
) -> DisparityResult:
    """Angular disparity ``d = θ_j − θ_i`` on both rectified grids with SGBM and a left-right check.

    - ``min_depth_ratio``: nearest plausible scene distance divided by the baseline; sets the search range
      (``disparity_search_range``).
    - Direction: θ_j = θ_i + d with d ≥ 0, i.e. a point sits at a *larger* column in j than in i. SGBM finds the
      left pixel x at x − d in the right image, so i → j is computed on column-flipped images (left = flip(i),
      right = flip(j)). One SGBM pass: its own left-right check (``disp12MaxDiff``, from the cost volume) replaces a
      second pass j → i, and j's map is i's carried over (``_forward_warp``): half the time of two passes.
    - Both images are extended past θ = 0 and θ = π by ``pad_theta`` so that SGBM's blind border (the first
      ``num_disparities`` columns of the left image) falls outside the real grid.
    - Pixels are invalid where SGBM found no match, where the two directions disagree by more than
      ``lr_max_diff_px`` (rounded to whole pixels), closer than ``min_epipole_angle_deg`` to the epipole or the anti-epipole, or untextured
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
    matcher = _make_sgbm(num, min_disparity, 1, params, lr_max_diff_px)
    t0 = time.perf_counter()
    left = np.ascontiguousarray(pad_theta(gray_i, 0, pad)[:, ::-1])
    right = np.ascontiguousarray(pad_theta(gray_j, 0, pad)[:, ::-1])
    disp_i = _sgbm_pixels(matcher, left, right, min_disparity)[:, ::-1][:, :n_theta]
    log.debug("SGBM %dx%d, %d disparities: %.2fs", n_phi, n_theta, num, time.perf_counter() - t0)
    theta = theta_of_columns(n_theta)
    margin = np.radians(min_epipole_angle_deg)
    away = ((theta >= margin) & (theta <= np.pi - margin))[None, :]
    with np.errstate(invalid="ignore"):
        valid_i = np.isfinite(disp_i) & away & (disp_i > 0) & _textured(gray_i, params)
    disp_j = _forward_warp(np.where(valid_i, disp_i, np.nan))
    with np.errstate(invalid="ignore"):
        valid_j = np.isfinite(disp_j) & away & (disp_j > 0) & _textured(gray_j, params)
    pixel_angle = np.pi / n_theta
    return DisparityResult(
        disparity_i=np.where(valid_i, disp_i * np.float32(pixel_angle), np.nan).astype(np.float32),
        disparity_j=np.where(valid_j, disp_j * np.float32(pixel_angle), np.nan).astype(np.float32),
        valid_i=valid_i,
        valid_j=valid_j,
        num_disparities=num,
        pixel_angle=pixel_angle,
    )
