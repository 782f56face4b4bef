"""Upright two-view geometry: relative pose of two levelled panoramas, whose relative rotation is a pure yaw.

When both cameras' gravity directions are known (an IMU, or the vertical vanishing point of the scene), each
panorama can be rotated so that gravity is +y (the camera frame's "down"). The relative rotation of two such levelled
cameras is then a rotation about y alone, ``R_j_from_i = R_y(θ)``, and the essential matrix (``two_view``'s
convention ``b_iᵀ F b_j = 0``, ``F = [T]× Rᵀ``) has 3 degrees of freedom instead of 5:

    F = [T]× R_y(θ)ᵀ = [[ Ty s,       −Tz,   Ty c      ],
                        [ Tz c − Tx s,  0,   −Tz s − Tx c],
                        [−Ty c,        Tx,   Ty s      ]]    (c, s = cos θ, sin θ).

Three correspondences are a minimal sample (``upright_f_minimal``), so RANSAC needs far fewer hypotheses than with
the 8-point algorithm: for an inlier ratio w, ``log(1 − p) / log(1 − w³)`` instead of ``… / log(1 − w⁸)``.

Minimal solver. With θ fixed the constraint is linear in T: ``b_iᵀ [T]× Rᵀ b_j = T · m(θ)`` with
``m(θ) = (R_y(θ)ᵀ b_j) × b_i``. Three such vectors are coplanar: ``det[m₁ m₂ m₃](θ) = 0``. Each m is affine in
(cos θ, sin θ), so the determinant is a trigonometric polynomial of degree ≤ 3; its third harmonic vanishes (its
coefficient is a determinant of three vectors orthogonal, in the complex bilinear sense, to the same vector
(1, 0, −i)), so it has degree 2: at most 4 solutions, a quartic in tan(θ/2). T is the null vector of [m₁ m₂ m₃]ᵀ.

Gravity from an image (``estimate_gravity``): vertical scene edges lie on great circles through the vertical
vanishing direction v; each detected segment gives its circle's normal n, and v is the direction with n · v ≈ 0
for the largest family near ±y (RANSAC over pairs of normals, then the least-squares eigenvector).

References:
- F. Fraundorfer, P. Tanskanen, M. Pollefeys, "A minimal case solution to the calibrated relative pose problem for
  the case of two known orientation angles", ECCV 2010.
- M. Kalantari, A. Hashemi, F. Jung, J.-P. Guédon, "A new solution to the relative orientation problem using only
  3 points and the vertical direction", Journal of Mathematical Imaging and Vision, 2011.
- O. Saurer, P. Vasseur, R. Boutteau, C. Demonceaux, M. Pollefeys, F. Fraundorfer, "Homography based egomotion
  estimation with a common direction", TPAMI 2017 (levelling with known gravity).
- J.-C. Bazin, M. Pollefeys, "3-line RANSAC for orthogonal vanishing point detection", IROS 2012 (great-circle
  normals of line segments on the sphere).
"""

from __future__ import annotations

import numpy as np

from fullview.sfm import two_view as tv
from fullview.sfm.camera import normalize, skew, tangent_basis
from fullview.sfm.registration.poses import yaw_rotation

__all__ = [
    "UPRIGHT_SAMPLE_SIZE", "detect_line_normals", "estimate_f_upright_linear", "estimate_gravity",
    "estimate_gravity_with_std", "level_bearings", "leveling_rotation", "ransac_f_upright", "refine_f_upright",
    "unlevel_f", "unlevel_rotation", "upright_decompose", "upright_f", "upright_f_minimal", "upright_f_minimal_batch",
    "vertical_direction_from_normals", "vertical_direction_std",
]

UPRIGHT_SAMPLE_SIZE = 3
Y_AXIS = np.array([0.0, 1.0, 0.0])


# --------------------------------------------------------------------------------------------- upright structure
def upright_f(theta, T: np.ndarray) -> np.ndarray:
    """``F = [T]× R_y(θ)ᵀ``, batched over leading axes of ``theta`` (...,) and ``T`` (..., 3)."""
    return skew(T) @ np.swapaxes(yaw_rotation(theta), -1, -2)


