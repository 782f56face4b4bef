"""Two models joined by the pairs between them that are too weak to verify alone, when several agree.

Where rooms of two panoramas each are walked through doorways, the doorway pair is often the only pair that could
join two rooms, and on plain walls it holds about ten true matches among thirty or forty raw ones: below the upright
fit's `filter.min_inliers_upright`, at the level chance fits reach (8-13 inliers at 1024 px). The home then falls
apart into separate models (measured on new bare homes of 15-16 rooms with two panoramas per room: 28 + 4, 20 + 12).

One weak pair alone cannot be told from chance, but the pairs around a doorway see the same opening: each pair
between model b and model a that the upright fit gives enough inliers implies the rotation of b's frame into a's
(`M = R_lᵀ R_lk R_k`). Chance fits imply rotations spread over all yaws; the doorway's pairs agree to a fraction of a
degree. A join is taken when `MIN_AGREEING_PAIRS` or more pairs imply one rotation within
`MAX_ROTATION_DISAGREEMENT_DEG` and their baseline directions then place b's cameras consistently: the scale and
shift of b (4 unknowns, 2 equations per pair) by least squares when the pairs touch two cameras of b or more, else
the shift alone with b's median baseline set to a's (the same guess as a part whose scale no points fix); every
pair's direction must then lie within `MAX_DIRECTION_DISAGREEMENT_DEG` of where the placement puts its cameras.

Guided (`guided=True`): where no three fits agree, each fit in turn (most inliers first) lends its rotation to every
other cross pair, whose baseline then has 2 unknowns (`two_view.baseline_given_rotation`, the 2-point fit that
lifts a doorway pair's 7-11 true matches out of the chance 3-unknown fits' level); the join is taken when the seed
and `MIN_AGREEING_PAIRS` − 1 or more such guided pairs, connected by shared cameras (`_share_cameras`), place b
consistently (as above). Chance guided fits reach 6-9 inliers too, but point their baselines anywhere: the placement
and the shared cameras are what tell them apart.
Pure geometry: no file access.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullview.sfm import two_view, upright
from fullview.sfm.camera import normalize
from fullview.sfm.rotations import rotation_angle_deg

MIN_PAIR_INLIERS = 6  # a cross pair's upright fit below this many inliers implies nothing (at 0.35° on the bare homes
# at 1024 px, 5 of the 112 pairs between two models of seed 42 reach 6, 3 of them the doorway's, 7-11 inliers)
MAX_ROTATION_DISAGREEMENT_DEG = 1.0  # cross pairs implying rotations this close agree on the join
MIN_AGREEING_PAIRS = 3  # pairs that must agree on one rotation (and on the placement: 6 equations, 3-4 unknowns)
MAX_DIRECTION_DISAGREEMENT_DEG = 2.0  # each agreeing pair's baseline direction against the placement's
MAX_GUIDED_COMPANIONS = 12  # guided pairs (most inliers first) tried in threes with a seed fit
MAX_ITERATIONS = 2000  # upright RANSAC samples per cross pair (few matches: the cap is rarely reached)


@dataclass(kw_only=True)
class CrossPair:
    k: int  # camera of model b
    l: int  # camera of model a
    b_k: np.ndarray  # (M, 3) bearings of the raw matches in camera k
    b_l: np.ndarray  # (M, 3) ... and in camera l
    matches: np.ndarray  # (M, 2) feature indices (k's, l's)


@dataclass(kw_only=True)
class WeakJoin:
    M: np.ndarray  # (3, 3) rotation of model b's frame into model a's: x_a = scale M x_b + shift
    scale: float
    shift: np.ndarray  # (3,)
    pairs: list[tuple[int, int, int]]  # (k, l, inliers) of the agreeing cross pairs
    inlier_matches: list[tuple[int, int, int, int]]  # (k, feature, l, feature) of the agreeing pairs
    scale_guessed: bool  # the agreeing pairs touch one camera of b: its scale is model a's median baseline's
    kind: str  # the rule that found it: "agreeing weak pairs", "guided weak pairs", or a `rematch_join.KINDS` value


def join_by_weak_pairs(*, R_a: dict[int, np.ndarray], C_a: dict[int, np.ndarray], R_b: dict[int, np.ndarray],
                       C_b: dict[int, np.ndarray], gravity: np.ndarray, cross: list[CrossPair], threshold_rad: float,
                       step_a: float, step_b: float, seed: int = 0, guided: bool = False,
                       rematch=None, accept=None) -> WeakJoin | None:
    """The join of model b into model a that several weak cross pairs agree on, or None (see the module doc).

    R_a, C_a (R_b, C_b): rotations (cam from world) and centres of the models' cameras by image; gravity (N, 3) per
    image in its camera frame (zero rows: unknown, such pairs are skipped); step_a, step_b: the models' median
    used-pair baselines (the scale guess); guided: try each fit's rotation on the other pairs when none agree;
    rematch: last, `rematch(fits)` -> (M, chosen fits, placement, inlier rows) or None (`rematch_join`); accept:
    `accept(M, placement)` -> False rejects a join found (the placement check), the next rule is tried."""
    accept = accept or (lambda M, placed: True)
    fits = []
    for n, pair in enumerate(cross):
        fit = _upright_pair(pair, gravity, threshold_rad, seed + n)
        if fit is not None:
            R_lk, t_lk, inliers = fit
            M = R_a[pair.l].T @ R_lk @ R_b[pair.k]
            u = normalize(R_a[pair.l].T @ t_lk)  # from C_l towards C_k, in a's frame
            fits.append((pair, M, u, inliers))
    kind = "agreeing weak pairs"
    for candidate in _agreeing_sets(fits):
        chosen = [fits[n] for n in candidate]
        M = _mean_rotation(np.array([f[1] for f in chosen]))
        placed = _place(M, chosen, C_a, C_b, step_a, step_b)
        if placed is not None and accept(M, placed):
            break
    else:
        found = _guided_join(fits, cross, R_a, C_a, R_b, C_b, threshold_rad, step_a, step_b, seed) if guided else None
        if found is not None and not accept(found[0], found[2]):
            found = None
        if found is None:
            found = rematch(fits) if rematch is not None else None
            if found is None:
                return None
            M, chosen, placed, rows, kind = found
            return WeakJoin(M=M, scale=placed[0], shift=placed[1], pairs=[(f[0].k, f[0].l, len(f[3])) for f in chosen],
                            inlier_matches=rows, scale_guessed=placed[2], kind=kind)
        M, chosen, placed = found
        kind = "guided weak pairs"
    scale, shift, guessed = placed
    rows = [(f[0].k, int(a), f[0].l, int(b)) for f in chosen for a, b in f[0].matches[f[3]]]
    return WeakJoin(M=M, scale=scale, shift=shift, pairs=[(f[0].k, f[0].l, int(f[3].sum())) for f in chosen],
                    inlier_matches=rows, scale_guessed=guessed, kind=kind)


def _upright_pair(pair: CrossPair, gravity: np.ndarray, threshold_rad: float, seed: int):
    """(R_l_from_k, t_l_from_k, inlier mask) of the pair's upright fit on levelled bearings, or None."""
    g_k, g_l = gravity[pair.k], gravity[pair.l]
    if len(pair.b_k) < MIN_PAIR_INLIERS or not (np.any(g_k) and np.any(g_l)):
        return None
    L_k, L_l = upright.leveling_rotation(g_k), upright.leveling_rotation(g_l)
    options = two_view.RansacOptions(threshold_rad=threshold_rad, max_iterations=MAX_ITERATIONS, seed=seed)
    try:
        res = upright.ransac_f_upright(pair.b_k @ L_k.T, pair.b_l @ L_l.T, options)
        if res.inliers.sum() < MIN_PAIR_INLIERS:
            return None
        F = upright.unlevel_f(res.F, L_k, L_l)
        pose = two_view.relative_pose_from_f(F, pair.b_k[res.inliers], pair.b_l[res.inliers])
    except ValueError:  # degenerate samples or F: the pair implies nothing
        return None
    if pose.num_cheiral < 0.9 * res.inliers.sum():
        return None
    return pose.R_j_from_i, pose.t_j_from_i, res.inliers


