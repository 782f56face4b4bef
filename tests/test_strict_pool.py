"""Noisy pairs matched at a looser ratio: the strict matches lead (`sfm.matching.match_pair`), and the filter draws its
hypotheses from them only while every match counts (`two_view.RansacOptions.sample_pool`)."""
import numpy as np
import pytest

from fullview.sfm import two_view as tv
from fullview.sfm import upright as up
from fullview.sfm import wall_check
from fullview.sfm.camera import normalize
from fullview.sfm.matching import descriptor_basis, match_descriptors, match_pair, project_descriptors
from fullview.sfm.options import FilterOptions, MatchesOptions
from fullview.sfm.registration.poses import yaw_rotation
from fullview.stages import filter as filter_stage

THRESHOLD = np.radians(0.35)
LEVEL = (up.Y_AXIS, up.Y_AXIS)


def _descriptor_pair(seed, n=600, shared=300):
    """Two RootSIFT-like unit descriptor sets: `shared` of i's rows reappear in j with noise of many strengths (a
    noisy capture's descriptors of the same points: some stay distinctive, some not), the rest are unrelated."""
    rng = np.random.default_rng(seed)
    a = np.abs(rng.normal(size=(n, 128))).astype(np.float32)
    b = np.abs(rng.normal(size=(n, 128))).astype(np.float32)
    noise = rng.uniform(0.0, 1.5, size=(shared, 1))
    b[:shared] = np.abs(a[:shared] + noise * rng.normal(size=(shared, 128)))
    unit = lambda d: d / np.linalg.norm(d, axis=1, keepdims=True)  # noqa: E731
    return unit(a), unit(b)


@pytest.mark.parametrize("projected", [False, True])
def test_the_strict_matches_lead_a_noisy_pairs_matches(projected):
    a, b = _descriptor_pair(0)
    options = MatchesOptions(ratio=0.8, noisy_ratio=0.9, noisy_min_noise=0.3,
                             descriptor_dims=32 if projected else 0)
    kwargs = {}
    if projected:
        basis = descriptor_basis([a, b], 32)
        a_p, b_p = project_descriptors(a, basis), project_descriptors(b, basis)
        kwargs = {"full": (a, b)}
    else:
        a_p, b_p = a, b
    loose, strict_count = match_pair(a_p, b_p, options, 0.55, 0.1, **kwargs)
    strict = match_descriptors(a_p, b_p, options, **kwargs)
    # the matches at the strict ratio, in their order, are exactly the loose set's head
    assert 0 < strict_count == len(strict) < len(loose)
    assert np.array_equal(loose[:strict_count], strict)
    # a clean pair is matched at the strict ratio, all of it strict
    clean, clean_count = match_pair(a_p, b_p, options, 0.1, 0.1, **kwargs)
    assert np.array_equal(clean, strict) and clean_count == len(clean)


def _levelled_pair(seed, n, inliers, noise_deg=0.03, R=None, C=None):
    """n matches of a levelled pair (gravity = the y axis), the first `inliers` true, the rest random."""
    rng = np.random.default_rng(seed)
    R = yaw_rotation(rng.uniform(-np.pi, np.pi)) if R is None else R
    C = normalize(rng.normal(size=3)) if C is None else C
    P = rng.normal(size=(n, 3)) * 4
    b_i = normalize(normalize(P) + rng.normal(size=(n, 3)) * np.radians(noise_deg))
    b_j = normalize(normalize((P - C) @ R.T) + rng.normal(size=(n, 3)) * np.radians(noise_deg))
    b_j[inliers:] = normalize(rng.normal(size=(n - inliers, 3)))
    return b_i, b_j, R, C


def _inlier_truth(b_i, b_j, R, C):
    """Which matches the pose X_j = R (X_i − C) explains within the threshold."""
    return tv.epipolar_angular_errors(wall_check.f_of_pose(R, -R @ C), b_i, b_j) < THRESHOLD


def test_an_all_pool_search_is_the_plain_search():
    b_i, b_j, _, _ = _levelled_pair(1, 80, 40)
    opts = tv.RansacOptions(threshold_rad=THRESHOLD, seed=3)
    plain, pooled = up.ransac_f_upright(b_i, b_j, opts), up.ransac_f_upright(b_i, b_j, tv.RansacOptions(
        threshold_rad=THRESHOLD, seed=3, sample_pool=80))
    assert np.array_equal(plain.F, pooled.F) and plain.iterations == pooled.iterations


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hypotheses_come_from_the_strict_head_and_the_loose_tail_counts(seed):
    """The strict head: 20 true matches of 40. The loose tail: 200 matches, of which 30 true and 90 of one wrong
    pose (a repeated structure, as many ratio-test survivors are). Sampled over all, the wrong pose has the most
    support and wins; sampled from the head, the true pose is found, and the tail's true matches are its inliers."""
    rng = np.random.default_rng(seed + 100)
    head_i, head_j, R, C = _levelled_pair(seed, 40, 20)
    tail_i, tail_j, _, _ = _levelled_pair(seed + 10, 200, 30, R=R, C=C)
    R_wrong, C_wrong = yaw_rotation(rng.uniform(-np.pi, np.pi)), normalize(rng.normal(size=3))
    wrong_i, wrong_j, _, _ = _levelled_pair(seed + 20, 90, 90, R=R_wrong, C=C_wrong)
    tail_i[30:120], tail_j[30:120] = wrong_i, wrong_j
    b_i, b_j = np.concatenate([head_i, tail_i]), np.concatenate([head_j, tail_j])
    truth = _inlier_truth(b_i, b_j, R, C)
    unpooled = up.ransac_f_upright(b_i, b_j, tv.RansacOptions(threshold_rad=THRESHOLD, seed=seed))
    pooled = up.ransac_f_upright(b_i, b_j, tv.RansacOptions(threshold_rad=THRESHOLD, seed=seed, sample_pool=40))
    assert (unpooled.inliers & truth).sum() < 10  # the wrong pose
    assert (pooled.inliers & truth).sum() >= 0.95 * truth.sum() and (pooled.inliers & ~truth).sum() <= 5
    assert pooled.inliers[40:].sum() >= 28  # the loose tail's true matches count


def test_a_noisy_pairs_search_is_bounded_by_its_strict_matches(monkeypatch):
    """A pair of chance matches whose loose tail quadruples them: the hypothesis cap is the strict head's, not the
    cube of the loose count's (what made a looser ratio cost the filter 3-5x)."""
    b_i, b_j, _, _ = _levelled_pair(0, 140, 0)
    matches = np.stack([np.arange(140), np.arange(140)], axis=1)
    drawn = []
    fit = up.ransac_f_upright
    monkeypatch.setattr(up, "ransac_f_upright", lambda *a: drawn.append(a[2]) or fit(*a))
    options = FilterOptions()
    for pool in (35, None):
        filter_stage._verify_pair(b_i, b_j, matches, None, THRESHOLD, options, seed=0, gravity=LEVEL,
                                  needed=options.min_inliers_upright, pool=pool)
    strict, loose = drawn
    assert strict.sample_pool == 35 and loose.sample_pool == 0
    assert strict.max_iterations <= 300 < loose.max_iterations
