"""Parts of an averaged model whose relative scale the pair directions fix, and joining them by points.

Translation averaging knows baseline *directions* only. Where the view graph is not parallel rigid (room clusters
joined at one camera, or by pairs that fix no scale; ``flexible_modes`` > 0), the solver still returns centres —
λ ≥ 1 keeps the spacing sane — but the relative scale of the clusters is arbitrary, and a final bundle adjustment
does not repair it: the few tracks that span the join are triangulated with the wrong scale and discarded as
outliers before it runs.

So the layout is split into **rigid parts** (camera sets fixed up to one similarity by the directions among them;
a camera where two parts meet belongs to both) and the parts are joined to the largest one by the points they
share, as incremental SfM would do: rotations come from rotation averaging (one frame for all parts), so a join
has at most four unknowns — a scale and a shift — and only one, the scale about the camera, when the parts meet at a
camera. Each observation of a point triangulated on one side by a camera of the other side gives two linear
equations in them; the join is estimated robustly (every sample a minimal set, scored by angular error, refined on
its inliers) and kept only when enough distinct tracks agree. A part that cannot be joined is left out (it becomes
a model of its own later) rather than kept at a wrong scale. Pure geometry: no file access.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fullview.sfm.camera import normalize
from fullview.sfm.registration.translation_averaging import _block_system
from fullview.sfm.registration.view_graph import component_labels
from fullview.sfm.tracks import Tracks
from fullview.sfm.triangulation import gather_bearings

log = logging.getLogger(__name__)

RATE_TOLERANCE = 1e-5  # pairs whose scale rates under the flexible motions differ by less (relative) move as one
MIN_SCALE, MAX_SCALE = 0.1, 10.0  # a join's scale outside this range is a degenerate fit (a part collapsed onto
# its joint), not a measurement
JOIN_SAMPLES = 400  # RANSAC samples of a join with free shift (a join at a shared camera tries every observation)
MAX_SCALE_SPREAD = 0.05  # a join is kept when its scale is determined to this fraction by the threshold's noise
DISTINCT_SCALE = 0.1  # scales further apart than this (relative) are rival hypotheses ...
AMBIGUITY_RATIO = 2.0  # ... and the best must gather this many times the tracks a rival fits that it does not: one
# unknown fits a few chance matches (2D-3D matches through a doorway) at some scale, a true join stands out
HARD_WEIGHT = 1e3  # weight of the exact constraints of a join (shared camera, bridging pair) against point rows


def rigid_parts(centers: np.ndarray, pairs: np.ndarray, *, rel_tol: float = 1e-9) -> list[np.ndarray]:
    """Camera sets each fixed up to a similarity by the baseline directions of ``pairs`` (M, 2) among them, taken
    from ``centers``; largest first (ties: lowest camera). A camera where two parts meet is in both.

    The centre motions that keep every direction are the null space of ``Σ_p A_pᵀ (I − d_p d_pᵀ) A_p`` (as in
    ``flexible_modes``). A pair keeps its direction when its cameras' motions differ along it:
    ``v_j − v_i = b_p (c_j − c_i)``, so each pair has one rate ``b_p`` per flexible mode; inside a rigid part every
    motion is a similarity ``v = a + b c``, one rate for all its pairs. The parts are the groups of pairs, joined at a
    camera, whose rates agree — exact, unlike growing parts from triangles, which misses rigid cycles of parts."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    nodes, local = np.unique(pairs, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(nodes)
    c = np.asarray(centers, dtype=np.float64)[nodes]
    modes = _flexible_motions(c, local, rel_tol)
    if modes.shape[1] == 0:
        return [nodes]
    delta = c[local[:, 1]] - c[local[:, 0]]
    v = modes.reshape(n, 3, -1)
    rates = np.einsum("pa,pam->pm", delta, v[local[:, 1]] - v[local[:, 0]]) / np.einsum("pa,pa->p", delta,
                                                                                         delta)[:, None]
    tol = RATE_TOLERANCE * max(np.abs(rates).max(), 1e-12)
    labels = _group_pairs(local, rates, tol, n)
    parts = [np.unique(nodes[local[labels == g]]) for g in np.unique(labels)]
    return sorted(parts, key=lambda p: (-len(p), int(p[0])))


