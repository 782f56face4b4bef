"""Epipolar geometry on the sphere: F estimation, robust fitting, epipoles and relative pose.

The report's constraint is ``b_iᵀ F b_j = 0`` with ``F = [T]× R⁻¹`` where ``R = R_j_from_i`` and ``T`` is camera j's
centre in camera i's frame; in COLMAP terms ``F = E_j_from_iᵀ``. For calibrated spherical cameras F is an essential
matrix, so every estimate is projected onto the essential manifold (singular values 1, 1, 0).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from fullview.sfm.options import FilterOptions
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize, skew, tangent_basis

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------- linear estimation
def _design_matrix(b_i: np.ndarray, b_j: np.ndarray) -> np.ndarray:
    """Rows of the linear system b_iᵀ F b_j = 0 in the unknown vec(F) (row-major)."""
    return (b_i[..., :, None] * b_j[..., None, :]).reshape(b_i.shape[:-1] + (9,))


def project_to_essential(F: np.ndarray) -> np.ndarray:
    """Nearest essential matrix (singular values 1, 1, 0), batched over leading axes."""
    U, _, Vt = np.linalg.svd(F)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def estimate_f_linear(b_i: np.ndarray, b_j: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Normalised 8-point algorithm on bearings (unit vectors need no further scaling).

    Works for (N, 3) inputs or batched (B, N, 3) inputs; returns (3, 3) or (B, 3, 3) essential matrices.
    """
    A = _design_matrix(normalize(b_i), normalize(b_j))
    if weights is not None:
        A = A * weights[..., :, None]
    # The null vector of A is the eigenvector of AᵀA (9×9) with the smallest eigenvalue: cheap for any N.
    _, vecs = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)
    F = vecs[..., :, 0].reshape(A.shape[:-2] + (3, 3))
    return project_to_essential(F)


# --------------------------------------------------------------------------------------------- errors
def _epipolar_sines(Fs: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, design: np.ndarray) -> np.ndarray:
    """(B, N) sine of the larger of each correspondence's two angles to the epipolar circles, for F (B, 3, 3).

    Three matrix products (the normals of all hypotheses at once, and b_iᵀ F b_j as vec(F) against the design
    matrix) rather than stacked 3×3 products: this scores every RANSAC hypothesis."""
    count, n = len(Fs), len(b_i)
    n_i = (Fs.reshape(3 * count, 3) @ b_j.T).reshape(count, 3, n)  # normals of the epipolar planes in camera i
    n_j = (np.swapaxes(Fs, 1, 2).reshape(3 * count, 3) @ b_i.T).reshape(count, 3, n)  # ... in camera j
    num = np.abs(Fs.reshape(count, 9) @ design.T)
    n_i *= n_i
    n_j *= n_j
    norm2 = np.minimum(n_i.sum(axis=1), n_j.sum(axis=1))  # the smaller normal gives the larger angle
    num /= np.sqrt(np.maximum(norm2, 1e-24))
    return num


def epipolar_angular_errors(F: np.ndarray, b_i: np.ndarray, b_j: np.ndarray) -> np.ndarray:
    """Symmetric angular distance (radians) of each bearing to the other's epipolar great circle.

    The epipolar plane of b_j in camera i has normal F b_j; b_i's angle to that plane is asin(|b_i·n|/|n|).
    Returns the larger of the two angles. Batched: F (B,3,3) with bearings (N,3) gives (B, N).
    """
    F = np.asarray(F, dtype=np.float64)
    sines = _epipolar_sines(F.reshape(-1, 3, 3), b_i, b_j, _design_matrix(b_i, b_j))
    return np.arcsin(np.minimum(sines, 1.0)).reshape(F.shape[:-2] + (len(b_i),))


def _msac_scores(errors: np.ndarray, threshold: float) -> np.ndarray:
    """MSAC cost (lower is better): truncated squared error."""
    return np.minimum(errors, threshold) ** 2


SCORE_CHUNK = 64  # hypotheses scored together: their (64, 3, N) normals stay in cache


