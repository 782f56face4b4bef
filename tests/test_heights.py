"""The camera-height prior of bundle adjustment (`sfm/heights.py`, `sfm/bundle.py: _height_residuals`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm import heights
from fullview.sfm.bundle import (_build_layout, _height_terms, _pack, _prior_cameras, _Problem, _SchurSystem,
                                 _WeightedResiduals, bundle_adjust)
from fullview.sfm.camera import normalize, tangent_basis

DOWN = np.array([0.0, 1.0, 0.0])  # world gravity, as the filter's ("down" is +y)
HEIGHT = 1.5


def _two_rooms(rng, noise_rad=0.0):
    """Two rooms of 4 tripod cameras (at y = 0, the floor at y = 1.5 along the world's down), 1 m apart, joined through a doorway that only two-view tracks of cameras 3 and 4 cross: the bearings fix the
    direction between them, not the second room's scale. Each room's points (walls, furniture, floor markers) are
    seen by all its cameras."""
    centers = np.array([[x, 0.0, 0.0] for x in (0, 1, 2, 3, 5, 6, 7, 8)], np.float64)
    R = Rotation.from_euler("y", rng.uniform(-np.pi, np.pi, (8, 1))).as_matrix()
    points, cam, pt = [], [], []

    def add(p, cams):
        for c in cams:
            cam.append(c), pt.append(len(points))
        points.append(p)

    for room, cams in ((0, range(4)), (1, range(4, 8))):
        x0 = 0.0 if room == 0 else 5.0
        for _ in range(60):  # walls and furniture, above the floor
            add(rng.uniform([x0 - 2, -1.2, -2.5], [x0 + 5, 1.2, 2.5]), cams)
        for _ in range(25):  # floor markers
            add(np.array([rng.uniform(x0 - 1, x0 + 4), HEIGHT, rng.uniform(-2, 2)]), cams)
    for _ in range(20):  # the doorway: two-view tracks only
        add(rng.uniform([3.6, -1.0, -0.5], [4.4, 1.0, 0.5]), (3, 4))
    points, cam, pt = np.array(points), np.array(cam), np.array(pt)
    y = np.einsum("kij,kj->ki", R[cam], points[pt] - centers[cam])
    bearings = normalize(normalize(y) + rng.normal(scale=noise_rad, size=y.shape)) if noise_rad else normalize(y)
    return R, centers, points, cam, pt, bearings


def _scaled_second_room(centers, points, cam, pt, s):
    """The second room (cameras 4-7 and the points only they see) scaled by s about camera 4: the same bearings."""
    C, X = centers.copy(), points.copy()
    C[4:] = C[4] + s * (C[4:] - C[4])
    seen_by = np.zeros((len(points), 8), bool)
    seen_by[pt, cam] = True
    second = seen_by[:, 4:].any(1) & ~seen_by[:, :4].any(1)
    X[second] = C[4] + s * (X[second] - C[4])
    return C, X


def _prior(R, C, X, cam, pt, sigma_rel=0.03):
    return heights.height_prior(C, np.tile(DOWN, (len(C), 1)), X, pt, cam, np.zeros(len(C), int), sigma_rel)


def test_floor_rows_find_each_cameras_floor_and_its_height():
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(0))
    camera, point, h = heights.floor_rows(C, np.tile(DOWN, (8, 1)), X, pt, cam)
    np.testing.assert_allclose(h, HEIGHT, atol=1e-12)
    np.testing.assert_allclose(X[point, 1], HEIGHT, atol=1e-12)  # floor markers only, no wall point
    assert np.bincount(camera, minlength=8).min() >= heights.MIN_FLOOR_POINTS


def test_a_camera_that_takes_a_furniture_top_for_its_floor_is_left_out():
    shared = np.full((5, 5), 50)
    h = np.array([1.5, 1.52, 1.0, 1.48, np.nan])
    assert heights.consistent_cameras(h, shared).tolist() == [True, True, False, True, False]
    alone = np.zeros((5, 5), int)  # nothing to check against: kept
    assert heights.consistent_cameras(h, alone).tolist() == [True, True, True, True, False]


def test_a_model_with_too_few_floors_gets_no_prior():
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(0))
    far = X[:, 1] == HEIGHT
    keep = ~far[pt] | (cam < 3)  # only cameras 0-2 still see floor markers: 3 of 8
    assert heights.height_prior(C, np.tile(DOWN, (8, 1)), X, pt[keep], cam[keep], np.zeros(8, int), 0.03) is None


def test_height_rows_jacobian_and_schur_step():
    """The height rows' Jacobian (on the centres, the scale camera's sphere coordinates and the points) matches finite
    differences, and the Schur step with them as rows is the step of the full damped system."""
    rng = np.random.default_rng(1)
    R, C, X, cam, pt, bearings = _two_rooms(rng, noise_rad=np.radians(0.05))  # σ_obs > 0: the rows weigh
    prior = _prior(R, C, X, cam, pt)
    t = -np.einsum("nij,nj->ni", R, C)
    layout = _build_layout(C, len(X), np.array([0]), None, cam)
    problem = _Problem(R_init=R, t_init=t, C_init=C, obs_camera=cam, obs_point=pt, bearings=bearings,
                       basis=tangent_basis(bearings), layout=layout,
                       **_height_terms(prior, C, R, X, cam, pt, bearings))
    assert len(problem.height_camera) == len(prior.camera)
    x = _pack(layout, C, X) + rng.normal(scale=1e-3, size=layout.num_params)
    objective = _WeightedResiduals(problem)
    J, r = objective.jac(x).toarray(), objective.fun(x)
    rows = slice(2 * len(cam), 2 * (len(cam) + len(prior.camera)))
    floor_point = int(prior.point[0])
    sphere = layout.cam_col[layout.scale_camera] + 3
    columns = [layout.cam_col[2] + 4, sphere, sphere + 1, layout.point_col + 3 * floor_point + 1]  # + 4, + 1: y
    h = 1e-6
    for col in columns:
        e = np.zeros_like(x)
        e[col] = h
        fd = (objective.fun(x + e) - objective.fun(x - e)) / (2 * h)
        assert np.abs(fd[rows]).max() > 0 or col == sphere + 1  # the height rows depend on this column
        np.testing.assert_allclose(J[:, col], fd, atol=1e-6 * np.abs(fd).max() + 1e-9)
    damping = 1e-3
    step, _ = _SchurSystem(problem).solve(r.reshape(-1, 2), objective.jac_blocks(x), damping,
                                          objective.prior_blocks(x), _prior_cameras(problem))
    JtJ = J.T @ J
    expected = np.linalg.solve(JtJ + damping * np.diag(np.maximum(np.diag(JtJ), 1e-12)), -J.T @ r)
    np.testing.assert_allclose(step, expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())


def _room_scale_ratio(result):
    """The second room's scale over the first's: mean step of cameras 4-7 over that of cameras 0-3 (true: 1)."""
    C = -np.einsum("nji,nj->ni", result.R_cam_from_world, result.t_cam_from_world)
    steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
    return steps[4:].mean() / steps[:3].mean()


def test_height_prior_carries_the_scale_through_a_doorway_that_only_two_view_tracks_cross():
    """Started with the second room at 0.7 of its scale (the bearings' cost is the same: only two-view tracks cross),
    the adjustment keeps it without the prior and restores it within 1% with it (bearings 0.05° noisy, seeds 0-2),
    fitting the bearings as well."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        R, C, X, cam, pt, bearings = _two_rooms(rng, noise_rad=np.radians(0.05))
        C0, X0 = _scaled_second_room(C, X, cam, pt, 0.7)
        kwargs = dict(R_cam_from_world=R, t_cam_from_world=-np.einsum("nij,nj->ni", R, C0), points=X0,
                      obs_camera=cam, obs_point=pt, obs_bearings=bearings, loss="linear", max_nfev=60)
        free = bundle_adjust(**kwargs)
        held = bundle_adjust(**kwargs, height_prior=_prior(R, C0, X0, cam, pt))
        assert abs(_room_scale_ratio(free) - 0.7) < 0.02, _room_scale_ratio(free)
        assert abs(_room_scale_ratio(held) - 1.0) < 0.01, (seed, _room_scale_ratio(held))
        assert np.median(held.obs_error_rad) < 1.05 * np.median(free.obs_error_rad)


def test_height_spread_tells_a_tripod_tour_from_a_hand_held_one():
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(0))
    prior = _prior(R, C, X, cam, pt)
    assert heights.height_spread(C, X, prior) < 1e-9
    hand_held = C.copy()
    hand_held[:, 1] += np.random.default_rng(1).uniform(-0.3, 0.3, 8)  # 1.2-1.8 m above the floor
    assert heights.height_spread(hand_held, X, prior) > 0.06


