import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm.attach import attach_cameras
from fullview.sfm.camera import normalize
from fullview.sfm.registration import relative_from_absolute
from fullview.sfm.tracks import build_tracks


def _chain(seed=0, n_points=400, noise=0.0005):
    """Three cameras in a row, points around them; pairs (0,1) and (1,2) only, like sequential matching."""
    rng = np.random.default_rng(seed)
    centers = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.2], [2.1, -0.1, 0.5]])
    R = Rotation.from_euler("xyz", rng.uniform(-0.3, 0.3, (3, 3))).as_matrix()
    t = -np.einsum("nab,nb->na", R, centers)
    X = rng.uniform([-4, -2, -4], [6, 2, 4], (n_points, 3))
    bearings = [normalize((X - c) @ Rk.T + rng.normal(size=X.shape) * noise * 5) for Rk, c in zip(R, centers)]
    ids = np.arange(n_points)
    matches = {(0, 1): np.column_stack([ids, ids]), (1, 2): np.column_stack([ids, ids])}
    pairs = np.array([(0, 1), (1, 2)])
    R_rel, t_rel = relative_from_absolute(R, t, pairs[:, 0], pairs[:, 1])
    tracks, _ = build_tracks(matches, [n_points] * 3)
    return R, centers, pairs, R_rel, t_rel, tracks, bearings


def _run(R, centers, registered, pairs, R_rel, t_rel, tracks, bearings):
    return attach_cameras(R_cam_from_world=np.where(registered[:, None, None], R, np.eye(3)),
                          centers=np.where(registered[:, None], centers, 0.0), registered=registered, pairs=pairs,
                          R_j_from_i=R_rel, t_j_from_i=t_rel, weights=np.array([300.0, 300.0]), tracks=tracks,
                          bearings_per_image=bearings, max_error_rad=np.radians(0.5), min_angle_rad=np.radians(1))


def test_dangling_camera_gets_its_distance_from_the_points():
    R, centers, pairs, R_rel, t_rel, tracks, bearings = _chain()
    out = _run(R, centers, np.array([True, True, False]), pairs, R_rel, t_rel, tracks, bearings)
    assert out.registered.all() and out.attached == [2] and not out.seeded
    assert np.linalg.norm(out.centers[2] - centers[2]) < 0.01 * np.linalg.norm(centers[2] - centers[1])
    assert np.allclose(out.R_cam_from_world[2], R[2], atol=1e-9)


def test_empty_model_is_seeded_from_the_strongest_pair():
    R, centers, pairs, R_rel, t_rel, tracks, bearings = _chain(seed=1)
    out = _run(R, centers, np.zeros(3, bool), pairs, R_rel, t_rel, tracks, bearings)
    assert out.registered.all() and out.seeded
    # gauge: camera 0 at the origin with identity rotation, |c1 - c0| = 1; compare shape up to that similarity
    scale = np.linalg.norm(centers[1] - centers[0])
    true_local = (centers - centers[0]) @ R[0].T / scale
    est_local = (out.centers - out.centers[0]) @ out.R_cam_from_world[0].T
    assert np.allclose(est_local, true_local, atol=0.01)


def test_camera_without_shared_points_stays_unregistered():
    R, centers, pairs, R_rel, t_rel, tracks, bearings = _chain(seed=2)
    no_overlap = build_tracks({(0, 1): np.column_stack([np.arange(200)] * 2),
                               (1, 2): np.column_stack([np.arange(200, 400)] * 2)}, [400] * 3)[0]
    out = _run(R, centers, np.array([True, True, False]), pairs, R_rel, t_rel, no_overlap, bearings)
    assert not out.registered[2] and out.attached == []