def msac_costs(Fs: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, threshold: float) -> np.ndarray:
    """(B,) summed MSAC cost of hypotheses Fs (B, 3, 3): the same figure as `_msac_scores(epipolar_angular_errors)`
    summed, cheaper: the arcsine is taken only below the threshold (above it every error costs threshold²)."""
    design = _design_matrix(b_i, b_j)
    sin_threshold, out = np.sin(threshold), np.empty(len(Fs))
    for start in range(0, len(Fs), SCORE_CHUNK):
        sines = _epipolar_sines(Fs[start:start + SCORE_CHUNK], b_i, b_j, design)
        inside = sines < sin_threshold
        errors = np.arcsin(sines[inside])
        scores = np.full(sines.shape, threshold * threshold)
        scores[inside] = errors * errors
        out[start:start + SCORE_CHUNK] = scores.sum(axis=1)
    return out


# --------------------------------------------------------------------------------------------- robust estimation
@dataclass(kw_only=True)
class RansacOptions:
    threshold_rad: float  # inlier threshold on the angular epipolar error
    max_iterations: int = FilterOptions.max_iterations  # hard cap on hypotheses (default from the settings)
    min_iterations: int = 100  # never stop earlier than this
    confidence: float = FilterOptions.confidence  # adaptive stopping confidence (default from the settings)
    batch_size: int = 256  # hypotheses evaluated together (vectorised)
    head_share: float = 0.25  # guided samples draw from this leading share of the (quality-ordered) matches
    sample_pool: int = 0  # samples draw from this many leading matches only (the strict ones); 0 = all of them
    local_optimization_steps: int = 4  # iterative re-fits on inliers of each new best model
    refine: bool = True  # final non-linear refinement of R, t on the inliers
    seed: int = FilterOptions.seed  # random seed for sampling (default from the settings)


@dataclass(kw_only=True)
class FResult:
    F: np.ndarray  # (3, 3) essential matrix, b_iᵀ F b_j = 0
    inliers: np.ndarray  # (N,) bool
    errors: np.ndarray  # (N,) angular epipolar error, radians
    iterations: int  # hypotheses drawn (0 when seeded by hand points)


LO_THRESHOLD_SCHEDULE = (3.0, 2.0, 1.5, 1.0)  # inlier-set thresholds of the LO re-fits, in units of the threshold


def _local_optimization(b_i, b_j, F, threshold, steps, fit=None, min_points: int = 8):
    """LO step: weighted re-fits on inlier sets chosen at a shrinking threshold; keep the best-scoring model.

    Starting loose lets a model from a noisy minimal sample pull in the inliers it narrowly misses. `fit(b_i, b_j,
    weights)` is the linear re-fit (the 8-point `estimate_f_linear` by default; the upright model passes its own),
    which needs `min_points` inliers.
    """
    fit = estimate_f_linear if fit is None else fit
    errors = epipolar_angular_errors(F, b_i, b_j)  # of the current model: scored, then its inliers re-fitted
    best_F, best_cost = F, _msac_scores(errors, threshold).sum()
    schedule = LO_THRESHOLD_SCHEDULE + (1.0,) * max(0, steps - len(LO_THRESHOLD_SCHEDULE))
    for factor in schedule[:max(steps, 1)]:
        inliers = errors < factor * threshold
        if inliers.sum() < min_points:
            break
        # Cauchy-like weights so that borderline inliers pull less than clean ones.
        w = 1.0 / (1.0 + (errors[inliers] / (factor * threshold)) ** 2)
        current = fit(b_i[inliers], b_j[inliers], w)
        errors = epipolar_angular_errors(current, b_i, b_j)
        cost = _msac_scores(errors, threshold).sum()
        if cost < best_cost:
            best_F, best_cost = current, cost
    return best_F, best_cost


def required_iterations(inlier_ratio: float, confidence: float, sample_size: int = 8) -> float:
    """Samples needed to draw an all-inlier minimal sample with the given confidence (the RANSAC bound)."""
    p = inlier_ratio**sample_size
    if p <= 1e-12:
        return np.inf
    if p >= 1.0:
        return 0.0
    return np.log(1.0 - confidence) / np.log(1.0 - p)


def sample_pool(n: int, options: RansacOptions) -> int:
    """How many leading matches a search draws its samples from: `options.sample_pool`, all when 0 or larger.

    Why: on noisy panoramas the matches are taken at a looser ratio test (`matches.noisy_ratio`) to win back true
    matches the noise pushed past the strict one, and most of the added ones are wrong. Drawn only from the strict
    head, hypotheses are as likely to be all-inlier as without them, while every match still counts towards a
    hypothesis' score and inliers."""
    return n if not options.sample_pool else min(n, options.sample_pool)


