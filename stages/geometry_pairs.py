"""Pairs the registered model proposes before the final pass (used by the triangulation stage, not a stage itself).

Pair selection for large sets (a capture-order window, retrieval, GPS) can miss neighbours: two panoramas a metre
apart, taken an hour apart, that the vocabulary did not find alike. Once registration has placed the cameras, each
camera is matched with its `triangulation.geometry_neighbours` nearest registered cameras of its model that were
never matched (`sfm.pairs.geometry_pairs`). The relative pose is known, so no RANSAC runs: the matches within the
reprojection bound of its epipolar circles and in front of both cameras are kept (`sfm.two_view.consistent_with_pose`)
when there are at least `triangulation.geometry_min_inliers` of them. The tracks, and so the bundle adjustment, then
use them. With exhaustive pairs every pair was already matched and nothing runs.
"""

from __future__ import annotations

import logging
from functools import lru_cache, partial

import numpy as np

from fullview.sfm.camera import camera_center
from fullview.sfm.matching import match_descriptors
from fullview.sfm.options import MatchesOptions
from fullview.sfm.pairs import geometry_pairs
from fullview.sfm.two_view import consistent_with_pose
from fullview.stages.protocol import StageContext, thread_map

log = logging.getLogger(__name__)

DESCRIPTOR_CACHE = 16  # images whose descriptors are kept in memory (pairs arrive grouped by their first image)


def geometry_matches(ctx: StageContext, attempted: list[tuple[int, int]], model_id: np.ndarray, R: np.ndarray,
                     t: np.ndarray, bearings: list[np.ndarray], *, neighbours: int, threshold_rad: float,
                     min_inliers: int) -> dict[tuple[int, int], np.ndarray]:
    """Matches of the new pairs that hold under the registered poses (R, t: cam_from_world of every camera), keyed
    by pair; `attempted` lists the pairs matched before (verified or not), which are never matched again."""
    if neighbours <= 0:
        return {}
    centres = camera_center(R, t)
    new = [(i, j) for i, j in geometry_pairs(centres, model_id >= 0, attempted, neighbours)
           if model_id[i] == model_id[j]]
    if not new:
        return {}
    names = ctx.dataset.image_names
    descriptors = lru_cache(maxsize=DESCRIPTOR_CACHE)(lambda k: ctx.ws.load_descriptors(names[k]))
    check = partial(_match_and_check, descriptors, bearings, R, t, threshold_rad, min_inliers)
    found = {pair: m for pair, m in zip(new, thread_map(check, new)) if m is not None}
    log.info("geometry pairs: %d new pairs among the registered cameras' nearest, %d hold under the poses",
             len(new), len(found))
    return found


def _match_and_check(descriptors, bearings, R, t, threshold_rad, min_inliers, pair) -> np.ndarray | None:
    i, j = pair
    matches = match_descriptors(descriptors(i), descriptors(j), MatchesOptions())
    R_j_from_i = R[j] @ R[i].T
    keep = consistent_with_pose(bearings[i][matches[:, 0]], bearings[j][matches[:, 1]], R_j_from_i,
                                t[j] - R_j_from_i @ t[i], threshold_rad)
    return matches[keep] if keep.sum() >= min_inliers else None
