"""Pairs the registered model proposes (stages/geometry_pairs.py): matched before the final pass, verified against
the known relative pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.io.workspace import Workspace
from fullview.sfm.camera import normalize
from fullview.sfm.two_view import consistent_with_pose

SEQUENTIAL_WINDOW_1 = ["matches.pairs=sequential", "matches.window=1", "matches.retrieval_neighbours=0"]


def test_consistent_with_pose_keeps_true_matches_and_rejects_wrong_and_behind_ones():
    rng = np.random.default_rng(0)
    R = Rotation.from_rotvec([0.1, 0.4, -0.05]).as_matrix()
    t = np.array([0.8, -0.1, 0.3])
    X = rng.uniform(-3, 3, (300, 3)) + [0, 0, 5] * rng.choice([-1, 1], (300, 1))
    b_i, b_j = normalize(X), normalize(X @ R.T + t)
    threshold = np.radians(0.5)
    assert consistent_with_pose(b_i, b_j, R, t, threshold).all()
    wrong = consistent_with_pose(b_i, b_j[rng.permutation(300)], R, t, threshold)
    assert wrong.mean() < 0.05  # a random pairing rarely lands within 0.5° of the circle
    # The same rays reversed in both cameras satisfy the epipolar constraint exactly but lie behind the cameras.
    assert not consistent_with_pose(-b_i, -b_j, R, t, threshold).any()


def test_a_pair_never_matched_is_matched_and_joins_the_tracks(tiny_dataset, make_pipeline, tmp_path):
    """Three views matched only in capture order (0-1, 1-2): the model proposes 0-2, whose matches then make tracks
    of three views that the chain alone does not."""
    runs = {}
    for k in (0, 2):
        pipeline = make_pipeline(tiny_dataset, SEQUENTIAL_WINDOW_1 + [f"triangulation.geometry_neighbours={k}"],
                                 workspace=tmp_path / f"ws{k}")
        pipeline.run(until="triangulation")
        ws = Workspace(tmp_path / f"ws{k}", "tiny")
        runs[k] = (ws.read_manifest("triangulation")["summary"], ws.load_sparse())
    pairs = Workspace(tmp_path / "ws0", "tiny").load_inliers().pairs
    assert sorted(map(tuple, pairs)) == [(0, 1), (1, 2)]
    (before, sparse_before), (after, sparse_after) = runs[0], runs[2]
    assert before["geometry_pairs"] == 0 and after["geometry_pairs"] == 1
    seen_by_0_and_2 = [_tracks_seen_by(s, {0, 2}) for s in (sparse_before, sparse_after)]
    assert seen_by_0_and_2[1] > 1.2 * seen_by_0_and_2[0]
    assert after["median_error_deg"] < 1.0


def _tracks_seen_by(sparse, images: set[int]) -> int:
    track_ids, image_ids = np.asarray(sparse["track_ids"]), np.asarray(sparse["image_ids"])
    hits = np.zeros(int(track_ids.max()) + 1, int)
    for image in images:
        hits[np.unique(track_ids[image_ids == image])] += 1
    return int((hits == len(images)).sum())
