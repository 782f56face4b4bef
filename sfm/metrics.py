"""Accuracy metrics of camera poses: relative pose errors, AUC, similarity alignment (Umeyama)."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg


def pairwise_pose_differences(R_a, c_a, R_b, c_b, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For image pairs (P, 2) of two models (R_cam_from_world, centres): the angle between their relative rotations
    and between their translation directions t_j_from_i = R_j (c_i − c_j), in degrees."""
    i, j = pairs[:, 0], pairs[:, 1]
    rel_a = R_a[j] @ np.swapaxes(R_a[i], -1, -2)
    rel_b = R_b[j] @ np.swapaxes(R_b[i], -1, -2)
    dir_a = np.einsum("nab,nb->na", R_a[j], c_a[i] - c_a[j])
    dir_b = np.einsum("nab,nb->na", R_b[j], c_b[i] - c_b[j])
    return rotation_angle_deg(rel_a, rel_b), angle_between_deg(dir_a, dir_b)


def relative_pose_errors(R_est, c_est, R_gt, c_gt, registered) -> tuple[np.ndarray, np.ndarray]:
    """Per image pair (i<j): relative rotation error and translation-direction error in degrees.

    R_* are R_cam_from_world (N,3,3), c_* centres (N,3). Pairs touching an unregistered image get +inf, so they
    count as failures in the AUC. The translation direction is that of t_j_from_i = R_j (c_i − c_j), as in
    COLMAP's panorama benchmark.
    """
    pairs = np.array(list(combinations(range(len(R_gt)), 2)))
    i, j = pairs[:, 0], pairs[:, 1]
    rot_err, trans_err = pairwise_pose_differences(R_est, c_est, R_gt, c_gt, pairs)
    ok = registered[i] & registered[j]
    rot_err = np.where(ok, rot_err, np.inf)
    trans_err = np.where(ok, trans_err, np.inf)
    return rot_err, trans_err


def pose_auc(errors_deg: np.ndarray, thresholds_deg=(0.5, 1.0, 5.0, 10.0)) -> dict[str, float]:
    """Area under the recall-vs-error curve up to each threshold, in percent (COLMAP/glomap convention)."""
    errors = np.sort(np.asarray(errors_deg, np.float64))
    n = len(errors)
    recall = np.arange(1, n + 1) / n
    errors = np.concatenate([[0.0], errors])
    recall = np.concatenate([[0.0], recall])
    out = {}
    for t in thresholds_deg:
        last = np.searchsorted(errors, t)
        e = np.concatenate([errors[:last], [t]])
        r = np.concatenate([recall[:last], [recall[last - 1]]])
        out[f"auc@{t:g}"] = float(np.trapezoid(r, x=e) / t * 100.0)
    return out


@dataclass(kw_only=True)
class Similarity:
    scale: float  # s
    R: np.ndarray  # (3, 3) rotation
    t: np.ndarray  # (3,) translation: x_target = s R x_source + t

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.R.T + self.t


def umeyama(source: np.ndarray, target: np.ndarray) -> Similarity:
    """Least-squares similarity taking source points (N,3) onto target points (N,3), N >= 3."""
    if len(source) < 3:
        raise ValueError(f"similarity alignment needs at least 3 points, got {len(source)}")
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(source)
    scale = float(np.trace(np.diag(S) @ D) / var_s) if var_s > 0 else 1.0
    return Similarity(scale=scale, R=R, t=mu_t - scale * R @ mu_s)


def pose_metrics(R_est, c_est, R_gt, c_gt, registered) -> dict:
    """The summary of `fullview eval`: registered count, AUCs, median errors, centre error after alignment."""
    rot_err, trans_err = relative_pose_errors(R_est, c_est, R_gt, c_gt, registered)
    combined = np.maximum(rot_err, trans_err)
    out = {"images": int(len(R_gt)), "registered": int(registered.sum())}
    out.update(pose_auc(combined))
    finite = np.isfinite(rot_err)
    out["median_relative_rotation_error_deg"] = float(np.median(rot_err[finite])) if finite.any() else None
    out["median_translation_direction_error_deg"] = float(np.median(trans_err[finite])) if finite.any() else None
    scene_size = float(np.linalg.norm(c_gt.max(0) - c_gt.min(0)))
    if registered.sum() >= 3:
        sim = umeyama(c_est[registered], c_gt[registered])
        dist = np.linalg.norm(sim.apply(c_est[registered]) - c_gt[registered], axis=1)
        out["median_center_error_rel"] = float(np.median(dist) / max(scene_size, 1e-12))
        R_aligned = R_est[registered] @ sim.R.T  # cam_from_world in the aligned frame
        out["median_rotation_error_deg"] = float(np.median(rotation_angle_deg(
            R_aligned @ np.swapaxes(R_gt[registered], -1, -2))))
    return out
