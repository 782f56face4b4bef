"""A join's placement checked against what each model's cameras saw: free space must stay free.

The weak joins (`weak_joins`, `rematch_join`) rest on a doorway's few matches: 5-6 points per model for a one-pair
join, two pairs that only just beat their quarter turns for the several-pair one. A chance pair that passes them
places model b somewhere in model a's rooms. Its points then float in front of the surfaces a's cameras saw: a
camera of a that saw a point at some range along a ray would have seen b's point instead, were it really there
closer along the same ray. A true join puts b in the next room, behind a's walls (and a's points), or seen through
the doorway at the range a's cameras saw it.

So once a join's similarity is known, every point of b is looked for along the rays of a's cameras' observed
points (within `tolerance_rad`) and every point of a along b's: one on such a ray is an *overlap*; one closer than
`1 - RANGE_MARGIN` of the observed range is a *conflict*. A join is contradicted when both models together show
at least MIN_CONFLICTS conflicts and MAX_CONFLICT_SHARE of their overlaps conflict.
Pure geometry: no file access.
"""

from __future__ import annotations

import numpy as np

RANGE_MARGIN = 0.1  # a point this much closer than the range observed along the same ray blocks that observation
MIN_CONFLICTS = 10  # conflicts (both directions) a contradicted join shows at least
MAX_CONFLICT_SHARE = 0.05  # ... and more than this share of its overlaps: a true join's points lie behind a's (or
# at their range through the doorway)


def observed_rays(X: np.ndarray, point_of_feature: dict, R: dict, C: dict, bearings) -> dict:
    """camera -> (bearings (n, 3) in its frame of its features that are points of X, their ranges (n,))."""
    out = {}
    for k, rows in point_of_feature.items():
        seen = np.flatnonzero(rows >= 0)
        out[k] = (bearings[k][seen], np.linalg.norm(X[rows[seen]] - C[k], axis=1))
    return out


def conflicts(rays: dict, R: dict, C: dict, X: np.ndarray, tolerance_rad: float) -> tuple[int, int]:
    """(conflicts, overlaps) of the points X (P, 3), in the frame of the cameras R (cam from world), C, whose
    observed rays are given (`observed_rays`): a point within tolerance_rad of a camera's observed ray overlaps it,
    and conflicts with it when closer than 1 - RANGE_MARGIN of the observed range (counted once per camera)."""
    found = overlaps = 0
    cos_min = np.cos(tolerance_rad)
    for k, (B, ranges) in rays.items():
        if not len(B) or not len(X):
            continue
        V = (X - C[k]) @ R[k].T
        r = np.linalg.norm(V, axis=1)
        near = (B @ (V / np.maximum(r, 1e-12)[:, None]).T) >= cos_min  # (n, P)
        overlaps += int(near.any(axis=0).sum())
        found += int((near & (r[None, :] < (1.0 - RANGE_MARGIN) * ranges[:, None])).any(axis=0).sum())
    return found, overlaps


def join_conflicts(points_a, points_b, *, R_a: dict, C_a: dict, R_b: dict, C_b: dict, bearings, M: np.ndarray,
                   scale: float, shift: np.ndarray, tolerance_rad: float) -> tuple[int, int]:
    """(conflicts, overlaps) of the join x_a = scale M x_b + shift, both ways: b's points on a's cameras' observed
    rays and a's points on b's. points_a, points_b: `rematch_join.ModelPoints` in their models' frames."""
    rays_a = observed_rays(points_a.X, points_a.point_of_feature, R_a, C_a, bearings)
    ab = conflicts(rays_a, R_a, C_a, scale * points_b.X @ M.T + shift, tolerance_rad)
    R_b_in_a = {k: R_b[k] @ M.T for k in R_b}
    C_b_in_a = {k: scale * M @ C_b[k] + shift for k in C_b}
    rays_b = {k: (B, scale * r) for k, (B, r) in
              observed_rays(points_b.X, points_b.point_of_feature, R_b, C_b, bearings).items()}
    ba = conflicts(rays_b, R_b_in_a, C_b_in_a, points_a.X, tolerance_rad)
    return ab[0] + ba[0], ab[1] + ba[1]


def contradicted(found: int, overlaps: int) -> bool:
    """True when a join's (conflicts, overlaps) contradict it (see the module doc)."""
    return found >= MIN_CONFLICTS and found > MAX_CONFLICT_SHARE * overlaps
