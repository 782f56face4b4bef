"""The view graph: images are nodes, pairs with a relative pose are edges.

Owns the connectivity bookkeeping shared by the averaging steps: the largest connected component, peeling images
with too few pairs, one edge per unordered image pair, and the triangle-cycle inlier score of each pair.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from fullview.sfm.rotations import rotation_angle_deg

log = logging.getLogger(__name__)


def component_labels(num_images: int, pairs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(N,) connected-component label of every image in the graph of ``pairs[mask]`` (isolated images get their
    own label)."""
    e = pairs[mask] if len(pairs) else np.zeros((0, 2), np.int64)
    G = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_images, num_images))
    return connected_components(G, directed=False)[1]


def largest_component(num_images: int, pairs: np.ndarray, mask: np.ndarray, weights: np.ndarray) -> np.ndarray:
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


def prune_graph(num_images, pairs, mask, weights, min_degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Largest component, then peel images with fewer than ``min_degree`` pairs until stable."""
    mask = mask.copy()
    while True:
        nodes = largest_component(num_images, pairs, mask, weights)
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


def unique_edges(pairs, mask, weights):
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
    idx, key = unique_edges(pairs, mask, weights)
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
    if len(x) == 0:  # no two edges share a lower endpoint: no triangle (and scipy's empty lookup would be sparse)
        return support
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


def bridges(num_images: int, pairs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(P,) bool: pairs of ``pairs[mask]`` whose removal disconnects the graph (Tarjan's low-link, iterative DFS).

    A loop over the graph's edges (not a per-point hot path): views and pairs number in the hundreds or thousands.
    Parallel pairs between the same two images are never bridges."""
    adjacency: list[list[tuple[int, int]]] = [[] for _ in range(num_images)]
    for k in np.flatnonzero(mask):
        i, j = int(pairs[k, 0]), int(pairs[k, 1])
        adjacency[i].append((j, int(k)))
        adjacency[j].append((i, int(k)))
    order = np.full(num_images, -1)
    low = np.zeros(num_images, np.int64)
    out = np.zeros(len(pairs), bool)
    counter = 0
    for root in range(num_images):
        if order[root] >= 0 or not adjacency[root]:
            continue
        order[root] = low[root] = counter
        counter += 1
        stack = [(root, -1, iter(adjacency[root]))]
        while stack:
            node, via, edges = stack[-1]
            step = next(edges, None)
            if step is None:
                stack.pop()
                if stack:
                    parent = stack[-1][0]
                    low[parent] = min(low[parent], low[node])
                    if low[node] > order[parent]:
                        out[via] = True
                continue
            other, edge = step
            if edge == via:
                continue
            if order[other] < 0:
                order[other] = low[other] = counter
                counter += 1
                stack.append((other, edge, iter(adjacency[other])))
            else:
                low[node] = min(low[node], order[other])
    return out
