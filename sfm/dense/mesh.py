"""A coloured triangle mesh from the dense reconstruction: screened Poisson on the fused cloud, trimmed to what the
views support.

Poisson (open3d) needs oriented normals and closes every hole: it caps openings (doorways, windows, the unseen
nadir), bridges gaps and grows blobs from outliers. Three trims remove what the data does not support:

1. **density**: vertices whose Poisson density (how many samples shaped them) is below a low quantile;
2. **distance**: triangles with a vertex farther than a few voxels from any dense point (invented surface);
3. **visibility**: every triangle centre is projected into every range map (equirectangular, ranges from the
   camera centre). A view *contradicts* the triangle when it sees clearly beyond it along that ray (free space: the
   whole pixel window around the ray is ranged and farther than the triangle) and *supports* it when a ranged pixel
   of the window lies within the relative tolerance of the triangle's distance. A triangle is kept when at least
   one view supports it and no more views contradict than support it; views that see something nearer (occlusion)
   or nothing say nothing.

Vertex colours are the colours of the nearest dense points. Pure numpy / scipy / open3d, no file access; every
step is deterministic (single-threaded Poisson, fixed orders).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, ContextManager, Iterator, Sequence

import cv2
import numpy as np
from scipy.spatial import cKDTree

from fullview.sfm.camera import bearings_to_pixels
from fullview.sfm.open3d_module import open3d

log = logging.getLogger(__name__)

MIN_POISSON_DEPTH, MAX_POISSON_DEPTH = 5, 11  # automatic octree depth bounds (11: ~2 GiB on a large scene)
VIEW_THREADS = 2  # views judged at once (orientation of the normals, visibility trim)
POISSON_SCALE = 1.1  # open3d's default: the octree spans the cloud's box times this


@dataclass(kw_only=True)
class MeshParams:
    depth: int = 0  # Poisson octree depth; 0 = cells about cell_voxels voxels wide
    cell_voxels: float = 4.0  # with depth 0: the octree cells' width in voxels of the cloud
    density_quantile: float = 0.02  # vertices below this quantile of Poisson density are dropped
    max_distance_voxels: float = 3.0  # triangles with a vertex farther than this from a dense point are dropped
    support_tolerance: float = 0.03  # relative range tolerance of a view's support / free-space test
    window_px: int = 3  # pixel window (side) of the visibility tests, absorbs sub-pixel projection and edges
    min_component_triangles: int = 50  # connected pieces with fewer triangles are dropped (noise islands)


@dataclass(kw_only=True)
class Mesh:
    vertices: np.ndarray  # (V, 3) float64, the cloud's frame
    triangles: np.ndarray  # (T, 3) int32 vertex indices, counter-clockwise seen from outside (normals' side)
    vertex_colors: np.ndarray  # (V, 3) uint8 RGB
    stats: dict = field(default_factory=dict)


def mesh_from_dense(points: np.ndarray, colors: np.ndarray, normals: np.ndarray, R_cam_from_world: np.ndarray,
                    t_cam_from_world: np.ndarray, range_maps: Sequence[np.ndarray | None], *, voxel_size: float,
                    params: MeshParams = MeshParams(),
                    poisson: Callable[..., ContextManager] | None = None,
                    observers: np.ndarray | None = None) -> Mesh:
    """The trimmed, coloured Poisson mesh of a fused cloud. ``poisson``: how ``poisson_surface`` is started,
    ``poisson(fn, *args)`` giving a context whose value's ``result()`` is ``fn(*args)`` (the stage's
    ``protocol.forked``: a child process, open3d holds the GIL throughout); by default here, when asked.

    ``points`` / ``colors`` (uint8 RGB) / ``normals`` (N, 3): the fused cloud (the normals' signs do not matter:
    they are turned towards the cameras that see the points; ``observers``: ``nearest_observing_cameras`` of the
    points, when already found); ``R_cam_from_world`` (K, 3, 3), ``t_cam_from_world`` (K, 3) and ``range_maps[k]`` (H, W) ranges
    (NaN or ≤ 0: invalid; None: no map) of the same cameras; ``voxel_size``: the cloud's spacing."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 16:
        raise ValueError(f"a mesh needs at least 16 dense points, got {len(points)}")
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    depth = params.depth or auto_poisson_depth(points, voxel_size, params.cell_voxels)
    normals = orient_normals_to_views(points, normals, R_cam_from_world, t_cam_from_world, range_maps,
                                      tolerance=params.support_tolerance, window_px=params.window_px,
                                      observers=observers)
    with (poisson or _when_asked)(poisson_surface, points, normals, depth) as job:
        tree = cKDTree(points)  # the distance trim's and the colours' nearest points, made while Poisson runs
        vertices, triangles, density = job.result()
    stats = {"poisson_depth": int(depth), "poisson_vertices": int(len(vertices)),
             "poisson_triangles": int(len(triangles))}
    if len(triangles) == 0:
        raise ValueError(f"Poisson reconstruction (depth {depth}) of {len(points)} points gave no surface")
    keep = np.ones(len(triangles), bool)
    low = density < np.quantile(density, params.density_quantile)
    keep &= _drop("density", ~low[triangles].any(1), keep, stats)
    near = _near_points(vertices, tree, params.max_distance_voxels * voxel_size)
    keep &= _drop("distance", near[triangles].all(1), keep, stats)
    supported = np.ones(len(triangles), bool)
    if any(m is not None for m in range_maps):  # without any range map there is nothing to check against
        supported[keep] = view_support(vertices[triangles[keep]].mean(1), R_cam_from_world, t_cam_from_world,
                                       range_maps, tolerance=params.support_tolerance, window_px=params.window_px)
    keep &= _drop("visibility", supported, keep, stats)
    keep &= _drop("small_pieces", _large_components(triangles, keep, params.min_component_triangles), keep, stats)
    vertices, triangles = _compact(vertices, triangles[keep])
    vertex_colors = _nearest_colors(vertices, tree, colors)
    stats.update(vertices=int(len(vertices)), triangles=int(len(triangles)),
                 trimmed_share=float(1.0 - len(triangles) / max(stats["poisson_triangles"], 1)))
    log.info("mesh: Poisson depth %d, %d triangles, %d kept (trimmed: %s)", depth, stats["poisson_triangles"],
             len(triangles), ", ".join(f"{k} {v}" for k, v in stats.items() if k.startswith("trimmed_by_")))
    return Mesh(vertices=vertices, triangles=triangles.astype(np.int32), vertex_colors=vertex_colors, stats=stats)


