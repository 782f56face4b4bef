"""The join check: a join that puts one model's points in front of what the other's cameras saw is undone
(fullview.sfm.registration.placement_check, and its use by the weak joins)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.registration.placement_check import contradicted, join_conflicts
from fullview.sfm.registration.rematch_join import ModelPoints
from fullview.sfm.registration.weak_joins import CrossPair, _place

THRESHOLD = np.radians(0.35)
N = 1500  # surface points per room (dense enough that rays of one model pass near the other's points)


def _yaw(deg: float) -> np.ndarray:
    return Rotation.from_euler("y", deg, degrees=True).as_matrix()


def _wall_points(rng, lo, hi, n: int) -> np.ndarray:
    """n points on the four walls, floor and ceiling of the box [lo, hi] (what a camera inside it sees)."""
    X = rng.uniform(lo, hi, (n, 3))
    axis, side = rng.integers(0, 3, n), rng.integers(0, 2, n)
    X[np.arange(n), axis] = np.where(side == 1, np.asarray(hi)[axis], np.asarray(lo)[axis])
    return X


def _two_rooms(rng):
    """Room A (x in [-4, 0]) and room B (x in [0.1, 4.1]) side by side, two cameras in each seeing their own room's
    surfaces; model b's frame is x_a = s0 M0 x_b + T0. Returns (points a, points b, frames, bearings, truth)."""
    lo_a, hi_a = np.array([-4.0, -1.2, -2.0]), np.array([0.0, 1.3, 2.0])
    lo_b, hi_b = np.array([0.1, -1.2, -2.0]), np.array([4.1, 1.3, 2.0])
    X_a, X_b = _wall_points(rng, lo_a, hi_a, N), _wall_points(rng, lo_b, hi_b, N)
    R = [_yaw(10.0), _yaw(-60.0), _yaw(100.0), _yaw(200.0)]
    C = [np.array([-2.8, 0.0, 0.5]), np.array([-1.2, 0.02, -0.6]), np.array([1.4, 0.0, 0.4]),
         np.array([2.9, 0.01, -0.5])]
    M0, T0, s0 = _yaw(37.0), np.array([0.5, 0.0, -1.0]), 0.7
    bearings = [normalize((X_a if k < 2 else X_b) - C[k]) @ R[k].T for k in range(4)]
    every = np.arange(N)
    points_a = ModelPoints(X=X_a, point_of_feature={0: every, 1: every})
    points_b = ModelPoints(X=(X_b - T0) @ M0 / s0, point_of_feature={2: every, 3: every})
    frames = dict(R_a={0: R[0], 1: R[1]}, C_a={0: C[0], 1: C[1]},
                  R_b={k: R[k] @ M0 for k in (2, 3)}, C_b={k: M0.T @ (C[k] - T0) / s0 for k in (2, 3)})
    return points_a, points_b, frames, bearings, (M0, T0, s0)


def test_the_true_join_of_two_rooms_holds_and_a_model_placed_inside_the_other_is_contradicted():
    rng = np.random.default_rng(0)
    points_a, points_b, frames, bearings, (M0, T0, s0) = _two_rooms(rng)
    found, overlaps = join_conflicts(points_a, points_b, bearings=bearings, M=M0, scale=s0, shift=T0,
                                     tolerance_rad=2 * THRESHOLD, **frames)
    assert overlaps >= 50 and found == 0  # b's points lie behind a's walls, a's behind b's
    assert not contradicted(found, overlaps)
    # the same rotation and scale, room B moved 2 m into room A (a chance pair's placement): contradicted
    found, overlaps = join_conflicts(points_a, points_b, bearings=bearings, M=M0, scale=s0,
                                     shift=T0 + np.array([-2.0, 0.0, 0.0]), tolerance_rad=2 * THRESHOLD, **frames)
    assert contradicted(found, overlaps) and found >= 0.1 * overlaps
    # or turned by a quarter turn about the doorway's camera 2 and shrunk: contradicted too
    turn, c2 = _yaw(90.0), frames["C_b"][2]
    found, overlaps = join_conflicts(points_a, points_b, bearings=bearings, M=turn @ M0, scale=0.5 * s0,
                                     shift=s0 * M0 @ c2 + T0 - 0.5 * s0 * turn @ M0 @ c2 + np.array([-1.5, 0, 0]),
                                     tolerance_rad=2 * THRESHOLD, **frames)
    assert contradicted(found, overlaps)


def test_points_seen_through_a_doorway_at_the_observed_range_are_no_conflict():
    rng = np.random.default_rng(1)
    points_a, points_b, frames, bearings, (M0, T0, s0) = _two_rooms(rng)
    # model a also saw room B's points through the doorway (at their true ranges): the true join agrees with them
    X_a = np.concatenate([points_a.X, (s0 * points_b.X @ M0.T + T0)[:40]])
    rows = np.arange(N + 40)
    seen = {k: rows for k in (0, 1)}
    bearings = list(bearings)
    for k in (0, 1):
        bearings[k] = normalize(X_a - frames["C_a"][k]) @ frames["R_a"][k].T
    found, overlaps = join_conflicts(ModelPoints(X=X_a, point_of_feature=seen), points_b, bearings=bearings, M=M0,
                                     scale=s0, shift=T0, tolerance_rad=2 * THRESHOLD, **frames)
    assert overlaps >= 40 and not contradicted(found, overlaps)


def test_rays_from_one_camera_of_a_place_b_in_shape_with_the_guessed_scale():
    # b's cameras 2 and 3 both on rays from a's camera 0 (a doorway seen by two panoramas of one room): the rays
    # fix b's shape but not its size; the guessed scale (median baselines' ratio) then places b on them exactly
    M0, T0, s0 = _yaw(37.0), np.array([0.5, 0.0, -1.0]), 0.7
    C_a = {0: np.array([-1.0, 0.0, 0.3])}
    C = {2: np.array([1.2, 0.02, -0.4]), 3: np.array([2.6, -0.01, 0.9])}
    C_b = {k: M0.T @ (C[k] - T0) / s0 for k in C}
    chosen = [(CrossPair(k=k, l=0, b_k=np.zeros((0, 3)), b_l=np.zeros((0, 3)), matches=np.zeros((0, 2), int)), M0,
               normalize(C[k] - C_a[0]), None) for k in C]
    scale, shift, guessed = _place(M0, chosen, C_a, C_b, step_a=s0, step_b=1.0)
    assert guessed and abs(scale - s0) < 1e-12
    for k in C:
        assert np.linalg.norm(scale * M0 @ C_b[k] + shift - C[k]) < 1e-9
    # a direction off the plane the rays span is inconsistent with b's shape: no placement
    chosen[1] = chosen[1][:2] + (normalize(C[3] - C_a[0] + np.array([0.0, 0.4, 0.0])), None)
    assert _place(M0, chosen, C_a, C_b, step_a=s0, step_b=1.0) is None
