"""Absolute rotations from relative ones (the ``"general"`` model's rotation step).

Maximum spanning tree initialisation ranked by triangle support, repaired by consensus moves (single images, then
internally consistent clusters), then robust rotation averaging on the Lie algebra (Chatterjee & Govindu, "Robust
relative rotation averaging", TPAMI 2018): L1-IRLS followed by Cauchy-IRLS, each step one sparse weighted-Laplacian
solve. ``general_rotations`` chains these, rejects the pairs left with a large residual and re-fits on the rest.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.sparse.linalg import spsolve
from scipy.spatial.transform import Rotation

from fullview.sfm.registration.view_graph import prune_graph, triangle_support, unique_edges
from fullview.sfm.rotations import rotation_angle_deg

log = logging.getLogger(__name__)


def spanning_tree_rotations(num_images, pairs, R_j_from_i, weights, mask, root, *, priority=None) -> np.ndarray:
    """Absolute rotations (N, 3, 3) chained along the maximum spanning tree of ``pairs[mask]``.

    Edges are ranked by ``priority`` (e.g. :func:`triangle_support`), then by weight.  Images not reached
    from ``root`` get NaN.
    """
    idx, key = unique_edges(pairs, mask, weights)
    w = weights[idx]
    pr = np.zeros(len(idx)) if priority is None else np.asarray(priority, dtype=np.float64)[idx]
    # lexicographic (priority, weight) as one positive cost; zeros would mean "no edge"
    w_rank = (w - w.min()) / (w.max() - w.min() + 1.0)  # in [0, 1)
    cost = (pr.max() - pr) + (1.0 - w_rank) + 1.0
    G = sp.coo_matrix((cost, (key[:, 0], key[:, 1])), shape=(num_images, num_images)).tocsr()
    tree = minimum_spanning_tree(G)
    visit, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
    edge_of = {(a, b): p for (a, b), p in zip(key.tolist(), idx.tolist())}
    R = np.full((num_images, 3, 3), np.nan)
    R[root] = np.eye(3)
    for node in visit[1:]:
        parent = pred[node]
        p = edge_of[(min(parent, node), max(parent, node))]
        if pairs[p, 0] == parent:  # node = j: R_j = R_rel R_i
            R[node] = R_j_from_i[p] @ R[parent]
        else:  # node = i: R_i = R_relᵀ R_j
            R[node] = R_j_from_i[p].T @ R[parent]
    return R


def _camera_sweeps(R, pairs, R_j_from_i, thr, max_sweeps):
    """Image-level consensus moves (see :func:`consensus_sweeps`); returns the number of moves."""
    N, P = len(R), len(pairs)
    cam = np.concatenate([pairs[:, 1], pairs[:, 0]])  # image whose rotation is predicted
    other = np.concatenate([pairs[:, 0], pairs[:, 1]])
    rel = np.concatenate([R_j_from_i, np.swapaxes(R_j_from_i, -1, -2)])  # R_cam = rel @ R_other
    order = np.argsort(cam, kind="stable")
    cam, other, rel = cam[order], other[order], rel[order]
    deg = np.bincount(cam, minlength=N)
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    # every (candidate incidence a, incidence b of the same image)
    a_idx = np.repeat(np.arange(2 * P), deg[cam])
    first = np.repeat(np.cumsum(deg[cam]) - deg[cam], deg[cam])
    b_idx = start[cam[a_idx]] + np.arange(len(a_idx)) - first
    moves = 0
    for sweep in range(max_sweeps):
        pred = rel @ R[other]
        trunc_a = np.minimum(np.radians(rotation_angle_deg(pred[a_idx], pred[b_idx])), thr) ** 2
        cand_cost = np.bincount(a_idx, trunc_a, 2 * P)
        cur_cost = np.bincount(cam, np.minimum(np.radians(rotation_angle_deg(R[cam], pred)), thr) ** 2, N)
        best = np.lexsort((cand_cost, cam))[start[deg > 0]]  # cheapest candidate of each image
        gain = np.zeros(N)
        gain[cam[best]] = cur_cost[cam[best]] - cand_cost[best]
        gain[gain < 1e-3 * thr**2] = 0.0
        if not gain.any():
            break
        # move where the gain is the largest of the neighbourhood (equal gains: the lower index)
        nb_max = np.zeros(N)
        np.maximum.at(nb_max, pairs[:, 0], gain[pairs[:, 1]])
        np.maximum.at(nb_max, pairs[:, 1], gain[pairs[:, 0]])
        move = (gain > 0) & (gain >= nb_max)
        tie = (gain[pairs[:, 0]] == gain[pairs[:, 1]]) & (gain[pairs[:, 0]] > 0)
        move[pairs[tie].max(1)] = False
        moving = best[move[cam[best]]]
        R[cam[moving]] = pred[moving]
        moves += len(moving)
        log.debug("consensus sweep %d: %d image(s) switched", sweep, len(moving))
    return moves


def _cluster_moves(R, pairs, R_j_from_i, thr) -> int:
    """Cluster-level consensus: re-attach each internally consistent cluster to the largest one."""
    N = len(R)
    nodes = np.unique(pairs)
    res = np.radians(rotation_angle_deg(R_j_from_i, R[pairs[:, 1]] @ np.swapaxes(R[pairs[:, 0]], -1, -2)))
    ok = res < thr
    G = sp.coo_matrix((np.ones(ok.sum()), (pairs[ok, 0], pairs[ok, 1])), shape=(N, N))
    _, labels = connected_components(G, directed=False)
    sizes = np.bincount(labels[nodes], minlength=labels.max() + 1)
    if np.count_nonzero(sizes) <= 1:
        return 0
    main = int(np.argmax(sizes))
    li, lj = labels[pairs[:, 0]], labels[pairs[:, 1]]
    moved = 0
    for comp in np.flatnonzero(sizes)[np.argsort(-sizes[np.flatnonzero(sizes)], kind="stable")]:
        if comp == main:
            continue
        a = np.flatnonzero((li == comp) & (lj == main))  # i in the cluster: G = R_iᵀ R_relᵀ R_j
        b = np.flatnonzero((li == main) & (lj == comp))  # j in the cluster: G = R_jᵀ R_rel R_i
        if len(a) + len(b) == 0:
            continue
        cand = np.concatenate([
            np.swapaxes(R[pairs[a, 0]], -1, -2) @ np.swapaxes(R_j_from_i[a], -1, -2) @ R[pairs[a, 1]],
            np.swapaxes(R[pairs[b, 1]], -1, -2) @ R_j_from_i[b] @ R[pairs[b, 0]],
        ])
        # residual of crossing pair q under candidate G: angle between R_rel and R_j' R_i'ᵀ
        Ra_i, Ra_j = R[pairs[a, 0]], R[pairs[a, 1]]
        Rb_i, Rb_j = R[pairs[b, 0]], R[pairs[b, 1]]
        costs = np.zeros(len(cand))
        for Ri, Rj, Rrel, in_i in ((Ra_i, Ra_j, R_j_from_i[a], True), (Rb_i, Rb_j, R_j_from_i[b], False)):
            if len(Ri) == 0:
                continue
            if in_i:  # R_i' = R_i G
                pred = Rj[None] @ np.swapaxes(Ri[None] @ cand[:, None], -1, -2)
            else:  # R_j' = R_j G
                pred = (Rj[None] @ cand[:, None]) @ np.swapaxes(Ri[None], -1, -2)
            costs += (np.minimum(np.radians(rotation_angle_deg(Rrel[None], pred)), thr) ** 2).sum(1)
        current = (np.minimum(res[np.concatenate([a, b])], thr) ** 2).sum()
        best = int(np.argmin(costs))
        if costs[best] < current - 1e-3 * thr**2:
            members = np.flatnonzero(labels == comp)
            R[members] = R[members] @ cand[best]
            labels[members] = main
            li, lj = labels[pairs[:, 0]], labels[pairs[:, 1]]
            moved += 1
    log.debug("consensus: %d cluster(s) re-attached", moved)
    return moved


def consensus_sweeps(R: np.ndarray, pairs: np.ndarray, R_j_from_i: np.ndarray, *, threshold_deg: float = 5.0,
                     max_sweeps: int = 20, max_rounds: int = 10) -> np.ndarray:
    """Repair a rotation initialisation (e.g. a spanning tree through outlier pairs) by local consensus.

    Image moves: an image may take any rotation predicted by one of its pairs (``R_j_from_i R_i`` or
    ``R_j_from_iᵀ R_j``); it switches to the one minimising its truncated cost
    ``Σ_incident min(angle, threshold)²`` when that beats its current cost.  Images whose gain is the largest
    in their neighbourhood switch together (never two neighbours, so the total truncated cost decreases).
    Cluster moves: the components of the graph of consistent pairs (residual < threshold) are re-attached to
    the largest one by the common right factor ``R_k ← R_k G`` (which keeps their internal relative rotations)
    predicted by one of the crossing pairs, again minimising the truncated cost of the crossing pairs.
    ``R`` (N, 3, 3) must be finite on the images of ``pairs``.
    """
    R = np.asarray(R, dtype=np.float64).copy()
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    R_j_from_i = np.asarray(R_j_from_i, dtype=np.float64)
    thr = np.radians(threshold_deg)
    for _ in range(max_rounds):
        _camera_sweeps(R, pairs, R_j_from_i, thr, max_sweeps)
        if _cluster_moves(R, pairs, R_j_from_i, thr) == 0:
            break
    return R


def _rotation_residual_vectors(R, pairs, R_j_from_i) -> np.ndarray:
    """(M, 3) log(R_jᵀ R_j_from_i R_i): zero when consistent; ≈ ω_j − ω_i for R_k ← R_k exp(ω_k)."""
    E = np.swapaxes(R[pairs[:, 1]], -1, -2) @ R_j_from_i @ R[pairs[:, 0]]
    return Rotation.from_matrix(E).as_rotvec()


def _grounded_laplacian(pairs_local, w, n, root_local):
    """Weighted graph Laplacian with the root row / column removed, plus the column map."""
    i, j = pairs_local[:, 0], pairs_local[:, 1]
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([i, j, j, i])
    vals = np.concatenate([w, w, -w, -w])
    L = sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsc()
    keep = np.flatnonzero(np.arange(n) != root_local)
    return L[keep][:, keep], keep


def rotation_averaging_irls(
    R_init: np.ndarray,
    pairs: np.ndarray,
    R_j_from_i: np.ndarray,
    root: int,
    *,
    l1_iterations: int = 100,
    robust_iterations: int = 30,
    robust_scale_deg: float = 2.0,
    l1_tol_rad: float = 1e-6,
    tol_rad: float = 1e-10,
) -> np.ndarray:
    """Robust rotation averaging (Chatterjee & Govindu): L1-IRLS then Cauchy-IRLS on the Lie algebra.

    ``R_init`` (N, 3, 3) must be finite on every image in ``pairs``, which must form a connected graph;
    ``root`` stays fixed.  Each iteration solves ``min Σ w_p ‖ω_j − ω_i − log(R_jᵀ R_ij R_i)‖²``
    (one sparse Laplacian factorisation, three right-hand sides) and updates ``R_k ← R_k exp(ω_k)``.
    """
    nodes, local = np.unique(pairs, return_inverse=True)
    local = local.reshape(-1, 2)
    n = len(nodes)
    root_local = int(np.searchsorted(nodes, root))
    if n < 2 or nodes[root_local] != root:
        raise ValueError(f"root {root} must be one of the images in pairs ({n} images)")
    R = np.asarray(R_init, dtype=np.float64).copy()
    sigma = np.radians(robust_scale_deg)
    schedule = ["l1"] * l1_iterations + ["cauchy"] * robust_iterations
    stage_done = None
    for it, stage in enumerate(schedule):
        if stage == stage_done:
            continue
        dw = _rotation_residual_vectors(R, pairs, R_j_from_i)
        r = np.linalg.norm(dw, axis=1)
        w = 1.0 / np.maximum(r, 1e-6) if stage == "l1" else 1.0 / (1.0 + (r / sigma) ** 2)
        L, keep = _grounded_laplacian(local, w, n, root_local)
        b = np.zeros((n, 3))
        np.add.at(b, local[:, 1], w[:, None] * dw)
        np.add.at(b, local[:, 0], -w[:, None] * dw)
        omega = np.zeros((n, 3))
        omega[keep] = np.asarray(spsolve(L, b[keep])).reshape(-1, 3)
        R[nodes] = R[nodes] @ Rotation.from_rotvec(omega).as_matrix()
        step = np.abs(omega).max()
        if step < (l1_tol_rad if stage == "l1" else tol_rad):
            stage_done = stage
        log.debug("rotation IRLS %s it %d: median residual %.4f°, max step %.2e",
                  stage, it, np.degrees(np.median(r)), step)
    return R


def general_rotations(N, pairs, R_rel, w, use, root, thr_deg, robust_scale_deg):
    """``(R_abs (N, 3, 3), used pairs (P,))`` of the ``"general"`` model: tree + consensus initialisation, robust
    averaging, rejection of pairs above ``thr_deg`` and a re-fit on the largest consistent component (NaN elsewhere)."""
    support = triangle_support(N, pairs, R_rel, w, use, threshold_deg=thr_deg)
    R0 = spanning_tree_rotations(N, pairs, R_rel, w, use, root, priority=support)
    sel = np.flatnonzero(use)
    R0 = consensus_sweeps(R0, pairs[sel], R_rel[sel], threshold_deg=thr_deg)
    R_abs = rotation_averaging_irls(R0, pairs[sel], R_rel[sel], root, robust_scale_deg=robust_scale_deg)
    res = rotation_angle_deg(R_rel, R_abs[pairs[:, 1]] @ np.swapaxes(R_abs[pairs[:, 0]], -1, -2))
    inl = use & (res <= thr_deg)
    log.info("rotation averaging: %d/%d pairs within %.1f°, median residual %.3f°",
             inl.sum(), use.sum(), thr_deg, np.median(res[use]))
    nodes, inl = prune_graph(N, pairs, inl, w, 1)
    if len(nodes) < 2:
        return R_abs, inl
    root = int(nodes[0])
    sel = np.flatnonzero(inl)
    # final robust re-fit on the consistent pairs only (near least squares for small residuals)
    R_abs = rotation_averaging_irls(R_abs, pairs[sel], R_rel[sel], root, l1_iterations=0,
                                    robust_scale_deg=robust_scale_deg)
    keep = np.zeros(N, bool)
    keep[nodes] = True
    R_abs[~keep] = np.nan
    return R_abs, inl
