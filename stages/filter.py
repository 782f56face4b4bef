"""Stage 3 — geometric verification: F on the sphere, seeded by hand points where a pair has enough of them.

Pairs with hand points follow the report: F from the hand points, SIFT matches near its epipolar circles kept, F
re-estimated on all inliers. Other pairs use LO-MSAC with angular errors and a non-linear refinement. A pair whose
inliers a pure rotation explains has no baseline and is dropped. The stored inlier matches live in the extended
feature index space (SIFT features, then hand observations; see `Workspace.load_observations`).
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from fullview.io.dataset import Dataset
from fullview.sfm import two_view
from fullview.sfm.baseline import has_no_baseline
from fullview.sfm.matching import epipolar_candidates, match_descriptors
from fullview.sfm.options import FilterOptions, MatchesOptions
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("matches",)
INPUTS = ("hand_points",)


def run(ctx: StageContext) -> dict:
    options: FilterOptions = ctx.options
    obs = ctx.ws.load_observations(ctx.dataset)
    num_sift = [int(o["num_sift"]) for o in obs]
    guided = MatchesOptions(ratio=options.guided_ratio, mutual=True)
    descriptors = ([ctx.ws.load_features(n)["descriptors"] for n in ctx.dataset.image_names]
                   if options.guided_matching else None)
    guided_counts = []
    raw = ctx.ws.load_matches()
    threshold = np.radians(options.threshold_deg)
    inliers, Fs, seeded, num_hand, no_baseline = [], [], [], [], []
    for k, (i, j) in enumerate(tqdm(raw.pairs, desc="filter", unit="pair")):
        hand = hand_pair_matches(ctx.dataset, num_sift, i, j) if options.use_hand_points else np.zeros((0, 2), int)
        use_seed = len(hand) >= options.min_hand_points
        F, keep = _verify_pair(obs[i]["bearings"], obs[j]["bearings"], raw.matches[k], hand if use_seed else None,
                               threshold, options, seed=options.seed + k)
        good = np.concatenate([raw.matches[k][keep], hand]) if len(hand) else raw.matches[k][keep]
        if descriptors is not None and len(good) >= options.min_inliers:
            good, added = _add_guided(good, descriptors[i], descriptors[j], obs[i]["bearings"], obs[j]["bearings"],
                                      F, threshold, guided)
            guided_counts.append(added)
        flat = len(good) >= options.min_inliers and has_no_baseline(
            obs[i]["bearings"][good[:, 0]], obs[j]["bearings"][good[:, 1]], threshold)
        if flat:
            log.warning("pair %s-%s has no baseline (a rotation explains its matches); skipped",
                        ctx.dataset.image_names[i], ctx.dataset.image_names[j])
        if len(good) < options.min_inliers or flat:
            good = good[:0]
        inliers.append(good)
        Fs.append(F)
        seeded.append(use_seed)
        num_hand.append(len(hand))
        no_baseline.append(flat)
    ctx.out.save_inliers(raw.pairs, inliers, F=np.array(Fs).reshape(-1, 3, 3),
                         num_raw=np.array([len(m) for m in raw.matches]), seeded=np.array(seeded, bool),
                         num_hand=np.array(num_hand), no_baseline=np.array(no_baseline, bool))
    counts = np.array([len(m) for m in inliers])
    names = ctx.dataset.image_names
    return {"pairs": len(raw.pairs), "verified_pairs": int((counts > 0).sum()), "seeded_pairs": int(sum(seeded)),
            "median_inliers": int(np.median(counts)) if len(counts) else 0,
            "no_baseline_pairs": [[names[i], names[j]] for (i, j), f in zip(raw.pairs, no_baseline) if f],
            "guided_matches_added": int(sum(guided_counts))}


def _add_guided(good: np.ndarray, desc_i, desc_j, bear_i, bear_j, F, threshold, guided_options: MatchesOptions):
    """A verified pair's inliers plus the SIFT matches found along the epipolar circles of F (looser ratio test among
    the candidates near each circle, mutual check), kept when their symmetric epipolar error is within the threshold
    and they lie in front of both cameras under the pair's relative pose (the epipolar constraint alone cannot reject
    a match on the wrong side of the baseline). Only verified pairs are extended: a weak pair's F is too uncertain
    to guide (measured: promoting weak pairs broke registration on the synthetic home). Returns (inliers, added)."""
    num_i, num_j = len(desc_i), len(desc_j)
    allowed = epipolar_candidates(bear_i[:num_i], bear_j[:num_j], F, threshold)
    guided = match_descriptors(desc_i, desc_j, guided_options, block_rows=1024, allowed=allowed)
    if not len(guided):
        return good, 0
    errors = two_view.epipolar_angular_errors(F, bear_i[guided[:, 0]], bear_j[guided[:, 1]])
    guided = guided[errors <= threshold]
    try:
        pose = two_view.relative_pose_from_f(F, bear_i[good[:, 0]], bear_j[good[:, 1]])
    except ValueError:
        return good, 0
    depth_i, depth_j = two_view.ray_depths(bear_i[guided[:, 0]], bear_j[guided[:, 1]], pose.R_j_from_i,
                                           pose.t_j_from_i)
    guided = guided[(depth_i > 0) & (depth_j > 0)]
    width = max(int(good[:, 1].max(initial=0)), int(guided[:, 1].max(initial=0))) + 1
    new = guided[~np.isin(guided[:, 0] * width + guided[:, 1], good[:, 0] * width + good[:, 1])]
    return (np.concatenate([good, new]) if len(new) else good), len(new)


def hand_pair_matches(dataset: Dataset, num_sift: list[int], i: int, j: int) -> np.ndarray:
    """(K, 2) hand correspondences of images i, j in the extended feature index space."""
    hand = dataset.hand_observations
    tracks_i, _ = hand[dataset.image_names[i]]
    tracks_j, _ = hand[dataset.image_names[j]]
    _, ki, kj = np.intersect1d(tracks_i, tracks_j, assume_unique=True, return_indices=True)
    return np.column_stack([ki + num_sift[i], kj + num_sift[j]]).astype(np.int64)


def _verify_pair(bear_i, bear_j, matches, hand, threshold, options: FilterOptions, seed):
    """F and the inlier mask over `matches` (hand correspondences, when given, seed the estimate)."""
    b_i, b_j = bear_i[matches[:, 0]], bear_j[matches[:, 1]]
    opts = two_view.RansacOptions(threshold_rad=threshold, max_iterations=options.max_iterations,
                                  confidence=options.confidence, seed=seed)
    try:
        if hand is not None:
            res = two_view.fit_f_seeded(bear_i[hand[:, 0]], bear_j[hand[:, 1]], b_i, b_j, threshold)
        else:
            res = two_view.ransac_f(b_i, b_j, opts)
    except ValueError as e:  # too few correspondences: the pair is simply not verified
        log.debug("pair not verified: %s", e)
        return np.zeros((3, 3)), np.zeros(len(matches), bool)
    return res.F, res.inliers
