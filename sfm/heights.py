"""The camera-height prior of a tripod tour: every camera of a model at one height above the floor.

Why. A chain of rooms joined through doorways is held together by the tracks that cross each doorway; where only
two-view tracks cross (they fix the direction between the two cameras, not its length), the scale of the rooms
beyond rests on the one or two longer tracks that happen to cross, and the bundle adjustment keeps whatever scale
registration guessed (a scale error of tens of per cent between the rooms on either side of such a doorway: one
long track pins it only to its own triangulation error). A tripod keeps its height, and each camera sees the floor below it in its own
room's scale: its height above its floor points is a measurement of the local scale. Holding every camera's height
to its model's common height inside the adjustment carries one scale through every doorway.

Residuals. For camera i and each point f of its floor (`floor_rows`), ``r = w_i (d · (X_f − C_i) − h)``: ``d`` the
model's down direction, ``h`` the model's common height (re-estimated between reweighting rounds, as the gravity
prior's up direction), ``w_i = σ_obs / (σ_h h √n_i)`` so that camera i's n_i rows weigh as one height measured to
the relative standard error σ_h. One camera and one point per row: in the adjustment they are rows like the
bearings' (`bundle._height_residuals`), eliminated with the points.

Robustness (only where the data support it). A camera's floor is the farthest-down cluster of the points it sees
steeply below the horizon (`free_blocks.camera_heights`' rule); a camera whose height is far from the cameras it
shares many tracks with (the same room, the same local scale) took a furniture top and gets no rows; a model with
too few cameras measuring a floor gets none; and after the pose round, a model whose adjusted heights still
disagree (a hand-held capture, a split-level home) gets no prior in the final adjustment (`height_spread`).
Pure geometry: no file access.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix

from fullview.sfm.registration.free_blocks import MIN_FLOOR_POINTS, biconnected_blocks, camera_links, floor_clusters

# A camera whose floor height differs by more than this (relative, log scale) from the median of the cameras it
# shares NEIGHBOUR_TRACKS tracks with took something else for the floor: 3.6 times a camera's own spread (5 cm at
# 1.5 m, 0.033: `triangulation.height_prior_sigma`), while the lowest furniture top taken for the floor (a sofa
# seat, 0.45 m, under a 1.5 m camera) is log(1.5 / 1.05) = 0.36 off.
MAX_NEIGHBOUR_DEVIATION = 0.12
NEIGHBOUR_TRACKS = 20
# A model gets the prior only when at least this many of its cameras, and this share of them, measure a floor.
MIN_CAMERAS = 4
MIN_SHARE = 0.5


@dataclass(frozen=True, kw_only=True)
class HeightPrior:
    """Floor rows of a bundle adjustment: camera `camera[k]` stands `level` above point `point[k]` along `down`."""

    camera: np.ndarray  # (F,) camera index of each row
    point: np.ndarray  # (F,) point index of each row (a floor point the camera observes)
    down_world: np.ndarray  # (F, 3) the row's model's down direction, world coordinates, unit
    group: np.ndarray  # (F,) rows of one group (one model) share one height
    sigma_rel: float  # relative standard error of one camera's height (tripod and floor together)


# Each camera's floor points and height: the free blocks' rule (`free_blocks.floor_clusters`, at least
# MIN_FLOOR_POINTS points in a cluster).
floor_rows = floor_clusters


def shared_tracks(track_ids: np.ndarray, image_ids: np.ndarray, n: int) -> np.ndarray:
    """(N, N) how many tracks each two cameras both observe."""
    tracks = int(track_ids.max(initial=-1)) + 1
    incidence = csr_matrix((np.ones(len(track_ids)), (image_ids, track_ids)), shape=(n, tracks))
    incidence.data[:] = 1.0  # a camera seeing a track twice counts once
    return np.rint((incidence @ incidence.T).toarray()).astype(np.int64)


def rigid_tracks(track_ids: np.ndarray, image_ids: np.ndarray, n: int) -> np.ndarray:
    """(T,) tracks inside a block of three or more cameras (`free_blocks.biconnected_blocks` of the cameras that
    share a track). The others lie in a block of two cameras that only two-view tracks join (a doorway): the
    bearings leave that pair's baseline length free, and floor rows on its points (seen by both, each camera at its
    own height) would set the length from the two heights' difference, a few cm of height noise over a baseline
    that nothing else measures: the length then follows the noise."""
    order = np.lexsort((image_ids, track_ids))
    tracks, cams = track_ids[order], image_ids[order]
    first = np.r_[True, tracks[1:] != tracks[:-1]]
    rigid = np.zeros(int(track_ids.max(initial=-1)) + 1, bool)
    big = [b for b in biconnected_blocks(n, camera_links(track_ids, image_ids)) if len(b) >= 3]
    if not big:
        return rigid
    member = np.zeros((len(big), n), bool)
    for k, block in enumerate(big):
        member[k, block] = True
    # a track is rigid when some big block holds all its cameras: its first and last camera (sorted) and all between
    inside = member[:, cams]  # (B, observations)
    starts = np.flatnonzero(first)
    counts = np.add.reduceat(inside.astype(np.int64), starts, axis=1)  # (B, tracks present)
    lengths = np.diff(np.r_[starts, len(cams)])
    rigid[tracks[starts]] = (counts == lengths[None, :]).any(axis=0)
    return rigid


def consistent_cameras(heights: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """(N,) cameras whose height agrees with the median height of the cameras they share NEIGHBOUR_TRACKS or more
    tracks with (same room, same local scale), within MAX_NEIGHBOUR_DEVIATION; a camera without such a neighbour
    that measures a floor is kept (nothing to check it against)."""
    ok = np.isfinite(heights) & (heights > 0)
    keep = ok.copy()
    for c in np.flatnonzero(ok):
        near = (shared[c] >= NEIGHBOUR_TRACKS) & ok
        near[c] = False
        if near.any():
            keep[c] = abs(np.log(heights[c] / np.median(heights[near]))) <= MAX_NEIGHBOUR_DEVIATION
    return keep


def height_prior(centers: np.ndarray, down: np.ndarray, points: np.ndarray, track_ids: np.ndarray,
                 image_ids: np.ndarray, model_id: np.ndarray, sigma_rel: float) -> HeightPrior | None:
    """The floor rows of every model whose cameras measure a floor often enough (MIN_CAMERAS, MIN_SHARE), without
    the cameras that disagree with their room (`consistent_cameras`). None when no model qualifies."""
    camera, point, heights = floor_rows(centers, down, points, track_ids, image_ids)
    keep = consistent_cameras(heights, shared_tracks(track_ids, image_ids, len(centers)))
    rigid = rigid_tracks(track_ids, image_ids, len(centers))
    camera, point = camera[rigid[point]], point[rigid[point]]
    for model in np.unique(model_id[model_id >= 0]):
        members = model_id == model
        measured = int((keep & members).sum())
        if measured < max(MIN_CAMERAS, MIN_SHARE * members.sum()):
            keep[members] = False
    rows = keep[camera]
    if not rows.any():
        return None
    camera, point = camera[rows], point[rows]
    return HeightPrior(camera=camera, point=point, down_world=down[camera], group=model_id[camera],
                       sigma_rel=float(sigma_rel))


def height_spread(centers: np.ndarray, points: np.ndarray, prior: HeightPrior) -> float:
    """The largest robust relative spread (1.4826 · median absolute deviation of log height) of the cameras' heights
    above their floor rows, over the prior's models: about σ_h on a tripod tour once adjusted."""
    depth = np.einsum("fi,fi->f", points[prior.point] - centers[prior.camera], prior.down_world)
    spread = 0.0
    for group in np.unique(prior.group):
        rows = prior.group == group
        cams, index = np.unique(prior.camera[rows], return_inverse=True)
        h = np.bincount(index, depth[rows]) / np.bincount(index)
        if len(cams) >= 2 and (h > 0).all():
            logs = np.log(h)
            spread = max(spread, 1.4826 * float(np.median(np.abs(logs - np.median(logs)))))
    return spread


