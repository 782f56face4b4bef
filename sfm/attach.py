"""Attach cameras that translation averaging cannot place: a relative pose plus points fix their position.

Translation averaging only knows baseline *directions*, so a camera tied to the model by a single pair (a chain
0-1-2 with no pair 0-2, e.g. sequential matching) has an unknown distance along that baseline, and a model with
fewer than three cameras around a cycle has no scale link at all. Such a camera is attached as in incremental SfM:
its rotation from the relative pose, its centre on the baseline ray at the distance where the rays to the points
already triangulated by the model meet them (the median over the points, a robust 1-D resection).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fullview.sfm.camera import normalize
from fullview.sfm.tracks import Tracks
from fullview.sfm.triangulation import angular_errors, filter_tracks, gather_bearings, triangulate_multiview

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class Attachment:
    R_cam_from_world: np.ndarray  # (N, 3, 3) rotations, attached cameras filled in
    centers: np.ndarray  # (N, 3) centres, attached cameras filled in
    registered: np.ndarray  # (N,) bool, attached cameras included
    attached: list[int]  # cameras attached here, in order
    seeded: bool  # the model was empty and started from its strongest pair (unit baseline)


def attach_cameras(*, R_cam_from_world: np.ndarray, centers: np.ndarray, registered: np.ndarray, pairs: np.ndarray,
                   R_j_from_i: np.ndarray, t_j_from_i: np.ndarray, weights: np.ndarray, tracks: Tracks,
                   bearings_per_image: Sequence[np.ndarray], max_error_rad: float, min_angle_rad: float,
                   min_points: int = 6, allowed: np.ndarray | None = None) -> Attachment:
    """Grow the registered set one camera at a time over pairs with weight > 0 until nothing more attaches.

    ``allowed`` (N,) bool limits which cameras may be attached (default: every unregistered one); cameras of other
    models are excluded this way."""
    R, C, reg = R_cam_from_world.copy(), centers.copy(), registered.astype(bool).copy()
    allowed = ~reg if allowed is None else np.asarray(allowed, bool) & ~reg
    seeded = False
    if not reg.any():
        if not (weights > 0).any():
            return Attachment(R_cam_from_world=R, centers=C, registered=reg, attached=[], seeded=False)
        k = int(np.argmax(weights))
        i, j = pairs[k]
        R[i], C[i] = np.eye(3), np.zeros(3)
        R[j], C[j] = R_j_from_i[k], -R_j_from_i[k].T @ t_j_from_i[k]  # unit baseline
        reg[[i, j]] = True
        seeded = True
    attached = []
    while True:
        X, point_of_track = model_points(tracks, bearings_per_image, R, C, reg, max_error_rad, min_angle_rad)
        placed = False
        for b in _candidates(pairs, weights, reg, allowed):
            pose = _attach_one(b, R, C, reg, pairs, R_j_from_i, t_j_from_i, weights, tracks, bearings_per_image,
                               X, point_of_track, max_error_rad, min_points)
            if pose is not None:
                R[b], C[b] = pose
                reg[b] = True
                allowed[b] = False
                attached.append(int(b))
                placed = True
                break  # re-triangulate with the new camera before placing the next
        if not placed:
            break
    if attached or seeded:
        log.info("attached %d camera(s) by baseline and points: %s%s", len(attached), attached,
                 " (model seeded from its strongest pair)" if seeded else "")
    return Attachment(R_cam_from_world=R, centers=C, registered=reg, attached=attached, seeded=seeded)


def _candidates(pairs, weights, reg, allowed) -> list[int]:
    """Allowed unregistered cameras with a usable pair to a registered one, strongest link first."""
    strength: dict[int, float] = {}
    for (i, j), w in zip(pairs.tolist(), weights.tolist()):
        if w > 0 and reg[i] != reg[j]:
            b = j if reg[i] else i
            if not allowed[b]:
                continue
            strength[b] = max(strength.get(b, 0.0), w)
    return sorted(strength, key=lambda b: (-strength[b], b))


def model_points(tracks: Tracks, bearings, R, C, reg, max_error_rad, min_angle_rad):
    """Points of the tracks seen by >= 2 registered cameras, and each track's row in them (-1: none)."""
    point_of_track = np.full(tracks.num_tracks, -1)
    in_model = reg[tracks.image_ids]
    counts = np.bincount(tracks.track_ids[in_model], minlength=tracks.num_tracks)
    usable = counts >= 2
    if not usable.any():
        return np.zeros((0, 3)), point_of_track
    keep_obs = in_model & usable[tracks.track_ids]
    ids = np.flatnonzero(usable)
    sub = Tracks(track_ids=np.searchsorted(ids, tracks.track_ids[keep_obs]), image_ids=tracks.image_ids[keep_obs],
                 feature_ids=tracks.feature_ids[keep_obs],
                 offsets=np.concatenate([[0], np.cumsum(counts[ids])]), num_images=tracks.num_images)
    t = -np.einsum("nab,nb->na", R, np.nan_to_num(C))
    tri = triangulate_multiview(sub, bearings, R, t)
    good = filter_tracks(tri, max_error_rad=max_error_rad, min_angle_rad=min_angle_rad)
    point_of_track[ids[good]] = np.arange(good.sum())
    return tri.points[good], point_of_track


