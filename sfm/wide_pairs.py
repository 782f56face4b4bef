"""Wide baselines: verify an upright pair the normal filter rejected by the chance of a wrong pair fitting as well.

Two panoramas of adjacent rooms, a few metres apart, share few SIFT matches, most of them wrong; RANSAC's best fit
then has too few inliers for `filter.min_inliers_upright` (or a wrong fit has as many). Lowering that count would
admit wrong pairs. This module instead asks how likely the best fit's support is by chance (an a-contrario test,
Moisan & Stival 2004; Moisan, Moulon & Monasse, "Automatic homographic registration of a pair of images, with a
contrario elimination of outliers", IPOL 2012) under the physically constrained model of two levelled cameras:

1. Both panoramas are levelled by their measured gravity (`upright.leveling_rotation`): the relative rotation is a
   yaw θ, the baseline T = (cos e cos φ, sin e, cos e sin φ) has an azimuth φ and a small elevation e,
   |e| ≤ e_max = atan(height spread / shortest baseline) (`max_elevation`).
2. Only *informative* matches count: a match on the horizon band (|latitude| ≤ threshold + e_max in both views)
   lies within the threshold of the epipolar plane through the baseline and the horizontal for every yaw and
   azimuth, and one near the poles (within the band of a pole in both views) lies near the vertical epipolar plane
   of every hypothesis: they cannot tell poses apart. A match must also be in front of both cameras.
3. A scan over (θ, φ, e) on a grid one threshold apart counts informative inliers within threshold + step (the truth
   lies within half a step in each unknown); the best few distinct hypotheses are refined (`upright.refine_f_upright`)
   on their inliers and counted again at the threshold.
4. The number of false alarms of a hypothesis with k informative inliers among n informative matches is
   NFA = pairs tried × 4·C(n, 3)·(n − 3) × P(K ≥ k − 3), with K the number of the n − 3 other matches that fit by
   chance: every upright model with 3 or more inliers lies, to within the noise, among the ≤ 4 models through 3 of
   them (the 3-point solver), and k is chosen among n − 3 values. Each match's chance p_m is the share of its
   latitude circle in image j within the threshold of its epipolar circle (`chance_per_match`): the null keeps each
   bearing's latitude (SIFT features cluster on the horizon and the poles) and draws its longitude in j uniformly.
   The 3 inliers left out of the tail are those with the smallest p_m (the most telling: conservative). K is a sum
   of independent Bernoulli(p_m): `tail_at_least` is its exact Poisson-binomial tail. Accepted when NFA < ε and the
   pose is unique: against every hypothesis whose yaw differs by more than a coarse cell, the inliers it does not
   explain are meaningful on their own (`verify_wide`).
5. Guided evidence (`guided_nfa`): for the best hypotheses, every informative feature of i is matched again among
   the informative features of j within `band` thresholds of its epipolar circle and in front of both cameras, by
   the ratio test among those candidates only. Those matches are biased towards the hypothesis — they lie in the
   band by construction — so their chance is not p_m: under a wrong hypothesis the descriptor that wins among the
   candidates is unrelated to its exact distance from the circle, so it falls within one threshold with probability
   q = sin(t) / sin(band·t) ≈ 1/band. Guided NFA = pairs tried × hypotheses rematched × P(Binomial(n_g, q) ≥ k_g),
   over guided matches whose feature in i had no raw match (independent of the evidence that chose the hypothesis).
   Reported, not used to accept: it tells that a pair overlaps, not that the pose is right (a pose 4.3° off on a
   real pair scored 2.7e-12).
6. Once accepted, the pose is refined on the informative inliers and guided inliers, and the pair's inliers are the
   raw matches within the threshold plus the features matched again along its epipolar circles (the ratio test
   among candidates within one threshold) — all in front of both cameras.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from fullview.sfm import upright
from fullview.sfm.camera import normalize
from fullview.sfm.matching import match_descriptors
from fullview.sfm.options import MatchesOptions
from fullview.sfm.registration.poses import yaw_rotation

log = logging.getLogger(__name__)

UPRIGHT_MODELS_PER_SAMPLE = 4  # the 3-point upright solver's quartic has at most 4 real roots (upright.py)
SAMPLE = upright.UPRIGHT_SAMPLE_SIZE


@dataclass(frozen=True, kw_only=True)
class WideResult:
    accepted: bool  # NFA below epsilon and unique (no distinct rival explains its evidence)
    F: np.ndarray  # (3, 3) of the original bearings (zeros when nothing was found)
    inliers: np.ndarray  # (M, 2) feature pairs: raw inliers and guided ones (empty unless accepted)
    yaw_deg: float  # relative yaw in the levelled frames
    elevation_deg: float  # baseline elevation in the levelled frames
    informative: int  # n: informative raw matches
    informative_inliers: int  # k: of them, inliers of the best hypothesis
    nfa: float  # of the raw matches
    guided: int  # n_g: guided informative matches counted as evidence
    guided_hits: int  # k_g: of them within one threshold of the hypothesis
    guided_nfa: float  # of the guided matches (inf when not run)
    unique_nfa: float = 0.0  # the largest NFA of its evidence beyond a distinct rival's inliers (0: no rival)


# --------------------------------------------------------------------------------------------- chance
def log_binomial(n: int, k: int) -> float:
    return math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)


def tail_at_least(p: np.ndarray, k: int) -> float:
    """P(Σ Bernoulli(p_m) ≥ k) for independent trials (the Poisson-binomial tail), exact by dynamic programming
    over the count (capped at k); equal p_m give the binomial tail."""
    p = np.clip(np.asarray(p, dtype=np.float64).ravel(), 0.0, 1.0)
    if k <= 0:
        return 1.0
    if k > len(p):
        return 0.0
    dist = np.zeros(k + 1)  # dist[c]: P(count = c) for c < k, dist[k]: P(count ≥ k)
    dist[0] = 1.0
    for q in p:
        reached = dist[k] + dist[k - 1] * q
        dist[1:k] = dist[1:k] * (1.0 - q) + dist[:k - 1] * q
        dist[0] *= 1.0 - q
        dist[k] = reached
    return float(min(1.0, dist[k]))


def num_tests(n: int) -> float:
    """Upright hypotheses a scan over n matches can single out: 4 models per 3-point sample, n − 3 values of k."""
    if n < SAMPLE + 1:
        return 1.0
    return UPRIGHT_MODELS_PER_SAMPLE * math.exp(log_binomial(n, SAMPLE)) * (n - SAMPLE)


def nfa(p: np.ndarray, inliers: np.ndarray, pairs: int = 1) -> float:
    """Number of false alarms of a hypothesis whose `inliers` (bool, over matches with chances `p`) fit: the 3
    inliers of smallest chance stand for the sample, the tail is over the other matches (module docstring, 4)."""
    p, inliers = np.asarray(p, np.float64), np.asarray(inliers, bool)
    n, k = len(p), int(inliers.sum())
    if k <= SAMPLE:
        return float("inf")
    sample = np.flatnonzero(inliers)[np.argsort(p[inliers], kind="stable")[:SAMPLE]]
    rest = np.delete(p, sample)
    return pairs * num_tests(n) * tail_at_least(rest, k - SAMPLE)


def guided_nfa(n_guided: int, hits: int, band: float, threshold: float, hypotheses: int, pairs: int = 1) -> float:
    """NFA of `hits` of `n_guided` guided matches falling within one threshold of a circle they were sought within
    `band` thresholds of (chance sin t / sin(band t) each; module docstring, 5)."""
    if hits <= 0:
        return float("inf")
    q = math.sin(threshold) / math.sin(band * threshold)
    return pairs * hypotheses * tail_at_least(np.full(n_guided, q), hits)


def chance_per_match(bl_i: np.ndarray, bl_j: np.ndarray, theta: float, T: np.ndarray, threshold: float
                     ) -> np.ndarray:
    """(N,) per match, the share of the latitude circle of its levelled bearing in j (longitude uniform) within
    `threshold` of the epipolar circle the hypothesis (yaw θ, baseline T, levelled frames) gives its bearing in i.

    In j's frame the epipolar plane's unit normal is ν = R_y(θ) (T × b_i) / |·|; a bearing at latitude λ and
    longitude ψ has ν·b = ν_y sin λ + cos λ √(ν_x² + ν_z²) cos(ψ − ψ₀) = a + c cos u, and |ν·b| ≤ sin t on the
    share (acos(lo) − acos(hi)) / π of u, lo, hi = (∓ sin t − a) / c clipped to [−1, 1]. Only the j side of the
    symmetric error is required, and the side of the baseline is ignored: both make the chance larger (conservative).
    """
    R = yaw_rotation(theta)
    normals = normalize(np.cross(T, bl_i)) @ R.T
    sin_lat = bl_j[:, 1]
    cos_lat = np.sqrt(np.maximum(1.0 - sin_lat**2, 0.0))
    a = normals[:, 1] * sin_lat
    c = np.sqrt(normals[:, 0]**2 + normals[:, 2]**2) * cos_lat
    s = math.sin(threshold)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.clip((-s - a) / c, -1.0, 1.0)
        hi = np.clip((s - a) / c, -1.0, 1.0)
    share = (np.arccos(lo) - np.arccos(hi)) / np.pi
    # c ≈ 0: the latitude circle is (nearly) a point or the plane horizontal; it fits wholly or not at all
    flat = c < 1e-12
    share[flat] = (np.abs(a[flat]) <= s).astype(float)
    return np.clip(share, 0.0, 1.0)


# --------------------------------------------------------------------------------------------- geometry
def max_elevation(height_spread_m: float, min_baseline_m: float) -> float:
    """Largest baseline elevation (radians) of two cameras whose heights differ by at most height_spread_m over a
    baseline of at least min_baseline_m."""
    return math.atan2(height_spread_m, min_baseline_m)


def informative(bl: np.ndarray, band: float) -> np.ndarray:
    """Bearings (levelled, y vertical) off the horizon band and off the polar caps of half-width `band`."""
    lat = np.arcsin(np.clip(np.abs(bl[:, 1]), 0.0, 1.0))
    return (lat > band) & (lat < np.pi / 2 - band)


def baseline(phi, e=0.0) -> np.ndarray:
    """Unit baseline of azimuth φ and elevation e in the levelled frame (y vertical), batched."""
    phi, e = np.asarray(phi, np.float64), np.asarray(e, np.float64)
    return np.stack(np.broadcast_arrays(np.cos(e) * np.cos(phi), np.sin(e), np.cos(e) * np.sin(phi)), axis=-1)


def errors_and_front(bl_i: np.ndarray, bl_j: np.ndarray, theta: float, T: np.ndarray):
    """Symmetric angular epipolar errors (N,) and in-front-of-both masks (N,) of the levelled matches under yaw θ and
    baseline T (batched over T's leading axes: (..., 3) gives (..., N)). With c = R_y(θ)ᵀ b_j: the sine of b_i's
    angle to the plane (T, c) is |T·(c × b_i)| / |T × c|, of c's to the plane (T, b_i) the same over |T × b_i|;
    the midpoint depths of a b_i − b c = T have the signs of T·(b_i − c (c·b_i)) and T·((b_i·c) b_i − c)."""
    c = bl_j @ yaw_rotation(theta)  # rows: R_y(θ)ᵀ b_j
    m = np.cross(c, bl_i)
    cb = np.einsum("na,na->n", c, bl_i)
    u = bl_i - c * cb[:, None]
    w = bl_i * cb[:, None] - c
    num = np.abs(T @ m.T)
    tc, tb = T @ c.T, T @ bl_i.T
    den = np.sqrt(np.maximum(1.0 - np.maximum(tc**2, tb**2), 1e-24))
    err = np.arcsin(np.minimum(num / den, 1.0))
    return err, (T @ u.T > 0) & (T @ w.T > 0)


@dataclass(frozen=True, kw_only=True)
class _Hypothesis:
    theta: float
    T: np.ndarray  # (3,) unit, levelled frame of i
    count: int


COARSE_STEPS = 8  # the coarse scan's grid step, in thresholds; the fine scan about its best cells is one threshold


def _grid_counts(bl_i, bl_j, thetas, T, tolerance):
    """(len(thetas), *T.shape[:-1]) matches within `tolerance` and in front of both cameras, per hypothesis
    (`errors_and_front` in float32, on sines: the scan's hot loop)."""
    shape = T.shape[:-1]
    Tf = T.reshape(-1, 3).astype(np.float32)
    b_i = bl_i.astype(np.float32)
    tb2 = (Tf @ b_i.T) ** 2
    limit = np.float32(math.sin(tolerance) ** 2)
    counts = np.zeros((len(thetas), len(Tf)), np.int32)
    for a, theta in enumerate(thetas):
        c = (bl_j @ yaw_rotation(theta)).astype(np.float32)
        cb = np.einsum("na,na->n", c, b_i)
        num = Tf @ np.cross(c, b_i).T
        num *= num
        tc = Tf @ c.T
        den = 1.0 - np.maximum(tc * tc, tb2)
        ok = num <= limit * den
        tb = Tf @ b_i.T
        ok &= tb - tc * cb > 0  # T·(b_i − c (c·b_i)) > 0: in front of camera i
        ok &= tb * cb - tc > 0  # T·((b_i·c) b_i − c) > 0: in front of camera j
        counts[a] = ok.sum(axis=-1)
    return counts.reshape((len(thetas),) + shape)


def _grid(step: float, max_elev: float):
    levels = max(0, int(np.floor(max_elev / step + 0.5)))
    return np.arange(0.0, 2 * np.pi, step), np.arange(0.0, 2 * np.pi, step), step * np.arange(-levels, levels + 1)


def scan(bl_i: np.ndarray, bl_j: np.ndarray, threshold: float, max_elev: float, keep: int = 3) -> list[_Hypothesis]:
    """The `keep` best distinct hypotheses over yaw, azimuth and elevation by the number of matches in front of both
    cameras and within threshold + step of their circles (the truth lies within half a step in each unknown):
    a coarse grid `COARSE_STEPS` thresholds apart, then a grid one threshold apart about its best cells."""
    coarse = COARSE_STEPS * threshold
    thetas, phis, elevations = _grid(coarse, max_elev)
    T = baseline(phis[None, :], elevations[:, None])  # (E, P, 3)
    counts = _grid_counts(bl_i, bl_j, thetas, T, threshold + coarse)
    found: list[_Hypothesis] = []
    flat = counts.copy()
    fine = np.arange(-(COARSE_STEPS // 2), COARSE_STEPS // 2 + 1) * threshold
    _, _, fine_elevations = _grid(threshold, max_elev)
    for _ in range(3 * keep):
        a, e, p = np.unravel_index(int(np.argmax(flat)), flat.shape)
        if flat[a, e, p] <= SAMPLE:
            break
        # suppress the cell's neighbours (one hypothesis), then search the cell finely
        rows = np.arange(a - 1, a + 2) % len(thetas)
        cols = np.arange(p - 1, p + 2) % len(phis)
        flat[np.ix_(rows, np.arange(len(elevations)), cols)] = 0
        local_t = thetas[a] + fine
        local_T = baseline((phis[p] + fine)[None, :], fine_elevations[:, None])
        local = _grid_counts(bl_i, bl_j, local_t, local_T, 2 * threshold)  # within threshold + step
        la, le, lp = np.unravel_index(int(np.argmax(local)), local.shape)
        found.append(_Hypothesis(theta=float(local_t[la]), T=local_T[le, lp], count=int(local[la, le, lp])))
    found.sort(key=lambda h: -h.count)
    distinct: list[_Hypothesis] = []
    for h in found:
        if all(abs(np.angle(np.exp(1j * (h.theta - d.theta)))) > coarse or h.T @ d.T < np.cos(coarse)
               for d in distinct) and len(distinct) < keep:
            distinct.append(h)
    return distinct


LO_STEPS = 4  # local optimisation rounds (two_view's shrinking-threshold schedule)


def _pose_of(F_level: np.ndarray, bl_i, bl_j, threshold: float) -> tuple[float, np.ndarray]:
    """(θ, T) of a levelled upright F, T's sign the one that puts more of its inliers in front of both cameras."""
    theta, T, _ = upright.upright_decompose(F_level)
    err, front = errors_and_front(bl_i, bl_j, theta, np.stack([T, -T]))
    good = ((err <= threshold) & front).sum(axis=1)
    return float(theta), (T if good[0] >= good[1] else -T)


def _refined(bl_i, bl_j, hyp: _Hypothesis, threshold: float, max_elev: float) -> _Hypothesis:
    """The hypothesis after the upright local optimisation (`upright._local_optimization_upright`) and the robust
    refinement on its inliers, its elevation clamped to ±max_elev, counted at the threshold."""
    F0 = upright.upright_f(hyp.theta, hyp.T)
    F, _ = upright._local_optimization_upright(bl_i, bl_j, F0, threshold, LO_STEPS)
    theta, T = _pose_of(F, bl_i, bl_j, threshold)
    err, front = errors_and_front(bl_i, bl_j, theta, T)
    good = (err <= threshold) & front
    if good.sum() >= upright.MIN_LINEAR_POINTS:
        theta, T = _pose_of(upright.refine_f_upright(upright.upright_f(theta, T), bl_i[good], bl_j[good], threshold),
                            bl_i, bl_j, threshold)
    elev = float(np.clip(np.arcsin(np.clip(T[1], -1, 1)), -max_elev, max_elev))
    T = baseline(np.arctan2(T[2], T[0]), elev)
    err, front = errors_and_front(bl_i, bl_j, theta, T)
    return _Hypothesis(theta=theta, T=T, count=int(((err <= threshold) & front).sum()))


def _walls_agree(h: _Hypothesis, walls, L_i: np.ndarray, L_j: np.ndarray) -> bool:
    """Whether the hypothesis' rotation carries i's wall axis onto j's modulo 90° within the walls' tolerance (False
    without walls)."""
    if walls is None:
        return False
    from fullview.sfm import wall_check

    axis_i, axis_j, gravity_j, tolerance = walls
    R = upright.unlevel_rotation(yaw_rotation(h.theta), L_i, L_j)
    return abs(wall_check.wall_residual_deg(R, axis_i, axis_j, gravity_j)) <= tolerance


def _distinct(a: _Hypothesis, b: _Hypothesis, tolerance: float) -> bool:
    """Rotations further apart than `tolerance` in yaw. Not the baseline: with few inliers its direction is
    uncertain by degrees (a rival that only moves it explains the same matches; registration's direction check,
    `registration.max_direction_residual_deg`, judges it), while the yaw is what a wrong pose gets wrong."""
    return bool(abs(np.angle(np.exp(1j * (a.theta - b.theta)))) > tolerance)


def _band_candidates(bl_i, bl_j, theta: float, T: np.ndarray, width: float):
    """`allowed` for match_descriptors: feature r of i may match feature c of j when c lies within `width` of r's
    epipolar circle and the match is in front of both cameras."""
    c = (bl_j @ yaw_rotation(theta)).astype(np.float32)  # R_y(θ)ᵀ b_j
    normals = normalize(np.cross(T, bl_i)).astype(np.float32)
    tb = (bl_i @ T).astype(np.float32)
    tc = (c @ T.astype(np.float32))
    limit = np.float32(math.sin(width))
    b32 = bl_i.astype(np.float32)

    def allowed(start, stop):
        near = np.abs(normals[start:stop] @ c.T) <= limit
        G = b32[start:stop] @ c.T
        front = (tb[start:stop, None] - tc[None, :] * G > 0) & (tb[start:stop, None] * G - tc[None, :] > 0)
        return near & front
    return allowed


def guided_matches(desc_i, desc_j, bl_i, bl_j, theta: float, T: np.ndarray, width: float, ratio: float,
                   rows_ok=None, cols_ok=None) -> np.ndarray:
    """(M, 2) features matched again along the hypothesis' epipolar circles (`_band_candidates`; the ratio test and
    the mutual check among those candidates only), among the allowed features (rows_ok, cols_ok; None: all)."""
    rows = np.arange(len(desc_i)) if rows_ok is None else np.flatnonzero(rows_ok)
    cols = np.arange(len(desc_j)) if cols_ok is None else np.flatnonzero(cols_ok)
    allowed = _band_candidates(bl_i[rows], bl_j[cols], theta, T, width)
    found = match_descriptors(desc_i[rows], desc_j[cols], MatchesOptions(ratio=ratio, mutual=True),
                              block_rows=512, allowed=allowed)
    return np.column_stack([rows[found[:, 0]], cols[found[:, 1]]]) if len(found) else np.zeros((0, 2), np.int64)


# --------------------------------------------------------------------------------------------- the test
def verify_wide(bear_i: np.ndarray, bear_j: np.ndarray, matches: np.ndarray, gravity_i: np.ndarray,
                gravity_j: np.ndarray, threshold: float, *, max_elev: float, epsilon: float, pairs: int = 1,
                descriptors=None, band: float = 3.0, ratio: float = 0.9, keep: int = 3,
                seeds: tuple[np.ndarray, ...] = (), walls=None) -> WideResult:
    """The a-contrario verification of one upright pair (module docstring). bear_*: (N, 3) bearings of the
    features (SIFT first; descriptors, when given, (desc_i, desc_j) of the SIFT features), matches (M, 2) raw
    matches, gravity_* the images' gravity (camera frame), threshold in radians, pairs: pairs this test is run on in
    the dataset (the NFA's multiplicity), seeds: F of the original bearings to try beside the scan (the normal
    filter's fit), walls: (axis_i, axis_j, gravity_j, tolerance_deg) of the images' Manhattan frames
    (`wall_check.wall_residual_deg`) or None.

    The hypothesis of least NFA wins only if it is also unique: against every distinct hypothesis B, its inliers
    that B does not explain must be meaningful on their own (NFA over the matches outside B's inliers < ε). Two
    rotations several degrees apart that explain the same matches (points near the epipoles of a straight walk) leave
    the yaw undetermined: not verified. The walls, where both images have an axis, are evidence independent of the
    matches: among the meaningful hypotheses one whose yaw agrees with them (modulo 90°) is preferred, and rivals
    whose yaw they contradict are not rivals of one they agree with."""
    L_i, L_j = upright.leveling_rotation(gravity_i), upright.leveling_rotation(gravity_j)
    bl_i, bl_j = normalize(bear_i) @ L_i.T, normalize(bear_j) @ L_j.T
    empty = np.zeros((0, 2), np.int64)
    none = WideResult(accepted=False, F=np.zeros((3, 3)), inliers=empty, yaw_deg=float("nan"),
                      elevation_deg=float("nan"), informative=0, informative_inliers=0, nfa=float("inf"), guided=0,
                      guided_hits=0, guided_nfa=float("inf"))
    width = threshold + max_elev
    A_i, A_j = bl_i[matches[:, 0]], bl_j[matches[:, 1]]
    info = informative(A_i, width) & informative(A_j, width)
    if info.sum() <= SAMPLE + 1:
        return none
    m_i, m_j = A_i[info], A_j[info]
    starts = scan(m_i, m_j, threshold, max_elev, keep)
    for F in seeds:
        if np.abs(F).sum() > 0:
            theta, T = _pose_of(L_i @ F @ L_j.T, A_i, A_j, threshold)
            starts.append(_Hypothesis(theta=theta, T=T, count=0))
    hyps = [_refined(m_i, m_j, h, threshold, max_elev) for h in starts]
    if not hyps:
        return none
    scored = []
    for h in hyps:
        err, front = errors_and_front(A_i, A_j, h.theta, h.T)
        fit = (err <= threshold) & front
        p = chance_per_match(A_i, A_j, h.theta, h.T, threshold)
        scored.append((nfa(p, fit, pairs), h, fit, p))
    agrees = [_walls_agree(h, walls, L_i, L_j) for _, h, _, _ in scored]
    # the least NFA, among the meaningful hypotheses the walls agree with when there are such
    order = sorted(range(len(scored)), key=lambda k: (not (agrees[k] and scored[k][0] < epsilon), scored[k][0]))
    scored, agrees = [scored[k] for k in order], [agrees[k] for k in order]
    best_nfa, best, fit, p = scored[0]
    # uniqueness: the best's evidence beyond each distinct rival's inliers (rivals the walls rule out do not count)
    unique_nfa = max([nfa(p[~f], fit[~f], pairs) for (_, h, f, _), ok in zip(scored[1:], agrees[1:])
                      if _distinct(h, best, COARSE_STEPS * threshold) and (ok or not agrees[0])], default=0.0)
    g_n = g_k = 0
    g_nfa = float("inf")
    guided = empty
    if descriptors is not None and best_nfa < epsilon:  # (only logged: not computed for a pair chance explains)
        desc_i, desc_j = descriptors
        rows_ok = informative(bl_i[:len(desc_i)], width)
        rows_ok[matches[matches[:, 0] < len(desc_i), 0]] = False  # features with a raw match: not new evidence
        cols_ok = informative(bl_j[:len(desc_j)], width)
        found = guided_matches(desc_i, desc_j, bl_i, bl_j, best.theta, best.T, band * threshold, ratio, rows_ok,
                               cols_ok)
        err, front = errors_and_front(bl_i[found[:, 0]], bl_j[found[:, 1]], best.theta, best.T)
        g_n, g_k = len(found), int(((err <= threshold) & front).sum())
        g_nfa = guided_nfa(g_n, g_k, band, threshold, 1, pairs)
    # The guided matches' NFA is reported, not trusted: a pose 4.3° off the truth of an overlapping pair had 2.7e-12
    # (the true matches lie in its band and near its circles too): it tells that the pair overlaps, not its pose.
    accepted = bool(best_nfa < epsilon and unique_nfa < epsilon)
    result = dict(F=upright.unlevel_f(upright.upright_f(best.theta, best.T), L_i, L_j),
                  yaw_deg=float(np.degrees(best.theta)) % 360.0,
                  elevation_deg=float(np.degrees(np.arcsin(np.clip(best.T[1], -1, 1)))), informative=int(info.sum()),
                  informative_inliers=int((fit & info).sum()), nfa=best_nfa, guided=g_n, guided_hits=g_k,
                  guided_nfa=g_nfa, unique_nfa=unique_nfa)
    if not accepted:
        return WideResult(accepted=False, inliers=empty, **result)
    theta, T = best.theta, best.T
    if descriptors is not None:
        # the final pose: refined on the raw matches and the guided ones of the accepted hypothesis
        guided = guided_matches(desc_i, desc_j, bl_i, bl_j, theta, T, band * threshold, ratio)
        pool = np.concatenate([matches, guided])
        refined = _refined(bl_i[pool[:, 0]], bl_j[pool[:, 1]], best, threshold, max_elev)
        if not _distinct(refined, best, COARSE_STEPS * threshold):  # the guided matches refine, never move, the pose
            theta, T = refined.theta, refined.T
    pool = np.concatenate([matches, guided]) if len(guided) else matches
    err, front = errors_and_front(bl_i[pool[:, 0]], bl_j[pool[:, 1]], theta, T)
    pool = np.unique(pool[(err <= threshold) & front], axis=0)
    result.update(F=upright.unlevel_f(upright.upright_f(theta, T), L_i, L_j),
                  yaw_deg=float(np.degrees(theta)) % 360.0,
                  elevation_deg=float(np.degrees(np.arcsin(np.clip(T[1], -1, 1)))))
    return WideResult(accepted=True, inliers=pool, **result)


# --------------------------------------------------------------------------------------------- the filter's pass
def verify_rejected(options, obs, raw, gravity, results, descriptors, frames=None
                    ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """{pair k: (F, inliers)} ({} unless `options.wide_pairs`) of the upright pairs the normal fit rejected
    (`results`: the filter's per-pair results, read for inliers, seeded, no_baseline and F) that the wide test
    verifies. obs: per image bearings
    (`Workspace.load_observations`), raw: the raw matches, gravity (N, 3) (NaN: unknown), descriptors(n): image n's
    SIFT descriptors, frames: the images' Manhattan frames (the filter's `_gravity`: axis, its error, the gravity
    refitted with it; NaN where unknown) or None. The NFA's multiplicity is the number of pairs tested, so that `options.wide_false_alarms`
    bounds the wrong pairs expected over the whole dataset."""
    from fullview.sfm.baseline import has_no_baseline

    threshold = math.radians(options.threshold_deg)
    max_elev = max_elevation(options.wide_height_spread_m, options.wide_min_baseline_m)
    epsilon, band = options.wide_false_alarms, options.wide_guided_band
    if not options.wide_pairs:
        return {}
    tried = [k for k, ((i, j), r) in enumerate(zip(raw.pairs, results))
             if not len(r.inliers) and not r.seeded and not r.no_baseline and len(raw.matches[k]) > SAMPLE + 1
             and np.isfinite(gravity[i]).all() and np.isfinite(gravity[j]).all()]
    found = {}
    for k in tried:
        i, j = raw.pairs[k]
        walls = None
        if frames is not None and np.isfinite(frames[0][i]).all() and np.isfinite(frames[0][j]).all():
            from fullview.sfm import wall_check

            walls = (frames[0][i], frames[0][j], frames[2][j], wall_check.tolerance_deg(frames[1][i], frames[1][j]))
        res = verify_wide(obs[i]["bearings"], obs[j]["bearings"], raw.matches[k], gravity[i], gravity[j], threshold,
                          max_elev=max_elev, epsilon=epsilon, pairs=len(tried),
                          descriptors=(descriptors(i), descriptors(j)), band=band,
                          ratio=options.guided_ratio, seeds=(results[k].F,), walls=walls)
        log.info("wide pair %d-%d: %d raw, %d informative, %d of them inliers, NFA %.2g, guided %d/%d NFA %.2g, "
                 "rival NFA %.2g: %s", i, j, len(raw.matches[k]), res.informative, res.informative_inliers, res.nfa,
                 res.guided_hits, res.guided, res.guided_nfa, res.unique_nfa,
                 "verified" if res.accepted else "not verified")
        if res.accepted and not has_no_baseline(obs[i]["bearings"][res.inliers[:, 0]],
                                                obs[j]["bearings"][res.inliers[:, 1]], threshold):
            found[k] = (res.F, res.inliers)
    return found
