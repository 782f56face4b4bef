"""Off-screen pictures of reconstructions: colour-mapped range maps and point-cloud previews (atomic PNG writes).

Point clouds are drawn with matplotlib's Agg backend (no display, no OpenGL): orthographic views, points sorted far
to near (painter's algorithm) and splatted at about their spacing. Indoor scenes are seen from inside, so the
surfaces facing away from a view (given normals) or the points above the cameras (without normals) are left out:
the previews look into the room like into a doll's house.
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
    out = np.zeros(rng.shape + (3,), np.uint8)
    if not ok.any():
        return out
    inv = np.zeros_like(rng)
    inv[ok] = 1.0 / rng[ok]
    lo, hi = np.percentile(inv[ok], [2, 98])
    grey = np.clip((inv - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    out[ok] = cv2.applyColorMap(grey, colormap)[ok]
    return out


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
    At most ``max_points`` points (random subset, ``seed``) are drawn."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from scipy.spatial import cKDTree

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
    pts, cols = points[shown], colors[shown].astype(np.float64) / 255.0
    spacing = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 2 else 0.0

    dpi = 100
    fig = Figure(figsize=(panel_px * len(views) / dpi, panel_px / dpi + 0.5), dpi=dpi, facecolor="#151515")
    FigureCanvasAgg(fig)
    for k, (name, azimuth, elevation) in enumerate(views):
        ax = fig.add_axes((k / len(views), 0.0, 1.0 / len(views), panel_px / (panel_px + 50)))
        right, screen_up, towards = _view_basis(up, e1, e2, azimuth, elevation)
        order = np.argsort(pts @ towards)  # far first
        if normals is not None:
            order = order[normals[order] @ towards > 0.0]  # back faces culled
        x, y = pts[order] @ right, pts[order] @ screen_up
        (x_lo, x_hi), (y_lo, y_hi) = np.percentile(x, FRAME_PERCENTILES), np.percentile(y, FRAME_PERCENTILES)
        extent = max(x_hi - x_lo, y_hi - y_lo, 1e-9) * 1.08  # framed on the bulk, stray points may fall outside
        px_per_unit = panel_px / extent
        diameter_pt = max(1.0, 1.6 * spacing * px_per_unit) * 72.0 / dpi
        ax.scatter(x, y, s=diameter_pt**2, c=cols[order], marker="s", linewidths=0, rasterized=True)
        if cameras is not None and len(cameras):
            cams = np.asarray(cameras, np.float64)
            ax.scatter(cams @ right, cams @ screen_up, s=40, c="red", marker="^", edgecolors="white", linewidths=0.5)
        cx, cy = (x_lo + x_hi) / 2, (y_lo + y_hi) / 2
        ax.set_xlim(cx - extent / 2, cx + extent / 2)
        ax.set_ylim(cy - extent / 2, cy + extent / 2)
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_facecolor("#151515")
        label = f"{name} (az {azimuth:g}°, el {elevation:g}°)" if name != "top" else "top"
        ax.set_title(label, color="white", fontsize=11)
    if title:
        fig.suptitle(title, color="white", fontsize=12, y=0.995)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, facecolor=fig.get_facecolor())
    log.info("rendered %d points (%s) to %s", len(points),
             "back faces culled" if normals is not None else f"{len(pts)} below the ceiling cut", path)
    return Path(path)


def render_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray, **kwargs) -> Path:
    """Render a triangle mesh (RGB uint8 vertex ``colors``) like `render_point_cloud`: each triangle is splatted at
    its centre with its mean colour, shaded by the angle of its normal to the scene's up direction (so that walls,
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
    return render_point_cloud(path, corners.mean(1), np.clip(cols, 0, 255).astype(np.uint8), normals=normals,
                              **kwargs)