def _symmetric_part(M: np.ndarray) -> np.ndarray:
    """The 6 independent entries of M + Mᵀ."""
    return (M + M.T)[np.triu_indices(3)]


def upright_decompose(F: np.ndarray) -> tuple[float, np.ndarray, float]:
    """(θ, unit T, relative residual) with ``F ≈ [T]× R_y(θ)ᵀ`` (up to scale; the residual is 0 for an upright F).

    ``F R_y(θ)`` must be skew-symmetric, and its symmetric part is linear in (cos θ, sin θ): a 2-unknown least
    squares gives θ, the skew part gives T. For a non-upright F this is a cheap (not optimal) projection.
    Degenerate when T ∥ y (then θ and θ + π both fit).
    """
    F = np.asarray(F, dtype=np.float64)
    cos_part, sin_part, const_part = np.diag([1.0, 0.0, 1.0]), np.zeros((3, 3)), np.diag([0.0, 1.0, 0.0])
    sin_part[0, 2], sin_part[2, 0] = 1.0, -1.0  # R_y(θ) = cos_part c + sin_part s + const_part
    A = np.stack([_symmetric_part(F @ cos_part), _symmetric_part(F @ sin_part)], axis=1)
    (c, s), *_ = np.linalg.lstsq(A, -_symmetric_part(F @ const_part), rcond=None)
    theta = float(np.arctan2(s, c))
    M = F @ yaw_rotation(theta)
    T = 0.5 * np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    residual = np.linalg.norm(F - upright_f(theta, T)) / max(np.linalg.norm(F), 1e-300)
    return theta, normalize(T), float(residual)


# --------------------------------------------------------------------------------------------- minimal solver
# 5 equispaced angles sample a degree-2 trigonometric polynomial exactly (no aliasing).
_SAMPLE_ANGLES = 2.0 * np.pi * np.arange(5) / 5


