"""Camera centres from world-frame baseline directions ``d_ij ∝ c_j − c_i``, and their parallel rigidity.

LUD (Özyeşil & Singer, CVPR 2015: ``min Σ‖c_j − c_i − λ_ij d_ij‖`` s.t. ``λ_ij ≥ 1``, which prevents the collapse of
all centres to one point) solved by IRLS with λ eliminated by an active-set iteration, then a robust non-linear
refinement of the chordal distance (not kept where it collapses a part of the layout), rejection of inconsistent
pairs and re-solving. ``flexible_modes`` counts the centre motions the used directions leave free (collinear rows,
clusters joined at one camera).
Every linear solve is sparse (SuperLU).
"""

from __future__ import annotations

import logging

import numpy as np

from fullview.sfm.options import RegistrationOptions
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackNoConvergence, eigsh, splu, spsolve

from fullview.sfm.camera import normalize
from fullview.sfm.registration.view_graph import prune_graph

log = logging.getLogger(__name__)


def _local_indexing(pairs, root):
    nodes, local = np.unique(pairs, return_inverse=True)
    local = local.reshape(-1, 2)
    root_local = int(np.searchsorted(nodes, root))
    if nodes[root_local] != root:
        raise ValueError(f"root {root} must be one of the images in pairs")
    col = np.full(len(nodes), -1)  # column block of each node, -1 = fixed root
    free = np.arange(len(nodes)) != root_local
    col[free] = np.arange(free.sum())
    return nodes, local, col


def _lud_centres(local, col, directions, n, iterations: int) -> np.ndarray:
    """LUD by IRLS: ``min Σ ‖c_j − c_i − λ_p d_p‖`` s.t. ``λ_p ≥ 1``, root fixed at 0. Returns (n, 3).

    For fixed IRLS weights the optimal ``λ_p = max(1, ⟨c_j − c_i, d_p⟩)``; eliminating it leaves a piecewise
    quadratic in c, minimised by an active-set iteration: pairs with ``λ_p = 1`` contribute
    ``w‖c_j − c_i − d_p‖²``, the others ``w‖(I − d dᵀ)(c_j − c_i)‖²`` (one sparse solve per step).
    """
    M = len(local)
    i, j = local[:, 0], local[:, 1]
    P_perp = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    idx3 = _free_index(col, n)
    free = col >= 0

    def solve(w, active):
        B = np.where(active[:, None, None], np.eye(3), P_perp) * w[:, None, None]
        K, rhs = _block_system(local, idx3, B, (w * active)[:, None] * directions, n)
        K = K + 1e-12 * max(abs(K.diagonal()).max(), 1.0) * sp.identity(K.shape[0], format="csc")
        c = np.zeros((n, 3))
        c[free] = np.asarray(spsolve(K, rhs)).reshape(-1, 3)
        return c

    w = np.ones(M)
    active = np.ones(M, bool)
    c_prev = None
    for it in range(iterations):
        for _ in range(20):
            c = solve(w, active)
            proj = np.einsum("pa,pa->p", c[j] - c[i], directions)
            new_active = proj <= 1.0
            if np.array_equal(new_active, active):
                break
            active = new_active
        lam = np.maximum(proj, 1.0)
        r = np.linalg.norm(c[j] - c[i] - lam[:, None] * directions, axis=1)
        w = 1.0 / np.maximum(r, 1e-6 * max(np.median(lam), 1.0))
        if c_prev is not None and np.abs(c - c_prev).max() < 1e-9 * max(np.abs(c).max(), 1.0):
            break
        c_prev = c
    return c


def _block_system(local, free_idx3, blocks, vec, n):
    """``Σ_p A_pᵀ B_p A_p`` and ``Σ_p A_pᵀ v_p`` for ``A_p = (e_j − e_i) ⊗ I₃``, fixed (-1) columns dropped."""
    M = len(local)
    i, j = local[:, 0], local[:, 1]
    ii9, jj9 = np.repeat(np.arange(3), 3), np.tile(np.arange(3), 3)
    rows, cols, vals = [], [], []
    for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append(free_idx3[a][:, ii9].ravel())
        cols.append(free_idx3[b][:, jj9].ravel())
        vals.append(sign * blocks.reshape(M, 9).ravel())
    rows, cols, vals = map(np.concatenate, (rows, cols, vals))
    ok = (rows >= 0) & (cols >= 0)
    nf = int((free_idx3 >= 0).sum())
    K = sp.coo_matrix((vals[ok], (rows[ok], cols[ok])), shape=(nf, nf)).tocsc()
    rhs = np.zeros((n, 3))
    np.add.at(rhs, j, vec)
    np.add.at(rhs, i, -vec)
    return K, rhs[free_idx3[:, 0] >= 0].ravel()


def _free_index(col, n):
    idx3 = np.full((n, 3), -1)
    free = col >= 0
    idx3[free] = np.arange(3 * free.sum()).reshape(-1, 3)
    return idx3


