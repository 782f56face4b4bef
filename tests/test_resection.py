import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm import resection as rs
from fullview.sfm.camera import camera_center, normalize, tangent_basis
from fullview.sfm.triangulation import angular_errors

THRESHOLD = np.radians(0.25)


def _camera(rng):
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    C = rng.normal(size=3) * 3
    return R, -R @ C


def _points_around(rng, R, t, n, directions=None):
    """World points at distances 1..10 along camera-frame directions (default: uniform on the whole sphere)."""
    d = normalize(rng.normal(size=(n, 3))) if directions is None else directions
    return (d * rng.uniform(1.0, 10.0, (n, 1)) - t) @ R  # X = Rᵀ (x_cam − t)


def _pose_error(R_est, t_est, R, t):
    """Largest deviation of R plus the translation deviation relative to |t| (scale-free)."""
    return np.abs(R_est - R).max() + np.abs(t_est - t).max() / max(1.0, np.linalg.norm(t))


def _scene(seed, n=400, outliers=0.6, noise_deg=0.05):
    """Bearings with Gaussian angular noise; a share of them replaced by random directions (outliers)."""
    rng = np.random.default_rng(seed)
    R, t = _camera(rng)
    X = _points_around(rng, R, t, n)
    b = normalize(X @ R.T + t)
    noise = rng.normal(size=(n, 2)) * np.radians(noise_deg)
    b = normalize(b + np.einsum("nk,nkc->nc", noise, tangent_basis(b)))
    bad = np.zeros(n, dtype=bool)
    bad[rng.permutation(n)[: int(round(outliers * n))]] = True
    b[bad] = normalize(rng.normal(size=(bad.sum(), 3)))
    return b, X, R, t, ~bad


def _rotation_deg(A, B):
    return np.degrees(Rotation.from_matrix(A @ B.T).magnitude())


# --------------------------------------------------------------------------------------------- P3P
def test_p3p_exact_on_the_whole_sphere():
    behind = 0
    for seed in range(300):
        rng = np.random.default_rng(seed)
        R, t = _camera(rng)
        X = _points_around(rng, R, t, 3)
        f = normalize(X @ R.T + t)
        behind += int((f[:, 2] < 0).any())
        solutions = rs.p3p_bearings(f, X)
        assert 1 <= len(solutions) <= 4, seed
        assert min(_pose_error(Rs, ts, R, t) for Rs, ts in solutions) < 1e-9, seed
    assert behind > 200  # most samples have a point behind the camera (z < 0)


def test_p3p_exact_with_every_point_behind_the_camera():
    for seed in range(50):
        rng = np.random.default_rng(seed)
        R, t = _camera(rng)
        d = normalize(rng.normal(size=(3, 3)) * [1.0, 1.0, 0.3] - [0.0, 0.0, 1.0])
        assert (d[:, 2] < 0).all()
        X = _points_around(rng, R, t, 3, directions=d)
        solutions = rs.p3p_bearings(normalize(X @ R.T + t), X)
        assert min(_pose_error(Rs, ts, R, t) for Rs, ts in solutions) < 1e-9, seed


def test_p3p_scale_and_offset_invariance():
    rng = np.random.default_rng(3)
    R, t = _camera(rng)
    X = _points_around(rng, R, t, 3)
    f = normalize(X @ R.T + t)
    for scale, offset in ((1e-4, 0.0), (1e5, 0.0), (1.0, 1e4)):
        Xs = scale * X + offset  # the same camera moves with the world: t' = s t − R o
        ts = scale * t - R @ np.full(3, offset)
        assert min(_pose_error(Rp, tp, R, ts) for Rp, tp in rs.p3p_bearings(f, Xs)) < 1e-9


def test_every_p3p_solution_reproduces_its_correspondences():
    counts = []
    for seed in range(300):
        rng = np.random.default_rng(seed)
        R, t = _camera(rng)
        X = _points_around(rng, R, t, 3)
        f = normalize(X @ R.T + t)
        solutions = rs.p3p_bearings(f, X)
        counts.append(len(solutions))
        for Rs, ts in solutions:
            assert np.abs(Rs @ Rs.T - np.eye(3)).max() < 1e-12 and np.linalg.det(Rs) > 0
            cam = X @ Rs.T + ts
            assert (np.einsum("nc,nc->n", cam, f) > 0).all()  # positive distance along every bearing
            assert angular_errors(f, cam).max() < 1e-9
        centres = [camera_center(Rs, ts) for Rs, ts in solutions]
        assert all(np.linalg.norm(a - b) > 1e-9 for k, a in enumerate(centres) for b in centres[:k])  # no repeats
    assert max(counts) == 4 and sum(c > 1 for c in counts) > 30  # the multi-solution cases are covered


