"""The absolute gravity prior of bundle adjustment (`sfm/bundle.py: GravityPrior, gravity_prior_for_models`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.bundle import (
    GravityPrior,
    _build_layout,
    _pack,
    _prior_cameras,
    _prior_terms,
    _Problem,
    _SchurSystem,
    _WeightedResiduals,
    bundle_adjust,
    gravity_error_factor,
    gravity_prior_for_models,
    with_gravity_error,
)
from fullview.sfm.camera import normalize, tangent_basis

UP = np.array([0.0, 1.0, 0.0])  # world gravity ("down" is +y, as in the filter's estimates)


def _yaw(angles):
    return Rotation.from_euler("y", np.asarray(angles)[:, None]).as_matrix()


def _chain(rng, num_cameras=10, points_per_camera=60, noise_rad=np.radians(0.05)):
    """Level cameras 2 m apart along x, each seeing only the points near it (a chain of rooms): bearings hold the
    relative poses of neighbours, and the tilt drifts along the chain."""
    centers = np.stack([2.0 * np.arange(num_cameras), np.zeros(num_cameras), np.zeros(num_cameras)], 1)
    R = _yaw(rng.uniform(-np.pi, np.pi, num_cameras))
    points = np.concatenate([c + rng.uniform([-1.5, -1.2, -2.5], [1.5, 1.2, 2.5], (points_per_camera, 3))
                             for c in centers])
    owner = np.repeat(np.arange(num_cameras), points_per_camera)
    cam, pt = [], []
    for offset in (-1, 0, 1):  # each point is seen by its camera and its neighbours
        seen = (owner + offset >= 0) & (owner + offset < num_cameras)
        cam.append(owner[seen] + offset), pt.append(np.flatnonzero(seen))
    cam, pt = np.concatenate(cam), np.concatenate(pt)
    y = np.einsum("kij,kj->ki", R[cam], points[pt] - centers[cam])
    bearings = normalize(normalize(y) + rng.normal(scale=noise_rad, size=y.shape))
    t = -np.einsum("nij,nj->ni", R, centers)
    return R, t, points, cam, pt, bearings


def _tilt_deg(R):
    """Angle between each camera's true gravity (+y of a level camera) and the world's, as the poses put it."""
    return np.degrees(np.arccos(np.clip(np.einsum("nij,j->ni", R, UP)[:, 1], -1.0, 1.0)))


@pytest.mark.parametrize("tilt_free", [False, True])
def test_schur_step_with_the_prior_solves_the_damped_normal_equations(tilt_free):
    """Analytic Jacobian rows of the prior (and of a fixed camera whose tilt is free) match finite differences, and the
    Schur step is the step of the full damped system."""
    rng = np.random.default_rng(3)
    R, t, points, cam, pt, bearings = _chain(rng, num_cameras=5, points_per_camera=20)
    R = Rotation.from_rotvec(rng.normal(scale=0.01, size=(5, 3))).as_matrix() @ R
    C = -np.einsum("nji,nj->ni", R, t)
    layout = _build_layout(C, len(points), np.array([0]), None, cam, {0: R[0] @ UP} if tilt_free else None)
    gravity = normalize(UP + rng.normal(scale=0.01, size=(5, 3)))
    prior = GravityPrior(camera=np.arange(5), gravity_cam=gravity, up_world=np.tile(UP, (5, 1)),
                         sigma_rad=np.full(5, 0.002), group=np.zeros(5, int))
    terms = _prior_terms(prior, layout, R, C, points, cam, pt, bearings)
    problem = _Problem(R_init=R, t_init=t, C_init=C, obs_camera=cam, obs_point=pt, bearings=bearings,
                       basis=tangent_basis(bearings), layout=layout, **terms)
    x = _pack(layout, C, points) + rng.normal(scale=1e-3, size=layout.num_params)
    check_prior_rows_and_schur_step(problem, x, tilt_free)


def check_prior_rows_and_schur_step(problem: _Problem, x: np.ndarray, tilt_free: bool) -> None:
    """The Jacobian columns of camera 1's ω (and of camera 0's free tilt) match finite differences, the prior's rows
    among them, and the Schur step is the step of the full damped system."""
    objective, layout = _WeightedResiduals(problem), problem.layout
    J, r = objective.jac(x).toarray(), objective.fun(x)
    h = 1e-6
    columns = list(range(layout.cam_col[1], layout.cam_col[1] + 3)) + ([0, 1] if tilt_free else [])
    for col in columns:
        e = np.zeros_like(x)
        e[col] = h
        fd = (objective.fun(x + e) - objective.fun(x - e)) / (2 * h)
        assert np.abs(fd[2 * len(problem.obs_camera):]).max() > 0  # the prior's rows depend on this column
        np.testing.assert_allclose(J[:, col], fd, atol=1e-6 * np.abs(fd).max() + 1e-9)
    damping = 1e-3
    step, _ = _SchurSystem(problem).solve(r.reshape(-1, 2), objective.jac_blocks(x), damping,
                                          objective.prior_blocks(x), _prior_cameras(problem))
    JtJ = J.T @ J
    expected = np.linalg.solve(JtJ + damping * np.diag(np.maximum(np.diag(JtJ), 1e-12)), -J.T @ r)
    np.testing.assert_allclose(step, expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())


def test_gravity_prior_holds_the_tilt_along_a_chain():
    """Noisy bearings (0.2°) on a chain of 15 level cameras let the tilt drift (0.16-0.28° on average, seeds 0-2);
    gravities 0.05° off each hold it (0.035-0.048°), and the bearings still fit as well."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        R, t, points, cam, pt, bearings = _chain(rng, num_cameras=15, points_per_camera=20,
                                                 noise_rad=np.radians(0.2))
        sigma = np.radians(0.05)
        gravity = normalize(UP + rng.normal(scale=sigma, size=(len(R), 3)) * [1, 0, 1])
        kwargs = dict(R_cam_from_world=R, t_cam_from_world=t, points=points, obs_camera=cam, obs_point=pt,
                      obs_bearings=bearings, loss="linear", max_nfev=60)
        free = bundle_adjust(**kwargs)
        prior = gravity_prior_for_models(R, gravity, np.full(len(R), sigma), np.zeros(len(R), int))
        held = bundle_adjust(**kwargs, gravity_prior=prior)
        tilt_free, tilt_held = _tilt_deg(free.R_cam_from_world), _tilt_deg(held.R_cam_from_world)
        assert tilt_held[1:].mean() < 0.4 * tilt_free[1:].mean(), (seed, tilt_free, tilt_held)
        assert np.median(held.obs_error_rad) < 1.05 * np.median(free.obs_error_rad)


