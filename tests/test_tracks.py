"""Tests of fullview.sfm.tracks: union-find track building from pairwise matches."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fullview.sfm.tracks import Tracks, build_tracks


def _track_set(tracks: Tracks) -> set[frozenset[tuple[int, int]]]:
    """Tracks as a set of sets of (image, feature) pairs."""
    return {
        frozenset(zip(*(a.tolist() for a in tracks.observations(t)), strict=True)) for t in range(tracks.num_tracks)
    }


def _check_layout(tracks: Tracks) -> None:
    """Flat arrays are sorted by track then image, and offsets match the track ids."""
    assert tracks.offsets[0] == 0 and tracks.offsets[-1] == tracks.num_observations
    assert np.array_equal(np.repeat(np.arange(tracks.num_tracks), tracks.lengths), tracks.track_ids)
    key = tracks.track_ids * tracks.num_images + tracks.image_ids
    assert (np.diff(key) > 0).all()  # sorted, and no image twice in a track


def test_chain_merges_into_one_track():
    matches = {(0, 1): np.array([[0, 5]]), (1, 2): np.array([[5, 7]])}
    tracks, stats = build_tracks(matches, [3, 6, 8])
    assert tracks.num_tracks == 1
    assert _track_set(tracks) == {frozenset({(0, 0), (1, 5), (2, 7)})}
    assert stats.num_inconsistent == 0 and stats.num_short == 0 and stats.num_matches == 2
    _check_layout(tracks)


def test_conflicting_track_is_dropped_and_counted():
    matches = {
        (0, 1): np.array([[1, 2], [0, 0]]),
        (1, 2): np.array([[2, 3], [0, 0]]),
        (0, 2): np.array([[1, 4]]),  # closes the loop on a different feature of image 2
    }
    tracks, stats = build_tracks(matches, [2, 3, 5])
    assert _track_set(tracks) == {frozenset({(0, 0), (1, 0), (2, 0)})}
    assert stats.num_inconsistent == 1 and stats.num_components == 2 and stats.num_tracks == 1


def test_one_feature_matched_twice_in_same_image_is_inconsistent():
    tracks, stats = build_tracks({(0, 1): np.array([[0, 1], [0, 2], [3, 3]])}, [4, 4])
    assert _track_set(tracks) == {frozenset({(0, 3), (1, 3)})}
    assert stats.num_inconsistent == 1


def test_reverse_and_duplicate_pairs_are_merged():
    matches = {(0, 1): np.array([[2, 3], [2, 3]]), (1, 0): np.array([[3, 2]]), (2, 1): np.array([[0, 3]])}
    tracks, _ = build_tracks(matches, [3, 4, 1])
    assert _track_set(tracks) == {frozenset({(0, 2), (1, 3), (2, 0)})}


def test_min_length_drops_short_tracks():
    matches = {(0, 1): np.array([[0, 0], [1, 1]]), (1, 2): np.array([[0, 0]])}
    tracks, stats = build_tracks(matches, [2, 2, 2], min_length=3)
    assert _track_set(tracks) == {frozenset({(0, 0), (1, 0), (2, 0)})}
    assert stats.num_short == 1


def test_random_tracks_are_recovered_and_bad_merges_dropped():
    rng = np.random.default_rng(3)
    num_images, num_tracks = 12, 400
    num_features = rng.integers(500, 800, size=num_images)
    # Ground truth: each track visits 2..6 distinct images with distinct random features.
    perm = [rng.permutation(n) for n in num_features]
    used = np.zeros(num_images, dtype=int)
    truth = []
    for _ in range(num_tracks):
        images = np.sort(rng.choice(num_images, size=rng.integers(2, 7), replace=False))
        obs = [(int(i), int(perm[i][used[i]])) for i in images]
        used[images] += 1
        truth.append(obs)
    # Matches: a random spanning tree of each track, plus one redundant edge when possible.
    matches: dict[tuple[int, int], list] = {}
    for obs in truth:
        order = rng.permutation(len(obs))
        edges = [(obs[order[k]], obs[order[rng.integers(0, k)]]) for k in range(1, len(obs))]
        if len(obs) > 2:
            edges.append((obs[order[0]], obs[order[-1]]))
        for (i, fi), (j, fj) in edges:
            matches.setdefault((i, j), []).append((fi, fj))
    # Wrong matches joining pairs of tracks that share an image: both tracks become inconsistent.
    bad = set()
    for a, b in rng.choice(num_tracks, size=(15, 2), replace=False):
        ia, ib = dict(truth[a]), dict(truth[b])
        common = sorted(set(ia) & set(ib))
        only_a = sorted(set(ia) - set(ib))
        if not common or not only_a:
            continue
        i, j = only_a[0], common[0]
        matches.setdefault((i, j), []).append((ia[i], ib[j]))
        bad |= {a, b}
    tracks, stats = build_tracks({k: np.array(v) for k, v in matches.items()}, num_features)
    expected = {frozenset(obs) for t, obs in enumerate(truth) if t not in bad}
    assert _track_set(tracks) == expected
    assert stats.num_inconsistent >= 1 and len(bad) >= 4
    assert stats.num_tracks + stats.num_inconsistent + stats.num_short == stats.num_components
    _check_layout(tracks)


def test_subset_and_feature_lookup():
    matches = {(0, 1): np.array([[0, 1], [1, 0], [2, 2]]), (1, 2): np.array([[1, 0]])}
    tracks, _ = build_tracks(matches, [3, 3, 1])
    assert tracks.num_tracks == 3
    assert sorted(tracks.lengths.tolist()) == [2, 2, 3]
    lookup = tracks.feature_to_track(1, 3)
    for t in range(tracks.num_tracks):
        images, features = tracks.observations(t)
        assert lookup[features[images == 1]].tolist() == [t]
    keep = tracks.lengths == 3
    sub = tracks.subset(keep)
    assert sub.num_tracks == 1 and _track_set(sub) == {frozenset({(0, 0), (1, 1), (2, 0)})}
    _check_layout(sub)
    empty = tracks.subset(np.zeros(3, dtype=bool))
    assert empty.num_tracks == 0 and empty.num_observations == 0


def test_no_matches_gives_no_tracks():
    tracks, stats = build_tracks({(0, 1): np.zeros((0, 2), dtype=int)}, [5, 5])
    assert tracks.num_tracks == 0 and stats.num_components == 0
    assert tracks.offsets.tolist() == [0]


@pytest.mark.parametrize(
    ("matches", "message"),
    [
        ({(0, 0): np.array([[0, 1]])}, "key"),
        ({(0, 3): np.array([[0, 1]])}, "key"),
        ({(0, 1): np.array([[0, 5]])}, "out of range"),
        ({(0, 1): np.array([[-1, 0]])}, "out of range"),
        ({(0, 1): np.array([0, 1, 2])}, r"\(M, 2\)"),
        ({(0, 1): np.array([[0.0, 1.0]])}, r"\(M, 2\)"),
    ],
)
def test_bad_input_names_the_value(matches, message):
    with pytest.raises(ValueError, match=message):
        build_tracks(matches, [3, 5, 2])


def test_track_counts_cover_all_pairs():
    """Every pair of observations of a kept track is connected through matches (sanity on a grid)."""
    # Full matching of 4 images with 10 features each, feature f <-> f: 10 tracks of length 4.
    matches = {(i, j): np.stack([np.arange(10)] * 2, 1) for i, j in itertools.combinations(range(4), 2)}
    tracks, stats = build_tracks(matches, [10] * 4)
    assert tracks.num_tracks == 10 and (tracks.lengths == 4).all()
    assert stats.num_matches == 60
