"""Blocks of a final model that no track joins: found exactly, and re-scaled to one median step without changing a
single bearing (sfm/registration/free_blocks.py, stages/triangulation.py: _rescale_free_blocks)."""

import numpy as np

from fullview.sfm.camera import normalize
from fullview.sfm.registration.free_blocks import (biconnected_blocks, camera_heights, camera_links,
                                                   free_block_similarities)
from fullview.sfm.tracks import Tracks
from fullview.stages.triangulation import _rescale_free_blocks


def _tracks(camera_sets: list[list[int]], num_images: int) -> Tracks:
    track_ids = np.concatenate([np.full(len(c), k) for k, c in enumerate(camera_sets)]).astype(np.int64)
    image_ids = np.concatenate([np.sort(c) for c in camera_sets]).astype(np.int64)
    offsets = np.r_[0, np.cumsum([len(c) for c in camera_sets])].astype(np.int64)
    return Tracks(track_ids=track_ids, image_ids=image_ids, feature_ids=np.arange(len(track_ids), dtype=np.int64),
                  offsets=offsets, num_images=num_images)


def test_camera_links_are_the_pairs_of_cameras_sharing_a_track():
    tracks = _tracks([[0, 1, 2], [2, 3], [3, 2], [4, 5]], 6)
    np.testing.assert_array_equal(camera_links(tracks.track_ids, tracks.image_ids),
                                  [[0, 1], [0, 2], [1, 2], [2, 3], [4, 5]])


def test_blocks_meet_at_articulation_cameras():
    # two triangles sharing camera 2, a bridge 4-5 hanging from camera 4, an isolated camera 6
    links = np.array([[0, 1], [1, 2], [0, 2], [2, 3], [3, 4], [2, 4], [4, 5]])
    blocks = sorted(sorted(b.tolist()) for b in biconnected_blocks(7, links))
    assert blocks == [[0, 1, 2], [2, 3, 4], [4, 5]]


def _two_rooms(wrong_scale: float, seed: int = 0):
    """Cameras 0-4 and 4-8 on a zigzag line with equal steps, points seen only within one room (camera 4, the
    doorway, sees both rooms but no point of both); the second room scaled about camera 4 by `wrong_scale`."""
    rng = np.random.default_rng(seed)
    C = np.stack([np.arange(9.0), np.zeros(9), 0.3 * (-1.0) ** np.arange(9)], axis=1)  # equal steps
    rooms = [np.arange(0, 5), np.arange(4, 9)]
    camera_sets, points = [], []
    for room in rooms:
        for _ in range(40):
            cams = rng.choice(room, size=3, replace=False)
            camera_sets.append(cams.tolist())
            points.append(C[cams].mean(0) + rng.normal(0, 1.0, 3) + [0, 0, 2.0])
    points = np.array(points)
    pairs = np.array([(i, i + 1) for i in range(8)] + [(i, i + 2) for i in range(0, 7, 2)])
    second = np.arange(len(points)) >= 40
    C_wrong, P_wrong = C.copy(), points.copy()
    C_wrong[5:] = C[4] + wrong_scale * (C[5:] - C[4])
    P_wrong[second] = C[4] + wrong_scale * (points[second] - C[4])
    return C, C_wrong, P_wrong, _tracks(camera_sets, 9), pairs


def _bearings(R, C, points, tracks):
    return normalize(np.einsum("kab,kb->ka", R[tracks.image_ids], points[tracks.track_ids] - C[tracks.image_ids]))