def auto_poisson_depth(points: np.ndarray, voxel_size: float, cell_voxels: float = 4.0) -> int:
    """Octree depth whose cells are at most ``cell_voxels`` voxels of the cloud wide (more than half that). Four
    (cells of 2-4 voxels, 0.4-0.8% of the scene at the default voxel) keep the mesh within τ = 1% of the surface as
    two did, at a quarter of the Poisson time and of the triangles (README, dmesh); finer only fits noise."""
    extent = float(np.max(points.max(0) - points.min(0))) * POISSON_SCALE
    depth = int(np.ceil(np.log2(max(extent / (cell_voxels * voxel_size), 1.0))))
    return int(np.clip(depth, MIN_POISSON_DEPTH, MAX_POISSON_DEPTH))


def orient_normals_to_views(points: np.ndarray, normals: np.ndarray, R_cam_from_world: np.ndarray,
                            t_cam_from_world: np.ndarray, range_maps: Sequence[np.ndarray | None], *,
                            tolerance: float, window_px: int, observers: np.ndarray | None = None) -> np.ndarray:
    """Normals turned towards the nearest camera that observes each point (its range map ranges it within
    ``tolerance``; ``observers``: those cameras when already found, ``nearest_observing_cameras``), else towards
    the nearest camera. One viewpoint for the whole cloud (what outlier removal
    used) turns the walls between rooms the wrong way, and Poisson then inflates them into closed bubbles."""
    normals = np.asarray(normals, np.float64).reshape(-1, 3).copy()
    centers = -np.einsum("kba,kb->ka", np.asarray(R_cam_from_world, np.float64),
                         np.asarray(t_cam_from_world, np.float64))
    chosen = observers if observers is not None else nearest_observing_cameras(
        points, R_cam_from_world, t_cam_from_world, range_maps, tolerance=tolerance, window_px=window_px)
    towards = np.zeros_like(normals)
    found = chosen >= 0
    towards[found] = centers[chosen[found]] - points[found]
    unseen = ~found
    if unseen.any():
        _, nearest = cKDTree(centers).query(points[unseen])
        towards[unseen] = centers[nearest] - points[unseen]
    flip = np.einsum("na,na->n", normals, towards) < 0
    normals[flip] *= -1
    return normals


