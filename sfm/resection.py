"""Absolute pose (resection) of a spherical camera from 2-D–3-D correspondences given as unit bearings.

Minimal solver: Lambda Twist P3P (Persson & Nordberg, "Lambda Twist: An Accurate Fast Robust Perspective Three
Point (P3P) Solver", ECCV 2018). The unknowns are the distances λ_i along the three bearings f_i; the law of cosines
gives Grunert's three quadrics (Grunert 1841, reviewed by Haralick, Lee, Ottenberg & Nölle, IJCV 1994)

    λ_i² + λ_j² − 2 (f_i·f_j) λ_i λ_j = |X_i − X_j|²,   written  λᵀ M_ij λ = a_ij.

Eliminating the right-hand sides leaves two homogeneous conics in λ, D1 = a23 M12 − a12 M23 and
D2 = a23 M13 − a13 M23. Their pencil α D1 + β D2 holds a degenerate member (det = 0: a cubic in α:β), a pair of lines
through all the solutions; each line meets another member of the pencil in at most two points, the scale follows from
the distances, and a few Gauss–Newton steps on the three quadrics polish λ. Unlike the reference implementation, each
line is parametrised by an orthonormal basis and its intersections come from a 2×2 eigen-decomposition, so no
coordinate of λ is ever divided by. Nothing assumes the points lie in front of an image plane: bearings may point
anywhere on the sphere, and a solution is kept when all three λ_i are positive. The pose follows from the
camera-frame points λ_i f_i and the world points by absolute orientation without scale (Kabsch 1976; Umeyama 1991);
three points are coplanar, so the sign of the third singular direction must be fixed explicitly to avoid reflections.

Robust estimation: LO-MSAC (Torr & Zisserman 2000; Chum, Matas & Kittler 2003) over P3P samples, structured like
`two_view.ransac_f`: batches of minimal samples are solved and scored together with the truncated squared angular
error (a point behind its bearing always costs the full threshold), every new best model is re-fitted on its inliers by
non-linear least squares (local optimisation), the number of samples adapts to the inlier ratio, and a final
refinement on the inliers ends.

Refinement: each correspondence's angular residual as a 2-vector in the tangent plane of its bearing (the sphere's
log map, whose norm is the angle and which stays smooth at zero error where the plain angle has a kink), minimised
over (rotation vector, t) with scipy's least_squares and a soft-L1 loss scaled to the inlier threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize, tangent_basis
from fullview.sfm.triangulation import angular_errors
from fullview.sfm.two_view import required_iterations

MAX_SOLUTIONS = 4  # P3P has at most four real solutions
PAIRS = ((0, 1), (0, 2), (1, 2))  # the three quadrics, in the order (12, 13, 23)

# Degeneracy and acceptance tolerances, in the solver's normalised units (world triangle of RMS radius 1).
MIN_TRIANGLE_AREA = 1e-10  # |d12 × d13| / largest squared side: below it the world points are collinear
MIN_BEARING_SINE = 1e-10  # two bearings closer than this to parallel (same or opposite) lose a quadric's rank
MAX_QUADRIC_RESIDUAL = 1e-7  # a polished λ must satisfy the quadrics to this, relative to the largest a_ij
DUPLICATE_DISTANCE = 1e-7  # candidates closer than this in λ are one solution (both lines can share a point)
GAUSS_NEWTON_STEPS = 8  # quadratic convergence from the algebraic λ: a handful reach machine precision

SAMPLES_PER_BATCH = 32  # minimal samples solved and scored together
POINT_HYPOTHESIS_BUDGET = 1_000_000  # cap on (hypothesis, point) pairs scored at once, to bound memory
LO_THRESHOLD_SCHEDULE = (2.0, 1.0)  # inlier-set thresholds of the LO re-fits, in units of the threshold
MIN_REFIT_POINTS = 6  # fewer inliers than this are left to the minimal model (6 unknowns)
REFINE_MAX_EVALUATIONS = 50  # residual evaluations of one non-linear refinement


# --------------------------------------------------------------------------------------------- small linear algebra
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross of (..., 3) vectors, the same products and differences (bitwise the same result) without its axis
    handling, which costs ten times the arithmetic on the small batches RANSAC solves: a failing resection (2D-3D
    matches that are all wrong) draws every one of its 1,000 samples, and growth tries one per free image per round."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _adjugate(M: np.ndarray) -> np.ndarray:
    """Adjugate of (..., 3, 3) matrices (rows are the cross products of column pairs): adj(M) M = det(M) I."""
    c0, c1, c2 = M[..., :, 0], M[..., :, 1], M[..., :, 2]
    return np.stack([_cross(c1, c2), _cross(c2, c0), _cross(c0, c1)], axis=-2)


def _quadric_matrices(cosines: np.ndarray) -> np.ndarray:
    """(..., 3, 3, 3) matrices M_ij (one per pair) with λᵀ M_ij λ = λ_i² + λ_j² − 2 cos_ij λ_i λ_j."""
    M = np.zeros(cosines.shape[:-1] + (3, 3, 3))
    for k, (i, j) in enumerate(PAIRS):
        M[..., k, i, i] = M[..., k, j, j] = 1.0
        M[..., k, i, j] = M[..., k, j, i] = -cosines[..., k]
    return M


def _quadric_values(lam: np.ndarray, cosines: np.ndarray) -> np.ndarray:
    """(..., 3) values λᵀ M_ij λ for λ (..., 3) and the pairs' cosines (..., 3)."""
    i, j = np.array(PAIRS).T
    li, lj = lam[..., i], lam[..., j]
    return li * li + lj * lj - 2.0 * cosines * li * lj


