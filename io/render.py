"""Off-screen pictures of reconstructions: colour-mapped range maps and point-cloud previews (atomic PNG writes).

Point clouds are rasterised with numpy and OpenCV (no display, no OpenGL, no matplotlib): orthographic views, each
pixel showing the nearest of the squares splatted at about the points' spacing (what drawing them far to near, the
painter's algorithm, gives). Indoor scenes are seen from inside, so the surfaces facing away from a view (given
normals) or the points above the cameras (without normals) are left out: the previews look into the room like into a
doll's house.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fullview.io.artifacts import atomic_path

log = logging.getLogger(__name__)

CEILING_CUT = 0.35  # keep points up to the cameras' height + this share of the way to the highest points
FRAME_PERCENTILES = (1.0, 99.0)  # each view is framed on the points between these percentiles of its coordinates
SPACING_SAMPLE = 20_000  # points whose nearest-neighbour distances give the splat size
TITLE_BAND_PX = 50  # the band above the panels for the titles
BACKGROUND = (0x15, 0x15, 0x15)  # BGR of the dark background
CAMERA_MARKER_PX = 9  # side of a camera triangle


def save_png(path: Path, image: np.ndarray) -> Path:
    """Write a BGR (or grey) uint8 image as PNG, atomically."""
    ok, buf = cv2.imencode(".png", np.asarray(image))
    if not ok:
        raise OSError(f"could not encode {path} as PNG (shape {np.shape(image)}, dtype {np.asarray(image).dtype})")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return Path(path)


def colorize_range(range_map: np.ndarray, valid: np.ndarray | None = None, *,
                   colormap: int = cv2.COLORMAP_TURBO) -> np.ndarray:
    """BGR uint8 picture of a range map: inverse range (near = warm) stretched between its 2nd and 98th
    percentiles; invalid pixels black."""
    rng = np.asarray(range_map, np.float32)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(rng) & (rng > 0)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if not ok.any():
        return np.zeros(rng.shape + (3,), np.uint8)
    # whole-image operations (no boolean gathers and scatters of the picture: a third of the time)
    inv = np.divide(np.float32(1.0), rng, out=np.zeros_like(rng), where=ok)
    lo, hi = np.percentile(inv[ok], [2, 98])
    grey = np.clip((inv - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(grey, colormap) * ok[..., None].view(np.uint8)


def _up_and_axes(points: np.ndarray, up: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit up vector (given, or the least-variance axis of the points) and two horizontal axes (principal axes of
    the points' horizontal spread), right-handed: e1 × e2 = up."""
    centred = points - points.mean(0)
    if up is None:
        up = np.linalg.eigh(centred.T @ centred)[1][:, 0]
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    flat = centred - np.outer(centred @ up, up)
    e1 = np.linalg.eigh(flat.T @ flat)[1][:, 2]
    e1 = e1 - (e1 @ up) * up
    e1 /= np.linalg.norm(e1)
    return up, e1, np.cross(up, e1)


