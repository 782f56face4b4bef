"""Degenerate pairs: a pair whose matches a pure rotation explains has no baseline (identical images, a camera
turned on a tripod). Its F is then arbitrary and no relative translation can be recovered from it."""

from __future__ import annotations

import numpy as np

NO_BASELINE_SHARE = 0.95  # a rotation explaining this share of the F-inliers means "no baseline"


def rotation_from_bearings(b_i: np.ndarray, b_j: np.ndarray) -> np.ndarray:
    """Least-squares R_j_from_i with b_j ≈ R b_i (Kabsch on unit bearings)."""
    u, _, vt = np.linalg.svd(b_j.T @ b_i)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def has_no_baseline(b_i: np.ndarray, b_j: np.ndarray, threshold_rad: float) -> bool:
    """True when one rotation maps `b_i` onto `b_j` within `threshold_rad` / 2 for most matches."""
    if len(b_i) < 3:
        return False
    R = rotation_from_bearings(b_i, b_j)
    cos = np.clip(np.einsum("nk,nk->n", b_i @ R.T, b_j), -1.0, 1.0)
    return bool(np.mean(np.arccos(cos) <= 0.5 * threshold_rad) >= NO_BASELINE_SHARE)
