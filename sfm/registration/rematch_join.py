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

One pair (`points` given, `registration.weak_join_one_pair`): a doorway seen by one panorama on each side has one
pair, and no second one can confirm it. A confirmed pair alone places camera k of model b on a ray from camera l of
model a; the rematched matches that are points of model a (seen by l) then fix k's distance along that ray (each
point's ray from k meets the ray at one distance: true matches agree on it, chance ones scatter), and those that are
points of model b (seen by k) fix l's distance from k in b's units: their ratio is b's scale. The pair joins the
models only when `min_points` points of each model agree (registration.min_merge_points: as many as a merge by
shared points needs). A chance pair that the rematch confirms (2048 home
seed 44: 027-008, 28.7 m apart, objects of one texture in two rooms, 80 rematched matches) has points that agree on
no one distance. Seeds then come also from the images' walls: each image's Manhattan axis fixes the two models'
relative yaw modulo 90°, so each cross pair is fitted (2-unknown baseline) under the four rotations the walls allow,
and the best `MAX_WALL_SEEDS` are rematched under their rotation (a doorway pair whose raw matches are too few for
a 3-unknown fit: seed 44's 020-019, 12 true of 38 raw).

Several pairs (`several`, `registration.weak_join_several`, last): in a box room the quarter turns rematch nearly as
well as the true pose (1024 home seed 61: its doorway pair 007-009 37 rematched, 34 under its 90-degree turn; 008-009
34 at its true pose against 15-24), so no doorway pair passes the margins at any pose. Each seed is then taken when
it only beats every quarter turn (`SEVERAL_MARGINS`), with `MIN_SEVERAL_CONFIRMED` - 1 or more pairs sharing one of
its cameras that do the same under its rotation and place b consistently. The guard is the join check
(`accept`, `placement_check`), which every join found here passes before it is taken.

A guess (`guess`, only with `registration.unconfirmed_joins: approximate`, the very last): a doorway pair that the
rematch confirms by homejoin's margins, with no companion and none of either model's points among its matches, fixes
b's rotation and the direction from l to k, but neither the length nor b's scale: one pair's epipolar geometry
carries no distance. So k is put on the ray at model a's median baseline, b's scale is the median baselines' ratio,
and every camera it carries is marked approximate (docs/trust.md); the triangulation stage's height prior and bridge
floor measure both. Where no upright fit of the doorway exists, every rotation the walls allow is tried on every
cross pair, rematched once, and the most rematched are confirmed. A chance pair the rematch confirms, put at a
guessed place, is refused by the join check (free space: its points may not lie in front of what the other model's
cameras saw).
Pure geometry: no file access.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fullview.sfm import two_view, upright
from fullview.sfm.camera import normalize
from fullview.sfm.matching import epipolar_candidates, match_descriptors
from fullview.sfm.options import MatchesOptions, RegistrationOptions
from fullview.sfm.registration.weak_joins import MIN_PAIR_INLIERS, _place, guessed_scale
from fullview.sfm.wall_check import f_of_pose, turn, wall_residual_deg

log = logging.getLogger(__name__)

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
MIN_POINT_SHARE = 0.75  # ... and this share of the rematched matches that are its points (2048 home seed 44: the
# chance pair 027-008 9 of 17 and 7 of 20, 028-008 7 of 8 and 2 of 14)
MAX_SCALE_FACTOR = 2.0  # b's scale from the points within this factor of the models' median baselines' ratio (one
# to three panoramas per room: neighbours are a room apart everywhere)
POINT_TOLERANCE = 2.0  # ... their error in the pair's other camera, in inlier thresholds (points carry their own)
MIN_POINT_PARALLAX_DEG = 3.0  # points this close to the baseline's line fix no distance along it
MAX_WALL_SEEDS = 6  # (pair, rotation the walls allow) hypotheses rematched, most 2-unknown inliers first
SCAN_MIN_INLIERS = 3  # the guess rule's wall hypotheses: raw inliers of their 2-unknown baseline (1024 home seed 96:
# doorway 018-019, 5 true of 25 raw, 4 inliers under the walls' rotation; 647 hypotheses, 18.7 CPU s to rematch)
MAX_SCANNED = 1000  # ... at most this many rematched (most raw inliers first)
MIN_SEVERAL_CONFIRMED = 2  # pairs (seed included) that place b when each only beats its quarter turns
SEVERAL_MARGINS = (1.0, 1)  # ... by (factor, excess): more matches than under any quarter turn (doorway 007-009 of
# 1024 home seed 61: 37 rematched from its seed fit, 34 under its 90-degree turn; 008-009 34 against 13-32)


class Rematched(NamedTuple):
    """A join found by rematching: b's rotation into a, the chosen fits, the placement (scale, shift, guessed), the
    inlier rows (k, feature, l, feature), and which rule found it (`KINDS`)."""

    M: np.ndarray
    chosen: list
    placed: tuple
    rows: list
    kind: str


KINDS = {"companions": "rematched pairs", "one_pair": "one rematched pair and points of both models",
         "several": "rematched pairs each above its quarter turns", "guess": "one rematched pair, guessed length"}


@dataclass(kw_only=True)
class ModelPoints:
    X: np.ndarray  # (P, 3) a model's points in its frame
    point_of_feature: dict  # image -> (F_i,) row in X of each of its features (-1: none)


def rematched(b_k: np.ndarray, b_l: np.ndarray, d_k: np.ndarray, d_l: np.ndarray, R_lk: np.ndarray, t_lk: np.ndarray,
              threshold_rad: float) -> np.ndarray:
    """(M, 2) matches (feature of k, feature of l) found by descriptors among the features within the threshold of
    each other's epipolar circles under the pose (R_lk, t_lk) of l from k, in front of both cameras.

    b_k, b_l: (N, 3) bearings of the features whose descriptors d_k, d_l (N, D) are given."""
    F = f_of_pose(R_lk, t_lk)  # b_kᵀ F b_l = 0
    allowed = epipolar_candidates(b_k, b_l, F, threshold_rad)
    m = match_descriptors(d_k, d_l, MatchesOptions(ratio=RATIO, mutual=True), block_rows=1024, allowed=allowed)
    if not len(m):
        return m
    return m[two_view.consistent_with_pose(b_k[m[:, 0]], b_l[m[:, 1]], R_lk, t_lk, threshold_rad)]


def confirmed_pose(b_k, b_l, d_k, d_l, R_lk, t_lk, threshold_rad: float, *, g_k: np.ndarray, g_l: np.ndarray,
                   free_rotation: bool, raw: tuple[np.ndarray, np.ndarray], seed: int = 0,
                   margins: tuple[float, int] = (NULL_FACTOR, MIN_EXCESS)):
    """(R_lk, t_lk, matches) of the pair rematched in wide bands and refitted from the hypothesis, or None when it
    is not confirmed.

    g_k, g_l: the cameras' gravity; free_rotation: refit the rotation too (upright: yaw and baseline), else only the
    baseline under the given rotation. raw: the pair's raw matched bearings (k's, l's), whose baselines give the
    quarter-turned poses their best chance; margins: (factor, excess) the matches must beat the quarter turns' by."""
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
        turned = R_lk @ turn(g_k, 90.0 * q)
        t_q, _ = two_view.baseline_given_rotation(raw[0], raw[1], turned, threshold_rad, seed=seed)
        null = len(rematched(b_k, b_l, d_k, d_l, turned, t_q, threshold_rad))
        if len(m) < margins[0] * null or len(m) < null + margins[1]:
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


def join_by_rematching(fits: list, cross: list, *, R_a: dict, C_a: dict, R_b: dict, C_b: dict, gravity: np.ndarray,
                       bearings, descriptors, threshold_rad: float, step_a: float, step_b: float, seed: int = 0,
                       points: tuple[ModelPoints, ModelPoints] | None = None, wall_axes: np.ndarray | None = None,
                       several: bool = False, guess: bool = False, accept=None,
                       min_points: int = RegistrationOptions.min_merge_points) -> Rematched | None:
    """(M, chosen, placement, inlier rows) of the first seed fit (most inliers first) that the rematch confirms with
    companions placing model b consistently (see the module doc), or None.

    fits: `weak_joins` upright fits (pair, M, u, inlier mask); cross: the `weak_joins.CrossPair`s between the models;
    bearings, descriptors: per image (descriptors of its SIFT features, which come first in its bearings); points:
    (model a's, model b's) to join on one confirmed pair placed by both (None: two pairs needed); wall_axes: (N, 3)
    each image's Manhattan axis in its camera frame (zero rows: none), for the seeds the walls allow; several: last,
    MIN_SEVERAL_CONFIRMED pairs each above its quarter turns by SEVERAL_MARGINS (see the module doc); accept:
    `accept(M, (scale, shift, guessed))` -> False rejects a join (the placement check), the next seed is tried;
    min_points: points of each model that must agree on a one-pair join."""
    def confirm(pair, R_lk, t_lk, free_rotation: bool, n: int, margins=(NULL_FACTOR, MIN_EXCESS)):
        d_k, d_l = descriptors[pair.k], descriptors[pair.l]
        return confirmed_pose(bearings[pair.k][:len(d_k)], bearings[pair.l][:len(d_l)], d_k, d_l, R_lk, t_lk,
                              threshold_rad, g_k=gravity[pair.k], g_l=gravity[pair.l], free_rotation=free_rotation,
                              raw=(pair.b_k, pair.b_l), seed=seed + n, margins=margins)

    def placed_with_companions(pair, found, margins, min_confirmed: int):
        """The join the confirmed seed and the cross pairs sharing one of its cameras confirmed under its rotation
        place consistently (min_confirmed pairs or more), or None."""
        R_lk, t_lk, m = found
        M = R_a[pair.l].T @ R_lk @ R_b[pair.k]
        chosen = [(pair, M, normalize(R_a[pair.l].T @ t_lk), m)]
        for n, other in enumerate(cross):
            if other is pair or (other.k != pair.k and other.l != pair.l) or not (
                    np.any(gravity[other.k]) and np.any(gravity[other.l])):
                continue
            R_q = R_a[other.l] @ M @ R_b[other.k].T
            t_q, _ = two_view.baseline_given_rotation(other.b_k, other.b_l, R_q, threshold_rad, seed=seed + n)
            companion = confirm(other, R_q, t_q, False, n, margins)
            if companion is not None:
                chosen.append((other, M, normalize(R_a[other.l].T @ companion[1]), companion[2]))
        if len(chosen) < min_confirmed:
            return None
        placed = _place(M, chosen, C_a, C_b, step_a, step_b)
        if placed is None or not accept(M, placed):
            return None
        rows = [(f[0].k, int(a), f[0].l, int(b)) for f in chosen for a, b in f[3]]
        return Rematched(M, chosen, placed, rows, KINDS["several" if min_confirmed == MIN_SEVERAL_CONFIRMED
                                                        and margins == SEVERAL_MARGINS else "companions"])

    accept = accept or (lambda M, placed: True)
    seeds = sorted(fits, key=lambda f: -f[3].sum())[:MAX_SEEDS]
    alone = []  # seeds confirmed without a companion that places b
    for pair, M, u, _ in seeds:
        found = confirm(pair, R_a[pair.l] @ M @ R_b[pair.k].T, R_a[pair.l] @ u, True, 0)
        if found is None:
            continue
        alone.append((pair, found))
        joined = placed_with_companions(pair, found, (NULL_FACTOR, MIN_EXCESS), MIN_CONFIRMED)
        if joined is not None:
            return joined
    if points is not None:
        joined = _join_by_one_pair(alone, confirm, cross, gravity, bearings, points, wall_axes, threshold_rad, seed,
                                   accept, R_a=R_a, C_a=C_a, R_b=R_b, C_b=C_b,
                                   tolerance_rad=POINT_TOLERANCE * threshold_rad,
                                   step_ratio=guessed_scale(step_a, step_b), min_points=min_points)
        if joined is not None:
            return Rematched(*joined, KINDS["one_pair"])
    if several:
        for pair, M, u, _ in seeds:
            found = confirm(pair, R_a[pair.l] @ M @ R_b[pair.k].T, R_a[pair.l] @ u, True, 0, SEVERAL_MARGINS)
            joined = (placed_with_companions(pair, found, SEVERAL_MARGINS, MIN_SEVERAL_CONFIRMED)
                      if found is not None else None)
            if joined is not None:
                log.info("rematch: %d pairs (k, l, matches) %s, each above its quarter turns, place model b",
                         len(joined[1]), [(f[0].k, f[0].l, len(f[3])) for f in joined[1]])
                return joined
    if guess:
        placed = dict(R_a=R_a, C_a=C_a, R_b=R_b, C_b=C_b, step_a=step_a, step_b=step_b)
        joined = _first_guess_accepted(alone, accept, "", **placed)
        if joined is None and wall_axes is not None:
            scanned = _confirmed_wall_scan(confirm, cross, gravity, wall_axes, bearings, descriptors, threshold_rad,
                                           seed)
            joined = _first_guess_accepted(scanned, accept, " under the walls' rotation", **placed)
        if joined is not None:
            return Rematched(*joined, KINDS["guess"])
    return None


def _scanned_wall_seeds(cross: list, gravity, wall_axes, bearings, descriptors, threshold_rad: float, seed: int):
    """[(pair, R_lk, t_lk)] of the MAX_WALL_SEEDS (pair, rotation the walls allow) hypotheses that rematch the most
    matches (MIN_REMATCHED or more), among all with SCAN_MIN_INLIERS raw inliers or more (a doorway pair of 5 true
    among 25 raw ranks by its raw inliers below hundreds of chance hypotheses, by its rematched matches among the
    first three)."""
    hypotheses = wall_hypotheses(cross, gravity, wall_axes, threshold_rad, seed, min_inliers=SCAN_MIN_INLIERS,
                                 limit=MAX_SCANNED)
    counts = []
    for pair, R_lk, t_lk in hypotheses:
        d_k, d_l = descriptors[pair.k], descriptors[pair.l]
        counts.append(len(rematched(bearings[pair.k][:len(d_k)], bearings[pair.l][:len(d_l)], d_k, d_l, R_lk, t_lk,
                                    threshold_rad)))
    order = [n for n in np.argsort(-np.array(counts, int), kind="stable") if counts[n] >= MIN_REMATCHED]
    return [hypotheses[n] for n in order[:MAX_WALL_SEEDS]]


def _first_guess_accepted(candidates, accept, how: str, **placed):
    """The join (`_placed_by_a_guess`) of the first (pair, (R_lk, t_lk, matches)) of `candidates` that `accept`
    takes, or None."""
    for pair, found in candidates:
        joined = _placed_by_a_guess(pair, *found, **placed)
        if accept(joined[0], joined[2]):
            log.info("rematch: pair %d-%d (%d matches)%s, confirmed alone, places model b at a guessed length and "
                     "scale", pair.k, pair.l, len(found[2]), how)
            return joined
    return None


def _confirmed_wall_scan(confirm, cross, gravity, wall_axes, bearings, descriptors, threshold_rad: float, seed: int):
    """(pair, (R_lk, t_lk, matches)) of the scanned wall seeds (`_scanned_wall_seeds`) the rematch confirms, lazily
    (the scan runs only when no seed fit was confirmed alone)."""
    for n, (pair, R_lk, t_lk) in enumerate(_scanned_wall_seeds(cross, gravity, wall_axes, bearings, descriptors,
                                                                 threshold_rad, seed)):
        found = confirm(pair, R_lk, t_lk, False, 200 + n)
        if found is not None:
            yield pair, found


def _placed_by_a_guess(pair, R_lk, t_lk, m, *, R_a, C_a, R_b, C_b, step_a: float, step_b: float):
    """(M, chosen, placement, inlier rows) of the join by one confirmed pair (k of b, l of a) alone: camera k on the
    pair's baseline ray from l at model a's median baseline, b's scale the median baselines' ratio (guessed)."""
    k, l = pair.k, pair.l
    M = R_a[l].T @ R_lk @ R_b[k]
    u = normalize(R_a[l].T @ t_lk)  # from C_l towards C_k, in a's frame
    scale = guessed_scale(step_a, step_b)
    shift = C_a[l] + step_a * u - scale * M @ C_b[k]
    rows = [(k, int(a), l, int(b)) for a, b in m]
    return M, [(pair, M, u, m)], (float(scale), shift, True), rows


def _join_by_one_pair(alone: list, confirm, cross: list, gravity, bearings, points, wall_axes, threshold_rad: float,
                      seed: int, accept, min_points: int, **frames):
    """The one-pair join (see the module doc) of a confirmed seed, else of a wall seed that the rematch confirms;
    None if none is joined (or accepted)."""
    for pair, (R_lk, t_lk, m) in alone:
        found = _joined_by_points(pair, R_lk, t_lk, m, bearings, points, min_points=min_points, **frames)
        if found is not None and accept(found[0], found[2]):
            return found
    if wall_axes is None:
        return None
    for n, (pair, R_lk, t_lk) in enumerate(wall_hypotheses(cross, gravity, wall_axes, threshold_rad, seed)):
        if any(pair is p for p, _ in alone):
            continue
        found = confirm(pair, R_lk, t_lk, False, 100 + n)
        if found is not None:
            found = _joined_by_points(pair, *found, bearings, points, min_points=min_points, **frames)
            if found is not None and accept(found[0], found[2]):
                return found
    return None


def wall_hypotheses(cross: list, gravity: np.ndarray, wall_axes: np.ndarray, threshold_rad: float, seed: int = 0, *,
                    min_inliers: int = MIN_PAIR_INLIERS, limit: int = MAX_WALL_SEEDS):
    """[(pair, R_lk, t_lk)] of the `limit` best (most 2-unknown baseline inliers, `min_inliers` or more) of the cross
    pairs under each of the four upright rotations their images' wall axes allow."""
    found = []
    for n, pair in enumerate(cross):
        g_k, g_l, a_k, a_l = gravity[pair.k], gravity[pair.l], wall_axes[pair.k], wall_axes[pair.l]
        if not all(np.any(v) for v in (g_k, g_l, a_k, a_l)):
            continue
        level = two_view.rotation_between(normalize(np.asarray(g_k, float)), normalize(np.asarray(g_l, float)))
        aligned = turn(g_l, wall_residual_deg(level, a_k, a_l, g_l)) @ level
        for q in range(4):
            R = turn(g_l, 90.0 * q) @ aligned
            t, inliers = two_view.baseline_given_rotation(pair.b_k, pair.b_l, R, threshold_rad, seed=seed + n)
            if inliers.sum() >= min_inliers:
                found.append((int(inliers.sum()), n, q, pair, R, t))
    found.sort(key=lambda f: (-f[0], f[1], f[2]))
    return [(f[3], f[4], f[5]) for f in found[:limit]]


def _joined_by_points(pair, R_lk, t_lk, m, bearings, points, *, R_a, C_a, R_b, C_b, tolerance_rad: float,
                      step_ratio: float, min_points: int):
    """(M, chosen, placement, inlier rows) of the join by one confirmed pair (k of b, l of a) when points of both
    models agree on its length (see the module doc), or None."""
    k, l = pair.k, pair.l
    M = R_a[l].T @ R_lk @ R_b[k]
    u = normalize(R_a[l].T @ t_lk)  # from C_l towards C_k, in a's frame
    pa, pb = points
    if l not in pa.point_of_feature or k not in pb.point_of_feature:
        return None
    on_a, on_b = pa.point_of_feature[l][m[:, 1]], pb.point_of_feature[k][m[:, 0]]
    seen_a, seen_b = on_a >= 0, on_b >= 0
    if min(seen_a.sum(), seen_b.sum()) < min_points:
        return None
    rays_a = bearings[k][m[seen_a, 0]] @ (R_a[l].T @ R_lk).T  # k's rays in a's frame
    lam, n_a = distance_along(C_a[l], u, pa.X[on_a[seen_a]], rays_a, tolerance_rad)
    rays_b = bearings[l][m[seen_b, 1]] @ (R_a[l] @ M)  # l's rays in b's frame
    mu, n_b = distance_along(C_b[k], -M.T @ u, pb.X[on_b[seen_b]], rays_b, tolerance_rad)
    scale = lam / mu if mu > 0 else 0.0
    log.info("one pair %d-%d: %d of %d points of model a agree on its length, %d of %d of model b; scale %.3f "
             "(median baselines' ratio %.3f)", k, l, n_a, seen_a.sum(), n_b, seen_b.sum(), scale, step_ratio)
    if (min(n_a, n_b) < min_points or n_a < MIN_POINT_SHARE * seen_a.sum()
            or n_b < MIN_POINT_SHARE * seen_b.sum()
            or not 1.0 / MAX_SCALE_FACTOR <= scale / step_ratio <= MAX_SCALE_FACTOR):
        return None
    shift = C_a[l] + lam * u - scale * M @ C_b[k]
    rows = [(k, int(a), l, int(b)) for a, b in m]
    return M, [(pair, M, u, m)], (float(scale), shift, False), rows


def distance_along(origin: np.ndarray, v: np.ndarray, X: np.ndarray, rays: np.ndarray, tolerance_rad: float):
    """(λ, support): the distance along the unit direction v from origin of a camera that sees most of the points X
    (P, 3) along its rays (P, 3) (world frame) within tolerance_rad, in front; points within MIN_POINT_PARALLAX_DEG
    of the line fix nothing and are left out. (0.0, 0) when none is placed."""
    rays = normalize(rays)
    w = X - origin
    useful = np.linalg.norm(np.cross(normalize(w), v), axis=1) > np.sin(np.radians(MIN_POINT_PARALLAX_DEG))
    w, rays = w[useful], rays[useful]
    if not len(w):
        return 0.0, 0
    Pw = w - rays * np.sum(rays * w, axis=1, keepdims=True)  # the parts normal to each ray
    Pv = v[None, :] - rays * (rays @ v)[:, None]
    lam = np.sum(Pv * Pw, axis=1) / np.maximum(np.sum(Pv * Pv, axis=1), 1e-12)  # each point's own distance
    candidates = lam[lam > 0]
    if not len(candidates):
        return 0.0, 0

    def support(d: np.ndarray) -> np.ndarray:  # (C,) candidate distances -> (C, P) the points each one explains
        seen = w[None, :, :] - d[:, None, None] * v[None, None, :]
        cos = np.sum(normalize(seen) * rays[None], axis=2)
        return cos >= np.cos(tolerance_rad)

    best = int(np.argmax(support(candidates).sum(axis=1)))
    agree = support(candidates[best:best + 1])[0]
    if not agree.any():
        return 0.0, 0
    refined = float(np.median(lam[agree]))
    again = support(np.array([refined]))[0]
    return (refined, int(again.sum())) if again.sum() >= agree.sum() else (float(candidates[best]), int(agree.sum()))
