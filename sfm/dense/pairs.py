"""Which panoramas to pair for dense stereo, and the disparity search of a pair.

Pairs are ranked by inlier count and triangulation angle at the scene depth; the search range of a pair covers the
nearest plausible depth, taken from the sparse points since the model's scale is arbitrary.
"""

from __future__ import annotations

import numpy as np

from fullview.sfm.options import DensifyOptions


def select_stereo_pairs(
    centers: np.ndarray,
    inlier_counts: np.ndarray,
    *,
    k: int,
    min_triangulation_angle_deg: float,
    max_triangulation_angle_deg: float = DensifyOptions.max_triangulation_angle_deg,
    target_triangulation_angle_deg: float = 10.0,
    min_inliers: int = DensifyOptions.min_pair_inliers,
    scene_depths: np.ndarray | None = None,
    min_epipole_separation_deg: float = 0.0,
) -> np.ndarray:
    """Union over cameras of each camera's ``k`` best dense-stereo partners, as (M, 2) pairs (i < j), sorted.

    The triangulation angle of a pair is ``2·atan(B / (2·depth))`` with B the baseline and depth the mean of the two
    cameras' ``scene_depths`` (e.g. median sparse-point distance; default: the median camera-to-camera distance, a
    rough scene scale). Candidates need ``min_inliers`` matches and an angle within [min, max]; they are ranked by
    ``inliers · min(1, angle / target_angle)``: inlier count, discounted for baselines shorter than the target.
    A camera's partners are spread over baseline directions (``min_epipole_separation_deg``, see
    ``_diverse_partners``), so that each pixel has a partner whose epipole is far from it.
    """
    centers = np.asarray(centers, dtype=np.float64)
    inliers = np.asarray(inlier_counts, dtype=np.float64)
    n = len(centers)
    if inliers.shape != (n, n):
        raise ValueError(f"inlier_counts must be ({n}, {n}) for {n} centers, got {inliers.shape}")
    inliers = np.maximum(inliers, inliers.T)  # symmetric
    baseline = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    if scene_depths is None:
        off = baseline[~np.eye(n, dtype=bool)]
        scene_depths = np.full(n, np.median(off) if off.size else 1.0)
    depth = 0.5 * (np.asarray(scene_depths, dtype=np.float64)[:, None] + np.asarray(scene_depths)[None])
    angle = np.degrees(2 * np.arctan2(baseline, 2 * depth))
    ok = (
        (inliers >= min_inliers)
        & (angle >= min_triangulation_angle_deg)
        & (angle <= max_triangulation_angle_deg)
        & ~np.eye(n, dtype=bool)
    )
    score = np.where(ok, inliers * np.minimum(1.0, angle / target_triangulation_angle_deg), -np.inf)
    best = _diverse_partners(centers, score, k, min_epipole_separation_deg)
    i_idx = np.repeat(np.arange(n), k)
    j_idx = best.ravel()
    good = j_idx >= 0
    pairs = np.sort(np.stack([i_idx[good], j_idx[good]], axis=1), axis=1)
    return np.unique(pairs, axis=0) if len(pairs) else np.zeros((0, 2), dtype=np.intp)


def _diverse_partners(centers: np.ndarray, score: np.ndarray, k: int, min_separation_deg: float) -> np.ndarray:
    """(n, k) each camera's partners (−1: none), best score first, skipping a candidate whose baseline direction is
    within ``min_separation_deg`` of a chosen partner's (or of its opposite): its epipoles would fall where the
    chosen pair's do, leaving the same pixels ill-conditioned. When too few candidates are far enough apart (cameras
    on a line), the best remaining ones fill the slots."""
    n = len(centers)
    order = np.argsort(-score, axis=1, kind="stable")
    out = np.full((n, k), -1)
    cos_max = np.cos(np.radians(min_separation_deg))
    for i in range(n):  # a few candidates per camera
        cand = [j for j in order[i] if np.isfinite(score[i, j])]
        if not cand:
            continue
        d = centers[cand] - centers[i]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        chosen: list[int] = []
        for c in range(len(cand)):
            if len(chosen) == k:
                break
            if min_separation_deg <= 0 or all(abs(d[c] @ d[o]) < cos_max for o in chosen):
                chosen.append(c)
        chosen += [c for c in range(len(cand)) if c not in chosen][:k - len(chosen)]
        out[i, :len(chosen)] = [cand[c] for c in chosen]
    return out


def pair_min_depth_ratio(near_i: float, near_j: float, baseline: float, factor: float,
                         max_disparity_deg: float) -> float:
    """Nearest plausible depth over the baseline (``dense.disparity_search_range``'s argument): the nearer of the
    two cameras' low-percentile sparse depths times ``factor``, bounded so the search spans at most
    ``max_disparity_deg``."""
    near = np.nanmin([near_i, near_j]) if np.isfinite([near_i, near_j]).any() else baseline
    return max(factor * float(near) / baseline, 1.0 / np.sin(np.radians(min(max_disparity_deg, 90.0))))