def test_gravity_prior_for_models_one_up_per_model_outliers_and_unknowns_left_out():
    rng = np.random.default_rng(0)
    n = 8
    R = _yaw(rng.uniform(-np.pi, np.pi, n))
    model_id = np.array([0, 0, 0, 0, 1, 1, 1, -1])
    R[4:7] = R[4:7] @ Rotation.from_rotvec([0.3, 0.0, 0.0]).as_matrix()  # model 1's world is tilted
    gravity = np.tile(UP, (n, 1))
    gravity[2] = normalize(np.array([0.1, 1.0, 0.0]))  # a wrong vanishing point, 5.7° off
    gravity[5] = np.nan  # no vertical lines
    sigma = np.full(n, np.radians(0.1))
    prior = gravity_prior_for_models(R, gravity, sigma, model_id)
    assert list(prior.camera) == [0, 1, 3, 4, 6]
    np.testing.assert_allclose(prior.up_world[:3], np.tile(UP, (3, 1)), atol=1e-12)
    np.testing.assert_allclose(prior.up_world[3:], np.tile(R[4].T @ UP, (2, 1)), atol=1e-12)
    # A standard error below the floor is raised to it.
    sigma[0] = 1e-9
    assert gravity_prior_for_models(R, gravity, sigma, model_id).sigma_rad[0] > 1e-6
    assert gravity_prior_for_models(R, np.full((n, 3), np.nan), sigma, model_id) is None
    assert gravity_prior_for_models(R, np.zeros((n, 3)), np.full(n, np.inf), model_id) is None  # as the filter
    # stores unknown gravity


@pytest.mark.parametrize("views", [2, 3])
def test_the_observation_noise_the_prior_is_weighed_against_is_not_understated_by_the_fitted_points(views):
    """The prior's weight is σ_obs / σ_g, with σ_obs from the residuals of triangulated points. A two-view track's
    point absorbs 3 of its 4 residual components, so the residuals' median alone gave 0.39 of the true noise (0.67
    with three views): the prior 2-7 times too weak against the bearings. Counted with the residual degrees of
    freedom it is the noise."""
    rng = np.random.default_rng(5)
    noise = np.radians(0.05)
    centers = np.stack([2.0 * np.arange(views), np.zeros(views), 0.3 * (-1.0) ** np.arange(views)], 1)
    R = _yaw(rng.uniform(-np.pi, np.pi, views))
    t = -np.einsum("nij,nj->ni", R, centers)
    points = rng.uniform([-2.0, -1.5, 2.0], [2.0 * views, 1.5, 5.0], (3000, 3))
    cam, pt = np.tile(np.arange(views), len(points)), np.repeat(np.arange(len(points)), views)
    y = np.einsum("kij,kj->ki", R[cam], points[pt] - centers[cam])
    bearings = normalize(normalize(y) + rng.normal(scale=noise, size=y.shape))
    fitted = bundle_adjust(R_cam_from_world=R, t_cam_from_world=t, points=points, obs_camera=cam, obs_point=pt,
                           obs_bearings=bearings, fixed_cameras=tuple(range(views)), loss="soft_l1",
                           loss_scale_rad=1.0, max_nfev=20)
    prior = GravityPrior(camera=np.arange(views), gravity_cam=np.einsum("nij,j->ni", R, UP),
                         up_world=np.tile(UP, (views, 1)), group=np.zeros(views, np.int64),
                         sigma_rad=np.full(views, 1.0))
    terms = _prior_terms(prior, None, R, centers, fitted.points, cam, pt, bearings)
    np.testing.assert_allclose(terms["prior_sqrt_w"], noise, rtol=0.1)  # σ_obs / σ_g with σ_g = 1


