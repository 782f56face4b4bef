"""Bundle adjustment on the sphere: angular residuals, analytic sparse Jacobian, fixed gauge.

Parameters. Each camera is ``(ω, C)``: a rotation vector applied on top of the initial rotation,
``R = exp([ω]×) R_init``, and its centre ``C`` (so ``x_cam = R (X − C)``, ``t = −R C``); points are
free world coordinates ``X``.

Residuals. For an observation with observed unit bearing ``z`` and predicted direction
``p = normalize(R (X − C))``, let ``E`` (2×3) be an orthonormal basis of the plane orthogonal to
``z``, ``q = E p`` (``|q| = sin θ``), ``θ = atan2(|q|, zᵀp)`` the angular error. The residual is
``r = (θ / sin θ) q``: a 2-vector whose norm is exactly θ (radians) and whose direction is the
tangent direction of the error. It stays large behind the camera (``|r| = θ → π`` as ``p → −z``,
where plain ``E p`` would go back to zero); exactly at ``p = −z`` it is ``(π, 0)``.

Gauge (7 dof: rotation, translation, scale). The cameras in ``fixed_cameras`` keep their poses
exactly. If only one camera is fixed, the scale is fixed by keeping the distance between that
camera's centre and the centre of a ``scale_camera`` (by default the camera farthest from it,
which is well defined whatever the direction of the baseline, unlike fixing one coordinate):
that camera's centre moves on a sphere, parametrised by 2 tangent coordinates. With two or more
fixed cameras (distinct centres) the scale is already fixed and no camera is constrained.
With a gravity prior, a fixed camera with a measured gravity that is its group's only fixed camera keeps its centre
and heading but not its tilt (the prior's up direction fixes the tilt gauge instead; `_tilt_free_cameras`).

Robust loss. The cost is ``½·f²·Σ_k ρ((θ_k/f)²)`` with scipy's loss names. It is minimised by
iteratively reweighted least squares (linear loss on weighted residuals), with the scale f lowered
from about the initial error size to ``loss_scale_rad``; see ``_irls`` for why not scipy's own
robust losses.

Gravity prior (optional, ``GravityPrior``). A camera whose gravity was measured in its own frame (from vertical
lines) adds the residual ``r = w · E_g R u``: ``u`` the world's up direction (one per model), ``E_g`` a basis of the
plane orthogonal to the measured gravity ``g``, ``w = σ_obs / σ_g`` (observation noise over the gravity's standard
error, so both terms are in the same units). It depends on the camera's rotation only and enters the reduced camera
system as a 3×3 block on ω. Why: on a chain of rooms the bearings leave the tilt of each room free to drift slowly
(0.1-0.3° at the far end); each image's gravity is ~0.1° off but independent, so together they hold the tilt.
Both σ are estimated from the data, one variance component per group (Helmert/Förstner): σ_obs from the bearings'
residuals over their residual degrees of freedom (`_observation_sigma`), and the stated σ_g, a lower bound, scaled
by how far the measured gravities lie from an adjusted model's up direction (`gravity_error_factor`).

Height prior (optional, ``heights.HeightPrior``). Rows ``w (d · (X_f − C_i) − h)`` for camera i and each point f of
the floor below it: ``d`` the model's down, ``h`` the model's common camera height (re-estimated between reweighting
rounds), ``w = σ_obs / (σ_h h √n_i)``. Each row depends on one camera's centre and one point, like a bearing's, so
the rows join the bearings' in the Schur system (`_rows`) and are eliminated with the points; see `heights` for why.

Solver. Each weighted problem takes Levenberg-Marquardt steps (Marquardt's diagonal damping, Nielsen's
damping update) solved through the Schur complement, as COLMAP/Ceres do: the 3×3 point blocks are
inverted in one batch and eliminated, leaving the reduced camera system (6 unknowns per camera),
dense Cholesky when small, sparse LU otherwise. An earlier version called scipy's trf with lsmr, whose
iterative solves of the whole system took ~80% of the time (see README "Benchmark").

Jacobian. Analytic, returned as a CSR matrix whose structure is built once: every residual row
depends on at most 6 camera parameters and 3 point parameters. The rotation part uses the left
Jacobian of SO(3), ``∂(exp([ω+δ]×) v)/∂δ = −[exp([ω]×) v]× J_l(ω)``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.linalg import spsolve

from fullview.sfm import manhattan
from fullview.sfm.heights import HeightPrior
from fullview.sfm.camera import camera_center, normalize, skew, tangent_basis
from fullview.sfm.triangulation import _pairs_within_tracks

log = logging.getLogger(__name__)
PARALLEL_MIN_OBSERVATIONS = 20_000  # residuals of larger problems are computed on two threads (`_residuals`)

# Robust losses ρ(s) of s = (θ / f)² and their derivatives ρ'(s), named as in scipy's least_squares.
# All are concave in s, which makes the reweighting in _irls a majorise-minimise scheme.
_LOSSES = {
    "linear": (lambda s: s, np.ones_like),
    "soft_l1": (lambda s: 2.0 * (np.sqrt(1.0 + s) - 1.0), lambda s: 1.0 / np.sqrt(1.0 + s)),
    "huber": (lambda s: np.where(s <= 1.0, s, 2.0 * np.sqrt(s) - 1.0), lambda s: 1.0 / np.sqrt(np.maximum(s, 1.0))),
    "cauchy": (np.log1p, lambda s: 1.0 / (1.0 + s)),
    "arctan": (np.arctan, lambda s: 1.0 / (1.0 + s**2)),
}
# Ratio between successive robust-loss scales of the graduated schedule (see _scale_schedule).
_SCALE_STEP = 4.0
# Most residual evaluations of one weighted solve before the weights are recomputed.
_ROUND_NFEV = 5
# Levenberg-Marquardt: initial damping (relative to the diagonal of JᵀJ, Ceres' default trust radius 1e4) and its
# bounds; diagonal entries are clamped from below so that unconstrained directions stay invertible.
_LM_INITIAL_DAMPING = 1e-4
_LM_DAMPING_BOUNDS = (1e-12, 1e12)
_MIN_DIAGONAL = 1e-12
# Reduced camera systems up to this many unknowns are solved dense (Cholesky), larger ones sparse (LU).
_DENSE_CAMERA_UNKNOWNS = 3000
# Dense Schur products: entries of one chunk of the (6N, 3·points) matrix, and how many multiply-adds of a BLAS
# product cost what one observation pair costs in numpy (measured ~0.8 µs a pair against ~10 G multiply-adds/s).
_DENSE_SCHUR_ENTRIES = 2_000_000  # 16 MB a chunk: at 4 M its 32 MB set the 24-view triangulation's memory peak
_PAIR_FLOPS = 8000.0
# Listed observation pairs hold ~0.8 kB each (the 96-view room's 3.4 M took 2 GB); above this many the dense products,
# whose chunks are bounded, are used whatever they cost, so memory stays bounded.
_MAX_OBSERVATION_PAIRS = 500_000


@dataclass(frozen=True, kw_only=True)
class BundleResult:
    """Refined cameras and points, with costs and per-observation errors."""

    R_cam_from_world: np.ndarray  # (N, 3, 3) refined rotations
    t_cam_from_world: np.ndarray  # (N, 3) refined translations
    points: np.ndarray  # (P, 3) refined world points
    initial_cost: float  # robust cost ½·f²·Σ_k ρ((θ_k/f)²) before optimisation (f = loss_scale_rad), plus the prior's
    final_cost: float  # same cost after optimisation
    obs_error_rad: np.ndarray  # (K,) final angular error of every observation, radians
    scale_camera: int  # camera whose distance to the first fixed camera was held (-1: none needed)
    num_evaluations: int  # residual evaluations made (Jacobian evaluations not counted)
    success: bool  # converged (cost decrease below ftol) before max_nfev ran out
    message: str  # how it stopped


@dataclass(frozen=True, kw_only=True)
class GravityPrior:
    """Measured gravity of some cameras, pulling their tilt towards the world's up direction (see module docstring)."""

    camera: np.ndarray  # (M,) camera index
    gravity_cam: np.ndarray  # (M, 3) measured unit gravity ("down") in the camera frame
    up_world: np.ndarray  # (M, 3) unit direction the camera should see as gravity, in world coordinates (a start:
    # bundle_adjust re-estimates it per group from the cameras it moves)
    group: np.ndarray  # (M,) cameras of one group (one model) share one world up direction
    sigma_rad: np.ndarray  # (M,) standard error of the measured gravity, radians


