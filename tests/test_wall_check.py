"""A pair's yaw checked against its images' wall directions (fullview.sfm.wall_check, filter._checked_against_walls)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm import two_view
from fullview.sfm.camera import normalize
from fullview.sfm.rotations import rotation_angle_deg
from fullview.sfm.wall_check import (f_of_pose, inlier_plane, plane_poses, pose_the_plane_allows, pose_the_walls_allow,
                                      turn, wall_residual_deg)
from fullview.stages.filter import _checked_against_walls

THRESHOLD = np.radians(0.35)
DOWN = np.array([0.0, 1.0, 0.0])  # world y down
WALL = np.array([1.0, 0.0, 0.0])  # the world's walls run along x and z


def _camera(yaw_deg: float, tilt_deg: float = 0.0) -> np.ndarray:
    """R cam from world: a yaw about the vertical, then a small tilt (an inexact zenith correction)."""
    return (Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
            @ Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix())


def _pair(rng, n_true: int, n_junk: int, yaw_i=20.0, yaw_j=-65.0):
    R_i, R_j = _camera(yaw_i, 0.4), _camera(yaw_j, -0.3)
    C_i, C_j = np.zeros(3), np.array([1.4, 0.03, 0.6])
    X = rng.uniform([-4, -1, -4], [4, 1.2, 4], (n_true, 3))
    b_i = normalize((X - C_i) @ R_i.T)
    b_j = normalize((X - C_j) @ R_j.T)
    b_i = np.concatenate([b_i, normalize(rng.normal(size=(n_junk, 3)))])
    b_j = np.concatenate([b_j, normalize(rng.normal(size=(n_junk, 3)))])
    R_ji = R_j @ R_i.T
    frames = dict(axis_i=R_i @ WALL, axis_j=R_j @ WALL, gravity_j=R_j @ DOWN)
    return b_i, b_j, R_ji, R_j @ (C_i - C_j), frames, (R_i, R_j)


def test_the_residual_is_the_yaw_error_modulo_90_and_turning_by_it_aligns_the_walls():
    rng = np.random.default_rng(0)
    _, _, R_ji, _, f, (R_i, R_j) = _pair(rng, 5, 0)
    assert abs(wall_residual_deg(R_ji, f["axis_i"], f["axis_j"], f["gravity_j"])) < 1e-9
    for error in (7.0, -23.0, 90.0, 101.8, -178.0):
        wrong = turn(f["gravity_j"], error) @ R_ji
        residual = wall_residual_deg(wrong, f["axis_i"], f["axis_j"], f["gravity_j"])
        assert abs(residual - ((-error + 45.0) % 90.0 - 45.0)) < 1e-9  # minus the error, modulo 90°
        fixed = turn(f["gravity_j"], residual) @ wrong
        assert abs(wall_residual_deg(fixed, f["axis_i"], f["axis_j"], f["gravity_j"])) < 1e-9
        # a multiple of 90° from the truth: the walls cannot tell it apart
        assert min(rotation_angle_deg(turn(f["gravity_j"], 90.0 * q) @ fixed, R_ji) for q in range(4)) < 1e-6


def test_the_pose_the_walls_allow_is_the_true_one_from_a_wrong_yaw():
    rng = np.random.default_rng(1)
    b_i, b_j, R_ji, t_ji, f, _ = _pair(rng, n_true=14, n_junk=30)
    for error in (5.7, 88.3, 118.3, -101.8):
        wrong = turn(f["gravity_j"], error) @ R_ji
        R, t, inliers = pose_the_walls_allow(b_i, b_j, wrong, f["axis_i"], f["axis_j"], f["gravity_j"], THRESHOLD)
        assert rotation_angle_deg(R, R_ji) < 1e-6
        assert np.degrees(np.arccos(np.clip(normalize(t) @ normalize(t_ji), -1, 1))) < 0.2
        assert inliers[:14].all() and inliers[14:].sum() <= 3


def _frames(f, n=2):
    axis = np.array([f["axis_i"], f["axis_j"]])
    gravity = np.array([f["gravity_j"], f["gravity_j"]])  # the check reads j's
    return axis, np.full(n, np.radians(0.05)), gravity, np.full(n, np.radians(0.05))


def test_a_weak_pair_whose_fit_contradicts_the_walls_takes_their_pose_a_fit_that_agrees_stays():
    """A weak pair fitted at a yaw the walls do not allow takes the walls' pose (its true matches); the true fit, and
    a fit within the tolerance of the walls, are left alone."""
    rng = np.random.default_rng(2)
    b_i, b_j, R_ji, t_ji, f, _ = _pair(rng, n_true=16, n_junk=30)
    matches = np.column_stack([np.arange(len(b_i))] * 2)
    for error in (3.0, 5.7, 10.0):
        wrong = turn(f["gravity_j"], error) @ R_ji
        t_wrong, keep = two_view.baseline_given_rotation(b_i, b_j, wrong, THRESHOLD)
        assert keep.sum() >= 5
        F_out, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(wrong, t_wrong), keep, _frames(f), 0,
                                                  1, THRESHOLD, 0, 30)
        assert how == "fitted" and kept[:16].all()
    # the true fit is left alone, and so is a fit within the tolerance of the walls (0.5°, below 1°)
    for error in (0.0, 0.5):
        R = turn(f["gravity_j"], error) @ R_ji
        t, keep = two_view.baseline_given_rotation(b_i, b_j, R, THRESHOLD)
        F_out, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(R, t), keep, _frames(f), 0, 1,
                                                  THRESHOLD, 0, 30)
        assert how == "" and (kept == keep).all() and kept.sum() >= 14
    # an image without a wall axis: no check
    no_axis = dict(f, axis_j=np.full(3, np.nan))
    wrong = turn(f["gravity_j"], 5.7) @ R_ji
    t_wrong, keep = two_view.baseline_given_rotation(b_i, b_j, wrong, THRESHOLD)
    F_out, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(wrong, t_wrong), keep, _frames(no_axis),
                                              0, 1, THRESHOLD, 0, 30)
    assert how == "" and (kept == keep).all()


def test_a_strong_fit_the_walls_explain_far_worse_stays():
    """Walls not at right angles (an axis 30° off): the walls' best pose explains few of a strong pair's matches, so
    its fit stays; where the walls' pose explains as many, it replaces the strong fit."""
    rng = np.random.default_rng(4)
    b_i, b_j, R_ji, t_ji, f, _ = _pair(rng, n_true=40, n_junk=20)
    matches = np.column_stack([np.arange(len(b_i))] * 2)
    keep = two_view.consistent_with_pose(b_i, b_j, R_ji, t_ji, THRESHOLD)
    skewed = dict(f, axis_j=turn(f["gravity_j"], 30.0) @ f["axis_j"])
    F_out, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(R_ji, t_ji), keep, _frames(skewed), 0, 1,
                                           THRESHOLD, 0, 30)
    assert how == "" and (kept == keep).all()
    off = dict(f, axis_j=turn(f["gravity_j"], 5.0) @ f["axis_j"])  # the walls' pose 5° off still explains most
    F_out, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(R_ji, t_ji), keep, _frames(off), 0, 1,
                                           THRESHOLD, 0, 30)
    walls_pose = turn(f["gravity_j"], -5.0) @ R_ji
    explained = two_view.baseline_given_rotation(b_i, b_j, walls_pose, THRESHOLD)[1].sum()
    assert (how == "fitted") == (explained >= 0.9 * keep.sum())