def _draw_samples(rng: np.random.Generator, batch: int, n: int, head_share: float) -> np.ndarray:
    """(batch, 8) distinct indices; half the samples come from the first `head_share` of the correspondences.

    Matches arrive ordered by distinctiveness, and the head holds a larger share of inliers, so guided samples find a
    good model far sooner (PROSAC's idea); the other half samples uniformly, so a bad ordering costs at most 2x.
    """
    head = max(16, int(np.ceil(head_share * n)))
    pool = np.where(np.arange(batch) % 2 == 0, min(head, n), n)[:, None]
    keys = rng.random((batch, n))
    keys[np.arange(n)[None, :] >= pool] = 2.0  # outside this sample's pool: never among the 8 smallest
    return np.argpartition(keys, 7, axis=1)[:, :8]


def ransac_f(b_i: np.ndarray, b_j: np.ndarray, options: RansacOptions) -> FResult:
    """LO-MSAC on bearings with the 8-point minimal solver, angular errors, optional refinement."""
    n = len(b_i)
    if n < 8:
        raise ValueError(f"need at least 8 correspondences for F, got {n}")
    rng = np.random.default_rng(options.seed)
    thr = options.threshold_rad
    pool = sample_pool(n, options)
    if pool < 8:
        raise ValueError(f"need at least 8 correspondences to sample F from, got {pool}")
    best_F, best_cost, drawn = None, np.inf, 0
    while drawn < options.max_iterations:
        batch = min(options.batch_size, options.max_iterations - drawn)
        samples = _draw_samples(rng, batch, pool, options.head_share)
        Fs = estimate_f_linear(b_i[samples], b_j[samples])
        costs = msac_costs(Fs, b_i, b_j, thr)
        drawn += batch
        k = int(np.argmin(costs))
        if costs[k] < best_cost:
            best_F, best_cost = _local_optimization(b_i, b_j, Fs[k], thr, options.local_optimization_steps)
        # the inlier ratio among the matches samples are drawn from
        ratio = float((epipolar_angular_errors(best_F, b_i[:pool], b_j[:pool]) < thr).mean())
        if drawn >= options.min_iterations and drawn >= required_iterations(ratio, options.confidence):
            break
    return _finish(b_i, b_j, best_F, thr, options.refine, drawn)


HAND_INLIER_SHARE = 0.8  # a seeded fit must keep this share of the hand points within the threshold


def fit_f_seeded(b_i_seed: np.ndarray, b_j_seed: np.ndarray, b_i: np.ndarray, b_j: np.ndarray,
                 threshold_rad: float, refine: bool = True) -> FResult:
    """The report's data augmentation: F from hand points, keep the matches near its epipolar circles, re-fit."""
    if len(b_i_seed) < 8:
        raise ValueError(f"need at least 8 hand points for a seeded F, got {len(b_i_seed)}")
    F_seed = estimate_f_linear(b_i_seed, b_j_seed)
    # Hand points are kept as observations of the final fit: they are reliable, and they anchor the re-estimate.
    all_i, all_j = np.concatenate([b_i_seed, b_i]), np.concatenate([b_j_seed, b_j])
    F, _ = _local_optimization(all_i, all_j, F_seed, threshold_rad, steps=4)
    result = _finish(all_i, all_j, F, threshold_rad, refine, 0)
    m = len(b_i_seed)
    if result.inliers[:m].mean() < HAND_INLIER_SHARE:
        # The matches pulled F away from the hand points (measured on plain-walled rooms: SIFT outliers along one
        # structure outvoted 59 hand points and rotated the pose by 40°). Hand points are trusted: keep their F and
        # only the matches near its circles.
        result = _finish(all_i, all_j, F_seed, threshold_rad, False, 0)
        refined = _finish(all_i, all_j, F_seed, threshold_rad, refine, 0)
        if refined.inliers[:m].mean() >= HAND_INLIER_SHARE:
            result = refined
    return FResult(F=result.F, inliers=result.inliers[m:], errors=result.errors[m:], iterations=0)