def _flexible_motions(c: np.ndarray, local: np.ndarray, rel_tol: float) -> np.ndarray:
    """(3n, f) orthonormal centre motions keeping every pair's direction, beyond translation and scale."""
    n = len(c)
    d = normalize(c[local[:, 1]] - c[local[:, 0]])
    P_perp = np.eye(3) - d[:, :, None] * d[:, None, :]
    K, _ = _block_system(local, np.arange(3 * n).reshape(n, 3), P_perp, np.zeros((len(local), 3)), n)
    ev, vec = np.linalg.eigh(K.toarray())
    null = vec[:, ev < rel_tol * max(np.abs(ev).max(), 1e-300)]
    similarity = np.concatenate([np.tile(np.eye(3), (n, 1)), (c - c.mean(0)).reshape(-1, 1)], axis=1)
    q, _ = np.linalg.qr(similarity)
    rest = null - q @ (q.T @ null)
    u, sv, _ = np.linalg.svd(rest, full_matrices=False)
    return u[:, sv > 1e-6]


def _group_pairs(local: np.ndarray, rates: np.ndarray, tol: float, n: int) -> np.ndarray:
    """(M,) group of each pair: pairs meeting at a camera with rates within ``tol`` are one group (the connected
    components of the graph whose nodes are the pairs)."""
    rates = rates.reshape(len(local), -1)
    links = []
    for camera in range(n):  # per camera, every two pairs meeting there
        at = np.flatnonzero((local == camera).any(axis=1))
        x, y = np.triu_indices(len(at), 1)
        close = np.abs(rates[at[x]] - rates[at[y]]).max(axis=1, initial=0.0) <= tol
        links.append(np.column_stack([at[x][close], at[y][close]]))
    links = np.concatenate(links) if links else np.zeros((0, 2), np.int64)
    return component_labels(len(local), links, np.ones(len(links), bool))


@dataclass(kw_only=True)
class Join:
    scale: float  # part coordinates x map to scale * x + shift in the main frame
    shift: np.ndarray  # (3,)
    num_tracks: int  # distinct tracks whose observations agree with it
    num_observations: int  # cross observations it was estimated from
    confirmed: bool = False  # the points confirm the placement averaging gave (no change)