# --------------------------------------------------------------------------------------------- P3P
def p3p_bearings(f: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """All poses (R_cam_from_world, t_cam_from_world) with λ_i f_i = R X_i + t for some λ_i > 0.

    f: (3, 3) bearing rows (any non-zero norm, anywhere on the sphere); X: (3, 3) world point rows. Returns up to four
    solutions; degenerate input (collinear or coincident points, parallel bearings, non-finite values) gives [].
    """
    f, X = np.asarray(f, dtype=np.float64), np.asarray(X, dtype=np.float64)
    if f.shape != (3, 3) or X.shape != (3, 3):
        raise ValueError(f"p3p needs (3, 3) bearings and points, got {f.shape} and {X.shape}")
    R, t, valid = p3p_bearings_batch(f[None], X[None])
    return [(R[0, k], t[0, k]) for k in np.flatnonzero(valid[0])]


def p3p_bearings_batch(f: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`p3p_bearings` over B samples at once: f, X (B, 3, 3) -> R (B, 4, 3, 3), t (B, 4, 3), valid (B, 4) bool."""
    f, X = np.asarray(f, dtype=np.float64), np.asarray(X, dtype=np.float64)
    B = len(f)
    R = np.broadcast_to(np.eye(3), (B, MAX_SOLUTIONS, 3, 3)).copy()
    t = np.zeros((B, MAX_SOLUTIONS, 3))
    valid = np.zeros((B, MAX_SOLUTIONS), dtype=bool)
    with np.errstate(all="ignore"):  # degenerate input and candidates produce inf/nan; they are masked, never returned
        ok = _well_posed(f, X)
        if ok.any():
            f_ok = normalize(f[ok])
            lam, found = _p3p_distances(f_ok, X[ok])
            lam = np.where(found[..., None], lam, 1.0)  # keep the SVD below finite
            R[ok], t[ok] = _absolute_orientation(lam[..., None] * f_ok[:, None], X[ok][:, None])
            valid[ok] = found
    return R, t, valid


def _well_posed(f: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(B,) samples with finite values, non-collinear world points and pairwise non-parallel bearings."""
    finite = np.isfinite(f).all(axis=(1, 2)) & np.isfinite(X).all(axis=(1, 2))
    f = normalize(np.where(finite[:, None, None], f, 1.0))
    X = np.where(finite[:, None, None], X, 0.0)
    unit = np.abs(np.linalg.norm(f, axis=-1) - 1.0).max(axis=-1) < 1e-6  # zero bearings stay zero in normalize
    i, j = np.array(PAIRS).T
    bearing_sines = np.linalg.norm(_cross(f[:, i], f[:, j]), axis=-1).min(axis=-1)
    sides = X[:, i] - X[:, j]
    largest_side2 = (sides * sides).sum(-1).max(axis=-1)
    area = np.linalg.norm(_cross(sides[:, 0], sides[:, 1]), axis=-1)
    return finite & unit & (bearing_sines > MIN_BEARING_SINE) & (area > MIN_TRIANGLE_AREA * largest_side2)


def _p3p_distances(f: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, 4, 3) distances λ along the unit bearings f (K, 3, 3), and (K, 4) validity, for world points X (K, 3, 3)."""
    # Work on a world triangle of RMS radius 1 so that the tolerances are scale-free.
    centred = X - X.mean(axis=1, keepdims=True)
    scale = np.sqrt((centred * centred).sum(-1).mean(-1))
    i, j = np.array(PAIRS).T
    sides = (centred[:, i] - centred[:, j]) / scale[:, None, None]
    a = (sides * sides).sum(-1)  # (K, 3) squared sides a12, a13, a23
    cosines = (f[:, i] * f[:, j]).sum(-1)  # (K, 3)
    M = _quadric_matrices(cosines)
    D1 = a[:, 2, None, None] * M[:, 0] - a[:, 0, None, None] * M[:, 2]
    D2 = a[:, 2, None, None] * M[:, 1] - a[:, 1, None, None] * M[:, 2]
    alpha, beta = _degenerate_member(D1, D2)
    A = alpha[:, None, None] * D1 + beta[:, None, None] * D2
    # A second member of the pencil, never proportional to A, supplies the points on A's lines.
    C = -beta[:, None, None] * D1 + alpha[:, None, None] * D2
    p, q, lines_ok = _line_pair(A)  # (K, 2, 3) twice: an orthonormal basis of each line
    directions, meets = _line_conic_intersections(p, q, C)  # (K, 2, 2, 3)
    directions = directions.reshape(-1, MAX_SOLUTIONS, 3)
    found = (meets & lines_ok[:, :, None]).reshape(-1, MAX_SOLUTIONS)
    lam, scaled = _scale_to_distances(directions, a, cosines)
    lam = _polish_distances(lam, a, cosines)
    residual = np.abs(_quadric_values(lam, cosines[:, None]) - a[:, None]).max(-1)
    found &= scaled & (residual < MAX_QUADRIC_RESIDUAL * a.max(-1)[:, None]) & (lam > 0).all(-1)
    found &= ~_duplicates(lam, found)
    return lam * scale[:, None, None], found


def _degenerate_member(D1: np.ndarray, D2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit (α, β) with det(α D1 + β D2) = 0, at the best-conditioned real root of that cubic."""
    # det(D1 + γ D2) = det D1 + γ tr(adj(D1) D2) + γ² tr(adj(D2) D1) + γ³ det D2.
    c0, c3 = np.linalg.det(D1), np.linalg.det(D2)
    c1 = np.trace(_adjugate(D1) @ D2, axis1=-2, axis2=-1)
    c2 = np.trace(_adjugate(D2) @ D1, axis1=-2, axis2=-1)
    coeffs = np.stack([c3, c2, c1, c0], axis=-1)  # highest power of γ first
    # Solve in γ = β/α or in μ = α/β, whichever has the larger leading coefficient: the roots then stay bounded.
    swap = np.abs(c0) > np.abs(c3)
    coeffs = np.where(swap[:, None], coeffs[:, ::-1], coeffs)
    coeffs = coeffs / np.maximum(np.abs(coeffs).max(-1, keepdims=True), 1e-300)
    lead = coeffs[:, 0]
    lead = np.where(lead < 0, -1.0, 1.0) * np.maximum(np.abs(lead), 1e-14)  # a vanishing pencil is caught later
    root = _sharpest_real_root(coeffs[:, 1:] / lead[:, None])
    ab = np.where(swap[:, None], np.stack([root, np.ones_like(root)], -1), np.stack([np.ones_like(root), root], -1))
    ab = normalize(ab)
    return ab[:, 0], ab[:, 1]


def _sharpest_real_root(c: np.ndarray) -> np.ndarray:
    """The real root of x³ + c0 x² + c1 x + c2 with the steepest slope (farthest from the others), Newton-polished.

    Any real root gives a degenerate conic through the solutions; a steep one is a simple root, well conditioned.
    """
    c0, c1, c2 = c[:, 0:1], c[:, 1:2], c[:, 2:3]

    def value(x):
        return ((x + c0) * x + c1) * x + c2

    def slope(x):
        return (3.0 * x + 2.0 * c0) * x + c1

    companion = np.zeros((len(c), 3, 3))
    companion[:, 0, :] = -c
    companion[:, 1, 0] = companion[:, 2, 1] = 1.0
    roots = np.linalg.eigvals(companion)  # (K, 3) complex
    imag = np.abs(roots.imag)
    # Rounding can leave a tiny imaginary part on a real root; if no root looks real take the least complex one.
    real = (imag <= 1e-8 * (1.0 + np.abs(roots.real))) | (imag == imag.min(-1, keepdims=True))
    best = np.argmax(np.where(real, np.abs(slope(roots.real)), -1.0), axis=-1)
    x = np.take_along_axis(roots.real, best[:, None], axis=-1)
    for _ in range(3):
        d = slope(x)
        x = np.where(d != 0, x - value(x) / np.where(d != 0, d, 1.0), x)
    return x[:, 0]


def _line_pair(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two lines of the degenerate conic A (K, 3, 3): bases p (K, 2, 3), q (K, 2, 3) and (K, 2) realness.

    With eigenvalues 0, l_small, l_large (by magnitude) and eigenvectors e0, e_s, e_l, the zero set
    l_large (e_l·z)² + l_small (e_s·z)² = 0 is the line pair e_l·z = ± v e_s·z, v = sqrt(−l_small / l_large),
    real when the two eigenvalues have opposite signs. Both lines pass through e0.
    """
    values, vectors = np.linalg.eigh(A)
    order = np.argsort(np.abs(values), axis=-1)
    rows = np.arange(len(A))[:, None]
    values = values[rows, order]  # (K, 3) by magnitude
    vectors = np.swapaxes(vectors, -1, -2)[rows, order]  # (K, 3, 3) eigenvectors as rows, same order
    e0, e_s, e_l = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    ratio = -values[:, 1] / np.where(values[:, 2] == 0, 1.0, values[:, 2])
    v = np.sqrt(np.maximum(ratio, 0.0))
    signs = np.array([1.0, -1.0])[None, :, None]
    # The line e_l·z = s v e_s·z is spanned by e0 and s v e_l + e_s.
    q = normalize(signs * v[:, None, None] * e_l[:, None] + e_s[:, None])
    p = np.broadcast_to(e0[:, None], q.shape)
    real = np.broadcast_to((ratio > -1e-9)[:, None], (len(A), 2))
    return p, q, real


def _line_conic_intersections(p: np.ndarray, q: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the lines spanned by p, q (K, 2, 3) meet the conic C (K, 3, 3): (K, 2, 2, 3) directions, (K, 2, 2) real.

    On z = u p + w q the conic is a 2×2 quadratic form; with eigenvalues m0, m1 and eigenvectors g0, g1 its zero
    directions are sqrt|m1| g0 ± sqrt|m0| g1, real when m0 m1 ≤ 0.
    """
    basis = np.stack([p, q], axis=-2)  # (K, 2, 2, 3)
    form = basis @ C[:, None] @ np.swapaxes(basis, -1, -2)  # (K, 2, 2, 2)
    m, g = np.linalg.eigh(form)
    signs = np.array([1.0, -1.0])[:, None]
    g0, g1 = g[..., None, :, 0], g[..., None, :, 1]  # (K, 2, 1, 2) eigenvectors, one axis for the ± below
    uw = np.sqrt(np.abs(m[..., None, 1:2])) * g0 + signs * np.sqrt(np.abs(m[..., None, 0:1])) * g1  # (K, 2, 2, 2)
    directions = uw @ basis  # (K, 2, 2, 3): two intersections per line
    real = m[..., 0] * m[..., 1] <= 0.0
    return directions, np.broadcast_to(real[..., None], real.shape + (2,))


def _scale_to_distances(directions: np.ndarray, a: np.ndarray, cosines: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale and sign directions (K, 4, 3) so the quadrics best match the squared sides a: λ (K, 4, 3), (K, 4) ok."""
    k = _quadric_values(directions, cosines[:, None])  # on the base locus k_ij ∝ a_ij
    s2 = (k * a[:, None]).sum(-1) / (k * k).sum(-1)
    ok = np.isfinite(s2) & (s2 > 0)
    lam = np.sqrt(np.where(ok, s2, 1.0))[..., None] * directions
    lam *= np.where(lam.sum(-1, keepdims=True) < 0, -1.0, 1.0)  # the direction's sign is arbitrary
    return lam, ok


def _polish_distances(lam: np.ndarray, a: np.ndarray, cosines: np.ndarray) -> np.ndarray:
    """Gauss–Newton on the three quadrics (as in Lambda Twist), each step kept only if it lowers the residual."""
    i, j = np.array(PAIRS).T
    a, cosines = a[:, None], cosines[:, None]
    for _ in range(GAUSS_NEWTON_STEPS):
        r = _quadric_values(lam, cosines) - a
        J = np.zeros(lam.shape + (3,))
        rows = np.arange(3)
        J[..., rows, i] = 2.0 * (lam[..., i] - cosines * lam[..., j])
        J[..., rows, j] = 2.0 * (lam[..., j] - cosines * lam[..., i])
        det = np.linalg.det(J)
        step = (_adjugate(J) @ r[..., None])[..., 0] / np.where(det == 0, 1.0, det)[..., None]
        trial = lam - step
        better = (np.abs(_quadric_values(trial, cosines) - a).max(-1) < np.abs(r).max(-1)) & np.isfinite(trial).all(-1)
        lam = np.where(better[..., None], trial, lam)
    return lam


def _duplicates(lam: np.ndarray, found: np.ndarray) -> np.ndarray:
    """(K, 4) candidates that repeat an earlier found one (the two lines can share a solution)."""
    close = np.abs(lam[:, :, None] - lam[:, None, :]).max(-1) < DUPLICATE_DISTANCE * np.abs(lam).max(-1)[:, :, None]
    earlier = np.tri(MAX_SOLUTIONS, k=-1, dtype=bool)  # [k, m] is True for m < k
    return (close & earlier & found[:, None, :]).any(-1)


def _absolute_orientation(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch/Umeyama without scale: R, t minimising Σ |R X_n + t − P_n|² over rows n of (..., 3, 3) point sets."""
    P_mean, X_mean = P.mean(-2, keepdims=True), X.mean(-2, keepdims=True)
    H = np.swapaxes(X - X_mean, -1, -2) @ (P - P_mean)  # Σ x pᵀ
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    # Three points are coplanar: the third singular value is zero and only this sign rules out a reflection.
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    V = V * np.stack([np.ones_like(d), np.ones_like(d), np.where(d == 0, 1.0, d)], -1)[..., None, :]
    R = V @ np.swapaxes(U, -1, -2)
    t = P_mean[..., 0, :] - (R @ X_mean[..., 0, :, None])[..., 0]
    return R, t


# --------------------------------------------------------------------------------------------- robust estimation
@dataclass(kw_only=True)
class ResectionOptions:
    threshold_rad: float  # angular inlier threshold between a bearing and its projected point
    max_iterations: int = 1000  # hard cap on minimal samples drawn
    min_iterations: int = 50  # never stop sampling earlier than this
    confidence: float = 0.9999  # adaptive stopping: probability of having drawn an all-inlier sample
    seed: int = 0  # random seed for sampling (same seed, same result)
    refine: bool = True  # final non-linear refinement of R, t on the inliers
    min_inliers: int = 12  # fewer inliers than this and resection fails (returns None)


@dataclass(kw_only=True)
class Resection:
    R_cam_from_world: np.ndarray  # (3, 3) rotation
    t_cam_from_world: np.ndarray  # (3,) translation, x_cam = R X + t
    inliers: np.ndarray  # (N,) bool: angular error below the threshold and the point in front along its bearing
    errors: np.ndarray  # (N,) angular error, radians
    num_inliers: int  # inliers.sum()
    iterations: int  # minimal samples drawn


def _msac_costs(R: np.ndarray, t: np.ndarray, bearings: np.ndarray, points: np.ndarray, threshold: float) -> np.ndarray:
    """(H,) MSAC cost (lower is better) of poses R (H, 3, 3), t (H, 3): truncated squared angular error.

    A point behind its bearing (non-positive depth) is an outlier and costs the full threshold.
    """
    cam = points @ np.swapaxes(R, -1, -2) + t[:, None]  # (H, N, 3)
    depth = (cam * bearings).sum(-1)
    error = np.arctan2(np.linalg.norm(_cross(bearings, cam), axis=-1), depth)
    return (np.where(depth > 0, np.minimum(error, threshold), threshold) ** 2).sum(-1)


def _pose_cost(R, t, bearings, points, threshold) -> float:
    return float(_msac_costs(R[None], t[None], bearings, points, threshold)[0])


def _inlier_mask(R, t, bearings, points, threshold) -> np.ndarray:
    cam = points @ R.T + t
    depth = (cam * bearings).sum(-1)
    return (angular_errors(bearings, cam) < threshold) & (depth > 0)


def _draw_triplets(rng: np.random.Generator, batch: int, n: int) -> np.ndarray:
    """(batch, 3) indices, distinct within each row, uniform over the correspondences (which carry no ordering).

    Rows with a repeated index are redrawn: O(batch) work however large n is, and rarely a second round.
    """
    samples = rng.integers(0, n, (batch, 3))
    while True:
        a, b, c = samples.T
        repeated = (a == b) | (a == c) | (b == c)
        if not repeated.any():
            return samples
        samples[repeated] = rng.integers(0, n, (int(repeated.sum()), 3))


def _hypotheses(bearings: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All P3P poses of a batch of samples (B, 3, 3) as flat arrays R (H, 3, 3), t (H, 3)."""
    R, t, valid = p3p_bearings_batch(bearings, points)
    return R[valid], t[valid]


def _local_optimization(bearings, points, R, t, threshold) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """LO step: re-fit on the inliers at a shrinking threshold; keep the best-scoring pose.

    Starting loose lets a pose from a noisy minimal sample pull in the inliers it narrowly misses.
    """
    best, best_cost = (R, t), _pose_cost(R, t, bearings, points, threshold)
    current = best
    for factor in LO_THRESHOLD_SCHEDULE:
        inliers = _inlier_mask(*current, bearings, points, factor * threshold)
        if inliers.sum() < MIN_REFIT_POINTS:
            break
        current = refine_pose(*current, bearings[inliers], points[inliers], factor * threshold)
        cost = _pose_cost(*current, bearings, points, threshold)
        if cost < best_cost:
            best, best_cost = current, cost
    return best, best_cost


def resect(bearings: np.ndarray, points: np.ndarray, options: ResectionOptions) -> Resection | None:
    """LO-MSAC over P3P samples: the camera pose seeing world points (N, 3) along unit bearings (N, 3).

    Returns None when N < 3 or fewer than options.min_inliers correspondences support the best pose.
    """
    bearings = normalize(np.asarray(bearings, dtype=np.float64))
    points = np.asarray(points, dtype=np.float64)
    n = len(bearings)
    if n < max(3, options.min_inliers):
        return None
    rng = np.random.default_rng(options.seed)
    thr = options.threshold_rad
    per_batch = int(np.clip(POINT_HYPOTHESIS_BUDGET // (MAX_SOLUTIONS * n), 1, SAMPLES_PER_BATCH))
    best, best_cost, drawn = None, np.inf, 0
    while drawn < options.max_iterations:
        batch = min(per_batch, options.max_iterations - drawn)
        samples = _draw_triplets(rng, batch, n)
        R, t = _hypotheses(bearings[samples], points[samples])
        drawn += batch
        if len(R):
            costs = _msac_costs(R, t, bearings, points, thr)
            k = int(np.argmin(costs))
            if costs[k] < best_cost:
                best, best_cost = _local_optimization(bearings, points, R[k], t[k], thr)
        if best is not None:
            ratio = float(_inlier_mask(*best, bearings, points, thr).mean())
            if drawn >= options.min_iterations and drawn >= required_iterations(ratio, options.confidence, 3):
                break
    if best is None:
        return None
    R, t = _final_refinement(bearings, points, *best, thr) if options.refine else best
    inliers = _inlier_mask(R, t, bearings, points, thr)
    if inliers.sum() < options.min_inliers:
        return None
    return Resection(R_cam_from_world=R, t_cam_from_world=t, inliers=inliers,
                     errors=angular_errors(bearings, points @ R.T + t), num_inliers=int(inliers.sum()),
                     iterations=drawn)


def _final_refinement(bearings, points, R, t, threshold) -> tuple[np.ndarray, np.ndarray]:
    """Refine on the inliers; keep the refined pose only if it does not score worse (a robust fit never should)."""
    inliers = _inlier_mask(R, t, bearings, points, threshold)
    if inliers.sum() < MIN_REFIT_POINTS:
        return R, t
    R_new, t_new = refine_pose(R, t, bearings[inliers], points[inliers], threshold)
    if _pose_cost(R_new, t_new, bearings, points, threshold) <= _pose_cost(R, t, bearings, points, threshold):
        return R_new, t_new
    return R, t


# --------------------------------------------------------------------------------------------- refinement
def _tangent_residuals(bearings: np.ndarray, basis: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """(N, 2) log-map residuals: the projected point's offset from its bearing in the bearing's tangent plane.

    The tangent components of the unit point have norm sin θ; scaling them by θ / sin θ makes the norm the angle θ.
    """
    p = normalize(points_cam)
    tangential = np.einsum("nkc,nc->nk", basis, p)
    sin = np.linalg.norm(tangential, axis=-1)
    angle = np.arctan2(sin, (p * bearings).sum(-1))
    gain = np.where(sin > 1e-12, angle / np.where(sin > 1e-12, sin, 1.0), 1.0)
    return tangential * gain[:, None]


def refine_pose(R: np.ndarray, t: np.ndarray, bearings: np.ndarray, points: np.ndarray,
                threshold_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Non-linear least squares of the angular errors over (rotation vector, t), soft-L1 loss scaled to the threshold.

    R = exp(ω) R0 and t = t0 + s δ, where s is the median camera-to-point distance, so that all six parameters move
    the projections by comparable angles (a step of 1 in δ is one typical depth).
    """
    R0, t0 = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    bearings = normalize(np.asarray(bearings, dtype=np.float64))
    points = np.asarray(points, dtype=np.float64)
    basis = tangent_basis(bearings)
    scale = float(np.median(np.linalg.norm(points @ R0.T + t0, axis=-1))) or 1.0

    def pose(x):
        return Rotation.from_rotvec(x[:3]).as_matrix() @ R0, t0 + scale * x[3:]

    def residuals(x):
        Rx, tx = pose(x)
        return _tangent_residuals(bearings, basis, points @ Rx.T + tx).ravel()

    # Imported here: scipy.optimize costs 0.1-0.16 CPU s to import (linprog, HiGHS, scipy.fft) and most runs never
    # resect (global registration places every camera of a well-connected tour).
    from scipy.optimize import least_squares

    sol = least_squares(residuals, np.zeros(6), loss="soft_l1", f_scale=threshold_rad / 2, method="trf",
                        max_nfev=REFINE_MAX_EVALUATIONS)
    return pose(sol.x)
