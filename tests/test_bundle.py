"""Tests of fullview.sfm.bundle: residuals, analytic Jacobian, gauge, convergence, robustness.

Run as a script (``python tests/test_bundle.py``) for a timing check with 24 cameras and 5000 points.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

import fullview.sfm.bundle as bundle_module
from fullview.sfm.bundle import (
    _build_layout,
    _SchurSystem,
    _WeightedResiduals,
    _jacobian_structure,
    _pack,
    _Problem,
    _residuals,
    bundle_adjust,
    rotation_exp,
)
from fullview.sfm.camera import normalize, tangent_basis

NOISE_RAD = 0.0015  # ≈ 0.5 px at 2048 px width


def _scene(rng, num_cameras=8, num_points=300, visibility=0.7):
    """Cameras on a ring with random orientations, points around them, random visibility (>= 2 views)."""
    ang = np.linspace(0, 2 * np.pi, num_cameras, endpoint=False)
    centers = np.stack([3 * np.cos(ang), 0.3 * rng.normal(size=num_cameras), 3 * np.sin(ang)], 1)
    R = Rotation.random(num_cameras, random_state=rng).as_matrix()
    t = -np.einsum("nij,nj->ni", R, centers)
    points = rng.uniform(-8, 8, size=(3 * num_points, 3))
    points = points[(np.linalg.norm(points[:, None] - centers[None], axis=2) > 1.5).all(1)][:num_points]
    seen = rng.random((num_cameras, num_points)) < visibility
    seen[:2] = True
    cam, pt = np.nonzero(seen)
    bearings = normalize(np.einsum("kij,kj->ki", R[cam], points[pt]) + t[cam])
    return dict(R=R, t=t, centers=centers, points=points, cam=cam, pt=pt, bearings=bearings)


def _perturb(rng, s, rot_rad=0.02, pos=0.1, fixed=(0,)):
    """Perturbed poses (fixed cameras exact) and points."""
    n = len(s["R"])
    dR = Rotation.from_rotvec(rng.normal(scale=rot_rad, size=(n, 3))).as_matrix()
    R = dR @ s["R"]
    C = s["centers"] + rng.normal(scale=pos, size=(n, 3))
    R[list(fixed)], C[list(fixed)] = s["R"][list(fixed)], s["centers"][list(fixed)]
    t = -np.einsum("nij,nj->ni", R, C)
    t[list(fixed)] = s["t"][list(fixed)]
    return R, t, s["points"] + rng.normal(scale=pos, size=s["points"].shape)


def _rotation_errors_deg(R_est, R_true):
    rel = np.einsum("nji,njk->nik", R_est, R_true)
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def _problem(R, t, points, cam, pt, bearings, fixed=(0,)):
    C = -np.einsum("nji,nj->ni", R, t)
    layout = _build_layout(C, len(points), np.array(fixed), None, cam)
    return _Problem(R_init=R, t_init=t, C_init=C, obs_camera=cam, obs_point=pt, bearings=bearings,
                    basis=tangent_basis(bearings), layout=layout)


def _run(R, t, points, s, bearings=None, **kw):
    return bundle_adjust(R_cam_from_world=R, t_cam_from_world=t, points=points, obs_camera=s["cam"],
                         obs_point=s["pt"], obs_bearings=s["bearings"] if bearings is None else bearings, **kw)


def test_tangent_basis_is_orthonormal_and_orthogonal():
    z = normalize(np.random.default_rng(0).normal(size=(500, 3)))
    z[:3] = np.eye(3)
    E = tangent_basis(z)
    np.testing.assert_allclose(np.einsum("kij,klj->kil", E, E), np.broadcast_to(np.eye(2), (500, 2, 2)), atol=1e-12)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", E, z), 0.0, atol=1e-12)


def test_rotation_exp_and_left_jacobian():
    rng = np.random.default_rng(1)
    omega = np.concatenate([rng.normal(size=(20, 3)), 1e-5 * rng.normal(size=(5, 3)), np.zeros((1, 3))])
    R, J = rotation_exp(omega)
    np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=1e-12)
    v, h = rng.normal(size=3), 1e-6
    for k in range(3):  # exp(ω + δ) v ≈ exp(ω) v − [exp(ω) v]× J_l δ
        e = np.zeros(3)
        e[k] = h
        fd = (rotation_exp(omega + e)[0] @ v - rotation_exp(omega - e)[0] @ v) / (2 * h)
        Rv = R @ v
        np.testing.assert_allclose(fd, -np.cross(Rv, J[:, :, k]), atol=1e-8)


def test_residual_norm_is_the_angle_even_behind_the_camera():
    rng = np.random.default_rng(2)
    s = _scene(rng, num_cameras=3, num_points=40)
    bearings = s["bearings"].copy()
    flip = np.arange(len(bearings)) % 3 == 0
    bearings[flip] = normalize(-bearings[flip] + rng.normal(scale=0.3, size=(flip.sum(), 3)))
    bearings[1] = -s["bearings"][1]  # exactly behind
    prob = _problem(s["R"], s["t"], s["points"], s["cam"], s["pt"], bearings)
    r, _ = _residuals(_pack(prob.layout, prob.C_init, s["points"]), prob, False)
    pred = np.einsum("kij,kj->ki", s["R"][s["cam"]], s["points"][s["pt"]]) + s["t"][s["cam"]]
    angle = np.arccos(np.clip(np.einsum("ki,ki->k", normalize(pred), bearings), -1, 1))
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), angle, atol=1e-7)
    assert np.linalg.norm(r[1]) == pytest.approx(np.pi)
    assert (np.linalg.norm(r[flip], axis=1) > np.pi / 2).all()


def test_analytic_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    s = _scene(rng, num_cameras=5, num_points=30)
    R, t, points = _perturb(rng, s)
    bearings = s["bearings"].copy()
    bearings[::7] = normalize(rng.normal(size=bearings[::7].shape))  # outliers, some behind the camera
    prob = _problem(R, t, points, s["cam"], s["pt"], bearings)
    assert prob.layout.scale_camera > 0
    x = _pack(prob.layout, prob.C_init, points) + rng.normal(scale=0.05, size=prob.layout.num_params)
    mask, indices, indptr = _jacobian_structure(prob)
    J = csr_matrix((_residuals(x, prob, True)[1][mask], indices, indptr), shape=(2 * len(bearings), len(x)))
    J = J.toarray()
    h = 1e-6
    fd = np.empty_like(J)
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        fd[:, i] = (_residuals(x + e, prob, False)[0] - _residuals(x - e, prob, False)[0]).ravel() / (2 * h)
    np.testing.assert_allclose(J, fd, atol=1e-6 * max(1.0, np.abs(J).max()))
    assert (np.abs(J) > 0).sum() > 0.9 * len(indices)  # the sparsity pattern is not mostly empty


def test_recovers_poses_without_noise_and_keeps_gauge():
    rng = np.random.default_rng(4)
    s = _scene(rng)
    R, t, points = _perturb(rng, s)
    res = _run(R, t, points, s, loss="soft_l1")
    assert res.success and res.final_cost < 1e-12 < res.initial_cost
    assert _rotation_errors_deg(res.R_cam_from_world, s["R"]).max() < 0.01
    # Gauge: camera 0 untouched, distance camera 0 -> scale camera as in the initial values.
    assert np.array_equal(res.R_cam_from_world[0], R[0]) and np.array_equal(res.t_cam_from_world[0], t[0])
    C_init = -np.einsum("nji,nj->ni", R, t)
    C = -np.einsum("nji,nj->ni", res.R_cam_from_world, res.t_cam_from_world)
    k = res.scale_camera
    assert k > 0
    scale = np.linalg.norm(C_init[k] - C_init[0]) / np.linalg.norm(s["centers"][k] - s["centers"][0])
    assert np.linalg.norm(C[k] - C[0]) == pytest.approx(np.linalg.norm(C_init[k] - C_init[0]), rel=1e-12)
    # Everything else is the truth in that gauge: scaled about camera 0.
    np.testing.assert_allclose(C, C[0] + scale * (s["centers"] - s["centers"][0]), atol=1e-6)
    np.testing.assert_allclose(res.points, C[0] + scale * (s["points"] - s["centers"][0]), atol=1e-5)
    assert res.obs_error_rad.max() < 1e-7


@pytest.mark.parametrize("path", ["dense products", "observation pairs", "sparse LU"])
def test_schur_step_solves_the_damped_normal_equations(path, monkeypatch):
    """Every way of assembling and solving the reduced camera system gives the step of the full damped system."""
    rng = np.random.default_rng(11)
    s = _scene(rng, num_cameras=6, num_points=60)
    R, t, points = _perturb(rng, s)
    prob = _problem(R, t, points, s["cam"], s["pt"], s["bearings"])
    objective = _WeightedResiduals(prob)
    objective.sqrt_w = rng.uniform(0.5, 1.0, len(s["cam"]))
    if path == "sparse LU":
        monkeypatch.setattr(bundle_module, "_DENSE_CAMERA_UNKNOWNS", 0)
    system = _SchurSystem(prob)
    system.dense_products = path == "dense products"
    x = _pack(prob.layout, -np.einsum("nji,nj->ni", R, t), points)
    damping = 1e-3
    step, predicted = system.solve(objective.fun(x).reshape(-1, 2), objective.jac_blocks(x), damping)
    J, r = objective.jac(x).toarray(), objective.fun(x)
    JtJ = J.T @ J
    expected = np.linalg.solve(JtJ + damping * np.diag(np.maximum(np.diag(JtJ), 1e-12)), -J.T @ r)
    np.testing.assert_allclose(step, expected, rtol=1e-7, atol=1e-10 * np.abs(expected).max())
    assert predicted == pytest.approx(0.5 * (r @ r) - 0.5 * np.sum((r + J @ expected) ** 2), rel=1e-8)


def test_two_fixed_cameras_fix_the_scale():
    rng = np.random.default_rng(5)
    s = _scene(rng)
    R, t, points = _perturb(rng, s, fixed=(0, 3))
    res = _run(R, t, points, s, fixed_cameras=(3, 0), loss="linear")
    assert res.scale_camera == -1
    for k in (0, 3):
        assert np.array_equal(res.R_cam_from_world[k], R[k]) and np.array_equal(res.t_cam_from_world[k], t[k])
    C = -np.einsum("nji,nj->ni", res.R_cam_from_world, res.t_cam_from_world)
    np.testing.assert_allclose(C, s["centers"], atol=1e-6)
    assert _rotation_errors_deg(res.R_cam_from_world, s["R"]).max() < 0.01


def test_noise_reduces_cost_and_poses_are_accurate():
    rng = np.random.default_rng(6)
    s = _scene(rng)
    bearings = normalize(s["bearings"] + rng.normal(scale=NOISE_RAD, size=s["bearings"].shape))
    R, t, points = _perturb(rng, s, fixed=(0, 1))
    res = _run(R, t, points, s, bearings=bearings, fixed_cameras=(0, 1))
    assert res.final_cost < 0.05 * res.initial_cost
    assert _rotation_errors_deg(res.R_cam_from_world, s["R"]).max() < 0.05
    assert np.median(res.obs_error_rad) < 2 * NOISE_RAD


def test_soft_l1_is_robust_to_outliers():
    rng = np.random.default_rng(7)
    s = _scene(rng, num_points=400)
    bearings = normalize(s["bearings"] + rng.normal(scale=NOISE_RAD, size=s["bearings"].shape))
    outlier = rng.random(len(bearings)) < 0.04
    bearings[outlier] = normalize(rng.normal(size=(outlier.sum(), 3)))
    R, t, points = _perturb(rng, s, fixed=(0, 1))
    robust = _run(R, t, points, s, bearings=bearings, fixed_cameras=(0, 1), loss="soft_l1", loss_scale_rad=0.005)
    plain = _run(R, t, points, s, bearings=bearings, fixed_cameras=(0, 1), loss="linear")
    err_robust = _rotation_errors_deg(robust.R_cam_from_world, s["R"]).max()
    err_plain = _rotation_errors_deg(plain.R_cam_from_world, s["R"]).max()
    assert err_robust < 0.06 and err_plain > 3 * err_robust  # (0.035° vs 3.2° with seed 7)
    # The outliers stand out in the final errors; the inliers fit to the noise level.
    assert np.median(robust.obs_error_rad[outlier]) > 0.1
    assert np.quantile(robust.obs_error_rad[~outlier], 0.95) < 4 * NOISE_RAD


def test_max_nfev_is_respected():
    rng = np.random.default_rng(8)
    s = _scene(rng)
    R, t, points = _perturb(rng, s)
    res = _run(R, t, points, s, max_nfev=4)
    assert res.num_evaluations <= 4 + 1 and not res.success
    assert res.final_cost < res.initial_cost


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(fixed_cameras=()), "fixed_cameras"),
        (dict(fixed_cameras=(9,)), "fixed_cameras"),
        (dict(loss="l2"), "loss"),
        (dict(loss_scale_rad=0.0), "loss_scale_rad"),
        (dict(scale_camera=0), "scale_camera"),
        (dict(obs_point=np.full(10, 99)), "obs_point"),
        (dict(points=np.full((5, 3), np.nan)), "points"),
    ],
)
def test_bad_input_names_the_value(change, message):
    rng = np.random.default_rng(9)
    s = _scene(rng, num_cameras=3, num_points=5, visibility=1.0)
    args = dict(R_cam_from_world=s["R"], t_cam_from_world=s["t"], points=s["points"], obs_camera=s["cam"],
                obs_point=s["pt"], obs_bearings=s["bearings"]) | change
    if "obs_point" in change:
        args["obs_camera"], args["obs_bearings"] = s["cam"][:10], s["bearings"][:10]
    with pytest.raises(ValueError, match=message):
        bundle_adjust(**args)


def timing_check(num_cameras=24, num_points=5000, visibility=0.25, outlier_fraction=0.02, seed=0) -> None:
    """Print the run time of a BA with noisy bearings, outliers and perturbed poses (not a test)."""
    rng = np.random.default_rng(seed)
    s = _scene(rng, num_cameras=num_cameras, num_points=num_points, visibility=visibility)
    bearings = normalize(s["bearings"] + rng.normal(scale=NOISE_RAD, size=s["bearings"].shape))
    outlier = rng.random(len(bearings)) < outlier_fraction
    bearings[outlier] = normalize(rng.normal(size=(outlier.sum(), 3)))
    R, t, points = _perturb(rng, s)
    start = time.perf_counter()
    res = _run(R, t, points, s, bearings=bearings)
    elapsed = time.perf_counter() - start
    print(
        f"{num_cameras} cameras, {len(points)} points, {len(bearings)} observations "
        f"({outlier_fraction:.0%} outliers): {elapsed:.2f} s, {res.num_evaluations} evaluations, "
        f"cost {res.initial_cost:.4g} -> {res.final_cost:.4g}, "
        f"max rotation error {_rotation_errors_deg(res.R_cam_from_world, s['R']).max():.4f} deg ({res.message})"
    )


if __name__ == "__main__":
    for vis in (0.25, 0.5, 1.0):
        timing_check(visibility=vis)
