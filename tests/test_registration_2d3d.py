"""2D-3D matching in registration growth: an image no track ties to a model is placed by its descriptors."""

from __future__ import annotations

import numpy as np

from fullview.sfm.options import RegistrationOptions
from fullview.sfm.registration.models import build_models
from fullview.sfm.tracks import add_observations, build_tracks

from tests.test_models import _assert_matches_truth, _links, _world


def _room_with_an_unpaired_image(seed: int = 3):
    """8 cameras in one room; image 7 has no verified pair at all (so no track), but its features carry the same
    descriptors as the model's (one random unit descriptor per scene point, as ideal SIFT would)."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([rng.uniform(0, 6, 8), rng.uniform(-0.2, 0.2, 8), rng.uniform(0, 3, 8)])
    R, X, feature_of, bearings = _world(rng, centres, reach=6.0)
    links, matches = _links(R, centres, feature_of)
    unpaired = (links.pairs == 7).any(axis=1)
    links.weights[unpaired] = 0.0
    point_descriptors = rng.normal(size=(len(X), 128)).astype(np.float32)
    point_descriptors /= np.linalg.norm(point_descriptors, axis=1, keepdims=True)
    descriptors = [point_descriptors[f] for f in feature_of]
    tracks, _ = build_tracks({tuple(p): matches[tuple(p)] for p, w in zip(links.pairs, links.weights) if w > 0},
                             [len(b) for b in bearings])
    return R, centres, links, tracks, bearings, descriptors, feature_of


def test_an_image_without_tracks_is_placed_by_2d3d_matching_at_its_true_pose():
    R, centres, links, tracks, bearings, descriptors, feature_of = _room_with_an_unpaired_image()
    assert not (tracks.image_ids == 7).any()
    models = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions(),
                          descriptors=descriptors)
    assert (models.model_id == 0).all() and models.matched == [7]
    _assert_matches_truth(models, 0, R, centres, tol_deg=1e-6, tol_rel=1e-7)
    # its inlier matches joined the tracks, each with a model observation of the same scene point
    assert len(models.matches_2d3d) >= RegistrationOptions().min_resection_points
    for b, f, a, g in models.matches_2d3d:
        assert b == 7 and a != 7 and feature_of[b][f] == feature_of[a][g]
    assert (models.tracks.image_ids == 7).sum() == len(models.matches_2d3d)


def test_without_descriptors_the_image_stays_out():
    _, _, links, tracks, bearings, _, _ = _room_with_an_unpaired_image()
    models = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions())
    assert models.model_id[7] == -1 and not models.matched


def test_add_observations_joins_tracks_and_refuses_a_second_feature_of_one_image():
    matches = {(0, 1): np.array([[0, 0], [1, 1]]), (1, 2): np.array([[2, 0]]), (2, 3): np.array([[0, 0]])}
    tracks, _ = build_tracks(matches, [3, 3, 3, 3])  # tracks: {0:0, 1:0}, {0:1, 1:1}, {1:2, 2:0, 3:0}
    t01 = tracks.feature_to_track(0, 3)
    # image 3 feature 1 is new: it joins track of (0, 0); (2, 0) already sits in a track with image 1 -> skipped
    # when matched to the track of (0, 1), which has image 1 too
    new, taken = add_observations(tracks, [t01[0], t01[1]], [3, 2], [1, 0])
    assert taken.tolist() == [True, False]
    assert new.num_tracks == 3 and new.num_observations == tracks.num_observations + 1
    # a feature already in another track brings that track along when they share no image, else it is skipped
    more, _ = build_tracks({**matches, (2, 3): np.array([[0, 0], [1, 1]])}, [3, 3, 3, 3])
    t = more.feature_to_track(0, 3)
    merged, taken = add_observations(more, [t[0], t[0]], [2, 2], [1, 0])
    assert taken.tolist() == [True, False]  # (2, 1) sits in {2:1, 3:1}; (2, 0) in a track holding image 1
    assert merged.num_tracks == more.num_tracks - 1 and merged.num_observations == more.num_observations
    images, _ = merged.observations(merged.feature_to_track(0, 3)[0])
    assert images.tolist() == [0, 1, 2, 3]


def test_a_group_no_pair_joins_is_placed_by_2d3d_matching_not_left_a_model_of_its_own():
    rng = np.random.default_rng(5)
    centres = np.column_stack([rng.uniform(0, 6, 10), rng.uniform(-0.2, 0.2, 10), rng.uniform(0, 3, 10)])
    R, X, feature_of, bearings = _world(rng, centres, reach=6.0)
    links, matches = _links(R, centres, feature_of)
    group = links.pairs >= 6
    links.weights[group[:, 0] != group[:, 1]] = 0.0  # no pair between images 0-5 and 6-9: two groups
    point_descriptors = rng.normal(size=(len(X), 128)).astype(np.float32)
    point_descriptors /= np.linalg.norm(point_descriptors, axis=1, keepdims=True)
    tracks, _ = build_tracks({tuple(p): matches[tuple(p)] for p, w in zip(links.pairs, links.weights) if w > 0},
                             [len(b) for b in bearings])
    without = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions())
    assert without.sizes() == [6, 4]
    models = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions(),
                          descriptors=[point_descriptors[f] for f in feature_of])
    assert models.sizes() == [10] and sorted(models.matched) == [6, 7, 8, 9]
    _assert_matches_truth(models, 0, R, centres, tol_deg=1e-6, tol_rel=1e-7)
