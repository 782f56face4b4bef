"""Comparing two reconstructions of the same panoramas (ours against COLMAP): agreement, alignment, the gate.

Pure functions, no file access. Poses follow docs/CONVENTIONS.md: `R_cam_from_world` (N,3,3), centres (N,3),
`registered` (N,) masks; image k of one model is image k of the other.

- Agreement is gauge-free: per image pair registered by both, the angle between the two models' relative rotations
  `R_j R_iᵀ` and between their translation directions `t_j_from_i ∝ R_j (c_i − c_j)`.
- Alignment is a similarity on the camera centres (Umeyama); with fewer than three centres, or collinear ones, the
  rotation comes from the camera orientations instead.
- The gate compares a few metrics of a run with a stored baseline under stated tolerances.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from fullview.sfm.camera import camera_up  # re-exported: the `up` of the top view
from fullview.sfm.metrics import Similarity, pairwise_pose_differences, umeyama
from fullview.sfm.rotations import rotation_angle_deg
# re-exported for the model statistics; the one implementation of angular reprojection errors is the triangulation's
from fullview.sfm.triangulation import reprojection_errors as angular_reprojection_errors

COLLINEAR_RATIO = 1e-3  # second/first singular value of the centred centres below this: treated as collinear
MAX_PLANE_TILT_DEG = 45.0  # top view: a PCA plane of the centres tilted more than this from `up` is not used


# --------------------------------------------------------------------------------------------- agreement
@dataclass(kw_only=True)
class Agreement:
    pairs: np.ndarray  # (K, 2) image pairs (i < j) registered by both models
    rotation_deg: np.ndarray  # (K,) angle between the relative rotations R_j R_iᵀ of the two models
    translation_deg: np.ndarray  # (K,) angle between the translation directions t_j_from_i of the two models
    pairs_total: int  # all pairs of the image list

    def summary(self) -> dict:
        def stats(x):
            return (float(np.median(x)), float(np.max(x))) if len(x) else (None, None)
        rot_med, rot_max = stats(self.rotation_deg)
        tr_med, tr_max = stats(self.translation_deg)
        return {"pairs_compared": int(len(self.pairs)), "pairs_total": int(self.pairs_total),
                "rotation_median_deg": rot_med, "rotation_max_deg": rot_max,
                "translation_median_deg": tr_med, "translation_max_deg": tr_max}


def relative_agreement(R_a: np.ndarray, c_a: np.ndarray, registered_a: np.ndarray,
                       R_b: np.ndarray, c_b: np.ndarray, registered_b: np.ndarray) -> Agreement:
    """Relative-pose differences between two models over the pairs both registered (gauge-free)."""
    n = len(R_a)
    if not (len(R_b) == len(c_a) == len(c_b) == len(registered_a) == len(registered_b) == n):
        raise ValueError(f"models differ in image count: {len(R_a)}, {len(c_a)}, {len(R_b)}, {len(c_b)}")
    both = np.asarray(registered_a, bool) & np.asarray(registered_b, bool)
    pairs = np.array([(i, j) for i, j in combinations(range(n), 2) if both[i] and both[j]], np.int64).reshape(-1, 2)
    rot, trans = pairwise_pose_differences(R_a, c_a, R_b, c_b, pairs)
    return Agreement(pairs=pairs, rotation_deg=rot, translation_deg=trans, pairs_total=n * (n - 1) // 2)


# --------------------------------------------------------------------------------------------- alignment
def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (Frobenius) to a 3×3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _collinear(centers: np.ndarray) -> bool:
    s = np.linalg.svd(centers - centers.mean(0), compute_uv=False)
    return s[0] <= 0 or s[1] / s[0] < COLLINEAR_RATIO


def rotation_alignment(R_src: np.ndarray, R_dst: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The rotation A (world_dst_from_world_src) best matching the orientations: chordal mean of R_dst_kᵀ R_src_k."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise ValueError("rotation alignment needs at least one image registered by both models")
    return project_to_rotation(np.einsum("nba,nbc->ac", R_dst[mask], R_src[mask]))


def align_cameras(R_src: np.ndarray, c_src: np.ndarray, R_dst: np.ndarray, c_dst: np.ndarray,
                  mask: np.ndarray) -> Similarity:
    """Similarity x_dst = s R x_src + t taking the source model's world onto the destination's.

    Umeyama on the centres of the images in `mask` (three or more, not collinear); otherwise the rotation is the
    chordal mean of R_dst_kᵀ R_src_k over the masked cameras and scale/translation come from the centres.
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        raise ValueError("alignment needs at least one image registered by both models")
    cs, cd = c_src[mask], c_dst[mask]
    if mask.sum() >= 3 and not _collinear(cd) and not _collinear(cs):
        return umeyama(cs, cd)
    R = rotation_alignment(R_src, R_dst, mask)
    spread_s = np.sqrt(((cs - cs.mean(0)) ** 2).sum(1).mean())
    spread_d = np.sqrt(((cd - cd.mean(0)) ** 2).sum(1).mean())
    scale = float(spread_d / spread_s) if spread_s > 0 else 1.0
    return Similarity(scale=scale, R=R, t=cd.mean(0) - scale * R @ cs.mean(0))


def transform_poses(sim: Similarity, R_cam_from_world: np.ndarray, centers: np.ndarray):
    """Poses expressed in the similarity's target world: R' = R Simᵀ, c' = sim(c)."""
    return R_cam_from_world @ sim.R.T, sim.apply(centers)