def _wall_pair(rng, n: int, yaw_i=-174.7, yaw_j=98.7):
    """Two upright cameras 1.0 and 1.7 m in front of one wall (the plane z = 1.6, normal along the world's z: one
    of the walls' directions) and n points on it: new home seed 80's 023-024 doorway, whose matches all lie on the
    wall between them."""
    R_i, R_j = _camera(yaw_i), _camera(yaw_j)
    C_i, C_j = np.array([0.0, 0.0, 0.6]), np.array([1.53, 0.01, -0.1])
    X = np.column_stack([rng.uniform(-0.8, 1.5, n), rng.uniform(-0.6, 1.4, n), np.full(n, 1.6)])
    b_i, b_j = normalize((X - C_i) @ R_i.T), normalize((X - C_j) @ R_j.T)
    return b_i, b_j, R_j @ R_i.T, normalize(R_j @ (C_i - C_j)), (R_i, R_j)


def test_a_walls_matches_fix_two_poses_and_the_plane_check_takes_the_one_that_puts_the_wall_on_js_walls():
    """Noise-free points on one wall: the homography's other pose (59° off, within 0.4° of upright) explains nearly
    every match (58 of 60: two fall behind a camera); with only j's wall axis known, the wall's normal picks the true pose back to 1e-6° and its baseline
    direction to 0.01°; given the true pose, the check leaves it."""
    rng = np.random.default_rng(3)
    b_i, b_j, R_ji, t_ji, (R_i, R_j) = _wall_pair(rng, 60)
    plane = inlier_plane(b_i, b_j, R_ji, t_ji)
    assert plane is not None
    others = [R for R, _, _ in plane_poses(R_ji, t_ji, *plane) if rotation_angle_deg(R, R_ji) > 1.0]
    assert len(others) == 1 and rotation_angle_deg(others[0], R_ji) > 20.0
    wrong = others[0]
    t_wrong, keep = two_view.baseline_given_rotation(b_i, b_j, wrong, THRESHOLD)
    assert keep.sum() >= 0.9 * len(keep)  # the wrong pose explains nearly every match: the matches cannot tell
    axis_j, g_i, g_j = R_j @ WALL, R_i @ DOWN, R_j @ DOWN
    R, t, inliers = pose_the_plane_allows(b_i, b_j, keep, wrong, t_wrong, axis_j, g_i, g_j, THRESHOLD)
    assert rotation_angle_deg(R, R_ji) < 1e-6
    assert np.degrees(np.arccos(np.clip(normalize(t) @ t_ji, -1, 1))) < 0.01
    assert inliers.all()
    t_true, keep = two_view.baseline_given_rotation(b_i, b_j, R_ji, THRESHOLD)
    assert pose_the_plane_allows(b_i, b_j, keep, R_ji, t_true, axis_j, g_i, g_j, THRESHOLD) is None


