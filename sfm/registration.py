"""Global registration: absolute camera poses from pairwise relative poses.

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

The algorithm is deterministic (no random choice); ``seed`` is accepted for a uniform stage API.
Every linear solve is sparse (SuperLU): no dense LAPACK calls whose threading could stall busy machines.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.sparse.linalg import ArpackNoConvergence, eigsh, splu, spsolve
from scipy.spatial.transform import Rotation

from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg
from fullview.sfm.camera import normalize

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


# ----------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------


def relative_from_absolute(
    R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, i, j
) -> tuple[np.ndarray, np.ndarray]:
    """``(R_j_from_i, t_j_from_i / |t_j_from_i|)`` of images i, j (ints or index arrays)."""
    R = np.asarray(R_cam_from_world, dtype=np.float64)
    t = np.asarray(t_cam_from_world, dtype=np.float64)
    R_rel = R[j] @ np.swapaxes(R[i], -1, -2)
    t_rel = t[j] - np.einsum("...ab,...b->...a", R_rel, t[i])
    return R_rel, normalize(t_rel)


def yaw_rotation(theta: np.ndarray) -> np.ndarray:
    """``R_y(θ)`` (rotation about the y axis, world y pointing down), batched: (...,) -> (..., 3, 3)."""
    theta = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(theta.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 2], R[..., 1, 1], R[..., 2, 0], R[..., 2, 2] = c, s, 1.0, -s, c
    return R


def rotation_yaw(R: np.ndarray) -> np.ndarray:
    """Angle of the rotation about y closest to ``R`` (exact for ``yaw_rotation`` output), batched."""
    R = np.asarray(R, dtype=np.float64)
    return np.arctan2(R[..., 0, 2] - R[..., 2, 0], R[..., 0, 0] + R[..., 2, 2])


# ----------------------------------------------------------------------------------------------
# view graph
# ----------------------------------------------------------------------------------------------


def _largest_component(num_images: int, pairs: np.ndarray, mask: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Sorted image ids of the largest component of the graph of ``pairs[mask]`` (ties: weight, low id)."""
    if not mask.any():
        return np.zeros(0, dtype=np.int64)
    e = pairs[mask]
    G = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_images, num_images))
    _, labels = connected_components(G, directed=False)
    size = np.bincount(labels, minlength=labels.max() + 1)
    wsum = np.bincount(labels[e[:, 0]], weights=weights[mask], minlength=len(size))
    first = np.full(len(size), num_images)
    np.minimum.at(first, labels, np.arange(num_images))
    best = np.lexsort((first, -wsum, -size))[0]
    return np.flatnonzero(labels == best)


