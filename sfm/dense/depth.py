"""Ranges from disparities (law of sines), back to the panoramas, and per-panorama range maps.

Owns ``depth_from_disparity``, the rectified range maps, their resampling into each camera's equirectangular frame
(edge-aware, never blending across depth edges), ``densify_pair`` (one pair end to end), and the per-panorama
treatment of the pair estimates: expected range error per pixel, combination of several estimates, latitude mask.
Ranges are distances from the camera centre; invalid ones are NaN.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from fullview.sfm.options import DensifyOptions

from fullview.sfm.camera import bearings_to_pixels_f32, pixel_grid_bearings, pixel_grid_lonlat, pixel_latitude
from fullview.sfm.dense.disparity import DisparityResult, SgbmParams, compute_disparity
from fullview.sfm.dense.rectify import rectify_pair, theta_of_columns

log = logging.getLogger(__name__)

BACKMAP_ROWS = 64  # panorama rows resampled at a time (temporaries of a few MB, not ~250 MB per map)
COMBINE_ROWS = 64  # panorama rows whose pair estimates are combined at a time
SORTING_NETWORKS = {2: [(0, 1)], 3: [(0, 1), (1, 2), (0, 1)], 4: [(0, 1), (2, 3), (0, 2), (1, 3), (1, 2)]}


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
    theta_i, d = np.broadcast_arrays(np.asarray(theta_i, dtype=np.float64), np.asarray(disparity_angle, np.float64))
    out = np.full(d.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        matched = d > 0  # the law of sines only where there is a disparity (elementwise: the same numbers)
        r = baseline * np.sin(theta_i[matched] + d[matched]) / np.sin(d[matched])
        out[matched] = np.where(r > 0, r, np.nan)
    return out


def rectified_range_maps(disparity: DisparityResult, baseline: float) -> tuple[np.ndarray, np.ndarray]:
    """(range_i, range_j): float32 ranges on the rectified grids of cameras i and j (NaN invalid);
    ``depth_from_disparity`` cast to float32, computed in place (``_ranges_by_sines``)."""
    theta = theta_of_columns(disparity.disparity_i.shape[1])
    return (_ranges_by_sines(theta, disparity.disparity_i, baseline),
            _ranges_by_sines(np.pi - theta, disparity.disparity_j, baseline))


def _ranges_by_sines(theta: np.ndarray, disparity: np.ndarray, baseline: float) -> np.ndarray:
    """float32 ``depth_from_disparity(theta[None, :], disparity, baseline)`` for a rectified grid (``theta`` per
    column): the same float64 operations on the matched pixels, element for element, but masked in place instead
    of gathered and scattered (a third less CPU; the stereo does it for 14 maps per stage on the bench's room)."""
    out = np.full(disparity.shape, np.nan, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        matched = disparity > 0
        d = disparity.astype(np.float64)
        r = np.add(theta[None, :], d)
        np.sin(r, out=r, where=matched)
        np.sin(d, out=d, where=matched)
        np.multiply(baseline, r, out=r, where=matched)
        np.divide(r, d, out=r, where=matched)
        np.copyto(out, r, casting="same_kind", where=matched & (r > 0))
    return out


def sample_edge_aware(
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
    rows: slice = slice(None),
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a rectified range map into the camera's own equirectangular frame.

    ``range_rect`` is (n_phi, n_theta) on the rectified grid of that camera (NaN invalid); ``R_rect_from_cam`` is
    the camera's ``RectifiedPair.R_rect_from_cam_*``. Output size ``width`` × ``height`` (default width / 2).
    ``interpolation``: ``"nearest"`` or ``"edge_aware"`` (bilinear except across depth edges / invalid pixels; see
    ``sample_edge_aware``). Only the panorama ``rows`` are resampled, the others left invalid (the rows a latitude
    cap masks: ``latitude_rows``). Returns (range float32 (H, W) with NaN invalid, valid bool (H, W)).
    """
    if interpolation not in ("nearest", "edge_aware"):
        raise ValueError(f"interpolation must be 'nearest' or 'edge_aware', got {interpolation!r}")
    height = int(height or width // 2)
    n_phi, n_theta = range_rect.shape
    grid = pixel_grid_bearings(width, height, np.float32)
    R_t = np.asarray(R_rect_from_cam, np.float32).T
    values = np.asarray(range_rect, dtype=np.float32)
    out = np.full((height, width), np.nan, np.float32)
    first, stop, _ = rows.indices(height)
    for top in range(first, stop, BACKMAP_ROWS):  # elementwise per pixel: the same numbers as in one piece
        block = slice(top, min(top + BACKMAP_ROWS, stop))
        # the rectified frame is an equirectangular camera (n_phi x n_theta) whose top pole is the epipole: θ from
        # the pole
        v, u = bearings_to_pixels_f32(grid[block] @ R_t, n_phi, n_theta, from_pole=True)
        if interpolation == "nearest":
            col = np.clip(np.floor(u), 0, n_theta - 1).astype(np.intp)
            row = np.mod(np.floor(v), n_phi).astype(np.intp)
            out[block] = values[row, col]
        else:
            out[block] = sample_edge_aware(values, u, v, edge_tol, wrap_rows=True)
    valid = np.isfinite(out) & (out > 0)
    return np.where(valid, out, np.nan).astype(np.float32), valid


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
    min_epipole_angle_deg: float = DensifyOptions.epipole_margin_deg,
    params: SgbmParams | None = None,
    latitudes_deg: tuple[float, float] = (-90.0, 90.0),
) -> PairDepth:
    """Rectify, match (with LR check), triangulate and map back to both panoramas (size ``out_width`` ×
    ``out_width/2``, default the source size), on the panorama rows within ``latitudes_deg`` (the others are
    invalid: ``latitude_rows``; the stage masks them anyway, ``densify.min_latitude_deg``)."""
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
    rows = latitude_rows(width // 2, *latitudes_deg)
    pano_i, valid_i = range_map_to_panorama(range_i, pair.R_rect_from_cam_i, width=width, rows=rows)
    pano_j, valid_j = range_map_to_panorama(range_j, pair.R_rect_from_cam_j, width=width, rows=rows)
    t.append(time.perf_counter())
    timings = {"rectify": t[1] - t[0], "disparity": t[2] - t[1], "depth_and_backmap": t[3] - t[2]}
    log.debug("densify_pair timings: %s", timings)
    return PairDepth(range_i=pano_i, range_j=pano_j, valid_i=valid_i, valid_j=valid_j, timings=timings)


def range_error_per_pixel(range_map: np.ndarray, R_cam_from_world: np.ndarray, center: np.ndarray,
                          other_center: np.ndarray, pixel_angle: float) -> np.ndarray:
    """Relative range error caused by one rectified pixel (``pixel_angle`` rad) of disparity error, per pixel of a
    camera's equirectangular range map from the pair with the camera at ``other_center``.

    With r = |O_i P|, r_j = |O_j P|, baseline T and θ the angle at O_i between the baseline and the ray, the law of
    sines r = T sin(θ + d) / sin(d) gives |∂r/∂d| / r = r_j² / (r T sin θ): large near the epipoles and for distant
    points. NaN where the range is invalid."""
    height, width = range_map.shape
    baseline = np.asarray(other_center, np.float64) - np.asarray(center, np.float64)
    T = float(np.linalg.norm(baseline))
    e = (np.asarray(R_cam_from_world, np.float64) @ baseline / T).astype(np.float32)  # epipole, camera frame
    lon, lat = pixel_grid_lonlat(width, height, np.float32)
    cos_theta = (np.cos(lat)[:, None] * (np.sin(lon) * e[0] + np.cos(lon) * e[2])[None, :]
                 - np.sin(lat)[:, None] * e[1])
    sin_theta = np.sqrt(np.maximum(1.0 - cos_theta**2, 1e-12))
    r = np.asarray(range_map, np.float32)
    r_j_sq = r * r + T * T - 2.0 * T * r * cos_theta
    with np.errstate(invalid="ignore", divide="ignore"):
        return (r_j_sq * np.float32(pixel_angle) / (r * np.float32(T) * sin_theta)).astype(np.float32)


def combine_range_estimates(estimates: list[np.ndarray], rel_tol: float,
                            errors: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One range map from a panorama's pair estimates (each (H, W), NaN invalid).

    Where one pair has a range it is kept; where several have, the estimates within ``rel_tol`` (relative) of their
    median are averaged, weighted by confidence (1 / error² with ``errors`` the expected relative error of each
    estimate per pixel, ``range_error_per_pixel``: a partner whose epipole is near the pixel counts little), and the
    pixel is dropped unless at least two agree (two conflicting estimates cannot say which is right). Returns
    (range float32 NaN-invalid, valid bool)."""
    return combine_with_conflicts(estimates, rel_tol, errors)[:2]


def combine_with_conflicts(estimates: list[np.ndarray], rel_tol: float, errors: list[np.ndarray] | None = None
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``combine_range_estimates`` and ``conflicting_estimates`` of the same estimates in one pass over the pixels
    (the stage needs both; each pixel's agreement with the median is found once): (range, valid, flat pixel indices
    of the conflicts, their estimates)."""
    if not estimates:
        raise ValueError("combine_range_estimates needs at least one estimate")
    if len(estimates) == 1:
        rng = np.asarray(estimates[0], np.float32)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(rng) & (rng > 0)
        return (np.where(valid, rng, np.nan).astype(np.float32), valid, np.zeros(0, np.intp),
                np.zeros((1, 0), np.float32))
    shape = np.shape(estimates[0])
    out, valid = np.empty(shape, np.float32), np.empty(shape, bool)
    pixels, candidates = [], []
    for top in range(0, shape[0], COMBINE_ROWS):  # per pixel: the same numbers as in one piece, in cache
        rows = slice(top, top + COMBINE_ROWS)
        out[rows], valid[rows], raw, conflict = _combine_rows(
            [e[rows] for e in estimates], rel_tol, None if errors is None else [e[rows] for e in errors])
        pixels.append(np.flatnonzero(conflict) + top * shape[1])
        candidates.append(raw[:, conflict])
    return out, valid, np.concatenate(pixels), np.concatenate(candidates, axis=1)


def single_partner(estimates: list[np.ndarray], partners: list[int]) -> np.ndarray:
    """(H, W) int32: the partner camera whose pair gave a pixel's only estimate (``partners[k]`` for ``estimates[k]``),
    −1 where none or several pairs did. A panorama's range there rests on that one pair; the partner's own range at
    the same point comes from the same disparity and is no independent check of it
    (``fusion.seen_through_single_estimates``)."""
    out = np.full(np.shape(estimates[0]), -1, np.int32)
    count = np.zeros(out.shape, np.int32)
    for estimate, partner in zip(estimates, partners):
        finite = np.isfinite(estimate)
        count += finite
        out[finite] = partner
    out[count != 1] = -1
    return out


def conflicting_estimates(estimates: list[np.ndarray], rel_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The pixels ``combine_range_estimates`` drops because its pair estimates conflict (two or more, fewer than two
    within ``rel_tol`` of their median): (flat pixel indices (N,), their estimates (len(estimates), N) float32,
    NaN where a pair has none). Another panorama can tell which one is right (``fusion.resolve_conflicts``)."""
    if len(estimates) < 2:
        return np.zeros(0, np.intp), np.zeros((len(estimates), 0), np.float32)
    return combine_with_conflicts(estimates, rel_tol)[2:]


def _combine_rows(estimates: list[np.ndarray], rel_tol: float, errors: list[np.ndarray] | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``combine_with_conflicts`` of a block of rows of two or more estimates: the combined range, its validity, the
    estimates stacked (float32, (n, rows, W)) and where they conflict (two or more, fewer than two agreeing)."""
    raw = np.stack(estimates).astype(np.float32)
    stack, count, agree = _agreement_with_median(raw, rel_tol)
    n_agree = agree.sum(0)
    if errors is None:
        weight = agree.astype(np.float32)
    else:
        err = np.stack(errors).astype(np.float32)
        with np.errstate(invalid="ignore", divide="ignore"):
            weight = np.where(agree & np.isfinite(err) & (err > 0), 1.0 / np.maximum(err, 1e-6) ** 2, 0.0)
        weight = np.where(agree & (weight.sum(0) == 0)[None], 1.0, weight)  # no usable error: plain mean
    mean = (np.where(agree, raw, 0) * weight).sum(0) / np.maximum(weight.sum(0), 1e-30)
    valid = ((count == 1) | (n_agree >= 2)) & (count > 0)
    out = np.where(count == 1, stack[0], mean)
    valid &= np.isfinite(out) & (out > 0)
    return np.where(valid, out, np.nan).astype(np.float32), valid, raw, (count >= 2) & (n_agree < 2)


def _agreement_with_median(raw: np.ndarray, rel_tol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of (n, ...) estimates (NaN invalid): the estimates sorted finite first (``_sorted_finite_first``), their count
    of finite ones per pixel, and which estimates lie within ``rel_tol`` (relative) of their median (bool (n, ...))."""
    stack = _sorted_finite_first(raw)
    count = np.isfinite(stack).sum(0)
    lo = np.take_along_axis(stack, np.maximum((count - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(stack, np.maximum(count // 2, 0)[None], 0)[0]
    median = 0.5 * (lo + hi)
    with np.errstate(invalid="ignore"):
        return stack, count, np.abs(raw - median) <= rel_tol * median


def _sorted_finite_first(raw: np.ndarray) -> np.ndarray:
    """(n, ...) the estimates sorted along axis 0 with the finite ones first: at each pixel, positions below its
    count of finite values hold exactly what ``np.sort`` gives there (a sorting network of minima and maxima for a
    few estimates, the invalid ones as +inf; the positions beyond the count are not NaN then, and not used)."""
    if len(raw) not in SORTING_NETWORKS:
        return np.sort(raw, axis=0)  # NaN sorts last
    s = list(np.where(np.isfinite(raw), raw, np.float32(np.inf)))
    for a, b in SORTING_NETWORKS[len(s)]:
        s[a], s[b] = np.minimum(s[a], s[b]), np.maximum(s[a], s[b])
    return np.stack(s)


def mask_below_latitude(rng: np.ndarray, valid: np.ndarray, min_latitude_deg: float,
                        max_latitude_deg: float = 90.0):
    """Invalidate the rows of an equirectangular map whose centre latitude is below ``min_latitude_deg`` (nadir
    cap) or above ``max_latitude_deg`` (zenith cap)."""
    if min_latitude_deg <= -90.0 and max_latitude_deg >= 90.0:
        return rng, valid
    height = rng.shape[0]
    outside = np.ones((height, 1), bool)
    outside[latitude_rows(height, min_latitude_deg, max_latitude_deg)] = False
    return np.where(outside, np.nan, rng).astype(np.float32), valid & ~outside


def latitude_rows(height: int, min_latitude_deg: float, max_latitude_deg: float) -> slice:
    """The rows of an equirectangular map of ``height`` rows whose centre latitude lies within [min, max] (degrees):
    one run of rows, from the top (latitude falls with the row)."""
    lat = np.degrees(pixel_latitude(np.arange(height) + 0.5, height))
    inside = np.flatnonzero((lat >= min_latitude_deg) & (lat <= max_latitude_deg))
    return slice(int(inside[0]), int(inside[-1]) + 1) if len(inside) else slice(0, 0)


def apply_mask(rng: np.ndarray, valid: np.ndarray, keep: np.ndarray | None):
    """Invalidate a range map where an image mask (any size, True = keep) removes the pixel: the mask is resampled
    to the map by area, and a map pixel counts as kept only when all of it is."""
    if keep is None:
        return rng, valid
    height, width = rng.shape
    share = cv2.resize(keep.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    kept = share >= 1.0 - 1e-6
    return np.where(kept, rng, np.nan).astype(np.float32), valid & kept
