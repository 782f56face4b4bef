"""COLMAP interop: write our model as a COLMAP text model, run pycolmap's panorama pipeline, read its models."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from fullview.io.exports import SparseModel, write_colmap_model

log = logging.getLogger(__name__)


def write_text_model(out_dir: Path, *, image_sizes: list[tuple[int, int]], image_names: list[str], registered: np.ndarray,
                     R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, points: np.ndarray,
                     colors: np.ndarray, errors_rad: np.ndarray, track_image: np.ndarray,
                     track_point2d: np.ndarray, track_point3d: np.ndarray, pixels: list[np.ndarray]) -> Path:
    """COLMAP text model in `out_dir` (cameras/images/points3D/rigs/frames.txt), written by pycolmap through
    `exports.write_colmap_model`: one EQUIRECTANGULAR camera per image size, image id = index + 1, point id =
    index + 1, point errors in pixels as COLMAP computes them (`exports.point_errors_px`; `errors_rad` is not
    written).

    Observations are given flat: image index, index of the 2-D point within that image's `pixels`, 3-D point index.
    """
    model = SparseModel(image_names=list(image_names), image_sizes=list(image_sizes), registered=registered,
                        R_cam_from_world=R_cam_from_world, t_cam_from_world=t_cam_from_world, points=points,
                        colors=colors, point_errors_rad=errors_rad, track_point3d=track_point3d,
                        track_image=track_image, track_point2d=track_point2d, pixels=pixels)
    return write_colmap_model(model, out_dir, binary=False)


# ------------------------------------------------------------------------------------------------------------------
# COLMAP as baseline and reference (fullview colmap-check / fullview compare)

def pycolmap_version() -> str:
    import pycolmap
    return str(pycolmap.__version__)


def reconstruct_equirectangular(images_dir: Path, out_dir: Path, model_dir: Path, *, render_type: str = "spherical",
                                matcher: str = "exhaustive", seed: int = 0) -> dict:
    """pycolmap.panorama.reconstruct (CPU); the largest model, as one EQUIRECTANGULAR image per panorama, is
    written to `model_dir` (binary). Returns wall time, number of models and the model's path (None if empty).

    With a perspective render type, panorama.reconstruct returns the rig models, whose frame pose is that of
    virtual camera 0 (pitched by 35° for PERSPECTIVE_OVERLAPPING), not of the panorama; the converted models it
    writes to `sparse_equirectangular/<idx>` carry the panorama poses, so those are the ones used here.
    """
    import pycolmap
    from pycolmap import panorama

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    options = panorama.PanoramaReconstructionOptions(
        matcher=panorama.Matcher(matcher), render_type=panorama.PanoRenderType(render_type),
        random_seed=seed, use_gpu=False, show_progress=False)
    t0 = time.perf_counter()
    recs = panorama.reconstruct(Path(images_dir), out_dir, options)
    wall = time.perf_counter() - t0
    out = {"wall_time_s": round(wall, 3), "num_models": len(recs), "model_dir": None}
    if not recs:
        return out
    best_idx = max(recs, key=lambda k: recs[k].num_reg_images())
    if panorama.PanoRenderType(render_type) == panorama.PanoRenderType.SPHERICAL:
        best = recs[best_idx]
    else:
        best = pycolmap.Reconstruction(out_dir / "sparse_equirectangular" / str(best_idx))
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    best.write(model_dir)
    out["model_dir"] = model_dir
    return out


def load_reconstruction(model_dir: Path):
    """A pycolmap.Reconstruction from a model folder (binary or text)."""
    import pycolmap
    return pycolmap.Reconstruction(Path(model_dir))


def model_arrays(rec, image_names: list[str]) -> dict[str, np.ndarray]:
    """Poses, points and observations of an EQUIRECTANGULAR pycolmap Reconstruction, indexed like `image_names`.

    Observation bearings come from each image's own camera model (`cam_ray_from_img`), unit norm. Keys:
    R_cam_from_world, t_cam_from_world, centers, registered, points (P,3), obs_point (O,), obs_image (O,),
    obs_bearings (O,3); observations are grouped by 3-D point.
    """
    n = len(image_names)
    index = {name: k for k, name in enumerate(image_names)}
    R = np.tile(np.eye(3), (n, 1, 1))
    t = np.zeros((n, 3))
    registered = np.zeros(n, bool)
    image_index = {}
    for image in rec.images.values():
        k = index.get(Path(image.name).name)
        if k is None or not image.has_pose or registered[k]:
            continue
        M = image.cam_from_world().matrix()
        R[k], t[k], registered[k] = M[:, :3], M[:, 3], True
        image_index[image.image_id] = k
    points, obs_point, obs_image, obs_xy, obs_cam = [], [], [], [], []
    for p, point in enumerate(rec.points3D.values()):
        points.append(point.xyz)
        for el in point.track.elements:
            image = rec.images[el.image_id]
            obs_point.append(p)
            obs_image.append(image_index.get(el.image_id, -1))
            obs_xy.append(image.points2D[el.point2D_idx].xy)
            obs_cam.append(image.camera_id)
    obs_xy = np.array(obs_xy, np.float64).reshape(-1, 2)
    obs_cam = np.array(obs_cam, np.int64)
    bearings = np.zeros((len(obs_xy), 3))
    for cam_id in np.unique(obs_cam):
        sel = obs_cam == cam_id
        rays = np.asarray(rec.cameras[int(cam_id)].cam_ray_from_img(obs_xy[sel]), np.float64)
        bearings[sel] = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    centers = -np.einsum("nba,nb->na", R, t)
    centers[~registered] = np.nan
    return {"R_cam_from_world": R, "t_cam_from_world": t, "centers": centers, "registered": registered,
            "points": np.array(points, np.float64).reshape(-1, 3), "obs_point": np.array(obs_point, np.int64),
            "obs_image": np.array(obs_image, np.int64), "obs_bearings": bearings}


def extract_sift_on_images(image_dir: Path, database_path: Path, groups: dict[str, list[str]],
                           *, max_num_features: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """pycolmap's SIFT (CPU, default options except the feature cap) on perspective images in `image_dir`.

    `groups` maps a PINHOLE camera's params string "fx,fy,cx,cy" to the image names it covers (one camera per
    group). Returns per image name (keypoints (N,2) in COLMAP's continuous pixel coordinates — (0,0) is the
    top-left corner of the top-left pixel — and uint8 descriptors (N,128), COLMAP's L1-root normalisation).
    """
    import pycolmap

    database_path = Path(database_path)
    database_path.unlink(missing_ok=True)
    options = pycolmap.FeatureExtractionOptions()
    options.use_gpu = False
    if max_num_features > 0:
        options.sift.max_num_features = int(max_num_features)
    for params, names in groups.items():
        pycolmap.extract_features(
            database_path, Path(image_dir), image_names=list(names), camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE", camera_params=params),
            extraction_options=options, device=pycolmap.Device.cpu)
    out = {}
    with pycolmap.Database.open(database_path) as db:
        for image in db.read_all_images():
            kp = np.asarray(db.read_keypoints(image.image_id), np.float64)
            xy = kp[:, :2].copy() if kp.ndim == 2 and len(kp) else np.zeros((0, 2))
            desc = np.asarray(db.read_descriptors(image.image_id).data, np.uint8).reshape(-1, 128)
            out[image.name] = (xy, desc)
    return out