def estimate_join(*, R_cam_from_world: np.ndarray, centers: np.ndarray, main: np.ndarray, part: np.ndarray,
                  main_points: tuple[np.ndarray, np.ndarray], part_points: tuple[np.ndarray, np.ndarray],
                  tracks: Tracks, bearings: Sequence[np.ndarray], pairs: np.ndarray, directions: np.ndarray,
                  threshold_rad: float, min_tracks: int, seed: int, extra=None, kept: np.ndarray | None = None
                  ) -> Join | None:
    """Scale and shift taking the cameras of ``part`` (N,) bool into the frame of ``main`` (N,) bool, both in the
    rotation frame of ``R_cam_from_world``; None when fewer than ``min_tracks`` tracks agree.

    ``main_points`` / ``part_points``: (points, point_of_track) triangulated by each side alone. ``pairs`` (M, 2)
    with world ``directions`` (M, 3) ∝ c_j − c_i: the used pairs, whose directions between the sides must hold
    (with a camera shared by both sides, they fix the shift but for the scale about it). ``extra``: more cross
    observations (world ray, point, camera centre, whether the point is the part's, point id), e.g. from 2D-3D
    matching. ``kept`` (4,): (scale, shift) of the placement averaging gave the part; when the points agree with it
    about as well as with any other (``AMBIGUITY_RATIO``), it is confirmed rather than replaced (a handful of tracks
    seen through a doorway fit loosely, and averaging's spacing is usually near the truth)."""
    rows = _cross_observations(R_cam_from_world, centers, main, part, main_points, part_points, tracks, bearings)
    if extra is not None:
        rows = extra if rows is None else tuple(np.concatenate(c) for c in zip(rows, extra))
    if rows is None:
        return None
    u, point, camera, moved_point, track = rows
    hard_A, hard_b = _hard_constraints(centers, main, part, pairs, directions)
    A, b = _point_rows(u, point, camera, moved_point)
    rank = np.linalg.matrix_rank(hard_A) if len(hard_A) else 0
    sample_size = 1 if rank >= 2 else 2
    if len(u) < sample_size:
        return None
    samples = _samples(len(u), sample_size, seed)
    best, best_inliers = None, np.zeros(len(u), bool)
    hypotheses = []  # (scale, inlier mask) of every sample, for the ambiguity check
    for sample in samples:
        x = _solve(hard_A, hard_b, A.reshape(-1, 3, 4)[sample].reshape(-1, 4), b.reshape(-1, 3)[sample].ravel())
        if x is None:
            continue
        inliers = _errors(x, u, point, camera, moved_point) <= threshold_rad
        hypotheses.append((x[0], inliers))
        if inliers.sum() > best_inliers.sum():
            best, best_inliers = x, inliers
    if kept is not None:
        kept_inliers = _errors(kept, u, point, camera, moved_point) <= threshold_rad
        kept_tracks = len(np.unique(track[kept_inliers]))
        best_tracks = len(np.unique(track[best_inliers]))
        if kept_tracks >= min_tracks and AMBIGUITY_RATIO * kept_tracks >= best_tracks:
            log.info("part of %d camera(s): %d tracks confirm averaging's placement (best other scale: %d tracks)",
                     part.sum(), kept_tracks, best_tracks)
            return Join(scale=1.0, shift=kept[1:].copy(), num_tracks=kept_tracks, num_observations=len(u),
                        confirmed=True)
        hypotheses.append((1.0, kept_inliers))
    if best is None:
        return None
    log.debug("join of %d cameras: hard rows %d (rank %d), %d observations, best %s with %d inliers", part.sum(),
              len(hard_A), rank, len(u), np.round(best, 3), best_inliers.sum())
    for _ in range(3):  # refit on the inliers, rows weighted to angles by the current distances
        w = 1.0 / np.maximum(_distances(best, point, camera, moved_point), 1e-9)
        x = _solve(hard_A, hard_b, (A.reshape(-1, 3, 4) * w[:, None, None])[best_inliers].reshape(-1, 4),
                   (b.reshape(-1, 3) * w[:, None])[best_inliers].ravel())
        if x is None:
            break
        inliers = _errors(x, u, point, camera, moved_point) <= threshold_rad
        if inliers.sum() < best_inliers.sum():
            break
        best, best_inliers = x, inliers
    agreeing = len(np.unique(track[best_inliers]))
    rival = max((len(np.unique(track[inl & ~best_inliers])) for sc, inl in hypotheses
                 if abs(np.log(sc / best[0])) > np.log(1.0 + DISTINCT_SCALE)), default=0)
    if agreeing < AMBIGUITY_RATIO * rival:
        log.info("part of %d camera(s) not joined: scale %.3f (%d tracks) and another scale (%d tracks) both fit",
                 part.sum(), best[0], agreeing, rival)
        return None
    spread = _scale_spread(best, hard_A, A, u, point, camera, moved_point, best_inliers) * threshold_rad
    if not spread <= MAX_SCALE_SPREAD * best[0]:
        log.info("part of %d camera(s) not joined: its scale is undetermined (%.3f ± %.3f from %d tracks)",
                 part.sum(), best[0], spread, agreeing)
        return None
    if agreeing < min_tracks:
        log.info("part of %d camera(s) not joined: %d track(s) agree on a scale (%d needed), %d cross observations",
                 part.sum(), agreeing, min_tracks, len(u))
        return None
    return Join(scale=float(best[0]), shift=best[1:].copy(), num_tracks=agreeing, num_observations=len(u))


def _scale_spread(x, hard_A, A, u, point, camera, moved_point, inliers) -> float:
    """Standard deviation of the scale per radian of angular noise on the inlier rays (linearised least squares):
    far points or rays through the joint leave the scale loose even when they all agree."""
    w = 1.0 / np.maximum(_distances(x, point, camera, moved_point), 1e-9)
    M = np.concatenate([hard_A, (A.reshape(-1, 3, 4) * w[:, None, None])[inliers].reshape(-1, 4)])
    try:
        return float(np.sqrt(max(np.linalg.inv(M.T @ M)[0, 0], 0.0)))
    except np.linalg.LinAlgError:
        return np.inf