def _refine_centres(local, col, directions, c0, robust_scale_deg: float, max_iterations: int = 100) -> np.ndarray:
    """Robust chordal refinement ``min Σ_p ρ(‖(c_j − c_i)/‖c_j − c_i‖ − d_p‖)``, Cauchy ρ, root fixed.

    Levenberg-Marquardt with IRLS weights on the per-pair residual norm and sparse normal equations; the
    (otherwise free) scale is fixed by the linear gauge ``mean_p ⟨c_j − c_i, d_p⟩ = const``.
    """
    M, n = len(local), len(c0)
    i, j = local[:, 0], local[:, 1]
    idx3 = _free_index(col, n)
    free = col >= 0
    sigma2 = np.radians(robust_scale_deg) ** 2
    c = np.asarray(c0, dtype=np.float64) - c0[~free][0]
    s0 = np.einsum("pa,pa->", c[j] - c[i], directions) / M
    if not s0 > 0:  # cannot happen after LUD (λ ≥ 1) unless the input is degenerate: keep the initialisation
        log.warning("translation refinement skipped: mean baseline projection %.3g is not positive", s0)
        return c
    gauge_row = np.zeros((n, 3))  # ∂gauge/∂c
    np.add.at(gauge_row, j, directions / (M * s0))
    np.add.at(gauge_row, i, -directions / (M * s0))
    a = gauge_row[free].ravel()

    def residuals(c):
        u = c[j] - c[i]
        nrm = np.maximum(np.linalg.norm(u, axis=1), 1e-12)
        f = u / nrm[:, None] - directions
        gauge = np.einsum("pa,pa->", u, directions) / (M * s0) - 1.0
        return u, nrm, f, gauge

    def cost(f, gauge):
        return float(np.sum(sigma2 * np.log1p(np.einsum("pa,pa->p", f, f) / sigma2)) + gauge**2)

    u, nrm, f, gauge = residuals(c)
    current = cost(f, gauge)
    mu = 1e-4
    for it in range(max_iterations):
        w = 1.0 / (1.0 + np.einsum("pa,pa->p", f, f) / sigma2)
        uh = u / nrm[:, None]
        Jb = (np.eye(3) - uh[:, :, None] * uh[:, None, :]) / nrm[:, None, None]  # ∂f/∂c_j (symmetric)
        H, g = _block_system(local, idx3, w[:, None, None] * Jb @ Jb, w[:, None] * np.einsum("pab,pb->pa", Jb, f), n)
        g = g + a * gauge  # the gauge adds the rank-one a aᵀ to H: Sherman-Morrison keeps it sparse
        diag = sp.diags(np.maximum(H.diagonal() + a * a, 1e-12))
        accepted = False
        while mu < 1e10:
            lu = splu((H + mu * diag).tocsc())
            y, z = lu.solve(-g), lu.solve(a)
            step = y - z * (a @ y) / (1.0 + a @ z)
            trial = c.copy()
            trial[free] += step.reshape(-1, 3)
            u_t, nrm_t, f_t, gauge_t = residuals(trial)
            new = cost(f_t, gauge_t)
            if np.all(np.isfinite(step)) and new <= current:
                accepted = True
                break
            mu *= 10.0
        if not accepted:
            break
        rel = np.abs(step).max() / max(np.abs(c).max(), 1e-12)
        c, u, nrm, f, gauge, done = trial, u_t, nrm_t, f_t, gauge_t, current - new <= 1e-15 * max(current, 1e-300)
        current = new
        mu = max(mu / 10.0, 1e-12)
        if rel < 1e-12 or done:
            break
    log.debug("chordal refinement: %d iterations, robust cost %.3e", it + 1, current)
    return c


COLLAPSE_RATIO = 0.01  # a used pair shorter than this fraction of the median one: the refinement collapsed a part


def _shortest_pair(c: np.ndarray, local: np.ndarray) -> float:
    """Length of the shortest pair over the median pair length."""
    lengths = np.linalg.norm(c[local[:, 1]] - c[local[:, 0]], axis=1)
    return float(lengths.min() / max(np.median(lengths), 1e-300))


def _collapses(c: np.ndarray, local: np.ndarray) -> bool:
    """Whether the chordal refinement shrank a group of cameras to a point. Its cost sees directions only, so the
    scale of a part the directions leave free (a flexible mode) is not held, and shrinking the part changes none of
    its own pairs' directions while the pairs out of it may fit better. LUD's λ ≥ 1 rules that out; the refinement
    must not undo it (bare 2048 px home seed 3 with filter seed 1: four cameras of one room at one point, pairs 1e-10
    of the median length, which no later step separates)."""
    return _shortest_pair(c, local) < COLLAPSE_RATIO