def _all_positive_distances(f, X, starts=200):
    """Every positive solution of Grunert's system, by multi-start Newton: an independent check of completeness."""
    i, j = np.array(rs.PAIRS).T
    a, c = ((X[i] - X[j]) ** 2).sum(-1), (f[i] * f[j]).sum(-1)
    lam = np.random.default_rng(0).uniform(0, 6 * np.sqrt(a.max()), (starts, 3))
    for _ in range(40):
        r = lam[:, i] ** 2 + lam[:, j] ** 2 - 2 * c * lam[:, i] * lam[:, j] - a
        J = np.zeros((starts, 3, 3))
        J[:, np.arange(3), i] = 2 * (lam[:, i] - c * lam[:, j])
        J[:, np.arange(3), j] = 2 * (lam[:, j] - c * lam[:, i])
        ok = np.abs(np.linalg.det(J)) > 1e-12
        lam[ok] -= np.linalg.solve(J[ok], r[ok][..., None])[..., 0]
    r = lam[:, i] ** 2 + lam[:, j] ** 2 - 2 * c * lam[:, i] * lam[:, j] - a
    return lam[(np.abs(r).max(-1) < 1e-10 * a.max()) & (lam > 0).all(-1)]


def test_p3p_finds_every_solution():
    for seed in range(40):
        rng = np.random.default_rng(seed)
        R, t = _camera(rng)
        X = _points_around(rng, R, t, 3)
        f = normalize(X @ R.T + t)
        found = np.array([np.linalg.norm(X @ Rs.T + ts, axis=1) for Rs, ts in rs.p3p_bearings(f, X)])
        for lam in _all_positive_distances(f, X):
            assert np.abs(found - lam).max(-1).min() < 1e-6 * lam.max(), seed


def test_p3p_batch_matches_single_calls():
    rng = np.random.default_rng(7)
    f, X = [], []
    for _ in range(20):
        R, t = _camera(rng)
        Xk = _points_around(rng, R, t, 3)
        f.append(normalize(Xk @ R.T + t))
        X.append(Xk)
    f[5] = f[5][[0, 0, 1]]  # a degenerate sample in the batch does not disturb the others
    R_b, t_b, valid = rs.p3p_bearings_batch(np.array(f), np.array(X))
    for k in range(20):
        single = rs.p3p_bearings(f[k], X[k])
        assert len(single) == valid[k].sum()
        for (Rs, ts), m in zip(single, np.flatnonzero(valid[k])):
            assert np.array_equal(Rs, R_b[k, m]) and np.array_equal(ts, t_b[k, m])
    assert not valid[5].any()


_rng = np.random.default_rng(0)
_F = normalize(_rng.normal(size=(3, 3)))
_X = _rng.normal(size=(3, 3))


@pytest.mark.parametrize("f, X", [
    (_F, np.array([[0.0, 0, 0], [1, 2, 3], [2, 4, 6]])),  # collinear points
    (_F, np.array([[0.0, 0, 0], [1, 2, 3], [-3, -6, -9]])),  # collinear, the middle one not between
    (_F, np.array([[1.0, 2, 3], [1, 2, 3], [0, 1, 0]])),  # two coincident points
    (_F, np.ones((3, 3))),  # all three coincident
    (_F[[0, 0, 1]], _X),  # two identical bearings
    (np.array([_F[0], -_F[0], _F[1]]), _X),  # opposite bearings
    (np.zeros((3, 3)), _X),  # zero bearings
    (np.array([_F[0], _F[1], [np.nan, 0, 1]]), _X),  # non-finite values
    (_F, np.array([[0.0, 0, 0], [1, np.inf, 0], [0, 0, 1]])),
])
def test_p3p_degenerate_input_returns_no_solution(f, X):
    with np.errstate(all="raise"):  # no silent floating-point trouble either
        assert rs.p3p_bearings(f, X) == []


