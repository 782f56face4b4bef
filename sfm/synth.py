"""Synthetic 360° equirectangular scenes with exact ground truth (pure: no file access).

The scene is a textured room (an axis-aligned box seen from inside) with 3-6 furniture-like
axis-aligned boxes standing on its floor. The world frame has y pointing DOWN like the camera
frame (floor at ``y = +FLOOR_Y``, eye height at ``y ≈ 0``), so a level camera has a
``R_world_from_cam`` that is a rotation about y.

Rendering is a vectorised ray cast (slab test against every box) along the bearings of
``fullview.sfm.camera`` (pixel (i, j) looks along the bearing of its centre (j + 0.5, i + 0.5)).
Every face carries its own procedural, world-anchored, non-periodic texture (multi-octave colour
noise, thresholded-noise blobs, random shapes and glyphs, a few target markers on the room faces),
looked up by the 2-D surface coordinates of the hit point from a mip-mapped texture atlas
(trilinear filtering) and the image is supersampled, so detections are stable across views.

Face indexing: face ``6 * k + 2 * axis + side`` is the face of box k (box 0 = room) whose normal
is along ``axis``; side 0 is the plane ``x[axis] = box_min[axis]``, side 1 the max plane.
"""

from __future__ import annotations

import colorsys
import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage
from tqdm import tqdm

from fullview.sfm.camera import bearings_to_pixels, pixels_to_bearings

log = logging.getLogger(__name__)

FLOOR_Y = 1.6  # world y of the floor (m); eye height 1.6 m is at y = 0
EYE_HEIGHT_JITTER = 0.2  # cameras' y is uniform in [-this, +this]
CLEARANCE = 0.6  # minimum horizontal distance from a camera centre to any wall or box (m)
MAX_TILT_DEG = 5.0  # maximum |roll| and |pitch| of a camera
STEP_RANGE = (0.6, 1.6)  # distance from a camera to the previous one in the random walk (m)
MIN_CAMERA_SEPARATION = 0.5  # minimum distance between any two cameras (m)
MAX_SPREAD = 1.8  # preferred maximum distance of a new camera from the centroid of the previous ones (m)
TEXEL_AT_2048 = 0.0075  # texel size (m) used for width-2048 renders (scaled by 2048 / width)
MIP_LEVELS = 7  # texture pyramid levels (level l is 2**l times coarser)
ATLAS_PAD = 2  # replicated border around every atlas tile (texels)
SUPERSAMPLE = 2  # default supersampling factor per axis for the image (depth uses pixel centres)
CHUNK_RAYS = 1 << 17  # rays per vectorised chunk (bounds memory)
RENDER_THREADS = max(1, min(4, os.cpu_count() or 1))  # threads rendering row bands in parallel
MARKERS_PER_ROOM_FACE = 4  # target markers drawn on each room face (hand-point candidates)
MARKER_RADIUS = 0.07  # marker radius (m)

# Per normal axis: the world axes used as texture (u, v) coordinates of that face.
FACE_UV_AXES = np.array([[2, 1], [0, 2], [0, 1]])
# Smooth colour noise octaves: (cell size m, relative amplitude).
NOISE_OCTAVES = ((1.2, 0.22), (0.4, 0.18), (0.13, 0.16), (0.045, 0.14), (0.016, 0.10))
# Thresholded-noise blob layers: noise cell size (m).
BLOB_CELLS = (0.25, 0.08, 0.03)
# Random shape bands: (typical size m, fraction of the face area covered by the band).
SHAPE_BANDS = ((0.45, 0.12), (0.22, 0.15), (0.11, 0.15), (0.055, 0.12), (0.028, 0.08))
GOLDEN_HUE_STEP = 0.381966  # hue increment between consecutive faces (golden-ratio spread)
LIGHT_DIR = np.array([0.35, -1.0, 0.55]) / np.linalg.norm([0.35, -1.0, 0.55])  # towards the light


@dataclass(kw_only=True)
class SynthView:
    name: str  # image file name, e.g. "pano_000.png"
    image: np.ndarray  # (H, W, 3) uint8, BGR (OpenCV order)
    depth: np.ndarray  # (H, W) float32, range (m) from the camera centre along the pixel-centre bearing
    R_world_from_cam: np.ndarray  # (3, 3) rotation, x_world = R_world_from_cam @ x_cam + center
    center: np.ndarray  # (3,) camera centre in world


@dataclass(kw_only=True)
class SceneGeometry:
    boxes: np.ndarray  # (K, 2, 3) axis-aligned boxes (min, max corner); box 0 = room, seen from inside
    texel: float  # texture sample spacing (m) at mip level 0
    atlas: np.ndarray  # (A_h, A_w, 3) uint8 BGR atlas of every face texture at every mip level (shaded)
    tile_offset: np.ndarray  # (L, F, 2) float32 atlas (x, y) of texel (0, 0) of face f at mip level l
    markers: np.ndarray  # (M, 3) world centres of the target markers drawn on the room faces
    marker_names: list[str]  # (M,) names of the markers, e.g. "room_face3_marker1"


@dataclass(kw_only=True)
class SynthScene:
    views: list[SynthView]  # rendered panoramas with their true poses
    hand_points: list[dict]  # [{"name": str, "observations": {image_name: [x, y]}}], each track in >= 2 views
    boxes: np.ndarray  # (K, 2, 3) axis-aligned boxes (min corner, max corner), room included as box 0
    scene_size: float  # diagonal of the room (m), used to normalise errors
    hand_point_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) true point of hand_points[p]
    geometry: SceneGeometry | None = None  # textured geometry, to render further views with render_view


# ----------------------------------------------------------------------------------------------
# ray casting