# A bridge's own points (its two-view tracks) on the floor measure its length: scaling the bridge scales them about
# the near camera, and both cameras stand the model's common height above the floor. A cluster of this many points
# below both (the free blocks' floor rule) suffices: a doorway's floor is small.
BRIDGE_MIN_FLOOR_POINTS = 3
BRIDGE_FLOOR_AGREEMENT = 0.05  # the two cameras' depths of those points agree to this (relative): one floor
BRIDGE_MAX_CHANGE = 2.0  # a floor asking for a larger change of the length than this factor is not the floor


def model_levels(centers: np.ndarray, points: np.ndarray, prior: HeightPrior, model_id: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) each camera's model's common height above the floor (the median over the model's cameras of their mean
    floor-row depth, as the adjustment's level) and (N, 3) its model's down; nan where the model has no rows."""
    level, down = np.full(len(centers), np.nan), np.full((len(centers), 3), np.nan)
    depth = np.einsum("fi,fi->f", points[prior.point] - centers[prior.camera], prior.down_world)
    for group in np.unique(prior.group):
        rows = prior.group == group
        _, index = np.unique(prior.camera[rows], return_inverse=True)
        level[model_id == group] = np.median(np.bincount(index, depth[rows]) / np.bincount(index))
        down[model_id == group] = prior.down_world[np.flatnonzero(rows)[0]]
    return level, down


def bridge_floor_scale(centers: np.ndarray, points: np.ndarray, own: np.ndarray, near: int, far: int,
                       level: float, down: np.ndarray) -> float | None:
    """The factor λ on bridge near-far's length that puts its own floor points (`own`: its two-view tracks; the
    farthest-down cluster of at least BRIDGE_MIN_FLOOR_POINTS seen steeply below both cameras) at the model's common
    height `level` below both: moving the far side along the bridge scales those points about the near camera, and
    so their depth below either camera, by λ. None without such a floor, where the two cameras' depths disagree, or
    where λ is beyond BRIDGE_MAX_CHANGE."""
    if not (np.isfinite(level) and level > 0 and len(own)):
        return None
    track_ids = np.concatenate([own, own])
    image_ids = np.repeat(np.array([near, far]), len(own))
    _, _, h = floor_clusters(centers, np.broadcast_to(down, centers.shape), points, track_ids, image_ids,
                             min_points=BRIDGE_MIN_FLOOR_POINTS)
    h = h[[near, far]]
    if not (np.isfinite(h).all() and (h > 0).all() and abs(np.log(h[0] / h[1])) <= BRIDGE_FLOOR_AGREEMENT):
        return None
    scale = level / float(np.mean(h))
    return scale if 1.0 / BRIDGE_MAX_CHANGE <= scale <= BRIDGE_MAX_CHANGE else None


def restore_bridges(centers_before: np.ndarray, centers: np.ndarray, points: np.ndarray, track_ids: np.ndarray,
                    image_ids: np.ndarray, roots: np.ndarray, level: np.ndarray | None = None,
                    down: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Cameras and points with every bridge's baseline back at its length in `centers_before`: a bridge is two
    cameras that only two-view tracks join (a block of two, `free_blocks.biconnected_blocks`), so the bearings leave
    its length free. Levenberg-Marquardt's diagonal damping lets the large steps of the height prior leak into that
    free direction (a free length costs nothing, so the damping does not hold it: it can shrink to nothing); the
    length is not
    measured by the bearings, so it goes back to where registration put it, unless its own points show the floor
    below both cameras: with `level` and `down` ((N,) and (N, 3), `model_levels`) the length is then the one that
    puts that floor at the model's camera height (`bridge_floor_scale`: the camera height is a length both sides
    measure). The side away from `roots` (each model's fixed camera) moves along the bridge, its tracks with
    it, the bridge's own points scale about the near camera: no bearing changes. Returns (centers, points, bridges,
    bridges whose length the floor set)."""
    n = len(centers)
    links = camera_links(track_ids, image_ids)
    bridges = [b for b in biconnected_blocks(n, links) if len(b) == 2]
    if not bridges:
        return centers, points, 0, 0
    centers, points = centers.copy(), points.copy()
    adjacency = [set() for _ in range(n)]
    for a, b in links:
        adjacency[a].add(int(b)), adjacency[b].add(int(a))
    order = np.lexsort((image_ids, track_ids))
    cams = image_ids[order]
    starts = np.flatnonzero(np.r_[True, track_ids[order][1:] != track_ids[order][:-1]])
    track_of, lengths = track_ids[order][starts], np.diff(np.r_[starts, len(cams)])
    depth = _hops(adjacency, roots, n)
    measured = 0
    for i, j in sorted(bridges, key=lambda b: min(depth[b[0]], depth[b[1]])):
        near, far = (i, j) if depth[i] <= depth[j] else (j, i)
        before = np.linalg.norm(centers_before[far] - centers_before[near])
        now = np.linalg.norm(centers[far] - centers[near])
        if not (now > 0 and before > 0):
            continue
        own = np.add.reduceat(((cams == near) | (cams == far)).astype(np.int64), starts) == lengths
        own &= np.add.reduceat((cams == near).astype(np.int64), starts) > 0
        own &= np.add.reduceat((cams == far).astype(np.int64), starts) > 0
        floor = None if level is None or down is None else bridge_floor_scale(
            centers, points, track_of[own], near, far, level[near], down[near])
        if floor is not None:
            before, measured = floor * now, measured + 1
        side = _side(adjacency, far, near)
        shift = (before / now - 1.0) * (centers[far] - centers[near])
        centers[side] += shift
        in_side = np.isin(cams, side)
        inside = np.add.reduceat(in_side.astype(np.int64), starts) == lengths
        points[track_of[inside]] += shift
        points[track_of[own]] = centers[near] + before / now * (points[track_of[own]] - centers[near])
    return centers, points, len(bridges), measured


def _hops(adjacency, roots, n: int) -> np.ndarray:
    """Link-graph distance of every camera from the nearest root (n where unreachable)."""
    depth = np.full(n, n)
    frontier = [int(r) for r in roots]
    depth[frontier] = 0
    while frontier:
        nxt = []
        for v in frontier:
            for w in adjacency[v]:
                if depth[w] > depth[v] + 1:
                    depth[w] = depth[v] + 1
                    nxt.append(w)
        frontier = nxt
    return depth


def _side(adjacency, start: int, cut: int) -> np.ndarray:
    """Cameras reached from `start` without passing `cut`'s link to it (the far side of a bridge)."""
    seen, stack = {start}, [start]
    while stack:
        v = stack.pop()
        for w in adjacency[v]:
            if w not in seen and not (v == start and w == cut):
                seen.add(w)
                stack.append(w)
    return np.array(sorted(seen), np.int64)
