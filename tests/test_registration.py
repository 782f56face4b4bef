"""Tests of fullview.sfm.registration (global rotation / translation averaging, planar model)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.metrics import umeyama
from fullview.sfm.rotations import rotation_angle_deg
from fullview.sfm.registration import (
    consensus_sweeps,
    flexible_modes,
    planar_epipole_cost,
    planar_epipole_cost_derivatives,
    register,
    relative_from_absolute,
    rotation_yaw,
    spanning_tree_rotations,
    translation_averaging,
    triangle_support,
    yaw_rotation,
)

# ---------------------------------------------------------------------------------------------
# synthetic scenes
# ---------------------------------------------------------------------------------------------


def make_scene(rng, n, *, planar=False, tilt_deg=8.0, extent=10.0):
    """Ground-truth R_cam_from_world (n,3,3) and centres (n,3)."""
    centres = rng.uniform(-extent / 2, extent / 2, (n, 3))
    yaw = rng.uniform(-np.pi, np.pi, n)
    if planar:
        centres[:, 1] = 0.0
        R = yaw_rotation(yaw)
    else:
        centres[:, 1] *= 0.2  # y is vertical: flatter in height
        tilt = Rotation.from_rotvec(np.radians(tilt_deg) * rng.uniform(-1, 1, (n, 3)) * [1, 0, 1]).as_matrix()
        R = tilt @ yaw_rotation(yaw)
    return R, centres


def knn_pairs(centres, k):
    n = len(centres)
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    nbr = np.argsort(d, axis=1)[:, 1 : k + 1]
    pairs = {(min(a, b), max(a, b)) for a in range(n) for b in nbr[a]}
    return np.array(sorted(pairs), dtype=np.int64)


def perturb_rotations(rng, R, sigma_deg):
    axis = rng.normal(size=(len(R), 3))
    return Rotation.from_rotvec(np.radians(sigma_deg) / np.sqrt(3) * axis).as_matrix() @ R


def perturb_directions(rng, t, sigma_deg):
    axis = np.cross(t, rng.normal(size=t.shape))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.radians(sigma_deg) * rng.normal(size=len(t))
    return Rotation.from_rotvec(axis * ang[:, None]).apply(t)


def make_measurements(rng, R, centres, pairs, *, rot_noise_deg=0.0, dir_noise_deg=0.0, outlier_fraction=0.0,
                      min_inlier_degree=3):
    t = -np.einsum("nab,nb->na", R, centres)
    R_rel, t_rel = relative_from_absolute(R, t, pairs[:, 0], pairs[:, 1])
    R_rel = perturb_rotations(rng, R_rel, rot_noise_deg) if rot_noise_deg else R_rel
    t_rel = perturb_directions(rng, t_rel, dir_noise_deg) if dir_noise_deg else t_rel
    weights = rng.integers(50, 500, len(pairs)).astype(float)
    outlier = np.zeros(len(pairs), bool)
    deg = np.bincount(pairs.ravel(), minlength=len(R))
    for p in rng.permutation(len(pairs)):
        if outlier.sum() >= round(outlier_fraction * len(pairs)):
            break
        if (deg[pairs[p]] - 1 < min_inlier_degree).any():
            continue
        deg[pairs[p]] -= 1
        outlier[p] = True
        while True:  # gross: far from the truth in both rotation and direction
            Rr = Rotation.random(random_state=rng.integers(2**31)).as_matrix()
            tr = rng.normal(size=3)
            tr /= np.linalg.norm(tr)
            if rotation_angle_deg(Rr, R_rel[p]) > 20 and np.degrees(np.arccos(tr @ t_rel[p])) > 20:
                break
        R_rel[p], t_rel[p] = Rr, tr
    return R_rel, t_rel, weights, outlier


def pose_errors(reg, R_true, c_true, idx=None):
    """(max rotation error deg, max centre error / scene size) after gauge / similarity alignment.

    Scene size = largest distance between two ground-truth centres.
    """
    idx = np.flatnonzero(reg.registered) if idx is None else idx
    R_est = reg.R_cam_from_world[idx]
    # R_est_k ≈ R_true_k G
    M = np.einsum("kba,kbc->ac", R_true[idx], R_est)
    U, _, Vt = np.linalg.svd(M)
    G = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    rot_err = rotation_angle_deg(R_est, R_true[idx] @ G)
    aligned = umeyama(reg.centers[idx], c_true[idx]).apply(reg.centers[idx])
    size = np.linalg.norm(c_true[idx, None] - c_true[None, idx], axis=-1).max()
    return rot_err.max(), np.linalg.norm(aligned - c_true[idx], axis=1).max() / size


def run(R_true, c_true, pairs, R_rel, t_rel, weights, **kw):
    return register(num_images=len(R_true), pairs=pairs, R_j_from_i=R_rel, t_j_from_i=t_rel, weights=weights, **kw)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def test_rotation_angle_deg_matches_scipy_including_extremes():
    rng = np.random.default_rng(0)
    Ra = Rotation.random(50, random_state=1).as_matrix()
    Rb = Rotation.random(50, random_state=2).as_matrix()
    expected = np.degrees((Rotation.from_matrix(Ra) * Rotation.from_matrix(Rb).inv()).magnitude())
    np.testing.assert_allclose(rotation_angle_deg(Ra, Rb), expected, atol=1e-9)
    tiny = Rotation.from_rotvec([1e-9, 0, 0]).as_matrix()
    assert rotation_angle_deg(tiny, np.eye(3)) == pytest.approx(np.degrees(1e-9), rel=1e-6)
    axis = rng.normal(size=3)
    half = Rotation.from_rotvec((np.pi - 1e-7) * axis / np.linalg.norm(axis)).as_matrix()
    assert rotation_angle_deg(half, np.eye(3)) == pytest.approx(180.0 - np.degrees(1e-7), abs=1e-9)
    assert rotation_angle_deg(half, half) == pytest.approx(0.0, abs=1e-12)
    assert rotation_angle_deg(Ra[:, None], Rb[None]).shape == (50, 50)  # broadcasts


def test_relative_from_absolute_follows_convention():
    rng = np.random.default_rng(1)
    R, c = make_scene(rng, 2)
    t = -np.einsum("nab,nb->na", R, c)
    R_rel, t_rel = relative_from_absolute(R, t, 0, 1)
    x_world = rng.normal(size=3)
    x_i, x_j = R[0] @ x_world + t[0], R[1] @ x_world + t[1]
    scale = np.linalg.norm(c[1] - c[0])
    np.testing.assert_allclose(x_j, R_rel @ x_i + scale * t_rel, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(t_rel), 1.0)
    np.testing.assert_allclose(-R[1].T @ t_rel, (c[1] - c[0]) / scale, atol=1e-12)  # world baseline


def test_yaw_round_trip():
    theta = np.linspace(-3.1, 3.1, 13)
    R = yaw_rotation(theta)
    np.testing.assert_allclose(R, Rotation.from_rotvec(theta[:, None] * [0, 1, 0]).as_matrix(), atol=1e-15)
    np.testing.assert_allclose(rotation_yaw(R), theta, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# general model
# ---------------------------------------------------------------------------------------------


def test_general_noise_free_is_exact_and_gauge_is_documented():
    rng = np.random.default_rng(3)
    R, c = make_scene(rng, 10, tilt_deg=30)
    pairs = knn_pairs(c, 4)
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert reg.registered.all() and reg.pair_inlier_mask.all() and reg.pair_used_mask.all()
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 1e-6 and c_err < 1e-6
    # gauge: first image at identity / origin, mean distance to centroid 1
    assert reg.reference_image == 0
    np.testing.assert_allclose(reg.R_cam_from_world[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(reg.centers[0], 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(reg.centers - reg.centers.mean(0), axis=1).mean(), 1.0)
    np.testing.assert_allclose(reg.t_cam_from_world, -np.einsum("nab,nb->na", reg.R_cam_from_world, reg.centers))
    # exact gauge transform of the truth: R_k R_0ᵀ
    np.testing.assert_allclose(reg.R_cam_from_world, R @ R[0].T, atol=1e-8)
    assert np.nanmax(reg.rotation_residual_deg) < 1e-6 and np.nanmax(reg.direction_residual_deg) < 1e-6
    assert reg.epipole_cost < 1e-12


@pytest.mark.parametrize("n, k, seed", [(6, 5, 10), (12, 6, 11), (16, 6, 12), (24, 7, 13), (24, 5, 14)])
def test_general_noisy_with_outliers(n, k, seed):
    rng = np.random.default_rng(seed)
    R, c = make_scene(rng, n)
    pairs = knn_pairs(c, k)
    R_rel, t_rel, w, outlier = make_measurements(
        rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2, outlier_fraction=0.15)
    assert outlier.sum() >= 0.1 * len(pairs)
    assert flexible_modes(c, pairs[~outlier]) == 0
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert reg.registered.all() and reg.flexible_modes == 0
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 0.1, rot_err
    assert c_err < 0.01, c_err
    assert not reg.pair_inlier_mask[outlier].any()
    assert not reg.pair_used_mask[outlier].any()
    assert reg.pair_inlier_mask[~outlier].all()
    assert np.nanmax(reg.rotation_residual_deg[~outlier]) < 0.5
    assert np.nanmin(reg.rotation_residual_deg[outlier]) > 5 or np.nanmin(reg.direction_residual_deg[outlier]) > 10


def test_general_arbitrary_rotations_dense_graph():
    rng = np.random.default_rng(20)
    n = 15
    _, c = make_scene(rng, n)
    R = Rotation.random(n, random_state=21).as_matrix()
    pairs = knn_pairs(c, 8)
    R_rel, t_rel, w, outlier = make_measurements(
        rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2, outlier_fraction=0.2)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    rot_err, c_err = pose_errors(reg, R, c)
    assert reg.registered.all() and rot_err < 0.1 and c_err < 0.01
    np.testing.assert_array_equal(reg.pair_inlier_mask, ~outlier)


def test_heaviest_pairs_being_outliers_do_not_break_the_spanning_tree_init():
    rng = np.random.default_rng(30)
    R, c = make_scene(rng, 14)
    pairs = knn_pairs(c, 6)
    R_rel, t_rel, w, outlier = make_measurements(
        rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2, outlier_fraction=0.15)
    w[outlier] = 10_000.0  # every outlier is in the maximum-weight spanning tree
    reg = run(R, c, pairs, R_rel, t_rel, w)
    rot_err, c_err = pose_errors(reg, R, c)
    assert reg.registered.all() and rot_err < 0.1 and c_err < 0.01
    np.testing.assert_array_equal(reg.pair_inlier_mask, ~outlier)


def test_triangle_support_and_consensus_repair_a_tree_through_outliers():
    rng = np.random.default_rng(31)
    n = 12
    R, c = make_scene(rng, n)
    pairs = knn_pairs(c, 5)
    R_rel, t_rel, w, outlier = make_measurements(rng, R, c, pairs, rot_noise_deg=0.05, outlier_fraction=0.2)
    mask = np.ones(len(pairs), bool)
    support = triangle_support(n, pairs, R_rel, w, mask)
    assert (support[outlier] == 0).all() and np.median(support[~outlier]) >= 2
    w_bad = np.where(outlier, 1e4, w)  # the maximum-weight tree takes every outlier it can

    def errors(R_est):  # up to the best-supported global rotation R_est_k ≈ R_k G
        G = np.swapaxes(R, -1, -2) @ R_est
        err = rotation_angle_deg(R_est[None], R[None] @ G[:, None])
        return err[np.argmin(np.median(err, axis=1))]

    R_tree = spanning_tree_rotations(n, pairs, R_rel, w_bad, mask, 0)
    assert (errors(R_tree) > 20).sum() >= 2
    R_fixed = consensus_sweeps(R_tree, pairs, R_rel)
    assert errors(R_fixed).max() < 0.5
    R_prior = spanning_tree_rotations(n, pairs, R_rel, w_bad, mask, 0, priority=support)
    assert errors(R_prior).max() < 0.5


def test_reversed_and_duplicate_pairs():
    rng = np.random.default_rng(32)
    R, c = make_scene(rng, 8)
    pairs = knn_pairs(c, 4)
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2)
    flip = np.arange(len(pairs)) % 2 == 1  # express every other pair as (j, i)
    pairs2 = np.where(flip[:, None], pairs[:, ::-1], pairs)
    t = -np.einsum("nab,nb->na", R, c)
    R2, t2 = relative_from_absolute(R, t, pairs2[:, 0], pairs2[:, 1])
    R2 = np.where(flip[:, None, None], R2, R_rel)
    t2 = np.where(flip[:, None], t2, t_rel)
    # plus a duplicate of pair 0 that is a gross outlier with a low weight
    pairs2 = np.vstack([pairs2, pairs2[:1]])
    R2 = np.concatenate([R2, Rotation.from_rotvec([[0, 2.0, 0]]).as_matrix() @ R2[:1]])
    t2 = np.vstack([t2, [[1.0, 0, 0]]])
    w2 = np.append(w, 1.0)
    reg = run(R, c, pairs2, R2, t2, w2)
    rot_err, c_err = pose_errors(reg, R, c)
    assert reg.registered.all() and rot_err < 0.1 and c_err < 0.01
    assert not reg.pair_inlier_mask[-1] and reg.pair_inlier_mask[:-1].all()


def test_disconnected_images_are_unregistered():
    rng = np.random.default_rng(4)
    R, c = make_scene(rng, 12)
    main = knn_pairs(c[:8], 4)
    # images 8, 9 only connected to each other; 10 isolated; 11 connected by a too-light pair only
    pairs = np.vstack([main, [[8, 9], [3, 11]]])
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2)
    w[-1] = 5.0
    reg = run(R, c, pairs, R_rel, t_rel, w, min_weight=20)
    np.testing.assert_array_equal(reg.registered, np.arange(12) < 8)
    assert np.isnan(reg.centers[8:]).all() and np.isnan(reg.R_cam_from_world[8:]).all()
    assert np.isnan(reg.t_cam_from_world[8:]).all()
    assert not reg.pair_inlier_mask[-2:].any() and np.isnan(reg.rotation_residual_deg[-2:]).all()
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 0.1 and c_err < 0.01
    # without the weight threshold image 11 (one pair: position along the ray unknown) is peeled off
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert not reg.registered[11]
    reg = run(R, c, pairs, R_rel, t_rel, w, min_pairs_per_camera=1)
    assert reg.registered[11] and reg.pair_used_mask[-1]


def test_camera_with_only_outlier_pairs_is_unregistered():
    rng = np.random.default_rng(5)
    R, c = make_scene(rng, 12)
    pairs = knn_pairs(c, 5)
    R_rel, t_rel, w, outlier = make_measurements(rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2)
    bad = 7
    on_bad = (pairs == bad).any(1)
    assert on_bad.sum() >= 3
    R_rel[on_bad] = Rotation.random(on_bad.sum(), random_state=6).as_matrix()
    t_rel[on_bad] = rng.normal(size=(on_bad.sum(), 3))
    t_rel[on_bad] /= np.linalg.norm(t_rel[on_bad], axis=1, keepdims=True)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    np.testing.assert_array_equal(reg.registered, np.arange(12) != bad)
    assert not reg.pair_inlier_mask[on_bad].any()
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 0.1 and c_err < 0.01


def test_corridor_nearly_collinear_layout():
    rng = np.random.default_rng(7)
    n = 16
    c = np.zeros((n, 3))
    c[:, 2] = np.cumsum(rng.uniform(0.8, 1.2, n))  # walking along z
    c[:, 0] = 0.15 * rng.normal(size=n)  # small lateral wobble
    c[:, 1] = 0.02 * rng.normal(size=n)
    R = yaw_rotation(rng.uniform(-0.2, 0.2, n))
    pairs = np.array([(a, b) for a in range(n) for b in range(a + 1, min(a + 4, n))])
    R_rel, t_rel, w, outlier = make_measurements(
        rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2, outlier_fraction=0.1)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert reg.registered.all()
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 0.1 and c_err < 0.03, c_err
    assert not reg.pair_inlier_mask[outlier].any()


def test_exactly_collinear_layout_does_not_crash_and_keeps_order():
    rng = np.random.default_rng(8)
    n = 8
    c = np.zeros((n, 3))
    c[:, 2] = np.cumsum(rng.uniform(0.5, 1.5, n))
    R = yaw_rotation(rng.uniform(-1, 1, n))
    pairs = np.array([(a, b) for a in range(n) for b in range(a + 1, min(a + 3, n))])
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert reg.registered.all()
    # positions along the line are not observable, but the line and the ordering are
    direction = reg.centers[-1] - reg.centers[0]
    direction /= np.linalg.norm(direction)
    along = reg.centers @ direction
    assert np.all(np.diff(along) > 0)
    off_line = reg.centers - along[:, None] * direction
    assert np.abs(off_line).max() < 1e-6
    assert np.all(np.isfinite(reg.centers))
    assert reg.flexible_modes > 0  # the spacing along the line is not observable and is reported


def test_flexible_modes_counts_non_rigid_layouts():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 1]])
    assert flexible_modes(tri, [(0, 1), (1, 2), (0, 2)]) == 0
    assert flexible_modes(tri, [(0, 1), (1, 2)]) == 1  # a path: the ratio of the two baselines is free
    assert flexible_modes(tri[:2], [(0, 1)]) == 0
    # two rigid triangles sharing a single camera: their relative scale is free
    two = np.vstack([tri, tri[1:] + [3.0, 0, 2]])
    assert flexible_modes(two, [(0, 1), (1, 2), (0, 2), (0, 3), (3, 4), (0, 4)]) == 1


def test_no_usable_pairs_registers_nothing():
    reg = register(num_images=3, pairs=np.zeros((0, 2), int), R_j_from_i=np.zeros((0, 3, 3)),
                   t_j_from_i=np.zeros((0, 3)), weights=np.zeros(0))
    assert not reg.registered.any() and reg.reference_image == -1
    reg = register(num_images=2, pairs=[(0, 1)], R_j_from_i=np.eye(3)[None], t_j_from_i=[[np.nan, 0, 0]],
                   weights=[10.0])
    assert not reg.registered.any() and not reg.pair_inlier_mask.any()


def test_two_images():
    rng = np.random.default_rng(9)
    R, c = make_scene(rng, 2)
    pairs = np.array([[0, 1]])
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs)
    reg = run(R, c, pairs, R_rel, t_rel, w)
    assert reg.registered.all()
    np.testing.assert_allclose(reg.R_cam_from_world[1], R_rel[0], atol=1e-12)
    np.testing.assert_allclose(reg.centers[1], 2 * (-R_rel[0].T @ t_rel[0]), atol=1e-9)  # spread 1


def test_bad_inputs_name_the_value():
    ok = dict(num_images=2, pairs=[(0, 1)], R_j_from_i=np.eye(3)[None], t_j_from_i=[[1.0, 0, 0]], weights=[1.0])
    with pytest.raises(ValueError, match="model"):
        register(**ok, model="spherical")
    with pytest.raises(ValueError, match=r"pair \(0, 2\)"):
        register(**{**ok, "pairs": [(0, 2)]})
    with pytest.raises(ValueError, match="t_j_from_i"):
        register(**{**ok, "t_j_from_i": np.zeros((2, 3))})
    with pytest.raises(ValueError, match="weights"):
        register(**{**ok, "weights": [1.0, 2.0]})


def test_explicit_sign_ambiguous_epipoles_give_same_result():
    rng = np.random.default_rng(15)
    R, c = make_scene(rng, 9)
    pairs = knn_pairs(c, 4)
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2)
    e_ij = -np.einsum("pba,pb->pa", R_rel, t_rel)
    signs = rng.choice([-1.0, 1.0], size=(len(pairs), 1))
    ref = run(R, c, pairs, R_rel, t_rel, w)
    reg = run(R, c, pairs, R_rel, t_rel, w, e_ij=signs * e_ij, e_ji=-signs * t_rel)
    np.testing.assert_allclose(reg.centers, ref.centers, atol=1e-9)
    e_ij[0] = np.nan  # a missing epipole falls back to the one derived from (R, t)
    reg = run(R, c, pairs, R_rel, t_rel, w, e_ij=e_ij, e_ji=np.zeros_like(t_rel))
    np.testing.assert_allclose(reg.centers, ref.centers, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# planar model (the report's method)
# ---------------------------------------------------------------------------------------------


def _true_epipoles(R, c, pairs):
    e_ij = np.einsum("pab,pb->pa", R[pairs[:, 0]], c[pairs[:, 1]] - c[pairs[:, 0]])
    e_ji = np.einsum("pab,pb->pa", R[pairs[:, 1]], c[pairs[:, 0]] - c[pairs[:, 1]])
    return (e_ij / np.linalg.norm(e_ij, axis=1, keepdims=True), e_ji / np.linalg.norm(e_ji, axis=1, keepdims=True))


def test_planar_cost_is_zero_at_truth_and_derivatives_match():
    rng = np.random.default_rng(40)
    R, c = make_scene(rng, 8, planar=True)
    c[:, 1] = 0.3 * rng.normal(size=8)  # cost is exact also for different heights
    theta = rotation_yaw(R)
    pairs = knn_pairs(c, 4)
    e_ij, e_ji = _true_epipoles(R, c, pairs)
    flip = rng.choice([-1.0, 1.0], size=(len(pairs), 1))
    assert planar_epipole_cost(theta, pairs, flip * e_ij, e_ji) == pytest.approx(0.0, abs=1e-12)
    assert planar_epipole_cost(theta + rng.normal(0, 0.1, 8), pairs, e_ij, e_ji) > 1e-4
    x = theta + rng.normal(0, 0.3, 8)
    f, g, H = planar_epipole_cost_derivatives(x, pairs, e_ij, e_ji)
    h = 1e-6
    eye = np.eye(8)
    g_num = np.array([(planar_epipole_cost(x + h * eye[k], pairs, e_ij, e_ji)
                       - planar_epipole_cost(x - h * eye[k], pairs, e_ij, e_ji)) / (2 * h) for k in range(8)])
    H_num = np.array([(planar_epipole_cost_derivatives(x + h * eye[k], pairs, e_ij, e_ji)[1]
                       - planar_epipole_cost_derivatives(x - h * eye[k], pairs, e_ij, e_ji)[1]) / (2 * h)
                      for k in range(8)])
    np.testing.assert_allclose(g, g_num, atol=1e-7)
    np.testing.assert_allclose(H.toarray(), H_num, atol=1e-6)


def test_planar_noise_free_is_exact():
    rng = np.random.default_rng(41)
    R, c = make_scene(rng, 12, planar=True)
    pairs = knn_pairs(c, 4)
    R_rel, t_rel, w, _ = make_measurements(rng, R, c, pairs)
    reg = run(R, c, pairs, R_rel, t_rel, w, model="planar")
    assert reg.model == "planar" and reg.registered.all() and reg.pair_inlier_mask.all()
    np.testing.assert_allclose(reg.R_cam_from_world, R @ R[0].T, atol=1e-9)
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 1e-6 and c_err < 1e-6
    assert reg.epipole_cost < 1e-12
    # all rotations are about the (downward) world y axis
    np.testing.assert_allclose(reg.R_cam_from_world[:, 1], np.tile([0, 1, 0], (12, 1)), atol=1e-12)


@pytest.mark.parametrize("n, seed", [(6, 42), (12, 43), (24, 44)])
def test_planar_noisy_with_outliers(n, seed):
    rng = np.random.default_rng(seed)
    R, c = make_scene(rng, n, planar=True)
    pairs = knn_pairs(c, 6)
    R_rel, t_rel, w, outlier = make_measurements(
        rng, R, c, pairs, rot_noise_deg=0.05, dir_noise_deg=0.2, outlier_fraction=0.15)
    assert flexible_modes(c, pairs[~outlier]) == 0  # the inlier graph determines the layout
    reg = run(R, c, pairs, R_rel, t_rel, w, model="planar")
    assert reg.registered.all() and reg.flexible_modes == 0
    rot_err, c_err = pose_errors(reg, R, c)
    assert rot_err < 0.1 and c_err < 0.01, (rot_err, c_err)
    assert not reg.pair_inlier_mask[outlier].any()
    assert reg.pair_inlier_mask[~outlier].all()


def test_the_chordal_refinement_does_not_collapse_a_part_the_directions_leave_free():
    """Stored baseline directions of the bare 2048 px home (seed 3, filter seed 1): its chordal refinement, whose cost
    sees directions only, shrank one room's four cameras (a part whose scale the directions leave free) to a point,
    pairs 1e-10 of the median length, and nothing later separated them. LUD's λ ≥ 1 layout is kept instead."""
    data = np.load(Path(__file__).parent / "data" / "collapsing_layout.npz")
    centres, used = translation_averaging(
        int(data["num_images"]), data["pairs"], data["directions"], int(data["root"]), weights=data["weights"],
        max_direction_residual_deg=float(data["max_direction_residual_deg"]))
    pairs = data["pairs"][used]
    lengths = np.linalg.norm(centres[pairs[:, 1]] - centres[pairs[:, 0]], axis=1)
    assert used.sum() > 50 and np.isfinite(centres).all()
    assert lengths.min() > 0.1 * np.median(lengths)