def cast_rays(origins: np.ndarray, dirs: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest surface hit of rays inside the room.

    ``origins`` (3,) or (N, 3), ``dirs`` (N, 3) unit directions (world), ``boxes`` (K, 2, 3) with the
    room as box 0. Returns ``t`` (N,) float32 distance along the ray (= range for unit dirs) and
    ``face`` (N,) int32 face index (see the module doc). Rays are assumed to start inside the room
    and outside every furniture box; the room interior is hit where the ray exits the room box,
    furniture at its nearest entry point.
    """
    d = np.asarray(dirs, dtype=np.float32)
    o = np.asarray(origins, dtype=np.float32)
    if d.ndim != 2 or d.shape[1] != 3 or o.shape not in ((3,), d.shape):
        raise ValueError(f"dirs must be (N, 3) and origins (3,) or (N, 3), got {d.shape} and {o.shape}")
    comps = [np.ascontiguousarray(d[:, a]) for a in range(3)]
    orig = [o[a] if o.ndim == 1 else np.ascontiguousarray(o[:, a]) for a in range(3)]
    return _cast(orig, comps, np.asarray(boxes, dtype=np.float32))


def _cast(o: list, d: list[np.ndarray], b: np.ndarray, furniture: list[int] | None = None
          ) -> tuple[np.ndarray, np.ndarray]:
    """Slab-test ray cast on per-axis component arrays (see cast_rays); ``furniture``: box indices to test."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = [np.float32(1.0) / c for c in d]
        # room: exit point = smallest per-axis exit distance (+inf for axis-parallel rays)
        t = face = None
        for a in range(3):
            ta = np.maximum((b[0, 0, a] - o[a]) * inv[a], (b[0, 1, a] - o[a]) * inv[a])
            fa = np.where(d[a] > 0, np.int32(2 * a + 1), np.int32(2 * a))
            if t is None:
                t, face = ta, fa
            else:
                m = ta < t
                t, face = np.where(m, ta, t), np.where(m, fa, face)
        # furniture: nearest entry point
        for k in range(1, b.shape[0]) if furniture is None else furniture:
            t1 = [(b[k, 0, a] - o[a]) * inv[a] for a in range(3)]
            t2 = [(b[k, 1, a] - o[a]) * inv[a] for a in range(3)]
            mn = [np.minimum(x, y) for x, y in zip(t1, t2)]
            tfar = np.minimum(np.minimum(np.maximum(t1[0], t2[0]), np.maximum(t1[1], t2[1])),
                              np.maximum(t1[2], t2[2]))
            ax1 = mn[1] > mn[0]
            tnear = np.where(ax1, mn[1], mn[0])
            ax2 = mn[2] > tnear
            tnear = np.where(ax2, mn[2], tnear)
            hit = (tnear <= tfar) & (tnear > 0) & (tnear < t)
            if not hit.any():
                continue
            axis = np.where(ax2, 2, np.where(ax1, 1, 0)).astype(np.int32)
            d_axis = np.where(ax2, d[2], np.where(ax1, d[1], d[0]))
            fk = np.int32(6 * k) + 2 * axis + (d_axis < 0)
            t, face = np.where(hit, tnear, t), np.where(hit, fk, face)
    return t.astype(np.float32, copy=False), face.astype(np.int32, copy=False)


def _lonlat_tables(width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(sin lon, cos lon) per column and (sin lat, cos lat) per row of the pixel centres.

    bearing(i, j) = (cos lat_i sin lon_j, -sin lat_i, cos lat_i cos lon_j), exactly as
    ``camera.pixel_grid_bearings`` (computed with ``camera.pixels_to_bearings`` on the equator row and
    the central meridian column).
    """
    cols = pixels_to_bearings(np.stack([np.arange(width) + 0.5, np.full(width, height / 2)], axis=1), width, height)
    rows = pixels_to_bearings(np.stack([np.full(height, width / 2), np.arange(height) + 0.5], axis=1), width, height)
    return cols[:, 0], cols[:, 2], -rows[:, 1], rows[:, 2]


def _world_dirs(tables: tuple, R: np.ndarray, r0: int, r1: int) -> list[np.ndarray]:
    """World-frame unit ray directions (per-axis float32 arrays) of the pixel centres of rows [r0, r1)."""
    sin_lon, cos_lon, sin_lat, cos_lat = tables
    bx = (cos_lat[r0:r1, None] * sin_lon[None, :]).astype(np.float32).ravel()
    bz = (cos_lat[r0:r1, None] * cos_lon[None, :]).astype(np.float32).ravel()
    by = np.repeat((-sin_lat[r0:r1]).astype(np.float32), len(sin_lon))
    Rf = R.astype(np.float32)
    return [Rf[a, 0] * bx + Rf[a, 1] * by + Rf[a, 2] * bz for a in range(3)]


def _row_chunks(height: int, width: int, multiple: int = 1) -> list[tuple[int, int]]:
    rows = max(multiple, (CHUNK_RAYS // max(width, 1)) // multiple * multiple)
    return [(r, min(r + rows, height)) for r in range(0, height, rows)]


def _shade_samples(geometry: SceneGeometry, origin: np.ndarray, d: list[np.ndarray], t: np.ndarray,
                   face: np.ndarray, pixel_angle: float) -> np.ndarray:
    """(N, 3) float32 BGR colour of hit points, trilinear mip-mapped texture lookup."""
    o = origin.astype(np.float32)
    p = [o[a] + t * d[a] for a in range(3)]
    axis = (face % 6) // 2
    on_x, on_y = axis == 0, axis == 1
    face_u0, face_v0 = _face_uv_origins(geometry.boxes)
    inv_texel = np.float32(1.0 / geometry.texel)
    u = (np.where(on_x, p[2], p[0]) - face_u0.take(face)) * inv_texel
    v = (np.where(on_y, p[2], p[1]) - face_v0.take(face)) * inv_texel
    cos_inc = np.abs(np.where(on_x, d[0], np.where(on_y, d[1], d[2])))
    footprint = t * np.float32(pixel_angle) * inv_texel / np.sqrt(np.maximum(cos_inc, np.float32(1e-3)))
    lam = np.log2(np.maximum(footprint, np.float32(1.0)))
    levels, n_faces = geometry.tile_offset.shape[:2]
    lam = np.minimum(lam, np.float32(levels - 1 - 1e-3))
    l0 = lam.astype(np.int32)
    w = (lam - l0)[:, None]
    off_x, off_y = (np.ascontiguousarray(geometry.tile_offset[..., i].ravel()) for i in range(2))
    samples = []
    for lev in (l0, l0 + 1):
        # tile coordinates stay inside [-0.5, n - 0.5] up to rounding; the tile padding absorbs that
        idx = lev * n_faces + face
        scale = np.ldexp(np.float32(1.0), -lev).astype(np.float32)
        samples.append(_remap_flat(geometry.atlas, u * scale + off_x.take(idx), v * scale + off_y.take(idx)))
    return samples[0] + w * (samples[1] - samples[0])


def _face_uv_origins(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) float32 world u and v coordinates of texel (0, 0) of every face."""
    faces = np.arange(6 * len(boxes))
    axis = (faces % 6) // 2
    lo = boxes[faces // 6, 0]
    return (lo[faces, FACE_UV_AXES[axis, 0]].astype(np.float32),
            lo[faces, FACE_UV_AXES[axis, 1]].astype(np.float32))


def _remap_flat(atlas: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear lookup of (N,) float coordinates in ``atlas`` -> (N, 3) float32."""
    n = mx.shape[0]
    cols = 4096
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.pad(mx.astype(np.float32, copy=False), (0, pad)).reshape(rows, cols)
    my = np.pad(my.astype(np.float32, copy=False), (0, pad)).reshape(rows, cols)
    out = cv2.remap(atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1, 3)[:n].astype(np.float32)


def render_view(geometry: SceneGeometry, *, R_world_from_cam: np.ndarray, center: np.ndarray, width: int,
                supersample: int = SUPERSAMPLE) -> tuple[np.ndarray, np.ndarray]:
    """Render one equirectangular panorama: ``(image (H, W, 3) uint8 BGR, depth (H, W) float32)``.

    The image is rendered at ``supersample`` times the resolution and area-downsampled; depth is the
    exact range along each pixel-centre bearing (height = width // 2). Row bands are rendered in
    parallel threads (numpy and OpenCV release the GIL); the output does not depend on scheduling.
    """
    if width < 8 or width % 2:
        raise ValueError(f"width must be an even integer >= 8, got {width}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    R = np.asarray(R_world_from_cam, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64)
    if not np.all((c > geometry.boxes[0, 0]) & (c < geometry.boxes[0, 1])):
        raise ValueError(f"center {c} is outside the room")
    height = width // 2
    ws, hs = width * supersample, height * supersample
    image = np.empty((height, width, 3), np.uint8)
    depth = np.empty((height, width), np.float32)
    image_pass = _Pass(geometry, R, c, ws, hs)
    depth_pass = _Pass(geometry, R, c, width, height) if supersample > 1 else None

    def colour_band(rows: tuple[int, int]) -> None:
        r0, r1 = rows
        d, t, face = image_pass.cast(r0, r1)
        col = _shade_samples(geometry, c, d, t, face, np.pi / hs).reshape(r1 - r0, ws, 3)
        if supersample > 1:
            col = cv2.resize(col, (width, (r1 - r0) // supersample), interpolation=cv2.INTER_AREA)
        else:
            depth[r0:r1] = t.reshape(r1 - r0, width)
        image[r0 // supersample:r1 // supersample] = np.clip(col + np.float32(0.5), 0, 255).astype(np.uint8)

    def depth_band(rows: tuple[int, int]) -> None:
        r0, r1 = rows
        depth[r0:r1] = depth_pass.cast(r0, r1)[1].reshape(r1 - r0, width)

    jobs = [(colour_band, rows) for rows in _row_chunks(hs, ws, supersample)]
    if depth_pass is not None:
        jobs += [(depth_band, rows) for rows in _row_chunks(height, width)]
    with ThreadPoolExecutor(max_workers=min(RENDER_THREADS, len(jobs))) as pool:
        for fut in [pool.submit(fn, rows) for fn, rows in jobs]:
            fut.result()
    return image, depth


class _Pass:
    """Ray directions and per-row-band furniture culling of one equirectangular grid and pose."""

    def __init__(self, geometry: SceneGeometry, R: np.ndarray, c: np.ndarray, width: int, height: int):
        self.tables = _lonlat_tables(width, height)
        self.R, self.c32 = R, list(c.astype(np.float32))
        self.boxes = np.asarray(geometry.boxes, dtype=np.float32)
        self.height = height
        # angular bounding cone (centre latitude in the camera frame, radius) of every furniture box
        rel = (geometry.boxes[1:].mean(axis=1) - c) @ R
        dist = np.linalg.norm(rel, axis=1)
        radius = 0.5 * np.linalg.norm(geometry.boxes[1:, 1] - geometry.boxes[1:, 0], axis=1)
        self.lat_c = np.arcsin(np.clip(-rel[:, 1] / dist, -1, 1))
        self.ang_r = np.where(dist > radius * 1.001, np.arcsin(np.minimum(radius / dist, 1.0)), np.pi)

    def cast(self, r0: int, r1: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """World directions, ranges and faces of the pixel centres of rows [r0, r1)."""
        lat_hi = np.pi * (0.5 - r0 / self.height)  # band latitude range incl. the pixels' extent
        lat_lo = np.pi * (0.5 - r1 / self.height)
        slack = 1e-3
        keep = np.flatnonzero((self.lat_c + self.ang_r >= lat_lo - slack) & (self.lat_c - self.ang_r <= lat_hi + slack))
        d = _world_dirs(self.tables, self.R, r0, r1)
        t, face = _cast(self.c32, d, self.boxes, [int(k) + 1 for k in keep])
        return d, t, face


# ----------------------------------------------------------------------------------------------
# scene layout


def _room(rng: np.random.Generator) -> np.ndarray:
    lx, lz, h = rng.uniform(7.0, 9.0), rng.uniform(5.0, 7.0), rng.uniform(2.7, 3.1)
    return np.array([[-lx / 2, FLOOR_Y - h, -lz / 2], [lx / 2, FLOOR_Y, lz / 2]])


def _rect_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal (x-z) gap between two boxes' footprints (0 if they overlap)."""
    dx = max(a[0, 0] - b[1, 0], b[0, 0] - a[1, 0], 0.0)
    dz = max(a[0, 2] - b[1, 2], b[0, 2] - a[1, 2], 0.0)
    return math.hypot(dx, dz)


def _sample_box(rng: np.random.Generator, kind: str, room: np.ndarray) -> np.ndarray:
    (x0, ceil_y, z0), (x1, floor_y, z1) = room
    if kind == "cupboard":
        w, dep, h = rng.uniform(0.8, 1.6), rng.uniform(0.4, 0.6), rng.uniform(1.8, 2.2)
        wall = rng.integers(4)
        gap = 0.02
        if wall < 2:  # against an x wall: extent along z
            z = rng.uniform(z0 + 0.1, z1 - 0.1 - w)
            x = x0 + gap if wall == 0 else x1 - gap - dep
            lo, hi = [x, floor_y - h, z], [x + dep, floor_y, z + w]
        else:
            x = rng.uniform(x0 + 0.1, x1 - 0.1 - w)
            z = z0 + gap if wall == 2 else z1 - gap - dep
            lo, hi = [x, floor_y - h, z], [x + w, floor_y, z + dep]
        return np.array([lo, hi])
    if kind == "column":
        s = rng.uniform(0.3, 0.5)
        x, z = rng.uniform(x0 + 0.8, x1 - 0.8 - s), rng.uniform(z0 + 0.8, z1 - 0.8 - s)
        return np.array([[x, ceil_y, z], [x + s, floor_y, z + s]])
    if kind == "table":
        w, dep, h = rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0), rng.uniform(0.7, 0.8)
    else:  # low crate / bench
        w, dep, h = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.7), rng.uniform(0.35, 0.6)
    if rng.random() < 0.5:
        w, dep = dep, w
    x, z = rng.uniform(x0 + 0.3, x1 - 0.3 - w), rng.uniform(z0 + 0.3, z1 - 0.3 - dep)
    return np.array([[x, floor_y - h, z], [x + w, floor_y, z + dep]])


def _free_mask(boxes: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid of camera positions (x-z cell centres) at least CLEARANCE (+ half a cell) from walls and boxes."""
    room = boxes[0]
    xs = np.arange(room[0, 0] + res / 2, room[1, 0], res)
    zs = np.arange(room[0, 2] + res / 2, room[1, 2], res)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    margin = CLEARANCE + res
    free = ((gx - room[0, 0] >= margin) & (room[1, 0] - gx >= margin)
            & (gz - room[0, 2] >= margin) & (room[1, 2] - gz >= margin))
    for box in boxes[1:]:
        dx = np.maximum(np.maximum(box[0, 0] - gx, gx - box[1, 0]), 0.0)
        dz = np.maximum(np.maximum(box[0, 2] - gz, gz - box[1, 2]), 0.0)
        free &= np.hypot(dx, dz) >= margin
    return free, gx, gz


def _layout_boxes(rng: np.random.Generator) -> np.ndarray:
    """Room + 3-6 non-overlapping furniture boxes leaving a connected free area for the cameras."""
    for _attempt in range(100):
        room = _room(rng)
        n = int(rng.integers(3, 7))
        kinds = ["cupboard", "table"] + list(rng.choice(["table", "cupboard", "column", "crate"], size=n - 2))
        boxes = [room]
        for kind in kinds:
            for _try in range(50):
                box = _sample_box(rng, kind, room)
                if all(_rect_gap(box, other) >= 0.4 for other in boxes[1:]):
                    boxes.append(box)
                    break
        boxes = np.array(boxes)
        if len(boxes) < 4:
            continue
        free, _, _ = _free_mask(boxes, 0.1)
        labels, count = ndimage.label(free)
        if count and np.bincount(labels.ravel())[1:].max() * 0.01 >= 6.0:
            return boxes
    raise RuntimeError("could not lay out a room with enough free space")


def _place_cameras(rng: np.random.Generator, boxes: np.ndarray, views: int) -> tuple[np.ndarray, np.ndarray]:
    """Random walk of camera centres in the largest free region; returns (R_world_from_cam (V,3,3), centers (V,3))."""
    res = 0.05
    free, gx, gz = _free_mask(boxes, res)
    labels, _ = ndimage.label(free)
    largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    cells = np.stack([gx[labels == largest], gz[labels == largest]], axis=1)
    pos: list[np.ndarray] = []
    centers, rots = [], []
    for k in range(views):  # camera k depends only on cameras < k (prefix-stable in ``views``)
        if k == 0:
            cand = cells
        else:
            d_prev = np.linalg.norm(cells - pos[-1], axis=1)
            d_all = np.min(np.linalg.norm(cells[:, None] - np.array(pos)[None], axis=2), axis=1)
            d_mean = np.linalg.norm(cells - np.mean(pos, axis=0), axis=1)
            ok = d_all >= MIN_CAMERA_SEPARATION + res  # + res: the jitter below moves up to res / sqrt(2)
            step = ok & (d_prev >= STEP_RANGE[0]) & (d_prev <= STEP_RANGE[1])
            cand = cells[step & (d_mean <= MAX_SPREAD)]  # keep the cluster compact
            if len(cand) == 0:
                cand = cells[step]
            if len(cand) == 0:  # walk stuck: attach to any camera
                cand = cells[ok & (d_all <= 2.0)]
            if len(cand) == 0:
                cand = cells[ok] if ok.any() else cells
        pos.append(cand[rng.integers(len(cand))] + rng.uniform(-res / 2, res / 2, 2))
        y = rng.uniform(-EYE_HEIGHT_JITTER, EYE_HEIGHT_JITTER)
        yaw = rng.uniform(0.0, 2 * np.pi)
        pitch, roll = np.deg2rad(rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG, 2))
        centers.append([pos[-1][0], y, pos[-1][1]])
        rots.append(_rot_y(yaw) @ _rot_x(pitch) @ _rot_z(roll))
    return np.array(rots), np.array(centers)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _face_frame(boxes: np.ndarray, face: int) -> tuple[int, int, int, float, np.ndarray, np.ndarray]:
    """(axis, u axis, v axis, plane coordinate, (u, v) min, (u, v) size) of a face."""
    k, axis, side = face // 6, (face % 6) // 2, face % 2
    uax, vax = FACE_UV_AXES[axis]
    lo, hi = boxes[k]
    plane = hi[axis] if side else lo[axis]
    return axis, int(uax), int(vax), float(plane), lo[[uax, vax]], (hi - lo)[[uax, vax]]


def _face_normal(face: int, room: bool) -> np.ndarray:
    """Unit normal of a face pointing into free space (inwards for the room)."""
    axis, side = (face % 6) // 2, face % 2
    n = np.zeros(3)
    n[axis] = (1.0 if side else -1.0) * (-1.0 if room else 1.0)
    return n


def _markers(rng: np.random.Generator, boxes: np.ndarray) -> tuple[np.ndarray, list[str], list[int]]:
    """Target marker centres on the six room faces: (M, 3), names, face index of each."""
    pts, names, faces = [], [], []
    for face in range(6):
        axis, uax, vax, plane, uv0, size = _face_frame(boxes, face)
        for m in range(MARKERS_PER_ROOM_FACE):
            uv = uv0 + rng.uniform(0.3, size - 0.3)
            p = np.zeros(3)
            p[axis], p[uax], p[vax] = plane, uv[0], uv[1]
            pts.append(p)
            names.append(f"room_face{face}_marker{m}")
            faces.append(face)
    return np.array(pts), names, faces


# ----------------------------------------------------------------------------------------------
# textures


def _texel_for_width(width: int) -> float:
    return float(np.clip(TEXEL_AT_2048 * 2048.0 / width, 0.003, 0.06))


def _hsv_bgr(h: float, s: float, v: float) -> np.ndarray:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, s, v)
    return np.array([b, g, r]) * 255.0


def _noise_field(rng: np.random.Generator, size_uv: np.ndarray, shape: tuple[int, int], texel: float,
                 cell: float, channels: int) -> np.ndarray | None:
    """World-anchored smooth noise (bicubic on a grid of ``cell`` metres); None if finer than the texels."""
    gu, gv = int(math.ceil(size_uv[0] / cell)) + 4, int(math.ceil(size_uv[1] / cell)) + 4
    grid = rng.standard_normal((gv, gu, channels)).astype(np.float32)
    if cell < 2.5 * texel:
        return None
    nv, nu = shape
    mx = np.arange(nu, dtype=np.float32) * np.float32(texel / cell) + np.float32(1.5)
    my = np.arange(nv, dtype=np.float32) * np.float32(texel / cell) + np.float32(1.5)
    map_x = np.ascontiguousarray(np.broadcast_to(mx[None, :], (nv, nu)))
    map_y = np.ascontiguousarray(np.broadcast_to(my[:, None], (nv, nu)))
    out = cv2.remap(grid, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return out.reshape(nv, nu, channels)


def _face_texture(rng: np.random.Generator, size_uv: np.ndarray, texel: float, shade: float, hue: float,
                  markers_uv: np.ndarray) -> np.ndarray:
    """(n_v, n_u, 3) uint8 BGR texture of one face; texel (a, b) sits at (u, v) = (a, b) * texel."""
    nu, nv = (int(math.ceil(s / texel)) + 1 for s in size_uv)
    base = _hsv_bgr(hue + rng.uniform(-0.04, 0.04), rng.uniform(0.2, 0.55), rng.uniform(0.45, 0.8))
    palette = [_hsv_bgr(hue + rng.uniform(-0.25, 0.25), rng.uniform(0.25, 0.85), rng.uniform(0.1, 1.0))
               for _ in range(3)]
    palette += [_hsv_bgr(rng.uniform(), rng.uniform(0.25, 0.85), rng.uniform(0.1, 1.0)) for _ in range(2)]
    img = np.empty((nv, nu, 3), np.float32)
    img[:] = base
    for cell, amp in NOISE_OCTAVES:
        n = _noise_field(rng, size_uv, (nv, nu), texel, cell, 3)
        if n is not None:
            img *= 1.0 + amp * (0.8 * n[..., :1] + 0.35 * n)
    for cell in BLOB_CELLS:
        thr = rng.uniform(0.4, 1.1)
        colour = palette[int(rng.integers(len(palette)))] * rng.uniform(0.7, 1.2)
        n = _noise_field(rng, size_uv, (nv, nu), texel, cell, 1)
        if n is not None:
            alpha = np.clip(0.5 + (n - thr) * np.float32(cell / (2.0 * texel)), 0.0, 1.0)
            img += alpha * (colour.astype(np.float32) - img)
    img8 = np.clip(img, 0, 255).astype(np.uint8)
    _draw_shapes(img8, rng, size_uv, texel, palette)
    for uv in markers_uv:
        _draw_marker(img8, uv / texel, MARKER_RADIUS / texel)
    return np.clip(img8.astype(np.float32) * shade, 0, 255).astype(np.uint8)


def _draw_shapes(img: np.ndarray, rng: np.random.Generator, size_uv: np.ndarray, texel: float,
                 palette: list[np.ndarray]) -> None:
    """Random circles, rings, ellipses, polygons, lines and glyphs, coarse to fine (in place)."""
    area = float(size_uv[0] * size_uv[1])
    glyphs = "ABCDEFGHJKLMNPRSTUVWXYZ0123456789#&%@"
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX)
    sh = 4
    one = float(1 << sh) / texel  # metres -> fixed-point texel units
    for size, cover in SHAPE_BANDS:
        n = int(rng.poisson(cover * area / size ** 2))
        cu = rng.uniform(0, size_uv[0], n) * one
        cv = rng.uniform(0, size_uv[1], n) * one
        sz = size * rng.uniform(0.6, 1.5, n) * one
        kind = rng.integers(0, 7, n)
        ang = rng.uniform(0, 360, n)
        aspect = rng.uniform(0.25, 1.0, n)
        use_grey = rng.random(n) < 0.35
        grey = rng.uniform(0, 255, n)
        pal = rng.integers(0, len(palette), n)
        jitter = rng.normal(0, 15, (n, 3))
        verts = rng.uniform(-0.5, 0.5, (n, 3, 2))
        glyph = rng.integers(0, len(glyphs), (n, 2))
        font = rng.integers(0, len(fonts), n)
        if size * 0.6 < 2.0 * texel:  # too fine for this texel size (parameters drawn anyway)
            continue
        colours = np.where(use_grey[:, None], grey[:, None], np.array(palette)[pal] + jitter)
        colours = np.clip(colours, 0, 255)
        for i in range(n):
            _draw_one(img, int(kind[i]), float(cu[i]), float(cv[i]), float(sz[i]), float(ang[i]),
                      float(aspect[i]), tuple(colours[i].tolist()), verts[i], sh,
                      glyphs[glyph[i, 0]] + glyphs[glyph[i, 1]], fonts[font[i]])


def _draw_one(img: np.ndarray, kind: int, x: float, y: float, s: float, ang: float, aspect: float,
              colour: tuple, verts: np.ndarray, sh: int, text: str, font: int) -> None:
    aa = cv2.LINE_AA
    c = (int(x), int(y))
    unit = float(1 << sh)
    if kind == 0:
        cv2.circle(img, c, int(s / 2), colour, -1, aa, sh)
    elif kind == 1:
        cv2.circle(img, c, int(s / 2), colour, max(1, int(s / unit / 8)), aa, sh)
    elif kind == 2:
        cv2.ellipse(img, c, (int(s / 2), int(s * aspect / 2)), ang, 0, 360, colour, -1, aa, sh)
    elif kind == 3:
        a = math.radians(ang)
        ca, sa = math.cos(a), math.sin(a)
        hw, hh = s / 2, s * aspect / 2
        pts = [(x + ca * dx - sa * dy, y + sa * dx + ca * dy) for dx, dy in ((-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh))]
        cv2.fillConvexPoly(img, np.array(pts, np.int32), colour, aa, sh)
    elif kind == 4:
        pts = np.array([x, y]) + verts * s * 1.4
        cv2.fillConvexPoly(img, pts.astype(np.int32), colour, aa, sh)
    elif kind == 5:
        a = math.radians(ang)
        dx, dy = math.cos(a) * s / 2, math.sin(a) * s / 2
        cv2.line(img, (int(x - dx), int(y - dy)), (int(x + dx), int(y + dy)), colour,
                 max(1, int(s * aspect / unit / 5)), aa, sh)
    else:
        scale = s / unit / 30.0
        org = (int((x - s / 2) / unit), int((y + s / 4) / unit))
        cv2.putText(img, text, org, font, scale, colour, max(1, int(scale * 2)), aa)


def _draw_marker(img: np.ndarray, centre: np.ndarray, radius: float) -> None:
    """Quadrant target (black/white) whose centre is the exact marker point (texel units)."""
    sh = 4
    c = (int(round(centre[0] * 16)), int(round(centre[1] * 16)))
    r = int(round(radius * 16))
    aa = cv2.LINE_AA
    cv2.circle(img, c, int(r * 1.15), (0, 0, 0), -1, aa, sh)
    cv2.circle(img, c, r, (255, 255, 255), -1, aa, sh)
    cv2.ellipse(img, c, (r, r), 0, 0, 90, (0, 0, 0), -1, aa, sh)
    cv2.ellipse(img, c, (r, r), 0, 180, 270, (0, 0, 0), -1, aa, sh)


def _face_shade(face: int) -> float:
    """Constant Lambert-like shading factor of a face (view independent, differs between orientations)."""
    n = _face_normal(face, room=face < 6)
    return float(0.55 + 0.45 * max(0.0, float(n @ LIGHT_DIR)))


def _build_atlas(textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Shelf-pack every face texture and its pyrDown levels into one atlas."""
    tiles = []
    for f, tex in enumerate(textures):
        lvl = tex
        for level in range(MIP_LEVELS):
            tiles.append((level, f, lvl))
            if min(lvl.shape[:2]) >= 2:
                lvl = cv2.pyrDown(lvl)  # level-l texel k sits at level-0 texel k * 2**l
            else:
                lvl = cv2.resize(lvl, ((lvl.shape[1] + 1) // 2, (lvl.shape[0] + 1) // 2), interpolation=cv2.INTER_AREA)
    order = sorted(range(len(tiles)), key=lambda i: (-tiles[i][2].shape[0], i))
    atlas_w = max(4096, max(t[2].shape[1] for t in tiles) + 2 * ATLAS_PAD)
    offset = np.zeros((MIP_LEVELS, len(textures), 2), np.float32)
    placed = []
    x = y = shelf_h = 0
    for i in order:
        level, f, img = tiles[i]
        h, w = img.shape[0] + 2 * ATLAS_PAD, img.shape[1] + 2 * ATLAS_PAD
        if x + w > atlas_w:
            x, y, shelf_h = 0, y + shelf_h, 0
        placed.append((x, y, img))
        offset[level, f] = (x + ATLAS_PAD, y + ATLAS_PAD)
        x += w
        shelf_h = max(shelf_h, h)
    atlas = np.zeros((y + shelf_h, atlas_w, 3), np.uint8)
    for x0, y0, img in placed:
        padded = cv2.copyMakeBorder(img, ATLAS_PAD, ATLAS_PAD, ATLAS_PAD, ATLAS_PAD, cv2.BORDER_REPLICATE)
        atlas[y0:y0 + padded.shape[0], x0:x0 + padded.shape[1]] = padded
    if atlas.shape[0] >= 32767 or atlas.shape[1] >= 32767:
        raise ValueError(f"texture atlas too large ({atlas.shape[:2]}); texel too small")
    return atlas, offset


def build_geometry(boxes: np.ndarray, *, texel: float, seed: np.random.SeedSequence | int,
                   markers: np.ndarray | None = None, marker_names: list[str] | None = None,
                   marker_faces: list[int] | None = None) -> SceneGeometry:
    """Procedural textures (one per face, seeded) and their mip-mapped atlas for ``boxes``."""
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3) or np.any(boxes[:, 1] <= boxes[:, 0]):
        raise ValueError(f"boxes must be (K, 2, 3) with min < max, got shape {boxes.shape}")
    markers = np.zeros((0, 3)) if markers is None else np.asarray(markers, dtype=np.float64)
    marker_faces = marker_faces or []
    seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    # children derived without SeedSequence.spawn (which mutates seq): same seed -> same textures
    hue0 = np.random.default_rng(np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key + (1 << 20,))).uniform()
    textures = []
    for face in range(6 * len(boxes)):
        child = np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key + (face,))
        _, uax, vax, _, uv0, size = _face_frame(boxes, face)
        on_face = [m for m, f in zip(markers, marker_faces) if f == face]
        muv = np.array([[m[uax], m[vax]] for m in on_face]).reshape(-1, 2) - uv0
        hue = hue0 + GOLDEN_HUE_STEP * face  # neighbouring face indices get well separated hues
        textures.append(_face_texture(np.random.default_rng(child), size, texel, _face_shade(face), hue, muv))
    atlas, offset = _build_atlas(textures)
    return SceneGeometry(boxes=boxes, texel=texel, atlas=atlas, tile_offset=offset,
                         markers=markers, marker_names=list(marker_names or []))


# ----------------------------------------------------------------------------------------------
# hand points


def _box_corners(box: np.ndarray) -> np.ndarray:
    idx = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return np.where(idx == 1, box[1], box[0])


def _hand_candidates(geometry: SceneGeometry) -> tuple[np.ndarray, list[str]]:
    pts, names = [], []
    for k, box in enumerate(geometry.boxes):
        for c, p in enumerate(_box_corners(box)):
            pts.append(p)
            names.append(f"room_corner{c}" if k == 0 else f"box{k}_corner{c}")
    pts.extend(geometry.markers)
    names.extend(geometry.marker_names)
    return np.array(pts), names


def visible_observations(points: np.ndarray, views: list[SynthView], *,
                         border_frac: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Exact projections (P, V, 2) of world points and a (P, V) visibility mask (depth test vs the depth maps)."""
    points = np.asarray(points, dtype=np.float64)
    pix = np.zeros((len(points), len(views), 2))
    vis = np.zeros((len(points), len(views)), bool)
    for v, view in enumerate(views):
        h, w = view.depth.shape
        rel = points - view.center
        pix[:, v] = bearings_to_pixels(rel @ view.R_world_from_cam, w, h)
        rng_ = np.linalg.norm(rel, axis=1)
        x, y = pix[:, v, 0], pix[:, v, 1]
        margin = max(2.0, border_frac * h)
        inside = (y >= margin) & (y <= h - margin) & (x >= margin) & (x <= w - margin)
        # the (up to) 4 pixel centres around the projection must not be in front of the point
        j0 = np.floor(x - 0.5).astype(int)
        i0 = np.clip(np.floor(y - 0.5).astype(int), 0, h - 2)
        near = np.min([view.depth[i0 + di, (j0 + dj) % w] for di in (0, 1) for dj in (0, 1)], axis=0)
        tol = 0.02 + rng_ * max(0.02, 2.0 * 2.0 * np.pi / w)
        vis[:, v] = inside & (near >= rng_ - tol)
    return pix, vis


def _hand_points(geometry: SceneGeometry, views: list[SynthView], rng: np.random.Generator,
                 noise_px: float) -> tuple[list[dict], np.ndarray]:
    pts, names = _hand_candidates(geometry)
    pix, vis = visible_observations(pts, views)
    noise = rng.normal(0.0, 1.0, pix.shape) * noise_px
    tracks, xyz = [], []
    for p in np.flatnonzero(vis.sum(axis=1) >= 2):
        obs = {}
        for v in np.flatnonzero(vis[p]):
            h, w = views[v].depth.shape
            x, y = pix[p, v] + noise[p, v]
            obs[views[v].name] = [float(np.mod(x, w)), float(np.clip(y, 0.0, h))]
        tracks.append({"name": names[p], "observations": obs})
        xyz.append(pts[p])
    return tracks, np.array(xyz).reshape(-1, 3)


# ----------------------------------------------------------------------------------------------
# scene


def render_scene(*, views: int = 6, width: int = 2048, seed: int = 0, hand_point_noise_px: float = 1.0,
                 supersample: int = SUPERSAMPLE) -> SynthScene:
    """Render a seeded synthetic room seen by ``views`` panoramas of ``width`` x ``width // 2``.

    The same arguments give bit-identical output; the room, furniture and textures depend only on
    ``seed`` (the texture resolution on ``width``) and camera k does not depend on ``views`` > k.
    """
    if not isinstance(views, (int, np.integer)) or views < 1:
        raise ValueError(f"views must be a positive integer, got {views!r}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if hand_point_noise_px < 0:
        raise ValueError(f"hand_point_noise_px must be >= 0, got {hand_point_noise_px}")
    if width < 16 or width % 2:
        raise ValueError(f"width must be an even integer >= 16, got {width}")
    t0 = time.perf_counter()
    s_layout, s_cam, s_tex, s_noise = np.random.SeedSequence(int(seed)).spawn(4)
    layout_rng = np.random.default_rng(s_layout)
    boxes = _layout_boxes(layout_rng)
    markers, marker_names, marker_faces = _markers(layout_rng, boxes)
    geometry = build_geometry(boxes, texel=_texel_for_width(width), seed=s_tex, markers=markers,
                              marker_names=marker_names, marker_faces=marker_faces)
    t1 = time.perf_counter()
    rots, centers = _place_cameras(np.random.default_rng(s_cam), boxes, views)
    out = []
    for k in tqdm(range(views), desc="render", disable=None, leave=False):
        image, depth = render_view(geometry, R_world_from_cam=rots[k], center=centers[k], width=width,
                                   supersample=supersample)
        out.append(SynthView(name=f"pano_{k:03d}.png", image=image, depth=depth,
                             R_world_from_cam=rots[k], center=centers[k]))
    t2 = time.perf_counter()
    hand, hand_xyz = _hand_points(geometry, out, np.random.default_rng(s_noise), hand_point_noise_px)
    log.info("synthetic scene seed=%d: %d boxes, textures %.2fs, %d views %dx%d %.2fs, %d hand tracks",
             seed, len(boxes) - 1, t1 - t0, views, width, width // 2, t2 - t1, len(hand))
    return SynthScene(views=out, hand_points=hand, boxes=boxes, scene_size=float(np.linalg.norm(boxes[0, 1] - boxes[0, 0])),
                      hand_point_xyz=hand_xyz, geometry=geometry)


# ----------------------------------------------------------------------------------------------
# surface sampling


def sample_surface_points(scene: SynthScene, *, spacing: float, seed: int = 0, min_views: int = 0) -> np.ndarray:
    """(N, 3) roughly uniform (jittered grid, ``spacing`` m) points on every surface that can be seen.

    Covers the room's walls, floor and ceiling and the furniture faces, minus surfaces hidden in
    contact or in crevices narrower than 5 cm (box bottoms, floor under boxes, cupboard backs).
    With ``min_views`` > 0 only points with a free line of sight to at least that many of the
    scene's camera centres are kept.
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    boxes = np.asarray(scene.boxes, dtype=np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for face in range(6 * len(boxes)):
        axis, uax, vax, plane, uv0, size = _face_frame(boxes, face)
        nu, nv = (max(1, int(round(s / spacing))) for s in size)
        u = (np.arange(nu)[None, :] + rng.uniform(0, 1, (nv, nu))) * (size[0] / nu) + uv0[0]
        v = (np.arange(nv)[:, None] + rng.uniform(0, 1, (nv, nu))) * (size[1] / nv) + uv0[1]
        p = np.empty((nu * nv, 3))
        p[:, axis], p[:, uax], p[:, vax] = plane, u.ravel(), v.ravel()
        n = _face_normal(face, room=face < 6)
        out.append(p[_open_surface(p, n, boxes)])
    pts = np.concatenate(out)
    if min_views > 0:
        seen = np.zeros(len(pts), int)
        for view in scene.views:
            rel = pts - view.center
            dist = np.linalg.norm(rel, axis=1)
            for s in range(0, len(pts), CHUNK_RAYS):
                t, _ = cast_rays(view.center, rel[s:s + CHUNK_RAYS] / dist[s:s + CHUNK_RAYS, None], boxes)
                seen[s:s + CHUNK_RAYS] += t >= dist[s:s + CHUNK_RAYS] - 1e-3 * np.maximum(dist[s:s + CHUNK_RAYS], 1.0)
        pts = pts[seen >= min_views]
    return pts


def _open_surface(p: np.ndarray, n: np.ndarray, boxes: np.ndarray, gap: float = 0.05) -> np.ndarray:
    """Mask of surface points whose outward side is inside the room, outside every box, with >= gap free space."""
    q = p + 1e-4 * n
    room = boxes[0]
    ok = np.all((q > room[0]) & (q < room[1]), axis=1)
    for box in boxes[1:]:
        ok &= ~np.all((q > box[0]) & (q < box[1]), axis=1)
    if ok.any():
        t, _ = cast_rays(q[ok], np.broadcast_to(n, (int(ok.sum()), 3)), boxes)
        ok[np.flatnonzero(ok)] = t >= gap
    return ok