# --------------------------------------------------------------------------------------------- robust resection
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_resect_recovers_pose_and_outliers(seed):
    b, X, R, t, good = _scene(seed)
    result = rs.resect(b, X, rs.ResectionOptions(threshold_rad=THRESHOLD))
    assert result is not None
    assert _rotation_deg(result.R_cam_from_world, R) < 0.1
    centre_error = np.linalg.norm(camera_center(result.R_cam_from_world, result.t_cam_from_world) - camera_center(R, t))
    assert centre_error < 0.005 * np.median(np.linalg.norm(X @ R.T + t, axis=1))
    true_positives = (result.inliers & good).sum()
    assert true_positives / result.inliers.sum() > 0.99  # precision
    assert true_positives / good.sum() > 0.98  # recall
    assert result.num_inliers == result.inliers.sum()
    assert np.allclose(result.errors, angular_errors(b, X @ result.R_cam_from_world.T + result.t_cam_from_world))
    assert (result.errors[result.inliers] < THRESHOLD).all()
    assert result.iterations <= 1000


def test_resect_counts_points_behind_their_bearing_as_outliers():
    b, X, R, t, _ = _scene(4, n=200, outliers=0.0, noise_deg=0.0)
    C = camera_center(R, t)
    X_behind = X.copy()
    X_behind[:20] = 2 * C - X[:20]  # mirrored through the centre: on the bearing's line, but behind
    result = rs.resect(b, X_behind, rs.ResectionOptions(threshold_rad=THRESHOLD))
    assert _rotation_deg(result.R_cam_from_world, R) < 1e-6
    assert not result.inliers[:20].any() and result.inliers[20:].all()


def test_resect_is_deterministic_for_a_seed():
    b, X, *_ = _scene(5)
    runs = [rs.resect(b, X, rs.ResectionOptions(threshold_rad=THRESHOLD, seed=s)) for s in (3, 3, 4)]
    assert np.array_equal(runs[0].R_cam_from_world, runs[1].R_cam_from_world)
    assert np.array_equal(runs[0].t_cam_from_world, runs[1].t_cam_from_world)
    assert np.array_equal(runs[0].inliers, runs[1].inliers) and runs[0].iterations == runs[1].iterations
    assert _rotation_deg(runs[0].R_cam_from_world, runs[2].R_cam_from_world) < 0.02  # another seed, same answer


def test_resect_without_refinement_still_finds_the_inliers():
    b, X, R, t, good = _scene(6)
    result = rs.resect(b, X, rs.ResectionOptions(threshold_rad=THRESHOLD, refine=False))
    assert _rotation_deg(result.R_cam_from_world, R) < 0.1
    assert (result.inliers == good).mean() > 0.99


def test_resect_returns_none_with_too_few_inliers():
    b, X, *_ = _scene(7, n=30, outliers=20 / 30)  # only 10 correct correspondences
    assert rs.resect(b, X, rs.ResectionOptions(threshold_rad=THRESHOLD, min_inliers=12)) is None
    found = rs.resect(b, X, rs.ResectionOptions(threshold_rad=THRESHOLD, min_inliers=8))
    assert found is not None and found.num_inliers >= 10
    assert rs.resect(b[:2], X[:2], rs.ResectionOptions(threshold_rad=THRESHOLD, min_inliers=0)) is None
    assert rs.resect(b[:0], X[:0], rs.ResectionOptions(threshold_rad=THRESHOLD)) is None


# --------------------------------------------------------------------------------------------- refinement
def test_refine_pose_reaches_the_noise_level_from_a_perturbed_start():
    b, X, R, t, _ = _scene(8, n=300, outliers=0.0, noise_deg=0.05)
    rng = np.random.default_rng(8)
    R0 = Rotation.from_rotvec(np.radians(3.0) * normalize(rng.normal(size=3))).as_matrix() @ R
    C0 = camera_center(R, t) + 0.3 * normalize(rng.normal(size=3))
    R1, t1 = rs.refine_pose(R0, -R0 @ C0, b, X, THRESHOLD)

    def rms(R_, t_):
        return np.sqrt(np.mean(angular_errors(b, X @ R_.T + t_) ** 2))

    assert rms(R0, -R0 @ C0) > 20 * rms(R, t)  # the start is far off
    assert rms(R1, t1) <= rms(R, t) * 1.001  # the fit is at least as good as the truth: the noise level
    assert _rotation_deg(R1, R) < 0.02
    assert np.linalg.norm(camera_center(R1, t1) - camera_center(R, t)) < 0.01


def test_cross_is_numpys_bit_for_bit():
    """resection's own cross product (no axis handling, for speed) gives np.cross's result exactly, broadcasting
    alike, so RANSAC's samples, costs and poses are unchanged by it."""
    from fullview.sfm.resection import _cross
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(7, 5, 3)), rng.normal(size=(5, 3)) * 1e3
    assert np.array_equal(_cross(a, b), np.cross(a, b))
    assert np.array_equal(_cross(b, a), np.cross(b, a))