def test_the_plane_check_leaves_pairs_whose_points_are_not_one_wall():
    """Points spread through the room fix the pose: no plane, no change; points on the floor: a plane whose normal
    says nothing about the yaw, no change either."""
    rng = np.random.default_rng(4)
    b_i, b_j, R_ji, t_ji, f, (R_i, R_j) = _pair(rng, n_true=60, n_junk=0)
    keep = np.ones(len(b_i), bool)
    assert inlier_plane(b_i, b_j, R_ji, t_ji) is None
    wrong = turn(f["gravity_j"], 30.0) @ R_ji
    t_wrong, keep = two_view.baseline_given_rotation(b_i, b_j, wrong, THRESHOLD)
    assert pose_the_plane_allows(b_i, b_j, keep, wrong, t_wrong, f["axis_j"], R_i @ DOWN, R_j @ DOWN,
                                 THRESHOLD) is None
    C_i, C_j = np.zeros(3), np.array([1.4, 0.0, 0.6])
    X = np.column_stack([rng.uniform(-3, 3, 60), np.full(60, 1.5), rng.uniform(-3, 3, 60)])  # the floor, y down
    b_i, b_j = normalize((X - C_i) @ R_i.T), normalize((X - C_j) @ R_j.T)
    t_ji = normalize(R_j @ (C_i - C_j))
    assert inlier_plane(b_i, b_j, R_ji, t_ji) is not None
    keep = np.ones(60, bool)
    assert pose_the_plane_allows(b_i, b_j, keep, turn(f["gravity_j"], 30.0) @ R_ji, t_ji, f["axis_j"], R_i @ DOWN,
                                 R_j @ DOWN, THRESHOLD) is None


