"""Tests of fullview.sfm.registration.models: one model per group, growth by resection, merging by similarity."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.metrics import umeyama
from fullview.sfm.options import RegistrationOptions
from fullview.sfm.registration import relative_from_absolute
from fullview.sfm.registration.models import PairLinks, build_models
from fullview.sfm.rotations import rotation_angle_deg
from fullview.sfm.tracks import build_tracks


def _world(rng, centres, num_points=900, reach=4.0):
    """Level cameras at `centres`, points in a slab around them; each camera sees the points within `reach`."""
    n = len(centres)
    R = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (n, 1))).as_matrix()
    lo, hi = centres.min(0) - 3.0, centres.max(0) + 3.0
    X = rng.uniform(lo, hi, (num_points, 3))
    X[:, 1] = rng.uniform(-1.5, 1.5, num_points)
    seen = np.linalg.norm(X[None] - centres[:, None], axis=2) < reach
    feature_of = [np.flatnonzero(s) for s in seen]
    bearings = [normalize((X[f] - centres[k]) @ R[k].T) for k, f in enumerate(feature_of)]
    return R, X, feature_of, bearings


def _links(R, centres, feature_of, pairs_wanted=None, min_shared=20):
    """Every pair sharing >= min_shared points: exact relative pose, weight = shared points, matches."""
    n = len(R)
    t = -np.einsum("nab,nb->na", R, centres)
    pairs, matches = [], {}
    for i in range(n):
        for j in range(i + 1, n):
            _, a, b = np.intersect1d(feature_of[i], feature_of[j], return_indices=True)
            if len(a) >= min_shared and (pairs_wanted is None or (i, j) in pairs_wanted):
                pairs.append((i, j))
                matches[(i, j)] = np.column_stack([a, b])
    pairs = np.array(pairs)
    R_rel, t_rel = relative_from_absolute(R, t, pairs[:, 0], pairs[:, 1])
    weights = np.array([len(matches[tuple(p)]) for p in pairs], float)
    return PairLinks(pairs=pairs, R_j_from_i=R_rel, t_j_from_i=normalize(t_rel), weights=weights), matches


def _build(links, matches, bearings, **options):
    tracks, _ = build_tracks({tuple(p): matches[tuple(p)] for p, w in zip(links.pairs, links.weights) if w > 0},
                             [len(b) for b in bearings])
    return build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions(**options))


def _assert_matches_truth(models, m, R, centres, tol_deg=1e-3, tol_rel=1e-4):
    """Model m equals the truth up to a similarity (rotations and centres)."""
    k = np.flatnonzero(models.model_id == m)
    sim = umeyama(models.centers[k], centres[k])
    spread = np.linalg.norm(centres[k] - centres[k].mean(0), axis=1).mean()
    assert np.abs(sim.apply(models.centers[k]) - centres[k]).max() < tol_rel * spread
    aligned = models.R_cam_from_world[k] @ sim.R.T
    assert rotation_angle_deg(aligned, R[k]).max() < tol_deg


def test_two_separate_groups_become_two_models_largest_first():
    rng = np.random.default_rng(0)
    centres = np.concatenate([np.column_stack([np.arange(4) * 1.5, np.zeros(4), rng.uniform(-.5, .5, 4)]),
                              np.column_stack([40 + np.arange(6) * 1.5, np.zeros(6), rng.uniform(-.5, .5, 6)])])
    R, _, feature_of, bearings = _world(rng, centres, num_points=3000)
    links, matches = _links(R, centres, feature_of)
    models = _build(links, matches, bearings)
    assert models.model_id.tolist() == [1] * 4 + [0] * 6
    assert models.sizes() == [6, 4] and not models.merges
    for m in (0, 1):
        _assert_matches_truth(models, m, R, centres)


def _room_with_wrong_image():
    """8 cameras in one room; image 5's relative poses are gross outliers, its matches are right."""
    rng = np.random.default_rng(1)
    centres = np.column_stack([rng.uniform(0, 6, 8), np.zeros(8), rng.uniform(0, 3, 8)])
    R, _, feature_of, bearings = _world(rng, centres, reach=6.0)
    links, matches = _links(R, centres, feature_of)
    bad = (links.pairs == 5).any(axis=1)
    links.R_j_from_i[bad] = Rotation.from_rotvec([0.0, 2.0, 0.5]).as_matrix() @ links.R_j_from_i[bad]
    return R, centres, links, matches, bearings


def test_image_with_wrong_pair_poses_is_placed_by_resection():
    """Averaging rejects image 5's pairs and attaching along them fails, but resection places it from the model's
    points."""
    R, centres, links, matches, bearings = _room_with_wrong_image()
    models = _build(links, matches, bearings)
    assert (models.model_id == 0).all() and models.resected == [5]
    _assert_matches_truth(models, 0, R, centres)


def test_resection_off_leaves_it_out():
    _, _, links, matches, bearings = _room_with_wrong_image()
    models = _build(links, matches, bearings, resection=False)
    assert models.model_id[5] == -1 and not models.resected


