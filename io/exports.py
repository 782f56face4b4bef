"""Export formats for a sparse model: COLMAP (text or binary, through pycolmap), nerfstudio, PLY point clouds.

Pure functions over arrays: they get an output folder or path and know nothing of the workspace layout.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fullview.io.artifacts import atomic_path, save_json, save_mesh_ply, save_ply
from fullview.io.errors import FullviewError
from fullview.sfm.open3d_module import open3d

log = logging.getLogger(__name__)

COLMAP_FILES = ("cameras", "images", "points3D", "rigs", "frames")
# What COLMAP's text reader cannot hold in an image name (pycolmap 4.2.1, read back): it splits the line at ASCII
# whitespace ("pano 0.png" reads back as "pano") and a line break cuts the image's two lines apart (the model is
# unreadable); other control characters are refused too. Non-ASCII letters and spaces (é, U+00A0) read back exactly.
COLMAP_TEXT_UNSAFE = re.compile(r"[\x00-\x20\x7f-\x9f]")


class ExportError(FullviewError, ValueError):
    """A model cannot be written in the asked format without changing it (an image name the format cannot hold)."""
# nerfstudio camera axes are OpenGL's (x right, y up, z back): ours with y and z flipped
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])


@dataclass(kw_only=True)
class SparseModel:
    """A sparse reconstruction as flat arrays; images are indexed 0..N-1, points 0..P-1."""

    image_names: list[str]  # N image file names (COLMAP's image name)
    image_sizes: list[tuple[int, int]]  # N (width, height) in pixels
    registered: np.ndarray  # (N,) bool: the image has a pose
    R_cam_from_world: np.ndarray  # (N, 3, 3) rotations, x_cam = R x_world + t
    t_cam_from_world: np.ndarray  # (N, 3) translations
    points: np.ndarray  # (P, 3) world coordinates
    colors: np.ndarray  # (P, 3) uint8 RGB
    point_errors_rad: np.ndarray  # (P,) mean angular reprojection error, radians
    track_point3d: np.ndarray  # (K,) observation -> point index
    track_image: np.ndarray  # (K,) observation -> image index
    track_point2d: np.ndarray  # (K,) observation -> index into pixels[image]
    pixels: list[np.ndarray]  # N arrays (M_i, 2): every 2-D feature of image i, equirectangular pixels

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres −Rᵀt (NaN for unregistered images)."""
        c = -np.einsum("nba,nb->na", self.R_cam_from_world, self.t_cam_from_world)
        c[~np.asarray(self.registered, bool)] = np.nan
        return c

    def validate(self) -> None:
        """Raise ValueError naming the field whose shape or indices do not fit the rest, before pycolmap's own
        checks fail with a less readable message."""
        n, p = len(self.image_names), len(self.points)
        for name, shape in [("registered", (n,)), ("R_cam_from_world", (n, 3, 3)), ("t_cam_from_world", (n, 3)),
                            ("points", (p, 3)), ("colors", (p, 3)), ("point_errors_rad", (p,))]:
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(f"SparseModel.{name} has shape {np.shape(getattr(self, name))}, expected {shape}")
        for name in ("image_sizes", "pixels"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"SparseModel.{name} has {len(getattr(self, name))} entries for {n} images")
        k = len(self.track_point3d)
        for name in ("track_image", "track_point2d"):
            if len(getattr(self, name)) != k:
                raise ValueError(f"SparseModel.{name} has {len(getattr(self, name))} entries, track_point3d {k}")
        if k == 0:
            return
        image, feature = np.asarray(self.track_image), np.asarray(self.track_point2d)
        for name, arr, size in (("track_point3d", np.asarray(self.track_point3d), p), ("track_image", image, n)):
            if arr.min() < 0 or arr.max() >= size:
                raise ValueError(f"SparseModel.{name} holds indices outside [0, {size})")
        counts = np.array([len(px) for px in self.pixels], np.int64)
        if np.any((feature < 0) | (feature >= counts[image])):
            raise ValueError("SparseModel.track_point2d holds indices beyond their image's pixels")


