"""Leave-one-out agreement of range maps (fullview.sfm.dense_metrics): a measure of dense depth without ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from fullview import synth
from fullview.sfm.camera import pixel_grid_bearings
from fullview.sfm.dense_agreement import visible_agreement
from fullview.sfm.dense_metrics import leave_one_out_agreement, predicted_range_map
from fullview.synth.render import cast_rays


@pytest.fixture(scope="module")
def room(small_room):
    ranges, R, t = small_room
    return [r.copy() for r in ranges], R, t


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


# ------------------------------------------------------------------------------------------------ with visibility
def test_exact_ranges_agree_with_visibility_and_wrong_maps_do_not(room):
    ranges, R, t = room
    for entry in visible_agreement(ranges, R, t, stride=1):  # the rest: pixels of 1.4° at grazing angles
        assert entry["agreement"] > 0.92 and entry["checked_share"] > 0.5
    for factor in (1.1, 0.9):  # a map 10% too far, or too near, everywhere
        wrong = [r.copy() for r in ranges]
        wrong[2] *= factor
        result = visible_agreement(wrong, R, t, stride=1)
        assert result[2]["agreement"] < 0.2
        for k in (0, 1, 3):  # outvoted where it sees through the others' points; a surface it puts in front of
            assert result[k]["agreement"] > 0.85  # them (too near) still vetoes them


def test_the_far_side_of_a_wall_is_no_prediction():
    # two rooms of one box split by a closed 10 cm wall, two panoramas in each: exact ranges agree with visibility;
    # the splatted prediction takes the wall's other face and the far room behind the gaps between splats
    boxes = np.array([[[-3.0, -1.3, -2.0], [3.0, 1.2, 2.0]], [[-0.05, -1.3, -2.0], [0.05, 1.2, 2.0]]])
    centers = np.array([[-1.5, 0.0, 0.0], [-2.0, 0.1, 1.0], [1.5, 0.0, 0.5], [1.0, -0.1, -0.8]])
    width = 256
    bearings = pixel_grid_bearings(width, width // 2).reshape(-1, 3)
    ranges = [cast_rays(c, bearings, boxes)[0].reshape(width // 2, width).astype(np.float64) for c in centers]
    R, t = np.tile(np.eye(3), (4, 1, 1)), -centers
    splatted = [e["agreement"] for e in leave_one_out_agreement(ranges, R, t, stride=1)]
    assert min(splatted) < 0.85
    for entry in visible_agreement(ranges, R, t, stride=1):
        assert entry["agreement"] > 0.98
