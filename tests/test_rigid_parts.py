"""Rigid parts of an averaged layout and their join by points (fullview.sfm.registration.rigid_parts, models)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.metrics import umeyama
from fullview.sfm.options import RegistrationOptions
from fullview.sfm.registration import register, relative_from_absolute
from fullview.sfm.registration.models import PairLinks, build_models
from fullview.sfm.registration.rigid_parts import rigid_parts
from fullview.sfm.tracks import build_tracks

# Two rooms side by side along x, joined by a doorway camera (index 0) that sees both; the other cameras see only
# their own room. Pairs exist only within a room (the doorway camera belongs to both), so the directions leave the
# relative scale of the rooms free: the view graph is two rigid parts meeting at one camera.
ROOM_A = np.array([[-6.0, 0.1, -1.5], [-4.5, -0.1, 1.8], [-2.5, 0.0, -1.2], [-7.0, 0.05, 1.0]])
ROOM_B = np.array([[11.0, 0.0, 2.4], [6.0, 0.1, -2.7], [3.0, -0.05, 2.5], [12.5, 0.1, -1.8]])
DOOR = np.array([[0.0, 0.0, 0.0]])


def _scene(seed: int, door_points_seen_by_rooms: bool):
    """Cameras, points, bearings and pair links. With `door_points_seen_by_rooms`, points near the doorway are
    seen by the doorway camera and by cameras of both rooms (tracks that fix the rooms' relative scale); without,
    each room's cameras see only the points of their own room."""
    rng = np.random.default_rng(seed)
    centres = np.concatenate([DOOR, ROOM_A, ROOM_B])
    room = np.array([-1] + [0] * len(ROOM_A) + [1] * len(ROOM_B))
    n = len(centres)
    R = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (n, 1))).as_matrix()
    X = np.column_stack([rng.uniform(-10, 15, 1600), rng.uniform(-1.5, 1.5, 1600), rng.uniform(-3, 3, 1600)])
    point_room = (X[:, 0] > 0).astype(int)
    near_door = np.abs(X[:, 0]) < 2.0
    seen = np.zeros((n, len(X)), bool)
    seen[0] = True
    for k in range(1, n):
        seen[k] = point_room == room[k]
        if door_points_seen_by_rooms:
            seen[k] |= near_door
    feature_of = [np.flatnonzero(s) for s in seen]
    bearings = [normalize((X[f] - centres[k]) @ R[k].T) for k, f in enumerate(feature_of)]
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n) if room[i] == room[j] or room[i] < 0]
    matches = {}
    for i, j in pairs:
        _, a, b = np.intersect1d(feature_of[i], feature_of[j], return_indices=True)
        matches[(i, j)] = np.column_stack([a, b])
    pairs = np.array(pairs)
    t = -np.einsum("nab,nb->na", R, centres)
    R_rel, t_rel = relative_from_absolute(R, t, pairs[:, 0], pairs[:, 1])
    links = PairLinks(pairs=pairs, R_j_from_i=R_rel, t_j_from_i=normalize(t_rel),
                      weights=np.array([len(matches[tuple(p)]) for p in pairs], float))
    tracks, _ = build_tracks(matches, [len(b) for b in bearings])
    return centres, R, links, tracks, bearings


def _similarity_residual(estimated: np.ndarray, truth: np.ndarray) -> float:
    """Largest centre error after the best similarity, relative to the spread of the true centres."""
    sim = umeyama(estimated, truth)
    spread = np.linalg.norm(truth - truth.mean(0), axis=1).mean()
    return float(np.abs(sim.apply(estimated) - truth).max() / spread)


def test_rigid_parts_of_two_triangles():
    c = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0, 1], [-1, 0, 0], [-0.5, 0, 1], [0.5, 0, -1]], float)
    at_a_vertex = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [3, 4], [0, 4]])
    parts = rigid_parts(c, at_a_vertex)
    assert [p.tolist() for p in parts] == [[0, 1, 2], [0, 3, 4]]
    on_an_edge = np.array([[0, 1], [1, 2], [0, 2], [0, 5], [1, 5]])
    assert [p.tolist() for p in rigid_parts(c, on_an_edge)] == [[0, 1, 2, 5]]


def test_a_scale_free_join_is_not_fixed_by_averaging_alone():
    centres, R, links, _, _ = _scene(0, door_points_seen_by_rooms=True)
    reg = register(num_images=len(centres), pairs=links.pairs, R_j_from_i=links.R_j_from_i,
                   t_j_from_i=links.t_j_from_i, weights=links.weights)
    assert reg.flexible_modes == 1
    assert reg.registered.all()
    assert _similarity_residual(reg.centers, centres) > 0.05  # the rooms' relative scale is arbitrary


def test_rooms_joined_at_one_camera_get_their_true_scale_from_shared_points():
    centres, R, links, tracks, bearings = _scene(0, door_points_seen_by_rooms=True)
    models = build_models(links=links, tracks=tracks, bearings=bearings, options=RegistrationOptions())
    assert models.sizes() == [len(centres)]
    assert len(models.joins) == 1 and models.joins[0]["tracks"] >= RegistrationOptions().min_join_points
    assert _similarity_residual(models.centers, centres) < 1e-6


def test_rooms_no_point_joins_become_two_models_never_a_wrong_scale():
    centres, R, links, tracks, bearings = _scene(1, door_points_seen_by_rooms=False)
    models = build_models(links=links, tracks=tracks, bearings=bearings,
                          options=RegistrationOptions())
    assert models.sizes() == [len(ROOM_A) + 1, len(ROOM_B)] or models.sizes() == [len(ROOM_B) + 1, len(ROOM_A)]
    assert not models.joins and sorted(models.scale_free)
    for m in range(models.num_models):
        k = np.flatnonzero(models.model_id == m)
        assert _similarity_residual(models.centers[k], centres[k]) < 1e-6


def test_asked_to_keep_it_a_part_no_point_joins_is_attached_approximate_and_says_so():
    """unconfirmed_joins: approximate: room B is attached along its verified pairs into the door camera at a guessed
    scale, every camera of it marked approximate; each room stays exact (only their relative scale is a guess)."""
    centres, R, links, tracks, bearings = _scene(1, door_points_seen_by_rooms=False)
    models = build_models(links=links, tracks=tracks, bearings=bearings,
                          options=RegistrationOptions(unconfirmed_joins="approximate"))
    assert models.sizes() == [len(centres)]
    guessed = [j for j in models.join_records if not j["confirmed"]]
    room_b = 1 + len(ROOM_A) + np.arange(len(ROOM_B))
    assert len(guessed) == 1 and sorted(guessed[0]["images"]) == room_b.tolist() and guessed[0]["scale"] == "guessed"
    assert models.approximate.tolist() == [k in room_b for k in range(len(centres))]
    for room in (np.arange(1 + len(ROOM_A)), room_b):
        assert _similarity_residual(models.centers[room], centres[room]) < 1e-6