def _guided_join(fits: list, cross: list[CrossPair], R_a: dict, C_a: dict, R_b: dict, C_b: dict,
                 threshold_rad: float, step_a: float, step_b: float, seed: int):
    """(M, chosen fits, placement) of the first seed fit (most inliers first) whose rotation gives other cross pairs
    2-unknown baselines (MIN_PAIR_INLIERS or more) that, with the seed's, place b consistently; None if none does."""
    for seed_fit in sorted(fits, key=lambda f: -f[3].sum()):
        M = seed_fit[1]
        guided = []
        for n, pair in enumerate(cross):
            if pair is seed_fit[0]:
                continue
            R_lk = R_a[pair.l] @ M @ R_b[pair.k].T
            t_lk, inliers = two_view.baseline_given_rotation(pair.b_k, pair.b_l, R_lk, threshold_rad, seed=seed + n)
            if inliers.sum() >= MIN_PAIR_INLIERS:
                guided.append((pair, M, normalize(R_a[pair.l].T @ t_lk), inliers))
        guided = sorted(guided, key=lambda f: -f[3].sum())[:MAX_GUIDED_COMPANIONS]
        best = None
        for a in range(len(guided)):
            for b in range(a + 1, len(guided)):
                start = [seed_fit, guided[a], guided[b]]
                if not _share_cameras(start):
                    continue
                chosen = _consistent_extension(start, guided, M, C_a, C_b, step_a, step_b)
                if chosen is not None and (best is None or _size(chosen[0]) > _size(best[0])):
                    best = chosen
        if best is not None:
            return M, best[0], best[1]
    return None


