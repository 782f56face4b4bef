"""Leave-one-out pose check: each camera's pose estimated again from the other cameras' points alone.

No ground truth is needed. For every registered camera of a model:

1. Every track the camera observes and at least two other cameras observe too is triangulated again from those
   other observations only (``triangulation.triangulate_multiview``), and kept under the triangulation stage's own
   filter: every ray within the inlier threshold θ of the point, a triangulation angle above the stage's minimum,
   the point in front of every ray. These points owe nothing to the camera's own observations.
2. The camera's pose is estimated from its bearings of those points by the registration's robust resection
   (``resection.resect``: P3P in LO-MSAC with the same θ, then the soft-L1 refinement).
3. The re-estimate is compared with the pose the model holds: the rotation between them (degrees), the distance
   between the centres (relative to the model's size, ``sfm.dense.scene_size``: the diagonal of the box around its
   cameras and points, the length every relative figure of fullview uses; a two-camera model's camera extent would
   be its baseline), and the angle between the bearings the two poses predict for the re-estimate's inliers
   (``shift``: rotation and centre together, as the observations see them).

The bound (why θ). The model's observations are its inliers at θ: a bearing more than θ from its point is not kept.
A held pose whose predicted bearings of the other cameras' points differ from the re-estimate's by more than θ at the
median point would make half of the camera's observations outliers of those points: its pose and the other cameras'
points are not one consistent model at the model's own precision. So a camera *disagrees* when its median shift
exceeds θ. In rotation alone that is a rotation of θ; in centre alone a displacement of about θ·d, d the median
depth of the points, at the median point. The check can only tell such a difference from its own scatter: a least-
squares pose from n bearings with residual σ predicts its bearings to σ·√(6 / 2n) on average (6 parameters, 2n
residuals: the mean leverage); where three times that reaches θ, or where fewer than ``min_points`` points or inliers
are left (the count registration needs to add a camera by resection), the camera is *unverifiable*, which is not the
same as disagreeing: a two-camera model, whose tracks have no third view, is unverifiable as a whole.

Pure geometry: no file access. ``check_poses`` runs the check on one model's arrays.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fullview.sfm.camera import camera_center
from fullview.sfm.resection import ResectionOptions, resect
from fullview.sfm.rotations import rotation_angle_deg
from fullview.sfm.tracks import Tracks
from fullview.sfm.triangulation import gather_bearings, triangulate_multiview

log = logging.getLogger(__name__)

NOISE_SIGMAS = 3.0  # the re-estimate's scatter times this must stay below θ for its verdict to mean anything
PARAMETERS = 6  # a pose's degrees of freedom (the mean leverage of n bearings is 6 / 2n)


@dataclass(frozen=True, kw_only=True)
class PoseCheckOptions:
    threshold_rad: float  # θ: the model's inlier threshold (triangulation.max_reprojection_error_deg), the bound
    min_angle_rad: float  # triangulation angle a leave-one-out point needs (triangulation.min_triangulation_angle_deg)
    min_points: int  # points and inliers a re-estimate needs (registration.min_resection_points)
    seed: int = 0  # the resection's RANSAC seed


@dataclass(frozen=True, kw_only=True)
class CameraCheck:
    status: str  # "agrees", "disagrees" or "unverifiable"
    reason: str  # the evidence in plain words
    points: int  # leave-one-out points the camera sees
    inliers: int  # of them, inliers of the re-estimate (0 without one)
    rotation_deg: float | None  # rotation between the held pose and the re-estimate
    centre_distance: float | None  # distance between their centres (model units)
    shift_deg: float | None  # median angle between the bearings the two poses predict (the re-estimate's inliers)
    noise_deg: float | None  # the re-estimate's own scatter of predicted bearings, σ √(6 / 2n)
    median_depth: float | None  # median distance of the inliers from the re-estimated centre

    def as_dict(self, scene_size: float) -> dict:
        out = {k: getattr(self, k) for k in ("status", "reason", "points", "inliers", "rotation_deg", "shift_deg",
                                             "noise_deg")}
        out["centre_rel"] = None if self.centre_distance is None else self.centre_distance / max(scene_size, 1e-12)
        out["median_depth_rel"] = None if self.median_depth is None else self.median_depth / max(scene_size, 1e-12)
        return out


def leave_one_out_points(track_ids: np.ndarray, image_ids: np.ndarray, feature_ids: np.ndarray,
                         bearings_per_image: Sequence[np.ndarray], R_cam_from_world: np.ndarray,
                         t_cam_from_world: np.ndarray, options: PoseCheckOptions
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every observation (k) whose track has at least two other observations: its track's point triangulated
    from those others alone, kept under the triangulation's filter. Returns (image, feature, point) of the kept
    ones: (M,), (M,), (M, 3). All tracks at once: observation k's track without k is a track of its own."""
    order = np.lexsort((image_ids, track_ids))
    tid, img, fid = (np.asarray(a, np.int64)[order] for a in (track_ids, image_ids, feature_ids))
    lengths = np.bincount(tid, minlength=int(tid.max(initial=-1)) + 1)
    start = np.cumsum(lengths) - lengths
    held = np.flatnonzero(lengths[tid] >= 3)
    if not len(held):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    reps = lengths[tid[held]]
    owner = np.repeat(np.arange(len(held)), reps)
    member = start[tid[held]][owner] + np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps)
    others = member != held[owner]
    owner, member = owner[others], member[others]
    tracks = Tracks(track_ids=owner, image_ids=img[member], feature_ids=fid[member],
                    offsets=np.r_[0, np.cumsum(reps - 1)].astype(np.int64), num_images=len(R_cam_from_world))
    tri = triangulate_multiview(tracks, bearings_per_image, R_cam_from_world, t_cam_from_world)
    keep = (np.isfinite(tri.points).all(axis=1) & (tri.max_error_rad < options.threshold_rad)
            & (tri.max_angle_rad > options.min_angle_rad) & tri.positive_depth)
    return img[held][keep], fid[held][keep], tri.points[keep]


