"""Triangulation from unit bearings: two-view midpoint and multi-view least squares.

Two views (the report's midpoint): camera 1 at the origin, ray 1 is ``a z1``, ray 2 is
``b R⁻¹ z2 + c2`` with ``c2 = -Rᵀ t`` the centre of camera 2 in frame 1. With ``A = [z1, -R⁻¹z2]``
the least-squares ``[a, b] = (AᵀA)⁻¹ Aᵀ c2`` gives the closest points of the two lines; the point
is their midpoint.

Multi-view (the report's "mean point"): ``P_i = r_i d_i + C_i`` with ``d_i = R_iᵀ z_i`` (world
ray direction) and ``C_i`` the camera centre; minimise ``Σ ‖P_i − P̄‖²`` over the ``r_i``, ``P̄``
the mean. Since the mean is the point minimising ``Σ ‖P_i − X‖²``, this is
``min_{X, r} Σ ‖r_i d_i + C_i − X‖²``; for fixed ``X`` the best ``r_i = d_iᵀ(X − C_i)`` (the
projection), leaving ``min_X Σ ‖(I − d_i d_iᵀ)(X − C_i)‖²``: the point closest to all the lines in
the least-squares sense, the solution of the 3×3 system
``[Σ (I − d_i d_iᵀ)] X = Σ (I − d_i d_iᵀ) C_i``. Every track's system is accumulated with
``np.add.at`` and all are solved at once with a batched ``np.linalg.solve``.

Errors are radians. The angular reprojection error of an observation is the angle between its
observed bearing and ``normalize(R X + t)``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fullview.sfm.camera import normalize
from fullview.sfm.tracks import Tracks

log = logging.getLogger(__name__)

# Smallest eigenvalue of Σ(I − d dᵀ), per ray, below which a track's rays count as parallel
# (for two rays at angle φ the smallest eigenvalue is 1 − cos φ, so this is φ ≈ 0.004°).
_MIN_NORMAL_EIGENVALUE = 1e-9


@dataclass(frozen=True, kw_only=True)
class TwoViewPoints:
    """Midpoint triangulation of N ray pairs, in the frame of camera 1."""

    points: np.ndarray  # (N, 3) midpoints in frame 1 (NaN where the rays are parallel)
    depth1: np.ndarray  # (N,) a: distance along ray 1 of its closest point (NaN if parallel)
    depth2: np.ndarray  # (N,) b: distance along ray 2 of its closest point (NaN if parallel)
    parallax_rad: np.ndarray  # (N,) angle between the two rays' directions


@dataclass(frozen=True, kw_only=True)
class MultiviewPoints:
    """Least-squares triangulation of T tracks, with per-track quality."""

    points: np.ndarray  # (T, 3) world points (NaN where all rays are near parallel)
    max_error_rad: np.ndarray  # (T,) largest angular reprojection error over the track's observations
    max_angle_rad: np.ndarray  # (T,) largest angle between two rays centre->point of the track (NaN if no point)
    positive_depth: np.ndarray  # (T,) bool: every ray depth r_i = d_iᵀ(X − C_i) is > 0
    obs_error_rad: np.ndarray  # (K,) angular reprojection error of every observation (tracks order)


def angular_errors(bearings: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """(N,) angle between observed bearings and camera-frame points (any norm), in radians."""
    b = normalize(bearings)
    p = normalize(points_cam)
    return np.arctan2(np.linalg.norm(np.cross(b, p), axis=-1), np.einsum("ij,ij->i", b, p))


def reprojection_errors(
    R_cam_from_world: np.ndarray,
    t_cam_from_world: np.ndarray,
    points: np.ndarray,
    obs_camera: np.ndarray,
    obs_point: np.ndarray,
    obs_bearings: np.ndarray,
) -> np.ndarray:
    """(K,) angular reprojection error of observations (camera, point, observed bearing)."""
    R = R_cam_from_world[obs_camera]
    x_cam = np.einsum("kij,kj->ki", R, points[obs_point]) + t_cam_from_world[obs_camera]
    return angular_errors(obs_bearings, x_cam)


def triangulate_two_view_midpoint(
    b1: np.ndarray, b2: np.ndarray, R_2_from_1: np.ndarray, t_2_from_1: np.ndarray
) -> TwoViewPoints:
    """Midpoint of the closest points of rays ``b1`` (camera 1 at origin) and ``b2`` (camera 2).

    ``x_2 = R_2_from_1 @ x_1 + t_2_from_1``; ``b1``, ``b2`` are (N, 3) bearings (normalised here).
    Depths ``a``, ``b`` are signed distances along the rays: both > 0 means the point is in front.
    """
    z1, z2 = normalize(np.atleast_2d(b1)), normalize(np.atleast_2d(b2))
    if z1.shape != z2.shape or z1.shape[-1] != 3:
        raise ValueError(f"b1 {np.shape(b1)} and b2 {np.shape(b2)} must both be (N, 3)")
    R, t = np.asarray(R_2_from_1, float), np.asarray(t_2_from_1, float).reshape(3)
    d2 = z2 @ R  # rows R^T z2: ray 2 directions in frame 1
    c2 = -R.T @ t  # centre of camera 2 in frame 1
    cos = np.einsum("ij,ij->i", z1, d2)
    det = 1.0 - cos**2  # det(AᵀA) for A = [z1, -d2] with unit columns
    rhs1, rhs2 = z1 @ c2, -(d2 @ c2)  # Aᵀ c2
    ok = det > 1e-12
    safe = np.where(ok, det, 1.0)
    a = np.where(ok, (rhs1 + cos * rhs2) / safe, np.nan)
    b = np.where(ok, (cos * rhs1 + rhs2) / safe, np.nan)
    points = 0.5 * (a[:, None] * z1 + b[:, None] * d2 + c2)
    parallax = np.arctan2(np.linalg.norm(np.cross(z1, d2), axis=-1), cos)
    return TwoViewPoints(points=points, depth1=a, depth2=b, parallax_rad=parallax)


def gather_bearings(
    bearings_per_image: Sequence[np.ndarray], image_ids: np.ndarray, feature_ids: np.ndarray
) -> np.ndarray:
    """(K, 3) unit bearings of observations (image_ids[k], feature_ids[k])."""
    counts = np.array([len(b) for b in bearings_per_image], dtype=np.int64)
    valid = (image_ids >= 0) & (image_ids < len(counts))
    valid[valid] &= (feature_ids[valid] >= 0) & (feature_ids[valid] < counts[image_ids[valid]])
    if not valid.all():
        k = int(np.argmin(valid))
        raise ValueError(f"observation {k} (image {image_ids[k]}, feature {feature_ids[k]}) has no bearing "
                         f"in bearings_per_image ({len(counts)} images)")
    arrays = [np.asarray(b, dtype=np.float64).reshape(-1, 3) for b in bearings_per_image]
    flat = np.concatenate([np.zeros((0, 3)), *arrays])
    return normalize(flat[(np.cumsum(counts) - counts)[image_ids] + feature_ids])


def _solve_points(track_ids, centers, dirs, num_tracks) -> np.ndarray:
    """(T, 3) least-squares closest points to the lines centers + r dirs, grouped by track."""
    M = np.eye(3) - dirs[:, :, None] * dirs[:, None, :]  # (K, 3, 3) projector orthogonal to each ray
    A = np.zeros((num_tracks, 3, 3))
    rhs = np.zeros((num_tracks, 3))
    np.add.at(A, track_ids, M)
    np.add.at(rhs, track_ids, np.einsum("kij,kj->ki", M, centers))
    n_rays = np.bincount(track_ids, minlength=num_tracks)
    ok = np.linalg.eigvalsh(A)[:, 0] > _MIN_NORMAL_EIGENVALUE * np.maximum(n_rays, 1)
    points = np.full((num_tracks, 3), np.nan)
    if ok.any():
        points[ok] = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
    return points


def _pairs_within_tracks(offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (first, second) of every unordered pair of observations inside each track.

    ``offsets`` are CSR offsets of consecutive tracks (``offsets[0]`` need not be 0).
    """
    base, offsets = offsets[0], offsets - offsets[0]
    lengths = np.diff(offsets)
    pos = np.arange(offsets[-1]) - np.repeat(offsets[:-1], lengths)  # position inside the track
    count = np.repeat(lengths, lengths) - 1 - pos  # partners after each observation
    first = np.repeat(np.arange(offsets[-1]), count)
    starts = np.cumsum(count) - count
    second = first + 1 + np.arange(count.sum()) - np.repeat(starts, count)
    return first + base, second + base


