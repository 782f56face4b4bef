"""Stage 3 — geometric verification: F on the sphere, seeded by hand points where a pair has enough of them.

Pairs with hand points follow the report: F from the hand points, SIFT matches near its epipolar circles kept, F
re-estimated on all inliers. Other pairs use LO-MSAC with angular errors and a non-linear refinement. The stored
inlier matches live in the extended feature index space (SIFT features, then hand observations; see io.store).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.dataset import Dataset
from fullview.io.store import hand_pair_matches, load_observations, load_pair_data, save_pair_data
from fullview.io.workspace import Workspace
from fullview.sfm import two_view

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("matches",)
INPUTS = ("hand_points",)


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    obs = load_observations(ws, dataset)
    num_sift = [int(o["num_sift"]) for o in obs]
    pairs, raw, _ = load_pair_data(ws.matches_path())
    threshold = np.radians(config["threshold_deg"])
    inliers, Fs, seeded, num_hand = [], [], [], []
    for k, (i, j) in enumerate(tqdm(pairs, desc="filter", unit="pair")):
        hand = hand_pair_matches(dataset, num_sift, i, j) if config["use_hand_points"] else np.zeros((0, 2), int)
        use_seed = len(hand) >= config["min_hand_points"]
        F, keep = _verify_pair(obs[i]["bearings"], obs[j]["bearings"], raw[k], hand if use_seed else None,
                               threshold, config, seed=config["seed"] + k)
        good = np.concatenate([raw[k][keep], hand]) if len(hand) else raw[k][keep]
        if len(good) < config["min_inliers"]:
            good = good[:0]
        inliers.append(good)
        Fs.append(F)
        seeded.append(use_seed)
        num_hand.append(len(hand))
    save_pair_data(ws.inliers_path(out_dir), pairs, inliers, F=np.array(Fs).reshape(-1, 3, 3),
                   num_raw=np.array([len(m) for m in raw]), seeded=np.array(seeded, bool),
                   num_hand=np.array(num_hand))
    counts = np.array([len(m) for m in inliers])
    return {"pairs": len(pairs), "verified_pairs": int((counts > 0).sum()), "seeded_pairs": int(sum(seeded)),
            "median_inliers": int(np.median(counts)) if len(counts) else 0}


def _verify_pair(bear_i, bear_j, matches, hand, threshold, config, seed):
    """F and the inlier mask over `matches` (hand correspondences, when given, seed the estimate)."""
    b_i, b_j = bear_i[matches[:, 0]], bear_j[matches[:, 1]]
    opts = two_view.RansacOptions(threshold_rad=threshold, max_iterations=config["max_iterations"],
                                  confidence=config["confidence"], seed=seed)
    try:
        if hand is not None:
            res = two_view.fit_f_seeded(bear_i[hand[:, 0]], bear_j[hand[:, 1]], b_i, b_j, threshold)
        else:
            res = two_view.ransac_f(b_i, b_j, opts)
    except ValueError as e:  # too few correspondences: the pair is simply not verified
        log.debug("pair not verified: %s", e)
        return np.zeros((3, 3)), np.zeros(len(matches), bool)
    return res.F, res.inliers
