"""COLMAP interop: write our model as a COLMAP text model, run pycolmap's panorama pipeline, read its poses."""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fullview.io.artifacts import atomic_path

log = logging.getLogger(__name__)


def write_text_model(out_dir: Path, *, width: int, height: int, image_names: list[str], registered: np.ndarray,
                     R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, points: np.ndarray,
                     colors: np.ndarray, errors_rad: np.ndarray, track_image: np.ndarray,
                     track_point2d: np.ndarray, track_point3d: np.ndarray, pixels: list[np.ndarray]) -> Path:
    """cameras.txt (one EQUIRECTANGULAR camera), images.txt, points3D.txt, readable by pycolmap.Reconstruction.

    Observations are given flat: image index, index of the 2-D point within that image's `pixels`, 3-D point index.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _write(out_dir / "cameras.txt", ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                                     f"1 EQUIRECTANGULAR {width} {height} {width} {height}"])
    point2d_of = {}  # (image, 2-D index) -> 3-D point id (1-based)
    for img, p2, p3 in zip(track_image.tolist(), track_point2d.tolist(), track_point3d.tolist()):
        point2d_of[(img, p2)] = p3 + 1
    lines = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, name in enumerate(image_names):
        if not registered[k]:
            continue
        qx, qy, qz, qw = Rotation.from_matrix(R_cam_from_world[k]).as_quat()
        t = t_cam_from_world[k]
        lines.append(f"{k + 1} {qw:.17g} {qx:.17g} {qy:.17g} {qz:.17g} {t[0]:.17g} {t[1]:.17g} {t[2]:.17g} 1 {name}")
        lines.append(" ".join(f"{x:.3f} {y:.3f} {point2d_of.get((k, n), -1)}"
                              for n, (x, y) in enumerate(pixels[k])))
    _write(out_dir / "images.txt", lines)
    order = np.argsort(track_point3d, kind="stable")
    starts = np.searchsorted(track_point3d[order], np.arange(len(points) + 1))
    lines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for p in range(len(points)):
        obs = order[starts[p]:starts[p + 1]]
        track = " ".join(f"{track_image[o] + 1} {track_point2d[o]}" for o in obs)
        x, y, z = points[p]
        r, g, b = (int(c) for c in colors[p])
        lines.append(f"{p + 1} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} {np.degrees(errors_rad[p]):.6g} {track}")
    _write(out_dir / "points3D.txt", lines)
    return out_dir


def _write(path: Path, lines: list[str]) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def run_panorama_reconstruct(images_dir: Path, out_dir: Path, *, render_type: str = "spherical",
                             matcher: str = "exhaustive", seed: int = 0) -> dict:
    """pycolmap.panorama.reconstruct (CPU) on a folder of panoramas; poses of the largest model and wall time."""
    import pycolmap
    from pycolmap import panorama

    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    options = panorama.PanoramaReconstructionOptions(
        matcher=panorama.Matcher(matcher), render_type=panorama.PanoRenderType(render_type),
        random_seed=seed, use_gpu=False, show_progress=False)
    t0 = time.perf_counter()
    recs = panorama.reconstruct(Path(images_dir), out_dir, options)
    wall = time.perf_counter() - t0
    if not recs:
        return {"wall_time_s": wall, "reconstruction": None}
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    return {"wall_time_s": wall, "reconstruction": best}


def poses_by_panorama(rec, image_names: list[str]) -> dict[str, np.ndarray]:
    """R_cam_from_world, centres and registered mask per panorama name from a pycolmap Reconstruction.

    For rendered perspective rigs the panorama pose is that of the rig frame; image names of virtual cameras are
    '<subfolder>/<panorama name>', so a panorama is matched by its file name.
    """
    n = len(image_names)
    R = np.tile(np.eye(3), (n, 1, 1))
    c = np.full((n, 3), np.nan)
    registered = np.zeros(n, bool)
    index = {name: k for k, name in enumerate(image_names)}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        k = index.get(Path(image.name).name)
        if k is None or registered[k]:
            continue
        pose = image.frame.rig_from_world if hasattr(image, "frame") and image.frame is not None else image.cam_from_world()
        M = pose.matrix()
        R[k], registered[k] = M[:, :3], True
        c[k] = -M[:, :3].T @ M[:, 3]
    return {"R_cam_from_world": R, "centers": c, "registered": registered}
