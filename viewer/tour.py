"""The tour's geometry, from the model: each camera's floor and ceiling, which neighbours it sees, and its hotspots
(on the floor below each visible neighbour, sized by distance, never overlapping); the 3-D scene's robust bounds and
a spatially uniform order of a cloud. Pure numpy: the workspace is read by viewer/scene.py.

Frames: world (the model's), camera (x_cam = R_cam_from_world (x_world - centre)); `up` is the model's up (the
cameras' mean up, sfm.camera.camera_up). Distances are in model units.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from fullview.sfm.camera import bearings_to_lonlat, bearings_to_pixels, pixel_grid_bearings

CONE_DEG = 30.0  # floor (ceiling): the depth within this angle of the nadir (zenith) of a panorama
CONE_MIN_SHARE = 0.05  # ... when at least this share of the cone's pixels has a depth, else the points below it
CONE_MIN_POINTS = 20  # points (sparse or dense) in the cone needed for a floor from points
WINDOW_STEPS = (1, 2, 4, 8)  # visibility: depth pixels within this many pixels of a neighbour's direction (3x3 first)
DEFAULT_WIDTH = 512  # ... pixel size of the windows without a depth map (0.7°)
POINTS_IN_CONE = 3  # ... without depth there, this many points in a cone as wide (the nearest 10% decide)
HOTSPOT_RADIUS = 0.15  # a hotspot is a floor disc of this share of the median camera height (0.22 m at 1.5 m)
MIN_RADIUS_DEG = 2.0  # never smaller than this angle (a 1000-px high view at 90° shows it 25 px wide)
MAX_RADIUS_DEG = 12.0  # never larger than this (a neighbour right next to the camera)
SHRINK_LIMIT = 0.5  # a hotspot crowded by nearer ones is shrunk to no less than this share of its size by distance
GAP = 1.02  # two hotspots' discs keep this factor of their radii apart (rounding of the page's pixels)
MEASURE_WINDOW_PX = 2  # a measured point's range: the valid depth within this many depth-map pixels (a 5x5 window)
BOUNDS_PERCENTILES = (2.0, 98.0)  # the 3-D view's bounds: these percentiles of the points per axis
READABLE_CELLS = 128  # the point budget never drops below one point per occupied cell of (bounds extent / this)
ORDER_LEVELS = 14  # spatial order: one representative per voxel of extent / 2^L, L = 0 .. ORDER_LEVELS - 1


def cone_extent(rng: np.ndarray, valid: np.ndarray, axis_cam: np.ndarray) -> float | None:
    """Median distance along `axis_cam` (a unit camera-frame direction: down for the floor, up for the ceiling) of
    the depth within CONE_DEG of it, or None when too little of the cone has depth."""
    H, W = rng.shape
    along = _grid(W, H) @ axis_cam.astype(np.float32)
    cone = along > np.cos(np.radians(CONE_DEG))
    ok = cone & valid.reshape(-1) & np.isfinite(rng.reshape(-1)) & (rng.reshape(-1) > 0)
    if ok.sum() < max(CONE_MIN_SHARE * cone.sum(), 1):
        return None
    return float(np.median(rng.reshape(-1)[ok] * along[ok]))


@lru_cache(maxsize=4)
def _grid(W: int, H: int) -> np.ndarray:
    return pixel_grid_bearings(W, H, np.float32).reshape(-1, 3)


def points_cone_extent(points: np.ndarray, center: np.ndarray, axis_world: np.ndarray) -> float | None:
    """The same from 3-D points (world): the median distance along `axis_world` of the points within CONE_DEG of
    it seen from `center`, or None with fewer than CONE_MIN_POINTS."""
    if not len(points):
        return None
    d = points - center
    r = np.linalg.norm(d, axis=1)
    along = d @ axis_world
    cone = along > np.cos(np.radians(CONE_DEG)) * np.maximum(r, 1e-12)
    if cone.sum() < CONE_MIN_POINTS:
        return None
    return float(np.median(along[cone]))


def visibility(center: np.ndarray, R: np.ndarray, targets: np.ndarray, depth: dict | None,
               clouds: list[tuple[str, np.ndarray]], own: np.ndarray, tolerance: float
               ) -> list[tuple[bool | None, str, float, float | None]]:
    """Whether each target (world points) is seen from a camera: (True, evidence, window) when the geometry along
    its direction lies beyond it (within `tolerance`, relative), (False, evidence, window) when it stops nearer,
    (None, "", inf, None) when nothing says; `window` is the angular radius of the evidence (radians), the last the
    range the geometry was found at along the direction (None when it came from points beyond). The evidence
    nearest in angle decides: for each window of WINDOW_STEPS pixels (of the depth map's width) around the
    direction, the depth map (the median of its valid ranges there); then points: any cloud's
    point nearer than the target in that cone blocks it (a surface is there), and the camera's `own` points (sparse
    points it observed) beyond it see it. Points of other cameras beyond it prove nothing (a plain wall between
    holds no point but hides what they saw)."""
    rel = (targets - center) @ R.T
    dist = np.linalg.norm(rel, axis=1)
    b = rel / np.maximum(dist, 1e-12)[:, None]
    width = depth["range"].shape[1] if depth is not None else DEFAULT_WIDTH
    px = np.floor(bearings_to_pixels(b, width, width // 2)).astype(int)

    widest = np.cos((WINDOW_STEPS[-1] + 0.5) * 2 * np.pi / width)

    def rays(points):
        """(cosine to each target (N, T), range) of the points inside the widest cone of some target."""
        prel = (points - center.astype(points.dtype)) @ R.T.astype(points.dtype)  # float32 clouds: 5x faster
        pr = np.sqrt((prel * prel).sum(axis=1))
        cos = (prel @ b.T.astype(points.dtype)) / np.maximum(pr, 1e-12)[:, None]
        keep = (cos > widest).any(axis=1)
        return cos[keep], pr[keep]

    blockers = [(kind, *rays(points)) for kind, points in clouds if len(points)]
    own_cos, own_r = rays(own)
    out: list[tuple[bool | None, str, float, float | None]] = []
    for t, (x, y) in enumerate(px):
        answer: tuple[bool | None, str] = (None, "")
        window_rad, found = np.inf, None
        for step in WINDOW_STEPS:
            if depth is not None:
                H, W = depth["range"].shape
                ys = np.clip(np.arange(y - step, y + step + 1), 0, H - 1)
                xs = np.arange(x - step, x + step + 1) % W
                window, ok = depth["range"][np.ix_(ys, xs)], depth["valid"][np.ix_(ys, xs)]
                if ok.any():
                    seen = found = float(np.median(window[ok]))  # the depth map decides where it has depth
                    answer = (bool(seen >= dist[t] * (1 - tolerance)),
                              f"depth ({2 * step + 1} px window): {seen:.3g} along the way to {dist[t]:.3g}")
            cos = np.cos((step + 0.5) * 2 * np.pi / width)
            for kind, pc, pr in blockers if answer[0] is None else []:
                near = (pc[:, t] > cos) & (pr < dist[t] * (1 - tolerance))
                if near.sum() >= POINTS_IN_CONE:
                    answer = (False, f"{near.sum()} {kind} points ({2 * step + 1} px cone) nearer than "
                                     f"{dist[t]:.3g}, from {pr[near].min():.3g}")
                    break
            if answer[0] is None:
                beyond = (own_cos[:, t] > cos) & (own_r >= dist[t] * (1 - tolerance))
                if beyond.sum() >= POINTS_IN_CONE:
                    answer = (True, f"{beyond.sum()} points it observed ({2 * step + 1} px cone) beyond "
                                    f"{dist[t]:.3g}, from {own_r[beyond].min():.3g}")
            if answer[0] is not None:
                break
        if answer[0] is not None:
            window_rad = (step + 0.5) * 2 * np.pi / width
        out.append((*answer, float(window_rad), found))
    return out


def mutual(ab: tuple, ba: tuple) -> tuple[bool | None, str, float | None]:
    """The segment between two cameras seen from both ends (`visibility` answers of a towards b and b towards a):
    the evidence of the narrower window decides (a doorway's frame fills a wide window around a free line of
    sight); a tie with a disagreement is not seen. Also the range of the geometry beyond b seen from a (None when
    the other end decided or no depth gave it)."""
    (va, ea, wa, ra), (vb, eb, wb, _) = ab, ba
    if vb is None or (va is not None and (wa < wb or (wa == wb and not va))):
        return va, ea, ra
    return vb, f"from the other end: {eb}", None


def place_hotspots(candidates: list[dict], radius_world: float) -> tuple[list[dict], list[dict]]:
    """Hotspots from the visible candidates ({"name", "bearing" (unit, camera frame, towards the floor point),
    "distance" (to the floor point)}): nearest first, each a disc of angular radius atan(radius_world / distance)
    clamped to [MIN_RADIUS_DEG, MAX_RADIUS_DEG], shrunk to clear the nearer ones already placed; one that cannot
    clear them at SHRINK_LIMIT of its size (nor at MIN_RADIUS_DEG) is left out, named with the nearer hotspot in its
    way (you walk there first): sizes keep saying distance.
    Returns (hotspots with "radius" in radians, left out with "behind")."""
    lo, hi = np.radians(MIN_RADIUS_DEG), np.radians(MAX_RADIUS_DEG)
    placed: list[dict] = []
    left: list[dict] = []
    for c in sorted(candidates, key=lambda c: c["distance"]):
        radius = float(np.clip(np.arctan2(radius_world, c["distance"]), lo, hi))
        smallest = max(lo, SHRINK_LIMIT * radius)
        blocker = None
        for p in placed:
            sep = float(np.arccos(np.clip(np.dot(p["bearing"], c["bearing"]), -1, 1)))
            room = sep / GAP - p["radius"]
            if room < radius:
                radius = room
                blocker = p
        if radius < smallest:
            left.append({"name": c["name"], "behind": blocker["name"]})
            continue
        lon, lat = bearings_to_lonlat(np.asarray(c["bearing"]))
        placed.append({**c, "radius": radius, "yaw": float(lon), "pitch": float(lat)})
    return placed, left


def range_at(depth: dict, bearing: np.ndarray, relative_sigma: float) -> tuple[float, float] | None:
    """The range along a camera-frame bearing and its standard error: the median of the valid depth within
    MEASURE_WINDOW_PX of its pixel, the error the larger of the window's robust spread (1.4826 MAD: a window across
    an edge mixes surfaces) and `relative_sigma` of the range; None when the window holds no valid depth."""
    rng, valid = depth["range"], depth["valid"]
    H, W = rng.shape
    x, y = np.floor(bearings_to_pixels(bearing[None], W, H)[0]).astype(int)
    ys = np.clip(np.arange(y - MEASURE_WINDOW_PX, y + MEASURE_WINDOW_PX + 1), 0, H - 1)
    xs = np.arange(x - MEASURE_WINDOW_PX, x + MEASURE_WINDOW_PX + 1) % W
    values = rng[np.ix_(ys, xs)][valid[np.ix_(ys, xs)]]
    if not len(values):
        return None
    r = float(np.median(values))
    return r, max(1.4826 * float(np.median(np.abs(values - r))), relative_sigma * r)


def distance_between(points: np.ndarray, rays: np.ndarray, sigmas: np.ndarray) -> tuple[float, float]:
    """Distance between two points (world) found along unit rays (world) with range errors `sigmas`, and its
    standard error (first order: d distance / d range_i = ±(A − B)·ray_i / distance)."""
    diff = points[0] - points[1]
    d = float(np.linalg.norm(diff))
    if d == 0:
        return 0.0, float(np.hypot(*sigmas))
    j = np.array([diff @ rays[0], -diff @ rays[1]]) / d
    return d, float(np.hypot(j[0] * sigmas[0], j[1] * sigmas[1]))


def robust_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(low, high) corners of the BOUNDS_PERCENTILES of the points per axis (a few stray points do not widen it)."""
    if len(points) < 2:
        return None
    lo, hi = np.percentile(points, BOUNDS_PERCENTILES, axis=0)
    return lo, hi


