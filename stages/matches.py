"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list."""

from __future__ import annotations

import logging
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.workspace import Workspace
from fullview.sfm.matching import match_descriptors, pair_list
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("features",)
INPUTS: tuple[str, ...] = ()
IMAGE_BLOCKS = 8  # the images are cut into this many blocks; one task matches the pairs between two blocks


def run(ctx: StageContext) -> dict:
    options = ctx.options
    names = ctx.dataset.image_names
    pairs = pair_list(len(names), options.pairs, options.window)
    blocks = pair_blocks(pairs, len(names))
    # Each task loads only its blocks' descriptors (a cluster worker reads them itself rather than receiving
    # them); numpy releases the GIL in the products and reductions, so local threads use every core.
    jobs = ctx.map(partial(match_block, ctx.ws.root, names, options), [[pairs[k] for k in b] for b in blocks])
    per_pair: list[np.ndarray] = [np.zeros((0, 2), np.int64)] * len(pairs)
    for block, matches in zip(blocks, tqdm(jobs, total=len(blocks), desc="matches", unit="block")):
        for k, m in zip(block, matches):
            per_pair[k] = m
    ctx.out.save_matches(pairs, per_pair)
    counts = [len(m) for m in per_pair]
    return {"pairs": len(pairs), "median_matches": int(np.median(counts)) if counts else 0}


def pair_blocks(pairs: list[tuple[int, int]], num_images: int) -> list[list[int]]:
    """Indices into `pairs`, grouped by the blocks of images their two images fall in (pair order kept)."""
    size = -(-num_images // IMAGE_BLOCKS) or 1
    groups: dict[tuple[int, int], list[int]] = {}
    for k, (i, j) in enumerate(pairs):
        groups.setdefault((i // size, j // size), []).append(k)
    return list(groups.values())


def match_block(ws_root: Path, names: list[str], options, pairs: list[tuple[int, int]]) -> list[np.ndarray]:
    """The matches of `pairs`, reading the features of their images from the workspace (a top-level function: a
    cluster task of its own)."""
    ws = Workspace(Path(ws_root).parent, Path(ws_root).name)
    descriptors = {i: ws.load_features(names[i])["descriptors"] for i in sorted({i for p in pairs for i in p})}
    return [match_descriptors(descriptors[i], descriptors[j], options) for i, j in pairs]
