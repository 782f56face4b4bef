"""A pair's relative yaw checked against the two images' wall directions, and the pose the walls allow.

In a box room most of a pair's matches often lie on one plane (a wall, a textured furniture face). Such matches do not
fix the relative pose: several upright poses, their yaws tens of degrees apart, explain all of them (measured on the
bare 2048 px home seed 44: 009-012 holds 112 inliers, all true matches, under a pose 102° off; an upright pose 102.5°
from the chosen one explains as many; correct pairs show the same, e.g. 012-015, 84 inliers, an alternative 89° off
with 85). The upright fit then picks one by chance.

Each image's Manhattan frame (`manhattan.manhattan_axis`: the wall direction modulo 90° about gravity, from its own
lines) fixes the relative yaw modulo 90° independently of the matches: R_j_from_i must carry i's wall axis onto j's
within a multiple of 90°. Correct pairs agree to 0.1° (median; 0.25° at the 90th percentile on bare home seed 45).
A pair whose fit disagrees by more than the tolerance is fitted again under the four yaws the walls allow (the
baseline by `two_view.baseline_given_rotation`, 2 unknowns); the best of them replaces the fit when it explains
nearly as many matches (`AMBIGUOUS_SHARE`): the matches could not tell the poses apart, the walls can. A weak pair
(fewer than `filter.min_inliers`) takes the walls' pose even when it explains fewer: on seed 44 the three weak pairs
that contradict the walls (5.7°, 88° and 118° off) hold 16, 15 and 21 inliers, chance matches among them, and the
walls' pose 13, 13 and 17, within 0.2° of the truth (the pair then verifies only if those reach the minimum). Where a
strong pair's walls' pose explains far fewer, the matches decide and the fit stays (a scene whose walls are not at
right angles, a wrong axis). With `filter.wall_check_drop` such pairs are dropped instead (README, wallfix).
Pure geometry: no file access.
"""

from __future__ import annotations

import numpy as np

from fullview.sfm import two_view
from fullview.sfm.camera import normalize, skew

MIN_TOLERANCE_DEG = 1.0  # a fit this close to the walls' yaw (modulo 90°) is not questioned
AXIS_SIGMAS = 3.0  # ... nor one within this many standard errors of the two images' axes
AMBIGUOUS_SHARE = 0.9  # the walls' pose replaces the fit when it explains this share of the fit's inliers


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