def _noisy_gravities(rng, R, up_world, sigma_true):
    """Each camera's gravity in its frame, off the true one by isotropic tangent noise of sigma_true per component."""
    true = np.einsum("nij,nj->ni", R, up_world)
    basis = tangent_basis(true)
    return normalize(true + np.einsum("nk,nki->ni", rng.normal(size=(len(R), 2)) * sigma_true[:, None], basis))


@pytest.mark.parametrize("understated", [1.0, 1.7, 4.0])
def test_gravity_error_factor_recovers_how_much_the_standard_errors_are_understated(understated):
    """Two models (one with a tilted world), gravities off by their true standard errors (0.1-0.4°, one per
    camera) but stated `understated` times smaller: the factor is that ratio, and the widened prior states them."""
    rng = np.random.default_rng(11)
    n = 400
    model_id = np.repeat([0, 1], n // 2)
    R = _yaw(rng.uniform(-np.pi, np.pi, n))
    up_world = np.tile(UP, (n, 1))
    up_world[model_id == 1] = Rotation.from_rotvec([0.2, 0.0, 0.1]).apply(UP)
    sigma_true = np.radians(rng.uniform(0.1, 0.4, n))  # stated above MIN_GRAVITY_SIGMA_RAD
    gravity = _noisy_gravities(rng, R, up_world, sigma_true)
    prior = gravity_prior_for_models(R, gravity, sigma_true / understated, model_id)
    factor = gravity_error_factor(R, prior)
    np.testing.assert_allclose(factor, understated, rtol=0.08)
    np.testing.assert_allclose(with_gravity_error(prior, factor).sigma_rad, prior.sigma_rad * factor)


def test_a_stated_standard_error_is_widened_never_narrowed():
    rng = np.random.default_rng(2)
    R = _yaw(rng.uniform(-np.pi, np.pi, 6))
    sigma = np.radians(np.full(6, 0.2))
    prior = gravity_prior_for_models(R, _noisy_gravities(rng, R, np.tile(UP, (6, 1)), sigma / 4), sigma,
                                     np.zeros(6, int))
    assert gravity_error_factor(R, prior) < 0.6
    np.testing.assert_array_equal(with_gravity_error(prior, gravity_error_factor(R, prior)).sigma_rad, sigma)
    one = gravity_prior_for_models(R[:1], np.einsum("ij,j->i", R[0], UP)[None], sigma[:1], np.zeros(1, int))
    assert gravity_error_factor(R[:1], one) == 1.0  # no redundancy: the stated error stands


def test_a_prior_stated_too_confident_is_widened_and_holds_the_tilt_as_the_right_one_does():
    """A chain of 15 cameras whose gravities are 0.3° off but stated as 0.075°: held to them, each camera follows its
    own error (0.049-0.058° of tilt on average, seeds 0-2). The pose round's spread measures the understatement
    (2.5-4×), and the prior widened by it holds the tilt as well as the right standard errors (0.021-0.034°)."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        R, t, points, cam, pt, bearings = _chain(rng, num_cameras=15, points_per_camera=40)
        sigma_true = np.full(len(R), np.radians(0.3))
        gravity = _noisy_gravities(rng, R, np.tile(UP, (len(R), 1)), sigma_true)
        kwargs = dict(t_cam_from_world=t, points=points, obs_camera=cam, obs_point=pt, obs_bearings=bearings,
                      loss="linear", max_nfev=60)
        stated = bundle_adjust(R_cam_from_world=R, **kwargs,
                               gravity_prior=gravity_prior_for_models(R, gravity, sigma_true / 4, np.zeros(15, int)))
        R_pose = stated.R_cam_from_world
        prior = gravity_prior_for_models(R_pose, gravity, sigma_true / 4, np.zeros(15, int))
        factor = gravity_error_factor(R_pose, prior)
        assert 2.0 < factor < 5.0, (seed, factor)
        widened = bundle_adjust(R_cam_from_world=R_pose, **{**kwargs, "t_cam_from_world": stated.t_cam_from_world,
                                                            "points": stated.points},
                                gravity_prior=with_gravity_error(prior, factor))
        right = bundle_adjust(R_cam_from_world=R, **kwargs,
                              gravity_prior=gravity_prior_for_models(R, gravity, sigma_true, np.zeros(15, int)))
        tilt = [_tilt_deg(x.R_cam_from_world)[1:].mean() for x in (stated, widened, right)]
        assert tilt[1] < 0.75 * tilt[0] and tilt[1] < 1.25 * tilt[2], (seed, tilt)
