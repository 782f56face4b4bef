"""Accuracy of dense reconstructions against ground truth: per-panorama range maps and fused point clouds.

A reconstruction is known up to a similarity; every function takes the alignment explicitly (``scale`` for range
maps, which live in the cameras' own frames and only need scaling; a ``Similarity`` for world points), normally the
one that aligns the estimated camera centres onto the true ones (``fullview.sfm.metrics.umeyama``).

The true surface is sampled by back-projecting the ground-truth range maps of all panoramas with the true poses
(``surface_samples``), which works for any dataset that has ground-truth depth and covers what the cameras see.
Pure functions (numpy / scipy / cv2), no file access.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from fullview.sfm.camera import bearings_to_pixels, pixels_to_bearings
from fullview.sfm.metrics import Similarity


def backproject_range_map(range_map: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                          *, stride: int = 1) -> np.ndarray:
    """(N, 3) world points of the valid (finite, > 0) pixels of an equirectangular range map, every ``stride``-th
    pixel in both directions (pixel centres)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    height, width = range_map.shape
    rows, cols = np.mgrid[0:height:stride, 0:width:stride]
    ranges = np.asarray(range_map, np.float64)[rows, cols]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(ranges) & (ranges > 0)
    pix = np.stack([cols[ok] + 0.5, rows[ok] + 0.5], axis=1)
    x_cam = pixels_to_bearings(pix, width, height).reshape(-1, 3) * ranges[ok][:, None]
    return (x_cam - np.asarray(t_cam_from_world, np.float64)) @ np.asarray(R_cam_from_world, np.float64)