def _cross_observations(R, C, main, part, main_points, part_points, tracks: Tracks, bearings):
    """Observations across the join: main's points seen by the part's own cameras, and the part's points seen by
    main's own cameras. Returns (world ray u, point, camera centre, moved_point flag, track) per observation."""
    own_part = part & ~main
    own_main = main & ~part
    chunks = []
    for (X, of_track), cams, moved in ((main_points, own_part, False), (part_points, own_main, True)):
        sel = cams[tracks.image_ids] & (of_track[tracks.track_ids] >= 0)
        if not sel.any():
            continue
        images = tracks.image_ids[sel]
        z = gather_bearings(bearings, images, tracks.feature_ids[sel])
        u = np.einsum("kba,kb->ka", R[images], z)  # R_camᵀ z: world ray
        chunks.append((u, X[of_track[tracks.track_ids[sel]]], C[images], np.full(sel.sum(), moved),
                       tracks.track_ids[sel]))
    if not chunks:
        return None
    return tuple(np.concatenate(c) for c in zip(*chunks))


def _point_rows(u, point, camera, moved_point):
    """Per observation, three rows (rank 2) of A x = b in x = (s, shift): the ray from the camera through the point,
    with the part's side mapped by x → s x + shift.

    Part camera c seeing main point X: u × (X − s c − shift) = 0. Main camera c seeing part point Y:
    u × (s Y + shift − c) = 0."""
    ux = _skew(u)  # [u]_× v = u × v
    moving = np.where(moved_point[:, None], point, camera)
    fixed = np.where(moved_point[:, None], camera, point)
    A = np.concatenate([np.cross(u, moving)[:, :, None], ux], axis=2)  # (K, 3, 4): s u × m + u × shift
    b = np.cross(u, fixed)
    return A.reshape(-1, 4), b.ravel()


def _hard_constraints(C, main, part, pairs, directions):
    """Rows that must hold exactly (weighted HARD_WEIGHT): a camera in both sides stays where it is
    (s c + shift = c), and a used pair between the sides keeps its direction (d × (s c_j + shift − c_i) = 0)."""
    rows, rhs = [], []
    for c in np.flatnonzero(main & part):
        rows.append(np.column_stack([C[c], np.eye(3)]))
        rhs.append(C[c])
    i, j = pairs[:, 0], pairs[:, 1]
    for k in np.flatnonzero((main[i] & ~main[j] & part[j]) | (main[j] & ~main[i] & part[i])):
        a, p, d = (i[k], j[k], directions[k]) if main[i[k]] else (j[k], i[k], -directions[k])
        rows.append(np.concatenate([np.cross(d, C[p])[:, None], _skew(d[None])[0]], axis=1))
        rhs.append(np.cross(d, C[a]))
    if not rows:
        return np.zeros((0, 4)), np.zeros(0)
    scale = max(np.abs(C[main | part]).max(), 1e-9)  # hard rows in the units of the point rows (≈ distances)
    return HARD_WEIGHT * np.concatenate(rows) / scale, HARD_WEIGHT * np.concatenate(rhs) / scale


def _skew(v: np.ndarray) -> np.ndarray:
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def _samples(n: int, size: int, seed: int) -> np.ndarray:
    if size == 1:
        return np.arange(n)[:, None]
    rng = np.random.default_rng(seed)
    first = rng.integers(0, n, JOIN_SAMPLES)
    second = (first + rng.integers(1, n, JOIN_SAMPLES)) % n if n > 1 else first
    return np.column_stack([first, second])


def _solve(hard_A, hard_b, A, b) -> np.ndarray | None:
    M, y = np.concatenate([hard_A, A]), np.concatenate([hard_b, b])
    x, _, rank, _ = np.linalg.lstsq(M, y, rcond=None)
    if rank < 4 or not np.isfinite(x).all() or not MIN_SCALE <= x[0] <= MAX_SCALE:
        return None
    return x


def _mapped(x, point, camera, moved_point):
    """(ray origin, point) of every observation after mapping the part's side by x."""
    s, shift = x[0], x[1:]
    origin = np.where(moved_point[:, None], camera, s * camera + shift)
    target = np.where(moved_point[:, None], s * point + shift, point)
    return origin, target


def _errors(x, u, point, camera, moved_point) -> np.ndarray:
    origin, target = _mapped(x, point, camera, moved_point)
    v = normalize(target - origin)
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ka,ka->k", u, v))


def _distances(x, point, camera, moved_point) -> np.ndarray:
    origin, target = _mapped(x, point, camera, moved_point)
    return np.linalg.norm(target - origin, axis=1)