def _attach_one(b, R, C, reg, pairs, R_j_from_i, t_j_from_i, weights, tracks: Tracks, bearings, X, point_of_track,
                max_error_rad, min_points):
    """(R_b, c_b) from b's strongest pair to the model and the model points b sees; None if too few agree."""
    best = max((k for k, (i, j) in enumerate(pairs.tolist()) if weights[k] > 0 and b in (i, j)
                and reg[j if i == b else i]), key=lambda k: weights[k])
    i, j = pairs[best]
    a = j if i == b else i
    R_b, direction = pose_along_pair(a, b, pairs[best], R_j_from_i[best], t_j_from_i[best], R[a])
    u, seen = points_seen_by(b, R_b, tracks, bearings, X, point_of_track)
    if len(u) < min_points:
        return None
    s, lam = _ray_distances(direction, u, seen - C[a])
    ok = (s > 0) & (lam > 0)
    if ok.sum() < min_points:
        return None
    c_b = C[a] + np.median(s[ok]) * direction
    err = angular_errors(u, seen - c_b)
    if (err < 4 * max_error_rad).sum() < min_points:
        return None
    return R_b, c_b


def pose_along_pair(a: int, b: int, pair, R_j_from_i: np.ndarray, t_j_from_i: np.ndarray, R_a: np.ndarray):
    """(R_b, world direction from a's centre towards b's) of camera b from the relative pose of `pair` (a, b in either
    order) and camera a's rotation."""
    # R_j = R_rel R_i and c_j − c_i ∝ −R_jᵀ t_rel
    if b == pair[1]:
        R_b = R_j_from_i @ R_a
        return R_b, normalize(-R_b.T @ t_j_from_i)
    return R_j_from_i.T @ R_a, normalize(R_a.T @ t_j_from_i)


def points_seen_by(b: int, R_b: np.ndarray, tracks: Tracks, bearings, X: np.ndarray, point_of_track: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Camera b's observations of the model points X (rows `point_of_track`, -1: none): its rays in the world frame
    under rotation R_b (K, 3) and the points they see (K, 3)."""
    sel = (tracks.image_ids == b) & (point_of_track[tracks.track_ids] >= 0)
    u = gather_bearings(bearings, tracks.image_ids[sel], tracks.feature_ids[sel]) @ R_b  # R_bᵀ z, world rays
    return u, X[point_of_track[tracks.track_ids[sel]]]


def distance_by_few_points(direction: np.ndarray, u: np.ndarray, P: np.ndarray, max_error_rad: float,
                           min_points: int) -> tuple[float, int] | None:
    """A camera on the ray `direction` (unit, world) from a model camera, whose rays u (K, 3) (unit, world) see the
    model points P (K, 3) (relative to that camera's centre): the distance most points agree on (each point's own
    least-squares distance is a candidate, scored by the points within `max_error_rad` there; the inliers' median),
    and how many agree; None when fewer than `min_points` do. For a camera too few points reach to attach it
    (`attach_cameras`' `min_points`), still better than a guessed distance when they agree."""
    s, lam = _ray_distances(direction, u, P)
    ok = np.isfinite(s) & (s > 0) & (lam > 0)
    if ok.sum() < min_points:
        return None
    s, u, P = s[ok], u[ok], P[ok]
    seen = P[None, :, :] - s[:, None, None] * direction  # (candidate, point, 3) from each candidate
    errors = angular_errors(np.broadcast_to(u, seen.shape).reshape(-1, 3), seen.reshape(-1, 3)).reshape(len(s), -1)
    agree = errors < max_error_rad
    best = int(np.argmax(agree.sum(axis=1)))
    if agree[best].sum() < min_points:
        return None
    return float(np.median(s[agree[best]])), int(agree[best].sum())


def _ray_distances(direction: np.ndarray, u: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: least-squares (s, λ) with s·direction + λ·u_k ≈ P_k (2x2 normal equations, vectorised)."""
    du = u @ direction
    dp = P @ direction
    up = np.einsum("ka,ka->k", u, P)
    det = 1.0 - du * du  # |direction| = |u| = 1
    det = np.where(np.abs(det) < 1e-9, np.nan, det)
    return (dp - du * up) / det, (up - du * dp) / det