def _coplanarity_vectors(b_i: np.ndarray, b_j: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """m_k(θ) = (R_y(θ)ᵀ b_j,k) × b_i,k for samples (B, 3, 3) and angles (B, A) -> (B, A, 3, 3)."""
    rotated = b_j[:, None] @ yaw_rotation(theta)  # row vectors: bᵀ R = (Rᵀ b)ᵀ
    return np.cross(rotated, b_i[:, None])


def _trig_coefficients(values: np.ndarray) -> np.ndarray:
    """(…, 5) samples at _SAMPLE_ANGLES -> (…, 5) coefficients (a0, a1, b1, a2, b2) of
    a0 + a1 cos θ + b1 sin θ + a2 cos 2θ + b2 sin 2θ (a discrete Fourier transform)."""
    k_theta = np.outer([1, 2], _SAMPLE_ANGLES)
    a = values @ np.cos(k_theta).T * 0.4
    b = values @ np.sin(k_theta).T * 0.4
    return np.stack([values.mean(-1), a[..., 0], b[..., 0], a[..., 1], b[..., 1]], axis=-1)


def _trig_eval(coef: np.ndarray, theta: np.ndarray, derivative: bool = False) -> np.ndarray:
    """Value (or θ-derivative) of the degree-2 trigonometric polynomials coef (B, 5) at theta (B, K)."""
    a0, a1, b1, a2, b2 = (coef[:, k, None] for k in range(5))
    c1, s1, c2, s2 = np.cos(theta), np.sin(theta), np.cos(2 * theta), np.sin(2 * theta)
    if derivative:
        return -a1 * s1 + b1 * c1 - 2 * a2 * s2 + 2 * b2 * c2
    return a0 + a1 * c1 + b1 * s1 + a2 * c2 + b2 * s2


def _trig_roots(coef: np.ndarray, pivot: np.ndarray, imag_tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Real roots θ (B, 4) and validity (B, 4) of the trigonometric polynomials coef (B, 5).

    θ = pivot + 2 atan(t) turns f into a quartic in t whose leading coefficient is f(pivot + π); the caller picks the
    pivot so that this is the largest sample of |f|, keeping every root far from t = ∞.
    """
    a0, a1, b1, a2, b2 = coef.T
    cp, sp, c2p, s2p = np.cos(pivot), np.sin(pivot), np.cos(2 * pivot), np.sin(2 * pivot)
    a1, b1 = a1 * cp + b1 * sp, b1 * cp - a1 * sp  # harmonics of f(pivot + ψ) as a function of ψ
    a2, b2 = a2 * c2p + b2 * s2p, b2 * c2p - a2 * s2p
    # (1 + t²)² f with cos ψ = (1 − t²)/(1 + t²), sin ψ = 2t/(1 + t²); highest power first.
    quartic = np.stack([a0 - a1 + a2, 2 * b1 - 4 * b2, 2 * a0 - 6 * a2, 2 * b1 + 4 * b2, a0 + a1 + a2], axis=-1)
    companion = np.zeros((len(coef), 4, 4))
    companion[:, 0, :] = -quartic[:, 1:] / quartic[:, :1]
    companion[:, [1, 2, 3], [0, 1, 2]] = 1.0
    t = np.linalg.eigvals(companion)
    valid = np.abs(t.imag) <= imag_tol * (1.0 + np.abs(t))
    return pivot[:, None] + 2.0 * np.arctan(t.real), valid


def _polish_roots(coef: np.ndarray, theta: np.ndarray, steps: int = 2) -> np.ndarray:
    """Newton steps on f(θ) (bounded, so near-double roots cannot jump away)."""
    for _ in range(steps):
        d = _trig_eval(coef, theta, derivative=True)
        step = -_trig_eval(coef, theta) / np.where(np.abs(d) > 1e-300, d, 1e-300)
        theta = theta + np.clip(step, -0.01, 0.01)
    return theta


def upright_f_minimal_batch(b_i: np.ndarray, b_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upright essential matrices of B minimal samples: (B, 3, 3) bearings each -> F (B, 4, 3, 3), valid (B, 4).

    Every valid F is ``[T]× R_y(θ)ᵀ`` with unit T and satisfies the sample's three constraints; the true model is
    among them for noise-free data. Invalid slots (complex roots, degenerate samples) hold zeros.
    """
    b_i, b_j = normalize(b_i), normalize(b_j)
    B = len(b_i)
    dets = np.linalg.det(_coplanarity_vectors(b_i, b_j, np.broadcast_to(_SAMPLE_ANGLES, (B, 5))))
    coef = _trig_coefficients(dets)
    largest = np.argmax(np.abs(dets), axis=1)
    # f ≡ 0: every yaw fits (e.g. camera i's three bearings all vertical); nothing to pick. (A pure rotation is not
    # caught here: f then has a triple root at the true yaw, where T is undefined, and spurious roots elsewhere.)
    nondegenerate = np.abs(dets[np.arange(B), largest]) > 1e-14
    constant = np.array([1.0, 0.0, 0.0, 0.0, 0.0])  # stand-in for degenerate samples: no roots, no division by 0
    theta, valid = _trig_roots(np.where(nondegenerate[:, None], coef, constant), _SAMPLE_ANGLES[largest] + np.pi)
    theta = _polish_roots(coef, theta)
    M = _coplanarity_vectors(b_i, b_j, theta)  # (B, 4, 3, 3): rows m_k, T is their common normal
    _, sv, Vt = np.linalg.svd(M)
    T = Vt[..., 2, :]
    valid &= nondegenerate[:, None] & (sv[..., 1] > 1e-10)  # rank 2: T unique up to sign
    F = np.where(valid[..., None, None], upright_f(theta, T), 0.0)
    return F, valid


def upright_f_minimal(b_i: np.ndarray, b_j: np.ndarray) -> np.ndarray:
    """The (K ≤ 4, 3, 3) upright essential matrices through three correspondences b_i, b_j (3, 3)."""
    F, valid = upright_f_minimal_batch(np.asarray(b_i, float)[None], np.asarray(b_j, float)[None])
    return F[0][valid[0]]


# --------------------------------------------------------------------------------------------- fits on many points
# vec(F) (row-major) = G x with x = (Ty s, Ty c, Tz, Tx, Tz c − Tx s, −Tz s − Tx c): the linear upright structure.
_UPRIGHT_BASIS = np.zeros((9, 6))
for _col, _entries in enumerate([((0, 1), (8, 1)), ((2, 1), (6, -1)), ((1, -1),), ((7, 1),), ((3, 1),), ((5, 1),)]):
    for _index, _value in _entries:
        _UPRIGHT_BASIS[_index, _col] = _value


def estimate_f_upright_linear(b_i: np.ndarray, b_j: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Linear fit in the 6 entries of the upright structure (≥ 5 points), projected onto upright essentials."""
    A = tv._design_matrix(normalize(b_i), normalize(b_j)) @ _UPRIGHT_BASIS
    if weights is not None:
        A = A * weights[:, None]
    _, vecs = np.linalg.eigh(A.T @ A)
    theta, T, _ = upright_decompose((_UPRIGHT_BASIS @ vecs[:, 0]).reshape(3, 3))
    return upright_f(theta, T)


def refine_f_upright(F: np.ndarray, b_i: np.ndarray, b_j: np.ndarray, threshold: float,
                     loss: str = "soft_l1") -> np.ndarray:
    """Robust non-linear least squares over yaw and T's 2 tangent parameters; the result stays exactly upright."""
    theta0, T0, _ = upright_decompose(F)
    u, v = tangent_basis(T0[None])[0]
    def models(x):  # (..., 3) parameters -> (..., 3, 3) upright F
        return upright_f(theta0 + x[..., 0], normalize(T0 + x[..., 1:2] * u + x[..., 2:3] * v))

    with_jacobian = tv.sine_residuals_with_jacobian(models, b_i, b_j)
    # The in-house solver of two_view's refinement (the same soft_l1 minimum as scipy's least_squares, without its
    # per-call cost), which also has the Cauchy loss of the polish; the polish refines a few times per pair.
    return models(tv.robust_levenberg_marquardt(with_jacobian, np.zeros(3), threshold / 2, loss))


# --------------------------------------------------------------------------------------------- robust estimation
MIN_LINEAR_POINTS = 6  # the linear upright fit has 5 degrees of freedom; one more to be over-determined


def _draw_upright_samples(rng: np.random.Generator, batch: int, n: int, head_share: float) -> np.ndarray:
    """(batch, 3) distinct indices with two_view's guided scheme: 3 random members of its 8-index samples."""
    if n < 8:  # two_view's sampler needs 8 points; tiny sets are sampled uniformly
        return np.argpartition(rng.random((batch, n)), UPRIGHT_SAMPLE_SIZE - 1, axis=1)[:, :UPRIGHT_SAMPLE_SIZE]
    eight = tv._draw_samples(rng, batch, n, head_share)
    # argpartition's order is not random: choose which 3 of the 8 with a fresh permutation per row.
    pick = rng.permuted(np.tile(np.arange(8), (batch, 1)), axis=1)[:, :UPRIGHT_SAMPLE_SIZE]
    return np.take_along_axis(eight, pick, axis=1)


def _local_optimization_upright(b_i, b_j, F, threshold, steps):
    """two_view's LO schedule (shrinking inlier thresholds, Cauchy weights) with the upright linear re-fit."""
    return tv._local_optimization(b_i, b_j, F, threshold, steps, fit=estimate_f_upright_linear,
                                  min_points=MIN_LINEAR_POINTS)


def ransac_f_upright(b_i: np.ndarray, b_j: np.ndarray, options: tv.RansacOptions) -> tv.FResult:
    """LO-MSAC for levelled cameras: 3-point upright samples, upright local optimisation and refinement.

    Same options and result as ``two_view.ransac_f``; ``iterations`` counts minimal samples (each gives ≤ 4
    models). The returned F is ``[T]× R_y(θ)ᵀ`` to machine precision (see ``upright_decompose``).
    """
    b_i, b_j = normalize(b_i), normalize(b_j)
    n = len(b_i)
    if n < UPRIGHT_SAMPLE_SIZE:
        raise ValueError(f"need at least {UPRIGHT_SAMPLE_SIZE} correspondences for an upright F, got {n}")
    rng = np.random.default_rng(options.seed)
    thr = options.threshold_rad
    pool = tv.sample_pool(n, options)
    if pool < UPRIGHT_SAMPLE_SIZE:
        raise ValueError(f"need at least {UPRIGHT_SAMPLE_SIZE} correspondences to sample an upright F from, got {pool}")
    best_F, best_cost, drawn = None, np.inf, 0
    while drawn < options.max_iterations:
        batch = min(options.batch_size, options.max_iterations - drawn)
        samples = _draw_upright_samples(rng, batch, pool, options.head_share)
        Fs, valid = upright_f_minimal_batch(b_i[samples], b_j[samples])
        drawn += batch
        if valid.any():
            Fs = Fs[valid]
            costs = tv.msac_costs(Fs, b_i, b_j, thr)
            k = int(np.argmin(costs))
            if costs[k] < best_cost:
                best_F, best_cost = _local_optimization_upright(b_i, b_j, Fs[k], thr,
                                                                options.local_optimization_steps)
        if best_F is None:
            continue
        # the inlier ratio among the matches samples are drawn from
        ratio = float((tv.epipolar_angular_errors(best_F, b_i[:pool], b_j[:pool]) < thr).mean())
        required = tv.required_iterations(ratio, options.confidence, sample_size=UPRIGHT_SAMPLE_SIZE)
        if drawn >= options.min_iterations and drawn >= required:
            break
    if best_F is None:
        raise ValueError("no upright model: every sample was degenerate")
    # two_view's refinement is not upright: the upright one, polished (`two_view._finish`): the same F and inliers
    # whichever sample found the model.
    return tv._finish(b_i, b_j, best_F, thr, options.refine, drawn, refine_fn=refine_f_upright,
                      min_points=MIN_LINEAR_POINTS, polish=True)


# --------------------------------------------------------------------------------------------- levelling
def leveling_rotation(gravity_cam: np.ndarray) -> np.ndarray:
    """The minimal rotation L with ``L @ gravity_cam ∝ (0, 1, 0)`` (gravity onto the camera's "down" axis)."""
    return tv.rotation_between(normalize(np.asarray(gravity_cam, dtype=np.float64)), Y_AXIS)


def level_bearings(bearings: np.ndarray, gravity_cam: np.ndarray) -> np.ndarray:
    """Bearings (N, 3) expressed in the levelled frame, where gravity is +y."""
    return np.asarray(bearings, dtype=np.float64) @ leveling_rotation(gravity_cam).T


def unlevel_f(F_level: np.ndarray, L_i: np.ndarray, L_j: np.ndarray) -> np.ndarray:
    """F of the original bearings from F of the levelled ones: (L_i b_i)ᵀ F_level (L_j b_j) = b_iᵀ F b_j."""
    return L_i.T @ F_level @ L_j


def unlevel_rotation(R_level: np.ndarray, L_i: np.ndarray, L_j: np.ndarray) -> np.ndarray:
    """R_j_from_i of the original cameras from the levelled relative rotation (a yaw): L_jᵀ R_level L_i."""
    return L_j.T @ R_level @ L_i


# --------------------------------------------------------------------------------------------- gravity from lines
def _segment_detector():
    """A function gray uint8 image -> (K, 4) segments x1, y1, x2, y2 (LSD, else Canny + probabilistic Hough)."""
    import cv2  # OpenCV only for the image part: the geometry above stays numpy/scipy

    try:
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
        return lambda gray: _as_segments(lsd.detect(gray)[0])
    except (cv2.error, AttributeError):  # builds without LSD (OpenCV 3.4.6–4.5.0 removed it)
        def hough(gray):
            edges = cv2.Canny(gray, 50, 150)
            size = min(gray.shape)
            return _as_segments(cv2.HoughLinesP(edges, 1, np.pi / 720, threshold=size // 10,
                                                minLineLength=size // 20, maxLineGap=3))
        return hough


def _as_segments(lines) -> np.ndarray:
    return np.zeros((0, 4)) if lines is None else np.asarray(lines, dtype=np.float64).reshape(-1, 4)


def detect_line_normals(image: np.ndarray, *, face_size: int = 0, margin_deg: float = 5.0,
                        min_length_frac: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (M, 3) of the great circles of straight segments, camera frame, and their lengths (M,) in
    face pixels. Segments are detected on the 4 horizontal cube faces, where vertical edges look near-vertical and
    straight (an equirectangular image bends them).
    """
    import cv2

    from fullview.sfm.features import face_keypoints_to_bearings, face_maps, native_face_size

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    gray = gray if gray.dtype == np.uint8 else np.clip(gray, 0, 255).astype(np.uint8)
    height, width = gray.shape
    size = face_size or native_face_size(width, margin_deg)
    map_x, map_y, focal = face_maps(size, margin_deg, width, height)
    detect = _segment_detector()
    normals, lengths = [], []
    for face in range(4):  # front, right, back, left: the faces around the horizon
        segments = detect(cv2.remap(gray, map_x[face], map_y[face], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP))
        length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
        segments = segments[length >= min_length_frac * size]
        # OpenCV puts pixel centres at integers; face_keypoints_to_bearings wants continuous coordinates.
        ends = face_keypoints_to_bearings(segments.reshape(-1, 2) + 0.5, face, size, focal).reshape(-1, 2, 3)
        normals.append(normalize(np.cross(ends[:, 0], ends[:, 1])))
        lengths.append(length[length >= min_length_frac * size])
    return np.concatenate(normals), np.concatenate(lengths)


def _circle_pairs(m: int, num_pairs: int, seed: int) -> np.ndarray:
    """(P, 2) pairs of m circles whose intersections are the candidate directions: every pair when there are at most
    num_pairs of them (an image's 16-130 vertical segments: the result then does not depend on the seed), else
    num_pairs random ones."""
    if m * (m - 1) // 2 <= num_pairs:
        return np.column_stack(np.triu_indices(m, k=1))
    return np.random.default_rng(seed).integers(0, m, size=(num_pairs, 2))


GRAVITY_REFIT_ROUNDS = 20  # at most this many least-squares re-fits of the vertical direction


def vertical_direction_from_normals(normals: np.ndarray, weights: np.ndarray | None = None, *,
                                    max_tilt_deg: float = 20.0, inlier_deg: float = 1.0, min_lines: int = 6,
                                    num_pairs: int = 10_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """Direction v (y ≥ 0) within max_tilt_deg of +y that the most great circles (unit normals) pass through, and
    the inlier mask; None with fewer than min_lines supporting circles.

    RANSAC over pairs (v = n₁ × n₂, scored by the summed weights of circles within inlier_deg of v), then the
    least-squares direction: the eigenvector of Σ w n nᵀ with the smallest eigenvalue, over the inliers.
    """
    normals = normalize(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    weights = np.ones(len(normals)) if weights is None else np.asarray(weights, dtype=np.float64)
    # A circle through a v within max_tilt of y has |n · y| ≤ sin(max_tilt): the other circles cannot be inliers.
    candidates = np.abs(normals[:, 1]) < np.sin(np.radians(max_tilt_deg))
    n, w = normals[candidates], weights[candidates]
    if len(n) < max(min_lines, 2):
        return None
    pairs = _circle_pairs(len(n), num_pairs, seed)
    v = np.cross(n[pairs[:, 0]], n[pairs[:, 1]])
    # Near-parallel circles (one edge detected twice) pin v down poorly.
    v = normalize(v[np.linalg.norm(v, axis=1) > np.sin(np.radians(5.0))])
    v *= np.where(v[:, 1] < 0, -1.0, 1.0)[:, None]
    v = v[v[:, 1] > np.cos(np.radians(max_tilt_deg))]
    if len(v) == 0:
        return None
    sin_inlier = np.sin(np.radians(inlier_deg))
    scores = (np.abs(v @ n.T) < sin_inlier) @ w
    best = v[np.argmax(scores)]
    # Least squares on the inliers, then re-select them around the refined direction, until they no longer change:
    # a fixed number of rounds leaves the direction depending on which sampled pair won (the RANSAC seed would move
    # the result by a fraction of the inlier band).
    inliers = np.abs(n @ best) < sin_inlier
    for _ in range(GRAVITY_REFIT_ROUNDS):
        if inliers.sum() < 2:
            return None
        _, vecs = np.linalg.eigh((n[inliers] * w[inliers, None]).T @ n[inliers])
        best = vecs[:, 0] * (1.0 if vecs[1, 0] >= 0 else -1.0)
        previous, inliers = inliers, np.abs(n @ best) < sin_inlier
        if np.array_equal(previous, inliers):
            break
    if inliers.sum() < min_lines:
        return None
    mask = np.zeros(len(normals), dtype=bool)
    mask[np.flatnonzero(candidates)[inliers]] = True
    return best, mask


def estimate_gravity(image: np.ndarray, *, face_size: int = 0, max_tilt_deg: float = 20.0, inlier_deg: float = 1.0,
                     min_lines: int = 6, seed: int = 0) -> tuple[np.ndarray, int] | None:
    """Gravity direction in the camera frame (unit, pointing "down", towards +y) from the vertical edges of an
    equirectangular image (H, W, 3) uint8 or gray, and the number of supporting segments; None with too few.

    Assumes the camera is within max_tilt_deg of level and the scene has vertical edges (walls, doors, furniture).
    Segments are weighted by length in the fit: long edges locate their circle more precisely.
    """
    found = estimate_gravity_with_std(image, face_size=face_size, max_tilt_deg=max_tilt_deg, inlier_deg=inlier_deg,
                                      min_lines=min_lines, seed=seed)
    return None if found is None else found[:2]


def estimate_gravity_with_std(image: np.ndarray, *, face_size: int = 0, max_tilt_deg: float = 20.0,
                              inlier_deg: float = 1.0, min_lines: int = 6,
                              seed: int = 0) -> tuple[np.ndarray, int, float] | None:
    """`estimate_gravity` and the standard error of its direction (radians, `vertical_direction_std`)."""
    normals, lengths = detect_line_normals(np.asarray(image), face_size=face_size)
    return gravity_with_std_from_normals(normals, lengths, max_tilt_deg=max_tilt_deg, inlier_deg=inlier_deg,
                                         min_lines=min_lines, seed=seed)


def gravity_with_std_from_normals(normals: np.ndarray, lengths: np.ndarray, *, max_tilt_deg: float = 20.0,
                                  inlier_deg: float = 1.0, min_lines: int = 6,
                                  seed: int = 0) -> tuple[np.ndarray, int, float] | None:
    """`estimate_gravity_with_std` on line segments already found (`detect_line_normals`)."""
    found = vertical_direction_from_normals(normals, lengths, max_tilt_deg=max_tilt_deg, inlier_deg=inlier_deg,
                                            min_lines=min_lines, seed=seed)
    if found is None:
        return None
    v, inliers = found
    return v, int(inliers.sum()), vertical_direction_std(normals[inliers], lengths[inliers], v)


def vertical_direction_std(normals: np.ndarray, weights: np.ndarray, v: np.ndarray) -> float:
    """Standard error (radians, along the worst direction) of the weighted least-squares direction v through the
    great circles with these unit normals: the residual spread s² = Σ w (n·v)² / (m − 2) (weights scaled to mean 1)
    over the information the circles give in the plane orthogonal to v, s² (Bᵀ Σ w n nᵀ B)⁻¹. Segments of one edge
    are not independent, so this is a lower bound; the bundle adjustment widens it by the spread of the images'
    gravities about its adjusted up direction (`bundle.gravity_error_factor`)."""
    w = np.asarray(weights, dtype=np.float64) / np.mean(weights)
    n = np.asarray(normals, dtype=np.float64)
    if len(n) < 3:
        return float("inf")
    s2 = float(w @ (n @ v) ** 2) / (len(n) - 2)
    B = tangent_basis(v[None])[0].T  # (3, 2)
    info = B.T @ ((n * w[:, None]).T @ n) @ B
    try:
        return float(np.sqrt(s2 * np.linalg.eigvalsh(np.linalg.inv(info)).max()))
    except np.linalg.LinAlgError:
        return float("inf")
