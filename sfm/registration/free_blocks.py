"""Blocks of a final model whose relative scale no track fixes, and their re-scaling to a common step.

After the final bundle adjustment a model can still consist of *blocks* that meet at one camera and share no
track: rooms joined through a doorway camera that sees one room's points and the other room's, never a point of
both (bare 1024 px home seed 0: one of camera 12's 1,273 features has a true match on both sides). The scale of
such a block about its junction camera leaves every reprojection error unchanged, so the adjustment keeps whatever
registration guessed part by part (a median over the 3-5 pairs of a small part, 5-20% off) and chained guesses
compound. Here each block is found as a biconnected component of the graph "two cameras share a track"; its
junctions are the articulation cameras. Every block with enough verified pairs is scaled about its junction so
that its cameras' median height above the floor equals that of the block with the most pairs (a tripod keeps the
height: it measures the scale), or where either block's floor is not seen, so that its median verified-pair
baseline equals that block's (rooms of one capture are walked with similar steps, but they vary by 10-40% between
blocks). Cameras and points move together, so the adjustment's cost is exactly the same. Pure geometry: no file
access.
"""

from __future__ import annotations

import numpy as np


def camera_links(track_ids: np.ndarray, image_ids: np.ndarray) -> np.ndarray:
    """(E, 2) distinct camera pairs (i < j) that observe a common track, from the observations' track and image."""
    order = np.lexsort((image_ids, track_ids))
    track_ids, image_ids = track_ids[order], image_ids[order]
    starts = np.flatnonzero(np.r_[True, track_ids[1:] != track_ids[:-1]])
    lengths = np.diff(np.r_[starts, len(track_ids)])
    n = int(image_ids.max(initial=0)) + 1
    codes = [np.zeros(0, np.int64)]
    for length in np.unique(lengths[lengths >= 2]):  # tracks of one length at a time: all their camera pairs at once
        cams = image_ids[starts[lengths == length][:, None] + np.arange(length)]
        a, b = np.triu_indices(length, k=1)
        lo, hi = np.minimum(cams[:, a], cams[:, b]).ravel(), np.maximum(cams[:, a], cams[:, b]).ravel()
        codes.append(np.unique(lo[lo != hi] * n + hi[lo != hi]))  # a pair as one integer: unique is a 1-D sort
    codes = np.unique(np.concatenate(codes))
    return np.stack([codes // n, codes % n], axis=1)


def biconnected_blocks(num_images: int, links: np.ndarray) -> list[np.ndarray]:
    """Camera sets of the biconnected components of the link graph (Tarjan, iterative); a camera in two of them is
    an articulation camera: removing it separates them."""
    adjacency = [[] for _ in range(num_images)]
    for a, b in links:
        adjacency[a].append(int(b))
        adjacency[b].append(int(a))
    disc, low = np.full(num_images, -1), np.zeros(num_images, np.int64)
    blocks, edges, time = [], [], 0
    for root in range(num_images):
        if disc[root] >= 0 or not adjacency[root]:
            continue
        disc[root] = low[root] = time
        time += 1
        stack = [(root, -1, iter(adjacency[root]))]
        while stack:
            v, parent, neighbours = stack[-1]
            w = next(neighbours, None)
            if w is None:
                stack.pop()
                if parent >= 0:
                    low[parent] = min(low[parent], low[v])
                    if low[v] >= disc[parent]:  # parent separates v's subtree: its edges form one block
                        block = set()
                        while True:
                            edge = edges.pop()
                            block.update(edge)
                            if edge == (parent, v):
                                break
                        blocks.append(np.array(sorted(block)))
            elif disc[w] < 0:
                disc[w] = low[w] = time
                time += 1
                edges.append((v, w))
                stack.append((w, v, iter(adjacency[w])))
            elif w != parent and disc[w] < disc[v]:
                edges.append((v, w))
                low[v] = min(low[v], disc[w])
    return blocks


# Camera heights above the floor (`camera_heights`): the floor is the lowest surface a camera sees, so its height is
# the farthest-down cluster of the points it sees below the horizon; a cluster is the points within a relative
# WINDOW below its top, at least MIN_FLOOR_POINTS of them (fewer are stray points under the floor, or no floor).
FLOOR_WINDOW = 0.03
MIN_FLOOR_POINTS = 5
FLOOR_MIN_ELEVATION_DEG = 15.0  # points less steeply below the horizon are mostly walls and furniture
# A block's height is the median over its cameras (junctions left out: they see two blocks' points) that measure one;
# fewer than this and the block's scale falls back to the median baseline.
MIN_HEIGHT_CAMERAS = 3


def camera_heights(centers: np.ndarray, down: np.ndarray, points: np.ndarray, track_ids: np.ndarray,
                   image_ids: np.ndarray) -> np.ndarray:
    """(N,) each camera's height above the floor in the model's units (nan where no floor is seen), from the points
    it observes (`points[track_ids]` seen by `image_ids`) and its model's down direction `down` (N, 3), unit.

    On the bare 1024 px home seed 0 the floor's points (markers, the furniture's feet) give all 30 cameras' heights
    within 1% of the truth times their local model scale, where the densest cluster is often a furniture top: hence
    the lowest cluster with enough points, not the largest. At 2048 px furniture tops still win on a third of the
    cameras, so blocks compare medians."""
    return floor_clusters(centers, down, points, track_ids, image_ids)[2]


def floor_clusters(centers: np.ndarray, down: np.ndarray, points: np.ndarray, track_ids: np.ndarray,
                   image_ids: np.ndarray, min_points: int = MIN_FLOOR_POINTS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each camera's floor points: (camera (F,), point (F,), height (N,)) with the camera's height above them (the
    median depth of its floor cluster of at least `min_points` along `down` (N, 3), nan where no floor is seen or
    `down` is nan)."""
    n = len(centers)
    heights = np.full(n, np.nan)
    cams, pts = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    order = np.argsort(image_ids, kind="stable")
    starts = np.searchsorted(image_ids[order], np.arange(n + 1))
    slope = np.tan(np.radians(FLOOR_MIN_ELEVATION_DEG))
    for c in range(n):
        if not np.isfinite(down[c]).all():
            continue
        seen = np.unique(track_ids[order[starts[c]:starts[c + 1]]])
        v = points[seen] - centers[c]
        d = v @ down[c]
        below = d > slope * np.linalg.norm(v - d[:, None] * down[c], axis=1)
        seen, d = seen[below], d[below]
        sort = np.argsort(d)
        seen, d = seen[sort], d[sort]
        count = np.searchsorted(d, d, side="right") - np.searchsorted(d, (1.0 - FLOOR_WINDOW) * d, side="left")
        enough = np.flatnonzero(count >= min_points)
        if len(enough):
            top = d[enough[-1]]
            floor = (d <= top) & (d >= (1.0 - FLOOR_WINDOW) * top)
            heights[c] = np.median(d[floor])
            cams.append(np.full(floor.sum(), c))
            pts.append(seen[floor])
    return np.concatenate(cams), np.concatenate(pts), heights


def free_block_similarities(centers: np.ndarray, links: np.ndarray, pairs: np.ndarray, min_pairs: int,
                            heights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per camera the similarity x -> scale·x + shift that puts every block with at least `min_pairs` verified
    pairs (`pairs` (P, 2)) inside it at the median baseline of its component's block with the most verified pairs
    (the root), scaled about the junction camera it hangs from (its subtree of blocks moving with it), and the
    camera's depth in the tree of blocks (0: the root, -1: no link). With `heights` (N,) (`camera_heights`), a block
    whose cameras and the root's both measure one gets the root's median camera height instead (a tripod keeps the
    height, where the steps of a walk vary by tens of per cent). A track lies in one block: its points move with its
    deepest camera. A root with fewer than `min_pairs` pairs scales nothing. Returns (scale (N,), shift (N, 3),
    depth (N,))."""
    n = len(centers)
    scale, shift, depth = np.ones(n), np.zeros((n, 3)), np.full(n, -1)
    # the block with the most verified pairs sets the step: its median is the steadiest
    blocks = sorted(biconnected_blocks(n, links), key=lambda b: (len(_inner_pairs(b, pairs)), len(b)), reverse=True)
    junctions = np.bincount(np.concatenate(blocks), minlength=n) > 1 if blocks else np.zeros(n, bool)
    h = np.full(n, np.nan) if heights is None else np.where(junctions, np.nan, heights)
    C = centers.copy()
    placed = np.zeros(len(blocks), bool)
    for root in range(len(blocks)):
        if placed[root] or (depth[blocks[root]] >= 0).any():
            continue  # a block of a component already rooted
        placed[root] = True
        depth[blocks[root]] = 0
        reference = _median_baseline(C, blocks[root], pairs) if len(_inner_pairs(blocks[root], pairs)) >= min_pairs \
            else np.nan
        reference_height = _median_height(h, blocks[root]) if np.isfinite(reference) else np.nan
        queue = [root]
        while queue:
            parent = queue.pop(0)
            for k in np.flatnonzero(~placed):
                junction = np.intersect1d(blocks[k], blocks[parent])
                if not len(junction):
                    continue
                placed[k] = True
                queue.append(k)
                v, members = junction[0], blocks[k][blocks[k] != junction[0]]
                depth[members] = depth[v] + 1
                own = _median_baseline(C, blocks[k], pairs) if len(_inner_pairs(blocks[k], pairs)) >= min_pairs \
                    else np.nan
                s = reference / own if np.isfinite(reference) and np.isfinite(own) and own > 0 else 1.0
                own_height = _median_height(h * scale, blocks[k])  # the heights as moved so far
                if np.isfinite(own) and np.isfinite(reference_height) and np.isfinite(own_height):
                    s = reference_height / own_height
                # the block's whole subtree moves: cameras not yet placed that this block reaches without v
                moving = _subtree(blocks, k, v, placed)
                C[moving] = C[v] + s * (C[moving] - C[v])
                scale[moving] *= s
                shift[moving] = C[v] + s * (shift[moving] - C[v])
    return scale, shift, depth


def _median_height(heights: np.ndarray, cameras: np.ndarray) -> float:
    known = heights[cameras][np.isfinite(heights[cameras])]
    return float(np.median(known)) if len(known) >= MIN_HEIGHT_CAMERAS and np.median(known) > 0 else np.nan


def _inner_pairs(cameras: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    return pairs[np.isin(pairs, cameras).all(axis=1)]


def _median_baseline(C: np.ndarray, cameras: np.ndarray, pairs: np.ndarray) -> float:
    inner = _inner_pairs(cameras, pairs)
    return float(np.median(np.linalg.norm(C[inner[:, 1]] - C[inner[:, 0]], axis=1))) if len(inner) else np.nan


def _subtree(blocks: list[np.ndarray], k: int, junction: int, placed: np.ndarray) -> np.ndarray:
    """Cameras of block k and of the blocks beyond it (not yet placed, reached through k without the junction)."""
    cameras = set(blocks[k].tolist()) - {int(junction)}
    grown = True
    taken = {k}
    while grown:
        grown = False
        for b, block in enumerate(blocks):
            if b in taken or placed[b] and b != k:
                continue
            if cameras & set(block.tolist()):
                cameras |= set(block.tolist())
                taken.add(b)
                grown = True
    return np.array(sorted(cameras - {int(junction)}), np.int64)
