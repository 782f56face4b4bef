"""A pair's relative yaw checked against the two images' wall directions, and the pose the walls allow.

In a box room most of a pair's matches often lie on one plane (a wall, a textured furniture face). Such matches do not
fix the relative pose: a plane's matches fix only its homography, and the upright poses it allows can lie tens of
degrees apart in yaw while each explains every match; the upright fit then picks one by chance.

Each image's Manhattan frame (`manhattan.manhattan_axis`: the wall direction modulo 90° about gravity, from its own
lines) fixes the relative yaw modulo 90° independently of the matches: R_j_from_i must carry i's wall axis onto j's
within a multiple of 90°. Correct pairs agree to a few tenths of a degree (measured on the real captures under their
adjusted poses: 360_Flat's 55 pairs median 0.19°, 90th percentile 0.39°, largest 0.52°; 360_school's 6 at most 0.32°).
A pair whose fit disagrees by more than the tolerance is fitted again under the four yaws the walls allow (the
baseline by `two_view.baseline_given_rotation`, 2 unknowns); the best of them replaces the fit when it explains
nearly as many matches (`AMBIGUOUS_SHARE`): the matches could not tell the poses apart, the walls can. A weak pair
(fewer than `filter.min_inliers`) takes the walls' pose even when it explains fewer: below that count the filter does
not trust the matches' own fit (chance matches among them), and the pair then verifies only if the walls' pose
reaches the upright minimum. Where a strong pair's walls' pose explains far fewer, the matches decide and the fit
stays (a scene whose walls are not at right angles, a wrong axis). On the real captures no pair disagrees with its
walls (360_Flat, 360_school: none refitted).
Pure geometry: no file access.
"""

from __future__ import annotations

import cv2
import numpy as np

from fullview.sfm import two_view
from fullview.sfm.camera import normalize, skew

# A fit this close to the walls' yaw (modulo 90°) is not questioned: twice the largest residual of a correct pair on
# the real captures (0.52°, 360_Flat; the axes' stated errors are too small there: residuals reach 5.9 of them).
MIN_TOLERANCE_DEG = 1.0
AXIS_SIGMAS = 3.0  # ... nor one within this many standard errors of the two images' axes (a 3-sigma test)
# The walls' pose replaces the fit when it explains this share of the fit's inliers: the matches then do not tell the
# poses apart. Not measured on real data (no real pair reaches the check); not from a seed either.
AMBIGUOUS_SHARE = 0.9


def wall_residual_deg(R_j_from_i: np.ndarray, axis_i: np.ndarray, axis_j: np.ndarray, gravity_j: np.ndarray) -> float:
    """Yaw (degrees, in [−45, 45)) by which R_j_from_i misses carrying i's wall axis onto j's modulo 90°, about j's
    gravity: turning camera j by it about its gravity (`turn`) puts the axes into line."""
    g = normalize(np.asarray(gravity_j, np.float64))
    v = R_j_from_i @ axis_i
    v = v - (v @ g) * g
    angle = np.degrees(np.arctan2(np.cross(v, axis_j) @ g, v @ axis_j))
    return float((angle + 45.0) % 90.0 - 45.0)