def _max_pair_angle(rays: np.ndarray, offsets: np.ndarray, chunk_pairs: int = 2_000_000) -> np.ndarray:
    """(T,) largest angle between two unit rays of each track (0 for single rays).

    The angle is arccos of the smallest pairwise dot product (exact to ~1e-8 rad). Tracks are taken
    in chunks of about ``chunk_pairs`` pairs, so memory stays bounded for long tracks.
    """
    num_tracks = len(offsets) - 1
    lengths = np.diff(offsets)
    cum_pairs = np.cumsum(lengths * (lengths - 1) // 2)
    total = int(cum_pairs[-1]) if num_tracks else 0
    splits = np.unique(np.searchsorted(cum_pairs, np.arange(chunk_pairs, total, chunk_pairs)))
    min_dot = np.ones(num_tracks)
    for lo, hi in zip(np.r_[0, splits], np.r_[splits, num_tracks], strict=True):
        first, second = _pairs_within_tracks(offsets[lo : hi + 1])
        track = np.repeat(np.arange(lo, hi), lengths[lo:hi])[first - offsets[lo]]
        np.minimum.at(min_dot, track, np.einsum("ki,ki->k", rays[first], rays[second]))
    return np.arccos(np.clip(min_dot, -1.0, 1.0))


def _max_per_track(values: np.ndarray, track_ids: np.ndarray, num_tracks: int) -> np.ndarray:
    """(T,) max of ``values`` over each track (-inf for tracks without values, NaN propagates)."""
    out = np.full(num_tracks, -np.inf)
    np.maximum.at(out, track_ids, values)
    return out


def triangulate_multiview(
    tracks: Tracks,
    bearings_per_image: Sequence[np.ndarray],
    R_cam_from_world: np.ndarray,
    t_cam_from_world: np.ndarray,
) -> MultiviewPoints:
    """Triangulate every track at once (point closest to all its rays) and measure its quality.

    ``bearings_per_image[i]`` is the (F_i, 3) bearing array of image i (indexed by feature id);
    poses are (N, 3, 3) and (N, 3), one per image.
    """
    R = np.asarray(R_cam_from_world, dtype=np.float64)
    t = np.asarray(t_cam_from_world, dtype=np.float64)
    if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (len(R), 3) or len(R) < tracks.num_images:
        raise ValueError(f"poses R {R.shape}, t {t.shape} must be (N,3,3), (N,3) with N >= {tracks.num_images}")
    bearings = gather_bearings(bearings_per_image, tracks.image_ids, tracks.feature_ids)
    cam, tid = tracks.image_ids, tracks.track_ids
    centers = -np.einsum("nji,nj->ni", R, t)[cam]  # C = -Rᵀ t per observation
    dirs = np.einsum("kji,kj->ki", R[cam], bearings)  # d = Rᵀ z
    points = _solve_points(tid, centers, dirs, tracks.num_tracks)

    to_point = points[tid] - centers
    depth = np.einsum("ki,ki->k", dirs, to_point)
    obs_err = angular_errors(bearings, np.einsum("kij,kj->ki", R[cam], to_point))
    positive = np.ones(tracks.num_tracks, dtype=bool)
    np.logical_and.at(positive, tid, depth > 0)  # NaN depth compares False
    return MultiviewPoints(
        points=points,
        max_error_rad=_max_per_track(obs_err, tid, tracks.num_tracks),
        max_angle_rad=_max_pair_angle(normalize(to_point), tracks.offsets),
        positive_depth=positive,
        obs_error_rad=obs_err,
    )


def filter_tracks(
    triangulated: MultiviewPoints,
    *,
    max_error_rad: float,
    min_angle_rad: float,
    require_positive_depth: bool = True,
) -> np.ndarray:
    """(T,) bool keep-mask: finite point, max error < ``max_error_rad``, max angle > ``min_angle_rad``,
    and (if required) every ray depth positive. Counts of each rejection are logged."""
    finite = np.isfinite(triangulated.points).all(axis=1)
    small_error = triangulated.max_error_rad < max_error_rad
    wide_angle = triangulated.max_angle_rad > min_angle_rad
    in_front = triangulated.positive_depth | (not require_positive_depth)
    keep = finite & small_error & wide_angle & in_front
    log.info(
        "filter_tracks: kept %d of %d (degenerate %d, error >= %.3g rad %d, angle <= %.3g rad %d, behind %d)",
        keep.sum(), len(keep), (~finite).sum(), max_error_rad, (finite & ~small_error).sum(),
        min_angle_rad, (finite & ~wide_angle).sum(), (finite & ~in_front).sum(),
    )
    return keep


def longest_tracks_per_image(tracks: Tracks, per_image: int) -> np.ndarray:
    """(T,) bool: the tracks among the `per_image` longest (ties by track index) of at least one of their images.

    Long tracks constrain the poses most; every image keeps min(per_image, its tracks) of them, so a pose-only
    adjustment on this subset sees every camera (the others' points are re-triangulated afterwards anyway)."""
    lengths = tracks.lengths[tracks.track_ids]
    order = np.lexsort((tracks.track_ids, -lengths, tracks.image_ids))  # per image: longest first, then by index
    per_image_count = np.bincount(tracks.image_ids, minlength=tracks.num_images)
    starts = np.cumsum(per_image_count) - per_image_count
    rank = np.empty(tracks.num_observations, np.int64)
    rank[order] = np.arange(tracks.num_observations) - np.repeat(starts, per_image_count)
    keep = np.zeros(tracks.num_tracks, bool)
    keep[tracks.track_ids[rank < per_image]] = True
    return keep
