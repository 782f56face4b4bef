import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.metrics import pose_auc, pose_metrics, relative_pose_errors, umeyama


def test_auc_matches_reference_values():
    assert pose_auc(np.zeros(4))["auc@1"] == 100.0
    assert pose_auc(np.full(4, np.inf))["auc@10"] == 0.0
    # ten pairs at 0.5°: the reference implementation ramps recall linearly from (0, 0) to (0.5°, 0.1), then
    # jumps to 1: area = 0.5·0.05 + 0.5·1 = 0.525 of the 1° square
    assert np.isclose(pose_auc(np.full(10, 0.5))["auc@1"], 52.5)


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R = Rotation.random(random_state=1).as_matrix()
    dst = 2.5 * src @ R.T + [1, 2, 3]
    sim = umeyama(src, dst)
    assert np.isclose(sim.scale, 2.5) and np.allclose(sim.R, R) and np.allclose(sim.apply(src), dst)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(src[:2], dst[:2])


def test_pose_metrics_are_gauge_invariant_and_count_failures():
    rng = np.random.default_rng(2)
    n = 6
    R_gt = Rotation.random(n, random_state=3).as_matrix()
    c_gt = rng.normal(size=(n, 3))
    S = Rotation.random(random_state=4).as_matrix()  # estimate in another similarity frame
    R_est = R_gt @ S.T
    c_est = 0.3 * c_gt @ S.T + 5
    reg = np.ones(n, bool)
    m = pose_metrics(R_est, c_est, R_gt, c_gt, reg)
    assert m["auc@0.5"] > 99.99 and m["median_center_error_rel"] < 1e-9 and m["median_rotation_error_deg"] < 1e-6
    reg[0] = False
    rot, trans = relative_pose_errors(R_est, c_est, R_gt, c_gt, reg)
    assert np.isinf(rot).sum() == n - 1
    assert np.isclose(pose_metrics(R_est, c_est, R_gt, c_gt, reg)["auc@1"], 100 * (1 - (n - 1) / 15), atol=1e-6)