def test_the_filter_fixes_a_wall_pair_when_only_one_image_has_a_wall_axis_whichever_it_is():
    """`_checked_against_walls` with one image's axis unknown (NaN): the wrong decomposition is replaced by the
    true pose, with the axis on j or, the pair swapped, on i."""
    rng = np.random.default_rng(5)
    b_i, b_j, R_ji, t_ji, (R_i, R_j) = _wall_pair(rng, 60)
    plane = inlier_plane(b_i, b_j, R_ji, t_ji)
    wrong = [R for R, _, _ in plane_poses(R_ji, t_ji, *plane) if rotation_angle_deg(R, R_ji) > 1.0][0]
    t_wrong, keep = two_view.baseline_given_rotation(b_i, b_j, wrong, THRESHOLD)
    matches = np.column_stack([np.arange(60)] * 2)
    gravity = np.array([R_i @ DOWN, R_j @ DOWN])
    for known in (0, 1):
        axis = np.full((2, 3), np.nan)
        axis[known] = (R_i, R_j)[known] @ WALL
        frames = (axis, np.where(np.isnan(axis[:, 0]), np.nan, np.radians(0.05)), np.where(np.isnan(axis), np.nan,
                  gravity), np.full(2, np.radians(0.05)))
        F, kept, how = _checked_against_walls(b_i, b_j, matches, f_of_pose(wrong, t_wrong), keep, frames, 0, 1,
                                              THRESHOLD, 0, 30, gravity=gravity)
        assert how == "fitted" and kept.all()
        pose = two_view.relative_pose_from_f(F, b_i, b_j)
        assert rotation_angle_deg(pose.R_j_from_i, R_ji) < 1e-6


def test_a_planar_patch_counts_from_the_extent_that_fixes_its_normal_within_the_wall_tolerance():
    """PLANE_MIN_EXTENT's derivation: 8 points spread by it across a wall, scattered through the plane band, give a
    normal whose tilt (rms) is PLANE_TOLERANCE_DEG; and `inlier_plane` takes a patch wider than that, not a
    narrower one."""
    from fullview.sfm.wall_check import PLANE_MIN_EXTENT, PLANE_OFFSET, PLANE_TOLERANCE_DEG
    rng, d = np.random.default_rng(5), 1.5

    def patch(n, extent):
        a = extent * d * np.sqrt(3.0)  # uniform half-width of that standard deviation
        return np.column_stack([rng.uniform(-a, a, n), rng.uniform(-a, a, n),
                                d + rng.uniform(-0.95, 0.95, n) * PLANE_OFFSET * d])

    tilts = []
    for _ in range(2000):
        X = patch(8, PLANE_MIN_EXTENT)
        normal = np.linalg.svd(X - X.mean(axis=0))[2][2]
        tilts.append(np.degrees(np.arcsin(abs(normal[0]) / np.linalg.norm(normal))))
    rms = np.sqrt(np.mean(np.square(tilts)))
    assert 0.8 * PLANE_TOLERANCE_DEG < rms < 1.25 * PLANE_TOLERANCE_DEG, rms
    C_j = np.array([1.0, 0.0, 0.0])  # camera i at the origin, both unrotated; the baseline is the unit
    t_ji = -C_j
    for extent, found in ((1.5 * PLANE_MIN_EXTENT, True), (0.6 * PLANE_MIN_EXTENT, False)):
        X = patch(40, extent)
        plane = inlier_plane(normalize(X), normalize(X - C_j), np.eye(3), t_ji)
        assert (plane is not None) == found, extent
        if found:
            assert np.degrees(np.arccos(abs(plane[0][2]))) < PLANE_TOLERANCE_DEG and abs(plane[1] - d) < 0.02 * d
