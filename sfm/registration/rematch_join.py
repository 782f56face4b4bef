"""Two models joined through one doorway by rematching its pairs' descriptors along their epipolar circles.

Where a home of one or two panoramas per room splits at a doorway, the doorway's pairs hold 7-17 true matches among
30-45 raw ones: the global ratio test (every feature of the other panorama competing) drops most true
correspondences on plain walls, and those left are too few to verify, or to agree with the weak joins of
`weak_joins` (three pairs). Once a pose hypothesis exists, a feature only competes with the features near its
epipolar circle: rematched there (ratio test and mutual check among those candidates, matches in front of both
cameras), the doorway pair 027-028 of bare home seed 45 holds 57 matches, 36 true, under the true pose (raw: 42, 17
true), and 026-028 49 (29 true; raw 7 true); pairs that see nothing of each other hold 10-13 band matches under any
pose.

So each cross pair's upright fit (`weak_joins`, 6+ inliers, most first) is a hypothesis: its pair is rematched under
it, refitted on the rematched matches (3 unknowns: yaw and baseline) and rematched again. It is confirmed when it
holds `MIN_REMATCHED` matches, and `NULL_FACTOR` times and `MIN_EXCESS` more than under the same pose turned by 90°,
180° or 270° about gravity (each with its own best baseline): the rematch finds band matches under any pose (about
a feature's 0.5% of the sphere holds a few candidates, and some pass the ratio test), and a box room's walls make
the quarter turns the likeliest wrong hypotheses. The confirmed seed's rotation of model b into model a then
guides the cross pairs sharing one of its cameras (the doorway's other pairs): baseline from their raw matches
(2 unknowns, `two_view.baseline_given_rotation`), rematched, refitted and judged the same way. The seed and the
confirmed companions (at least `MIN_CONFIRMED` pairs in all) must place b consistently (`weak_joins._place`: its
cameras on the pairs' baseline rays within 2°).
Pure geometry: no file access.
"""

from __future__ import annotations

import numpy as np

from fullview.sfm import two_view, upright
from fullview.sfm.camera import normalize, skew
from fullview.sfm.matching import epipolar_candidates, match_descriptors
from fullview.sfm.options import MatchesOptions
from fullview.sfm.registration.weak_joins import _place

MAX_SEEDS = 6  # upright fits (most inliers first) tried as hypotheses
MIN_REMATCHED = 20  # rematched matches a confirmed pair holds (band matches of pairs seeing nothing: 10-13 at 1024 px)
NULL_FACTOR = 1.5  # ... and this many times those under its pose turned by a quarter turn about gravity
MIN_EXCESS = 15  # ... and this many more: band matches by chance grow with the features (doorway 027-028 of bare
# home seed 45: 55 rematched at its pose, 25-28 under the quarter turns; pairs seeing nothing of each other 10-13)
MIN_CONFIRMED = 2  # confirmed pairs (seed included) that must place model b (two rays meet: one redundant equation)
REFIT_BANDS = (4.0, 2.0)  # rematch-and-refit rounds before the final rematch, their bands in inlier thresholds: a
# hypothesis 0.3° off in yaw and 2° in its baseline keeps only 16 of 39 true matches within one threshold (with 7
# chance ones, which the refit then follows); a wider band keeps them, and the refit at one threshold finds them
RATIO = 0.8  # the ratio test among a feature's epipolar candidates


def rematched(b_k: np.ndarray, b_l: np.ndarray, d_k: np.ndarray, d_l: np.ndarray, R_lk: np.ndarray, t_lk: np.ndarray,
              threshold_rad: float) -> np.ndarray:
    """(M, 2) matches (feature of k, feature of l) found by descriptors among the features within the threshold of
    each other's epipolar circles under the pose (R_lk, t_lk) of l from k, in front of both cameras.

    b_k, b_l: (N, 3) bearings of the features whose descriptors d_k, d_l (N, D) are given."""
    F = R_lk.T @ skew(t_lk).T  # b_kᵀ F b_l = 0 (`two_view.consistent_with_pose`)
    allowed = epipolar_candidates(b_k, b_l, F, threshold_rad)
    m = match_descriptors(d_k, d_l, MatchesOptions(ratio=RATIO, mutual=True), block_rows=1024, allowed=allowed)
    if not len(m):
        return m
    return m[two_view.consistent_with_pose(b_k[m[:, 0]], b_l[m[:, 1]], R_lk, t_lk, threshold_rad)]


