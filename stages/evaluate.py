"""`fullview eval`: the reconstruction in the workspace against the dataset's ground_truth/."""

from __future__ import annotations

import logging

import numpy as np

from fullview.io.artifacts import ArtifactError, save_json
from fullview.io.dataset import Dataset, DatasetError
from fullview.io.store import load_poses
from fullview.io.workspace import Workspace
from fullview.sfm.metrics import pose_metrics

log = logging.getLogger(__name__)


def evaluate(dataset: Dataset, ws: Workspace) -> dict:
    """Pose metrics (and dense metrics when available); written to workspace/<dataset>/eval/metrics.json."""
    if not dataset.has_ground_truth():
        raise DatasetError(f"{dataset.root}: no ground_truth/poses.yaml to evaluate against")
    gt = dataset.ground_truth_poses()
    missing = [n for n in dataset.image_names if n not in gt]
    if missing:
        raise DatasetError(f"{dataset.ground_truth_dir / 'poses.yaml'}: no pose for {missing}")
    est, source = load_poses(ws)
    stored = [str(n) for n in est["image_names"]]
    if stored != dataset.image_names:
        raise ArtifactError(f"{ws.root}: the reconstruction is of images {stored}, the dataset now has "
                            f"{dataset.image_names}; rerun the pipeline")
    R_gt = np.stack([gt[n].R_world_from_cam.T for n in dataset.image_names])
    c_gt = np.stack([gt[n].center for n in dataset.image_names])
    metrics = {"dataset": dataset.name, "poses_from": source}
    metrics.update(pose_metrics(est["R_cam_from_world"], est["centers"], R_gt, c_gt, est["registered"]))
    densify, triangulation = ws.read_manifest("densify"), ws.read_manifest("triangulation")
    dense_current = (densify is not None and triangulation is not None and source == "triangulation"
                     and densify["upstream"].get("triangulation") == triangulation["fingerprint"])
    if dense_current and dataset.ground_truth_depth(dataset.image_names[0]) is not None:
        from fullview.stages.densify import evaluate_dense
        dense = evaluate_dense(dataset, ws, est, R_gt, c_gt)
        if dense is not None:
            metrics["dense"] = dense
    save_json(ws.eval_path(), metrics)
    return metrics