def check_poses(cameras: Sequence[int], track_ids: np.ndarray, image_ids: np.ndarray, feature_ids: np.ndarray,
                bearings_per_image: Sequence[np.ndarray], R_cam_from_world: np.ndarray,
                t_cam_from_world: np.ndarray, options: PoseCheckOptions) -> dict[int, CameraCheck]:
    """The leave-one-out check (module doc) of the given cameras of one model, from that model's observations
    (track, image, feature per observation) and every image's bearings and pose."""
    R = np.asarray(R_cam_from_world, np.float64)
    t = np.asarray(t_cam_from_world, np.float64)
    img, fid, points = leave_one_out_points(track_ids, image_ids, feature_ids, bearings_per_image, R, t, options)
    theta = options.threshold_rad
    out = {}
    for c in cameras:  # one robust resection per camera
        sel = img == c
        n = int(sel.sum())
        if n < options.min_points:
            out[c] = _unverifiable(f"{n} points of the other cameras in view (fewer than {options.min_points})", n)
            continue
        bearings = gather_bearings(bearings_per_image, img[sel], fid[sel])
        res = resect(bearings, points[sel], ResectionOptions(threshold_rad=theta, min_inliers=options.min_points,
                                                             seed=options.seed))
        if res is None:
            out[c] = _unverifiable(f"no pose with {options.min_points} inliers among its {n} points", n)
            continue
        out[c] = _compare(R[c], t[c], res.R_cam_from_world, res.t_cam_from_world, points[sel][res.inliers],
                          res.errors[res.inliers], n, theta)
    return out


def _unverifiable(reason: str, points: int, inliers: int = 0) -> CameraCheck:
    return CameraCheck(status="unverifiable", reason=reason, points=points, inliers=inliers, rotation_deg=None,
                       centre_distance=None, shift_deg=None, noise_deg=None, median_depth=None)


def _compare(R_held, t_held, R_new, t_new, inlier_points, inlier_errors, points: int, theta: float) -> CameraCheck:
    """The held pose against the re-estimate on the re-estimate's inliers (module doc: the bound)."""
    c_held, c_new = camera_center(R_held, t_held), camera_center(R_new, t_new)
    a, b = (inlier_points - c_held) @ R_held.T, (inlier_points - c_new) @ R_new.T
    shift = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
    n = len(inlier_points)
    noise = float(np.sqrt(np.mean(inlier_errors ** 2)) * np.sqrt(PARAMETERS / (2 * n)))
    median_shift = float(np.median(shift))
    common = dict(points=points, inliers=n, rotation_deg=float(rotation_angle_deg(R_held, R_new)),
                  centre_distance=float(np.linalg.norm(c_held - c_new)), shift_deg=float(np.degrees(median_shift)),
                  noise_deg=float(np.degrees(noise)),
                  median_depth=float(np.median(np.linalg.norm(inlier_points - c_new, axis=1))))
    bound = np.degrees(theta)
    if NOISE_SIGMAS * noise >= theta:
        return CameraCheck(status="unverifiable", reason=f"the re-estimate's own scatter ({np.degrees(noise):.3g}°) "
                           f"times {NOISE_SIGMAS:g} reaches the bound {bound:.3g}°", **common)
    if median_shift > theta:
        return CameraCheck(status="disagrees", reason=f"the other cameras' points put it elsewhere: its view of them "
                           f"moves by {np.degrees(median_shift):.3g}° (median), more than the inlier threshold "
                           f"{bound:.3g}°", **common)
    return CameraCheck(status="agrees", reason=f"its view of the other cameras' points moves by "
                       f"{np.degrees(median_shift):.3g}° (median), within the inlier threshold {bound:.3g}°", **common)


def summarise(checks: dict[str, dict]) -> dict:
    """The ``pose_check`` section of ``fullview eval`` from per-image entries (``CameraCheck.as_dict``, with its
    model): the flagged images (disagreeing or unverifiable, listed apart too) and the medians over verified ones."""
    verified = [c for c in checks.values() if c["rotation_deg"] is not None]
    disagrees = [n for n, c in checks.items() if c["status"] == "disagrees"]
    unverifiable = [n for n, c in checks.items() if c["status"] == "unverifiable"]
    return {"per_image": checks, "flagged": disagrees + unverifiable, "disagrees": disagrees,
            "unverifiable": unverifiable,
            "median_rot_deg": float(np.median([c["rotation_deg"] for c in verified])) if verified else None,
            "median_centre_rel": float(np.median([c["centre_rel"] for c in verified])) if verified else None,
            "median_shift_deg": float(np.median([c["shift_deg"] for c in verified])) if verified else None}
