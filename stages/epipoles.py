"""Stage 4 — epipoles and relative pose of every verified pair (the report's rotation formula + cheirality)."""

from __future__ import annotations

import logging
from functools import partial

import numpy as np

from fullview.sfm import two_view
from fullview.stages.protocol import StageContext, thread_map

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("filter",)
INPUTS: tuple[str, ...] = ()


def run(ctx: StageContext) -> dict:
    obs = ctx.ws.load_observations(ctx.dataset)
    verified = ctx.ws.load_inliers()
    P = len(verified.pairs)
    R, t = np.tile(np.eye(3), (P, 1, 1)), np.zeros((P, 3))
    e_i, e_j = np.zeros((P, 3)), np.zeros((P, 3))
    n_cheiral, svd_diff = np.zeros(P, np.int64), np.full(P, np.nan)
    # Pairs are independent: local threads (numpy releases the GIL on the inliers' arrays), the same poses.
    poses = thread_map(partial(_pair_pose, ctx.dataset.image_names, obs, verified), range(P))
    for k, pose in enumerate(poses):
        if pose is not None:
            R[k], t[k], e_i[k], e_j[k] = pose.R_j_from_i, pose.t_j_from_i, pose.e_i, pose.e_j
            n_cheiral[k], svd_diff[k] = pose.num_cheiral, pose.svd_rotation_diff_deg
    n_inliers = np.array([len(m) for m in verified.matches])
    valid = (n_inliers >= 8) & (n_cheiral >= ctx.options.min_cheiral_ratio * np.maximum(n_inliers, 1)) & (n_cheiral > 0)
    ctx.out.save_epipoles(pairs=np.array(verified.pairs).reshape(-1, 2), R_j_from_i=R, t_j_from_i=t, e_i=e_i, e_j=e_j,
                          num_inliers=n_inliers, num_cheiral=n_cheiral, svd_rotation_diff_deg=svd_diff, valid=valid)
    worst = float(np.nanmax(svd_diff)) if np.isfinite(svd_diff).any() else 0.0
    return {"valid_pairs": int(valid.sum()), "pairs": P, "max_svd_rotation_diff_deg": worst}


def _pair_pose(names: list[str], obs, verified, k: int):
    """The relative pose of verified pair k from its F and inliers; None when it has fewer than 8 or F is
    degenerate."""
    (i, j), m = verified.pairs[k], verified.matches[k]
    if len(m) < 8:
        return None
    try:
        return two_view.relative_pose_from_f(verified.extra["F"][k], obs[i]["bearings"][m[:, 0]],
                                             obs[j]["bearings"][m[:, 1]])
    except ValueError as e:  # a degenerate F (no baseline the filter did not catch): the pair is unusable
        log.warning("pair %s-%s has no usable relative pose (%s); skipped", names[i], names[j], e)
        return None
