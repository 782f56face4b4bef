"""Every unregistered image gets the reason a user can act on."""

import numpy as np

from fullview.sfm.registration.diagnosis import unregistered_reasons


def test_each_kind_of_unregistered_image_gets_its_reason():
    names = [f"img{k}" for k in range(8)]
    # model: 0-1-2; separate group: 3-4; 5 only a no-baseline pair with 0; 6 too few features; 7 weak pair to 1;
    # 2 is in the model's component but was rejected by registration
    pairs = np.array([[0, 1], [1, 2], [0, 2], [3, 4], [0, 5], [1, 7], [2, 6]])
    num_inliers = np.array([200, 150, 180, 90, 300, 12, 0])
    no_baseline = np.array([False, False, False, False, True, False, False])
    usable = num_inliers >= 30
    usable[4] = False  # the no-baseline pair never becomes usable
    registered = np.array([True, True, False, False, False, False, False, False])
    reasons = unregistered_reasons(names=names, registered=registered,
                                   num_features=np.array([900, 900, 900, 700, 700, 800, 3, 500]), pairs=pairs,
                                   num_inliers=num_inliers, usable=usable, no_baseline=no_baseline, min_features=8,
                                   min_inliers=30)
    assert set(reasons) == {f"img{k}" for k in range(2, 8)}
    assert reasons["img2"].startswith("rejected as inconsistent")
    assert reasons["img3"].startswith("in a separate group of 2 image(s)") and "img4" in reasons["img3"]
    assert "no baseline" in reasons["img5"]
    assert reasons["img6"] == "too few features (3)"
    assert reasons["img7"] == "no verified pair with >= 30 inliers (best: 12)"


def test_pairs_toward_main_name_the_best_matched_pairs_between_two_models():
    from fullview.sfm.registration.diagnosis import pairs_toward_main
    model_id = np.array([1, 1, 0, 0, 0, -1])
    pairs = np.array([[0, 1], [0, 2], [1, 2], [1, 3], [2, 3], [0, 5], [1, 4]])
    num_raw = np.array([90, 20, 39, 0, 70, 50, 12])
    # within a model, to no model and without raw matches: not listed; image of model 1 first, most matches first
    assert pairs_toward_main(pairs=pairs, num_raw=num_raw, model_id=model_id, model=1) == [(1, 2, 39), (0, 2, 20),
                                                                                           (1, 4, 12)]
    assert pairs_toward_main(pairs=pairs, num_raw=num_raw, model_id=model_id, model=1, count=1) == [(1, 2, 39)]
    assert pairs_toward_main(pairs=pairs, num_raw=num_raw, model_id=model_id, model=2) == []