def _bearings(R, C, X, cam, pt):
    return normalize(np.einsum("kij,kj->ki", R[cam], X[pt] - C[cam]))


def test_a_bridge_goes_back_to_its_length_without_changing_a_bearing():
    """The doorway of `_two_rooms` (cameras 3 and 4, two-view tracks only) is a bridge: its length is free. Moved to
    0.2 of it (the second room translated along it, the doorway's points scaled about camera 3: the same bearings),
    `restore_bridges` puts it back exactly, every bearing unchanged; a scene without a bridge is left as it is."""
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(2))
    seen_by = np.zeros((len(X), 8), bool)
    seen_by[pt, cam] = True
    doorway = seen_by[:, 3] & seen_by[:, 4] & (seen_by.sum(1) == 2)
    second = seen_by[:, 4:].all(1)
    shift = -0.8 * (C[4] - C[3])
    C1, X1 = C.copy(), X.copy()
    C1[4:] += shift
    X1[second] += shift
    X1[doorway] = C[3] + 0.2 * (X[doorway] - C[3])
    np.testing.assert_allclose(_bearings(R, C1, X1, cam, pt), _bearings(R, C, X, cam, pt), atol=1e-12)
    C2, X2, bridges, _ = heights.restore_bridges(C, C1, X1, pt, cam, np.array([0]))
    assert bridges == 1
    np.testing.assert_allclose(C2, C, atol=1e-12)
    np.testing.assert_allclose(_bearings(R, C2, X2, cam, pt), _bearings(R, C, X, cam, pt), atol=1e-12)
    # one three-view track across the doorway: no bridge, nothing moves
    cam3, pt3 = np.r_[cam, 2], np.r_[pt, np.flatnonzero(doorway)[0]]
    C3, X3, bridges, _ = heights.restore_bridges(C, C1, X1, pt3, cam3, np.array([0]))
    assert bridges == 0 and np.array_equal(C3, C1) and np.array_equal(X3, X1)