def turn(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation by angle_deg about the unit axis (Rodrigues)."""
    K = skew(normalize(np.asarray(axis, np.float64)))
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * K @ K


def tolerance_deg(axis_std_i: float, axis_std_j: float) -> float:
    """The residual a correct pair may show: the axes' combined standard error times AXIS_SIGMAS, at least
    MIN_TOLERANCE_DEG."""
    return max(MIN_TOLERANCE_DEG, AXIS_SIGMAS * float(np.degrees(np.hypot(axis_std_i, axis_std_j))))


def pose_the_walls_allow(b_i: np.ndarray, b_j: np.ndarray, R_j_from_i: np.ndarray, axis_i: np.ndarray,
                         axis_j: np.ndarray, gravity_j: np.ndarray, threshold_rad: float, seed: int = 0):
    """(R_j_from_i, t_j_from_i, inlier mask) of the best of the four poses whose yaw the walls allow (the given
    rotation turned into line with the walls, then by 0°, 90°, 180°, 270° about j's gravity), each with the baseline
    that explains most of the matches b_i, b_j."""
    aligned = turn(gravity_j, wall_residual_deg(R_j_from_i, axis_i, axis_j, gravity_j)) @ R_j_from_i
    best = None
    for q in range(4):
        R = turn(gravity_j, 90.0 * q) @ aligned
        t, inliers = two_view.baseline_given_rotation(b_i, b_j, R, threshold_rad, seed=seed)
        if best is None or inliers.sum() > best[2].sum():
            best = (R, t, inliers)
    return best


def f_of_pose(R_j_from_i: np.ndarray, t_j_from_i: np.ndarray) -> np.ndarray:
    """F with b_iᵀ F b_j = 0 for the pose (`two_view.consistent_with_pose`'s convention)."""
    return R_j_from_i.T @ skew(t_j_from_i).T


# A pair whose inliers lie on one plane: the two poses of its homography explain them all (see `plane_poses`).
PLANE_SHARE = 0.9  # the inliers are planar when this share of them lie on one plane ...
PLANE_OFFSET = 0.02  # ... within this fraction of the plane's distance from camera i
MAX_WALL_TILT_DEG = 5.0  # a plane whose normal is this close to horizontal is a wall (a floor's tells no yaw)
# A wall's normal this close to an image's wall axis (modulo 90°) is one of its walls: about four times the largest
# wall residual of a correct pair on the real captures (0.52°, 360_Flat), so a wall fitted from a patch still counts.
PLANE_TOLERANCE_DEG = 2.0
# ... and the planar inliers spread along both of the plane's directions by at least this fraction of its distance
# (standard deviation s): points scattered across the PLANE_OFFSET band (std PLANE_OFFSET/√3) tilt the normal fitted
# to the 8 points a fit needs by (PLANE_OFFSET/√3) / (s √(8 − 3)) rad (rms; 3 unknowns of the plane), which must stay
# within PLANE_TOLERANCE_DEG: s = 0.148.
PLANE_MIN_EXTENT = PLANE_OFFSET / np.sqrt(3.0) / (np.sqrt(8.0 - 3.0) * np.radians(PLANE_TOLERANCE_DEG))


def inlier_plane(b_i: np.ndarray, b_j: np.ndarray, R_j_from_i: np.ndarray, t_j_from_i: np.ndarray
                 ) -> tuple[np.ndarray, float] | None:
    """(unit normal n in frame i, distance d > 0) of the plane nᵀX = d that holds PLANE_SHARE of the matches b_i, b_j
    triangulated under the pose (t's length is the unit), or None when they are not planar, too few, or a small patch
    (PLANE_MIN_EXTENT)."""
    a, b = two_view.ray_depths(b_i, b_j, R_j_from_i, t_j_from_i)
    front = (a > 0) & (b > 0)
    if front.sum() < 8:
        return None
    X = a[front, None] * b_i[front]
    centre = np.median(X, axis=0)
    n = np.linalg.svd(X - centre, full_matrices=False)[2][2]
    for _ in range(3):  # refit on the points near the plane: a few stray matches must not tilt it
        d = float(n @ centre)
        near = np.abs(X @ n - d) <= PLANE_OFFSET * abs(d)
        if near.sum() < 8:
            return None
        centre = X[near].mean(axis=0)
        n = np.linalg.svd(X[near] - centre, full_matrices=False)[2][2]
    d = float(n @ centre)
    near = np.abs(X @ n - d) <= PLANE_OFFSET * abs(d)
    if not (abs(d) > 0 and near.mean() >= PLANE_SHARE):
        return None
    spread = np.linalg.svd(X[near] - X[near].mean(axis=0), compute_uv=False) / np.sqrt(near.sum())
    if spread[1] < PLANE_MIN_EXTENT * abs(d):
        return None
    return (n, d) if d > 0 else (-n, -d)


def plane_poses(R_j_from_i: np.ndarray, t_j_from_i: np.ndarray, normal_i: np.ndarray, distance: float):
    """The poses (R_j_from_i, unit t_j_from_i, plane normal in frame i) of the plane's homography H = R + t nᵀ/d: a
    plane's matches fix H, and H has two decompositions with the plane in front of camera i, both explaining every
    match; the given pose is one of them. One per rotation (the sign of t and n
    is left to cheirality)."""
    H = R_j_from_i + np.outer(t_j_from_i, normal_i) / distance
    _, Rs, ts, ns = cv2.decomposeHomographyMat(H, np.eye(3))
    poses = []
    for R, t, n in zip(Rs, ts, ns):  # four: two rotations, each with (t, n) and (−t, −n); the sign is cheirality's
        if not any(np.allclose(R, other) for other, _, _ in poses):
            poses.append((np.asarray(R, np.float64), normalize(t.ravel()), n.ravel()))
    return poses


def pose_the_plane_allows(b_i: np.ndarray, b_j: np.ndarray, keep: np.ndarray, R_j_from_i: np.ndarray,
                          t_j_from_i: np.ndarray, axis_j: np.ndarray, gravity_i: np.ndarray, gravity_j: np.ndarray,
                          threshold_rad: float, seed: int = 0):
    """Where only image j has a wall axis and the fit's inliers (`keep`) lie on a wall: (R_j_from_i, t_j_from_i,
    inlier mask) of the homography's other pose when the fit puts the wall off j's walls (modulo 90°) and that pose
    puts it on them; None otherwise (not planar, a floor, the fit agrees, or no pose agrees).

    A wall seen by both images fixes only its homography, whose two poses explain every match (the wrong one can lie
    tens of degrees off in yaw). The wall is one of j's walls, so its normal carried into j must lie on j's axis
    modulo 90°: only the true pose puts it there (within PLANE_TOLERANCE_DEG). The chosen pose is levelled (i's gravity onto j's) and turned about j's gravity so
    the normal lies exactly on j's axis, and its baseline is fitted again (`two_view.baseline_given_rotation`)."""
    plane = inlier_plane(b_i[keep], b_j[keep], R_j_from_i, t_j_from_i)
    if plane is None:
        return None
    g_i, g_j = normalize(np.asarray(gravity_i, np.float64)), normalize(np.asarray(gravity_j, np.float64))
    normal_j = R_j_from_i @ plane[0]
    if _tilt_deg(normal_j, g_j) > MAX_WALL_TILT_DEG:
        return None  # a floor or a ceiling: its normal says nothing about the yaw
    if abs(wall_residual_deg(R_j_from_i, plane[0], axis_j, g_j)) <= PLANE_TOLERANCE_DEG:
        return None
    best = None
    for R, _, n in plane_poses(R_j_from_i, t_j_from_i, *plane):
        R = two_view.rotation_between(R @ g_i, g_j) @ R  # levelled: the homography knows no gravity
        residual = wall_residual_deg(R, n, axis_j, g_j)
        if abs(residual) > PLANE_TOLERANCE_DEG or _tilt_deg(R @ n, g_j) > MAX_WALL_TILT_DEG:
            continue
        R = turn(g_j, residual) @ R
        t, inliers = two_view.baseline_given_rotation(b_i, b_j, R, threshold_rad, seed=seed)
        if best is None or inliers.sum() > best[2].sum():
            best = (R, t, inliers)
    return best


def _tilt_deg(normal: np.ndarray, gravity: np.ndarray) -> float:
    """How far a plane of unit `normal` is from vertical (degrees; 0: a wall, 90: a floor) under unit `gravity`."""
    return float(np.degrees(np.arcsin(min(1.0, abs(normal @ gravity)))))
