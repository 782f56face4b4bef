"""Stage 2 — putative matches: ratio test and mutual check for every pair of the pair list.

The pair list comes from `sfm.pairs.plan_pairs` (`matches.pairs`: exhaustive for small sets, else the capture
order, retrieval and GPS). With a capture order (`auto` above the exhaustive size, `sequential`) the retrieval pairs
more than twice the window apart are loop candidates, matched in rounds after the others (`sfm.pairs.loop_rounds`):
each image proposes its candidates in similarity order and stops after `matches.loop_patience` of them in a row find
fewer than `matches.loop_min_share` of its window pairs' median matches. On a walk most far retrieval pairs are chance
look-alikes that cannot verify; a place visited again, or a room's images, keep finding matches and keep looking.
Which pairs a round proposes depends only on the matches of earlier rounds, so the artifact is deterministic, and
the pairs not matched are simply not in it.

Descriptors are streamed: retrieval reads each image's descriptors when it needs them, and pairs are matched in
blocks (`sfm.matching.pair_blocks`), each block a task that loads only its images' descriptors (at most
2 x `BLOCK_IMAGES`), so the peak does not grow with the number of panoramas; the tasks run on the stage's fan-out
(`StageContext.map`: local threads, or a Dask cluster under `fullview batch`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.workspace import Workspace
from fullview.sfm.matching import basis_from_moments, match_pair, pair_blocks, project_descriptors, second_moment
from fullview.sfm.options import MatchesOptions
from fullview.sfm.pairs import first_loop_proposals, loop_rounds, plan_pairs, uses_gps
from fullview.stages.protocol import StageContext, thread_map

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
    with ThreadPoolExecutor(1) as side:
        # The pair plan is made on a side thread (retrieval's per-image work on local threads: its tasks are lambdas
        # over the stored descriptors) while the stage's fan-out computes the images' second moments, which do not
        # depend on it: retrieval's serial parts left a core idle on a walk. The fan-out stays on this thread (a
        # cluster's map needs the worker's own task thread). The moments are summed in image order: the basis of
        # `descriptor_basis`, bit for bit.
        plan = side.submit(plan_pairs, StoredDescriptors(ctx.ws, names), options, gps, map=thread_map)
        basis = (basis_from_moments(ctx.map(partial(image_moment, ctx.ws.root, names), range(len(names))),
                                    options.descriptor_dims) if options.descriptor_dims else None)
        plan = plan.result()
    matched: dict[tuple[int, int], np.ndarray] = {}
    strict: dict[tuple[int, int], int] = {}  # per pair: its leading matches that pass the strict ratio
    with tqdm(total=len(plan.all_pairs), desc="matches", unit="pair") as bar:
        match = partial(_match_pairs, ctx, options, basis, matched, strict, bar)
        # The candidates matched whatever they find go with the other pairs (one round fewer of descriptor loads).
        first = first_loop_proposals(plan.loop_candidates, options.loop_patience)
        match(sorted([*plan.pairs, *first]))
        window_median = _window_median(matched, len(names), options.window)
        share = options.loop_min_share
        enough = lambda pair, m: len(m) >= share * min(window_median[list(pair)])  # noqa: E731
        loops, rounds = loop_rounds(plan.loop_candidates, options.loop_patience,
                                    lambda pairs: {p: enough(p, m) for p, m in zip(pairs, match(pairs))},
                                    found={p: enough(p, matched[p]) for p in first})
        bar.total = len(matched)
        bar.refresh()
    pairs = sorted(matched)
    per_pair = [matched[p] for p in pairs]
    ctx.out.save_matches(pairs, per_pair, num_strict=np.array([strict[p] for p in pairs], np.int64))
    counts = [len(m) for m in per_pair]
    sources = {**plan.summary, **({"loop_matched": len(loops), "loop_rounds": rounds}
                                  if "loop_candidates" in plan.summary else {})}
    return {"pairs": len(pairs), "pair_sources": sources,
            "median_matches": int(np.median(counts)) if counts else 0}


def _match_pairs(ctx: StageContext, options: MatchesOptions, basis: np.ndarray | None,
                 matched: dict[tuple[int, int], np.ndarray], strict: dict[tuple[int, int], int], bar,
                 pairs: list[tuple[int, int]]) -> list[np.ndarray]:
    """Match `pairs` in blocks on the stage's fan-out, recording each pair's matches in `matched` and how many of
    them lead at the strict ratio in `strict`."""
    names = ctx.dataset.image_names
    block_images = max(1, min(BLOCK_IMAGES, -(-len(names) // MIN_BLOCKS_PER_SIDE)))
    # Largest blocks first: the last tasks to start are small, so both threads finish together (at 6 images the
    # blocks hold 4, 4, 4, 1, 1, 1 pairs: 8 pair-times instead of 9 in index order; results land by pair index).
    blocks = sorted(pair_blocks(pairs, block_images), key=len, reverse=True)
    jobs = ctx.map(partial(match_block, ctx.ws.root, names, options, basis=basis),
                   [[pairs[k] for k in b] for b in blocks])
    for block, found in zip(blocks, jobs):
        for k, (m, num_strict) in zip(block, found):
            strict[pairs[k]] = num_strict
            matched[pairs[k]] = m.astype(np.int32)  # the stored format is int64; int32 halves what is held meanwhile
        bar.update(len(block))
    return [matched[p] for p in pairs]


def _window_median(matched: dict[tuple[int, int], np.ndarray], num_images: int, window: int) -> np.ndarray:
    """(N,) each image's median matches over its pairs within `window` capture steps that were matched (0 if none):
    what a loop candidate's matches are measured against."""
    counts: list[list[int]] = [[] for _ in range(num_images)]
    for (i, j), m in matched.items():
        if j - i <= window:
            counts[i].append(len(m))
            counts[j].append(len(m))
    return np.array([float(np.median(c)) if c else 0.0 for c in counts])


def image_moment(ws_root: Path, names: list[str], k: int) -> np.ndarray:
    """Image k's descriptor second moment, read from the workspace (a top-level function: a cluster task)."""
    return second_moment(Workspace(Path(ws_root).parent, Path(ws_root).name).load_descriptors(names[k]))


def match_block(ws_root: Path, names: list[str], options: MatchesOptions, pairs: list[tuple[int, int]], *,
                basis: np.ndarray | None = None) -> list[tuple[np.ndarray, int]]:
    """The matches of `pairs` and how many of them pass the strict ratio (`match_pair`), reading the features of their images from the workspace itself (a top-level function
    of picklable arguments: a cluster task of its own), searched on `basis`'s components when given."""
    ws = Workspace(Path(ws_root).parent, Path(ws_root).name)
    images = sorted({i for p in pairs for i in p})
    full = {i: ws.load_descriptors(names[i]) for i in images}
    noise = {i: float(ws.load_features(names[i], ("noise_sigma",))["noise_sigma"]) for i in images}
    if basis is None:
        return [match_pair(full[i], full[j], options, noise[i], noise[j]) for i, j in pairs]
    projected = {i: project_descriptors(d, basis) for i, d in full.items()}
    return [match_pair(projected[i], projected[j], options, noise[i], noise[j], full=(full[i], full[j]))
            for i, j in pairs]
