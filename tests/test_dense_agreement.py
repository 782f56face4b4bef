"""Leave-one-out agreement of range maps (fullview.sfm.dense_metrics): a measure of dense depth without ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from fullview import synth
from fullview.sfm.dense_metrics import leave_one_out_agreement, predicted_range_map


@pytest.fixture(scope="module")
def room():
    scene = synth.render_scene(views=4, width=256, seed=2, supersample=1)
    R = np.stack([v.R_world_from_cam.T for v in scene.views])
    t = -np.einsum("nab,nb->na", R, np.stack([v.center for v in scene.views]))
    return [v.depth.astype(np.float64) for v in scene.views], R, t


def test_exact_ranges_agree_and_predict_each_other(room):
    ranges, R, t = room
    predicted = predicted_range_map(0, ranges, R, t, stride=1)
    both = np.isfinite(predicted)
    assert both.mean() > 0.5  # the other panoramas see most of what panorama 0 sees
    assert np.median(np.abs(predicted[both] - ranges[0][both]) / ranges[0][both]) < 0.01
    for entry in leave_one_out_agreement(ranges, R, t, stride=1):
        assert entry["valid_share"] == 1.0 and entry["agreement"] > 0.85 and entry["checked_share"] > 0.5


def test_a_wrong_range_map_disagrees_and_the_others_still_agree(room):
    ranges, R, t = room
    wrong = [r.copy() for r in ranges]
    wrong[2] *= 1.1  # 10% too far everywhere
    wrong[3][:, :64] = np.nan  # a quarter without depth
    result = leave_one_out_agreement(wrong, R, t, stride=1)
    assert result[2]["agreement"] < 0.2
    assert result[3]["valid_share"] == pytest.approx(0.75)
    # the nearest prediction wins, so a map that is too far spoils the others only where it alone sees their surface
    for k in (0, 1, 3):
        assert result[k]["agreement"] > max(0.5, 3 * result[2]["agreement"])


def test_missing_maps_and_single_panorama():
    ranges = [np.full((8, 16), 2.0), None]
    R, t = np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3))
    result = leave_one_out_agreement(ranges, R, t)
    assert result[0]["agreement"] is None and result[0]["checked_share"] == 0.0
    assert result[1] == {"valid_share": 0.0, "agreement": None, "checked_share": 0.0}