def voxel_downsample(points: np.ndarray, voxel_size: float, colors: np.ndarray | None = None,
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """Mean point (and mean colour) of every occupied voxel of side ``voxel_size``; (points (M, 3), colours (M, 3)
    of the input dtype, or None). The voxel grid is anchored at the origin, so repeated calls share one grid."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return pts, (None if colors is None else np.asarray(colors).reshape(0, 3))
    cells = np.floor(pts / voxel_size).astype(np.int64)
    cells -= cells.min(0)
    span = cells.max(0) + 1
    if np.prod(span.astype(np.float64)) >= 2.0**62:
        raise ValueError(f"voxel_size {voxel_size} is too small for points spanning {span * voxel_size}")
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.stack([np.bincount(inverse, pts[:, k], len(counts)) for k in range(3)], axis=1) / counts[:, None]
    if colors is None:
        return out, None
    cols = np.asarray(colors)
    mean = np.stack([np.bincount(inverse, cols[:, k].astype(np.float64), len(counts)) for k in range(cols.shape[1])],
                    axis=1) / counts[:, None]
    return out, (np.rint(mean).astype(cols.dtype) if cols.dtype.kind in "ui" else mean.astype(cols.dtype))


def surface_samples(range_maps: Sequence[np.ndarray], R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                    *, spacing: float, max_pixels_per_map: int = 1 << 20) -> np.ndarray:
    """Roughly uniform samples (one per ``spacing`` voxel) of the surfaces seen in ground-truth range maps.

    Each map is back-projected (with a pixel stride keeping at most ``max_pixels_per_map`` pixels) and voxel
    down-sampled, so nearby surfaces do not outweigh distant ones.
    """
    parts = []
    for k, rmap in enumerate(range_maps):
        stride = max(1, int(np.ceil(np.sqrt(rmap.size / max_pixels_per_map))))
        pts = backproject_range_map(rmap, R_cam_from_world[k], t_cam_from_world[k], stride=stride)
        parts.append(voxel_downsample(pts, spacing)[0])
    if not parts:
        return np.zeros((0, 3))
    return voxel_downsample(np.concatenate(parts), spacing)[0]


def resize_nearest(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A map resampled to ``shape`` (height, width) by the nearest pixel centre (no blending across edges)."""
    if values.shape == tuple(shape):
        return values
    out = cv2.resize(np.asarray(values, np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
    return out.astype(values.dtype) if values.dtype != bool else out.astype(bool)


def range_map_errors(range_est: np.ndarray, valid_est: np.ndarray, range_gt: np.ndarray, *, scale: float = 1.0,
                     ) -> dict[str, float]:
    """Relative range error of an estimated range map (scaled by ``scale`` into ground-truth units).

    The ground truth is resampled to the estimate's size (nearest). Returns the median and 90th percentile relative
    error over the valid pixels, the share of valid pixels within 5 % and the share of pixels (with a finite true
    range) that are valid.
    """
    gt = resize_nearest(np.asarray(range_gt, np.float32), range_est.shape).astype(np.float64)
    with np.errstate(invalid="ignore"):
        has_gt = np.isfinite(gt) & (gt > 0)
        valid = np.asarray(valid_est, bool) & np.isfinite(range_est) & has_gt
    rel = np.abs(scale * np.asarray(range_est, np.float64)[valid] - gt[valid]) / gt[valid]
    out = {"valid_share": float(valid.sum() / max(has_gt.sum(), 1))}
    if len(rel):
        out.update(median_rel_error=float(np.median(rel)), p90_rel_error=float(np.percentile(rel, 90)),
                   share_within_5pct=float(np.mean(rel <= 0.05)))
    else:
        out.update(median_rel_error=None, p90_rel_error=None, share_within_5pct=None)
    return out


def cloud_accuracy_completeness(points: np.ndarray, surface: np.ndarray, tau: float) -> dict[str, float]:
    """Accuracy (share of ``points`` within ``tau`` of the true ``surface`` samples) and completeness (share of the
    surface samples within ``tau`` of a point), with the median distances both ways; points already aligned."""
    if not tau > 0:
        raise ValueError(f"tau must be > 0, got {tau}")
    points = np.asarray(points, np.float64).reshape(-1, 3)
    surface = np.asarray(surface, np.float64).reshape(-1, 3)
    if len(points) == 0 or len(surface) == 0:
        return {"accuracy": 0.0, "completeness": 0.0, "median_point_to_surface": None,
                "median_surface_to_point": None, "tau": float(tau)}
    d_acc, _ = cKDTree(surface).query(points, distance_upper_bound=10 * tau, workers=-1)
    d_comp, _ = cKDTree(points).query(surface, distance_upper_bound=10 * tau, workers=-1)
    return {"accuracy": float(np.mean(d_acc <= tau)), "completeness": float(np.mean(d_comp <= tau)),
            "median_point_to_surface": _finite_median(d_acc), "median_surface_to_point": _finite_median(d_comp),
            "tau": float(tau)}


def sample_mesh_surface(vertices: np.ndarray, triangles: np.ndarray, spacing: float, *, seed: int = 0,
                        max_samples: int = 4_000_000) -> np.ndarray:
    """Points spread uniformly over a triangle mesh's surface, about one per ``spacing``² of area (at most
    ``max_samples``): triangles drawn by area, positions uniform inside each (seeded, reproducible)."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    corners = vertices[np.asarray(triangles, np.int64).reshape(-1, 3)]
    if len(corners) == 0:
        return np.zeros((0, 3))
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    if not area.sum() > 0:
        return corners.reshape(-1, 3)
    count = int(np.clip(np.ceil(area.sum() / spacing**2), 1, max_samples))
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(corners), count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1  # fold the unit square onto the triangle
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = corners[tri, 0], corners[tri, 1], corners[tri, 2]
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def _finite_median(values: np.ndarray) -> float | None:
    """Median, or None when it is infinite (beyond a KD-tree query's distance bound)."""
    m = float(np.median(values))
    return m if np.isfinite(m) else None


def dense_metrics(*, range_est: Sequence[np.ndarray | None], valid_est: Sequence[np.ndarray | None],
                  range_gt: Sequence[np.ndarray], R_gt_cam_from_world: np.ndarray, t_gt_cam_from_world: np.ndarray,
                  sim: Similarity, points: np.ndarray | None, scene_size: float, names: Sequence[str],
                  tau_rel: float = 0.01, mesh: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Per-panorama range errors and fused-cloud (and mesh) accuracy / completeness at τ = ``tau_rel`` ·
    ``scene_size``.

    ``range_est[k]`` / ``valid_est[k]``: the estimated range map of panorama k (None if it has none); ``sim`` takes
    the reconstruction onto the ground truth (its scale converts ranges). ``points`` (N, 3): the fused cloud in the
    reconstruction's frame (None: no cloud metrics); ``mesh``: (vertices (V, 3), triangles (T, 3)) in that frame,
    measured by its surface sampled uniformly every τ / 3 (None: no mesh metrics). The true surface is sampled every
    τ / 3 from the true range maps.
    """
    per_view = {}
    for k, name in enumerate(names):
        if range_est[k] is not None:
            per_view[name] = range_map_errors(range_est[k], valid_est[k], range_gt[k], scale=sim.scale)
    out: dict = {"per_panorama": per_view}
    errs = [v["median_rel_error"] for v in per_view.values() if v["median_rel_error"] is not None]
    if per_view:
        out["max_median_rel_error"] = float(max(errs)) if errs else None
        out["min_valid_share"] = float(min(v["valid_share"] for v in per_view.values()))
    tau = tau_rel * scene_size
    out["scene_size"] = float(scene_size)
    surface = None
    if points is not None or mesh is not None:
        surface = surface_samples(range_gt, R_gt_cam_from_world, t_gt_cam_from_world, spacing=tau / 3)
    if points is not None:
        out["cloud"] = {"points": int(len(points)), "surface_samples": int(len(surface)),
                        **cloud_accuracy_completeness(sim.apply(np.asarray(points, np.float64)), surface, tau)}
    if mesh is not None:
        vertices, triangles = mesh
        samples = sample_mesh_surface(sim.apply(np.asarray(vertices, np.float64)), triangles, tau / 3)
        out["mesh"] = {"vertices": int(len(vertices)), "triangles": int(len(triangles)),
                       "mesh_samples": int(len(samples)), "surface_samples": int(len(surface)),
                       **cloud_accuracy_completeness(samples, surface, tau)}
    return out


def predicted_range_map(k: int, range_maps: Sequence[np.ndarray], R_cam_from_world: np.ndarray,
                        t_cam_from_world: np.ndarray, *, stride: int = 2) -> np.ndarray:
    """(H, W) range that the other panoramas' range maps predict for panorama k: their pixels (every ``stride``-th)
    back-projected to the world and splatted into k's equirectangular grid, nearest range per pixel (the visible
    surface); NaN where none lands."""
    height, width = range_maps[k].shape
    best = np.full(height * width, np.inf)
    for j, rng in enumerate(range_maps):
        if j == k or rng is None:
            continue
        x = backproject_range_map(rng, R_cam_from_world[j], t_cam_from_world[j], stride=stride)
        splat_nearest(x, R_cam_from_world[k], t_cam_from_world[k], (height, width), into=best)
    best[~np.isfinite(best)] = np.nan
    return best.reshape(height, width)


def splat_nearest(points: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                  shape: tuple[int, int], *, into: np.ndarray | None = None) -> np.ndarray:
    """(H·W,) per pixel of a camera's equirectangular grid of ``shape`` the nearest range of the world ``points``
    projecting into it, kept in ``into`` if given (+inf where none)."""
    height, width = shape
    best = np.full(height * width, np.inf) if into is None else into
    x_cam = points @ np.asarray(R_cam_from_world).T + t_cam_from_world
    dist = np.linalg.norm(x_cam, axis=1)
    ok = dist > 0
    pix = bearings_to_pixels(x_cam[ok], width, height)
    cols = np.clip(pix[:, 0].astype(np.int64), 0, width - 1)
    rows = np.clip(pix[:, 1].astype(np.int64), 0, height - 1)
    np.minimum.at(best, rows * width + cols, dist[ok])
    return best


def leave_one_out_agreement(range_maps: Sequence[np.ndarray | None], R_cam_from_world: np.ndarray,
                            t_cam_from_world: np.ndarray, *, tolerance: float = 0.02, stride: int = 2
                            ) -> list[dict[str, float | None]]:
    """Per panorama, without ground truth: ``valid_share`` (pixels with a range) and ``agreement``, the share of its
    ranged pixels where the other panoramas predict a range (`predicted_range_map`) that lies within ``tolerance``
    (relative) of its own; ``checked_share`` says on how many of its pixels the others could speak. A panorama whose
    depth is wrong disagrees with what the rest of the scene says it should see."""
    out = []
    for k, own in enumerate(range_maps):
        if own is None:
            out.append({"valid_share": 0.0, "agreement": None, "checked_share": 0.0})
            continue
        predicted = predicted_range_map(k, range_maps, R_cam_from_world, t_cam_from_world, stride=stride)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(own) & (own > 0)
            checked = valid & np.isfinite(predicted)
            agree = checked & (np.abs(predicted - own) <= tolerance * own)
        out.append({"valid_share": float(valid.mean()),
                    "agreement": float(agree.sum() / checked.sum()) if checked.any() else None,
                    "checked_share": float(checked.sum() / max(valid.sum(), 1))})
    return out
