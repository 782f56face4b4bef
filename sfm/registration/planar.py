"""The ``"planar"`` model (the report's method): level cameras, ``R_cam_from_world = R_y(θ)``.

θ is initialised by robust averaging of the relative rotations' yaw and refined by damped Newton (analytic gradient
and Hessian) on the report's epipole cost ``Σ_ij 1 − |e_ij,w · e_ji,w|`` with ``e_ij,w = R_iᵀ e_ij``,
``e_ji,w = R_jᵀ e_ji``, alternated with the rejection of pairs whose relative rotation (tilt included: a level
model predicts none) or epipoles disagree with the estimate.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from fullview.sfm.registration.poses import rotation_yaw, yaw_rotation
from fullview.sfm.registration.rotation_averaging import (consensus_sweeps, rotation_averaging_irls,
                                                          spanning_tree_rotations)
from fullview.sfm.registration.view_graph import prune_graph, triangle_support
from fullview.sfm.rotations import rotation_angle_deg

log = logging.getLogger(__name__)


def planar_epipole_cost(theta, pairs, e_ij, e_ji, weights=None) -> float:
    """The report's cost ``Σ_p w_p (1 − |e_ij,w · e_ji,w|)``, ``e_ij,w = R_y(θ_i)ᵀ e_ij``, ``e_ji,w = R_y(θ_j)ᵀ e_ji``

    ``theta`` (N,) yaw of each ``R_cam_from_world = R_y(θ)``; ``e_ij`` / ``e_ji`` (M, 3) unit epipoles
    (sign irrelevant); zero at the truth for level cameras.
    """
    return planar_epipole_cost_derivatives(theta, pairs, e_ij, e_ji, weights)[0]


def planar_epipole_cost_derivatives(theta, pairs, e_ij, e_ji, weights=None):
    """``(cost, gradient (N,), Hessian (N, N) sparse csr)`` of :func:`planar_epipole_cost` w.r.t. θ.

    With the horizontal (x, z) parts in polar form (r, φ):
    ``e_ij,w · e_ji,w = y_i y_j + r_i r_j cos(θ_j − θ_i + φ_j − φ_i)``.
    """
    theta = np.asarray(theta, dtype=np.float64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    a = np.asarray(e_ij, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(e_ji, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(pairs)) if weights is None else np.asarray(weights, dtype=np.float64)
    i, j = pairs[:, 0], pairs[:, 1]
    amp = np.hypot(a[:, 0], a[:, 2]) * np.hypot(b[:, 0], b[:, 2])
    k = theta[j] - theta[i] + np.arctan2(b[:, 2], b[:, 0]) - np.arctan2(a[:, 2], a[:, 0])
    g = a[:, 1] * b[:, 1] + amp * np.cos(k)
    sg = np.sign(g)
    cost = float(np.sum(w * (1.0 - np.abs(g))))
    d1 = w * sg * amp * np.sin(k)  # ∂/∂θ_j ; ∂/∂θ_i = −d1
    d2 = w * sg * amp * np.cos(k)
    n = len(theta)
    grad = np.bincount(j, d1, n) - np.bincount(i, d1, n)
    H = sp.coo_matrix(
        (np.concatenate([d2, d2, -d2, -d2]), (np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i]))), shape=(n, n)
    ).tocsr()
    return cost, grad, H


def planar_newton(theta0, pairs, e_ij, e_ji, root, *, weights=None, max_iterations: int = 100) -> np.ndarray:
    """Damped (Levenberg) Newton minimisation of :func:`planar_epipole_cost`, ``θ_root`` fixed."""
    theta = np.asarray(theta0, dtype=np.float64).copy()
    free = np.unique(np.asarray(pairs).ravel())
    free = free[free != root]
    cost, grad, H = planar_epipole_cost_derivatives(theta, pairs, e_ij, e_ji, weights)
    mu = 1e-9
    for it in range(max_iterations):
        g = grad[free]
        Hf = H[free][:, free].tocsc()
        scale = max(np.abs(Hf.diagonal()).max(), 1e-12)
        improved = False
        while mu < 1e12:
            step = -np.asarray(spsolve(Hf + mu * scale * sp.identity(len(free), format="csc"), g))
            trial = theta.copy()
            trial[free] += step
            c_new, g_new, H_new = planar_epipole_cost_derivatives(trial, pairs, e_ij, e_ji, weights)
            if np.all(np.isfinite(step)) and c_new <= cost:
                improved = True
                break
            mu *= 10.0
        if not improved:
            break
        theta, cost, grad, H = trial, c_new, g_new, H_new
        mu = max(mu / 10.0, 1e-12)
        if np.abs(step).max() < 1e-13 or np.abs(grad[free]).max() < 1e-15:
            break
    log.debug("planar Newton: %d iterations, cost %.3e", it + 1, cost)
    return theta


def planar_rotations(N, pairs, R_rel, w, use, root, e_i, e_j, rot_thr_deg, dir_thr_deg, robust_scale_deg):
    """``(R_abs = R_y(θ) (N, 3, 3), used pairs (P,))`` of the ``"planar"`` model: yaw averaging, then Newton on the
    epipole cost alternated with the rejection of inconsistent pairs (NaN outside the final component)."""
    psi = rotation_yaw(R_rel)
    R_yaw = yaw_rotation(psi)
    support = triangle_support(N, pairs, R_rel, w, use, threshold_deg=rot_thr_deg)  # cycles close for any poses
    R0 = spanning_tree_rotations(N, pairs, R_yaw, w, use, root, priority=support)
    sel = np.flatnonzero(use)
    R0 = consensus_sweeps(R0, pairs[sel], R_yaw[sel], threshold_deg=rot_thr_deg)
    # no L1 stage: in 1-D the L1 optimum is a median, which scattered outlier yaws can drag off the inlier mode
    R_abs = rotation_averaging_irls(R0, pairs[sel], R_yaw[sel], root, l1_iterations=0,
                                    robust_scale_deg=robust_scale_deg)
    theta = np.where(np.isfinite(R_abs[:, 0, 0]), rotation_yaw(R_abs), 0.0)
    theta -= theta[root]
    cos_thr = np.cos(np.radians(dir_thr_deg))
    inl = use.copy()
    for rnd in range(5):
        # full rotation residual (a level model predicts no relative tilt) and signed epipole agreement
        rot_res = rotation_angle_deg(R_rel, yaw_rotation(theta[pairs[:, 1]] - theta[pairs[:, 0]]))
        a = np.einsum("pba,pb->pa", yaw_rotation(theta[pairs[:, 0]]), e_i)
        b = np.einsum("pba,pb->pa", yaw_rotation(theta[pairs[:, 1]]), e_j)
        new = use & (rot_res <= rot_thr_deg) & (-np.einsum("pa,pa->p", a, b) >= cos_thr)
        nodes, new = prune_graph(N, pairs, new, w, 1)
        if rnd > 0 and np.array_equal(new, inl):
            break
        inl = new
        if len(nodes) < 2:
            break
        root = int(nodes[0])
        sel = np.flatnonzero(inl)
        theta = planar_newton(theta, pairs[sel], e_i[sel], e_j[sel], root)
        theta -= theta[root]
    log.info("planar rotations: %d/%d pairs consistent, epipole cost %.3e", inl.sum(), use.sum(),
             planar_epipole_cost(theta, pairs[inl], e_i[inl], e_j[inl]))
    R_abs = yaw_rotation(theta)
    keep = np.zeros(N, bool)
    keep[nodes] = True
    R_abs[~keep] = np.nan
    return R_abs, inl