def _view_basis(up, e1, e2, azimuth_deg: float, elevation_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(screen right, screen up, towards the viewer) of an orthographic view from the given direction."""
    if elevation_deg >= 89.9:
        return e1, e2, up
    a, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    towards = np.cos(el) * (np.cos(a) * e1 + np.sin(a) * e2) + np.sin(el) * up
    right = np.cross(up, towards)
    right /= np.linalg.norm(right)
    return right, np.cross(towards, right), towards


def render_point_cloud(path: Path, points: np.ndarray, colors: np.ndarray, *, normals: np.ndarray | None = None,
                       up: np.ndarray | None = None, cameras: np.ndarray | None = None,
                       views: Sequence[tuple[str, float, float]] = (("top", 0.0, 90.0), ("oblique", 30.0, 45.0),
                                                                   ("oblique", 210.0, 45.0)),
                       max_points: int = 400_000, panel_px: int = 900, title: str | None = None,
                       seed: int = 0) -> Path:
    """Render ``points`` (N, 3) with RGB uint8 ``colors`` to a PNG with one panel per view (name, azimuth°,
    elevation°; azimuth from the points' main horizontal axis). ``up``: the scene's up direction (default: the
    points' least-variance axis); ``cameras`` (M, 3) centres are drawn as red triangles and set the height above
    which points are cut away. With ``normals`` (N, 3) (oriented towards the cameras) each view shows only the points
    facing it instead (back-face culling: one looks into the room through the walls and ceiling that face away).
    At most ``max_points`` points (random subset, ``seed``) are drawn. The PNG is panel_px * len(views) wide and
    panel_px + TITLE_BAND_PX high."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    colors = np.asarray(colors).reshape(-1, 3)
    if len(points) != len(colors):
        raise ValueError(f"colors has {len(colors)} rows but points has {len(points)}")
    if len(points) < 3:
        raise ValueError(f"need at least 3 points to render, got {len(points)}")
    normals = None if normals is None else np.asarray(normals, np.float64).reshape(-1, 3)
    if normals is not None and len(normals) != len(points):
        raise ValueError(f"normals has {len(normals)} rows but points has {len(points)}")
    if len(points) > max_points:
        keep = np.random.default_rng(seed).choice(len(points), max_points, replace=False)
        points, colors = points[keep], colors[keep]
        normals = None if normals is None else normals[keep]
    up, e1, e2 = _up_and_axes(points, up)
    shown = np.ones(len(points), bool)
    if normals is None:
        height = points @ up
        top = np.percentile(height, 99)
        base = (np.median(np.asarray(cameras) @ up) if cameras is not None and len(cameras)
                else np.percentile(height, 50))
        shown = height <= base + CEILING_CUT * max(top - base, 0.0)
    pts, bgr = points[shown], np.ascontiguousarray(colors[shown][:, ::-1], dtype=np.uint8)
    spacing = _point_spacing(pts, seed)
    cams = None if cameras is None or not len(cameras) else np.asarray(cameras, np.float64).reshape(-1, 3)

    canvas = np.empty((panel_px + TITLE_BAND_PX, panel_px * len(views), 3), np.uint8)
    canvas[:] = BACKGROUND
    for k, (name, azimuth, elevation) in enumerate(views):
        right, screen_up, towards = _view_basis(up, e1, e2, azimuth, elevation)
        near_first = np.argsort(-(pts @ towards))
        if normals is not None:
            near_first = near_first[normals[near_first] @ towards > 0.0]  # back faces culled
        x, y = pts[near_first] @ right, pts[near_first] @ screen_up
        (x_lo, x_hi), (y_lo, y_hi) = np.percentile(x, FRAME_PERCENTILES), np.percentile(y, FRAME_PERCENTILES)
        extent = max(x_hi - x_lo, y_hi - y_lo, 1e-9) * 1.08  # framed on the bulk, stray points may fall outside
        px_per_unit = panel_px / extent
        left, top_y = (x_lo + x_hi - extent) / 2, (y_lo + y_hi + extent) / 2

        def pixels(xs, ys):  # (column, row) of the pixels holding the points (xs, ys)
            return (np.floor((xs - left) * px_per_unit).astype(np.int64),
                    np.floor((top_y - ys) * px_per_unit).astype(np.int64))

        side = max(1, int(round(1.6 * spacing * px_per_unit)))
        panel = _splat(*pixels(x, y), bgr[near_first], side, panel_px)
        if cams is not None:
            _draw_cameras(panel, *pixels(cams @ right, cams @ screen_up))
        canvas[TITLE_BAND_PX:, k * panel_px:(k + 1) * panel_px] = panel
        label = f"{name} (az {azimuth:g}°, el {elevation:g}°)" if name != "top" else "top"
        _put_text_centred(canvas, label, k * panel_px + panel_px // 2, TITLE_BAND_PX - 10, 0.5)
    if title:
        _put_text_centred(canvas, title, canvas.shape[1] // 2, 18, 0.55)
    save_png(path, canvas)
    log.debug("rendered %d points (%s) to %s", len(points),
              "back faces culled" if normals is not None else f"{len(pts)} below the ceiling cut", path)
    return Path(path)


def _point_spacing(points: np.ndarray, seed: int) -> float:
    """Median distance from a point to its nearest neighbour, estimated on a seeded sample of the points (the
    median of SPACING_SAMPLE distances is as good as that of all, and querying all cost a second on big clouds)."""
    from scipy.spatial import cKDTree

    if len(points) < 3:
        return 0.0
    sample = points if len(points) <= SPACING_SAMPLE else \
        points[np.random.default_rng(seed).choice(len(points), SPACING_SAMPLE, replace=False)]
    tree = cKDTree(points, balanced_tree=False, compact_nodes=False)  # built once, queried once: the fast build
    return float(np.median(tree.query(sample, k=2)[0][:, 1]))


def _splat(u: np.ndarray, v: np.ndarray, colors: np.ndarray, side: int, size: int) -> np.ndarray:
    """size × size BGR raster of squares ``side`` px wide at the integer pixels (u, v) (column, row), listed near
    first: each pixel shows the nearest square covering it, as the far-to-near painter's order would. The nearest
    point at each centre pixel is found once; a min filter of the side of a square over the raster of their depth
    ranks then stands for drawing every square."""
    pad = side  # squares centred just outside the panel still reach into it
    n = size + 2 * pad
    inside = np.flatnonzero((u >= -pad) & (u < size + pad) & (v >= -pad) & (v < size + pad))  # near first
    empty = float(len(u))  # ranks < 2**24 are exact in float32
    ranks = np.full(n * n, empty, np.float32)
    np.minimum.at(ranks, (v[inside] + pad) * n + (u[inside] + pad), inside.astype(np.float32))
    ranks = cv2.erode(ranks.reshape(n, n), np.ones((side, side), np.uint8), borderType=cv2.BORDER_CONSTANT,
                      borderValue=empty)[pad:pad + size, pad:pad + size]
    out = np.empty((size, size, 3), np.uint8)
    out[:] = BACKGROUND
    shown = ranks < empty
    out[shown] = colors[ranks[shown].astype(np.int64)]
    return out


def _draw_cameras(panel: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
    """Red triangles (pointing up, white edge) at the cameras' pixels."""
    h = CAMERA_MARKER_PX / 2
    for x, y in zip(u, v):  # a dozen cameras, not the points
        tri = np.round([[x, y - h], [x - h, y + h * 0.8], [x + h, y + h * 0.8]]).astype(np.int32)
        cv2.fillPoly(panel, [tri], (0, 0, 255), lineType=cv2.LINE_AA)
        cv2.polylines(panel, [tri], True, (255, 255, 255), 1, lineType=cv2.LINE_AA)


def _put_text_centred(image: np.ndarray, text: str, centre_x: int, baseline_y: int, scale: float) -> None:
    """White anti-aliased text centred on ``centre_x``; the Hershey fonts have no '°', drawn as a small ring."""
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 1
    pieces = text.split("°")
    widths = [cv2.getTextSize(p, font, scale, thick)[0][0] for p in pieces]
    cap = cv2.getTextSize("H", font, scale, thick)[0][1]
    ring = cap / 7  # radius of the degree sign
    gap = round(2 * ring + 3)
    x = centre_x - (sum(widths) + (len(pieces) - 1) * gap) // 2
    for k, (piece, width) in enumerate(zip(pieces, widths)):
        cv2.putText(image, piece, (x, baseline_y), font, scale, (255, 255, 255), thick, cv2.LINE_AA)
        x += width
        if k < len(pieces) - 1:  # drawn at a quarter pixel's precision (shift 2)
            centre = (round((x + ring + 1) * 4), round((baseline_y - cap + ring) * 4))
            cv2.circle(image, centre, round(ring * 4), (255, 255, 255), 1, cv2.LINE_AA, shift=2)
            x += gap


def render_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray, **kwargs) -> Path:
    """Render a triangle mesh (RGB uint8 vertex ``colors``) like `render_point_cloud`: each triangle is splatted at
    its centre and halfway to its corners with its mean colour, shaded by the angle of its normal to the scene's up direction (so that walls,
    floor and edges read as surfaces), and back faces are culled. Keywords as for `render_point_cloud`."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    tri = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(tri) < 3:
        raise ValueError(f"need at least 3 triangles to render, got {len(tri)}")
    corners = vertices[tri]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    up, e1, _ = _up_and_axes(corners.mean(1), kwargs.get("up"))
    light = up + 0.5 * e1
    shade = 0.55 + 0.45 * np.abs(normals @ (light / np.linalg.norm(light)))
    cols = np.asarray(colors, np.float64).reshape(-1, 3)[tri].mean(1) * shade[:, None]
    # the centre and the three points halfway to the corners: a coarse mesh's large triangles read as surfaces,
    # not as a grid of dots
    centres = corners.mean(1)
    samples = np.concatenate([centres[:, None], 0.5 * (corners + centres[:, None])], axis=1).reshape(-1, 3)
    return render_point_cloud(path, samples, np.repeat(np.clip(cols, 0, 255).astype(np.uint8), 4, axis=0),
                              normals=np.repeat(normals, 4, axis=0), **kwargs)