def nearest_observing_cameras(points: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                              range_maps: Sequence[np.ndarray | None], *, tolerance: float, window_px: int
                              ) -> np.ndarray:
    """(N,) index of the nearest camera whose range map observes each point (ranges it within ``tolerance`` in
    the pixel window around its ray; equal distances: the lower index), -1 where none does."""
    R = np.asarray(R_cam_from_world, np.float64)
    centers = -np.einsum("kba,kb->ka", R, np.asarray(t_cam_from_world, np.float64))
    views = [k for k, rng in enumerate(range_maps) if rng is not None]
    chosen = np.full(len(points), -1, np.intp)  # the nearest observing camera (-1: none)
    if views:
        dist = np.stack([np.linalg.norm(centers[k] - points, axis=1) for k in views], axis=1)
        # each point asks its cameras nearest first (ties: the lower index) and stops at the first that observes
        # it: the camera a pass over all of them keeps, for about one projection per point instead of one per view
        order = np.argsort(dist, axis=1, kind="stable")
        pending = np.arange(len(points))
        for rank in range(len(views)):
            asked = order[pending, rank]
            groups = [(v, pending[asked == v]) for v in range(len(views))]
            groups = [(v, sub) for v, sub in groups if len(sub)]

            def observed(group: tuple[int, np.ndarray]) -> np.ndarray:
                v, sub = group
                k = views[v]
                idx = _pixel_index(points[sub] @ R[k].T + t_cam_from_world[k], range_maps[k].shape)
                near, far = _window_extremes_at(np.asarray(range_maps[k]), idx, window_px)
                d = dist[sub, v]
                return (near <= d * (1 + tolerance)) & (far >= d * (1 - tolerance))

            for (v, sub), seen in zip(groups, _map_views(observed, groups)):
                chosen[sub[seen]] = views[v]
            pending = pending[chosen[pending] < 0]
            if not len(pending):
                break
    return chosen


