"""Rendering of equirectangular panoramas of a textured box scene: vectorised ray casting and shading.

Rays follow the bearings of ``fullview.sfm.camera`` (pixel (i, j) looks along the bearing of its centre
(j + 0.5, i + 0.5)); each is slab-tested against every box, shaded by a trilinear mip-mapped lookup in the
texture atlas, and the image is supersampled. Depth is the exact range along each pixel-centre bearing.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from fullview.sfm.camera import bearings_to_lonlat, pixel_grid_lonlat, pixel_latitude
from fullview.synth.geometry import SceneGeometry, face_uv_origins


SUPERSAMPLE = 2  # default supersampling factor per axis for the image (depth uses pixel centres)
CHUNK_RAYS = 1 << 17  # rays per vectorised chunk (bounds memory)
RENDER_THREADS = max(1, min(4, os.cpu_count() or 1))  # threads rendering row bands in parallel


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
    ``camera.pixel_grid_bearings`` (same float64 longitudes and latitudes), evaluated separably.
    """
    lon, lat = pixel_grid_lonlat(width, height)
    return np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)


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
    face_u0, face_v0 = face_uv_origins(geometry.boxes)
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
        self.lat_c = bearings_to_lonlat(rel)[1]
        self.ang_r = np.where(dist > radius * 1.001, np.arcsin(np.minimum(radius / dist, 1.0)), np.pi)

    def cast(self, r0: int, r1: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """World directions, ranges and faces of the pixel centres of rows [r0, r1)."""
        lat_hi = pixel_latitude(r0, self.height)  # band latitude range incl. the pixels' extent
        lat_lo = pixel_latitude(r1, self.height)
        slack = 1e-3
        keep = np.flatnonzero((self.lat_c + self.ang_r >= lat_lo - slack) & (self.lat_c - self.ang_r <= lat_hi + slack))
        d = _world_dirs(self.tables, self.R, r0, r1)
        t, face = _cast(self.c32, d, self.boxes, [int(k) + 1 for k in keep])
        return d, t, face