@dataclass(frozen=True, kw_only=True)
class _Layout:
    """Where each camera's and point's parameters live in the parameter vector."""

    cam_col: np.ndarray  # (N,) first column of each camera's parameters, -1 if fixed
    cam_dof: np.ndarray  # (N,) 0 fixed, 2 fixed but for its tilt (gravity prior), 5 scale camera (ω + 2 sphere
    # coordinates), 6 free (ω, C)
    point_col: int  # first column of the points (3 per point)
    num_params: int  # length of the parameter vector
    scale_camera: int  # index of the scale camera, -1 if none
    anchor: np.ndarray  # (3,) centre of the first fixed camera
    radius: float  # held distance anchor -> scale camera centre
    u0: np.ndarray  # (3,) initial unit direction anchor -> scale camera centre
    tangent: np.ndarray  # (3, 2) orthonormal basis orthogonal to u0
    tilt_basis: np.ndarray  # (N, 3, 2) for cam_dof 2: ω = basis @ (2 params), rotations about axes orthogonal to the
    # world up the camera sees (its tilt); zero otherwise


@dataclass(frozen=True, kw_only=True)
class _Problem:
    """Fixed inputs of one bundle adjustment."""

    R_init: np.ndarray  # (N, 3, 3) initial rotations (ω is applied on top)
    t_init: np.ndarray  # (N, 3) initial translations (returned as is for fixed cameras)
    C_init: np.ndarray  # (N, 3) initial centres (used for fixed cameras)
    obs_camera: np.ndarray  # (K,) camera of each observation
    obs_point: np.ndarray  # (K,) point of each observation
    bearings: np.ndarray  # (K, 3) observed unit bearings
    basis: np.ndarray  # (K, 2, 3) orthonormal tangent basis of each observed bearing
    layout: _Layout  # parameter layout
    prior_camera: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (M,) cameras with a gravity
    # prior (fixed ones too: they take part in the world up direction)
    prior_up: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (M, 3) their world up direction,
    # updated in place between reweighting rounds (`_update_world_up`)
    prior_group: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (M,) cameras sharing an up
    prior_gravity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (M, 3) measured gravity
    prior_basis: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # (M, 2, 3) basis orthogonal to
    # each measured gravity
    prior_sqrt_w: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) σ_obs / σ_g
    heading_camera: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (H,) cameras with a heading
    # prior (`manhattan`)
    heading_axis: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (H, 3) measured axis, camera frame
    heading_gravity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (H, 3) measured gravity
    heading_down: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (H, 3) the group's world down
    heading_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (H, 3) the group's world axis,
    # updated in place between reweighting rounds (`_update_world_axis`)
    heading_group: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (H,) cameras sharing an axis
    heading_sqrt_w: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (H,) σ_obs / σ_heading
    height_camera: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (F,) camera of each floor
    # row of the height prior (`heights`)
    height_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (F,) its floor point
    height_down: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (F, 3) its model's world down
    height_group: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (F,) rows sharing a height
    height_level: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (F,) the group's height, updated in
    # place between reweighting rounds (`_update_height_level`)
    height_sqrt_w: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (F,) σ_obs / (σ_h h √n_camera)