def test_floor_rows_leave_out_a_bridges_points():
    """Floor points seen only by the two cameras of a bridge get no rows: each camera's own height would set the
    bridge's free length."""
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(0))
    doorway_floor = np.array([3.5, HEIGHT, 0.0]), np.array([4.5, HEIGHT, 0.3])
    X2 = np.vstack([X, *doorway_floor])
    cam2 = np.r_[cam, 3, 4, 3, 4]
    pt2 = np.r_[pt, len(X), len(X), len(X) + 1, len(X) + 1]
    prior = _prior(R, C, X2, cam2, pt2)
    assert not np.isin(prior.point, [len(X), len(X) + 1]).any()
    assert heights.rigid_tracks(pt2, cam2, 8)[:len(X)].sum() == len(X) - 20  # all but the 20 doorway tracks


def test_a_bridges_floor_points_set_its_length_exactly():
    """The doorway of `_two_rooms` with four floor points seen only by its two cameras (two-view tracks), its
    length at 0.6 of the truth (the second room moved along it, the doorway's points scaled about camera 3: the
    same bearings, which leave the length free). Given the model's camera height (1.5), `restore_bridges` sets the
    length that puts those points 1.5 below both cameras: the true one, exactly, every bearing unchanged. Without
    the height it keeps the length it was given."""
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(3))
    floor = np.array([[3.6, HEIGHT, -0.4], [3.9, HEIGHT, 0.3], [4.2, HEIGHT, -0.2], [4.4, HEIGHT, 0.4]])
    X = np.vstack([X, floor])
    new = np.arange(len(X) - 4, len(X))
    cam, pt = np.r_[cam, [3] * 4, [4] * 4], np.r_[pt, new, new]
    seen_by = np.zeros((len(X), 8), bool)
    seen_by[pt, cam] = True
    doorway = seen_by[:, 3] & seen_by[:, 4] & (seen_by.sum(1) == 2)
    second = seen_by[:, 4:].all(1)
    shift = -0.4 * (C[4] - C[3])
    C1, X1 = C.copy(), X.copy()
    C1[4:] += shift
    X1[second] += shift
    X1[doorway] = C[3] + 0.6 * (X[doorway] - C[3])
    np.testing.assert_allclose(_bearings(R, C1, X1, cam, pt), _bearings(R, C, X, cam, pt), atol=1e-12)
    level, down = np.full(8, HEIGHT), np.tile(DOWN, (8, 1))
    C2, X2, bridges, measured = heights.restore_bridges(C1, C1, X1, pt, cam, np.array([0]), level=level, down=down)
    assert (bridges, measured) == (1, 1)
    np.testing.assert_allclose(C2, C, atol=1e-12)
    np.testing.assert_allclose(X2[doorway], X[doorway], atol=1e-12)
    np.testing.assert_allclose(_bearings(R, C2, X2, cam, pt), _bearings(R, C, X, cam, pt), atol=1e-12)
    C3, _, _, measured = heights.restore_bridges(C1, C1, X1, pt, cam, np.array([0]))
    assert measured == 0 and np.allclose(C3, C1)


def test_the_default_spread_limit_keeps_a_walk_within_the_stated_height_error_and_refuses_a_split_level():
    """triangulation.height_prior_sigma states 5 cm at 1.5 m; height_prior_max_spread is twice that: a tour whose
    cameras' heights scatter by 5 cm keeps the prior (several walks), one whose second room stands 20 cm higher (a
    split level: a step between the rooms) does not."""
    from fullview.sfm.options import TriangulationOptions
    options = TriangulationOptions()
    assert abs(options.height_prior_sigma - 0.05 / HEIGHT) < 1e-3
    R, C, X, cam, pt, _ = _two_rooms(np.random.default_rng(0))
    prior = _prior(R, C, X, cam, pt, options.height_prior_sigma)
    for seed in range(10):
        walk = C.copy()
        walk[:, 1] += np.random.default_rng(seed).normal(0.0, 0.05, len(C))
        assert heights.height_spread(walk, X, prior) < options.height_prior_max_spread, seed
    split = C.copy()
    split[4:, 1] -= 0.20  # y is down: the second room's cameras 20 cm higher above the same floor level
    assert heights.height_spread(split, X, prior) > options.height_prior_max_spread