def split_models(model: SparseModel, model_id: np.ndarray) -> list[SparseModel]:
    """One SparseModel per model k = 0, 1, ... of `model_id` (N,) (-1: in none): its images registered, its points
    (a point belongs to the model of its first observation's image) with their observations, rows renumbered."""
    model_id = np.asarray(model_id)
    count = int(model_id.max(initial=-1)) + 1
    first = np.searchsorted(model.track_point3d, np.arange(len(model.points)))
    point_model = model_id[model.track_image[first]] if len(model.points) else np.zeros(0, np.int64)
    out = []
    for k in range(count):
        keep = point_model == k
        row = np.cumsum(keep) - 1
        obs = keep[model.track_point3d]
        out.append(dataclasses.replace(
            model, registered=model_id == k, points=model.points[keep], colors=model.colors[keep],
            point_errors_rad=model.point_errors_rad[keep], track_point3d=row[model.track_point3d[obs]],
            track_image=model.track_image[obs], track_point2d=model.track_point2d[obs]))
    return out


# ------------------------------------------------------------------------------------------------------------------
# COLMAP

def write_colmap_model(model: SparseModel, out_dir: Path, *, binary: bool) -> Path:
    """Write `model` as a COLMAP model (cameras, images, points3D, rigs, frames; .txt or .bin) into `out_dir`.

    Binary models (and text models pycolmap would treat specially: a point with no observation in a registered
    image, a 2-D feature shared by two points) are built as a pycolmap.Reconstruction and written by pycolmap
    itself, so the files are whatever this COLMAP version reads (4.x wants a rig and a frame per image); other
    text models are formatted here, byte for byte the files pycolmap writes (tests compare them). One EQUIRECTANGULAR camera per distinct image size;
    image id = image index + 1, point id = point index + 1 (so ids match the rows of our arrays); only registered
    images are written, with all their 2-D features, and observations in unregistered images are dropped.
    A point's ERROR is our angular reprojection error in DEGREES, not pixels: the equirectangular pixel size
    varies with latitude, so a pixel error would not compare across the image.
    The files are written to a temporary folder first and then moved in, so a failure leaves no half model; the
    other format's files of the same model are removed (pycolmap would read a stale .bin before a fresh .txt).
    """
    model.validate()
    _check_names(model, binary)
    direct = not binary and _text_points_writable(model)
    rec = None if direct else build_reconstruction(model)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ext, other = (".bin", ".txt") if binary else (".txt", ".bin")
    with tempfile.TemporaryDirectory(prefix=".colmap.", dir=out_dir) as tmp:
        if direct:
            _write_text_model(model, Path(tmp))
        else:
            (rec.write_binary if binary else rec.write_text)(tmp)
        for name in COLMAP_FILES:
            (out_dir / (name + other)).unlink(missing_ok=True)
            if (Path(tmp) / (name + ext)).exists():
                os.replace(Path(tmp) / (name + ext), out_dir / (name + ext))
    log.debug("COLMAP %s model: %d images, %d points -> %s", "binary" if binary else "text",
              np.count_nonzero(model.registered), len(model.points), out_dir)
    return out_dir


def colmap_text_safe(model: SparseModel) -> bool:
    """Whether COLMAP's text format holds the name of every image `write_colmap_model` writes (the registered ones)."""
    return not any(COLMAP_TEXT_UNSAFE.search(model.image_names[k]) for k in np.flatnonzero(model.registered))


def _check_names(model: SparseModel, binary: bool) -> None:
    """An ExportError naming the first registered image whose name the format would change."""
    for k in np.flatnonzero(model.registered).tolist():
        name = model.image_names[k]
        if binary and "\x00" in name:  # the binary format ends a name at NUL (pycolmap's reader then fails)
            raise ExportError(f"image name {name!r} holds a NUL character, which COLMAP's binary format cannot hold")
        if not binary and COLMAP_TEXT_UNSAFE.search(name):
            raise ExportError(f"image name {name!r} cannot be written in COLMAP's text format (its reader splits "
                              f"names at spaces and lines at line breaks, so the model would read back with other "
                              f"names); export with --format colmap-bin, which keeps every name, or rename the image")


