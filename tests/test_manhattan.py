"""The Manhattan heading prior (`sfm/manhattan.py`, its hooks in `sfm/bundle.py`)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm import manhattan
from fullview.sfm.bundle import _build_layout, _heading_terms, _pack, _prior_cameras, _Problem, bundle_adjust
from fullview.sfm.camera import normalize, tangent_basis
from tests.test_gravity_prior import _chain as gravity_chain
from tests.test_gravity_prior import check_prior_rows_and_schur_step

UP = np.array([0.0, 1.0, 0.0])  # world gravity ("down" is +y, as the filter's estimates)
X_AXIS = np.array([1.0, 0.0, 0.0])


def _yaw(angles):
    return Rotation.from_euler("y", np.asarray(angles)[:, None]).as_matrix()


def _chain(rng, num_cameras=15, points_per_camera=20, noise_rad=np.radians(0.2)):
    """`test_gravity_prior`'s chain of rooms (level cameras 2 m apart, each seeing its own and its neighbours'
    points): the bearings hold the relative poses of neighbours, and the heading drifts along the chain."""
    return gravity_chain(rng, num_cameras=num_cameras, points_per_camera=points_per_camera, noise_rad=noise_rad)


def _measured_axes(R, rng, sigma_rad, world_axes=None):
    """Each camera's axis (the world x axis, or world_axes (N, 3)) seen in its frame, turned about its gravity by
    noise of sigma_rad, and its gravity."""
    axes = np.tile(X_AXIS, (len(R), 1)) if world_axes is None else world_axes
    turn = _yaw(rng.normal(scale=sigma_rad, size=len(R)))
    return np.einsum("nij,nj->ni", R, np.einsum("nij,nj->ni", turn, axes)), np.einsum("nij,j->ni", R, UP)


def _heading_error_deg(R_est, R_true):
    """Each camera's heading error: the angle about the world's vertical of R_trueᵀ R_est... as a yaw."""
    E = np.einsum("nji,njk->nik", R_true, R_est)  # R_trueᵀ R_est: the error in the world frame
    return np.degrees(Rotation.from_matrix(E).as_rotvec() @ UP)


def test_heading_residual_derivative_matches_finite_differences():
    rng = np.random.default_rng(0)
    v = normalize(rng.normal(size=(6, 3)))
    g = normalize(UP + rng.normal(scale=0.05, size=(6, 3)))
    d = normalize(np.cross(g, rng.normal(size=(6, 3))))
    w = rng.uniform(0.5, 2.0, 6)
    _, dr = manhattan.heading_residuals(v, d, g, w)
    h = 1e-7
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (manhattan.heading_residuals(v + e, d, g, w)[0] - manhattan.heading_residuals(v - e, d, g, w)[0]) / (2 * h)
        np.testing.assert_allclose(dr[:, k], fd, rtol=1e-6, atol=1e-9)
    # Δ for small errors, periodic in 90°
    delta = np.radians(0.3)
    turned = np.cos(delta) * d + np.sin(delta) * normalize(np.cross(g, d))
    np.testing.assert_allclose(manhattan.heading_residuals(turned, d, g, np.ones(6))[0], delta, rtol=1e-4)
    quarter = np.cross(g, d)  # the axis 90° on fits as well
    np.testing.assert_allclose(manhattan.heading_residuals(normalize(quarter), d, g, np.ones(6))[0], 0.0, atol=1e-12)


@pytest.mark.parametrize("tilt_free", [False, True])
def test_heading_prior_jacobian_and_schur_step(tilt_free):
    """The bundle adjustment's heading-prior rows (on ω, and on a fixed camera whose tilt is free) match finite
    differences, and the Schur step with them is the step of the full damped system."""
    rng = np.random.default_rng(3)
    R, t, points, cam, pt, bearings = _chain(rng, num_cameras=5, points_per_camera=20)
    R = Rotation.from_rotvec(rng.normal(scale=0.01, size=(5, 3))).as_matrix() @ R
    C = -np.einsum("nji,nj->ni", R, t)
    layout = _build_layout(C, len(points), np.array([0]), None, cam, {0: R[0] @ UP} if tilt_free else None)
    axis, gravity = _measured_axes(R, rng, 0.01)
    prior = manhattan.heading_prior_for_models(R, axis, gravity, np.full(5, 0.002), np.zeros(5, int))
    assert prior is not None and len(prior.camera) == 5
    problem = _Problem(R_init=R, t_init=t, C_init=C, obs_camera=cam, obs_point=pt, bearings=bearings,
                       basis=tangent_basis(bearings), layout=layout,
                       **_heading_terms(prior, R, C, points, cam, pt, bearings))
    x = _pack(layout, C, points) + rng.normal(scale=1e-3, size=layout.num_params)
    assert len(_prior_cameras(problem)) == 5  # one row each
    check_prior_rows_and_schur_step(problem, x, tilt_free)


def test_heading_prior_removes_the_heading_drift_along_a_chain():
    """Noisy bearings (0.2°) on a chain of 15 level cameras let the heading drift (0.08-0.12° on average, seeds 0-2);
    measured axes 0.02° off each hold it (0.012-0.020°: under 0.4 of the drift), and the bearings fit as well."""
    for seed in range(3):
        rng = np.random.default_rng(seed)
        R, t, points, cam, pt, bearings = _chain(rng)
        sigma = np.radians(0.02)
        axis, gravity = _measured_axes(R, rng, sigma)
        kwargs = dict(R_cam_from_world=R, t_cam_from_world=t, points=points, obs_camera=cam, obs_point=pt,
                      obs_bearings=bearings, loss="linear", max_nfev=60)
        free = bundle_adjust(**kwargs)
        prior = manhattan.heading_prior_for_models(R, axis, gravity, np.full(len(R), sigma), np.zeros(len(R), int))
        held = bundle_adjust(**kwargs, heading_prior=prior)
        drift = np.abs(_heading_error_deg(free.R_cam_from_world, R))
        kept = np.abs(_heading_error_deg(held.R_cam_from_world, R))
        assert drift[1:].mean() > 0.05, drift  # there is a drift to remove
        assert kept[1:].mean() < 0.4 * drift[1:].mean(), (seed, drift, kept)
        assert np.median(held.obs_error_rad) < 1.05 * np.median(free.obs_error_rad)


def test_a_scene_without_one_pair_of_wall_directions_gets_no_prior():
    """Cameras whose measured axes point in unrelated world directions (no Manhattan frame) get no prior, and the
    bundle adjustment is then exactly the one without; a wrong camera among agreeing ones is left out."""
    rng = np.random.default_rng(1)
    n = 10
    R = _yaw(rng.uniform(-np.pi, np.pi, n))
    world = _yaw(rng.uniform(0, np.pi / 2, n)) @ X_AXIS  # each camera's axis in another direction
    axis, gravity = _measured_axes(R, rng, 0.0, world)
    assert manhattan.heading_prior_for_models(R, axis, gravity, np.full(n, 0.001), np.zeros(n, int)) is None
    axis, gravity = _measured_axes(R, rng, np.radians(0.02))
    axis[3] = R[3] @ _yaw([np.radians(20.0)])[0] @ X_AXIS  # a room at another angle
    axis[5] = np.nan  # no axis measured
    model_id = np.r_[np.zeros(7, int), np.ones(3, int)]
    model_id[8] = -1  # not registered
    prior = manhattan.heading_prior_for_models(R, axis, gravity, np.full(n, np.radians(0.05)), model_id)
    assert list(prior.camera) == [0, 1, 2, 4, 6]  # model 1 has 2 measured cameras: fewer than 3, no prior
    along = np.maximum(np.abs(prior.axis_world @ X_AXIS), np.abs(prior.axis_world[:, 2]))  # x or z: modulo 90°
    assert (along > np.cos(np.radians(0.1))).all()


def test_manhattan_axis_from_the_lines_of_a_box_room_and_not_from_random_lines():
    """Great circles of the edges of a box room (horizontal ones along x and z, vertical ones) seen by a camera at
    some heading and 1° of tilt give its axis within 0.01°; lines in random horizontal directions give none."""
    rng = np.random.default_rng(2)
    R = Rotation.from_rotvec([0.017, 0.0, 0.0]).as_matrix() @ _yaw([0.7])[0]
    centre = np.array([0.3, 0.0, -0.2])

    def normals(directions, starts):
        a, b = starts - centre, starts + directions - centre
        return np.einsum("ij,nj->ni", R, normalize(np.cross(a, b)))

    x, y, z = np.eye(3)
    starts = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], (60, 3))
    directions = np.concatenate([np.tile(x, (25, 1)), np.tile(z, (25, 1)), np.tile(y, (10, 1))])
    lengths = rng.uniform(20, 200, 60)
    gravity = R @ UP
    found = manhattan.manhattan_axis(normals(directions, starts), lengths, gravity)
    assert found is not None and found[2] >= 40
    truth = R @ x
    angle = np.degrees(np.arccos(np.clip(np.max(np.abs([found[0] @ truth, found[0] @ np.cross(gravity, truth)])),
                                         -1, 1)))
    assert angle < 0.01
    # The frame refined on all the lines corrects a gravity 0.3° off (the vertical lines alone would keep the
    # segments' scatter; here they are exact) and its heading with it.
    off = Rotation.from_rotvec([0.0, 0.0, np.radians(0.3)]).as_matrix() @ gravity
    start = manhattan.manhattan_axis(normals(directions, starts), lengths, off)
    g, d, sigma_g, sigma_d = manhattan.manhattan_frame(normals(directions, starts), lengths, off, start[0])
    assert np.linalg.norm(np.cross(g, gravity)) < 1e-8
    assert min(np.linalg.norm(np.cross(d, truth)), abs(d @ truth)) < 1e-8  # along or across the x axis
    assert sigma_g < np.radians(1e-6) and sigma_d == manhattan.MIN_HEADING_SIGMA_RAD  # exact lines: no scatter
    random_directions = _yaw(rng.uniform(0, np.pi, 60)) @ x
    assert manhattan.manhattan_axis(normals(random_directions, starts), lengths, gravity) is None
