"""Hand points seed a pair's F, but hundreds of good matches win when their own fit explains the clicks
(fullview.stages.filter._verify_pair)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm import two_view
from fullview.sfm.camera import normalize
from fullview.sfm.options import FilterOptions
from fullview.stages.filter import _verify_pair

NO_GRAVITY = (np.full(3, np.nan), np.full(3, np.nan))
R_J_FROM_I = Rotation.from_rotvec([0.02, 0.3, -0.01]).as_matrix()
C_J = np.array([1.0, 0.1, 0.2])


def _bearings(X: np.ndarray, R: np.ndarray, centre: np.ndarray) -> np.ndarray:
    return normalize((X - centre) @ R.T)


def _pair(rng, num_matches: int, num_hand: int, hand_noise_deg: float, matches_pose=(R_J_FROM_I, C_J),
          clicks_pose=(R_J_FROM_I, C_J)):
    """Bearings of two cameras: `num_matches` exact matches of the pose `matches_pose` followed by `num_hand` clicks
    of `clicks_pose` (the true pose) with noise. Returns bear_i, bear_j, matches, hand (rows of feature indices)."""
    X = rng.uniform(-4, 4, (num_matches + num_hand, 3)) + [0, 0, 6] * rng.choice([-1, 1], (num_matches + num_hand, 1))
    bear_i = _bearings(X, np.eye(3), np.zeros(3))
    bear_j = np.concatenate([_bearings(X[:num_matches], *matches_pose), _bearings(X[num_matches:], *clicks_pose)])
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(hand_noise_deg), (num_hand, 3))).as_matrix()
    bear_j[num_matches:] = np.einsum("nab,nb->na", noise, bear_j[num_matches:])
    index = np.arange(num_matches + num_hand)
    return bear_i, bear_j, np.column_stack([index[:num_matches]] * 2), np.column_stack([index[num_matches:]] * 2)


def _rotation_error_deg(F, bear_i, bear_j, matches) -> float:
    pose = two_view.relative_pose_from_f(F, bear_i[matches[:, 0]], bear_j[matches[:, 1]])
    return float(np.degrees(Rotation.from_matrix(pose.R_j_from_i @ R_J_FROM_I.T).magnitude()))


def test_many_exact_matches_beat_a_seed_of_noisy_clicks():
    rng = np.random.default_rng(0)
    bear_i, bear_j, matches, hand = _pair(rng, num_matches=400, num_hand=10, hand_noise_deg=0.6)  # 1-2 px at 1024
    options, threshold = FilterOptions(), np.radians(FilterOptions().threshold_deg)
    F, keep = _verify_pair(bear_i, bear_j, matches, hand, threshold, options, seed=0, gravity=NO_GRAVITY)
    seeded = two_view.fit_f_seeded(bear_i[hand[:, 0]], bear_j[hand[:, 1]], bear_i[matches[:, 0]],
                                   bear_j[matches[:, 1]], threshold)
    assert keep.mean() > 0.99
    assert _rotation_error_deg(F, bear_i, bear_j, matches) < 1e-6
    assert _rotation_error_deg(seeded.F, bear_i, bear_j, matches) > 1.0  # what seeding alone gave


def test_matches_of_a_wrong_pose_do_not_replace_the_clicks():
    rng = np.random.default_rng(1)
    wrong = (Rotation.from_rotvec([0.0, 0.9, 0.0]).as_matrix(), np.array([-0.3, 0.0, 1.0]))
    bear_i, bear_j, matches, hand = _pair(rng, num_matches=300, num_hand=12, hand_noise_deg=0.1, matches_pose=wrong)
    options, threshold = FilterOptions(), np.radians(FilterOptions().threshold_deg)
    F, keep = _verify_pair(bear_i, bear_j, matches, hand, threshold, options, seed=0, gravity=NO_GRAVITY)
    hand_errors = two_view.epipolar_angular_errors(F, bear_i[hand[:, 0]], bear_j[hand[:, 1]])
    assert np.degrees(np.median(hand_errors)) < 0.5  # the clicks' pose, not the matches'
    assert keep.mean() < 0.2


def test_fit_from_a_nearby_f_reaches_the_exact_pose_without_sampling():
    rng = np.random.default_rng(2)
    bear_i, bear_j, matches, _ = _pair(rng, num_matches=300, num_hand=0, hand_noise_deg=0.0)
    b_i, b_j = bear_i[matches[:, 0]], bear_j[matches[:, 1]]
    b_j[:90] = normalize(rng.normal(size=(90, 3)))  # 30% outliers
    off = Rotation.from_rotvec([0.0, np.radians(0.5), 0.0]).as_matrix()  # a start 0.5° off, as a few clicks give
    start = two_view.skew(C_J) @ (off @ R_J_FROM_I)
    threshold = np.radians(FilterOptions().threshold_deg)
    fit = two_view.fit_f_from(start, b_i, b_j, threshold)
    assert fit.iterations == 0 and fit.inliers[90:].all() and fit.inliers[:90].mean() < 0.1
    assert _rotation_error_deg(fit.F, bear_i, bear_j, matches[90:]) < 1e-6


def test_iterations_to_beat_stops_a_search_that_cannot_find_a_better_model():
    options = two_view.RansacOptions(threshold_rad=0.01, max_iterations=5000, min_iterations=100, confidence=0.9999)
    assert two_view.iterations_to_beat(900, 1000, options).max_iterations == 100  # 90% inliers: the minimum
    bound = two_view.required_iterations(0.3, 0.9999, 3)  # 338 samples of 3 for a 30% model
    assert two_view.iterations_to_beat(300, 1000, options, sample_size=3).max_iterations == int(np.ceil(bound))
    assert two_view.iterations_to_beat(0, 1000, options).max_iterations == 5000  # nothing to beat: the full search


def test_a_wrong_gravity_does_not_spoil_a_seeded_pair():
    """Both cameras upright but their gravity estimated 3° off: the upright search finds few inliers, and the matches'
    own free fit near the clicks' F is kept, exact."""
    rng = np.random.default_rng(3)
    upright_pose = (Rotation.from_rotvec([0.0, 0.3, 0.0]).as_matrix(), C_J)
    bear_i, bear_j, matches, hand = _pair(rng, num_matches=400, num_hand=10, hand_noise_deg=0.6,
                                          matches_pose=upright_pose, clicks_pose=upright_pose)
    tilted = Rotation.from_rotvec([np.radians(3.0), 0.0, 0.0]).apply([0.0, 1.0, 0.0])
    options, threshold = FilterOptions(), np.radians(FilterOptions().threshold_deg)
    F, keep = _verify_pair(bear_i, bear_j, matches, hand, threshold, options, seed=0, gravity=(tilted, tilted))
    pose = two_view.relative_pose_from_f(F, bear_i[matches[:, 0]], bear_j[matches[:, 1]])
    assert keep.mean() > 0.99
    assert np.degrees(Rotation.from_matrix(pose.R_j_from_i @ upright_pose[0].T).magnitude()) < 1e-6