def _registered_observations(model: SparseModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point, image index, feature) of the observations in registered images, grouped by point (stable)."""
    point, image, feature = (np.asarray(a, np.int64) for a in
                             (model.track_point3d, model.track_image, model.track_point2d))
    keep = np.asarray(model.registered, bool)[image]
    order = np.argsort(point[keep], kind="stable")
    return point[keep][order], image[keep][order], feature[keep][order]


def _text_points_writable(model: SparseModel) -> bool:
    """True when `_write_text_model` gives pycolmap's own files: every point keeps an observation in a registered
    image and no 2-D feature serves two points (pycolmap's handling of either is left to pycolmap)."""
    point, image, feature = _registered_observations(model)
    if len(np.unique(point)) != len(model.points):
        return False
    key = image * (int(feature.max(initial=0)) + 1) + feature
    return len(np.unique(key)) == len(key)


G17 = "%.17g".__mod__  # COLMAP's text writer: 17 significant digits, %g style


def _quaternions_wxyz(R: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) of rotation matrices (N, 3, 3) computed as Eigen's Quaternion(Matrix3)
    does, operation for operation (its trace is m00 + (m11 + m22)): bitwise what pycolmap writes (a test checks)."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    q = np.empty((len(R), 4))
    trace = R[:, 0, 0] + (R[:, 1, 1] + R[:, 2, 2])
    pos = trace > 0
    t = np.sqrt(trace[pos] + 1.0)
    q[pos, 0] = 0.5 * t
    t = 0.5 / t
    q[pos, 1] = (R[pos, 2, 1] - R[pos, 1, 2]) * t
    q[pos, 2] = (R[pos, 0, 2] - R[pos, 2, 0]) * t
    q[pos, 3] = (R[pos, 1, 0] - R[pos, 0, 1]) * t
    for n in np.flatnonzero(~pos):
        m = R[n]
        i = 0
        if m[1, 1] > m[0, 0]:
            i = 1
        if m[2, 2] > m[i, i]:
            i = 2
        j, k = (i + 1) % 3, (i + 2) % 3
        t = np.sqrt(m[i, i] - m[j, j] - m[k, k] + 1.0)
        q[n, 1 + i] = 0.5 * t
        t = 0.5 / t
        q[n, 0] = (m[k, j] - m[j, k]) * t
        q[n, 1 + j] = (m[j, i] + m[i, j]) * t
        q[n, 1 + k] = (m[k, i] + m[i, k]) * t
    return q


def _write_text_model(model: SparseModel, folder: Path) -> None:
    """The five files of COLMAP's text model in `folder`, byte for byte what pycolmap writes for
    `build_reconstruction(model)` (tests compare them), without building it: pycolmap's per-point constructor
    cost ~9 µs a point and its import 0.2 s, the largest parts of the export."""
    point, image, feature = _registered_observations(model)
    num_points, num_obs = len(model.points), len(point)
    reg = np.flatnonzero(model.registered)
    sizes = sorted({tuple(int(v) for v in model.image_sizes[k]) for k in reg})
    camera_of = {size: cid for cid, size in enumerate(sizes, start=1)}
    cams = [f"{cid} EQUIRECTANGULAR {w} {h} {G17(float(w))} {G17(float(h))}\n" for (w, h), cid in camera_of.items()]
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {len(cams)}\n" + "".join(cams))
    (folder / "rigs.txt").write_text(
        "# Rig calib list with one line of data per calib:\n#   RIG_ID, NUM_SENSORS, REF_SENSOR_TYPE, REF_SENSOR_ID, "
        "SENSORS[] as (SENSOR_TYPE, SENSOR_ID, HAS_POSE, [QW, QX, QY, QZ, TX, TY, TZ])\n"
        f"# Number of rigs: {len(cams)}\n" + "".join(f"{cid} 1 CAMERA {cid}\n" for cid in camera_of.values()))
    quats = _quaternions_wxyz(np.asarray(model.R_cam_from_world)[reg])
    t = np.asarray(model.t_cam_from_world, np.float64)[reg]
    poses = [" ".join(map(G17, row)) for row in np.concatenate([quats, t], axis=1).tolist()]
    cam_ids = [camera_of[tuple(int(v) for v in model.image_sizes[k])] for k in reg.tolist()]
    (folder / "frames.txt").write_text(
        "# Frame list with one line of data per frame:\n#   FRAME_ID, RIG_ID, RIG_FROM_WORLD[QW, QX, QY, QZ, TX, TY, TZ], "
        "NUM_DATA_IDS, DATA_IDS[] as (SENSOR_TYPE, SENSOR_ID, DATA_ID)\n"
        f"# Number of frames: {len(reg)}\n"
        + "".join(f"{k + 1} {c} {pose} 1 CAMERA {c} {k + 1}\n" for k, c, pose in zip(reg.tolist(), cam_ids, poses)))

    lines = ["# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
             "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
             f"# Number of images: {len(reg)}, mean observations per image: {G17(num_obs / len(reg) if len(reg) else 0)}\n"]
    for k, c, pose in zip(reg.tolist(), cam_ids, poses):
        ids = np.full(len(model.pixels[k]), -1, np.int64)
        here = image == k
        ids[feature[here]] = point[here] + 1
        xy = np.asarray(model.pixels[k], np.float64).reshape(-1, 2)
        lines.append(f"{k + 1} {pose} {c} {model.image_names[k]}\n"
                     + "".join(map("%.17g %.17g %d ".__mod__, zip(*xy.T.tolist(), ids.tolist()))) + "\n")
    (folder / "images.txt").write_text("".join(lines))

    xyz = list(map(G17, np.asarray(model.points, np.float64).ravel().tolist()))
    errors = list(map(G17, np.degrees(np.asarray(model.point_errors_rad, np.float64)).tolist()))
    rgb = np.asarray(model.colors, np.uint8).tolist()
    observations = list(map("%d %d".__mod__, zip((image + 1).tolist(), feature.tolist())))
    starts = np.searchsorted(point, np.arange(num_points + 1)).tolist()
    rows = [f"{p + 1} {xyz[3 * p]} {xyz[3 * p + 1]} {xyz[3 * p + 2]} {rgb[p][0]} {rgb[p][1]} {rgb[p][2]} "
            f"{errors[p]} " + " ".join(observations[starts[p]:starts[p + 1]]) + "\n" for p in range(num_points)]
    (folder / "points3D.txt").write_text(
        "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        f"# Number of points: {num_points}, mean track length: {G17(num_obs / num_points if num_points else 0)}\n"
        + "".join(rows))


def build_reconstruction(model: SparseModel):
    """A pycolmap.Reconstruction holding `model` (see `write_colmap_model` for ids and units)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    reg = np.flatnonzero(model.registered)
    sizes = sorted({tuple(int(v) for v in model.image_sizes[k]) for k in reg})
    camera_of = {size: cid for cid, size in enumerate(sizes, start=1)}
    for (w, h), cid in camera_of.items():
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="EQUIRECTANGULAR", width=w, height=h,
                                                        params=[w, h], camera_id=cid))
    for k in reg.tolist():
        cid = camera_of[tuple(int(v) for v in model.image_sizes[k])]
        keypoints = np.asarray(model.pixels[k], np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=model.image_names[k], keypoints=keypoints, camera_id=cid, image_id=k + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(model.R_cam_from_world[k], np.float64)),
                                np.asarray(model.t_cam_from_world[k], np.float64))
        rec.add_image_with_trivial_frame(image, pose)
    _add_points(rec, model)
    return rec


def _add_points(rec, model: SparseModel) -> None:
    """Every point with its track (observations in registered images), colour and error in degrees."""
    import pycolmap

    point, image, feature = _registered_observations(model)
    starts = np.searchsorted(point, np.arange(len(model.points) + 1)).tolist()
    image, feature = (image + 1).tolist(), feature.tolist()
    errors_deg = np.degrees(np.asarray(model.point_errors_rad, np.float64)).tolist()
    points = np.asarray(model.points, np.float64)
    colors = np.asarray(model.colors, np.uint8)
    for p in range(len(points)):
        s, e = starts[p], starts[p + 1]
        track = pycolmap.Track([pycolmap.TrackElement(i, j) for i, j in zip(image[s:e], feature[s:e])])
        rec.add_point3D_with_id(p + 1, pycolmap.Point3D(xyz=points[p], color=colors[p], error=errors_deg[p],
                                                        track=track))


# ------------------------------------------------------------------------------------------------------------------
# nerfstudio

def write_nerfstudio(model: SparseModel, out_dir: Path, *, image_paths: list[str],
                     ply_name: str = "sparse_points.ply") -> Path:
    """`out_dir/transforms.json` for nerfstudio's `nerfstudio-data` parser, plus the sparse points as a PLY.

    Checked against nerfstudio (main, 2025-07): `cameras.py` casts EQUIRECTANGULAR rays from
    coord = ((x − cx)/fx, −(y − cy)/fy), lon = π·coord_x, polar angle from +y = π(0.5 − coord_y), in OpenGL camera
    axes; with fl_x = w/2, fl_y = h, cx = w/2, cy = h/2 (what `process_data/metashape_utils.py` writes for
    spherical sensors) that is exactly our bearing with y and z negated, so `transform_matrix` is our
    camera-to-world [Rᵀ | c] with its y and z columns negated. Pixel centres sit at +0.5 in both.
    Only registered images become frames; `file_path` is `image_paths[k]` as given (nerfstudio resolves a
    relative path against the folder of transforms.json). w, h and the intrinsics are top-level when all frames
    share a size, else per frame.
    World frame: kept as ours (no re-orientation to nerfstudio's z-up world; its dataparser orients and centres
    the poses itself, `orientation_method="up"` by default), so `applied_transform` is written as the identity.
    It is written rather than left out because, without it, nerfstudio assumes COLMAP's legacy axis swap
    whenever a `colmap/sparse/0` folder sits beside transforms.json. The PLY (`ply_file_path`, relative to
    out_dir, loaded by nerfstudio with open3d) is in the same world frame as the poses, as nerfstudio expects.
    """
    model.validate()
    if len(image_paths) != len(model.image_names):
        raise ValueError(f"image_paths has {len(image_paths)} entries for {len(model.image_names)} images")
    out_dir = Path(out_dir)
    reg = np.flatnonzero(model.registered)
    c2w = nerfstudio_camera_to_world(model.R_cam_from_world[reg], model.t_cam_from_world[reg])
    intrinsics = [_equirect_intrinsics(*model.image_sizes[k]) for k in reg]
    shared = intrinsics[0] if intrinsics and all(i == intrinsics[0] for i in intrinsics) else {}
    frames = [{"file_path": str(image_paths[k]), **({} if shared else intrinsics[f]),
               "transform_matrix": c2w[f].tolist()} for f, k in enumerate(reg.tolist())]
    write_point_cloud(out_dir / ply_name, model.points, model.colors)
    meta = {"camera_model": "EQUIRECTANGULAR", **shared, "frames": frames,
            "applied_transform": np.eye(4)[:3].tolist(), "ply_file_path": ply_name}
    return save_json(out_dir / "transforms.json", meta)


def _equirect_intrinsics(w: int, h: int) -> dict:
    return {"w": int(w), "h": int(h), "fl_x": w / 2.0, "fl_y": float(h), "cx": w / 2.0, "cy": h / 2.0}


def nerfstudio_camera_to_world(R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray) -> np.ndarray:
    """(N, 4, 4) camera-to-world matrices in nerfstudio's OpenGL camera axes (x right, y up, z back)."""
    R = np.asarray(R_cam_from_world, np.float64).reshape(-1, 3, 3)
    t = np.asarray(t_cam_from_world, np.float64).reshape(-1, 3)
    out = np.tile(np.eye(4), (len(R), 1, 1))
    out[:, :3, :3] = np.swapaxes(R, 1, 2) @ GL_FROM_CV
    out[:, :3, 3] = -np.einsum("nba,nb->na", R, t)
    return out


def read_nerfstudio(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(file paths, R_cam_from_world (F,3,3), centres (F,3)) of the frames of a transforms.json, in our camera
    axes and in the world frame before nerfstudio's `applied_transform` (undone when present and not identity).
    A file with `applied_scale` is refused: its meaning for the saved poses is not pinned down by nerfstudio."""
    meta = json.loads(Path(path).read_text())
    if "applied_scale" in meta:
        raise ValueError(f"{path}: applied_scale={meta['applied_scale']} is not supported")
    c2w = np.array([f["transform_matrix"] for f in meta["frames"]], np.float64).reshape(-1, 4, 4)
    if "applied_transform" in meta:
        applied = np.vstack([np.asarray(meta["applied_transform"], np.float64), [0, 0, 0, 1]])
        c2w = np.linalg.solve(applied, c2w)
    R_world_from_cam = c2w[:, :3, :3] @ GL_FROM_CV
    return [f["file_path"] for f in meta["frames"]], np.swapaxes(R_world_from_cam, 1, 2), c2w[:, :3, 3].copy()


# ------------------------------------------------------------------------------------------------------------------
# PLY

def write_point_cloud(path: Path, points: np.ndarray, colors: np.ndarray | None = None,
                      normals: np.ndarray | None = None) -> Path:
    """Binary PLY (float32 xyz, optional normals, uint8 rgb) through `artifacts.save_ply`, with lengths checked."""
    n = len(points)
    for name, arr in (("colors", colors), ("normals", normals)):
        if arr is not None and np.shape(arr) != (n, 3):
            raise ValueError(f"{name} has shape {np.shape(arr)}, expected ({n}, 3)")
    return save_ply(path, points, colors, normals)


def write_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> Path:
    """A coloured triangle mesh as binary PLY (``.ply``: float32 xyz, uint8 rgb, int32 faces) or Wavefront OBJ
    (``.obj``: ``v x y z r g b`` with colours in [0, 1], the vertex-colour extension MeshLab, Blender and open3d
    read; 1-based ``f`` lines), with shapes and indices checked."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, np.int64)
    if np.shape(colors) != vertices.shape:
        raise ValueError(f"colors has shape {np.shape(colors)}, expected ({len(vertices)}, 3)")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or (triangles.size and (
            triangles.min() < 0 or triangles.max() >= len(vertices))):
        raise ValueError(f"triangles must be (T, 3) indices below {len(vertices)}")
    path = Path(path)
    if path.suffix == ".ply":
        return save_mesh_ply(path, vertices, triangles, colors)
    if path.suffix != ".obj":
        raise ValueError(f"{path}: a mesh is written as .ply or .obj")
    v = np.column_stack([vertices, np.asarray(colors, np.float64) / 255.0])
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(f"# fullview dense mesh: {len(vertices)} vertices, {len(triangles)} triangles\n")
        np.savetxt(f, v, fmt="v %.6f %.6f %.6f %.4f %.4f %.4f")
        np.savetxt(f, triangles + 1, fmt="f %d %d %d")
    return path


def sparse_point_normals(points: np.ndarray, centers: np.ndarray, *, knn: int = 16,
                         track_point3d: np.ndarray | None = None, track_image: np.ndarray | None = None
                         ) -> np.ndarray:
    """(P, 3) unit normals of a sparse cloud: open3d's PCA over the `knn` nearest points, each flipped to face
    the cameras that see it (the mean centre of its observing cameras when tracks are given, else the mean
    camera centre). Why facing the cameras: a surface is seen from its front, and PCA only gives an axis.
    `centers` (N, 3) may hold NaN rows for unregistered cameras; they are ignored.
    """
    o3d = open3d()

    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros((0, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(max(3, int(knn))))
    normals = np.asarray(pcd.normals, np.float64).copy()
    toward = _view_targets(points, np.asarray(centers, np.float64).reshape(-1, 3), track_point3d, track_image)
    flip = np.einsum("pa,pa->p", normals, toward - points) < 0
    normals[flip] *= -1
    return normals


def _view_targets(points: np.ndarray, centers: np.ndarray, track_point3d, track_image) -> np.ndarray:
    """Per point, the mean centre of the registered cameras observing it; the mean camera centre otherwise."""
    valid = np.isfinite(centers).all(axis=1)
    if not valid.any():
        raise ValueError("centers has no finite camera centre to orient normals towards")
    targets = np.tile(centers[valid].mean(axis=0), (len(points), 1))
    if track_point3d is None or track_image is None:
        return targets
    keep = valid[track_image]
    pts, imgs = np.asarray(track_point3d)[keep], np.asarray(track_image)[keep]
    counts = np.bincount(pts, minlength=len(points))
    sums = np.stack([np.bincount(pts, centers[imgs, a], minlength=len(points)) for a in range(3)], axis=1)
    seen = counts > 0
    targets[seen] = sums[seen] / counts[seen, None]
    return targets
