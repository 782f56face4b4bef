"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list."""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from tqdm import tqdm

from fullview.sfm.matching import match_descriptors
from fullview.sfm.pairs import select_pairs
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("features",)
INPUTS: tuple[str, ...] = ()


def run(ctx: StageContext) -> dict:
    options = ctx.options
    descriptors = [ctx.ws.load_features(n)["descriptors"] for n in ctx.dataset.image_names]
    pairs, _sources = select_pairs(descriptors, options, ctx.dataset.gps_positions())
    # numpy releases the GIL in the products and reductions, so threads over pairs use every core.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        jobs = pool.map(lambda p: match_descriptors(descriptors[p[0]], descriptors[p[1]], options), pairs)
        per_pair = list(tqdm(jobs, total=len(pairs), desc="matches", unit="pair"))
    ctx.out.save_matches(pairs, per_pair)
    counts = [len(m) for m in per_pair]
    return {"pairs": len(pairs), "median_matches": int(np.median(counts)) if counts else 0}
