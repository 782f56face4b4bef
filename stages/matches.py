"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list."""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.matching import MatchOptions, match_descriptors, pair_list
from fullview.io.store import load_features, save_pair_data

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("features",)
INPUTS: tuple[str, ...] = ()


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    names = dataset.image_names
    descriptors = [load_features(ws, n)["descriptors"] for n in names]
    options = MatchOptions(ratio=config["ratio"], mutual=config["mutual"])
    pairs = pair_list(len(names), config["pairs"], config["window"])
    # numpy releases the GIL in the products and reductions, so threads over pairs use every core.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        jobs = pool.map(lambda p: match_descriptors(descriptors[p[0]], descriptors[p[1]], options), pairs)
        per_pair = list(tqdm(jobs, total=len(pairs), desc="matches", unit="pair"))
    save_pair_data(ws.matches_path(out_dir), pairs, per_pair)
    counts = [len(m) for m in per_pair]
    return {"pairs": len(pairs), "median_matches": int(np.median(counts)) if counts else 0}