def _prune_graph(num_images, pairs, mask, weights, min_degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Largest component, then peel images with fewer than ``min_degree`` pairs until stable."""
    mask = mask.copy()
    while True:
        nodes = _largest_component(num_images, pairs, mask, weights)
        inside = np.zeros(num_images, bool)
        inside[nodes] = True
        mask &= inside[pairs].all(1)
        if min_degree <= 1 or len(nodes) <= 2:
            return nodes, mask
        deg = np.bincount(pairs[mask].ravel(), minlength=num_images)
        low = nodes[deg[nodes] < min_degree]
        if len(low) == 0:
            return nodes, mask
        log.debug("peeling %d image(s) with < %d consistent pairs: %s", len(low), min_degree, low.tolist())
        inside[low] = False
        mask &= inside[pairs].all(1)


# ----------------------------------------------------------------------------------------------
# rotation averaging
# ----------------------------------------------------------------------------------------------


def _unique_edges(pairs, mask, weights):
    """Indices of ``pairs[mask]`` keeping the heaviest pair per unordered image pair, and their (min, max) keys."""
    idx = np.flatnonzero(mask)
    key = np.sort(pairs[idx], axis=1)
    order = np.lexsort((-weights[idx], key[:, 1], key[:, 0]))
    key, idx = key[order], idx[order]
    first = np.ones(len(idx), bool)
    first[1:] = (key[1:] != key[:-1]).any(1)
    return idx[first], key[first]


def triangle_support(num_images, pairs, R_j_from_i, weights, mask, *, threshold_deg: float = 5.0) -> np.ndarray:
    """(P,) number of view-graph triangles through each pair whose rotation cycle closes within the threshold.

    A triangle (a, b, c) is consistent when ``R_{c←a}ᵀ R_{c←b} R_{b←a}`` is within ``threshold_deg`` of I.
    Gross outliers rarely close a cycle, so the count is a cheap, local inlier score (pairs outside ``mask``
    and duplicates of an unordered pair other than the heaviest get 0).
    """
    P = len(pairs)
    idx, key = _unique_edges(pairs, mask, weights)
    support = np.zeros(P)
    if len(idx) < 3:
        return support
    E = len(idx)
    lookup = sp.coo_matrix((np.arange(1, E + 1), (key[:, 0], key[:, 1])), shape=(num_images, num_images)).tocsr()
    # incidences from the lower endpoint only: triangles a < b < c found once, at a
    order = np.argsort(key[:, 0], kind="stable")
    low, high, eid = key[order, 0], key[order, 1], order
    deg = np.bincount(low, minlength=num_images)
    start = np.concatenate([[0], np.cumsum(deg)[:-1]])
    rep = deg[low]
    x = np.repeat(np.arange(E), rep)
    y = start[low[x]] + np.arange(len(x)) - np.repeat(np.cumsum(rep) - rep, rep)
    keep = high[x] < high[y]
    x, y = x[keep], y[keep]
    e_bc = np.asarray(lookup[high[x], high[y]]).ravel() - 1
    tri = e_bc >= 0
    e_ab, e_ac, e_bc = eid[x[tri]], eid[y[tri]], e_bc[tri]
    if len(e_ab) == 0:
        return support

    def rel(e, src):
        """R_{dst←src} of unique edge e."""
        R = R_j_from_i[idx[e]]
        forward = pairs[idx[e], 0] == src
        return np.where(forward[:, None, None], R, np.swapaxes(R, -1, -2))

    a, b = key[e_ab, 0], key[e_ab, 1]
    cycle = np.swapaxes(rel(e_ac, a), -1, -2) @ rel(e_bc, b) @ rel(e_ab, a)
    ok = rotation_angle_deg(cycle, np.eye(3)) < threshold_deg
    counts = np.bincount(np.concatenate([e_ab[ok], e_ac[ok], e_bc[ok]]), minlength=E)
    support[idx] = counts
    return support


def spanning_tree_rotations(num_images, pairs, R_j_from_i, weights, mask, root, *, priority=None) -> np.ndarray:
    """Absolute rotations (N, 3, 3) chained along the maximum spanning tree of ``pairs[mask]``.

    Edges are ranked by ``priority`` (e.g. :func:`triangle_support`), then by weight.  Images not reached
    from ``root`` get NaN.
    """
    idx, key = _unique_edges(pairs, mask, weights)
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


# ----------------------------------------------------------------------------------------------
# translation averaging
# ----------------------------------------------------------------------------------------------


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


def translation_averaging(
    num_images: int,
    pairs: np.ndarray,
    directions: np.ndarray,
    root: int,
    *,
    weights: np.ndarray | None = None,
    max_direction_residual_deg: float = 10.0,
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
    nodes, used = _prune_graph(num_images, pairs, used, weights, min_pairs_per_camera)
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
        centres[:] = np.nan
        centres[nodes_l] = c_local
        u = normalize(centres[pairs[:, 1]] - centres[pairs[:, 0]])
        cos = np.einsum("pa,pa->p", u, directions)
        good = used & (cos >= cos_thr)
        if good.sum() == used.sum():
            break
        log.debug("translation round %d: rejecting %d pair(s)", rnd, used.sum() - good.sum())
        nodes, good = _prune_graph(num_images, pairs, good, weights, min_pairs_per_camera)
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


# ----------------------------------------------------------------------------------------------
# planar model (the report's method)
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# driver
# ----------------------------------------------------------------------------------------------


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
    model: str = "general",
    seed: int = 0,
    e_ij=None,
    e_ji=None,
    min_weight: float = 0.0,
    max_rotation_residual_deg: float = 5.0,
    max_direction_residual_deg: float = 10.0,
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
    ``seed`` is unused (the method is deterministic) and kept for a uniform stage API.
    """
    del seed
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

    nodes, use = _prune_graph(N, pairs, valid, w, 1)
    log.info("registration (%s): %d images, %d/%d valid pairs, largest component %d images",
             model, N, valid.sum(), P, len(nodes))
    R_abs = np.full((N, 3, 3), np.nan)
    centres = np.full((N, 3), np.nan)
    if len(nodes) >= 2:
        root = int(nodes[0])
        if model == "general":
            R_abs, use = _general_rotations(N, pairs, R_rel, w, use, root, max_rotation_residual_deg, robust_scale_deg)
        else:
            R_abs, use = _planar_rotations(N, pairs, R_rel, w, use, root, e_i, e_j,
                                           max_rotation_residual_deg, max_direction_residual_deg, robust_scale_deg)
        nodes, use = _prune_graph(N, pairs, use, w, 1)
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


def _general_rotations(N, pairs, R_rel, w, use, root, thr_deg, robust_scale_deg):
    support = triangle_support(N, pairs, R_rel, w, use, threshold_deg=thr_deg)
    R0 = spanning_tree_rotations(N, pairs, R_rel, w, use, root, priority=support)
    sel = np.flatnonzero(use)
    R0 = consensus_sweeps(R0, pairs[sel], R_rel[sel], threshold_deg=thr_deg)
    R_abs = rotation_averaging_irls(R0, pairs[sel], R_rel[sel], root, robust_scale_deg=robust_scale_deg)
    res = rotation_angle_deg(R_rel, R_abs[pairs[:, 1]] @ np.swapaxes(R_abs[pairs[:, 0]], -1, -2))
    inl = use & (res <= thr_deg)
    log.info("rotation averaging: %d/%d pairs within %.1f°, median residual %.3f°",
             inl.sum(), use.sum(), thr_deg, np.median(res[use]))
    nodes, inl = _prune_graph(N, pairs, inl, w, 1)
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


def _planar_rotations(N, pairs, R_rel, w, use, root, e_i, e_j, rot_thr_deg, dir_thr_deg, robust_scale_deg):
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
        nodes, new = _prune_graph(N, pairs, new, w, 1)
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