def fit_f_from(F_start: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, threshold_rad: float,
               refine: bool = True) -> FResult:
    """LO-MSAC's local optimisation and refinement started from a given F instead of sampled ones: the matches' own
    fit near an estimate (a few clicks' F), at the cost of a few linear fits."""
    if len(b_i) < 8:
        raise ValueError(f"need at least 8 correspondences for F, got {len(b_i)}")
    F, _ = _local_optimization(b_i, b_j, F_start, threshold_rad, steps=len(LO_THRESHOLD_SCHEDULE))
    return _finish(b_i, b_j, F, threshold_rad, refine, 0)


def iterations_to_beat(inliers: int, n: int, options: RansacOptions, sample_size: int = 8) -> RansacOptions:
    """`options` with the hypothesis cap a search needs to find a model with more than `inliers` of `n` inliers with
    the options' confidence: a model that would win has at least that inlier ratio, so more samples cannot help."""
    needed = required_iterations(inliers / max(n, 1), options.confidence, sample_size)
    cap = options.max_iterations if not np.isfinite(needed) else int(np.ceil(needed))
    return replace(options, max_iterations=min(options.max_iterations, max(options.min_iterations, cap)))


def consistent_with_pose(b_i: np.ndarray, b_j: np.ndarray, R_j_from_i: np.ndarray, t_j_from_i: np.ndarray,
                         threshold_rad: float) -> np.ndarray:
    """(N,) whether each correspondence lies within `threshold_rad` of the epipolar circles of a known relative pose
    and in front of both cameras (the epipolar constraint alone accepts points behind them)."""
    if not len(b_i):
        return np.zeros(0, bool)
    F = R_j_from_i.T @ skew(t_j_from_i).T  # b_jᵀ [t]× R b_i = 0, written b_iᵀ F b_j = 0
    depth_i, depth_j = ray_depths(b_i, b_j, R_j_from_i, t_j_from_i)
    return (epipolar_angular_errors(F, b_i, b_j) < threshold_rad) & (depth_i > 0) & (depth_j > 0)


MAX_BASELINE_HYPOTHESES = 5000  # match pairs tried by `baseline_given_rotation` (all of them below this)
BASELINE_BLOCK = 256  # hypotheses scored at once


