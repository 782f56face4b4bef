"""A dataset folder: equirectangular images, optional hand points and ground truth.

Layout::

    <dataset>/images/*.jpg|*.png          equirectangular panoramas, width = 2 x height
    <dataset>/hand_points.yaml            optional hand-picked tracks
    <dataset>/ground_truth/poses.yaml     optional: cameras: [{image, R_world_from_cam, center}]
    <dataset>/ground_truth/depth/<stem>.npy  optional: range in metres per pixel
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import PIL.Image
import yaml

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


class DatasetError(ValueError):
    """The dataset folder or one of its files is invalid."""


@dataclass(kw_only=True)
class HandTrack:
    name: str  # label of the track (given or generated)
    observations: dict[str, tuple[float, float]]  # image name -> equirectangular pixel (x, y)


@dataclass(kw_only=True)
class GroundTruthPose:
    R_world_from_cam: np.ndarray  # (3, 3)
    center: np.ndarray  # (3,) camera centre in world


class Dataset:
    """Read access to one dataset folder, validating what it reads."""

    def __init__(self, root: Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(f"dataset folder not found: {self.root}")
        if not self.images_dir.is_dir():
            raise DatasetError(f"{self.root}: no images/ folder")
        if len(self.image_names) < 2:
            raise DatasetError(f"{self.images_dir}: need at least two images, found {len(self.image_names)}")
        stems: dict[str, str] = {}
        for name in self.image_names:
            other = stems.setdefault(Path(name).stem.lower(), name)
            if other != name:  # artifacts are named by stem: two such images would overwrite each other's
                raise DatasetError(f"{self.images_dir}: images {other!r} and {name!r} share a file stem; rename one")

    @property
    def name(self) -> str:
        return self.root.resolve().name

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @property
    def hand_points_path(self) -> Path:
        return self.root / "hand_points.yaml"

    @property
    def ground_truth_dir(self) -> Path:
        return self.root / "ground_truth"

    @cached_property
    def image_names(self) -> list[str]:
        return sorted(p.name for p in self.images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)

    def image_path(self, name: str) -> Path:
        return self.images_dir / name

    def image_hash(self, name: str) -> str:
        return hashlib.sha256(self.image_path(name).read_bytes()).hexdigest()

    def hand_points_hash(self) -> str:
        p = self.hand_points_path
        return hashlib.sha256(p.read_bytes()).hexdigest() if p.exists() else "none"

    @cached_property
    def image_sizes(self) -> dict[str, tuple[int, int]]:
        """(width, height) of every image, from the file headers (validated 2:1)."""
        return {name: image_size(self.image_path(name)) for name in self.image_names}

    def load_image(self, name: str, width: int = 0) -> np.ndarray:
        """BGR uint8 image, resized to `width` (keeping 2:1) when width > 0."""
        native_w, native_h = self.image_sizes[name]
        # JPEG can decode at 1/2, 1/4, 1/8 size directly, much faster than a full decode and resize; only
        # reductions that divide the size exactly keep the 2:1 shape.
        reduction = max((r for r in (1, 2, 4, 8) if width and native_w // r >= width
                         and native_w % r == 0 and native_h % r == 0), default=1)
        image = read_image(self.image_path(name), reduction)
        if width and image.shape[1] != width:
            interp = cv2.INTER_AREA if width < image.shape[1] else cv2.INTER_LINEAR
            image = cv2.resize(image, (width, width // 2), interpolation=interp)
        return image

    def hand_tracks(self) -> list[HandTrack]:
        """Hand-picked tracks, validated against the image list and sizes; [] when the file is absent."""
        path = self.hand_points_path
        if not path.exists():
            return []
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise DatasetError(f"{path}: not valid YAML: {e}") from None
        points = data.get("points") if isinstance(data, dict) else None
        if not isinstance(points, list):
            raise DatasetError(f"{path}: expected a top-level 'points:' list")
        return [self._hand_track(path, k, p) for k, p in enumerate(points)]

    def _hand_track(self, path: Path, k: int, point) -> HandTrack:
        if not isinstance(point, dict) or not isinstance(point.get("observations"), dict):
            raise DatasetError(f"{path}: points[{k}] needs an 'observations' mapping")
        name = str(point.get("name", f"point_{k}"))
        obs = {}
        for image, xy in point["observations"].items():
            if image not in self.image_sizes:
                raise DatasetError(f"{path}: point {name!r} names unknown image {image!r}")
            if not (isinstance(xy, (list, tuple)) and len(xy) == 2 and all(_is_number(v) for v in xy)):
                raise DatasetError(f"{path}: point {name!r} in {image}: expected [x, y], got {xy!r}")
            w, h = self.image_sizes[image]
            x, y = float(xy[0]), float(xy[1])
            if not (0 <= x <= w and 0 <= y <= h):
                raise DatasetError(f"{path}: point {name!r} at ({x}, {y}) lies outside {image} ({w}x{h})")
            obs[image] = (x, y)
        return HandTrack(name=name, observations=obs)

    @cached_property
    def hand_observations(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per image: (track indices (K,), pixels (K, 2)) of its hand observations, tracks in file order."""
        out = {name: ([], []) for name in self.image_names}
        for k, track in enumerate(self.hand_tracks()):
            for image, xy in track.observations.items():
                out[image][0].append(k)
                out[image][1].append(xy)
        return {n: (np.array(t, np.int64), np.array(p, np.float64).reshape(-1, 2)) for n, (t, p) in out.items()}

    def has_ground_truth(self) -> bool:
        return (self.ground_truth_dir / "poses.yaml").exists()

    def ground_truth_poses(self) -> dict[str, GroundTruthPose]:
        """Ground-truth poses by image name, validated (known images, each once, proper rotations)."""
        path = self.ground_truth_dir / "poses.yaml"
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            raise DatasetError(f"{path}: not valid YAML: {e}") from None
        cameras = data.get("cameras") if isinstance(data, dict) else None
        if not isinstance(cameras, list):
            raise DatasetError(f"{path}: expected a top-level 'cameras:' list")
        out = {}
        for k, cam in enumerate(cameras):
            try:
                image = str(cam["image"])
                R = np.array(cam["R_world_from_cam"], dtype=np.float64).reshape(3, 3)
                c = np.array(cam["center"], dtype=np.float64).reshape(3)
            except (KeyError, ValueError, TypeError) as e:
                raise DatasetError(f"{path}: cameras[{k}] is invalid ({type(e).__name__}: {e})") from None
            if image not in self.image_sizes:
                raise DatasetError(f"{path}: cameras[{k}] names unknown image {image!r}")
            if image in out:
                raise DatasetError(f"{path}: image {image!r} appears twice")
            if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
                raise DatasetError(f"{path}: R_world_from_cam of {image!r} is not a rotation matrix")
            out[image] = GroundTruthPose(R_world_from_cam=R, center=c)
        return out

    def ground_truth_depth(self, name: str) -> np.ndarray | None:
        path = self.ground_truth_dir / "depth" / f"{Path(name).stem}.npy"
        return np.load(path, allow_pickle=False) if path.exists() else None


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


_REDUCED_FLAGS = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}


def read_image(path: Path, reduction: int = 1) -> np.ndarray:
    """BGR uint8 image (decoded at 1/reduction size); a clear error when unreadable or not 2:1 equirectangular."""
    image = cv2.imread(str(path), _REDUCED_FLAGS[reduction])
    if image is None:
        raise DatasetError(f"cannot read image {path} (missing, corrupt or not an image)")
    h, w = image.shape[:2]
    if w != 2 * h:
        raise DatasetError(f"image {path} is {w}x{h}; an equirectangular panorama must be twice as wide as high")
    return image


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header (no full decode), validated as 2:1."""
    try:
        with PIL.Image.open(path) as im:
            w, h = im.size
    except (OSError, PIL.UnidentifiedImageError):
        raise DatasetError(f"cannot read image {path} (missing, corrupt or not an image)") from None
    if w != 2 * h:
        raise DatasetError(f"image {path} is {w}x{h}; an equirectangular panorama must be twice as wide as high")
    return w, h
