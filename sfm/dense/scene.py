"""Scales of a sparse scene, in model units: per-camera depths of the sparse points and the scene's size."""

from __future__ import annotations

import numpy as np

SCENE_PERCENTILES = (1.0, 99.0)  # sparse points outside these percentiles do not count for the scene size


def camera_depths(centers: np.ndarray, sparse: dict, percentile: float) -> tuple[np.ndarray, np.ndarray]:
    """Per camera: (low ``percentile`` and median) distance to the sparse points it observes (all points if it has
    none); model units."""
    points = sparse["points"]
    near, median = np.full(len(centers), np.nan), np.full(len(centers), np.nan)
    if not len(points):
        return near, median
    for k, c in enumerate(centers):
        seen = np.unique(sparse["track_ids"][sparse["image_ids"] == k])
        dist = np.linalg.norm(points[seen if len(seen) >= 20 else slice(None)] - c, axis=1)
        near[k], median[k] = np.percentile(dist, percentile), np.median(dist)
    return near, median


def scene_size(centers: np.ndarray, points: np.ndarray) -> float:
    """Diagonal of the box around the camera centres and the sparse points (outer 1 % trimmed per axis)."""
    pts = centers if not len(points) else np.vstack([centers, points])
    lo, hi = np.percentile(pts, SCENE_PERCENTILES, axis=0)
    return float(np.linalg.norm(np.maximum(hi, centers.max(0)) - np.minimum(lo, centers.min(0))))
