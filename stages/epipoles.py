"""Stage 4 — epipoles and relative pose of every verified pair (the report's rotation formula + cheirality)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fullview.io.artifacts import save_npz
from fullview.io.dataset import Dataset
from fullview.io.store import EPIPOLES_VERSION, load_observations, load_pair_data
from fullview.io.workspace import Workspace
from fullview.sfm import two_view

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("filter",)
INPUTS: tuple[str, ...] = ()


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    obs = load_observations(ws, dataset)
    pairs, inliers, extra = load_pair_data(ws.inliers_path())
    P = len(pairs)
    R, t = np.tile(np.eye(3), (P, 1, 1)), np.zeros((P, 3))
    e_i, e_j = np.zeros((P, 3)), np.zeros((P, 3))
    n_cheiral, svd_diff = np.zeros(P, np.int64), np.full(P, np.nan)
    for k, (i, j) in enumerate(pairs):
        m = inliers[k]
        if len(m) < 8:
            continue
        pose = two_view.relative_pose_from_f(extra["F"][k], obs[i]["bearings"][m[:, 0]], obs[j]["bearings"][m[:, 1]])
        R[k], t[k], e_i[k], e_j[k] = pose.R_j_from_i, pose.t_j_from_i, pose.e_i, pose.e_j
        n_cheiral[k], svd_diff[k] = pose.num_cheiral, pose.svd_rotation_diff_deg
    n_inliers = np.array([len(m) for m in inliers])
    valid = (n_inliers >= 8) & (n_cheiral >= config["min_cheiral_ratio"] * np.maximum(n_inliers, 1))
    save_npz(ws.epipoles_path(out_dir), EPIPOLES_VERSION, pairs=np.array(pairs).reshape(-1, 2), R_j_from_i=R,
             t_j_from_i=t, e_i=e_i, e_j=e_j, num_inliers=n_inliers, num_cheiral=n_cheiral,
             svd_rotation_diff_deg=svd_diff, valid=valid)
    worst = float(np.nanmax(svd_diff)) if np.isfinite(svd_diff).any() else 0.0
    return {"valid_pairs": int(valid.sum()), "pairs": P, "max_svd_rotation_diff_deg": worst}