def test_a_free_block_gets_the_common_step_and_no_bearing_changes():
    C_true, C, points, tracks, pairs = _two_rooms(wrong_scale=1.3)
    R = np.repeat(np.eye(3)[None], 9, axis=0)
    t = -np.einsum("nab,nb->na", R, C)
    R2, t2, points2 = _rescale_free_blocks(tracks, R, t, points, pairs, min_pairs=3)
    C2 = -np.einsum("nba,nb->na", R2, t2)
    # the true layout up to one similarity: the steps of both rooms equal again
    steps = np.linalg.norm(np.diff(C2, axis=0), axis=1) / np.linalg.norm(np.diff(C_true, axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-9)
    # every observation's bearing is the same: the bundle adjustment's cost did not change
    np.testing.assert_allclose(_bearings(R2, C2, points2, tracks), _bearings(R, C, points, tracks), atol=1e-12)
    # before, the second room's steps were 1.3 times the first's
    before = np.linalg.norm(np.diff(C, axis=0), axis=1) / np.linalg.norm(np.diff(C_true, axis=0), axis=1)
    np.testing.assert_allclose(before[4:] / before[0], 1.3)


def test_one_track_across_the_doorway_makes_one_block_and_nothing_moves():
    _, C, points, tracks, pairs = _two_rooms(wrong_scale=1.3)
    joined = _tracks([tracks.image_ids[tracks.offsets[k]:tracks.offsets[k + 1]].tolist()
                      for k in range(tracks.num_tracks)] + [[3, 4, 5]], 9)
    scale, shift, _ = free_block_similarities(C, camera_links(joined.track_ids, joined.image_ids), pairs, 3)
    np.testing.assert_array_equal(scale, 1.0)
    np.testing.assert_array_equal(shift, 0.0)


def test_a_block_with_too_few_pairs_keeps_its_scale():
    _, C, points, tracks, pairs = _two_rooms(wrong_scale=1.3)
    links = camera_links(tracks.track_ids, tracks.image_ids)
    few = pairs[(pairs < 5).all(axis=1) | (pairs == [4, 5]).all(axis=1) | (pairs == [5, 6]).all(axis=1)]
    scale, _, _ = free_block_similarities(C, links, few, min_pairs=3)
    np.testing.assert_array_equal(scale, 1.0)
    scale, _, _ = free_block_similarities(C, links, few, min_pairs=2)
    np.testing.assert_allclose(scale[5:], 1.0 / 1.3)


def _two_rooms_on_a_floor(wrong_scale: float, floor_in_second: bool = True, seed: int = 0):
    """Cameras 1.5 above a floor (z = 0, world down -z): 0-4 with steps of 1, 4-8 with steps of 0.6 (a walk's steps
    vary), camera 4 the doorway. Each room's points, each seen by 3 of its cameras: floor points, three times as many
    points on furniture tops at 0.7 (the densest cluster below the cameras) and points on walls at any height (without
    `floor_in_second`, the second room's points all lie on the ceiling); the second room scaled about camera 4 by
    `wrong_scale`."""
    rng = np.random.default_rng(seed)
    x = np.r_[np.arange(5.0), 4.0 + 0.6 * np.arange(1, 5)]
    C = np.stack([x, 0.3 * (-1.0) ** np.arange(9), np.full(9, 1.5)], axis=1)
    camera_sets, points = [], []
    for room, floor in ((np.arange(0, 5), True), (np.arange(4, 9), floor_in_second)):
        middle = C[room].mean(0)
        kinds = [("floor", 40), ("top", 120), ("wall", 30)] if floor else [("ceiling", 190)]
        for kind, count in kinds:
            for _ in range(count):
                camera_sets.append(rng.choice(room, size=3, replace=False).tolist())
                xy = middle[:2] + rng.uniform(-2.5, 2.5, 2)
                z = {"floor": 0.0, "top": 0.7, "wall": rng.uniform(0.0, 2.6), "ceiling": 2.6}[kind]
                points.append([xy[0], xy[1] + (2.5 if kind == "wall" else 0.0), z])
    points = np.array(points)
    second = np.repeat([False, True], [190, 190])
    pairs = np.array([(i, i + 1) for i in range(8)] + [(i, i + 2) for i in range(0, 7, 2)])
    C_wrong, P_wrong = C.copy(), points.copy()
    C_wrong[5:] = C[4] + wrong_scale * (C[5:] - C[4])
    P_wrong[second] = C[4] + wrong_scale * (points[second] - C[4])
    return C, C_wrong, P_wrong, _tracks(camera_sets, 9), pairs


def test_camera_heights_are_the_floor_below_each_camera_not_the_densest_surface():
    _, C, points, tracks, _ = _two_rooms_on_a_floor(wrong_scale=1.3)
    down = np.tile([0.0, 0.0, -1.0], (9, 1))
    heights = camera_heights(C, down, points, tracks.track_ids, tracks.image_ids)
    np.testing.assert_allclose(heights[:4], 1.5, rtol=1e-12)
    np.testing.assert_allclose(heights[5:], 1.5 * 1.3, rtol=1e-12)
    # without a down direction (a model with no measured gravity) nothing is measured
    assert np.isnan(camera_heights(C, np.full((9, 3), np.nan), points, tracks.track_ids, tracks.image_ids)).all()


def test_a_free_block_gets_the_root_blocks_camera_height_not_its_step():
    C_true, C, points, tracks, pairs = _two_rooms_on_a_floor(wrong_scale=1.3)
    R = np.repeat(np.eye(3)[None], 9, axis=0)
    t = -np.einsum("nab,nb->na", R, C)
    down = np.tile([0.0, 0.0, -1.0], (9, 1))
    R2, t2, points2 = _rescale_free_blocks(tracks, R, t, points, pairs, 3, down)
    C2 = -np.einsum("nba,nb->na", R2, t2)
    # the true layout up to a scale about the doorway camera (either room may hold the frame)
    factor = np.linalg.norm(C2[0] - C2[4]) / np.linalg.norm(C_true[0] - C_true[4])
    np.testing.assert_allclose(C2 - C2[4], factor * (C_true - C_true[4]), atol=1e-12)
    np.testing.assert_allclose(_bearings(R2, C2, points2, tracks), _bearings(R, C, points, tracks), atol=1e-12)
    # the median baseline puts the second room's median pair (0.85 on the zigzag) at the first room's (1.17)
    _, t3, _ = _rescale_free_blocks(tracks, R, t, points, pairs, 3)
    C3 = -np.einsum("nba,nb->na", R2, t3)
    extent = np.linalg.norm(C3[8] - C3[4]) / np.linalg.norm(C3[0] - C3[4])
    true_extent = np.linalg.norm(C_true[8] - C_true[4]) / np.linalg.norm(C_true[0] - C_true[4])
    np.testing.assert_allclose(extent / true_extent, np.hypot(1.0, 0.6) / np.hypot(0.6, 0.6))


def test_a_block_whose_floor_is_not_seen_falls_back_to_the_median_baseline():
    _, C, points, tracks, pairs = _two_rooms_on_a_floor(wrong_scale=1.3, floor_in_second=False)
    R = np.repeat(np.eye(3)[None], 9, axis=0)
    t = -np.einsum("nab,nb->na", R, C)
    down = np.tile([0.0, 0.0, -1.0], (9, 1))
    heights = camera_heights(C, down, points, tracks.track_ids, tracks.image_ids)
    assert np.isnan(heights[5:]).all()
    _, with_down, _ = _rescale_free_blocks(tracks, R, t, points, pairs, 3, down)
    _, without, _ = _rescale_free_blocks(tracks, R, t, points, pairs, 3)
    np.testing.assert_allclose(with_down, without, atol=1e-12)