def aligned_differences(sim: Similarity, R_src, c_src, R_dst, c_dst, mask) -> dict:
    """Absolute differences after alignment, over the images in `mask`.

    Centres: distance after the similarity `sim`, relative to the destination scene's size. Rotations: angle left
    after the best common rotation of the orientations (`rotation_alignment`) — a centre-only similarity leaves
    the rotation about the line of nearly collinear centres loose, which would show up here as a false offset.
    """
    mask = np.asarray(mask, bool)
    c_al = sim.apply(c_src[mask])
    A = rotation_alignment(R_src, R_dst, mask)
    rot = rotation_angle_deg(R_src[mask] @ A.T @ np.swapaxes(R_dst[mask], -1, -2))
    size = float(np.linalg.norm(c_dst[mask].max(0) - c_dst[mask].min(0)))
    dist = np.linalg.norm(c_al - c_dst[mask], axis=1) / max(size, 1e-12)
    return {"images": int(mask.sum()), "scale": float(sim.scale),
            "rotation_median_deg": float(np.median(rot)), "rotation_max_deg": float(np.max(rot)),
            "center_median_rel": float(np.median(dist)), "center_max_rel": float(np.max(dist)),
            "similarity_vs_orientation_rotation_deg": float(rotation_angle_deg(sim.R @ A.T))}


# --------------------------------------------------------------------------------------------- model statistics
def model_statistics(*, registered: np.ndarray, points: np.ndarray, obs_image: np.ndarray, obs_point: np.ndarray,
                     errors_rad: np.ndarray) -> dict:
    """Registered images, 3-D points, mean track length and the median angular reprojection error (deg)."""
    return {"registered": int(np.sum(registered)), "images": int(len(registered)), "points": int(len(points)),
            "observations": int(len(obs_point)),
            "mean_track_length": float(len(obs_point) / len(points)) if len(points) else 0.0,
            "median_reprojection_error_deg": float(np.degrees(np.median(errors_rad))) if len(errors_rad) else None}


# --------------------------------------------------------------------------------------------- top view
def top_view_basis(centers: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """(2, 3) in-plane axes (e1, e2) of the centres' PCA plane, oriented so that e1 × e2 points along `up`.

    Projecting onto them shows the cameras from above whatever the model's gauge. When the centres do not span a
    plane (fewer than three, or collinear), or span one tilted more than MAX_PLANE_TILT_DEG from horizontal (a
    nearly straight walk whose vertical wobble beats its sideways one), the plane is the one orthogonal to `up`.
    """
    centers = np.asarray(centers, np.float64).reshape(-1, 3)
    up = np.zeros(3) if up is None else np.asarray(up, np.float64)
    if len(centers) >= 3 and not _collinear(centers):
        _, _, Vt = np.linalg.svd(centers - centers.mean(0))
        e1, e2 = Vt[0], Vt[1]
        if np.dot(np.cross(e1, e2), up) < 0:
            e2 = -e2
        if not np.any(up) or abs(np.dot(Vt[2], up)) >= np.cos(np.radians(MAX_PLANE_TILT_DEG)):
            return np.stack([e1, e2])
    normal = up if np.linalg.norm(up) > 0 else np.array([0.0, -1.0, 0.0])
    normal = normal / np.linalg.norm(normal)
    direction = np.linalg.svd(centers - centers.mean(0))[2][0] if len(centers) >= 2 else np.zeros(3)
    e1 = direction - normal * np.dot(direction, normal)
    if np.linalg.norm(e1) < 1e-9:
        e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 0.0, 1.0])
    e1 = e1 / np.linalg.norm(e1)
    return np.stack([e1, np.cross(normal, e1)])


# --------------------------------------------------------------------------------------------- baseline gate
# metric -> (direction, tolerance key): "higher" metrics may drop by at most the tolerance, "lower" ones may grow
# by at most the tolerance, relative to the stored baseline value.
GATES = {
    "ours_registered": ("higher", "registered_max_drop"),
    "ours_auc@1": ("higher", "auc@1_max_drop_points"),
    "agreement_rotation_median_deg": ("lower", "agreement_rotation_median_max_increase_deg"),
    "agreement_translation_median_deg": ("lower", "agreement_translation_median_max_increase_deg"),
}


def gated_metrics(result: dict) -> dict:
    """The gated metrics of a comparison result (the dict `fullview compare` writes); None where undefined."""
    gt = result.get("ground_truth", {}).get("ours", {})
    agreement = result.get("agreement", {})
    return {
        "ours_registered": result.get("ours", {}).get("registered"),
        "ours_auc@1": gt.get("auc@1"),
        "agreement_rotation_median_deg": agreement.get("rotation_median_deg"),
        "agreement_translation_median_deg": agreement.get("translation_median_deg"),
    }


def gate(current: dict, baseline: dict, tolerances: dict) -> list[str]:
    """Failure messages (empty when every baseline metric holds within its tolerance).

    A metric the baseline does not record (None or absent) is not gated; a recorded one that the current run
    lacks (e.g. no pair registered by both models) fails.
    """
    failures = []
    for name, (direction, tol_key) in GATES.items():
        base = baseline.get(name)
        if base is None:
            continue
        if tol_key not in tolerances:
            raise ValueError(f"baseline tolerances lack {tol_key!r} (needed for {name})")
        tol = float(tolerances[tol_key])
        value = current.get(name)
        if value is None:
            failures.append(f"{name}: missing (baseline {base:.6g})")
        elif direction == "higher" and value < base - tol:
            failures.append(f"{name}: {value:.6g} < baseline {base:.6g} - {tol:g}")
        elif direction == "lower" and value > base + tol:
            failures.append(f"{name}: {value:.6g} > baseline {base:.6g} + {tol:g}")
    return failures
