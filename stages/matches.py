"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list.

Descriptors are streamed: pairs are matched in blocks (`sfm.matching.pair_blocks`) and only the images of the
current block have their descriptors in memory, so the peak does not grow with the number of panoramas.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from tqdm import tqdm

from fullview.io.workspace import Workspace
from fullview.sfm.matching import match_descriptors, pair_blocks, pair_list
from fullview.sfm.options import MatchesOptions
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("features",)
INPUTS: tuple[str, ...] = ()
BLOCK_IMAGES = 16  # images per side of a block of pairs: at most 2 x 16 images' descriptors are loaded at once


def match_pair_block(ws: Workspace, image_names: list[str], pairs: list[tuple[int, int]], options: MatchesOptions,
                     pool: ThreadPoolExecutor | None = None) -> list[np.ndarray]:
    """Matches of a block of pairs (indices into `image_names`), loading the descriptors of the block's images
    itself: a unit of work that needs nothing but the workspace (a worker process or a cluster task can run it)."""
    images = sorted({k for pair in pairs for k in pair})
    descriptors = {k: ws.load_features(image_names[k])["descriptors"] for k in images}
    match = lambda p: match_descriptors(descriptors[p[0]], descriptors[p[1]], options)  # noqa: E731
    return list(pool.map(match, pairs)) if pool is not None else [match(p) for p in pairs]


def run(ctx: StageContext) -> dict:
    options = ctx.options
    names = ctx.dataset.image_names
    pairs = pair_list(len(names), options.pairs, options.window)
    per_pair: list[np.ndarray | None] = [None] * len(pairs)
    # numpy releases the GIL in the products and reductions, so threads over a block's pairs use every core.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool, \
            tqdm(total=len(pairs), desc="matches", unit="pair") as bar:
        for block in pair_blocks(pairs, BLOCK_IMAGES):
            for k, m in zip(block, match_pair_block(ctx.ws, names, [pairs[k] for k in block], options, pool)):
                per_pair[k] = m.astype(np.int32)  # the stored format is int64; int32 halves what is held meanwhile
            bar.update(len(block))
    ctx.out.save_matches(pairs, per_pair)
    counts = [len(m) for m in per_pair]
    return {"pairs": len(pairs), "median_matches": int(np.median(counts)) if counts else 0}