def _two_rooms_joined_by_wrong_pairs():
    """Two rooms of 5 cameras whose every cross pair has a random relative pose but correct matches."""
    rng = np.random.default_rng(2)
    left = np.column_stack([np.arange(5) * 1.2, np.zeros(5), rng.uniform(-.4, .4, 5)])
    centres = np.concatenate([left, left + [7.0, 0, 0]])
    R, _, feature_of, bearings = _world(rng, centres, num_points=2500, reach=5.0)
    links, matches = _links(R, centres, feature_of)
    cross = (links.pairs < 5).any(axis=1) & (links.pairs >= 5).any(axis=1)
    assert cross.sum() > 5
    links.R_j_from_i[cross] = Rotation.random(int(cross.sum()), random_state=5).as_matrix()
    links.t_j_from_i[cross] = normalize(rng.normal(size=(int(cross.sum()), 3)))
    return R, centres, links, matches, bearings


def test_a_room_fused_through_a_contradicted_bridge_is_placed_again_by_points():
    """Averaging joins the rooms through whichever wrong cross pair its spanning tree picks (no cycle checks a
    bridge); the other cross pairs contradict it, so the room behind it is cut off and resected from points."""
    R, centres, links, matches, bearings = _two_rooms_joined_by_wrong_pairs()
    models = _build(links, matches, bearings)
    assert (models.model_id == 0).all() and sorted(models.resected) == [5, 6, 7, 8, 9]
    _assert_matches_truth(models, 0, R, centres)


@pytest.mark.parametrize("merge", [True, False])
def test_two_models_sharing_points_are_merged_by_a_similarity(merge):
    """Without resection the cut-off room becomes a model of its own; the points both models triangulate (through
    the cross pairs' matches) give the similarity that merges them."""
    R, centres, links, matches, bearings = _two_rooms_joined_by_wrong_pairs()
    models = _build(links, matches, bearings, resection=False, merge_models=merge)
    if merge:
        assert (models.model_id == 0).all() and len(models.merges) == 1
        _assert_matches_truth(models, 0, R, centres)
    else:
        assert models.sizes() == [5, 5] and not models.merges
        for m in (0, 1):
            _assert_matches_truth(models, m, R, centres)


def test_chain_without_triangles_is_seeded_from_its_strongest_pair_and_attached():
    """Pairs (0,1), (1,2), (2,3) only: averaging cannot scale a chain, growth by points can."""
    rng = np.random.default_rng(3)
    centres = np.column_stack([np.arange(4) * 1.0, np.zeros(4), [0.0, 0.4, -0.3, 0.2]])
    R, _, feature_of, bearings = _world(rng, centres, reach=6.0)
    links, matches = _links(R, centres, feature_of, pairs_wanted={(0, 1), (1, 2), (2, 3)})
    models = _build(links, matches, bearings)
    assert (models.model_id == 0).all()
    _assert_matches_truth(models, 0, R, centres)


def test_models_are_deterministic():
    _, _, links, matches, bearings = _room_with_wrong_image()
    a, b = _build(links, matches, bearings), _build(links, matches, bearings)
    assert np.array_equal(a.model_id, b.model_id) and np.array_equal(a.centers, b.centers)


def test_a_contradicted_bridge_that_points_confirm_keeps_its_side():
    """Two rooms joined by the right doorway pair (4, 5) and one wrong pair (3, 6): rotation averaging rejects (3, 6),
    which makes (4, 5) a contradicted bridge; the tracks across it fit, so the room behind it stays in the model as
    averaged (before: it was cut off and attached again camera by camera)."""
    rng = np.random.default_rng(4)
    left = np.column_stack([np.arange(5) * 1.2, np.zeros(5), rng.uniform(-.4, .4, 5)])
    centres = np.concatenate([left, left + [6.0, 0, 0]])
    R, _, feature_of, bearings = _world(rng, centres, num_points=2500, reach=5.0)
    rooms = [range(5), range(5, 10)]
    wanted = {(i, j) for room in rooms for i in room for j in room if i < j} | {(4, 5), (3, 6)}
    links, matches = _links(R, centres, feature_of, pairs_wanted=wanted)
    assert {(4, 5), (3, 6)} <= {tuple(p) for p in links.pairs}
    wrong = np.flatnonzero((links.pairs == [3, 6]).all(axis=1))
    links.R_j_from_i[wrong] = Rotation.from_rotvec([0.0, 0.4, 0.1]).as_matrix() @ links.R_j_from_i[wrong]
    models = _build(links, matches, bearings, resection=False, merge_models=False)
    assert (models.model_id == 0).all() and not models.attached  # kept as averaged, not cut off and re-attached
    assert any(set(join["images"]) & set(range(5, 10)) and join["tracks"] >= 6 for join in models.joins)
    _assert_matches_truth(models, 0, R, centres, tol_deg=1e-2, tol_rel=1e-3)