def _so3_coefficients(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sinθ/θ, (1−cosθ)/θ², (θ−sinθ)/θ³ for rotation vectors (N, 3), with series near θ = 0."""
    th2 = np.einsum("ni,ni->n", omega, omega)
    th = np.sqrt(th2)
    small = th < 1e-3
    th_s = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0, np.sin(th_s) / th_s)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th_s)) / th_s**2)
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th_s - np.sin(th_s)) / th_s**3)
    return a, b, c


def rotation_exp(omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation matrices exp([ω]×) and left Jacobians J_l(ω), both (N, 3, 3), for ω (N, 3)."""
    a, b, c = _so3_coefficients(omega)
    W = skew(omega)
    W2 = W @ W
    eye = np.eye(3)
    R = eye + a[:, None, None] * W + b[:, None, None] * W2
    J = eye + b[:, None, None] * W + c[:, None, None] * W2
    return R, J


def _angle_scale(s: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """θ = atan2(s, c), g = θ / s and dg/dc (c = cos θ, s = sin θ ≥ 0), series for small θ."""
    theta = np.arctan2(s, c)
    small = theta < 1e-3
    s_safe = np.maximum(s, 1e-300)
    g = np.where(small, 1.0 + theta**2 / 6.0, theta / s_safe)
    dg = np.where(small, -1.0 / 3.0 - 2.0 * theta**2 / 15.0, (c * g - 1.0) / np.maximum(s, 1e-12) ** 2)
    return theta, g, dg


def _build_layout(
    centers: np.ndarray, num_points: int, fixed: np.ndarray, scale_camera: int | None, obs_camera: np.ndarray,
    tilt_free: dict[int, np.ndarray] | None = None,
) -> _Layout:
    """Parameter layout for the given gauge choice; `tilt_free` maps fixed cameras whose tilt is left free (a
    gravity prior fixes the world's up direction instead) to that direction in their frame."""
    n = len(centers)
    cam_dof = np.full(n, 6, dtype=np.int64)
    cam_dof[fixed] = 0
    tilt_basis = np.zeros((n, 3, 2))
    for camera, up_cam in (tilt_free or {}).items():
        cam_dof[camera] = 2
        tilt_basis[camera] = tangent_basis(normalize(np.asarray(up_cam, np.float64))[None])[0].T
    anchor = centers[fixed[0]]
    if len(fixed) >= 2:
        scale_camera = -1
    elif scale_camera is None:
        dist = np.linalg.norm(centers - anchor, axis=1)
        dist[fixed] = -1.0
        dist[np.bincount(obs_camera, minlength=n) == 0] = -1.0  # only observed cameras
        scale_camera = int(np.argmax(dist)) if dist.max() > 0 else -1  # -1: no camera to hold
    elif not 0 <= scale_camera < n or scale_camera in fixed:
        raise ValueError(f"scale_camera={scale_camera} must be a non-fixed camera index in [0, {n})")
    radius, u0, tangent = 0.0, np.zeros(3), np.zeros((3, 2))
    if scale_camera >= 0:
        baseline = centers[scale_camera] - anchor
        radius = float(np.linalg.norm(baseline))
        if radius <= 1e-12 * max(1.0, float(np.abs(centers).max())):
            raise ValueError(f"scale_camera={scale_camera} has the same centre as fixed camera {fixed[0]}")
        u0 = baseline / radius
        tangent = tangent_basis(u0[None])[0].T
        cam_dof[scale_camera] = 5
    cam_col = np.where(cam_dof > 0, np.cumsum(cam_dof) - cam_dof, -1)
    point_col = int(cam_dof.sum())
    return _Layout(
        cam_col=cam_col, cam_dof=cam_dof, point_col=point_col, num_params=point_col + 3 * num_points,
        scale_camera=scale_camera, anchor=anchor, radius=radius, u0=u0, tangent=tangent, tilt_basis=tilt_basis,
    )


def _pack(layout: _Layout, centers: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Initial parameter vector (ω = 0, the given centres and points)."""
    x = np.zeros(layout.num_params)
    free = np.flatnonzero(layout.cam_dof == 6)
    x[layout.cam_col[free, None] + np.arange(3, 6)] = centers[free]
    x[layout.point_col:] = points.ravel()
    return x


def _rotation_vectors(x: np.ndarray, lay: _Layout) -> np.ndarray:
    """(N, 3) rotation vector ω of every camera (zero for fixed ones)."""
    omega = np.zeros((len(lay.cam_dof), 3))
    moving = np.flatnonzero(lay.cam_dof > 2)
    omega[moving] = x[lay.cam_col[moving, None] + np.arange(3)]
    tilt = np.flatnonzero(lay.cam_dof == 2)
    omega[tilt] = np.einsum("nij,nj->ni", lay.tilt_basis[tilt], x[lay.cam_col[tilt, None] + np.arange(2)])
    return omega


def _unpack(x: np.ndarray, problem: _Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rotation vectors (N, 3), centres (N, 3), points (P, 3), and dC/d(sphere coords) (3, 2)."""
    lay = problem.layout
    omega = _rotation_vectors(x, lay)
    centers = problem.C_init.copy()
    free = np.flatnonzero(lay.cam_dof == 6)
    centers[free] = x[lay.cam_col[free, None] + np.arange(3, 6)]
    dC = np.zeros((3, 2))
    if lay.scale_camera >= 0:
        col = lay.cam_col[lay.scale_camera]
        w = lay.u0 + lay.tangent @ x[col + 3 : col + 5]
        nw = np.linalg.norm(w)
        centers[lay.scale_camera] = lay.anchor + lay.radius * w / nw
        dC = lay.radius * (np.eye(3) - np.outer(w, w) / nw**2) @ lay.tangent / nw
    points = x[lay.point_col :].reshape(-1, 3)
    return omega, centers, points, dC


def _residuals(x: np.ndarray, problem: _Problem, with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(K, 2) residuals and, if asked, (K, 2, 9) Jacobian blocks [ω or pad (3), C or sphere (3), X (3)].

    Every observation's row depends on it alone, so large problems are computed in two halves on two threads (numpy
    releases the GIL in its loops): the same numbers as in one piece, in half the time on the two idle cores
    of the serial stages."""
    k = len(problem.obs_camera)
    if k < PARALLEL_MIN_OBSERVATIONS:
        return _residuals_of(x, problem, with_jacobian, slice(None))
    halves = (slice(0, k // 2), slice(k // 2, k))
    # Each half writes its Jacobian blocks into its rows of one array (no concatenated copy of the largest array).
    J = np.empty((k, 2, 9)) if with_jacobian else None
    with ThreadPoolExecutor(max_workers=2) as pool:
        (r0, _), (r1, _) = pool.map(lambda obs: _residuals_of(x, problem, with_jacobian, obs,
                                                              None if J is None else J[obs]), halves)
    return np.concatenate([r0, r1]), J


def _residuals_of(x: np.ndarray, problem: _Problem, with_jacobian: bool, obs: slice, J_out: np.ndarray | None = None):
    """`_residuals` of the observations in `obs` (their Jacobian blocks written into `J_out` when given)."""
    omega, centers, points, dC = _unpack(x, problem)
    dR, J_l = rotation_exp(omega)
    R = dR @ problem.R_init
    cam, pt = problem.obs_camera[obs], problem.obs_point[obs]
    basis, bearings = problem.basis[obs], problem.bearings[obs]
    R_obs = R[cam]
    y = np.einsum("kij,kj->ki", R_obs, points[pt] - centers[cam])
    norm = np.maximum(np.linalg.norm(y, axis=1), 1e-300)
    p = y / norm[:, None]
    q = np.einsum("kij,kj->ki", basis, p)
    c = np.einsum("ki,ki->k", bearings, p)
    s = np.linalg.norm(q, axis=1)
    theta, g, dg = _angle_scale(s, c)
    antipodal = (s < 1e-12) & (c < 0)  # q carries no direction: use (θ, 0)
    r = np.where(antipodal[:, None], np.stack([theta, np.zeros_like(theta)], axis=1), g[:, None] * q)
    if not with_jacobian:
        return r, None
    dr_dp = g[:, None, None] * basis + (dg[:, None] * q)[:, :, None] * bearings[:, None, :]
    dr_dp[(s < 1e-6) & (c < 0)] = 0.0  # within 1e-6 rad of the antipode the direction of r is unstable
    proj = (np.eye(3) - p[:, :, None] * p[:, None, :]) / norm[:, None, None]
    D = dr_dp @ proj  # (K, 2, 3) dr/dy
    J_X = D @ R_obs
    J = np.empty((len(cam), 2, 9)) if J_out is None else J_out
    J[:, :, 0:3] = -(D @ skew(y)) @ J_l[cam]
    J[:, :, 3:6] = -J_X
    J[:, :, 6:9] = J_X
    on_sphere = cam == problem.layout.scale_camera
    J[on_sphere, :, 3:5] = -J_X[on_sphere] @ dC
    J[on_sphere, :, 5] = 0.0
    tilt = problem.layout.cam_dof[cam] == 2
    J[tilt, :, 0:2] = J[tilt, :, 0:3] @ problem.layout.tilt_basis[cam[tilt]]
    J[tilt, :, 2:6] = 0.0
    return r, J


def _height_residuals(x: np.ndarray, problem: _Problem, with_jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(F, 2) weighted floor rows of the height prior, w (d · (X − C) − h) and a zero, and if asked their (F, 2, 9)
    Jacobian blocks in the bearings' layout [ω or pad, C or sphere, X] (one camera and one point per row)."""
    cam, pt = problem.height_camera, problem.height_point
    if not len(cam):
        return np.zeros((0, 2)), (np.zeros((0, 2, 9)) if with_jacobian else None)
    _, centers, points, dC = _unpack(x, problem)
    depth = np.einsum("fi,fi->f", points[pt] - centers[cam], problem.height_down)
    r = np.zeros((len(cam), 2))
    r[:, 0] = problem.height_sqrt_w * (depth - problem.height_level)
    if not with_jacobian:
        return r, None
    lay = problem.layout
    J = np.zeros((len(cam), 2, 9))
    J_X = problem.height_sqrt_w[:, None] * problem.height_down
    J[:, 0, 3:6] = -J_X
    J[:, 0, 6:9] = J_X
    on_sphere = cam == lay.scale_camera
    J[on_sphere, 0, 3:5] = -J_X[on_sphere] @ dC
    J[on_sphere, 0, 5] = 0.0
    J[lay.cam_dof[cam] <= 2, :, 0:6] = 0.0  # a fixed camera's centre (and a tilt-free one's) does not move
    return r, J


def _update_height_level(x: np.ndarray, problem: _Problem) -> None:
    """Each group's common height: the median over its cameras of their mean height above their floor rows (the
    gauge holds the model's scale, so the level follows it)."""
    cam = problem.height_camera
    if not len(cam):
        return
    _, centers, points, _ = _unpack(x, problem)
    depth = np.einsum("fi,fi->f", points[problem.height_point] - centers[cam], problem.height_down)
    for group in np.unique(problem.height_group):
        rows = problem.height_group == group
        cams, index = np.unique(cam[rows], return_inverse=True)
        problem.height_level[rows] = np.median(np.bincount(index, depth[rows]) / np.bincount(index))


def _rows(problem: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """Camera and point of every row the points are eliminated from: the bearings', then the height prior's."""
    if not len(problem.height_camera):
        return problem.obs_camera, problem.obs_point
    return (np.concatenate([problem.obs_camera, problem.height_camera]),
            np.concatenate([problem.obs_point, problem.height_point]))


def _prior_residuals(x: np.ndarray, problem: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) weighted prior residuals and their (M, 2, 3) Jacobian blocks on the ω of `_prior_cameras`: the
    gravity prior's, then the heading prior's (one residual each, the second component zero)."""
    if not len(problem.heading_camera):
        return _gravity_residuals(x, problem)
    r_g, J_g = _gravity_residuals(x, problem)
    r_h, J_h = _heading_residuals(x, problem)
    return np.concatenate([r_g, r_h]), np.concatenate([J_g, J_h])


def _prior_cameras(problem: _Problem) -> np.ndarray:
    """The camera of each row of `_prior_residuals`."""
    if not len(problem.heading_camera):
        return problem.prior_camera
    return np.concatenate([problem.prior_camera, problem.heading_camera])


def _heading_residuals(x: np.ndarray, problem: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """(H, 2) weighted heading-prior residuals (`manhattan.heading_residuals`, second component zero) and their
    (H, 2, 3) Jacobian blocks on each camera's ω: v = exp([ω]×) R₀ u, ∂v/∂ω = −[v]× J_l(ω)."""
    cams = problem.heading_camera
    lay = problem.layout
    dR, J_l = rotation_exp(_rotation_vectors(x, lay)[cams])
    v = np.einsum("mij,mj->mi", dR @ problem.R_init[cams], problem.heading_world)
    r, dr_dv = manhattan.heading_residuals(v, problem.heading_axis, problem.heading_gravity, problem.heading_sqrt_w)
    J = np.zeros((len(cams), 2, 3))
    J[:, 0] = np.einsum("mi,mij->mj", dr_dv, -skew(v) @ J_l)
    J[lay.cam_dof[cams] == 0] = 0.0
    tilt = lay.cam_dof[cams] == 2
    J[tilt, :, 0:2] = J[tilt] @ lay.tilt_basis[cams[tilt]]
    J[tilt, :, 2] = 0.0
    return np.stack([r, np.zeros_like(r)], axis=1), J


def _update_world_axis(x: np.ndarray, problem: _Problem) -> None:
    """Each group's world Manhattan axis: the precision-weighted circular mean of its cameras' measured axes carried
    to the world by their current rotations (alternated with the pose steps, as `_update_world_up`)."""
    cams = problem.heading_camera
    if not len(cams):
        return
    R = rotation_exp(_rotation_vectors(x, problem.layout)[cams])[0] @ problem.R_init[cams]
    axis_world = np.einsum("mji,mj->mi", R, problem.heading_axis)
    for group in np.unique(problem.heading_group):
        rows = np.flatnonzero(problem.heading_group == group)
        down = problem.heading_down[rows[0]]
        problem.heading_world[rows] = manhattan.mean_axis(manhattan.world_heading(axis_world[rows], down),
                                                          problem.heading_sqrt_w[rows] ** 2, down)


def _gravity_residuals(x: np.ndarray, problem: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) weighted gravity-prior residuals and their (M, 2, 3) Jacobian blocks on each camera's ω."""
    cams = problem.prior_camera
    if not len(cams):
        return np.zeros((0, 2)), np.zeros((0, 2, 3))
    lay = problem.layout
    moving = lay.cam_dof[cams] > 0
    omega = _rotation_vectors(x, lay)[cams]
    dR, J_l = rotation_exp(omega)
    v = np.einsum("mij,mj->mi", dR @ problem.R_init[cams], problem.prior_up)  # world up seen by the camera
    w = problem.prior_sqrt_w[:, None, None]
    r = np.einsum("mij,mj->mi", problem.prior_basis, v) * problem.prior_sqrt_w[:, None]
    J = w * (problem.prior_basis @ (-skew(v) @ J_l))
    J[~moving] = 0.0
    tilt = lay.cam_dof[cams] == 2
    J[tilt, :, 0:2] = J[tilt] @ lay.tilt_basis[cams[tilt]]
    J[tilt, :, 2] = 0.0
    return r, J


def _update_world_up(x: np.ndarray, problem: _Problem) -> None:
    """Each group's world up: the precision-weighted mean of its cameras' gravities carried to the world by their
    current rotations. Alternating it with the pose steps lets the cameras' gravities, not the start, decide the
    tilt (the start is the tilt drift the prior is there to correct)."""
    cams = problem.prior_camera
    if not len(cams):
        return
    lay = problem.layout
    R = rotation_exp(_rotation_vectors(x, lay)[cams])[0] @ problem.R_init[cams]
    down_world = np.einsum("mji,mj->mi", R, problem.prior_gravity) * problem.prior_sqrt_w[:, None] ** 2
    groups, index = np.unique(problem.prior_group, return_inverse=True)
    sums = np.zeros((len(groups), 3))
    np.add.at(sums, index, down_world)
    # A group whose fixed camera's tilt is free keeps its up direction: it is the gauge there.
    gauge = np.zeros(len(groups), bool)
    gauge[index[lay.cam_dof[cams] == 2]] = True
    update = ~gauge[index]
    problem.prior_up[update] = normalize(sums)[index[update]]


def _jacobian_structure(problem: _Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 9) valid-slot mask broadcast to (K, 2, 9), CSR column indices and row pointers."""
    lay = problem.layout
    cam, pt = _rows(problem)
    cols = np.concatenate([lay.cam_col[cam, None] + np.arange(6), lay.point_col + 3 * pt[:, None] + np.arange(3)], 1)
    valid = np.concatenate([np.arange(6) < lay.cam_dof[cam, None], np.ones((len(cam), 3), dtype=bool)], 1)
    mask = np.broadcast_to(valid[:, None, :], (len(cam), 2, 9))
    indices = np.broadcast_to(cols[:, None, :], (len(cam), 2, 9))[mask]
    indptr = np.r_[0, np.cumsum(np.repeat(valid.sum(1), 2))]
    return mask, indices, indptr


def _robust_cost(theta: np.ndarray, loss: str, f_scale: float) -> float:
    """½·f²·Σρ((θ/f)²) of per-observation angular errors θ (radians)."""
    return float(0.5 * f_scale**2 * _LOSSES[loss][0]((theta / f_scale) ** 2).sum())


class _WeightedResiduals:
    """Residuals √w·r and their Jacobian (blocks, or CSR), with per-observation weights w.

    The unweighted residuals of the last point are cached, so scipy's first evaluation of a round
    (at the point where the weights were just computed) costs nothing; ``evaluations`` counts the
    residual evaluations actually made.
    """

    def __init__(self, problem: _Problem):
        self.problem = problem
        self.shape = (2 * len(_rows(problem)[0]), problem.layout.num_params)
        self.sqrt_w = np.ones(len(problem.obs_camera))
        self.evaluations = 0
        self.damping = _LM_INITIAL_DAMPING  # Levenberg-Marquardt's λ, kept between reweighting rounds
        self._cache: tuple[np.ndarray, np.ndarray] | None = None

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """(K, 2) unweighted residuals (cached for the last x)."""
        if self._cache is None or not np.array_equal(self._cache[0], x):
            self._cache = (x.copy(), _residuals(x, self.problem, False)[0])
            self.evaluations += 1
        return self._cache[1]

    def errors(self, x: np.ndarray) -> np.ndarray:
        """(K,) unweighted angular errors θ (the norm of each 2-D residual)."""
        return np.linalg.norm(self.residuals(x), axis=1)

    def fun(self, x: np.ndarray) -> np.ndarray:
        """(2K + 2F + 2M,) weighted residuals: the observations', the height prior's, then the gravity prior's."""
        return np.concatenate([(self.residuals(x) * self.sqrt_w[:, None]).ravel(),
                               _height_residuals(x, self.problem, False)[0].ravel(),
                               _prior_residuals(x, self.problem)[0].ravel()])

    def prior_cost(self, x: np.ndarray) -> float:
        """½|r|² of the priors' residuals, the height prior's too (0 without a prior)."""
        r = _prior_residuals(x, self.problem)[0]
        h = _height_residuals(x, self.problem, False)[0]
        return 0.5 * float((r**2).sum() + (h**2).sum())

    def prior_blocks(self, x: np.ndarray) -> np.ndarray:
        """(M, 2, 3) Jacobian blocks of the gravity prior on ω."""
        return _prior_residuals(x, self.problem)[1]

    def jac(self, x: np.ndarray) -> csr_matrix:
        """(2K + 2M, n) weighted Jacobian, sparse: the observations', then the gravity prior's rows."""
        mask, indices, indptr = _jacobian_structure(self.problem)  # built on demand: (K, 18) indices
        obs = csr_matrix((self.jac_blocks(x)[mask], indices, indptr), shape=self.shape)
        cams = _prior_cameras(self.problem)
        if not len(cams):
            return obs
        cols = np.broadcast_to((np.maximum(self.problem.layout.cam_col[cams], 0)[:, None] + np.arange(3))[:, None, :],
                               (len(cams), 2, 3))  # a fixed camera's blocks are zero
        rows = np.broadcast_to(np.arange(2 * len(cams)).reshape(-1, 2, 1), cols.shape)
        prior = coo_matrix((self.prior_blocks(x).ravel(), (rows.ravel(), cols.ravel())),
                           shape=(2 * len(cams), self.shape[1]))
        return csr_matrix(scipy.sparse.vstack([obs, prior]))

    def jac_blocks(self, x: np.ndarray) -> np.ndarray:
        """(K + F, 2, 9) weighted Jacobian blocks [ω or pad, C or sphere, X] (see `_residuals`), the height
        prior's rows last."""
        J = _residuals(x, self.problem, True)[1] * self.sqrt_w[:, None, None]
        if not len(self.problem.height_camera):
            return J
        return np.concatenate([J, _height_residuals(x, self.problem, True)[1]])


class _SchurSystem:
    """The normal equations JᵀJ δ = −Jᵀr of one bundle adjustment, solved by eliminating the points.

    Built once per problem: which parameters of each camera are free (of its 6 Jacobian columns: none for a fixed
    camera, 5 for the scale camera), where they live in x, the incidence matrices that sum per-observation blocks
    per camera and per point, and the pairs of observations of one point by two moving cameras, grouped by their
    camera pair (a point couples the cameras that see it in the reduced system).
    """

    def __init__(self, problem: _Problem):
        lay = problem.layout
        cam, pt = _rows(problem)
        n, p, k = len(lay.cam_dof), (lay.num_params - lay.point_col) // 3, len(cam)
        self.cam, self.pt, self.num_cameras, self.num_points = cam, pt, n, p
        active = np.arange(6)[None, :] < lay.cam_dof[:, None]  # (N, 6) free Jacobian columns of each camera
        self.active = np.flatnonzero(active.ravel())  # into the 6N camera unknowns
        self.x_cam = (np.where(active, lay.cam_col[:, None], 0) + np.arange(6))[active]  # the same, into x
        self.point_col = lay.point_col
        self.by_camera = csr_matrix((np.ones(k), (cam, np.arange(k))), shape=(n, k))
        self.by_point = csr_matrix((np.ones(k), (pt, np.arange(k))), shape=(p, k))
        self.pt_order = np.argsort(pt, kind="stable")
        self.pt_sorted = pt[self.pt_order]
        self.moving = lay.cam_dof[cam] > 0
        self.chunks = self._dense_chunks()
        # The Schur complement by dense matrix products costs 108·(cameras of a chunk)²·(its points) multiply-adds
        # at BLAS speed, by observation pairs 108 each at numpy's gather speed: dense wins unless tracks are short
        # among many cameras. The pairs themselves are listed only when used (they grow with the tracks' squares).
        dense_flops = sum(108.0 * (len(rows) // 6) ** 2 * len(np.unique(pt[obs])) for obs, _, _, rows in self.chunks)
        m = np.bincount(pt[self.moving], minlength=p).astype(np.float64)  # moving observations per point
        num_pairs = float((m * (m + 1) / 2).sum())
        self.dense_products = dense_flops < _PAIR_FLOPS * num_pairs or num_pairs > _MAX_OBSERVATION_PAIRS
        self._groups = None

    @property
    def groups(self):
        """Pairs (k before l) of observations of one point by two moving cameras, and the diagonal (k, k), each
        grouped by camera pair (see `_grouped`)."""
        if self._groups is None:
            p = self.num_points
            first, second = _pairs_within_tracks(np.r_[0, np.cumsum(np.bincount(self.pt, minlength=p))])
            first, second = self.pt_order[first], self.pt_order[second]
            both = self.moving[first] & self.moving[second]
            diagonal = np.flatnonzero(self.moving)
            self._groups = [self._grouped(first[both], second[both]), self._grouped(diagonal, diagonal)]
        return self._groups

    def _grouped(self, first: np.ndarray, second: np.ndarray):
        """Observation pairs sorted by camera pair, with the start of each camera pair's run and its cameras."""
        key = self.cam[first] * self.num_cameras + self.cam[second]
        order = np.argsort(key, kind="stable")
        keys, starts = np.unique(key[order], return_index=True)
        return first[order], second[order], starts, keys // self.num_cameras, keys % self.num_cameras

    def solve(self, r: np.ndarray, J: np.ndarray, damping: float, J_prior: np.ndarray | None = None,
              prior_camera: np.ndarray | None = None):
        """Step δ (in x's layout) of (JᵀJ + λ·D) δ = −Jᵀr, D the clamped diagonal of JᵀJ, with the cost decrease
        the linear model predicts, ½δᵀ(λDδ − Jᵀr); None when the damped system cannot be factored. r holds the K
        observation residuals, then those of the gravity prior (blocks J_prior on the ω of prior_camera)."""
        n, p, k = self.num_cameras, self.num_points, len(J)
        r, r_prior = r[:k], r[k:]
        # Per-observation products from a contiguous Jᵀ: numpy's batched product of small matrices takes a slow
        # path on a transposed view (3× the time). Slices of J and J_t keep each small matrix contiguous.
        J_t = np.ascontiguousarray(J.transpose(0, 2, 1))  # (K, 9, 2)
        U = (self.by_camera @ (J_t[:, :6] @ J[:, :, :6]).reshape(k, 36)).reshape(n, 6, 6)
        V = (self.by_point @ (J_t[:, 6:] @ J[:, :, 6:]).reshape(k, 9)).reshape(p, 3, 3)
        W = J_t[:, :6] @ J[:, :, 6:]  # (K, 6, 3) camera-point coupling of each observation
        g = (J_t @ r[:, :, None])[:, :, 0]  # (K, 9)
        g_c = self.by_camera @ g[:, :6]  # (N, 6)
        g_p = self.by_point @ g[:, 6:]  # (P, 3)
        del J_t, g  # per-observation arrays not held through the reduced system (the stage's memory peak)
        if J_prior is not None and len(J_prior):
            J_prior_t = J_prior.transpose(0, 2, 1)
            np.add.at(U, (prior_camera, slice(0, 3), slice(0, 3)), J_prior_t @ J_prior)
            np.add.at(g_c, (prior_camera, slice(0, 3)), (J_prior_t @ r_prior[:, :, None])[:, :, 0])
        D_c = np.maximum(np.einsum("nii->ni", U), _MIN_DIAGONAL)
        D_p = np.maximum(np.einsum("pii->pi", V), _MIN_DIAGONAL)
        U[:, np.arange(6), np.arange(6)] += damping * D_c
        V[:, np.arange(3), np.arange(3)] += damping * D_p
        V_inv = _inverse_spd3(V)  # positive definite: PSD plus a positive diagonal
        if not np.isfinite(V_inv).all():  # a determinant out of range: treated as a failed factorisation
            return None
        # Reduced camera system S δc = b with S = U − W V⁻¹ Wᵀ, b = −g_c + W V⁻¹ g_p.
        V_inv_g = (V_inv @ g_p[:, :, None])[:, :, 0]
        rhs = (-g_c + self.by_camera @ (W @ V_inv_g[self.pt][:, :, None])[:, :, 0]).ravel()[self.active]
        delta_c = np.zeros(6 * n)
        try:
            delta_c[self.active] = self._solve_reduced(U, V_inv, W, rhs)
        except (np.linalg.LinAlgError, RuntimeError):
            return None
        if not np.isfinite(delta_c).all():
            return None
        # Back-substitution: δp = V⁻¹ (−g_p − Wᵀ δc).
        W_t_delta = self.by_point @ (delta_c.reshape(n, 6)[self.cam][:, None, :] @ W)[:, 0, :]  # Σ Wᵀ δc, as δcᵀ W
        delta_p = (V_inv @ (-g_p - W_t_delta)[:, :, None])[:, :, 0]
        d_c = delta_c[self.active]
        step = np.zeros(self.point_col + 3 * p)
        step[self.x_cam] = d_c
        step[self.point_col:] = delta_p.ravel()
        predicted = 0.5 * (damping * ((D_c.ravel()[self.active] * d_c**2).sum() + (D_p * delta_p**2).sum())
                           - d_c @ g_c.ravel()[self.active] - delta_p.ravel() @ g_p.ravel())
        return step, predicted

    def _solve_reduced(self, U: np.ndarray, V_inv: np.ndarray, W: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Solve S δ = rhs over the active camera unknowns, S = U − Σ_points Σ_{k,l} W_k V⁻¹ W_lᵀ (k, l the
        point's observations): dense Cholesky for few cameras, sparse LU otherwise."""
        n = self.num_cameras
        dense = len(self.active) <= _DENSE_CAMERA_UNKNOWNS
        if dense and self.dense_products:
            S = self._dense_correction(V_inv, W)
            S.reshape(n, 6, n, 6)[np.arange(n), :, np.arange(n), :] += U
            S = S[np.ix_(self.active, self.active)]
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
        blocks, rows, cols = [U], [np.arange(n)], [np.arange(n)]
        T = W @ V_inv[self.pt]
        for i, (first, second, starts, cam_a, cam_b) in enumerate(self.groups):
            if not len(first):
                continue
            summed = -np.add.reduceat((T[first] @ W[second].transpose(0, 2, 1)).reshape(-1, 36), starts, axis=0)
            blocks.append(summed.reshape(-1, 6, 6))
            rows.append(cam_a), cols.append(cam_b)
            if i == 0:  # pairs k before l: the (l, k) terms are the transposed blocks
                blocks.append(summed.reshape(-1, 6, 6).transpose(0, 2, 1))
                rows.append(cam_b), cols.append(cam_a)
        if dense:
            S = np.zeros((n, 6, n, 6))
            for b, r, c in zip(blocks, rows, cols):
                S[r, :, c, :] += b  # camera pairs are unique within each group
            S = S.reshape(6 * n, 6 * n)[np.ix_(self.active, self.active)]
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(S), rhs)
        b, r, c = np.concatenate(blocks), np.concatenate(rows), np.concatenate(cols)
        r6 = np.broadcast_to((6 * r[:, None] + np.arange(6))[:, :, None], b.shape).ravel()
        c6 = np.broadcast_to((6 * c[:, None] + np.arange(6))[:, None, :], b.shape).ravel()
        S = csr_matrix(coo_matrix((b.ravel(), (r6, c6)), shape=(6 * n, 6 * n)))[self.active][:, self.active]
        return spsolve(S.tocsc(), rhs)

    def _dense_chunks(self) -> list[tuple[np.ndarray | slice, np.ndarray, int, np.ndarray]]:
        """Chunks of consecutive points for `_dense_correction`, each with at most `_DENSE_SCHUR_ENTRIES` entries of
        the dense (6·cameras, 3·points) matrix (only the chunk's cameras): its observations (a slice when one chunk
        holds them all), where each observation's 6×3 block starts in that matrix (its top-left entry), the
        matrix's width and the rows of S its rows add to. Fixed per problem, so every solve scatters at once."""
        chunks, size = [], max(1, _DENSE_SCHUR_ENTRIES // (18 * self.num_cameras))
        for lo in range(0, self.num_points, size):
            obs = self.pt_order[slice(*np.searchsorted(self.pt_sorted, [lo, lo + size]))]
            if len(obs) == len(self.pt):
                obs = slice(None)  # every observation, in its own order (the scatter sums them whatever the order)
            pt = self.pt[obs]
            cameras, local = np.unique(self.cam[obs], return_inverse=True)
            first, width = pt.min(), 3 * (pt.max() - pt.min() + 1)
            chunks.append((obs, 6 * width * local + 3 * (pt - first), width, (6 * cameras[:, None] + np.arange(6)).ravel()))
        return chunks

    def _dense_correction(self, V_inv: np.ndarray, W: np.ndarray) -> np.ndarray:
        """−W V⁻¹ Wᵀ as a dense (6N, 6N) matrix: with V⁻¹ = L Lᵀ per point and Z = W L, it is −Z Zᵀ, Z scattered into
        a dense (6·cameras, 3·points) matrix per chunk of points (only the chunk's cameras): one BLAS product each."""
        n = self.num_cameras
        L = _cholesky3(V_inv)
        if not np.isfinite(L).all():  # not numerically positive definite (numpy's cholesky would raise)
            raise np.linalg.LinAlgError("a point block is not positive definite")
        S = np.zeros((6 * n, 6 * n))
        for obs, start, width, rows in self.chunks:
            Z = W[obs] @ L[self.pt[obs]]  # (observations of the chunk, 6, 3)
            index = start[:, None, None] + (width * np.arange(6)[:, None] + np.arange(3))
            Z_dense = np.bincount(index.ravel(), weights=Z.ravel(), minlength=len(rows) * width)
            Z_dense = Z_dense.reshape(len(rows), width)
            S[np.ix_(rows, rows)] -= Z_dense @ Z_dense.T
        return S


def _inverse_spd3(A: np.ndarray) -> np.ndarray:
    """Inverses of symmetric positive definite 3×3 matrices (..., 3, 3) by their adjugates (a batched LAPACK
    inverse costs ~10× more per matrix at this size; the same values to rounding)."""
    a, b, c, d, e, f = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2], A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    m00, m01, m02 = d * f - e * e, c * e - b * f, b * e - c * d
    m11, m12, m22 = a * f - c * c, b * c - a * e, a * d - b * b
    adjugate = np.stack([m00, m01, m02, m01, m11, m12, m02, m12, m22], axis=-1).reshape(A.shape)
    with np.errstate(invalid="ignore", divide="ignore"):  # a singular block gives inf / NaN (callers check)
        return adjugate / (a * m00 + b * m01 + c * m02)[..., None, None]


def _cholesky3(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of symmetric positive definite 3×3 matrices (..., 3, 3), in closed form (numpy's
    batched LAPACK call costs more per matrix than the arithmetic)."""
    L = np.zeros_like(A)
    with np.errstate(invalid="ignore", divide="ignore"):  # a block that is not positive definite gives NaN
        L[..., 0, 0] = l00 = np.sqrt(A[..., 0, 0])
        L[..., 1, 0] = l10 = A[..., 1, 0] / l00
        L[..., 2, 0] = l20 = A[..., 2, 0] / l00
        L[..., 1, 1] = l11 = np.sqrt(A[..., 1, 1] - l10 * l10)
        L[..., 2, 1] = l21 = (A[..., 2, 1] - l20 * l10) / l11
        L[..., 2, 2] = np.sqrt(A[..., 2, 2] - l20 * l20 - l21 * l21)
    return L


def _validate(R, t, points, obs_camera, obs_point, obs_bearings, fixed, loss, loss_scale_rad, max_nfev):
    """Convert and check the inputs of bundle_adjust (errors name the argument at fault)."""
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    obs_camera, obs_point = np.asarray(obs_camera, dtype=np.int64), np.asarray(obs_point, dtype=np.int64)
    obs_bearings = np.asarray(obs_bearings, dtype=np.float64)
    n, k = len(R), len(obs_camera)
    if R.shape != (n, 3, 3) or t.shape != (n, 3):
        raise ValueError(f"R_cam_from_world {R.shape} and t_cam_from_world {t.shape} must be (N,3,3), (N,3)")
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise ValueError(f"points must be a finite (P, 3) array, got shape {points.shape}")
    if obs_camera.shape != (k,) or obs_point.shape != (k,) or obs_bearings.shape != (k, 3):
        raise ValueError(f"obs_camera {obs_camera.shape}, obs_point {obs_point.shape}, obs_bearings "
                         f"{obs_bearings.shape} must be (K,), (K,), (K, 3)")
    if k == 0 or not (np.isfinite(obs_bearings).all() and (np.abs(obs_bearings).sum(1) > 0).all()):
        raise ValueError("obs_bearings must be non-empty, finite and non-zero")
    if obs_camera.min() < 0 or obs_camera.max() >= n:
        raise ValueError(f"obs_camera values must be in [0, {n})")
    if obs_point.min() < 0 or obs_point.max() >= len(points):
        raise ValueError(f"obs_point values must be in [0, {len(points)})")
    fixed = np.unique(np.asarray(fixed, dtype=np.int64))
    if len(fixed) == 0 or fixed.min() < 0 or fixed.max() >= n:
        raise ValueError(f"fixed_cameras={tuple(fixed)} must name at least one camera in [0, {n})")
    if loss not in _LOSSES:
        raise ValueError(f"loss={loss!r} must be one of {sorted(_LOSSES)}")
    if not loss_scale_rad > 0 or max_nfev < 1:
        raise ValueError(f"loss_scale_rad={loss_scale_rad} and max_nfev={max_nfev} must be positive")
    return R, t, points, obs_camera, obs_point, normalize(obs_bearings), fixed


def bundle_adjust(
    *,
    R_cam_from_world: np.ndarray,
    t_cam_from_world: np.ndarray,
    points: np.ndarray,
    obs_camera: np.ndarray,
    obs_point: np.ndarray,
    obs_bearings: np.ndarray,
    fixed_cameras: Sequence[int] = (0,),
    scale_camera: int | None = None,
    loss: str = "soft_l1",
    loss_scale_rad: float = 0.005,
    max_nfev: int = 100,
    ftol: float = 1e-4,
    gravity_prior: GravityPrior | None = None,
    pose_tolerance_rad: float = 0.0,
    heading_prior: manhattan.HeadingPrior | None = None,
    height_prior: HeightPrior | None = None,
) -> BundleResult:
    """Refine camera poses and points by minimising robust angular errors of observed bearings.

    Observation k is camera ``obs_camera[k]`` seeing point ``obs_point[k]`` along unit bearing
    ``obs_bearings[k]``. Minimises ``½·f²·Σ_k ρ((θ_k/f)²)``, θ_k the angular error of observation
    k, ρ the ``loss`` (scipy's names) and f = ``loss_scale_rad``. ``max_nfev`` bounds the residual
    evaluations in all (the last round may overrun it by one); it stops when a reweighting round
    lowers the cost by less than ``ftol`` (relative). ``gravity_prior`` adds the tilt terms of the module docstring
    (their weight σ_obs / σ_g takes σ_obs from the initial errors' median). With ``pose_tolerance_rad`` > 0 it also
    stops once a reweighting round (at the final loss scale) moved no camera's bearings by more than that: no
    rotation by more, no centre by more than that angle seen from its median point depth (for callers that keep
    only the poses).
    See the module docstring for the residuals and the gauge.
    """
    R0, t0, X0, cam, pt, z, fixed = _validate(
        R_cam_from_world, t_cam_from_world, points, obs_camera, obs_point, obs_bearings, fixed_cameras, loss,
        loss_scale_rad, max_nfev,
    )
    C0 = camera_center(R0, t0)
    layout = _build_layout(C0, len(X0), fixed, scale_camera, cam, _tilt_free_cameras(gravity_prior, fixed, R0))
    problem = _Problem(R_init=R0, t_init=t0, C_init=C0, obs_camera=cam, obs_point=pt, bearings=z,
                       basis=tangent_basis(z), layout=layout,
                       **_prior_terms(gravity_prior, layout, R0, C0, X0, cam, pt, z),
                       **_heading_terms(heading_prior, R0, C0, X0, cam, pt, z),
                       **_height_terms(height_prior, C0, R0, X0, cam, pt, z))
    if (few := np.bincount(pt, minlength=len(X0)) < 2).any():
        log.warning("bundle_adjust: %d points have fewer than 2 observations", few.sum())
    objective = _WeightedResiduals(problem)
    x0 = _pack(layout, C0, X0)
    initial_cost = _robust_cost(objective.errors(x0), loss, loss_scale_rad) + objective.prior_cost(x0)
    x, converged = _irls(objective, x0, loss=loss, f_target=loss_scale_rad, max_nfev=max_nfev, ftol=ftol,
                         pose_tolerance_rad=pose_tolerance_rad)
    return _result(x, objective.evaluations, converged, problem, initial_cost, loss, loss_scale_rad)


# Gravity priors: a standard error below this is not believed: a tenth of a pixel at the width lines are found
# (0.1 × 360° / 2048, `filter.GRAVITY_WIDTH`), what a sub-pixel edge fit reaches; segments of one edge are not
# independent. The real captures state 0.043-0.068° per image (360_Flat, 360_school): it binds only on clean renders.
MIN_GRAVITY_SIGMA_RAD = np.radians(0.1 * 360.0 / 2048)
# A measured gravity farther than this many standard errors (a 6-sigma test: the real ones lie 1.85 stated
# errors away, root mean square, 360_Flat) and than MIN_GRAVITY_OUTLIER_RAD (four times the largest real error, 0.24° on 360_Flat)
# from its model's up direction is an outlier (a wrong vanishing point) and gets no prior.
GRAVITY_OUTLIER_SIGMAS = 6.0
MIN_GRAVITY_OUTLIER_RAD = np.radians(1.0)


def gravity_prior_for_models(R_cam_from_world: np.ndarray, gravity_cam: np.ndarray, sigma_rad: np.ndarray,
                             model_id: np.ndarray) -> GravityPrior | None:
    """The gravity prior of the cameras with a measured gravity (finite gravity and standard error): each model's
    up direction is the precision-weighted mean of its cameras' gravities carried to the world (the poses fix the
    frame), computed again without the outliers. None when no camera qualifies."""
    R = np.asarray(R_cam_from_world, dtype=np.float64)
    g = np.asarray(gravity_cam, dtype=np.float64)
    sigma = np.maximum(np.asarray(sigma_rad, dtype=np.float64), MIN_GRAVITY_SIGMA_RAD)
    measured = (np.isfinite(g).all(axis=1) & (np.abs(np.nan_to_num(g)).sum(axis=1) > 0) & np.isfinite(sigma)
                & (np.asarray(model_id) >= 0))  # the filter stores unknown gravity as zero with an infinite error
    down_world = np.where(measured[:, None], np.einsum("nji,nj->ni", R, np.where(measured[:, None], g, 0.0)), 0.0)
    up_world = np.zeros_like(down_world)
    tolerance = np.maximum(GRAVITY_OUTLIER_SIGMAS * sigma, MIN_GRAVITY_OUTLIER_RAD)
    for model in np.unique(model_id[measured]):
        members = np.flatnonzero(measured & (model_id == model))
        # The camera whose gravity most others agree with starts the mean (a wrong vanishing point cannot).
        angles = np.arccos(np.clip(down_world[members] @ down_world[members].T, -1.0, 1.0))
        agree = angles <= tolerance[members][None, :]
        inliers = members[agree[np.argmax(agree.sum(1))]]
        for _ in range(2):  # the weighted mean, then again over the cameras that agree with it
            mean = normalize((down_world[inliers] / sigma[inliers, None] ** 2).sum(0)[None])[0]
            angle = np.arccos(np.clip(down_world[members] @ mean, -1.0, 1.0))
            inliers = members[angle <= tolerance[members]]
        up_world[inliers] = mean
        measured[np.setdiff1d(members, inliers)] = False
    camera = np.flatnonzero(measured)
    if not len(camera):
        return None
    return GravityPrior(camera=camera, gravity_cam=normalize(g[camera]), up_world=up_world[camera],
                        sigma_rad=sigma[camera], group=np.asarray(model_id)[camera])


def gravity_error_factor(R_cam_from_world: np.ndarray, prior: GravityPrior) -> float:
    """How many times its stated standard error each measured gravity lies from the model's up direction, per
    tangent component: √(Σ (θ_i / σ_i)² / (2M − 2G)) over the prior's M cameras in G groups (each group's up, the
    precision-weighted mean of its gravities, takes 2 degrees of freedom). About 1 when the standard errors are right,
    1.3-1.85 on 360_school and 360_Flat, whose vertical
    lines are not independent segments. 1 when there is no redundancy."""
    R = np.asarray(R_cam_from_world, dtype=np.float64)[prior.camera]
    group = np.asarray(prior.group)
    groups, index = np.unique(group, return_inverse=True)
    dof = 2 * (len(group) - len(groups))
    if dof <= 0:
        return 1.0
    sigma = np.asarray(prior.sigma_rad, dtype=np.float64)
    down_world = np.einsum("mji,mj->mi", R, normalize(np.asarray(prior.gravity_cam, np.float64)))
    sums = np.zeros((len(groups), 3))
    np.add.at(sums, index, down_world / sigma[:, None] ** 2)
    cos = np.einsum("mi,mi->m", down_world, normalize(sums)[index])
    return float(np.sqrt(np.sum((np.arccos(np.clip(cos, -1.0, 1.0)) / sigma) ** 2) / dof))


def with_gravity_error(prior: GravityPrior, factor: float) -> GravityPrior:
    """The prior with its standard errors scaled by `factor` (`gravity_error_factor`) where that is above 1: the
    vertical-line σ_g is a lower bound (`upright.vertical_direction_std`), so it is widened, never narrowed."""
    return dataclasses.replace(prior, sigma_rad=np.asarray(prior.sigma_rad, np.float64) * max(float(factor), 1.0))


def _tilt_free_cameras(prior: GravityPrior | None, fixed: np.ndarray, R: np.ndarray) -> dict[int, np.ndarray]:
    """Fixed cameras whose tilt the gravity prior decides, with the world up they see: each fixed camera with a
    measured gravity that is its group's only fixed camera. Its group's up direction stays where the prior put it
    and the camera keeps its centre and heading but not its tilt: the same optimum as a free up direction with the
    camera held (a global rotation apart), reached by Levenberg-Marquardt steps instead of alternating."""
    if prior is None:
        return {}
    camera, group = np.asarray(prior.camera), np.asarray(prior.group)
    row_of = {int(c): k for k, c in enumerate(camera)}
    rows = [row_of[int(f)] for f in fixed if int(f) in row_of]
    fixed_groups, counts = np.unique(group[rows], return_counts=True) if rows else (np.zeros(0), np.zeros(0))
    single = set(fixed_groups[counts == 1].tolist())
    return {int(camera[k]): R[camera[k]] @ np.asarray(prior.up_world[k], np.float64)
            for k in rows if group[k] in single}


# Residuals beyond this many times the median error are outliers, not noise, in the observation noise estimate.
NOISE_CLIP_MEDIANS = 5.0


def _observation_sigma(errors: np.ndarray, pt: np.ndarray) -> float:
    """The bearings' noise (radians, per tangent component) from the angular errors of fitted points: their mean
    square (within NOISE_CLIP_MEDIANS medians) over the residual degrees of freedom. Each track's point absorbed 3 of
    its 2 per observation components (a two-view track keeps 1 of 4, and its residual lies along one direction), so
    the errors' median alone gave 0.39 of the noise on two-view tracks (0.67 on three-view ones) and weighed the
    gravity prior 2-7 times too little against the bearings."""
    kept = errors <= NOISE_CLIP_MEDIANS * max(float(np.median(errors)), 1e-12)
    components = 2 * len(errors)
    residual_dof = max(components - 3 * np.count_nonzero(np.bincount(pt)), 1)
    return float(np.sqrt(np.sum(errors[kept] ** 2) / residual_dof * len(errors) / max(kept.sum(), 1)))


def _checked_prior(name: str, prior, R, C, X, cam, pt, bearings) -> tuple[np.ndarray, np.ndarray, float]:
    """A prior's cameras and standard errors, checked (errors name the argument), and the bearings' noise σ_obs it is
    weighed against (`_observation_sigma` of the initial errors)."""
    camera = np.asarray(prior.camera, dtype=np.int64)
    if camera.size and (camera.min() < 0 or camera.max() >= len(R)):
        raise ValueError(f"{name}.camera values must be in [0, {len(R)})")
    sigma = np.asarray(prior.sigma_rad, dtype=np.float64)
    if not (np.isfinite(sigma) & (sigma > 0)).all():
        raise ValueError(f"{name}.sigma_rad must be finite and positive")
    y = np.einsum("kij,kj->ki", R[cam], X[pt] - C[cam])
    errors = np.arccos(np.clip(np.einsum("ki,ki->k", normalize(y), bearings), -1.0, 1.0))
    return camera, sigma, _observation_sigma(errors, pt)


def _prior_terms(prior: GravityPrior | None, layout: _Layout, R, C, X, cam, pt, bearings) -> dict:
    """The _Problem fields of the gravity prior: its moving cameras, their world up, bases and weights."""
    if prior is None:
        return {}
    camera, sigma, sigma_obs = _checked_prior("gravity_prior", prior, R, C, X, cam, pt, bearings)
    gravity = normalize(np.asarray(prior.gravity_cam, np.float64))
    return {"prior_camera": camera, "prior_up": normalize(np.asarray(prior.up_world, np.float64)),
            "prior_basis": tangent_basis(gravity), "prior_sqrt_w": sigma_obs / sigma,
            "prior_group": np.asarray(prior.group, np.int64), "prior_gravity": gravity}


def _heading_terms(prior: manhattan.HeadingPrior | None, R, C, X, cam, pt, bearings) -> dict:
    """The _Problem fields of the heading prior: its cameras, measured axes and gravities, world axes, weights."""
    if prior is None:
        return {}
    camera, sigma, sigma_obs = _checked_prior("heading_prior", prior, R, C, X, cam, pt, bearings)
    return {"heading_camera": camera, "heading_axis": normalize(np.asarray(prior.axis_cam, np.float64)),
            "heading_gravity": normalize(np.asarray(prior.gravity_cam, np.float64)),
            "heading_down": normalize(np.asarray(prior.down_world, np.float64)),
            "heading_world": normalize(np.asarray(prior.axis_world, np.float64)),
            "heading_group": np.asarray(prior.group, np.int64),
            "heading_sqrt_w": sigma_obs / sigma}


def _height_terms(prior: HeightPrior | None, C, R, X, cam, pt, bearings) -> dict:
    """The _Problem fields of the height prior: its floor rows, each group's starting height (the median of its
    cameras' heights) and each row's weight σ_obs / (σ_h h √n), n the rows of its camera."""
    if prior is None or not len(prior.camera):
        return {}
    camera, point = np.asarray(prior.camera, np.int64), np.asarray(prior.point, np.int64)
    if camera.min() < 0 or camera.max() >= len(C) or point.min() < 0 or point.max() >= len(X):
        raise ValueError(f"height_prior.camera values must be in [0, {len(C)}), point values in [0, {len(X)})")
    if not prior.sigma_rel > 0:
        raise ValueError(f"height_prior.sigma_rel={prior.sigma_rel} must be positive")
    y = np.einsum("kij,kj->ki", R[cam], X[pt] - C[cam])
    sigma_obs = _observation_sigma(np.arccos(np.clip(np.einsum("ki,ki->k", normalize(y), bearings), -1.0, 1.0)), pt)
    down = normalize(np.asarray(prior.down_world, np.float64))
    group = np.asarray(prior.group, np.int64)
    terms = {"height_camera": camera, "height_point": point, "height_down": down, "height_group": group,
             "height_level": np.zeros(len(camera)), "height_sqrt_w": np.zeros(len(camera))}
    depth = np.einsum("fi,fi->f", X[point] - C[camera], down)
    for g in np.unique(group):
        rows = group == g
        cams, index, counts = np.unique(camera[rows], return_inverse=True, return_counts=True)
        level = float(np.median(np.bincount(index, depth[rows]) / counts))
        terms["height_level"][rows] = level
        terms["height_sqrt_w"][rows] = sigma_obs / (prior.sigma_rel * abs(level) * np.sqrt(counts[index]))
    return terms


def _irls(
    objective: _WeightedResiduals, x: np.ndarray, *, loss: str, f_target: float, max_nfev: int, ftol: float,
    pose_tolerance_rad: float = 0.0,
) -> tuple[np.ndarray, bool]:
    """Iteratively reweighted least squares from x; returns (x, converged).

    Each round fixes weights w_k = ρ'((θ_k/f)²) and takes a few Levenberg-Marquardt steps on
    ½Σ w_k |r_k|² (``_levenberg_marquardt``). As ρ is concave in s, ρ(s) ≤ ρ(s₀) + ρ'(s₀)(s − s₀),
    so lowering the weighted cost lowers the robust cost (majorise-minimise). Unlike scipy's own
    robust losses, whose second-order correction leaves residuals far in the linear part with
    almost no curvature (tens of tiny steps), each round is a well-scaled Gauss-Newton problem.
    The scale f follows ``_scale_schedule`` down to ``f_target``, then stays there. It stops when a round at
    ``f_target`` lowers the cost by less than ``ftol`` (relative) or, with ``pose_tolerance_rad``, moves the cameras
    by less than that (`_pose_change_rad`).
    """
    system = _SchurSystem(objective.problem)
    depth = _median_depths(x, objective.problem) if pose_tolerance_rad > 0 else None
    theta = objective.errors(x)
    scales = _scale_schedule(theta, loss, f_target)
    cost, rounds = _robust_cost(theta, loss, f_target) + objective.prior_cost(x), 0
    while (budget := max_nfev - objective.evaluations) > 0:
        f_scale = scales[min(rounds, len(scales) - 1)]
        objective.sqrt_w = np.sqrt(_LOSSES[loss][1]((theta / f_scale) ** 2))
        _update_world_up(x, objective.problem)
        _update_world_axis(x, objective.problem)
        _update_height_level(x, objective.problem)
        x_before = x
        x, rounds = _levenberg_marquardt(objective, system, x, min(_ROUND_NFEV, budget), ftol), rounds + 1
        theta = objective.errors(x)
        new_cost, old_cost = _robust_cost(theta, loss, f_target) + objective.prior_cost(x), cost
        cost = new_cost
        log.debug("bundle_adjust round %d: f %.3g rad, cost %.6g, %d evaluations",
                  rounds, f_scale, cost, objective.evaluations)
        if rounds >= len(scales) and old_cost - new_cost <= ftol * old_cost:
            return x, True
        if (rounds >= len(scales) and depth is not None
                and _pose_change_rad(x_before, x, objective.problem, depth) <= pose_tolerance_rad):
            return x, True
    return x, False


def _median_depths(x: np.ndarray, problem: _Problem) -> np.ndarray:
    """(N,) median distance from each camera to the points it observes (inf for a camera without observations)."""
    _, centers, points, _ = _unpack(x, problem)
    dist = np.linalg.norm(points[problem.obs_point] - centers[problem.obs_camera], axis=1)
    order = np.lexsort((dist, problem.obs_camera))
    counts = np.bincount(problem.obs_camera, minlength=len(centers))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    depth = np.full(len(centers), np.inf)
    seen = counts > 0  # (cameras without observations, the last ones included, index no observation)
    depth[seen] = dist[order][starts[seen] + counts[seen] // 2]
    return depth


def _pose_change_rad(x_old: np.ndarray, x_new: np.ndarray, problem: _Problem, depth: np.ndarray) -> float:
    """The largest change of a camera's bearings between x_old and x_new: its rotation's angle, or its centre's
    displacement seen from its median point depth, whichever is larger."""
    omega_old, c_old, _, _ = _unpack(x_old, problem)
    omega_new, c_new, _, _ = _unpack(x_new, problem)
    relative = rotation_exp(omega_new)[0] @ rotation_exp(omega_old)[0].transpose(0, 2, 1)
    angle = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
    return float(max(angle.max(), (np.linalg.norm(c_new - c_old, axis=1) / depth).max()))


def _levenberg_marquardt(objective: _WeightedResiduals, system: _SchurSystem, x: np.ndarray, max_evaluations: int,
                         ftol: float) -> np.ndarray:
    """Levenberg-Marquardt on the weighted residuals from x, at most `max_evaluations` new residual evaluations;
    stops once an accepted step lowers the cost by less than `ftol` (relative). The damping λ carries over
    between calls (`objective.damping`); after a rejected step it grows by ν (doubling), after an accepted one it
    shrinks by the gain ratio ρ as max(1/3, 1 − (2ρ − 1)³) (Nielsen)."""
    r = objective.fun(x).reshape(-1, 2)  # cached: not a new evaluation
    cost, J, nu = 0.5 * float(r.ravel() @ r.ravel()), None, 2.0
    for _ in range(max_evaluations):
        if J is None:
            J, J_prior = objective.jac_blocks(x), objective.prior_blocks(x)
        solved = system.solve(r, J, objective.damping, J_prior, _prior_cameras(objective.problem))
        if solved is None or not solved[1] > 0:
            objective.damping, nu = min(objective.damping * nu, _LM_DAMPING_BOUNDS[1]), 2 * nu
            continue
        step, predicted = solved
        r_new = objective.fun(x + step).reshape(-1, 2)
        new_cost = 0.5 * float(r_new.ravel() @ r_new.ravel())
        gain = (cost - new_cost) / predicted
        if not gain > 0:  # NaN counts as a failure
            objective.damping, nu = min(objective.damping * nu, _LM_DAMPING_BOUNDS[1]), 2 * nu
            continue
        x, r, J, nu = x + step, r_new, None, 2.0
        objective.damping = max(objective.damping * max(1 / 3, 1 - (2 * gain - 1) ** 3), _LM_DAMPING_BOUNDS[0])
        decrease, cost = cost - new_cost, new_cost
        if decrease <= ftol * (cost + decrease):
            break
    return x


def _scale_schedule(theta: np.ndarray, loss: str, f_target: float) -> list[float]:
    """Robust-loss scales for the reweighting rounds, ending at ``f_target``.

    Starting at about the size of the initial errors and dividing by 4 per round keeps the inliers
    in the quadratic part of the loss while the estimate is still far off.
    """
    if loss == "linear" or len(theta) == 0:
        return [f_target]
    start = 3.0 * float(np.median(theta))
    scales = [f_target]
    while scales[-1] * _SCALE_STEP < start:
        scales.append(scales[-1] * _SCALE_STEP)
    return scales[::-1]


def _result(x, nfev, converged, problem: _Problem, initial_cost, loss: str, f_scale: float) -> BundleResult:
    """Poses, points, costs and errors at the solution x."""
    omega, centers, points, _ = _unpack(x, problem)
    R = rotation_exp(omega)[0] @ problem.R_init
    fixed = problem.layout.cam_dof == 0
    t = -np.einsum("nij,nj->ni", R, centers)
    R[fixed], t[fixed] = problem.R_init[fixed], problem.t_init[fixed]  # exactly the input, no rounding
    obs_error = np.linalg.norm(_residuals(x, problem, False)[0], axis=1)
    final_cost = (_robust_cost(obs_error, loss, f_scale) + 0.5 * float((_prior_residuals(x, problem)[0] ** 2).sum())
                  + 0.5 * float((_height_residuals(x, problem, False)[0] ** 2).sum()))
    message = "cost decrease below ftol" if converged else "max_nfev reached"
    log.info(
        "bundle_adjust: cost %.4g -> %.4g in %d evaluations, median error %.3g rad (%s)",
        initial_cost, final_cost, nfev, np.median(obs_error) if len(obs_error) else 0.0, message,
    )
    return BundleResult(
        R_cam_from_world=R, t_cam_from_world=t, points=points, initial_cost=initial_cost, final_cost=final_cost,
        obs_error_rad=obs_error, scale_camera=problem.layout.scale_camera, num_evaluations=nfev,
        success=converged, message=message,
    )