def baseline_given_rotation(b_i: np.ndarray, b_j: np.ndarray, R_j_from_i: np.ndarray, threshold_rad: float,
                            seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Unit ``t_j_from_i`` of a pair whose relative rotation is known (from rotation averaging), and (N,) its
    inliers (`consistent_with_pose`), from correspondences of which only a few may be true.

    With the rotation known, every match's rays span a plane holding the baseline, so two matches give it (up to
    sign, which cheirality decides): a 2-point RANSAC in which a pair with ten true matches among forty, too few for
    the 3-point upright or 5-point fits to stand out of chance, still does."""
    v = b_j @ R_j_from_i  # j's rays in frame i (Rᵀ b_j)
    n = normalize(np.cross(b_i, v))
    if len(n) < 2:
        return np.array([0.0, 0.0, 1.0]), np.zeros(len(n), bool)
    first, second = np.triu_indices(len(n), 1)
    if len(first) > MAX_BASELINE_HYPOTHESES:
        pick = np.random.default_rng(seed).choice(len(first), MAX_BASELINE_HYPOTHESES, replace=False)
        first, second = first[pick], second[pick]
    d = normalize(np.cross(n[first], n[second]))  # (H, 3) centre of j in frame i, up to sign
    d = d[np.linalg.norm(d, axis=1) > 0.5]
    d = np.concatenate([d, -d])
    # scored in blocks: (hypotheses, matches) tables stay small on pairs with thousands of raw matches
    count = np.concatenate([_plane_inliers(d[k:k + BASELINE_BLOCK], n, b_i, v, threshold_rad).sum(axis=1)
                            for k in range(0, len(d), BASELINE_BLOCK)] or [np.zeros(0, np.int64)])
    best = d[int(np.argmax(count))] if len(d) else np.array([0.0, 0.0, 1.0])
    for _ in range(3):  # refit: the direction closest to every inlier's plane
        inliers = _plane_inliers(best[None], n, b_i, v, threshold_rad)[0]
        if inliers.sum() < 2:
            break
        fit = np.linalg.svd(n[inliers])[2][2]
        best = fit if fit @ best > 0 else -fit
    t = -R_j_from_i @ best
    return t, consistent_with_pose(b_i, b_j, R_j_from_i, t, threshold_rad)


def _plane_inliers(d: np.ndarray, n: np.ndarray, b_i: np.ndarray, v: np.ndarray, threshold_rad: float) -> np.ndarray:
    """(H, N) whether centre direction d[h] (frame i) lies within the threshold of match k's epipolar plane (normal
    n[k]) with its point in front of both cameras (α b_i = d + β v, α, β > 0)."""
    close = np.abs(d @ n.T) < np.sin(threshold_rad)
    ea, eb, ab = d @ b_i.T, d @ v.T, np.einsum("ka,ka->k", b_i, v)
    det = np.maximum(1.0 - ab ** 2, 1e-12)
    alpha, beta = (ea - ab * eb) / det, (ab * ea - eb) / det
    return close & (alpha > 0) & (beta > 0)


MIN_SPREAD_RATIO = 0.015  # σ7 / σ1 of the 8-point system below which the points leave F undetermined


def points_determine_f(b_i: np.ndarray, b_j: np.ndarray) -> bool:
    """Whether correspondences (>= 8) pin F down on their own: not coplanar or otherwise degenerate.

    Points on one plane (floor targets, one wall) leave a 3-dimensional family of F (rank 6 for the 8-point system),
    so their 7th singular value sits at the noise level; measured with 0.35° noise: σ7/σ1 < 0.007 for 95% of planar
    8-point sets, > 0.026 for 95% of general ones."""
    if len(b_i) < 8:
        return False
    s = np.linalg.svd(_design_matrix(normalize(b_i), normalize(b_j)), compute_uv=False)
    return bool(s[6] > MIN_SPREAD_RATIO * s[0])


POLISH_ROUNDS = 8  # at most this many refinements, each on the inliers of the one before
POLISH_SPAN = 3.0  # matches within this many thresholds enter the final refinement (the LO's loosest inlier set)


def _finish(b_i, b_j, F, threshold, refine, iterations, refine_fn=None, min_points: int = 8,
            polish: bool = False) -> FResult:
    """The result of a search: F refined on its inliers (soft-l1 loss), or with `polish` to a fixed point.

    Why polish: one refinement on the inliers of the search's model leaves F depending on which sample found it (its
    inliers are not those of the refined F, and borderline matches enter or leave). Polished, F is refined with a
    Cauchy loss on the matches within POLISH_SPAN thresholds (a match at the span's edge weighs 3%, so which
    borderline matches are in hardly matters) until its inliers no longer change: models from different samples in
    one basin end at the same F and inliers (a result that depends on the RANSAC seed is not a measurement). The
    soft-l1 refinement on the settled inliers follows: the Cauchy fit down-weights the matches near the threshold,
    which are real, and is less precise alone. The
    upright search polishes; the 8-point one does not (its refinement on a thousand matches per pair made the filter
    on the bench's 24-view room 40% slower). `refine_fn` (default `refine_f`) replaces the refinement."""
    refine_fn = refine_f if refine_fn is None else refine_fn
    errors = epipolar_angular_errors(F, b_i, b_j)
    if refine and (errors < threshold).sum() >= min_points and not polish:
        F = refine_fn(F, b_i[errors < threshold], b_j[errors < threshold], threshold)
        errors = epipolar_angular_errors(F, b_i, b_j)
    span, best = errors < POLISH_SPAN * threshold, None
    for _ in range(POLISH_ROUNDS if refine and polish and (errors < threshold).sum() >= min_points else 0):
        current = refine_fn(F, b_i[span], b_j[span], threshold, loss="cauchy")
        current_errors = epipolar_angular_errors(current, b_i, b_j)
        cost = _msac_scores(current_errors, threshold).sum()
        if best is None or cost < best[0]:
            best = (cost, current, current_errors)
        settled = np.array_equal(current_errors < threshold, errors < threshold)
        F, errors, span = current, current_errors, current_errors < POLISH_SPAN * threshold
        if settled:
            break
    if best is not None:  # the lowest-cost refinement: where the inlier sets cycle, whichever the cycle began at
        _, F, errors = best
        # Then the usual soft-l1 refinement on those inliers: the same set and start whatever the seed, and the
        # accuracy of the unpolished fit (the Cauchy loss alone under-weights the real matches near the threshold).
        F = refine_fn(F, b_i[errors < threshold], b_j[errors < threshold], threshold)
        errors = epipolar_angular_errors(F, b_i, b_j)
    return FResult(F=F, inliers=errors < threshold, errors=errors, iterations=iterations)



# --------------------------------------------------------------------------------------------- refinement
def _rotations_from_rotvecs(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, batched: (K, 3) rotation vectors -> (K, 3, 3)."""
    angle = np.linalg.norm(w, axis=1)
    small = angle < 1e-12
    axis = w / np.where(small, 1.0, angle)[:, None]
    K = skew(axis)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def _f_from_params(R0: np.ndarray, t0: np.ndarray, x: np.ndarray, tangent: np.ndarray | None = None) -> np.ndarray:
    """F = [T]× Rᵀ with R = exp(ω) R0 and T on the sphere around t0 (2 tangent parameters); x (5,) or (K, 5)."""
    u, v = tangent_basis(t0[None])[0] if tangent is None else tangent
    xs = np.atleast_2d(x)
    R = _rotations_from_rotvecs(xs[:, :3]) @ R0
    T = normalize(t0 + xs[:, 3:4] * u + xs[:, 4:5] * v)
    F = skew(T) @ np.swapaxes(R, 1, 2)
    return F[0] if np.ndim(x) == 1 else F


def _sine_residuals_batch(Fs: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, design: np.ndarray | None = None
                          ) -> np.ndarray:
    """(K, 2N) signed sines of both bearings' angles to the other's epipolar circle, for F (K, 3, 3); `design`:
    `_design_matrix(b_i, b_j)` when the caller already has it (a refinement evaluates the same bearings often)."""
    count, n = len(Fs), len(b_i)
    n_i = (Fs.reshape(3 * count, 3) @ b_j.T).reshape(count, 3, n)
    n_j = (np.swapaxes(Fs, 1, 2).reshape(3 * count, 3) @ b_i.T).reshape(count, 3, n)
    num = Fs.reshape(count, 9) @ (_design_matrix(b_i, b_j) if design is None else design).T
    return np.concatenate([num / np.sqrt((n_i * n_i).sum(axis=1)), num / np.sqrt((n_j * n_j).sum(axis=1))], axis=1)


def sine_residuals_with_jacobian(models, b_i: np.ndarray, b_j: np.ndarray):
    """`with_jacobian(x)` for `robust_levenberg_marquardt`: the sine residuals of F = models(x) and their forward
    difference Jacobian (scipy's '2-point' steps), the model and its perturbed copies evaluated in one batch
    (`models`: (K, P) parameters -> (K, 3, 3) F)."""
    design = _design_matrix(b_i, b_j)

    def with_jacobian(x):
        steps = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(x))
        rows = _sine_residuals_batch(models(np.vstack([x, x + np.diag(steps)])), b_i, b_j, design)
        return rows[0], ((rows[1:] - rows[0]) / steps[:, None]).T

    return with_jacobian


def refine_f(F: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, threshold: float, loss: str = "soft_l1") -> np.ndarray:
    """Non-linear refinement of (R, T) minimising angular epipolar errors with a robust loss.

    The Jacobian is a forward difference like scipy's '2-point', but its 5 perturbed models are evaluated in one
    batch with the residuals themselves (the refinement runs once per pair, and scipy's per-column calls dominated
    its cost); the robust solver is `robust_levenberg_marquardt`, which stands in for scipy's least_squares."""
    R, t = decompose_f_svd(F)[0]  # any of the four decompositions spans the same F up to sign
    T = -R.T @ t  # F = [T]× Rᵀ takes camera j's centre in camera i (starting from t itself began off F)
    tangent = tangent_basis(T[None])[0]
    with_jacobian = sine_residuals_with_jacobian(lambda xs: _f_from_params(R, T, xs, tangent), b_i, b_j)
    x = robust_levenberg_marquardt(with_jacobian, np.zeros(5), threshold / 2, loss)
    return project_to_essential(_f_from_params(R, T, x, tangent))


LM_MAX_EVALUATIONS = 50  # as scipy's max_nfev was
LM_TOLERANCE = 1e-8  # scipy's ftol / xtol / gtol defaults


def _soft_l1_cost(r: np.ndarray, f_scale: float) -> float:
    """scipy's soft_l1 cost: ½ f² Σ 2(√(1 + (r/f)²) − 1)."""
    return float(f_scale**2 * np.sum(np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0))


def _cauchy_cost(r: np.ndarray, f_scale: float) -> float:
    """scipy's cauchy cost: ½ f² Σ ln(1 + (r/f)²)."""
    return float(0.5 * f_scale**2 * np.sum(np.log1p((r / f_scale) ** 2)))


# loss -> (cost, IRLS weight ρ'(z) of z = (r/f)²)
LOSSES = {"soft_l1": (_soft_l1_cost, lambda z: 1.0 / np.sqrt(1.0 + z)),
          "cauchy": (_cauchy_cost, lambda z: 1.0 / (1.0 + z))}


def robust_levenberg_marquardt(with_jacobian, x0: np.ndarray, f_scale: float, loss: str = "soft_l1") -> np.ndarray:
    """Minimises the robust cost (`LOSSES`: soft_l1, or cauchy) of the residuals; `with_jacobian(x)` -> (r, J) in one
    evaluation.

    Iteratively reweighted Gauss-Newton (soft_l1 weights ρ'(z) = 1/√(1 + (r/f)²)) damped Levenberg-Marquardt style,
    stopping on scipy's ftol / xtol / gtol tests: its minimum is scipy's least_squares(loss="soft_l1") minimum
    (the same stationarity condition Jᵀ ρ' r = 0), without scipy's per-call machinery, which cost 2 ms of the
    F refinement's 2.5 ms per pair (README, "Fifth speed pass")."""
    cost_of, weight_of = LOSSES[loss]
    x = np.asarray(x0, float)
    r, J = with_jacobian(x)
    cost, damping = cost_of(r, f_scale), 1e-3
    for _ in range(LM_MAX_EVALUATIONS - 1):
        weights = weight_of((r / f_scale) ** 2)
        gradient = J.T @ (weights * r)
        if np.max(np.abs(gradient)) < LM_TOLERANCE:
            break
        normal = J.T @ (J * weights[:, None])
        step = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), -gradient)
        x_new = x + step
        r_new, J_new = with_jacobian(x_new)
        cost_new = cost_of(r_new, f_scale)
        if cost_new < cost:
            small = (cost - cost_new < LM_TOLERANCE * cost
                     or np.linalg.norm(step) < LM_TOLERANCE * (LM_TOLERANCE + np.linalg.norm(x)))
            x, r, J, cost, damping = x_new, r_new, J_new, cost_new, max(damping * 0.1, 1e-12)
            if small:
                break
        else:
            damping *= 10.0
            if damping > 1e12:
                break
    return x


# --------------------------------------------------------------------------------------------- decomposition
def epipoles(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """e_i (Fᵀ e_i = 0) and e_j (F e_j = 0), unit vectors, signs arbitrary."""
    U, _, Vt = np.linalg.svd(F)
    return U[:, 2], Vt[2]


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The report's formula: the minimal rotation taking unit a onto unit b, R = I + [v]× + [v]×²(1−c)/s²."""
    v, c = np.cross(a, b), float(a @ b)
    s2 = float(v @ v)
    if s2 < 1e-20:
        if c > 0:
            return np.eye(3)
        axis = tangent_basis(a[None])[0, 0]  # a half turn about any axis orthogonal to a
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    V = skew(v)
    return np.eye(3) + V + V @ V * (1.0 - c) / s2


def report_rotation_candidates(F: np.ndarray) -> list[np.ndarray]:
    """Rotations R_j_from_i consistent with F via the report's epipole formula.

    The report sets R to the minimal rotation with e_j = −R e_i; that fixes R only up to a twist ψ about the
    baseline. We keep its formula for R0 and recover ψ from F itself: with M = [e_i]× R0ᵀ and N = −M [e_j]×,
    F ∝ cos ψ · M + sin ψ · N, a 2-parameter linear least-squares fit. Each sign choice of the epipoles gives
    candidates; cheirality picks among them (see `relative_pose_from_f`).
    """
    e_i, e_j = epipoles(F)
    out = []
    for s_i in (1.0, -1.0):
        for s_j in (1.0, -1.0):
            a, b = s_i * e_i, s_j * e_j
            R0 = rotation_between(-a, b)
            M = skew(a) @ R0.T
            N = -M @ skew(b)
            coef, *_ = np.linalg.lstsq(np.stack([M.ravel(), N.ravel()], 1), F.ravel(), rcond=None)
            psi = np.arctan2(coef[1], coef[0])
            for twist in (psi, psi + np.pi):
                out.append(Rotation.from_rotvec(twist * b).as_matrix() @ R0)
    return out


def decompose_f_svd(F: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Classic SVD decomposition of E = Fᵀ into the four (R_j_from_i, t_j_from_i) candidates."""
    U, _, Vt = np.linalg.svd(F.T)
    if np.linalg.det(U) < 0:
        U = -U
    if np.linalg.det(Vt) < 0:
        Vt = -Vt
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t = U[:, 2]
    return [(U @ W @ Vt, t), (U @ W @ Vt, -t), (U @ W.T @ Vt, t), (U @ W.T @ Vt, -t)]


def ray_depths(b_i: np.ndarray, b_j: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths (a, b) of the report's midpoint triangulation, camera i at the origin, camera j centre c = −Rᵀt.

    Minimises ‖a z_i − b Rᵀ z_j − c‖: the closed form of the 2×2 normal equations.
    """
    c = -R.T @ t
    d_j = b_j @ R  # Rᵀ z_j for every row
    aa = np.einsum("na,na->n", b_i, b_i)
    bb = np.einsum("na,na->n", d_j, d_j)
    ab = np.einsum("na,na->n", b_i, d_j)
    ac, bc = b_i @ c, d_j @ c
    det = aa * bb - ab * ab
    det = np.where(np.abs(det) < 1e-12, 1e-12, det)
    a = (bb * ac - ab * bc) / det
    b = (ab * ac - aa * bc) / det
    return a, b


def cheirality_count(b_i, b_j, R, t) -> int:
    a, b = ray_depths(b_i, b_j, R, t)
    return int(np.count_nonzero((a > 0) & (b > 0)))


@dataclass(kw_only=True)
class RelativePose:
    R_j_from_i: np.ndarray  # (3, 3) rotation
    t_j_from_i: np.ndarray  # (3,) unit translation direction
    e_i: np.ndarray  # (3,) epipole in camera i: direction of camera j's centre
    e_j: np.ndarray  # (3,) epipole in camera j: direction of camera i's centre
    num_cheiral: int  # inliers with both ray depths positive
    svd_rotation_diff_deg: float  # angle between the report-formula R and the SVD decomposition's R


def relative_pose_from_f(F: np.ndarray, b_i: np.ndarray, b_j: np.ndarray) -> RelativePose:
    """R from the report's epipole formula, sign ambiguities resolved by cheirality; cross-checked with SVD."""
    best = None
    for R in report_rotation_candidates(F):
        # With R fixed, F = [T]× Rᵀ gives T ∝ e_i; t = −R T; T's sign is the remaining ambiguity.
        T = epipoles(F)[0]
        for sign in (1.0, -1.0):
            t = -R @ (sign * T)
            residual = np.linalg.norm(_unit_sign(skew(sign * T) @ R.T) - _unit_sign(F))
            score = (cheirality_count(b_i, b_j, R, t), -residual)
            if residual < 1e-6 and (best is None or score > best[0]):
                best = (score, R, t, sign * T)
    if best is None:
        raise ValueError("F is not an essential matrix: no rotation reproduces it")
    (count, _), R, t, T = best
    svd_best = max(decompose_f_svd(F), key=lambda Rt: cheirality_count(b_i, b_j, *Rt))
    diff = np.degrees(Rotation.from_matrix(R @ svd_best[0].T).magnitude())
    return RelativePose(R_j_from_i=R, t_j_from_i=t, e_i=T, e_j=t, num_cheiral=count, svd_rotation_diff_deg=float(diff))


def _unit_sign(M: np.ndarray) -> np.ndarray:
    """M scaled to unit Frobenius norm with a canonical sign, so ±F compare equal."""
    M = M / np.linalg.norm(M)
    k = np.argmax(np.abs(M))
    return M * np.sign(M.flat[k])
