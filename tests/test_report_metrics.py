"""The report's metrics table: the eval's sections one level down are shown, per-image lists are not."""

from fullview.commands.report import metric_rows


def test_metric_rows_show_the_agreement_of_a_dataset_without_ground_truth():
    metrics = {"dataset": "360_Flat", "poses_from": "triangulation",
               "dense_agreement": {"tolerance": 0.02, "median_visible_agreement": 0.927,
                                   "per_image": {"a.jpg": {"valid_share": 0.6}}},
               "models": [{"registered": 11}]}
    rows = dict(metric_rows(metrics))
    assert rows == {"dataset": "360_Flat", "poses_from": "triangulation", "dense_agreement.tolerance": 0.02,
                    "dense_agreement.median_visible_agreement": 0.927}


def test_metric_rows_keep_the_top_level_order_and_values():
    metrics = {"registered": 6, "auc@1": 99.6, "dense": {"cloud": {"accuracy": 1.0}, "min_valid_share": 0.77}}
    assert metric_rows(metrics) == [("registered", 6), ("auc@1", 99.6), ("dense.min_valid_share", 0.77)]