def confirmed_pose(b_k, b_l, d_k, d_l, R_lk, t_lk, threshold_rad: float, *, g_k: np.ndarray, g_l: np.ndarray,
                   free_rotation: bool, raw: tuple[np.ndarray, np.ndarray], seed: int = 0):
    """(R_lk, t_lk, matches) of the pair rematched in wide bands and refitted from the hypothesis, or None when it is not confirmed.

    g_k, g_l: the cameras' gravity; free_rotation: refit the rotation too (upright: yaw and baseline), else only the
    baseline under the given rotation. raw: the pair's raw matched bearings (k's, l's), whose baselines give the
    quarter-turned poses their best chance."""
    for band in REFIT_BANDS:
        m = rematched(b_k, b_l, d_k, d_l, R_lk, t_lk, band * threshold_rad)
        if len(m) < MIN_REMATCHED:
            return None
        refit = _refit(b_k[m[:, 0]], b_l[m[:, 1]], R_lk, threshold_rad, (g_k, g_l) if free_rotation else None, seed)
        if refit is None:
            return None
        R_lk, t_lk = refit
    m = rematched(b_k, b_l, d_k, d_l, R_lk, t_lk, threshold_rad)
    if len(m) < MIN_REMATCHED:
        return None
    for q in (1, 2, 3):
        turned = R_lk @ _turn(normalize(np.asarray(g_k, float)), q * np.pi / 2)
        t_q, _ = two_view.baseline_given_rotation(raw[0], raw[1], turned, threshold_rad, seed=seed)
        null = len(rematched(b_k, b_l, d_k, d_l, turned, t_q, threshold_rad))
        if len(m) < NULL_FACTOR * null or len(m) < null + MIN_EXCESS:
            return None
    return R_lk, t_lk, m


def _refit(x_k: np.ndarray, x_l: np.ndarray, R_lk: np.ndarray, threshold_rad: float, gravities, seed: int):
    """(R_lk, t_lk) refitted on rematched matches: upright (yaw and baseline) with gravities (k's, l's) given, else
    the baseline under the kept rotation. None when the fit fails."""
    if gravities is None:
        t, inliers = two_view.baseline_given_rotation(x_k, x_l, R_lk, threshold_rad, seed=seed)
        return (R_lk, t) if inliers.sum() >= MIN_REMATCHED else None
    L_k, L_l = upright.leveling_rotation(gravities[0]), upright.leveling_rotation(gravities[1])
    options = two_view.RansacOptions(threshold_rad=threshold_rad, max_iterations=500, seed=seed)
    try:
        res = upright.ransac_f_upright(x_k @ L_k.T, x_l @ L_l.T, options)
        F = upright.unlevel_f(res.F, L_k, L_l)
        pose = two_view.relative_pose_from_f(F, x_k[res.inliers], x_l[res.inliers])
    except ValueError:
        return None
    return pose.R_j_from_i, pose.t_j_from_i


def _turn(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` about the unit `axis` (Rodrigues)."""
    K = skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def join_by_rematching(fits: list, cross: list, *, R_a: dict, C_a: dict, R_b: dict, C_b: dict, gravity: np.ndarray,
                       bearings, descriptors, threshold_rad: float, step_a: float, step_b: float, seed: int = 0):
    """(M, chosen, placement, inlier rows) of the first seed fit (most inliers first) that the rematch confirms with
    companions placing model b consistently (see the module doc), or None.

    fits: `weak_joins` upright fits (pair, M, u, inlier mask); cross: the `weak_joins.CrossPair`s between the models;
    bearings, descriptors: per image (descriptors of its SIFT features, which come first in its bearings)."""
    def confirm(pair, R_lk, t_lk, free_rotation: bool, n: int):
        d_k, d_l = descriptors[pair.k], descriptors[pair.l]
        return confirmed_pose(bearings[pair.k][:len(d_k)], bearings[pair.l][:len(d_l)], d_k, d_l, R_lk, t_lk,
                              threshold_rad, g_k=gravity[pair.k], g_l=gravity[pair.l], free_rotation=free_rotation,
                              raw=(pair.b_k, pair.b_l), seed=seed + n)

    for pair, M, u, _ in sorted(fits, key=lambda f: -f[3].sum())[:MAX_SEEDS]:
        found = confirm(pair, R_a[pair.l] @ M @ R_b[pair.k].T, R_a[pair.l] @ u, True, 0)
        if found is None:
            continue
        R_lk, t_lk, m = found
        M = R_a[pair.l].T @ R_lk @ R_b[pair.k]
        chosen = [(pair, M, normalize(R_a[pair.l].T @ t_lk), m)]
        for n, other in enumerate(cross):
            if other is pair or (other.k != pair.k and other.l != pair.l) or not (
                    np.any(gravity[other.k]) and np.any(gravity[other.l])):
                continue
            R_q = R_a[other.l] @ M @ R_b[other.k].T
            t_q, _ = two_view.baseline_given_rotation(other.b_k, other.b_l, R_q, threshold_rad, seed=seed + n)
            companion = confirm(other, R_q, t_q, False, n)
            if companion is not None:
                chosen.append((other, M, normalize(R_a[other.l].T @ companion[1]), companion[2]))
        if len(chosen) < MIN_CONFIRMED:
            continue
        placed = _place(M, chosen, C_a, C_b, step_a, step_b)
        if placed is not None:
            rows = [(f[0].k, int(a), f[0].l, int(b)) for f in chosen for a, b in f[3]]
            return M, chosen, placed, rows
    return None
