"""Doorway pairs rematched along their epipolar circles under a pose hypothesis (fullview.sfm.registration.rematch_join)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.matching import match_descriptors
from fullview.sfm.options import MatchesOptions
from fullview.sfm.registration.rematch_join import (MIN_REMATCHED, ModelPoints, confirmed_pose, distance_along,
                                                   join_by_rematching, rematched)
from fullview.sfm.registration.weak_joins import CrossPair
from fullview.sfm.rotations import rotation_angle_deg

THRESHOLD = np.radians(0.35)
DOWN = np.array([0.0, 1.0, 0.0])


def _yaw(deg: float) -> np.ndarray:
    return Rotation.from_euler("y", deg, degrees=True).as_matrix()


def _descriptors(rng, n: int) -> np.ndarray:
    return normalize(rng.normal(size=(n, 128))).astype(np.float32)


def _views(rng, R, C, X, D, lookalikes: int, noise: float = 0.25, alike_share: float = 1.0):
    """Per camera: bearings of the points X (descriptors D plus noise) and, for the first `alike_share` of the
    points, `lookalikes` features each of nearly the same descriptor at random directions (a plain wall's repeated
    texture), and as many unrelated ones."""
    out = []
    for R_k, C_k in zip(R, C):
        b = normalize((X - C_k) @ R_k.T)
        d = normalize(D + noise / np.sqrt(128) * rng.normal(size=D.shape))
        alike_of = np.repeat(D[:int(round(alike_share * len(D)))], lookalikes, axis=0)
        alike = normalize(alike_of + noise / np.sqrt(128) * rng.normal(size=alike_of.shape))
        other = _descriptors(rng, len(alike))
        b_all = np.concatenate([b, normalize(rng.normal(size=(2 * len(alike), 3)))])
        out.append((b_all, np.concatenate([d, alike, other]).astype(np.float32)))
    return out


def _doorway(rng, n=40, lookalikes=2):
    R = [_yaw(25.0), _yaw(-70.0)]
    C = [np.zeros(3), np.array([1.7, 0.04, 0.5])]
    X = rng.uniform([-4, -1, -4], [5, 1.2, 4], (n, 3))
    (b_k, d_k), (b_l, d_l) = _views(rng, R, C, X, _descriptors(rng, n), lookalikes)
    return b_k, d_k, b_l, d_l, R[1] @ R[0].T, R[1] @ (C[0] - C[1]), (R, C)


def test_the_rematch_under_the_true_pose_finds_the_matches_the_global_ratio_test_drops():
    rng = np.random.default_rng(0)
    b_k, d_k, b_l, d_l, R_lk, t_lk, _ = _doorway(rng)
    plain = match_descriptors(d_k, d_l, MatchesOptions(ratio=0.8, mutual=True))
    true_plain = int(((plain[:, 0] == plain[:, 1]) & (plain[:, 0] < 40)).sum())
    found = rematched(b_k, b_l, d_k, d_l, R_lk, t_lk, THRESHOLD)
    true_found = int(((found[:, 0] == found[:, 1]) & (found[:, 0] < 40)).sum())
    assert true_plain < 20 and true_found >= 36 and len(found) - true_found <= 10  # chance matches along the band
    turned = _yaw(90.0) @ R_lk  # the pose a quarter turn off: band matches by chance only
    assert len(rematched(b_k, b_l, d_k, d_l, turned, t_lk, THRESHOLD)) < true_found / 2


def test_a_near_hypothesis_is_confirmed_at_the_true_pose_and_an_unrelated_pair_is_not():
    rng = np.random.default_rng(1)
    b_k, d_k, b_l, d_l, R_lk, t_lk, _ = _doorway(rng)
    start_R = _yaw(0.3) @ R_lk
    start_t = Rotation.from_rotvec([0.0, np.radians(2.0), 0.0]).apply(normalize(t_lk))
    raw = match_descriptors(d_k, d_l, MatchesOptions(ratio=0.8, mutual=True))
    g_k, g_l = DOWN, DOWN  # level cameras
    found = confirmed_pose(b_k, b_l, d_k, d_l, start_R, start_t, THRESHOLD, g_k=g_k, g_l=g_l, free_rotation=True,
                           raw=(b_k[raw[:, 0]], b_l[raw[:, 1]]))
    assert found is not None
    R, t, m = found
    assert rotation_angle_deg(R, R_lk) < 0.05 and normalize(t) @ normalize(t_lk) > np.cos(np.radians(0.3))
    assert len(m) >= MIN_REMATCHED
    # descriptors of another room: nothing to confirm under any pose
    other = _descriptors(rng, len(d_l))
    assert confirmed_pose(b_k, b_l, d_k, other, start_R, start_t, THRESHOLD, g_k=g_k, g_l=g_l, free_rotation=True,
                          raw=(b_k[raw[:, 0]], b_l[raw[:, 1]])) is None


def test_a_seed_fit_and_a_companion_through_one_doorway_join_two_models_at_the_truth():
    rng = np.random.default_rng(2)
    # model a: cameras 0, 1 (true frame); model b: camera 2 (and 3, seeing nothing of a), frame x_a = M0 x_b + T0
    R = [_yaw(10.0), _yaw(-35.0), _yaw(70.0), _yaw(150.0)]
    C = [np.zeros(3), np.array([1.6, 0.02, 0.2]), np.array([1.0, 0.03, 1.8]), np.array([2.2, 0.0, 3.5])]
    M0, T0 = _yaw(41.0), np.array([0.7, 0.0, -0.4])
    R_b = {k: R[k] @ M0 for k in (2, 3)}
    C_b = {k: M0.T @ (C[k] - T0) for k in (2, 3)}
    X = rng.uniform([-3, -1, -1], [4, 1.2, 4], (40, 3))
    D = _descriptors(rng, 40)
    views = _views(rng, R, C, X, D, lookalikes=2, alike_share=0.7)  # raw: about 12 true matches of 40
    views[3] = (views[3][0], _descriptors(rng, len(views[3][1])))  # camera 3 sees another room
    bearings = [v[0] for v in views]
    descriptors = [v[1] for v in views]
    cross = []
    for k, l in ((2, 0), (2, 1), (3, 0), (3, 1)):
        raw = match_descriptors(descriptors[k], descriptors[l], MatchesOptions(ratio=0.8, mutual=True))
        cross.append(CrossPair(k=k, l=l, b_k=bearings[k][raw[:, 0]], b_l=bearings[l][raw[:, 1]], matches=raw))
    # the seed: pair (2, 0)'s rough fit, 0.3° off in yaw
    R_a = {0: R[0], 1: R[1]}
    C_a = {0: C[0], 1: C[1]}
    M_seed = _yaw(0.3) @ M0
    u = normalize(C[2] - C[0])
    fits = [(cross[0], M_seed, u, np.ones(8, bool))]
    gravity = np.array([R_k @ DOWN for R_k in R])
    join = join_by_rematching(fits, cross, R_a=R_a, C_a=C_a, R_b=R_b, C_b=C_b, gravity=gravity, bearings=bearings,
                              descriptors=descriptors, threshold_rad=THRESHOLD, step_a=1.6, step_b=1.6)
    assert join is not None
    M, chosen, (scale, shift, guessed), rows, _ = join
    assert rotation_angle_deg(M, M0) < 0.05
    assert {(f[0].k, f[0].l) for f in chosen} == {(2, 0), (2, 1)} and guessed
    assert np.linalg.norm(scale * M @ C_b[2] + shift - C[2]) < 0.02
    # the same rooms with the doorway closed (camera 2 sees another room too): no join
    descriptors[2] = _descriptors(rng, len(descriptors[2]))
    for pair in cross[:2]:
        pair.matches = match_descriptors(descriptors[pair.k], descriptors[pair.l],
                                         MatchesOptions(ratio=0.8, mutual=True))
        pair.b_k, pair.b_l = bearings[pair.k][pair.matches[:, 0]], bearings[pair.l][pair.matches[:, 1]]
    assert join_by_rematching(fits, cross, R_a=R_a, C_a=C_a, R_b=R_b, C_b=C_b, gravity=gravity, bearings=bearings,
                              descriptors=descriptors, threshold_rad=THRESHOLD, step_a=1.6, step_b=1.6) is None


def _one_doorway(rng, scale_b: float = 0.6):
    """Two models meeting through one pair (2 of b, 0 of a): a's cameras 0, 1 and b's 2, 3 see the doorway's points
    X; b's frame is x_a = s0 M0 x_b + T0. Returns the scene and the join's keyword arguments."""
    R = [_yaw(10.0), _yaw(-35.0), _yaw(70.0), _yaw(150.0)]
    C = [np.zeros(3), np.array([1.6, 0.02, 0.2]), np.array([1.0, 0.03, 1.8]), np.array([2.2, 0.0, 3.5])]
    M0, T0 = _yaw(41.0), np.array([0.7, 0.0, -0.4])
    R_b = {k: R[k] @ M0 for k in (2, 3)}
    C_b = {k: M0.T @ (C[k] - T0) / scale_b for k in (2, 3)}
    X = rng.uniform([-3, -1, -1], [4, 1.2, 4], (40, 3))
    views = _views(rng, R, C, X, _descriptors(rng, 40), lookalikes=2, alike_share=0.7)
    bearings, descriptors = [v[0] for v in views], [v[1] for v in views]
    raw = match_descriptors(descriptors[2], descriptors[0], MatchesOptions(ratio=0.8, mutual=True))
    cross = [CrossPair(k=2, l=0, b_k=bearings[2][raw[:, 0]], b_l=bearings[0][raw[:, 1]], matches=raw)]
    # the models' points: feature n < 40 of every camera is point n (a's in a's frame, b's in b's)
    of_feature = {k: np.where(np.arange(len(bearings[k])) < 40, np.arange(len(bearings[k])), -1) for k in range(4)}
    points = (ModelPoints(X=X, point_of_feature={0: of_feature[0], 1: of_feature[1]}),
              ModelPoints(X=(X - T0) @ M0 / scale_b, point_of_feature={2: of_feature[2], 3: of_feature[3]}))
    walls = np.array([R_k @ np.array([1.0, 0.0, 0.0]) for R_k in R])  # each camera's wall axis (walls along x, z)
    kwargs = dict(R_a={0: R[0], 1: R[1]}, C_a={0: C[0], 1: C[1]}, R_b=R_b, C_b=C_b,
                  gravity=np.array([R_k @ DOWN for R_k in R]), bearings=bearings, descriptors=descriptors,
                  threshold_rad=THRESHOLD, step_a=1.6, step_b=1.6)
    return (R, C, M0, T0, scale_b), cross, points, walls, kwargs


def _close_the_doorway(rng, kwargs) -> list:
    """The cross pairs of `_one_doorway` with its camera 2 given another room's descriptors (in `kwargs`, in place):
    the one pair 2-0 of raw matches by chance."""
    kwargs["descriptors"][2] = _descriptors(rng, len(kwargs["descriptors"][2]))
    raw = match_descriptors(kwargs["descriptors"][2], kwargs["descriptors"][0], MatchesOptions(ratio=0.8, mutual=True))
    b = kwargs["bearings"]
    return [CrossPair(k=2, l=0, b_k=b[2][raw[:, 0]], b_l=b[0][raw[:, 1]], matches=raw)]


def test_one_pair_whose_points_agree_joins_two_models_at_the_true_similarity():
    rng = np.random.default_rng(3)
    (R, C, M0, T0, s0), cross, points, walls, kwargs = _one_doorway(rng)
    fits = [(cross[0], _yaw(0.3) @ M0, normalize(C[2] - C[0]), np.ones(8, bool))]  # a rough seed fit
    assert join_by_rematching(fits, cross, **kwargs) is None  # one pair: no companion confirms it
    for seeds, axes in ((fits, None), ([], walls)):  # the seed fit, or no fit but the walls' rotations
        join = join_by_rematching(seeds, cross, points=points, wall_axes=axes, **kwargs)
        assert join is not None
        M, chosen, (scale, shift, guessed), rows, _ = join
        assert rotation_angle_deg(M, M0) < 0.05 and not guessed and len(chosen) == 1
        assert abs(scale / s0 - 1.0) < 0.01
        for k in (2, 3):  # b's cameras land on their true centres
            assert np.linalg.norm(scale * M @ kwargs["C_b"][k] + shift - C[k]) < 0.02
    # without walls and without a seed fit: nothing to start from
    assert join_by_rematching([], cross, points=points, **kwargs) is None


def test_a_closed_door_or_points_that_disagree_join_nothing():
    rng = np.random.default_rng(4)
    (R, C, M0, T0, s0), cross, points, walls, kwargs = _one_doorway(rng)
    fits = [(cross[0], _yaw(0.3) @ M0, normalize(C[2] - C[0]), np.ones(8, bool))]
    # look-alike objects: the same descriptors, but b's points lie elsewhere than a's (another room's layout)
    moved = ModelPoints(X=rng.uniform([-3, -1, -1], [4, 1.2, 4], points[1].X.shape), point_of_feature=points[1].point_of_feature)
    assert join_by_rematching(fits, cross, points=(points[0], moved), wall_axes=walls, **kwargs) is None
    # the doorway closed: camera 2 sees another room
    closed = _close_the_doorway(rng, kwargs)
    assert join_by_rematching(fits, closed, points=points, wall_axes=walls, **kwargs) is None


def test_the_distance_along_a_ray_is_exact_on_points_that_agree_and_unsupported_on_scattered_ones():
    rng = np.random.default_rng(5)
    origin, v, lam = np.array([0.3, -0.1, 0.2]), normalize(np.array([1.0, 0.1, 0.4])), 2.7
    X = rng.uniform(-4, 4, (30, 3))
    rays = normalize(X - (origin + lam * v))
    found, support = distance_along(origin, v, X, rays, THRESHOLD)
    assert abs(found - lam) < 1e-9 and support >= 28  # all but points near the baseline's line
    scattered = normalize(rng.normal(size=rays.shape))
    assert distance_along(origin, v, X, scattered, THRESHOLD)[1] <= 2


def _two_panoramas_through_one(rng):
    """b's cameras 2 and 3 see the doorway's points X that a's camera 0 sees (a's camera 1 sees another room): both
    cross pairs run from camera 0, whose rays fix b's shape but not its size. b's frame: x_a = s0 M0 x_b + T0."""
    R = [_yaw(10.0), _yaw(-35.0), _yaw(70.0), _yaw(150.0)]
    C = [np.zeros(3), np.array([-1.6, 0.02, 0.2]), np.array([1.5, 0.03, 1.6]), np.array([2.7, 0.0, 0.4])]
    M0, T0, s0 = _yaw(41.0), np.array([0.7, 0.0, -0.4]), 0.8
    X = rng.uniform([-1, -1, -1], [5, 1.2, 4], (40, 3))
    views = _views(rng, R, C, X, _descriptors(rng, 40), lookalikes=2, alike_share=0.7)
    views[1] = (views[1][0], _descriptors(rng, len(views[1][1])))
    bearings, descriptors = [v[0] for v in views], [v[1] for v in views]
    cross = []
    for k, l in ((2, 0), (3, 0), (2, 1), (3, 1)):
        raw = match_descriptors(descriptors[k], descriptors[l], MatchesOptions(ratio=0.8, mutual=True))
        cross.append(CrossPair(k=k, l=l, b_k=bearings[k][raw[:, 0]], b_l=bearings[l][raw[:, 1]], matches=raw))
    C_b = {k: M0.T @ (C[k] - T0) / s0 for k in (2, 3)}
    step_b = float(np.linalg.norm(C_b[2] - C_b[3]))
    kwargs = dict(R_a={0: R[0], 1: R[1]}, C_a={0: C[0], 1: C[1]}, R_b={k: R[k] @ M0 for k in (2, 3)}, C_b=C_b,
                  gravity=np.array([R_k @ DOWN for R_k in R]), bearings=bearings, descriptors=descriptors,
                  threshold_rad=THRESHOLD, step_a=s0 * step_b, step_b=step_b)  # the guess: b's true scale
    fits = [(cross[0], _yaw(0.3) @ M0, normalize(C[2] - C[0]), np.ones(8, bool))]  # a rough seed fit
    return (C, M0, X), cross, fits, kwargs


def test_two_panoramas_of_b_seeing_one_of_a_place_b_by_its_shape_and_the_guessed_scale():
    rng = np.random.default_rng(6)
    (C, M0, _), cross, fits, kwargs = _two_panoramas_through_one(rng)
    for several in (False, True):
        join = join_by_rematching(fits, cross, several=several, **kwargs)
        assert join is not None
        M, chosen, (scale, shift, guessed), rows, _ = join
        assert {(f[0].k, f[0].l) for f in chosen} == {(2, 0), (3, 0)} and guessed
        assert rotation_angle_deg(M, M0) < 0.05
        for k in (2, 3):  # the rays from camera 0 give b's shape: with its true scale guessed, its true centres
            assert np.linalg.norm(scale * M @ kwargs["C_b"][k] + shift - C[k]) < 0.03


def test_a_join_the_placement_check_rejects_is_not_taken():
    rng = np.random.default_rng(6)
    _, cross, fits, kwargs = _two_panoramas_through_one(rng)
    seen = []
    refuse = lambda M, placed: seen.append(placed) and False  # noqa: E731 - records the joins offered, takes none
    assert join_by_rematching(fits, cross, several=True, accept=refuse, **kwargs) is None
    assert len(seen) >= 1  # the join was found and offered to the check


def test_a_box_rooms_quarter_turn_defeats_the_margins_but_two_pairs_above_it_join():
    # camera 0 also sees, for 24 of the doorway's 40 points, a look-alike where the point would be were camera 2
    # (3) turned by 90° about gravity (a box room's walls and edges map onto each other): each pair's quarter turn
    # then rematches nearly as well as its true pose, below homejoin's margins (1.5x, +15)
    rng = np.random.default_rng(7)
    (C, M0, X), cross, fits, kwargs = _two_panoramas_through_one(rng)
    bearings, descriptors = kwargs["bearings"], kwargs["descriptors"]
    for k in (2, 3):
        turned = C[k] + (X[:24] - C[k]) @ _yaw(90.0).T
        bearings[0] = np.concatenate([bearings[0], normalize(turned - C[0]) @ kwargs["R_a"][0].T])
        descriptors[0] = np.concatenate([descriptors[0], normalize(
            descriptors[k][:24] + 0.25 / np.sqrt(128) * rng.normal(size=(24, 128))).astype(np.float32)])
    for pair in cross:  # raw matches again, look-alikes included
        pair.matches = match_descriptors(descriptors[pair.k], descriptors[pair.l],
                                         MatchesOptions(ratio=0.8, mutual=True))
        pair.b_k, pair.b_l = bearings[pair.k][pair.matches[:, 0]], bearings[pair.l][pair.matches[:, 1]]
    strict = join_by_rematching(fits, cross, **kwargs)
    several = join_by_rematching(fits, cross, several=True, **kwargs)
    assert several is not None
    M, chosen, (scale, shift, guessed), rows, kind = several
    assert rotation_angle_deg(M, M0) < 0.05
    for k in (2, 3):
        assert np.linalg.norm(scale * M @ kwargs["C_b"][k] + shift - C[k]) < 0.03
    assert strict is None


def test_one_pair_confirmed_alone_places_b_on_its_true_ray_at_a_guessed_length():
    # door2: one doorway pair (2-0), no companion, none of the models' points among its matches
    rng = np.random.default_rng(8)
    (R, C, M0, T0, s0), cross, _, _, kwargs = _one_doorway(rng)
    fits = [(cross[0], _yaw(0.3) @ M0, normalize(C[2] - C[0]), np.ones(8, bool))]  # a rough seed fit
    assert join_by_rematching(fits, cross, several=True, **kwargs) is None
    join = join_by_rematching(fits, cross, several=True, guess=True, **kwargs)
    assert join is not None
    M, chosen, (scale, shift, guessed), rows, _ = join
    assert rotation_angle_deg(M, M0) < 0.05 and guessed and [(f[0].k, f[0].l) for f in chosen] == [(2, 0)]
    assert scale == kwargs["step_a"] / kwargs["step_b"]
    placed = scale * M @ kwargs["C_b"][2] + shift - C[0]  # camera 2 from camera 0: the true direction, a's step
    assert np.degrees(np.arccos(normalize(placed) @ normalize(C[2] - C[0]))) < 0.3
    assert abs(np.linalg.norm(placed) - kwargs["step_a"]) < 1e-9
    assert len(rows) >= MIN_REMATCHED and {(k, l) for k, _, l, _ in rows} == {(2, 0)}


def test_a_guess_joins_no_closed_door_and_none_the_check_refuses():
    rng = np.random.default_rng(8)
    (R, C, M0, T0, s0), cross, _, _, kwargs = _one_doorway(rng)
    fits = [(cross[0], _yaw(0.3) @ M0, normalize(C[2] - C[0]), np.ones(8, bool))]
    seen = []
    refuse = lambda M, placed: seen.append(placed) and False  # noqa: E731 - records the joins offered, takes none
    assert join_by_rematching(fits, cross, guess=True, accept=refuse, **kwargs) is None and len(seen) == 1
    # the doorway closed: camera 2 sees another room, its seed fit (a chance fit) is not confirmed
    closed = _close_the_doorway(rng, kwargs)
    assert join_by_rematching(fits, closed, several=True, guess=True, **kwargs) is None


def test_without_a_seed_fit_the_walls_rotations_rematched_find_the_doorway_for_a_guess():
    # door2: no upright fit of the doorway pair (too few true raw matches); the walls allow four rotations, each
    # pair's most rematched ones are confirmed, the doorway's true rotation among them
    rng = np.random.default_rng(9)
    (R, C, M0, T0, s0), cross, _, walls, kwargs = _one_doorway(rng)
    assert join_by_rematching([], cross, wall_axes=walls, several=True, **kwargs) is None
    join = join_by_rematching([], cross, wall_axes=walls, guess=True, **kwargs)
    assert join is not None
    M, chosen, (scale, shift, guessed), rows, _ = join
    assert rotation_angle_deg(M, M0) < 0.05 and guessed
    placed = scale * M @ kwargs["C_b"][2] + shift - C[0]
    assert np.degrees(np.arccos(normalize(placed) @ normalize(C[2] - C[0]))) < 0.3
    # the walls' rotations turned by 45 degrees (a wrong wall axis): no rotation the walls allow rematches the pair
    wrong = np.array([_yaw(45.0) @ w if k == 2 else w for k, w in enumerate(walls)])
    assert join_by_rematching([], cross, wall_axes=wrong, guess=True, **kwargs) is None
