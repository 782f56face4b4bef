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


def _pair(rng, num_matches: int, num_hand: int, hand_noise_deg: float, matches_pose=(R_J_FROM_I, C_J)):
    """Bearings of two cameras: `num_matches` exact matches of the pose `matches_pose` followed by `num_hand` clicks
    of the true pose with noise. Returns bear_i, bear_j, matches, hand (rows of feature indices)."""
    X = rng.uniform(-4, 4, (num_matches + num_hand, 3)) + [0, 0, 6] * rng.choice([-1, 1], (num_matches + num_hand, 1))
    bear_i = _bearings(X, np.eye(3), np.zeros(3))
    bear_j = np.concatenate([_bearings(X[:num_matches], *matches_pose), _bearings(X[num_matches:], R_J_FROM_I, C_J)])
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
