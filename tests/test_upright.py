import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm import two_view as tv
from fullview.sfm import upright as up
from fullview.sfm.camera import normalize, pixel_grid_bearings, skew
from fullview.sfm.registration.poses import yaw_rotation

Y = np.array([0.0, 1.0, 0.0])


def _sign_free_distance(F, G):
    """Distance between F and G as projective matrices (scale and sign removed); F may be batched."""
    F = F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)
    G = G / np.linalg.norm(G, axis=(-2, -1), keepdims=True)
    return np.minimum(np.linalg.norm(F - G, axis=(-2, -1)), np.linalg.norm(F + G, axis=(-2, -1)))


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(normalize(a) @ normalize(b), -1.0, 1.0)))


def _yaw_diff_deg(a, b):
    return np.degrees(abs(np.angle(np.exp(1j * (a - b)))))


def _minimal_configs(seed, count):
    """`count` random upright 3-point configurations: bearings anywhere on the sphere, any yaw, any baseline."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi, count)
    R = yaw_rotation(theta)
    C = rng.normal(size=(count, 3))  # camera j's centre in camera i's frame (T)
    P = rng.normal(size=(count, 3, 3)) * 4
    b_i = normalize(P)
    b_j = normalize((P - C[:, None]) @ np.swapaxes(R, 1, 2))
    return b_i, b_j, skew(C) @ np.swapaxes(R, 1, 2)


def _upright_scene(seed, n=400, noise_deg=0.03, outliers=0.5):
    """Levelled pair: yaw θ, unit baseline C (camera j's centre in frame i), noisy bearings, random outliers."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(-np.pi, np.pi)
    R = yaw_rotation(theta)
    C = normalize(rng.normal(size=3))
    P = rng.normal(size=(n, 3)) * 4
    noise = np.radians(noise_deg)
    b_i = normalize(normalize(P) + rng.normal(size=(n, 3)) * noise)
    b_j = normalize(normalize((P - C) @ R.T) + rng.normal(size=(n, 3)) * noise)
    bad = rng.random(n) < outliers
    b_j[bad] = normalize(rng.normal(size=(bad.sum(), 3)))
    return b_i, b_j, theta, C, ~bad


# --------------------------------------------------------------------------------------------- minimal solver
def test_minimal_solver_exact_on_random_configurations():
    b_i, b_j, F_true = _minimal_configs(seed=0, count=2000)
    F, valid = up.upright_f_minimal_batch(b_i, b_j)
    distances = _sign_free_distance(np.where(valid[..., None, None], F, 1.0), F_true[:, None])
    errors = np.where(valid, distances, np.inf).min(axis=1)  # the solution closest to each configuration's truth
    assert errors.max() < 1e-9
    assert set(valid.sum(1)) <= {2, 4}  # a degree-2 trigonometric polynomial has 0, 2 or 4 roots on the circle


@pytest.mark.parametrize("seed", range(20))
def test_minimal_solver_single_sample_api(seed):
    b_i, b_j, F_true = _minimal_configs(seed=100 + seed, count=1)
    F = up.upright_f_minimal(b_i[0], b_j[0])
    assert F.shape[1:] == (3, 3) and 1 <= len(F) <= 4
    assert _sign_free_distance(F, F_true[0]).min() < 1e-9


def test_every_solution_satisfies_its_constraints_and_is_upright():
    b_i, b_j, _ = _minimal_configs(seed=1, count=500)
    F, valid = up.upright_f_minimal_batch(b_i, b_j)
    residuals = np.einsum("zka,zsab,zkb->zsk", b_i, F, b_j)[valid]
    assert np.abs(residuals).max() < 1e-10
    for Fk in F[valid][:300]:
        theta, T, residual = up.upright_decompose(Fk)
        assert residual < 1e-12
        assert _sign_free_distance(Fk, up.upright_f(theta, T)) < 1e-12
        assert np.allclose(np.linalg.svd(Fk, compute_uv=False), [1, 1, 0], atol=1e-12)  # essential, unit scale


def test_degenerate_sample_has_no_solution():
    """Three points on camera i's vertical axis: every yaw explains them (det ≡ 0), nothing is returned."""
    b_j = normalize(np.random.default_rng(2).normal(size=(3, 3)))
    assert len(up.upright_f_minimal(np.array([Y, -Y, Y]), b_j)) == 0


def test_decompose_and_linear_fit_are_exact_on_clean_data():
    b_i, b_j, theta, C, _ = _upright_scene(seed=3, n=30, noise_deg=0.0, outliers=0.0)
    F_true = up.upright_f(theta, C)
    th, T, residual = up.upright_decompose(-3.0 * F_true)  # scale and sign do not matter
    assert residual < 1e-14 and _yaw_diff_deg(th, theta) < 1e-10 and abs(abs(T @ C) - 1) < 1e-12
    assert _sign_free_distance(up.estimate_f_upright_linear(b_i, b_j), F_true) < 1e-10


# --------------------------------------------------------------------------------------------- robust estimation
@pytest.mark.parametrize("seed", range(3))
def test_ransac_upright_recovers_pose_with_half_outliers(seed):
    b_i, b_j, theta, C, good = _upright_scene(seed)
    options = tv.RansacOptions(threshold_rad=np.radians(0.2), batch_size=32, min_iterations=32, seed=seed)
    result = up.ransac_f_upright(b_i, b_j, options)
    th, T, residual = up.upright_decompose(result.F)
    assert residual < 1e-12  # upright to machine precision
    assert _yaw_diff_deg(th, theta) < 0.1
    pose = tv.relative_pose_from_f(result.F, b_i[result.inliers], b_j[result.inliers])  # cheirality fixes T's sign
    assert _angle_deg(pose.e_i, C) < 0.5
    assert np.degrees(Rotation.from_matrix(pose.R_j_from_i @ yaw_rotation(theta).T).magnitude()) < 0.1
    assert (result.inliers == good).mean() > 0.98

    general = tv.ransac_f(b_i, b_j, options)
    print(f"seed {seed}: upright {result.iterations} samples, 8-point {general.iterations} samples")
    assert result.iterations * 5 < general.iterations  # (w=0.5: 3-point needs ~70 for 0.9999, 8-point ~2400)


def test_ransac_upright_rejects_unknown_tilt():
    """The upright model is a real constraint: a 4° tilt left unlevelled costs most inliers at a tight threshold."""
    b_i, b_j, _, _, _ = _upright_scene(seed=4, noise_deg=0.0, outliers=0.0)
    options = tv.RansacOptions(threshold_rad=np.radians(0.2), batch_size=32, min_iterations=32)
    tilted_j = b_j @ Rotation.from_euler("x", 4, degrees=True).as_matrix().T
    assert up.ransac_f_upright(b_i, b_j, options).inliers.mean() == 1.0
    assert up.ransac_f_upright(b_i, tilted_j, options).inliers.mean() < 0.8


def test_ransac_upright_on_fewer_than_eight_points():
    b_i, b_j, theta, _, _ = _upright_scene(seed=6, n=5, noise_deg=0.0, outliers=0.0)
    result = up.ransac_f_upright(b_i, b_j, tv.RansacOptions(threshold_rad=np.radians(0.1), batch_size=16))
    assert result.inliers.all() and _yaw_diff_deg(up.upright_decompose(result.F)[0], theta) < 1e-6


# --------------------------------------------------------------------------------------------- levelling
def test_leveling_rotation_maps_gravity_to_down_axis():
    rng = np.random.default_rng(5)
    for g in normalize(rng.normal(size=(20, 3))):
        L = up.leveling_rotation(2.5 * g)
        assert np.allclose(L @ g, Y, atol=1e-12) and np.allclose(L @ L.T, np.eye(3)) and np.isclose(np.linalg.det(L), 1)
        assert np.allclose(up.level_bearings(g[None], g), Y[None], atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_level_solve_unlevel_reproduces_relative_pose(seed):
    rng = np.random.default_rng(seed)
    # World y is down (gravity). Each camera: a yaw, then a tilt of a few degrees.
    R_i, R_j = (Rotation.from_euler("yxz", [rng.uniform(-180, 180), *rng.uniform(-5, 5, 2)], degrees=True).as_matrix()
                for _ in range(2))
    C_i, C_j = rng.normal(size=(2, 3))
    P = rng.normal(size=(300, 3)) * 5
    noise = np.radians(0.02)
    b_i = normalize(normalize((P - C_i) @ R_i.T) + rng.normal(size=(300, 3)) * noise)
    b_j = normalize(normalize((P - C_j) @ R_j.T) + rng.normal(size=(300, 3)) * noise)
    g_i, g_j = R_i @ Y, R_j @ Y  # gravity seen by each camera
    L_i, L_j = up.leveling_rotation(g_i), up.leveling_rotation(g_j)

    options = tv.RansacOptions(threshold_rad=np.radians(0.15), batch_size=32, min_iterations=32, seed=seed)
    result = up.ransac_f_upright(up.level_bearings(b_i, g_i), up.level_bearings(b_j, g_j), options)
    assert result.inliers.mean() > 0.98
    R_true = R_j @ R_i.T
    R_from_yaw = up.unlevel_rotation(yaw_rotation(up.upright_decompose(result.F)[0]), L_i, L_j)
    assert np.degrees(Rotation.from_matrix(R_from_yaw @ R_true.T).magnitude()) < 0.05

    F = up.unlevel_f(result.F, L_i, L_j)
    assert np.median(tv.epipolar_angular_errors(F, b_i, b_j)) < np.radians(0.05)  # F fits the original bearings
    pose = tv.relative_pose_from_f(F, b_i, b_j)
    assert np.degrees(Rotation.from_matrix(pose.R_j_from_i @ R_true.T).magnitude()) < 0.05
    assert _angle_deg(pose.e_i, R_i @ (C_j - C_i)) < 0.5


# --------------------------------------------------------------------------------------------- gravity
def _render_room(R_cam_from_world, width=768, supersample=2):
    """Equirectangular view from inside a box room (world y down): vertical stripes of varying width on the walls
    (vertical world lines), a checkerboard on floor and ceiling (horizontal lines, the distractors)."""
    W, H = width * supersample, width * supersample // 2
    d = pixel_grid_bearings(W, H).reshape(-1, 3) @ R_cam_from_world  # world directions Rᵀ b, as rows
    lo, hi = np.array([-2.0, -1.2, -2.5]), np.array([3.0, 1.5, 4.0])
    with np.errstate(divide="ignore"):
        t_hit = np.where(d > 0, hi / d, lo / d)
    axis = np.argmin(t_hit, axis=1)  # the wall, floor or ceiling the ray meets first
    p = d * t_hit[np.arange(len(d)), axis][:, None]
    along = np.where(axis == 0, p[:, 2], p[:, 0])  # horizontal coordinate on the wall
    stripes = np.mod(along / 0.37 + 0.3 * np.sin(3 * along), 1.0) < 0.5
    checker = (np.floor(p[:, 0] / 0.6) + np.floor(p[:, 2] / 0.6)) % 2 == 0
    value = np.where(axis == 1, np.where(checker, 90, 160), np.where(stripes, 60, 200)).astype(np.float32)
    image = cv2.resize(value.reshape(H, W), (width, width // 2), interpolation=cv2.INTER_AREA)  # anti-aliasing
    return np.repeat(image.round().astype(np.uint8)[..., None], 3, axis=2)


@pytest.mark.parametrize("euler_deg", [(3.0, -2.0, 40.0), (-6.0, 4.0, 200.0)])
def test_estimate_gravity_recovers_tilt(euler_deg):
    R = Rotation.from_euler("xzy", euler_deg, degrees=True).as_matrix()
    found = up.estimate_gravity(_render_room(R))
    assert found is not None
    gravity, num_lines = found
    assert _angle_deg(gravity, R @ Y) < 1.0 and gravity[1] > 0
    assert num_lines >= 30


def test_estimate_gravity_hough_fallback(monkeypatch):
    """OpenCV builds without LSD: Canny + probabilistic Hough segments, coarser but still within a degree."""
    def unavailable(*args, **kwargs):
        raise AttributeError("no LSD in this build")
    monkeypatch.setattr(cv2, "createLineSegmentDetector", unavailable)
    R = Rotation.from_euler("xzy", (3.0, -2.0, 40.0), degrees=True).as_matrix()
    gravity, _ = up.estimate_gravity(_render_room(R))
    assert _angle_deg(gravity, R @ Y) < 1.0


def test_estimate_gravity_none_without_lines():
    assert up.estimate_gravity(np.full((384, 768, 3), 128, np.uint8)) is None
    assert up.estimate_gravity(np.full((384, 768), 50, np.uint8)) is None



# A weak pair like the bare homes' (50 matches, half of them wrong, noise almost half the threshold): models near the
# truth differ by which borderline matches they count as inliers.
def _weak_upright_pair(seed):
    return _upright_scene(seed, n=50, noise_deg=0.15, outliers=0.5)


@pytest.mark.parametrize("scene", range(6))
def test_ransac_upright_result_does_not_depend_on_the_seed(scene):
    """The search converges: different RANSAC seeds end at the same inliers and the same F to the refinement's
    tolerance. One soft-l1 refinement on the inliers of the sampled model left both seed-dependent (on these six
    scenes, four gave different inliers for some seed)."""
    b_i, b_j, theta, C, good = _weak_upright_pair(scene)
    fits = [up.ransac_f_upright(b_i, b_j, tv.RansacOptions(threshold_rad=np.radians(0.35), seed=s))
            for s in range(6)]
    for fit in fits[1:]:
        assert np.array_equal(fit.inliers, fits[0].inliers)
        assert _sign_free_distance(fit.F, fits[0].F) < 1e-5
    assert _yaw_diff_deg(up.upright_decompose(fits[0].F)[0], theta) < 0.5


def test_final_refinement_is_a_fixed_point():
    """Polishing the returned model again changes neither F nor its inliers."""
    b_i, b_j, *_ = _weak_upright_pair(7)
    thr = np.radians(0.35)
    fit = up.ransac_f_upright(b_i, b_j, tv.RansacOptions(threshold_rad=thr, seed=0))
    again = tv._finish(b_i, b_j, fit.F, thr, True, 0, refine_fn=up.refine_f_upright, min_points=6, polish=True)
    assert _sign_free_distance(again.F, fit.F) < 1e-6
    assert np.array_equal(again.inliers, fit.inliers)


@pytest.mark.parametrize("noise_deg, scene", [(0.4, 18), (0.5, 6), (0.5, 14), (0.5, 24)])
def test_vertical_direction_does_not_depend_on_the_seed(noise_deg, scene):
    """Gravity from noisy vertical circles and clutter: the re-fits run until the inliers settle, so the direction is
    the same whichever sampled pair of circles won (scenes where three fixed re-fits had not settled), and with at
    most `num_pairs` pairs of circles every pair is tried."""
    rng = np.random.default_rng(scene)
    v = normalize(np.array([0.05, 1.0, -0.03]))
    vertical = normalize(np.cross(v, rng.normal(size=(80, 3))) + rng.normal(size=(80, 3)) * np.radians(noise_deg))
    normals = np.concatenate([vertical, normalize(rng.normal(size=(60, 3)))])
    weights = rng.uniform(0.5, 2.0, len(normals))
    found = [up.vertical_direction_from_normals(normals, weights, seed=s) for s in range(8)]
    for direction, inliers in found[1:]:
        assert np.array_equal(inliers, found[0][1])
        assert np.allclose(direction, found[0][0], rtol=0.0, atol=1e-12)
    assert _angle_deg(found[0][0], v) < 0.5