def translation_averaging(
    num_images: int,
    pairs: np.ndarray,
    directions: np.ndarray,
    root: int,
    *,
    weights: np.ndarray | None = None,
    max_direction_residual_deg: float = RegistrationOptions.max_direction_residual_deg,
    robust_scale_deg: float = 2.0,
    min_pairs_per_camera: int = 2,
    lud_iterations: int = 20,
    max_rounds: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres from world-frame baseline directions ``d_p ∝ c_j − c_i`` (unit, (M, 3)).

    LUD initialisation, robust chordal refinement, rejection of pairs whose direction residual exceeds
    the threshold, pruning to the largest component with ``min_pairs_per_camera`` and re-solving.
    Returns ``(centres (N, 3) with NaN for unplaced images, used (M,) bool)``; the centres are in an
    arbitrary positive scale, translated so that the lowest placed image is at 0.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    directions = normalize(np.asarray(directions, dtype=np.float64).reshape(-1, 3))
    weights = np.ones(len(pairs)) if weights is None else np.asarray(weights, dtype=np.float64)
    centres = np.full((num_images, 3), np.nan)
    used = np.isfinite(directions).all(1) & (np.linalg.norm(directions, axis=1) > 0)
    nodes, used = prune_graph(num_images, pairs, used, weights, min_pairs_per_camera)
    if len(nodes) < 2:
        return centres, used
    root = root if root in nodes else int(nodes[0])
    sel = np.flatnonzero(used)
    nodes_l, local, col = _local_indexing(pairs[sel], root)
    c_local = _lud_centres(local, col, directions[sel], len(nodes_l), lud_iterations)
    centres[nodes_l] = c_local
    cos_thr = np.cos(np.radians(max_direction_residual_deg))
    for rnd in range(max_rounds):
        sel = np.flatnonzero(used)
        nodes_l, local, col = _local_indexing(pairs[sel], root)
        c0 = centres[nodes_l] - centres[root]
        c_local = _refine_centres(local, col, directions[sel], c0, robust_scale_deg)
        if _collapses(c_local, local):
            log.info("translation refinement collapses a part of the layout (a pair %.2g of the median length): "
                     "keeping the centres it started from (λ ≥ 1)", _shortest_pair(c_local, local))
            c_local = c0
        centres[:] = np.nan
        centres[nodes_l] = c_local
        u = normalize(centres[pairs[:, 1]] - centres[pairs[:, 0]])
        cos = np.einsum("pa,pa->p", u, directions)
        good = used & (cos >= cos_thr)
        if good.sum() == used.sum():
            break
        log.debug("translation round %d: rejecting %d pair(s)", rnd, used.sum() - good.sum())
        nodes, good = prune_graph(num_images, pairs, good, weights, min_pairs_per_camera)
        if len(nodes) < 2:
            centres[:] = np.nan
            return centres, good
        used = good
        root = root if root in nodes else int(nodes[0])
    placed = np.isfinite(centres).all(1)
    centres[~placed] = np.nan
    centres -= centres[np.flatnonzero(placed)[0]]
    return centres, used


def flexible_modes(centers: np.ndarray, pairs: np.ndarray, *, max_modes: int = 12, rel_tol: float = 1e-9) -> int:
    """Parallel-rigidity check: dimension of the space of centre motions that keep every baseline direction
    of ``pairs`` (taken from ``centers`` themselves, so exactly consistent), minus translation and scale.

    0 means the centres are determined up to a similarity; > 0 means part of the layout can move (e.g. the
    spacing along a collinear row, or the relative scale of two clusters joined at one camera).  Counted
    from the smallest eigenvalues of ``Σ_p A_pᵀ (I − d_p d_pᵀ) A_p`` (sparse shift-invert; at most
    ``max_modes − 4``, so large counts are lower bounds); -1 if the eigen-solver fails.  Images not in
    ``pairs`` are ignored.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return 0
    nodes, local = np.unique(pairs, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(nodes)
    c = np.asarray(centers, dtype=np.float64)[nodes]
    d = normalize(c[local[:, 1]] - c[local[:, 0]])
    P_perp = np.eye(3) - d[:, :, None] * d[:, None, :]
    K, _ = _block_system(local, np.arange(3 * n).reshape(n, 3), P_perp, np.zeros((len(local), 3)), n)
    top = max(np.abs(K.diagonal()).max(), 1e-300)
    k = min(max_modes, 3 * n)
    if 3 * n <= 60:
        ev = np.linalg.eigvalsh(K.toarray())[:k]
    else:
        try:
            ev = eigsh(K, k=k, sigma=-1e-6 * top, which="LM", return_eigenvectors=False)
        except (ArpackNoConvergence, RuntimeError) as exc:  # diagnostic only: never fail the registration
            log.warning("parallel-rigidity check failed (%s)", exc)
            return -1
    trivial = 4 if n > 2 else 3 * n - 2  # translation + scale (two cameras: only their distance is fixed)
    return max(int(np.sum(ev < rel_tol * top)) - min(trivial, 3 * n), 0)