def _share_cameras(fits: list) -> bool:
    """True if the fits' pairs are connected by shared cameras: the pairs that see one doorway are those between the
    one or two panoramas on either side of it, and a camera in two pairs is placed twice (its rays must meet), where
    pairs of chance matches scatter over the models (measured on the closed-door home: a seed and two chance pairs
    of other cameras placed within 1.4°)."""
    reached = {0}
    for _ in fits:
        reached |= {n for n, f in enumerate(fits) for r in reached
                    if f[0].k == fits[r][0].k or f[0].l == fits[r][0].l}
    return len(reached) == len(fits)


def _size(chosen: list) -> tuple[int, int]:
    return len(chosen), int(sum(f[3].sum() for f in chosen))


def _consistent_extension(start: list, candidates: list, M, C_a, C_b, step_a, step_b):
    """(chosen, placement): the start's placement (None if inconsistent) with every candidate whose direction lies
    within MAX_DIRECTION_DISAGREEMENT_DEG of it added, placed again."""
    placed = _place(M, start, C_a, C_b, step_a, step_b)
    if placed is None:
        return None
    scale, shift, _ = placed
    cos_max = np.cos(np.radians(MAX_DIRECTION_DISAGREEMENT_DEG))
    chosen = start + [f for f in candidates if all(f is not g for g in start)
                      and normalize(scale * M @ C_b[f[0].k] + shift - C_a[f[0].l]) @ f[2] >= cos_max]
    again = _place(M, chosen, C_a, C_b, step_a, step_b) if len(chosen) > len(start) else placed
    return (chosen, again) if again is not None else (start, placed)


def _agreeing_sets(fits: list) -> list[list[int]]:
    """Sets of fits agreeing with one of them on the rotation (MIN_AGREEING_PAIRS or more), most inliers first."""
    if len(fits) < MIN_AGREEING_PAIRS:
        return []
    Ms = np.array([f[1] for f in fits])
    counts = np.array([f[3].sum() for f in fits])
    found = {}
    for n in range(len(fits)):
        close = np.flatnonzero(rotation_angle_deg(Ms, np.broadcast_to(Ms[n], Ms.shape))
                               <= MAX_ROTATION_DISAGREEMENT_DEG)
        if len(close) >= MIN_AGREEING_PAIRS:
            found[tuple(close.tolist())] = int(counts[close].sum())
    return [list(k) for k, _ in sorted(found.items(), key=lambda kv: -kv[1])]


def _mean_rotation(Ms: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(Ms.sum(axis=0))
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def guessed_scale(step_a: float, step_b: float) -> float:
    """Model b's scale in model a's units when nothing measures it: the ratio of their median baselines."""
    return step_a / step_b if step_b > 0 else 1.0


def _place(M: np.ndarray, chosen: list, C_a: dict, C_b: dict, step_a: float, step_b: float):
    """(scale, shift, guessed) putting b's cameras of the chosen pairs on their baseline rays from a's cameras:
    u × (s M C_k + T − C_l) = 0 per pair; with one camera of b (or of a) the scale is the median-baseline guess. None when the
    scale is not positive or a pair's direction is more than MAX_DIRECTION_DISAGREEMENT_DEG off (or behind)."""
    b_cameras, a_cameras = {f[0].k for f in chosen}, {f[0].l for f in chosen}
    rows, rhs = [], []
    for pair, _, u, _ in chosen:
        U = _skew(u)
        rows.append(np.column_stack([U @ (M @ C_b[pair.k]), U]))
        rhs.append(U @ C_a[pair.l])
    A, y = np.concatenate(rows), np.concatenate(rhs)
    guessed = len(b_cameras) < 2 or len(a_cameras) < 2  # rays from one camera of a fix b's shape, not its size
    if guessed:
        scale = guessed_scale(step_a, step_b)
        shift = np.linalg.lstsq(A[:, 1:], y - scale * A[:, 0], rcond=None)[0]
    else:
        x = np.linalg.lstsq(A, y, rcond=None)[0]
        scale, shift = float(x[0]), x[1:]
    if not scale > 0:
        return None
    cos_max = np.cos(np.radians(MAX_DIRECTION_DISAGREEMENT_DEG))
    for pair, _, u, _ in chosen:
        if normalize(scale * M @ C_b[pair.k] + shift - C_a[pair.l]) @ u < cos_max:
            return None
    return float(scale), shift, guessed


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