def poisson_surface(points: np.ndarray, normals: np.ndarray, depth: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screened Poisson reconstruction (open3d, one thread: reproducible): vertices, triangles, densities."""
    o3d = open3d()  # heavy import, only where a mesh is made

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64).reshape(-1, 3))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=int(depth), scale=POISSON_SCALE, linear_fit=False, n_threads=1)
    return (np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64),
            np.asarray(density, np.float64))


def view_support(centres: np.ndarray, R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray,
                 range_maps: Sequence[np.ndarray | None], *, tolerance: float, window_px: int) -> np.ndarray:
    """(T,) bool: surface points (triangle centres) that some view observes within ``tolerance`` (relative range)
    and that no more views see through than observe them (see the module docstring)."""
    support = np.zeros(len(centres), np.int32)
    contradict = np.zeros(len(centres), np.int32)

    def judged(k: int) -> tuple[np.ndarray, np.ndarray]:
        near, far, through = _window_ranges(np.asarray(range_maps[k]), window_px)
        x_cam = centres @ np.asarray(R_cam_from_world[k], np.float64).T + t_cam_from_world[k]
        dist = np.linalg.norm(x_cam, axis=1)
        idx = _pixel_index(x_cam, range_maps[k].shape)
        return ((near.ravel()[idx] <= dist * (1 + tolerance)) & (far.ravel()[idx] >= dist * (1 - tolerance)),
                through.ravel()[idx] > dist * (1 + tolerance))

    views = [k for k, rng in enumerate(range_maps) if rng is not None] if len(centres) else []
    for supports, contradicts in _map_views(judged, views):
        support += supports
        contradict += contradicts
    return (support > 0) & (contradict <= support)


def _map_views(fn, views: list[int]):
    """``fn`` of each view, in order, two views at a time on local threads (numpy and OpenCV release the GIL)."""
    with ThreadPoolExecutor(max_workers=VIEW_THREADS) as pool:
        yield from pool.map(fn, views)


def _pixel_index(x_cam: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Flat index of the equirectangular pixel (of a map of ``shape``) each camera-frame point projects into."""
    height, width = shape
    pix = bearings_to_pixels(x_cam, width, height)
    cols = np.clip(pix[:, 0].astype(np.int64), 0, width - 1)
    rows = np.clip(pix[:, 1].astype(np.int64), 0, height - 1)
    return rows * width + cols


def _window_ranges(rng: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel over its window (wrapping in longitude): the nearest and the farthest valid range (±inf where
    none), and the nearest range when every pixel of the window is valid (0 otherwise: no free-space claim).
    OpenCV's erosion and dilation (minimum and maximum over the window, the same values as scipy's filters at a
    tenth of the time) on the map padded by wrapping around the seam; rows clamp at the poles."""
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(rng) & (rng > 0)
    pad, kernel = window // 2, np.ones((window, window), np.uint8)

    def extreme(values: np.ndarray, op) -> np.ndarray:
        wrapped = cv2.copyMakeBorder(values, 0, 0, pad, pad, cv2.BORDER_WRAP) if pad else values
        return op(wrapped, kernel, borderType=cv2.BORDER_REPLICATE)[:, pad:pad + values.shape[1]]

    near = extreme(np.where(valid, rng, np.inf), cv2.erode)
    far = extreme(np.where(valid, rng, -np.inf), cv2.dilate)
    through = extreme(np.where(valid, rng, 0.0), cv2.erode)
    return near, far, through


@contextmanager
def _when_asked(fn: Callable[..., Any], *args: Any) -> Iterator[Any]:
    """A job whose ``result()`` is ``fn(*args)``, computed here when asked (``mesh_from_dense``'s default)."""
    yield SimpleNamespace(result=lambda: fn(*args))


def _window_extremes_at(rng: np.ndarray, idx: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """``_window_ranges``' nearest and farthest valid range at the flat pixels ``idx`` only, read off the window's
    pixels (columns wrapping, rows clamped): the same values without filtering every pixel of the map (nor
    holding a view's filtered maps while the points are asked nearest camera first)."""
    height, width = rng.shape
    rows, cols = np.divmod(idx, width)
    flat = rng.ravel()
    near = np.full(len(idx), np.inf, rng.dtype)
    far = np.full(len(idx), -np.inf, rng.dtype)
    pad = window // 2
    for dr in range(-pad, pad + 1):
        base = np.clip(rows + dr, 0, height - 1) * width
        for dc in range(-pad, pad + 1):
            values = flat[base + (cols + dc) % width]
            with np.errstate(invalid="ignore"):
                valid = np.isfinite(values) & (values > 0)
            np.minimum(near, np.where(valid, values, np.inf), out=near)
            np.maximum(far, np.where(valid, values, -np.inf), out=far)
    return near, far


def _near_points(vertices: np.ndarray, tree: cKDTree, radius: float) -> np.ndarray:
    dist, _ = tree.query(vertices, distance_upper_bound=radius)
    return np.isfinite(dist)


def _large_components(triangles: np.ndarray, keep: np.ndarray, min_triangles: int) -> np.ndarray:
    """(T,) bool: kept triangles in edge-connected pieces of at least ``min_triangles`` kept triangles."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    out = np.zeros(len(triangles), bool)
    kept = np.flatnonzero(keep)
    if len(kept) == 0:
        return out
    tri = triangles[kept]
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(kept)), 3)
    _, edge_id = np.unique(edges[:, 0] * (int(triangles.max()) + 1) + edges[:, 1], return_inverse=True)
    # triangles sharing an edge are joined through that edge's node (bipartite triangle-edge graph)
    n = len(kept) + int(edge_id.max()) + 1
    graph = coo_matrix((np.ones(len(owner)), (owner, len(kept) + edge_id)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels[:len(kept)])
    out[kept] = sizes[labels[:len(kept)]] >= min_triangles
    return out


def _drop(reason: str, ok: np.ndarray, keep: np.ndarray, stats: dict) -> np.ndarray:
    stats[f"trimmed_by_{reason}"] = int(np.sum(keep & ~ok))
    return ok


def _compact(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no triangle uses; renumber the triangles (order kept)."""
    used = np.unique(triangles)
    renumber = np.full(len(vertices), -1, np.int64)
    renumber[used] = np.arange(len(used))
    return vertices[used], renumber[triangles].reshape(-1, 3)


def _nearest_colors(vertices: np.ndarray, tree: cKDTree, colors: np.ndarray) -> np.ndarray:
    if len(vertices) == 0:
        return np.zeros((0, 3), np.uint8)
    _, idx = tree.query(vertices)
    return np.asarray(colors, np.uint8).reshape(-1, 3)[idx]
