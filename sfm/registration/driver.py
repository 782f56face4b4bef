"""Global registration driver: absolute camera poses from pairwise relative poses.

Input per image pair p = (i, j): ``R_j_from_i`` (3x3), ``t_j_from_i`` (unit; ``x_j = R x_i + s t``,
s > 0) and a weight (inlier count); some pairs may be gross outliers.

Two models (``register(model=...)``):

``"general"`` (default)
    1. keep the largest connected component of the view graph (pairs with weight >= ``min_weight``);
    2. rotations: maximum spanning tree initialisation (edges ranked by the number of view-graph triangles
       whose rotation cycle closes — outliers rarely close one — then by weight), repaired by consensus
       moves (an image, or an internally consistent cluster, re-attached through the pair that minimises
       its truncated residuals), then robust rotation averaging on the Lie algebra (Chatterjee & Govindu,
       "Robust relative rotation averaging", TPAMI 2018): L1-IRLS followed by Cauchy-IRLS, each step one
       sparse weighted-Laplacian solve; pairs with a rotation residual above
       ``max_rotation_residual_deg`` are rejected and the rotations re-fitted on the rest;
    3. centres: translation averaging from the world-frame baseline directions
       ``d_ij ∝ c_j − c_i`` (``= −R_jᵀ t_j_from_i``): LUD (Özyeşil & Singer, CVPR 2015:
       ``min Σ‖c_j − c_i − λ_ij d_ij‖`` s.t. ``λ_ij ≥ 1`` — the constraint prevents the collapse
       of all centres to one point) solved by IRLS, λ eliminated by an active-set iteration, then a
       robust non-linear refinement of the chordal distance ``‖(c_j − c_i)/‖c_j − c_i‖ − d_ij‖``
       (Levenberg-Marquardt + IRLS Cauchy weights, sparse normal equations); pairs with a
       direction residual above ``max_direction_residual_deg`` are rejected and the problem
       re-solved.  Cameras left with fewer than ``min_pairs_per_camera`` consistent pairs (their
       position along the baseline is not observable) are peeled off and reported unregistered.
       Layouts that the directions do not pin down (collinear rows, clusters joined at one camera) are
       not an error: they are solved (λ ≥ 1 keeps the spacing sane), logged and counted in
       ``Registration.flexible_modes`` (:func:`flexible_modes`).

``"planar"`` (the report's method)
    Cameras are assumed level: ``R_cam_from_world = R_y(θ)``, a rotation about the world vertical
    axis.  The world y axis points *down*, as in the camera frame (the report uses z up; adapted).
    θ is initialised by robust averaging of the relative rotations' yaw (same tree / consensus init,
    Cauchy-IRLS) and refined by damped Newton (analytic gradient / Hessian) on the report's cost
    ``Σ_ij 1 − |e_ij,w · e_ji,w|`` with ``e_ij,w = R_iᵀ e_ij``, ``e_ji,w = R_jᵀ e_ji``
    (:func:`planar_epipole_cost`), alternated with the rejection of pairs whose relative rotation
    (tilt included: a level model predicts none) or epipoles disagree with the estimate; positions by
    the same translation averaging in full 3-D (heights are estimated, not assumed equal).

Epipoles: ``e_ij`` = direction of camera j's centre seen from camera i (frame i) = ``−R_j_from_iᵀ t``;
``e_ji`` = camera i's centre seen from j (frame j) = ``t_j_from_i``.  If given explicitly (they are
only known up to sign from a fundamental matrix) their signs are aligned with ``t_j_from_i``.

Gauge of the result: the first registered image (lowest index) has ``R = I`` and centre 0 (the world
frame is its camera frame); the scale makes the mean distance of the registered centres to their
centroid equal to 1.

The algorithm is deterministic (no random choice). Every linear solve is sparse (SuperLU): no dense LAPACK calls whose threading could stall busy machines.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from fullview.sfm.options import RegistrationOptions
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.registration.planar import planar_rotations
from fullview.sfm.registration.poses import relative_from_absolute
from fullview.sfm.registration.rotation_averaging import general_rotations
from fullview.sfm.registration.translation_averaging import flexible_modes, translation_averaging
from fullview.sfm.registration.view_graph import prune_graph
from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg

log = logging.getLogger(__name__)

MODELS = ("general", "planar")


@dataclass(kw_only=True)
class Registration:
    model: str  # "general" or "planar"
    registered: np.ndarray  # (N,) bool: image has an absolute pose
    R_cam_from_world: np.ndarray  # (N, 3, 3) rotations, NaN for unregistered images
    t_cam_from_world: np.ndarray  # (N, 3) translations, NaN for unregistered images
    centers: np.ndarray  # (N, 3) camera centres in the world frame, NaN for unregistered images
    reference_image: int  # image at R = I, centre 0 (the world frame); -1 when nothing is registered
    pair_inlier_mask: np.ndarray  # (P,) bool: both images registered and both residuals within thresholds
    pair_used_mask: np.ndarray  # (P,) bool: pair constrained the final solution
    rotation_residual_deg: np.ndarray  # (P,) angle between measured and estimated R_j_from_i; NaN if not registered
    direction_residual_deg: np.ndarray  # (P,) angle between measured and estimated t_j_from_i; NaN if not registered
    epipole_cost: float  # the report's Σ 1 − |e_ij,w · e_ji,w| over the used pairs at the solution
    flexible_modes: int  # centre motions (beyond a similarity) keeping all used directions; 0 = rigid, -1 = unknown

    @property
    def num_registered(self) -> int:
        return int(self.registered.sum())


def _check_inputs(num_images, pairs, R_j_from_i, t_j_from_i, weights, model, e_ij, e_ji):
    if not (isinstance(num_images, (int, np.integer)) and num_images >= 0):
        raise ValueError(f"num_images must be a non-negative int, got {num_images!r}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    P = len(pairs)
    R = np.asarray(R_j_from_i, dtype=np.float64)
    t = np.asarray(t_j_from_i, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if R.shape != (P, 3, 3):
        raise ValueError(f"R_j_from_i has shape {R.shape}, expected ({P}, 3, 3) for {P} pairs")
    if t.shape != (P, 3):
        raise ValueError(f"t_j_from_i has shape {t.shape}, expected ({P}, 3)")
    if w.shape != (P,):
        raise ValueError(f"weights has shape {w.shape}, expected ({P},)")
    if P and (pairs.min() < 0 or pairs.max() >= num_images):
        bad = pairs[(pairs < 0).any(1) | (pairs >= num_images).any(1)][0]
        raise ValueError(f"pair {tuple(bad.tolist())} out of range for num_images={num_images}")
    eps = []
    for name, e in (("e_ij", e_ij), ("e_ji", e_ji)):
        if e is not None:
            e = np.asarray(e, dtype=np.float64)
            if e.shape != (P, 3):
                raise ValueError(f"{name} has shape {e.shape}, expected ({P}, 3)")
        eps.append(e)
    return pairs, R, t, w, eps[0], eps[1]


def _epipoles(R, t, e_ij, e_ji):
    """Unit epipoles (M, 3) each, derived from (R, t) or, when given, sign-aligned with them.

    Given epipoles that are non-finite or zero fall back to the derived ones.
    """
    d_ij = normalize(-np.einsum("pba,pb->pa", R, t))  # c_j seen from i
    d_ji = normalize(t)  # c_i seen from j
    out = []
    for given, derived in ((e_ij, d_ij), (e_ji, d_ji)):
        if given is None:
            out.append(derived)
            continue
        g = normalize(np.nan_to_num(given, nan=0.0, posinf=0.0, neginf=0.0))
        ok = np.linalg.norm(g, axis=1) > 0.5
        flip = np.einsum("pa,pa->p", g, derived) < 0
        out.append(np.where(ok[:, None], np.where(flip[:, None], -g, g), derived))
    return out


def register(
    *,
    num_images: int,
    pairs,
    R_j_from_i,
    t_j_from_i,
    weights,
    model: str = RegistrationOptions.model,
    e_ij=None,
    e_ji=None,
    min_weight: float = 0.0,
    max_rotation_residual_deg: float = RegistrationOptions.max_rotation_residual_deg,
    max_direction_residual_deg: float = RegistrationOptions.max_direction_residual_deg,
    robust_scale_deg: float = 2.0,
    min_pairs_per_camera: int = 2,
) -> Registration:
    """Absolute poses of ``num_images`` cameras from relative poses of ``pairs`` (P, 2); see module doc.

    ``R_j_from_i`` (P, 3, 3), ``t_j_from_i`` (P, 3) (any norm > 0), ``weights`` (P,) (inlier counts);
    ``e_ij`` / ``e_ji`` (P, 3) optional epipoles (default: derived from R, t; signs are aligned with t).
    A pair is used only if its weight is > 0 and >= ``min_weight`` and its R / t are finite (t ≠ 0).
    Pairs are rejected when their rotation residual exceeds ``max_rotation_residual_deg`` or their
    baseline direction residual exceeds ``max_direction_residual_deg``; ``robust_scale_deg`` is the
    Cauchy scale of both averaging steps; images with fewer than ``min_pairs_per_camera`` consistent
    pairs are not placed (1 accepts positions fixed only along a ray).
    Never raises for disconnected or unconstrained images: they are reported unregistered.
    """
    pairs, R_rel, t_rel, w, e_ij, e_ji = _check_inputs(
        num_images, pairs, R_j_from_i, t_j_from_i, weights, model, e_ij, e_ji)
    P, N = len(pairs), num_images
    finite = (
        np.isfinite(R_rel).all((1, 2)) & np.isfinite(t_rel).all(1) & (np.linalg.norm(t_rel, axis=1) > 0)
        & (pairs[:, 0] != pairs[:, 1])
    )
    valid = finite & np.isfinite(w) & (w > 0) & (w >= min_weight)
    R_rel = np.where(finite[:, None, None], R_rel, np.eye(3))
    R_rel = Rotation.from_matrix(R_rel).as_matrix()  # project onto SO(3)
    t_rel = np.where(finite[:, None], t_rel, [0.0, 0.0, 1.0])
    e_i, e_j = _epipoles(R_rel, t_rel, e_ij, e_ji)

    nodes, use = prune_graph(N, pairs, valid, w, 1)
    log.info("registration (%s): %d images, %d/%d valid pairs, largest component %d images",
             model, N, valid.sum(), P, len(nodes))
    R_abs = np.full((N, 3, 3), np.nan)
    centres = np.full((N, 3), np.nan)
    if len(nodes) >= 2:
        root = int(nodes[0])
        if model == "general":
            R_abs, use = general_rotations(N, pairs, R_rel, w, use, root, max_rotation_residual_deg, robust_scale_deg)
        else:
            R_abs, use = planar_rotations(N, pairs, R_rel, w, use, root, e_i, e_j,
                                           max_rotation_residual_deg, max_direction_residual_deg, robust_scale_deg)
        nodes, use = prune_graph(N, pairs, use, w, 1)
        if len(nodes) >= 2:
            root = int(nodes[0])
            # world baseline direction c_j − c_i, seen from both ends: R_iᵀ e_ij and −R_jᵀ e_ji
            d = normalize(np.einsum("pba,pb->pa", R_abs[pairs[:, 0]], e_i)
                          - np.einsum("pba,pb->pa", R_abs[pairs[:, 1]], e_j))
            d = np.where(use[:, None], np.nan_to_num(d), 0.0)
            centres, use = translation_averaging(
                N, pairs, d, root, weights=w, max_direction_residual_deg=max_direction_residual_deg,
                robust_scale_deg=robust_scale_deg, min_pairs_per_camera=min_pairs_per_camera,
            )
        else:
            use[:] = False
    registered = np.isfinite(centres).all(1)
    if registered.sum() < 2:
        registered[:] = False
        use[:] = False
    return _finish(model, registered, R_abs, centres, pairs, R_rel, t_rel, e_i, e_j, finite, use,
                   max_rotation_residual_deg, max_direction_residual_deg)


def _finish(model, registered, R_abs, centres, pairs, R_rel, t_rel, e_i, e_j, finite, use, rot_thr, dir_thr):
    N, P = len(registered), len(pairs)
    R_out = np.full((N, 3, 3), np.nan)
    c_out = np.full((N, 3), np.nan)
    t_out = np.full((N, 3), np.nan)
    ref = -1
    if registered.any():
        ref = int(np.flatnonzero(registered)[0])
        R_ref = R_abs[ref]
        R_out[registered] = R_abs[registered] @ R_ref.T
        c = (centres[registered] - centres[ref]) @ R_ref.T
        spread = np.linalg.norm(c - c.mean(0), axis=1).mean()
        c_out[registered] = c / spread if spread > 0 else c
        t_out[registered] = -np.einsum("nab,nb->na", R_out[registered], c_out[registered])
    both = registered[pairs].all(1) & finite
    rot_res = np.full(P, np.nan)
    dir_res = np.full(P, np.nan)
    cost = 0.0
    if both.any():
        i, j = pairs[both, 0], pairs[both, 1]
        R_est, t_est = relative_from_absolute(R_out, t_out, i, j)
        rot_res[both] = rotation_angle_deg(R_rel[both], R_est)
        dir_res[both] = angle_between_deg(t_rel[both], t_est)
        u = use & registered[pairs].all(1)
        a = np.einsum("pba,pb->pa", R_out[pairs[u, 0]], e_i[u])
        b = np.einsum("pba,pb->pa", R_out[pairs[u, 1]], e_j[u])
        cost = float(np.sum(1.0 - np.abs(np.einsum("pa,pa->p", a, b))))
    inlier = both & (rot_res <= rot_thr) & (dir_res <= dir_thr)
    used = use & registered[pairs].all(1)
    flex = flexible_modes(c_out, pairs[used]) if used.any() else 0
    if flex > 0:
        log.warning("camera centres are not fully determined by the used baseline directions: %d flexible mode(s) "
                    "(view graph not parallel rigid, e.g. nearly collinear cameras or weakly linked clusters)", flex)
    log.info("registered %d/%d images; %d/%d pairs consistent (rotation ≤ %.1f°, direction ≤ %.1f°)",
             registered.sum(), N, inlier.sum(), P, rot_thr, dir_thr)
    return Registration(
        model=model,
        registered=registered,
        R_cam_from_world=R_out,
        t_cam_from_world=t_out,
        centers=c_out,
        reference_image=ref,
        pair_inlier_mask=inlier,
        pair_used_mask=used,
        rotation_residual_deg=rot_res,
        direction_residual_deg=dir_res,
        epipole_cost=cost,
        flexible_modes=flex,
    )
