"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list.

The pair list comes from `sfm.pairs.select_pairs` (`matches.pairs`: exhaustive for small sets, else the capture
order, retrieval and GPS). Descriptors are streamed: retrieval reads each image's descriptors when it needs them,
and pairs are matched in blocks (`sfm.matching.pair_blocks`), each block a task that loads only its images'
descriptors (at most 2 x `BLOCK_IMAGES`), so the peak does not grow with the number of panoramas; the tasks run on
the stage's fan-out (`StageContext.map`: local threads, or a Dask cluster under `fullview batch`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.workspace import Workspace
from fullview.sfm.matching import (basis_from_moments, match_descriptors, pair_blocks, project_descriptors,
                                   second_moment)
from fullview.sfm.options import MatchesOptions
from fullview.sfm.pairs import select_pairs, uses_gps
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("features",)
INPUTS: tuple[str, ...] = ()
BLOCK_IMAGES = 16  # images per side of a block of pairs: at most 2 x 16 images' descriptors are loaded at once
MIN_BLOCKS_PER_SIDE = 4  # small datasets are still cut into this many image blocks, so the tasks use every core


class StoredDescriptors(Sequence):
    """Every image's descriptors, read from the workspace when indexed (never all in memory at once)."""

    def __init__(self, ws: Workspace, names: list[str]):
        self.ws, self.names = ws, names

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, k: int) -> np.ndarray:
        return self.ws.load_descriptors(self.names[k])


def run(ctx: StageContext) -> dict:
    options = ctx.options
    names = ctx.dataset.image_names
    gps = ctx.dataset.gps_positions() if uses_gps(len(names), options) else None
    pairs, sources = select_pairs(StoredDescriptors(ctx.ws, names), options, gps)
    block_images = max(1, min(BLOCK_IMAGES, -(-len(names) // MIN_BLOCKS_PER_SIDE)))
    # Largest blocks first: the last tasks to start are small, so both threads finish together (at 6 images the
    # blocks hold 4, 4, 4, 1, 1, 1 pairs: 8 pair-times instead of 9 in index order; results land by pair index).
    blocks = sorted(pair_blocks(pairs, block_images), key=len, reverse=True)
    # The images' second moments on the executor (the other core idled while one loop read and multiplied them),
    # summed in image order: the basis of `descriptor_basis`, bit for bit.
    basis = (basis_from_moments(ctx.map(partial(image_moment, ctx.ws.root, names), range(len(names))),
                                options.descriptor_dims) if options.descriptor_dims else None)
    jobs = ctx.map(partial(match_block, ctx.ws.root, names, options, basis=basis),
                   [[pairs[k] for k in b] for b in blocks])
    per_pair: list[np.ndarray | None] = [None] * len(pairs)
    with tqdm(total=len(pairs), desc="matches", unit="pair") as bar:
        for block, matches in zip(blocks, jobs):
            for k, m in zip(block, matches):
                per_pair[k] = m.astype(np.int32)  # the stored format is int64; int32 halves what is held meanwhile
            bar.update(len(block))
    ctx.out.save_matches(pairs, per_pair)
    counts = [len(m) for m in per_pair]
    return {"pairs": len(pairs), "pair_sources": sources,
            "median_matches": int(np.median(counts)) if counts else 0}


def image_moment(ws_root: Path, names: list[str], k: int) -> np.ndarray:
    """Image k's descriptor second moment, read from the workspace (a top-level function: a cluster task)."""
    return second_moment(Workspace(Path(ws_root).parent, Path(ws_root).name).load_descriptors(names[k]))


def match_block(ws_root: Path, names: list[str], options: MatchesOptions, pairs: list[tuple[int, int]], *,
                basis: np.ndarray | None = None) -> list[np.ndarray]:
    """The matches of `pairs`, reading the features of their images from the workspace itself (a top-level function
    of picklable arguments: a cluster task of its own), searched on `basis`'s components when given."""
    ws = Workspace(Path(ws_root).parent, Path(ws_root).name)
    full = {i: ws.load_descriptors(names[i]) for i in sorted({i for p in pairs for i in p})}
    if basis is None:
        return [match_descriptors(full[i], full[j], options) for i, j in pairs]
    projected = {i: project_descriptors(d, basis) for i, d in full.items()}
    return [match_descriptors(projected[i], projected[j], options, full=(full[i], full[j])) for i, j in pairs]
