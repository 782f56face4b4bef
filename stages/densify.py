"""Stage 7 — dense reconstruction by rectified spherical disparity: one range map per panorama and a fused cloud.

1. Stereo pairs: each camera's best partners (inlier count, triangulation angle at its median sparse depth).
2. Per pair (``fullview.sfm.dense.densify_pair``): rectify, SGBM with a left-right check, law-of-sines ranges,
   back to both panoramas. The disparity search covers depths down to the nearest plausible one, taken from the
   sparse points (a low percentile of the camera-to-point distances), since the model's scale is arbitrary.
3. Per panorama: the pair estimates are combined (median of the agreeing ones; pixels whose estimates conflict are
   dropped) and saved as ``depth/<stem>.npz`` (``range``, ``valid``) and a colour-mapped ``depth/<stem>.png``.
4. Fusion: every panorama's points are kept where the nearest other panoramas agree, voxel down-sampled per
   panorama (bounded memory), then merged, cleaned (statistical outliers), given normals and written to
   ``dense.ply``; ``dense_preview.png`` renders it.

``evaluate_dense`` (used by ``fullview eval``) scores the range maps and the cloud against ground-truth depth.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.artifacts import load_npz, load_ply, save_json, save_npz, save_ply
from fullview.io.config import ConfigError
from fullview.io.dataset import Dataset
from fullview.io.render import colorize_range, render_point_cloud, save_png
from fullview.io.store import EPIPOLES_VERSION, SPARSE_VERSION, load_poses
from fullview.io.workspace import Workspace
from fullview.sfm import dense
from fullview.sfm.dense_metrics import dense_metrics, voxel_downsample
from fullview.sfm.metrics import Similarity, umeyama

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("triangulation",)
INPUTS = ("images",)
DEPTH_VERSION = 1  # format of depth/<stem>.npz: range (H, W) float32 (NaN invalid), valid (H, W) bool
DEFAULT_VOXEL_SHARE = 0.002  # voxel size = this share of the scene size when densify.voxel_size is 0
SCENE_PERCENTILES = (1.0, 99.0)  # sparse points outside these percentiles do not count for the scene size


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    t_start = time.perf_counter()
    poses, _ = load_poses(ws)
    sparse = load_npz(ws.sparse_path(), SPARSE_VERSION, ("points", "track_ids", "image_ids"))
    names = dataset.image_names
    R, t, centers = poses["R_cam_from_world"], poses["t_cam_from_world"], poses["centers"]
    registered = poses["registered"].astype(bool)
    near, median_depth = camera_depths(centers, sparse, config["min_depth_percentile"])
    pairs = _stereo_pairs(ws, centers, registered, median_depth, config)
    if not len(pairs):
        raise ConfigError(f"densify: no stereo pair satisfies the selection ({len(names)} images, "
                           f"{int(registered.sum())} registered); lower densify.min_triangulation_angle_deg "
                           "or densify.min_pair_inliers")
    cams = sorted(set(pairs.ravel().tolist()))
    width = config["working_width"] or dataset.image_sizes[names[cams[0]]][0]
    log.info("densify: %d stereo pairs over %d panoramas at %dx%d: %s", len(pairs), len(cams), width, width // 2,
             ", ".join(f"{i}-{j}" for i, j in pairs))
    images = {k: dataset.load_image(names[k], width=width) for k in cams}
    maps, pair_log = _range_maps(config, names, images, R, t, near, pairs, ws.depth_dir(out_dir))
    points, colors, normals, voxel = _fuse(config, images, maps, R, t, centers, sparse)
    save_ply(ws.dense_ply_path(out_dir), points, colors, normals)
    if config["preview"] and len(points) >= 3:
        render_point_cloud(out_dir / "dense_preview.png", points, colors, normals=normals, up=scene_up(R[cams]),
                           cameras=centers[cams], title=f"{dataset.name}: {len(points)} points")
    summary = {
        "pairs": int(len(pairs)), "panoramas": len(maps), "points": int(len(points)), "voxel_size": voxel,
        "median_pair_time_s": float(np.median([p["time_s"] for p in pair_log])),
        "valid_share": {names[k]: float(np.mean(m[1])) for k, m in maps.items()},
        "pair_log": pair_log, "wall_time_s": round(time.perf_counter() - t_start, 2),
    }
    save_json(out_dir / "summary.json", summary)
    return summary


# ------------------------------------------------------------------------------------------------ pairs and depth
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


def _stereo_pairs(ws: Workspace, centers, registered, median_depth, config) -> np.ndarray:
    """(M, 2) global camera indices (i < j) of the stereo pairs among the registered cameras."""
    epi = load_npz(ws.epipoles_path(), EPIPOLES_VERSION, ("pairs", "num_inliers", "valid"))
    n = len(centers)
    inliers = np.zeros((n, n))
    ok = epi["valid"].astype(bool)
    i, j = epi["pairs"][ok].T
    inliers[i, j] = inliers[j, i] = epi["num_inliers"][ok]
    idx = np.flatnonzero(registered)
    depths = median_depth[idx]
    if np.isfinite(depths).any():
        depths = np.where(np.isfinite(depths), depths, np.nanmedian(depths))
    pairs = dense.select_stereo_pairs(
        centers[idx], inliers[np.ix_(idx, idx)], k=config["neighbours"],
        min_triangulation_angle_deg=config["min_triangulation_angle_deg"],
        max_triangulation_angle_deg=config["max_triangulation_angle_deg"], min_inliers=config["min_pair_inliers"],
        scene_depths=depths if np.isfinite(depths).all() else None)
    return idx[pairs] if len(pairs) else np.zeros((0, 2), np.intp)


def _sgbm_params(config: dict) -> dense.SgbmParams:
    return dense.SgbmParams(block_size=config["block_size"], min_texture_std=config["min_texture_std"])


def pair_min_depth_ratio(near_i: float, near_j: float, baseline: float, factor: float,
                         max_disparity_deg: float) -> float:
    """Nearest plausible depth over the baseline (``dense.disparity_search_range``'s argument): the nearer of the
    two cameras' low-percentile sparse depths times ``factor``, bounded so the search spans at most
    ``max_disparity_deg``."""
    near = np.nanmin([near_i, near_j]) if np.isfinite([near_i, near_j]).any() else baseline
    return max(factor * float(near) / baseline, 1.0 / np.sin(np.radians(min(max_disparity_deg, 90.0))))


def _range_maps(config, names, images, R, t, near, pairs, depth_dir: Path):
    """Densify every pair; combine and save each panorama's estimates as soon as its last pair is done.

    Returns ({camera: (range float32 NaN-invalid, valid bool)}, per-pair log)."""
    remaining = {k: int(np.sum(pairs == k)) for k in np.unique(pairs)}
    estimates: dict[int, list[np.ndarray]] = {k: [] for k in remaining}
    maps, pair_log = {}, []
    params = _sgbm_params(config)
    for i, j in tqdm(pairs, desc="densify", unit="pair"):
        baseline = float(np.linalg.norm(dense.camera_center(R[i], t[i]) - dense.camera_center(R[j], t[j])))
        ratio = pair_min_depth_ratio(near[i], near[j], baseline, config["min_depth_factor"],
                                     config["max_disparity_deg"])
        t0 = time.perf_counter()
        res = dense.densify_pair(images[i], images[j], R[i], t[i], R[j], t[j], rect_height=config["rect_height"],
                                 out_width=images[i].shape[1], min_depth_ratio=ratio,
                                 min_epipole_angle_deg=config["epipole_margin_deg"], params=params)
        elapsed = time.perf_counter() - t0
        kept = {}
        for cam, other, rng in ((i, j, res.range_i), (j, i, res.range_j)):
            err = range_error_per_pixel(rng, R[cam], dense.camera_center(R[cam], t[cam]),
                                        dense.camera_center(R[other], t[other]), np.pi / config["rect_height"])
            with np.errstate(invalid="ignore"):
                rng[~(err <= config["max_range_error_per_px"])] = np.nan
            kept[cam] = float(np.isfinite(rng).mean())
        pair_log.append({"pair": [names[i], names[j]], "baseline": baseline, "min_depth_ratio": ratio,
                         "num_disparities": dense.disparity_search_range(config["rect_height"], ratio),
                         "valid_i": float(res.valid_i.mean()), "valid_j": float(res.valid_j.mean()),
                         "well_conditioned_i": kept[i], "well_conditioned_j": kept[j],
                         "time_s": round(elapsed, 3), "timings_s": {k: round(v, 3) for k, v in res.timings.items()}})
        log.info("pair %s-%s: baseline %.3f, depth ratio %.2f, valid %.0f%% / %.0f%% (well conditioned %.0f%% / "
                 "%.0f%%), %.1f s", names[i], names[j], baseline, ratio, 100 * res.valid_i.mean(),
                 100 * res.valid_j.mean(), 100 * kept[i], 100 * kept[j], elapsed)
        for cam, rng in ((i, res.range_i), (j, res.range_j)):
            estimates[cam].append(rng)
            remaining[cam] -= 1
            if remaining[cam] == 0:
                combined = combine_range_estimates(estimates.pop(cam), config["combine_tolerance"])
                combined = mask_below_latitude(*combined, config["min_latitude_deg"])
                _save_depth(depth_dir, names[cam], *combined)
                maps[cam] = combined
    return maps, pair_log


def range_error_per_pixel(range_map: np.ndarray, R_cam_from_world: np.ndarray, center: np.ndarray,
                          other_center: np.ndarray, pixel_angle: float) -> np.ndarray:
    """Relative range error caused by one rectified pixel (``pixel_angle`` rad) of disparity error, per pixel of a
    camera's equirectangular range map from the pair with the camera at ``other_center``.

    With r = |O_i P|, r_j = |O_j P|, baseline T and θ the angle at O_i between the baseline and the ray, the law of
    sines r = T sin(θ + d) / sin(d) gives |∂r/∂d| / r = r_j² / (r T sin θ): large near the epipoles and for distant
    points. NaN where the range is invalid."""
    height, width = range_map.shape
    baseline = np.asarray(other_center, np.float64) - np.asarray(center, np.float64)
    T = float(np.linalg.norm(baseline))
    e = (np.asarray(R_cam_from_world, np.float64) @ baseline / T).astype(np.float32)  # epipole, camera frame
    lon = (2 * np.pi * ((np.arange(width) + 0.5) / width - 0.5)).astype(np.float32)
    lat = (np.pi * (0.5 - (np.arange(height) + 0.5) / height)).astype(np.float32)
    cos_theta = (np.cos(lat)[:, None] * (np.sin(lon) * e[0] + np.cos(lon) * e[2])[None, :]
                 - np.sin(lat)[:, None] * e[1])
    sin_theta = np.sqrt(np.maximum(1.0 - cos_theta**2, 1e-12))
    r = np.asarray(range_map, np.float32)
    r_j_sq = r * r + T * T - 2.0 * T * r * cos_theta
    with np.errstate(invalid="ignore", divide="ignore"):
        return (r_j_sq * np.float32(pixel_angle) / (r * np.float32(T) * sin_theta)).astype(np.float32)


def combine_range_estimates(estimates: list[np.ndarray], rel_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """One range map from a panorama's pair estimates (each (H, W), NaN invalid).

    Where one pair has a range it is kept; where several have, the median is taken and the estimates within
    ``rel_tol`` (relative) of it are averaged, and the pixel is dropped unless at least two agree (two conflicting
    estimates cannot say which is right). Returns (range float32 NaN-invalid, valid bool)."""
    if not estimates:
        raise ValueError("combine_range_estimates needs at least one estimate")
    if len(estimates) == 1:
        rng = np.asarray(estimates[0], np.float32)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(rng) & (rng > 0)
        return np.where(valid, rng, np.nan).astype(np.float32), valid
    stack = np.sort(np.stack(estimates).astype(np.float32), axis=0)  # NaN sorts last
    count = np.isfinite(stack).sum(0)
    lo = np.take_along_axis(stack, np.maximum((count - 1) // 2, 0)[None], 0)[0]
    hi = np.take_along_axis(stack, np.maximum(count // 2, 0)[None], 0)[0]
    median = 0.5 * (lo + hi)
    with np.errstate(invalid="ignore"):
        agree = np.abs(stack - median) <= rel_tol * median
    n_agree = agree.sum(0)
    mean = np.where(agree, stack, 0).sum(0) / np.maximum(n_agree, 1)
    valid = ((count == 1) | (n_agree >= 2)) & (count > 0)
    out = np.where(count == 1, stack[0], mean)
    valid &= np.isfinite(out) & (out > 0)
    return np.where(valid, out, np.nan).astype(np.float32), valid


def mask_below_latitude(rng: np.ndarray, valid: np.ndarray, min_latitude_deg: float):
    """Invalidate the rows of an equirectangular map whose centre latitude is below ``min_latitude_deg``."""
    if min_latitude_deg <= -90.0:
        return rng, valid
    height = rng.shape[0]
    lat = 90.0 - (np.arange(height) + 0.5) * 180.0 / height
    below = (lat < min_latitude_deg)[:, None]
    return np.where(below, np.nan, rng).astype(np.float32), valid & ~below


def _save_depth(depth_dir: Path, name: str, rng: np.ndarray, valid: np.ndarray) -> None:
    stem = Path(name).stem
    save_npz(depth_dir / f"{stem}.npz", DEPTH_VERSION, range=rng, valid=valid)
    save_png(depth_dir / f"{stem}.png", colorize_range(rng, valid))


def load_depth(ws: Workspace, name: str) -> dict[str, np.ndarray] | None:
    """A panorama's saved range map (``range``, ``valid``), or None if it has none."""
    path = ws.depth_dir() / f"{Path(name).stem}.npz"
    return load_npz(path, DEPTH_VERSION, ("range", "valid")) if path.exists() else None


# ------------------------------------------------------------------------------------------------ fusion
def scene_size(centers: np.ndarray, points: np.ndarray) -> float:
    """Diagonal of the box around the camera centres and the sparse points (outer 1 % trimmed per axis)."""
    pts = centers if not len(points) else np.vstack([centers, points])
    lo, hi = np.percentile(pts, SCENE_PERCENTILES, axis=0)
    return float(np.linalg.norm(np.maximum(hi, centers.max(0)) - np.minimum(lo, centers.min(0))))


def scene_up(R_cam_from_world: np.ndarray) -> np.ndarray:
    """Mean 'up' (−y) axis of the cameras in world coordinates (panoramas are taken roughly level)."""
    down = np.asarray(R_cam_from_world)[:, 1, :].mean(0)
    return -down / max(np.linalg.norm(down), 1e-12)


def fusion_neighbours(centers: np.ndarray, k: int) -> list[list[int]]:
    """For each camera, the ``k`` nearest others (indices into ``centers``)."""
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")[:, : min(k, len(centers) - 1)]
    return [row.tolist() for row in order]


def _fuse(config, images, maps, R, t, centers, sparse):
    """Consistency-checked, voxel-merged, cleaned cloud: (points, RGB colours, normals, voxel size)."""
    cams = sorted(maps)
    voxel = config["voxel_size"] or DEFAULT_VOXEL_SHARE * scene_size(centers[cams], sparse["points"])
    ranges = [maps[k][0] for k in cams]
    rgb = [images[k][..., ::-1] for k in cams]
    neighbours = fusion_neighbours(centers[cams], config["fusion_views"])
    parts, part_cols, raw = [], [], 0
    for v in tqdm(range(len(cams)), desc="fusion", unit="pano"):
        pts, cols = dense.fuse_depth_maps(ranges, rgb, R[cams], t[cams], min_consistent=config["min_consistent"],
                                          rel_tol=config["consistency_tolerance"], stride=config["fusion_stride"],
                                          neighbors=neighbours, views=[v])
        raw += len(pts)
        pts, cols = voxel_downsample(pts, voxel, cols)
        parts.append(pts)
        part_cols.append(cols)
    points, colors = voxel_downsample(np.concatenate(parts), voxel, np.concatenate(part_cols))
    log.info("fusion: %d consistent points, %d after voxel merging (voxel %.4g)", raw, len(points), voxel)
    points, colors, normals = dense.clean_point_cloud(
        points, colors, voxel_size=0.0, nb_neighbors=config["outlier_neighbours"],
        std_ratio=config["outlier_std_ratio"], normal_radius=3.0 * voxel, viewpoint=centers[cams].mean(0))
    return points, colors, normals, float(voxel)


# ------------------------------------------------------------------------------------------------ evaluation
def evaluate_dense(dataset: Dataset, ws: Workspace, est: dict, R_gt_cam_from_world: np.ndarray,
                   c_gt: np.ndarray) -> dict | None:
    """Dense metrics of the workspace's densify results against the dataset's ground-truth depth (None when either
    is missing or fewer than 3 cameras are registered). The reconstruction is aligned by the similarity of its
    camera centres onto the true ones (as for the pose metrics)."""
    names = dataset.image_names
    gt = [dataset.ground_truth_depth(n) for n in names]
    registered = est["registered"].astype(bool)
    manifest = ws.read_manifest("densify")
    if manifest is None or any(g is None for g in gt) or registered.sum() < 3:
        return None
    sim: Similarity = umeyama(est["centers"][registered], c_gt[registered])
    depth = [load_depth(ws, n) if registered[k] else None for k, n in enumerate(names)]
    missing = {"range": np.full((1, 2), np.nan, np.float32), "valid": np.zeros((1, 2), bool)}
    depth = [d if d is not None else missing for d in depth]  # no range map: nothing of it is valid
    ply = ws.dense_ply_path()
    cloud = load_ply(ply) if ply.exists() else None
    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]) if cloud is not None else None
    t_gt = -np.einsum("nab,nb->na", R_gt_cam_from_world, c_gt)
    out = dense_metrics(range_est=[d["range"] for d in depth], valid_est=[d["valid"] for d in depth], range_gt=gt,
                        R_gt_cam_from_world=R_gt_cam_from_world, t_gt_cam_from_world=t_gt, sim=sim, points=points,
                        scene_size=_gt_scene_size(dataset, c_gt), names=names)
    out["median_pair_time_s"] = manifest.get("summary", {}).get("median_pair_time_s")
    out["stage_wall_time_s"] = manifest.get("wall_time_s")
    return out


def _gt_scene_size(dataset: Dataset, c_gt: np.ndarray) -> float:
    """``scene_size`` from ground_truth/scene.npz (synthetic scenes), else the extent of the true camera centres."""
    path = dataset.ground_truth_dir / "scene.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as data:
            if "scene_size" in data:
                return float(data["scene_size"])
    return float(np.linalg.norm(c_gt.max(0) - c_gt.min(0)))
