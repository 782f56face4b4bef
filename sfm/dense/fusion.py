"""Fusion of per-panorama range maps into one point cloud: multi-view consistency, cleaning, normals.

A back-projected pixel is kept where enough neighbouring views (``fusion_neighbours``) see a surface at the same range;
``clean_point_cloud`` then removes statistical outliers and estimates normals with open3d.
"""

from __future__ import annotations

import logging
from typing import Sequence

import numpy as np

from fullview.sfm.options import DensifyOptions

from fullview.sfm.camera import bearings_to_pixels, pixels_to_bearings
from fullview.sfm.dense.depth import sample_edge_aware
from fullview.sfm.open3d_module import open3d

log = logging.getLogger(__name__)


def _pixel_centers(height: int, width: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of a strided pixel grid."""
    rows, cols = np.mgrid[0:height:stride, 0:width:stride]
    return rows.ravel(), cols.ravel()


def _valid_range(values: np.ndarray) -> np.ndarray:
    """Finite and positive."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(values) & (values > 0)


def _sample_colors(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N, 3) uint8 colours of ``image`` at range-map pixels (rows, cols) of a map of ``shape`` (nearest)."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    img = np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img[..., :3]
    if img.dtype != np.uint8:
        img = np.clip(img * (255.0 if img.dtype.kind == "f" and img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    y = np.minimum(((rows + 0.5) * img.shape[0] / shape[0]).astype(np.intp), img.shape[0] - 1)
    x = np.minimum(((cols + 0.5) * img.shape[1] / shape[1]).astype(np.intp), img.shape[1] - 1)
    return img[y, x]


def _support(
    points: np.ndarray, range_map: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
    rel_tol: float,
) -> np.ndarray:
    """Whether each world point agrees (relative range difference ≤ rel_tol) with another view's range map, read
    with the edge-aware bilinear sampler at the point's projection."""
    x_cam = points @ R_cam_from_world.T + t_cam_from_world
    r_pred = np.linalg.norm(x_cam, axis=1)
    height, width = range_map.shape
    pix = bearings_to_pixels(x_cam, width, height)
    observed = sample_edge_aware(range_map, pix[:, 0], pix[:, 1], max(2 * rel_tol, 0.02), wrap_rows=False)
    with np.errstate(invalid="ignore"):
        return _valid_range(observed) & (np.abs(observed - r_pred) <= rel_tol * r_pred)


def fuse_depth_maps(
    range_maps: Sequence[np.ndarray],
    images: Sequence[np.ndarray],
    R_cam_from_world: np.ndarray,
    t_cam_from_world: np.ndarray,
    *,
    min_consistent: int = DensifyOptions.min_consistent,
    rel_tol: float = DensifyOptions.consistency_tolerance,
    stride: int = 1,
    neighbors: Sequence[Sequence[int]] | None = None,
    views: Sequence[int] | None = None,
    return_sources: bool = False,
):
    """Back-project per-panorama range maps to world points and keep the multi-view consistent ones.

    - ``range_maps[k]``: (H_k, W_k) range (distance from the centre) in camera k's equirectangular frame; NaN or
      ≤ 0 is invalid. ``images[k]``: that panorama (any size; grey or 3-channel, colours keep its channel order).
    - A point from view i is kept if at least ``min_consistent`` other views (``neighbors[i]``, default all) have a
      valid range at its projection within ``rel_tol`` (relative) of its predicted range. Views with no valid range
      there neither support nor veto it.
    - ``stride`` subsamples the pixels of every map.
    - ``views``: back-project only these views (default all); every map still supports the others' points. Fusing
      one view at a time bounds the memory to one view's points.
    Returns (points (N, 3) float64, colours (N, 3) uint8[, source view index (N,) int]).
    """
    R_all = np.asarray(R_cam_from_world, dtype=np.float64)
    t_all = np.asarray(t_cam_from_world, dtype=np.float64)
    n_views = len(range_maps)
    if len(images) != n_views or len(R_all) != n_views or len(t_all) != n_views:
        raise ValueError(
            f"range_maps ({n_views}), images ({len(images)}), R_cam_from_world ({len(R_all)}) and "
            f"t_cam_from_world ({len(t_all)}) must have the same length"
        )
    maps = [np.asarray(m, dtype=np.float32) for m in range_maps]
    all_pts, all_cols, all_src = [], [], []
    for i in range(n_views) if views is None else views:
        rmap = maps[i]
        rows, cols = _pixel_centers(*rmap.shape, stride)
        ranges = rmap[rows, cols]
        keep = _valid_range(ranges)
        rows, cols, ranges = rows[keep], cols[keep], ranges[keep]
        pix = np.stack([cols + 0.5, rows + 0.5], axis=1)
        x_cam = pixels_to_bearings(pix, rmap.shape[1], rmap.shape[0]) * ranges[:, None]
        pts = (x_cam - t_all[i]) @ R_all[i]  # world = Rᵀ (x_cam − t)
        count = np.zeros(len(pts), dtype=np.int32)
        others = neighbors[i] if neighbors is not None else range(n_views)
        # only a point still short of min_consistent supports is checked by the next view: a point already kept
        # stays kept whatever the others say, so the kept set is the one counting every view gives
        short = np.arange(len(pts)) if min_consistent > 0 else np.zeros(0, np.intp)
        for k in others:
            if k != i and len(short):
                count[short] += _support(pts[short], maps[k], R_all[k], t_all[k], rel_tol)
                short = short[count[short] < min_consistent]
        ok = count >= min_consistent
        log.debug("fusion: view %d keeps %d / %d points", i, ok.sum(), len(ok))
        all_pts.append(pts[ok])
        all_cols.append(_sample_colors(images[i], rows[ok], cols[ok], rmap.shape))
        all_src.append(np.full(ok.sum(), i, dtype=np.int64))
    points = np.concatenate(all_pts) if all_pts else np.zeros((0, 3))
    colors = np.concatenate(all_cols) if all_cols else np.zeros((0, 3), np.uint8)
    if return_sources:
        return points, colors, (np.concatenate(all_src) if all_src else np.zeros(0, np.int64))
    return points, colors


def pixel_rows_cols(x_cam: np.ndarray, norm: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) intp indices of the equirectangular pixel each (N, 3) camera-frame point falls in, given its
    norm (``np.linalg.norm(x_cam, axis=1)``, > 0): the clipped integer parts of ``camera.bearings_to_pixels``,
    the same operations element for element, without its second norm and its stacked (N, 2) copy."""
    lon = np.arctan2(x_cam[:, 0], x_cam[:, 2])
    lat = np.arcsin(np.clip(-x_cam[:, 1] / norm, -1.0, 1.0))
    x = np.mod((lon / (2.0 * np.pi) + 0.5) * width, width)
    y = (0.5 - lat / np.pi) * height
    return np.clip(y.astype(np.intp), 0, height - 1), np.clip(x.astype(np.intp), 0, width - 1)


def nearest_range_where(points: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                        wanted: np.ndarray) -> np.ndarray:
    """``dense_metrics.splat_nearest`` read only where it is asked: (H·W,) the nearest range of the world
    ``points`` projecting into each pixel of a camera's equirectangular grid where ``wanted`` ((H, W) bool) is
    set, +inf elsewhere. The same values at the wanted pixels (a minimum is exact in any
    order); the points that land elsewhere are never scattered (the stereo check reads a quarter of the pixels)."""
    height, width = wanted.shape
    x_cam = points @ np.asarray(R_cam_from_world).T + t_cam_from_world
    dist = np.linalg.norm(x_cam, axis=1)
    ok = dist > 0
    if not ok.all():
        x_cam, dist = x_cam[ok], dist[ok]
    rows, cols = pixel_rows_cols(x_cam, dist, width, height)
    flat = rows * width + cols
    hit = wanted.ravel()[flat]
    best = np.full(height * width, np.inf)
    np.minimum.at(best, flat[hit], dist[hit])
    return best


def seen_through_single_estimates(
    range_maps: Sequence[np.ndarray], single_partners: Sequence[np.ndarray], cameras: Sequence[int],
    R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, neighbors: Sequence[Sequence[int]], rel_tol: float,
    views: Sequence[int] | None = None, points: Sequence[np.ndarray] | None = None,
) -> list[np.ndarray]:
    """Per view (``views``, default all), (H, W) bool: the stereo ranges to drop, those resting on one pair
    (``single_partners[i] >= 0``, ``depth.single_partner``) that a neighbouring view (``neighbors[i]``) sees clearly
    beyond (its range at the point's nearest pixel exceeds the point's distance by more than ``rel_tol``) while
    no neighbour holds the point within ``rel_tol``. With ``points`` (each view's stereo as world points,
    ``dense_metrics.backproject_range_map``) a neighbour's point on the ray clearly in front of the range also
    rejects it (the range is too far: the ray meets that surface first), unless the neighbour is the partner.

    ``cameras[i]`` is view i's camera id, the id ``single_partners`` name. The partner's own range at the point,
    where it rests on this very pair, is the same disparity read from the other end: it neither confirms nor
    contradicts. A neighbour with a nearer range there says nothing (the point may be hidden from it): only a view
    that looks through the point can reject it, so a range no other view can judge is kept.
    Why: one pair's errors are mostly too far (a matching window straddling the line where two surfaces meet takes
    the far one's disparity) and seldom land on another pair's ranges; every such range also votes against the
    other views' right ranges in what they see."""
    R_all = np.asarray(R_cam_from_world, np.float64)
    t_all = np.asarray(t_cam_from_world, np.float64)
    out = []
    for i in range(len(range_maps)) if views is None else views:
        rmap = np.asarray(range_maps[i], np.float32)
        height, width = rmap.shape
        drop = np.zeros((height, width), bool)
        rows, cols = np.nonzero((np.asarray(single_partners[i]) >= 0) & _valid_range(rmap))
        if len(rows):
            x_cam = pixels_to_bearings(np.stack([cols + 0.5, rows + 0.5], axis=1), width, height) \
                * rmap[rows, cols, None].astype(np.float64)
            confirmed, beyond = _independent_votes((x_cam - t_all[i]) @ R_all[i], single_partners[i][rows, cols],
                                                   cameras[i], range_maps, single_partners, cameras, R_all, t_all,
                                                   neighbors[i], rel_tol)
            if points is not None:
                r_own = rmap[rows, cols]
                wanted = np.zeros((height, width), bool)
                wanted[rows, cols] = True
                for k in neighbors[i]:
                    if k != i:
                        nearest = nearest_range_where(points[k], R_all[i], t_all[i], wanted)
                        beyond += (nearest[rows * width + cols] < (1 - rel_tol) * r_own) \
                            & (single_partners[i][rows, cols] != cameras[k])
            bad = (beyond > 0) & (confirmed == 0)
            drop[rows[bad], cols[bad]] = True
        out.append(drop)
    return out


def _independent_votes(points: np.ndarray, partner: np.ndarray, camera: int, range_maps, single_partners,
                       cameras, R_all, t_all, neighbors: Sequence[int], rel_tol: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(confirming, seeing-through) neighbour counts (N,) of world points from one view (camera id ``camera``)
    whose ranges rest on the pair with ``partner`` (N,): a neighbour's range within ``rel_tol`` of the point's
    distance confirms it, one beyond it sees through it, read at the nearest pixel; the partner's range there that
    rests on this very pair (the same disparity) does neither."""
    confirmed = np.zeros(len(points), np.int32)
    beyond = np.zeros(len(points), np.int32)
    for k in neighbors:
        if cameras[k] == camera:
            continue
        x_k = points @ R_all[k].T + t_all[k]
        r_pred = np.linalg.norm(x_k, axis=1)
        h_k, w_k = np.shape(range_maps[k])
        row, col = pixel_rows_cols(x_k, r_pred, w_k, h_k)
        flat = row * w_k + col  # one gather each from the raveled maps (a 2-D fancy index costs twice as much)
        r_obs = np.ravel(range_maps[k]).take(flat)
        same_pair = (partner == cameras[k]) & (np.ravel(single_partners[k]).take(flat) == camera)
        with np.errstate(invalid="ignore"):
            confirmed += (np.abs(r_obs - r_pred) <= rel_tol * r_pred) & ~same_pair
            beyond += (r_obs > (1 + rel_tol) * r_pred) & ~same_pair
    return confirmed, beyond


def resolve_conflicts(range_maps: Sequence[np.ndarray], single_partners: Sequence[np.ndarray],
                      cameras: Sequence[int], R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                      neighbors: Sequence[Sequence[int]], rel_tol: float, view: int, pixels: np.ndarray,
                      candidates: np.ndarray, partners: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of ``view`` whose pair estimates conflict (``depth.conflicting_estimates``: flat ``pixels`` (N,),
    ``candidates`` (n, N) from the pairs with ``partners`` (n,)) that the neighbouring views settle: the estimate
    the most neighbours confirm (``_independent_votes``, at least one, no tie, none seeing through it) is taken.
    Returns (flat pixel indices, ranges). With collinear cameras the pairs of a panorama look along the same
    epipoles and make different mistakes at the same pixels; a third view tells which one is right."""
    R_all = np.asarray(R_cam_from_world, np.float64)
    t_all = np.asarray(t_cam_from_world, np.float64)
    height, width = np.shape(range_maps[view])
    if not len(pixels):
        return np.zeros(0, np.intp), np.zeros(0, np.float32)
    rows, cols = np.divmod(pixels, width)
    bearings = pixels_to_bearings(np.stack([cols + 0.5, rows + 0.5], axis=1), width, height)
    votes = np.full(candidates.shape, -1, np.int32)
    for m, partner in enumerate(partners):
        has = np.flatnonzero(np.isfinite(candidates[m]))
        points = (bearings[has] * candidates[m, has, None].astype(np.float64) - t_all[view]) @ R_all[view]
        confirmed, beyond = _independent_votes(points, np.full(len(has), partner), cameras[view], range_maps,
                                               single_partners, cameras, R_all, t_all, neighbors[view], rel_tol)
        votes[m, has] = np.where(beyond > 0, 0, confirmed)
    best = np.argmax(votes, axis=0)
    top = np.take_along_axis(votes, best[None], 0)[0]
    unique = (votes == top[None]).sum(0) == 1
    ok = (top >= 1) & unique
    return pixels[ok], candidates[best[ok], np.flatnonzero(ok)].astype(np.float32)


def clean_point_cloud(
    points: np.ndarray,
    colors: np.ndarray,
    *,
    voxel_size: float,
    nb_neighbors: int = DensifyOptions.outlier_neighbours,
    std_ratio: float = DensifyOptions.outlier_std_ratio,
    normal_radius: float | None = None,
    viewpoint: np.ndarray | None = None,
    return_index: bool = False,
):
    """Voxel down-sampling, statistical outlier removal and normal estimation with open3d.

    ``colors`` are uint8 (N, 3) (returned as uint8) or floats in [0, 1] (returned as float64). Normals are estimated
    from neighbours within ``normal_radius`` (default 3 · voxel_size, at most 30) and, if ``viewpoint`` (3,) is given,
    oriented towards it. Returns (points (M, 3), colours (M, 3), normals (M, 3)[, the kept input rows (M,), in
    order: only without down-sampling, ``voxel_size`` 0]).
    """
    o3d = open3d()

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = np.asarray(colors)
    if len(cols) != len(pts):
        raise ValueError(f"colors has {len(cols)} rows but points has {len(pts)}")
    is_u8 = cols.dtype == np.uint8
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(cols.astype(np.float64) / (255.0 if is_u8 else 1.0))
    if return_index and voxel_size > 0:
        raise ValueError("clean_point_cloud: return_index needs voxel_size 0 (a down-sampled point has no input row)")
    if voxel_size > 0:
        pcd = pcd.voxel_down_sample(voxel_size)
    kept = np.arange(len(pcd.points))
    if nb_neighbors > 0 and len(pcd.points) > nb_neighbors:
        pcd, index = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
        kept = np.asarray(index, np.int64)
    radius = normal_radius or 3.0 * voxel_size
    if len(pcd.points) >= 3:
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30) if radius > 0 else (
            o3d.geometry.KDTreeSearchParamKNN(30)
        )
        pcd.estimate_normals(search)
        if viewpoint is not None:
            pcd.orient_normals_towards_camera_location(np.asarray(viewpoint, dtype=np.float64))
    out_cols = np.asarray(pcd.colors)
    out_cols = np.clip(np.rint(out_cols * 255), 0, 255).astype(np.uint8) if is_u8 else out_cols
    normals = np.asarray(pcd.normals) if pcd.has_normals() else np.zeros((len(pcd.points), 3))
    log.info("clean_point_cloud: %d -> %d points", len(pts), len(pcd.points))
    if return_index:
        return np.asarray(pcd.points), out_cols, normals, kept
    return np.asarray(pcd.points), out_cols, normals


def fusion_neighbours(centers: np.ndarray, k: int) -> list[list[int]]:
    """For each camera, the ``k`` nearest others (indices into ``centers``)."""
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")[:, : min(k, len(centers) - 1)]
    return [row.tolist() for row in order]
