"""Two models joined by the weak pairs between them (fullview.sfm.registration.weak_joins)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.registration.weak_joins import CrossPair, _share_cameras, join_by_weak_pairs
from fullview.sfm.rotations import rotation_angle_deg

THRESHOLD = np.radians(0.35)
DOWN = np.array([0.0, 1.0, 0.0])  # world y points down, as in the synthetic scenes


def _yaw(deg: float) -> np.ndarray:
    return Rotation.from_euler("y", deg, degrees=True).as_matrix()


def _scene(rng, true_per_pair, raw_per_pair: int, noise_deg: float = 0.0):
    """Model a: cameras 0-2 in the true frame; model b: cameras 3-5 in a frame x_a = s0 M0 x_b + T0. Cross pairs
    (3, 0), (3, 1), (4, 0), (4, 1), (5, 2): `true_per_pair` (one count, or one per pair) true matches among
    `raw_per_pair`, the rest random; the true bearings turned by `noise_deg` (rms per axis) about random axes."""
    centers = np.array([[0, 0, 0], [1.5, 0.05, 0.3], [3.0, -0.03, 0.1], [4.6, 0.02, 0.4], [6.1, 0, 0.0],
                        [7.5, 0.04, 0.5]], float)
    R = np.array([_yaw(a) for a in rng.uniform(0, 360, len(centers))])  # cam from world, level
    M0, s0, T0 = _yaw(37.0), 0.4, np.array([2.0, 0.1, -1.0])
    R_b = {k: R[k] @ M0 for k in (3, 4, 5)}
    C_b = {k: M0.T @ (centers[k] - T0) / s0 for k in (3, 4, 5)}
    gravity = R @ DOWN
    bearings, cross = {}, []
    counts = np.broadcast_to(true_per_pair, 5)
    for (k, l), true_count in zip(((3, 0), (3, 1), (4, 0), (4, 1), (5, 2)), counts):
        X = (centers[k] + centers[l]) / 2 + rng.uniform(-3, 3, (true_count, 3)) * [1, 0.4, 1]
        X[:, 2] += np.where(rng.random(true_count) < 0.5, 2.5, -2.5)  # walls either side of the walk
        b_k = _jitter(rng, normalize((X - centers[k]) @ R[k].T), noise_deg)
        b_l = _jitter(rng, normalize((X - centers[l]) @ R[l].T), noise_deg)
        junk = raw_per_pair - true_count
        b_k = np.concatenate([b_k, normalize(rng.normal(size=(junk, 3)))])
        b_l = np.concatenate([b_l, normalize(rng.normal(size=(junk, 3)))])
        feats = np.arange(raw_per_pair)
        cross.append(CrossPair(k=k, l=l, b_k=b_k, b_l=b_l, matches=np.column_stack([feats, feats])))
    R_a = {k: R[k] for k in (0, 1, 2)}
    C_a = {k: centers[k] for k in (0, 1, 2)}
    return dict(R_a=R_a, C_a=C_a, R_b=R_b, C_b=C_b, gravity=gravity, cross=cross), (M0, s0, T0)


def _jitter(rng, bearings: np.ndarray, noise_deg: float) -> np.ndarray:
    if not noise_deg:
        return bearings
    turns = Rotation.from_rotvec(rng.normal(scale=np.radians(noise_deg), size=bearings.shape))
    return turns.apply(bearings)


def test_agreeing_weak_pairs_join_two_models_at_the_true_similarity():
    rng = np.random.default_rng(0)
    inputs, (M0, s0, T0) = _scene(rng, true_per_pair=10, raw_per_pair=35)
    join = join_by_weak_pairs(**inputs, threshold_rad=THRESHOLD, step_a=1.5, step_b=1.5 / 0.4 * 1.3)
    assert join is not None and len(join.pairs) >= 3 and not join.scale_guessed
    # noise-free true matches; a chance match within the threshold may join a pair's inliers and tilt its fit a little
    assert rotation_angle_deg(join.M, M0) < 0.2
    assert join.scale == pytest.approx(s0, rel=0.03)
    for k in (3, 4, 5):  # b's cameras placed where they are (the walk is 7.5 m long)
        placed = join.scale * join.M @ inputs["C_b"][k] + join.shift
        assert np.linalg.norm(placed - (s0 * M0 @ inputs["C_b"][k] + T0)) < 0.2
    # the agreeing pairs' inliers are their true matches (features 0-9 of each pair), chance ones are rare
    true = [f < 10 and g < 10 for _, f, _, g in join.inlier_matches]
    assert sum(true) >= 30 and np.mean(true) > 0.9


def test_chance_matches_join_nothing():
    for seed in range(4):
        inputs, _ = _scene(np.random.default_rng(seed), true_per_pair=0, raw_per_pair=35)
        assert join_by_weak_pairs(**inputs, threshold_rad=THRESHOLD, step_a=1.5, step_b=3.75) is None


def test_two_agreeing_pairs_are_not_enough():
    rng = np.random.default_rng(1)
    inputs, _ = _scene(rng, true_per_pair=10, raw_per_pair=35)
    inputs["cross"] = inputs["cross"][:2]
    assert join_by_weak_pairs(**inputs, threshold_rad=THRESHOLD, step_a=1.5, step_b=3.75) is None


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_one_fit_guides_pairs_too_weak_to_fit_alone_into_the_join(seed):
    # one doorway pair of 12 true matches fits alone; the others hold 6 true among 35 (0.1° noise), too few for the
    # 3-unknown upright fit to reach 6 inliers, but under the first pair's rotation their 2-unknown baselines do
    inputs, (M0, s0, T0) = _scene(np.random.default_rng(seed), true_per_pair=(12, 6, 6, 6, 6), raw_per_pair=35,
                                  noise_deg=0.1)
    args = dict(threshold_rad=THRESHOLD, step_a=1.5, step_b=1.5 / 0.4 * 1.3)
    assert join_by_weak_pairs(**inputs, **args) is None
    join = join_by_weak_pairs(**inputs, **args, guided=True)
    assert join is not None and len(join.pairs) >= 3
    assert rotation_angle_deg(join.M, M0) < 0.3
    assert join.scale == pytest.approx(s0, rel=0.05)


@pytest.mark.parametrize("true_per_pair", [0, (12, 0, 0, 0, 0)])
def test_guided_join_needs_more_than_chance(true_per_pair):
    # chance matches only, or one true pair whose rotation finds only chance baselines elsewhere: nothing joins
    for seed in range(6):
        inputs, _ = _scene(np.random.default_rng(seed), true_per_pair=true_per_pair, raw_per_pair=35, noise_deg=0.1)
        assert join_by_weak_pairs(**inputs, threshold_rad=THRESHOLD, step_a=1.5, step_b=3.75, guided=True) is None


def test_guided_pairs_must_share_cameras():
    # a chain through shared cameras (3-0, 3-1, 4-1) sees one doorway; pairs of three other camera pairs do not
    def fits(*pairs):
        return [(CrossPair(k=k, l=l, b_k=np.zeros((0, 3)), b_l=np.zeros((0, 3)), matches=np.zeros((0, 2), int)),)
                for k, l in pairs]
    assert _share_cameras(fits((3, 0), (3, 1), (4, 1)))
    assert _share_cameras(fits((4, 1), (5, 2), (4, 2)))
    assert not _share_cameras(fits((3, 0), (4, 1), (5, 2)))
    assert not _share_cameras(fits((5, 0), (3, 1), (4, 1)))
