"""The filter's hypothesis cap for pairs with few matches (`stages.filter.capped_for_verification`): a retrieval pair
that sees another room has a few dozen chance matches and used to draw `filter.max_iterations` hypotheses."""
import numpy as np
import pytest

from fullview.sfm import two_view as tv
from fullview.sfm import upright as up
from fullview.sfm.camera import normalize
from fullview.sfm.options import FilterOptions
from fullview.sfm.registration.poses import yaw_rotation
from fullview.stages import filter as filter_stage

THRESHOLD = np.radians(0.35)
LEVEL = (up.Y_AXIS, up.Y_AXIS)


def _levelled_pair(seed, n, inliers, noise_deg=0.03):
    """n matches of a levelled pair (gravity = the y axis) of which the first `inliers` are true, the rest random."""
    rng = np.random.default_rng(seed)
    R, C = yaw_rotation(rng.uniform(-np.pi, np.pi)), normalize(rng.normal(size=3))
    P = rng.normal(size=(n, 3)) * 4
    b_i = normalize(normalize(P) + rng.normal(size=(n, 3)) * np.radians(noise_deg))
    b_j = normalize(normalize((P - C) @ R.T) + rng.normal(size=(n, 3)) * np.radians(noise_deg))
    b_j[inliers:] = normalize(rng.normal(size=(n - inliers, 3)))
    return b_i, b_j


def test_pair_of_chance_matches_draws_a_bounded_number_of_hypotheses(monkeypatch):
    b_i, b_j = _levelled_pair(0, 35, 0)
    drawn = []
    fit = up.ransac_f_upright
    monkeypatch.setattr(up, "ransac_f_upright", lambda *a: drawn.append(a[2].max_iterations) or fit(*a))
    matches = np.stack([np.arange(35), np.arange(35)], axis=1)
    options = FilterOptions()
    filter_stage._verify_pair(b_i, b_j, matches, None, THRESHOLD, options, seed=0, gravity=LEVEL,
                              needed=options.min_inliers_upright)
    # ratio 15/35 at 3-point samples: ~110 samples for 0.9999, doubled; it was the full 5000
    assert drawn and drawn[0] <= 300 < options.max_iterations


@pytest.mark.parametrize("n, needed, sample_size", [(600, 15, 3), (100, 15, 3), (120, 30, 8)])
def test_pairs_with_many_matches_keep_the_full_cap(n, needed, sample_size):
    opts = tv.RansacOptions(threshold_rad=THRESHOLD)
    assert filter_stage.capped_for_verification(opts, needed, n, sample_size).max_iterations == opts.max_iterations


def test_a_pair_that_can_verify_is_still_found_within_the_cap():
    """15 true matches among 38 (the weakest a levelled pair can verify with): every seed finds them all."""
    found = []
    for seed in range(20):
        b_i, b_j = _levelled_pair(seed, 38, 15)
        opts = filter_stage.capped_for_verification(tv.RansacOptions(threshold_rad=THRESHOLD, seed=seed), 15, 38,
                                                    up.UPRIGHT_SAMPLE_SIZE)
        assert opts.max_iterations < 1000
        found.append(int(up.ransac_f_upright(b_i, b_j, opts).inliers[:15].sum()))
    assert min(found) == 15, found


def test_hand_points_lower_what_the_matches_must_supply():
    """A pair with 7 hand points (too few to seed) needs only 8 inlier matches: the cap is the one for 8."""
    opts = tv.RansacOptions(threshold_rad=THRESHOLD)
    for_8 = filter_stage.capped_for_verification(opts, 8, 38, up.UPRIGHT_SAMPLE_SIZE).max_iterations
    for_15 = filter_stage.capped_for_verification(opts, 15, 38, up.UPRIGHT_SAMPLE_SIZE).max_iterations
    assert for_8 > 4 * for_15


def test_the_stage_asks_the_matches_for_what_the_hand_points_do_not_supply(monkeypatch):
    """A pair with 7 hand points (fewer than the 8 of a seed) and 38 matches: the search is capped for 15 - 7 = 8."""
    from types import SimpleNamespace
    b_i, b_j = _levelled_pair(1, 45, 0)
    hand = np.stack([np.arange(38, 45), np.arange(38, 45)], axis=1)
    ctx = SimpleNamespace(dataset=SimpleNamespace(hand_pair_matches=lambda num_sift, i, j: hand))
    raw = SimpleNamespace(pairs=[(0, 1)], matches=[np.stack([np.arange(38), np.arange(38)], axis=1)])
    asked = []
    cap = filter_stage.capped_for_verification
    monkeypatch.setattr(filter_stage, "capped_for_verification",
                        lambda opts, needed, n, size: asked.append((needed, n, size)) or cap(opts, needed, n, size))
    obs = [{"bearings": b_i}, {"bearings": b_j}]
    options = FilterOptions(upright="level")
    filter_stage._filter_pair(ctx, options, obs, [38, 38], raw, np.array(LEVEL), None, None,
                              options.min_inliers_upright, 0)
    assert asked == [(options.min_inliers_upright - 7, 38, up.UPRIGHT_SAMPLE_SIZE)]