def spatial_order(points: np.ndarray, seed: int) -> tuple[np.ndarray, int]:
    """An order of the points in which every prefix is spread uniformly over space, and the readable budget.

    Coarse to fine: one random representative per occupied voxel of extent / 2^L for L = 0, 1, ... (nested: the
    first point of a voxel in a fixed random order is also the first of its sub-voxel), then the rest at random.
    The readable budget is the prefix that gives every occupied cell of extent / READABLE_CELLS a point."""
    n = len(points)
    perm = np.random.default_rng(seed).permutation(n)
    if n < 2:
        return perm, n
    p = points[perm]
    lo, hi = p.min(0), p.max(0)
    extent = float(np.max(hi - lo)) or 1.0
    level = np.full(n, ORDER_LEVELS, np.int64)
    readable = n
    for L in range(ORDER_LEVELS):
        cells = np.minimum(np.floor((p - lo) / (extent / 2 ** L)).astype(np.int64), 2 ** L - 1)
        key = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]  # 2^L <= 2^20 cells per axis
        _, first = np.unique(key, return_index=True)
        new = first[level[first] > L]
        level[new] = L
        if 2 ** L >= READABLE_CELLS and readable == n:
            readable = int((level <= L).sum())
    order = np.lexsort((np.arange(n), level))  # by level, then the random order
    return perm[order], readable
