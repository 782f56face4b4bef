"""A dataset folder: equirectangular images, optional hand points and ground truth.

Layout::

    <dataset>/images/*.jpg|*.png          equirectangular panoramas, width = 2 x height
    <dataset>/hand_points.yaml            optional hand-picked tracks
    <dataset>/ground_truth/poses.yaml     optional: cameras: [{image, R_world_from_cam, center}]
    <dataset>/ground_truth/depth/<stem>.npy  optional: range in metres per pixel

Validation policy: every bad input is a `DatasetError` whose message is one line naming the file and the problem;
nothing bad is accepted silently.

- Entries of images/ named like an image must be regular files (or symlinks to one): a folder named `x.jpg`, a
  FIFO or a broken symlink is an error rather than skipped, because skipping would silently change the image set
  (and with it every fingerprint) without the user noticing.
- Images must be complete JPEG or PNG files. libjpeg decodes a truncated JPEG "successfully", filling the missing
  part with grey, and only prints a warning to stderr, which OpenCV does not let us catch (and redirecting the
  process's stderr is not thread-safe). So `image_size`, which every image passes before it is decoded, reads the
  file once and checks its structure: a JPEG's marker segments are walked from SOI to the EOI ending its entropy-
  coded data (bytes after that EOI, such as zero padding or a camera's trailer, are allowed); a PNG's chunks are
  checked with PIL's `verify()` (CRC of every chunk up to IEND). This costs a read and a byte scan (a few ms for a
  5376x2688 JPEG) and keeps OpenCV's fast reduced-size decode. Corruption that keeps the structure intact (bit
  flips inside JPEG entropy-coded data) is not detectable without a full decode and is accepted, as libjpeg does.
- EXIF orientation is ignored everywhere: PIL's header size ignores it and OpenCV is told to
  (`IMREAD_IGNORE_ORIENTATION`). Equirectangular geometry is defined on the stored pixel grid, which is what the
  camera's stitcher wrote (a 90°-rotated panorama is 1:2, not an equirectangular image), and hand points are
  picked in stored pixels. A tag other than 1 is logged.
- hand_points.yaml and ground_truth/poses.yaml are read with `fullview.io.yamlio.load_yaml` (duplicate keys are
  errors) and validated completely: numbers are int or float (never bool), finite, of the expected shape.
"""

from __future__ import annotations

import datetime
import hashlib
import io
import logging
import math
import os
import re
import reprlib
import struct
import tempfile
import threading
import uuid
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property, partial
from pathlib import Path

import cv2
import numpy as np
import PIL.Image
from scipy.spatial import cKDTree

from fullview.io import limits
from fullview.io.artifacts import apply_umask, save_text
from fullview.io.errors import FullviewError
from fullview.io.yamlio import YamlError, dump_yaml, load_yaml

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
_JPEG_FORMATS = ("JPEG", "MPO")  # PIL calls a JPEG with a multi-picture (MPF) trailer "MPO"
_HAND_POINT_KEYS = {"name", "observations"}
_CAMERA_KEYS = ("image", "R_world_from_cam", "center")
_COINCIDENT = 1e-9  # centres closer than this fraction of the scene extent count as one position

_ABSENT = object()  # no hand_points.yaml (an empty file parses as None, and is refused)

# Values quoted in messages are abbreviated: a hostile file may nest aliases into an enormous structure.
_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 60


class DatasetError(FullviewError, ValueError):
    """The dataset folder or one of its files is invalid."""


@dataclass(kw_only=True)
class HandTrack:
    name: str  # label of the track (given or generated)
    observations: dict[str, tuple[float, float]]  # image name -> equirectangular pixel (x, y)


class HandObservations(dict):
    """`Dataset.hand_observations`: image name -> (track indices, pixels), and the sha256 of the file read."""

    def __init__(self, per_image: dict, *, sha256: str):
        super().__init__(per_image)
        self.sha256 = sha256


@dataclass(kw_only=True)
class GroundTruthPose:
    R_world_from_cam: np.ndarray  # (3, 3)
    center: np.ndarray  # (3,) camera centre in world


class Dataset:
    """Read access to one dataset folder, validating what it reads."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self._pins: dict[str, tuple | None] = {}  # file -> its signature when first read (see `_pinned`)
        self._sizes: dict[str, tuple[int, int]] | None = None
        self._sizes_lock = threading.Lock()  # the features stage asks for sizes from several threads at once
        if not self.root.is_dir():
            raise DatasetError(_not_a_folder(self.root))
        if not self.images_dir.is_dir():
            raise DatasetError(_no_images_folder(self.root))
        if len(self.image_names) < 2:
            raise DatasetError(f"{self.images_dir}: need at least two images, found {len(self.image_names)}")
        stems: dict[str, str] = {}
        for name in self.image_names:
            other = stems.setdefault(Path(name).stem.lower(), name)
            if other != name:  # artifacts are named by stem: two such images would overwrite each other's
                raise DatasetError(f"{self.images_dir}: images {other!r} and {name!r} share a file stem; rename one")

    def __getstate__(self) -> dict:
        # Picklable for cluster workers (fullview batch), with what it has already read and validated.
        return {k: v for k, v in self.__dict__.items() if k != "_sizes_lock"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._sizes_lock = threading.Lock()

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
        try:
            paths = [p for p in self.images_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
            for p in paths:
                _check_regular_file(p)
        except OSError as e:
            raise DatasetError(f"{self.images_dir}: cannot list ({_reason(e)})") from None
        return sorted(p.name for p in paths)

    def image_path(self, name: str) -> Path:
        return self.images_dir / name

    def image_hash(self, name: str) -> str:
        path = self.image_path(name)
        return hashlib.sha256(self._pinned(path, lambda: _read_bytes(path, "image"))).hexdigest()

    def _pinned(self, path: Path, read):
        """``read()`` of `path`, which must be the same file (device, inode, size, mtime and ctime) before and after
        the read as when this dataset first read it: the images and masks a run hashes for its fingerprints are the
        ones it validated and decodes, without holding their bytes (a panorama is megabytes). A replaced or
        rewritten file is an error, never a result filed under the other file's hash."""
        before = _signature(path)
        value = read()
        first = self._pins.setdefault(str(path), before)  # one atomic step: threads read images at once
        if before != first or _signature(path) != first:
            raise DatasetError(f"{path}: changed while fullview was reading the dataset; run again once it is "
                               f"complete")
        return value

    def refresh_inputs(self) -> None:
        """Forget the hand points read and the files pinned (a long-lived reader, the viewer, calls this when the
        dataset may have changed on purpose)."""
        self.__dict__.pop("hand_observations", None)
        self._pins.clear()

    # ------------------------------------------------------------------------------------------------- masks
    @property
    def masks_dir(self) -> Path:
        return self.root / "masks"

    def mask_path(self, name: str) -> Path:
        """COLMAP's convention: masks/<image name>.png, white = keep."""
        return self.masks_dir / f"{name}.png"

    def mask_hashes(self) -> dict[str, str]:
        """sha256 of every image's mask ('none' where it has none): the fingerprint input of masked stages."""
        return {name: hashlib.sha256(self._read_mask(name)).hexdigest()
                if self.mask_path(name).exists() else "none" for name in self.image_names}

    def _read_mask(self, name: str) -> bytes:
        path = self.mask_path(name)
        return self._pinned(path, lambda: _read_bytes(path, "mask"))

    def load_mask(self, name: str) -> np.ndarray | None:
        """(H, W) bool, True where the image is kept, at the image's own size; None when it has no mask. A mask of
        another size than its image, an unreadable or incomplete one, or one that keeps no pixel is an error naming
        the file."""
        path = self.mask_path(name)
        if not path.exists():
            return None
        data = self._read_mask(name)
        w, h = self.image_sizes[name]
        mw, mh = checked_image_file(path, data, "mask")  # complete before it is decoded: no libpng message
        if (mw, mh) != (w, h):
            raise DatasetError(f"{path}: mask is {mw}x{mh}, its image {name} is {w}x{h}")
        mask = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise DatasetError(f"{path}: not a readable image (a mask is a PNG, white = keep)")
        if mask.shape != (h, w):
            raise DatasetError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, its image {name} is {w}x{h}")
        keep = mask > 127
        if not keep.any():  # the image would give no feature: say so here, not stages later
            raise DatasetError(f"{path}: the mask keeps no pixel of {name} (white = keep; remove the image instead)")
        return keep

    def validate_inputs(self) -> None:
        """Check every input a run reads (image files, hand points, masks); a DatasetError names the first bad
        file."""
        self.image_sizes  # noqa: B018 (validates every image)
        self.hand_observations  # noqa: B018 (validates hand_points.yaml)
        self.check_masks()

    def check_masks(self) -> None:
        """Validate every mask (and refuse masks of no image) before any stage runs."""
        if self.masks_dir.is_symlink() and not self.masks_dir.exists():
            raise DatasetError(f"{self.masks_dir}: broken symbolic link (to {os.readlink(self.masks_dir)!r})")
        if not self.masks_dir.exists():
            return
        if not self.masks_dir.is_dir():
            raise DatasetError(f"{self.masks_dir}: not a folder (masks are masks/<image name>.png)")
        known = {f"{n}.png" for n in self.image_names}
        stray = sorted(p.name for p in self.masks_dir.iterdir() if p.name not in known)
        if stray:
            raise DatasetError(f"{self.masks_dir}: {stray[0]} names no image of images/ (expected <image name>.png)")
        for name in self.image_names:
            self.load_mask(name)

    def hand_points_hash(self) -> str:
        """sha256 of the very bytes `hand_observations` was parsed from ('none' without the file); of the file's
        bytes now when they are invalid (so that a status still tells the change; a run refuses the file)."""
        try:
            return self.hand_observations.sha256
        except DatasetError:
            return self._read_hand_points()[0]

    @property
    def image_sizes(self) -> dict[str, tuple[int, int]]:
        """(width, height) of every image as stored (EXIF orientation ignored), from the file headers; reading it
        validates every image (complete JPEG or PNG file, 2:1)."""
        with self._sizes_lock:
            if self._sizes is None:
                self._sizes = {name: self._pinned(self.image_path(name), partial(image_size, self.image_path(name)))
                               for name in self.image_names}
        return self._sizes

    def gps_positions(self) -> np.ndarray | None:
        """(N, 3) latitude, longitude (degrees, north/east positive) and altitude (m, 0 when absent) from every
        image's EXIF GPS tags, in image order, NaN rows for images without; None when no image has any."""
        rows = [exif_gps(self.image_path(n)) for n in self.image_names]
        if all(r is None for r in rows):
            return None
        return np.array([r if r is not None else (np.nan,) * 3 for r in rows], np.float64)

    def load_image(self, name: str, width: int = 0) -> np.ndarray:
        """BGR uint8 image, resized to `width` (keeping 2:1) when width > 0."""
        native_w, native_h = self.image_sizes[name]  # also validates the file before it is decoded
        # JPEG can decode at 1/2, 1/4, 1/8 size directly, much faster than a full decode and resize; only
        # reductions that divide the size exactly keep the 2:1 shape.
        reduction = max((r for r in (1, 2, 4, 8) if width and native_w // r >= width
                         and native_w % r == 0 and native_h % r == 0), default=1)
        image = self._pinned(self.image_path(name), partial(read_image, self.image_path(name), reduction))
        if width and image.shape[1] != width:
            interp = cv2.INTER_AREA if width < image.shape[1] else cv2.INTER_LINEAR
            image = cv2.resize(image, (width, width // 2), interpolation=interp)
        return image

    # ------------------------------------------------------------------------------------------- hand points
    def hand_tracks(self) -> list[HandTrack]:
        """Hand-picked tracks as the file holds them now, validated against the image list and sizes; [] when the
        file is absent. (A run uses `hand_observations`, read once.)"""
        _, data = self._read_hand_points()
        return [] if data is _ABSENT else self._parse_hand_points(self.hand_points_path, data)

    def _read_hand_points(self) -> tuple[str, object]:
        """(sha256, parsed YAML) of one read of hand_points.yaml: ('none', _ABSENT) when there is no file."""
        path = self.hand_points_path
        if not path.exists():
            return "none", _ABSENT
        raw = _read_bytes(path, "file")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise DatasetError(f"{path}: not UTF-8 text (byte {e.start})") from None
        sha = hashlib.sha256(raw).hexdigest()
        try:
            return sha, load_yaml(text, where=str(path))
        except YamlError as e:
            raise DatasetError(str(e)) from None

    def save_hand_points(self, points: list) -> Path | None:
        """Validate `points` (the `points:` list of hand_points.yaml) and write the file atomically. The file it
        replaces is kept first (`_keep_backup`); returns that backup's path (None when there was no file)."""
        tracks = self._parse_hand_points(self.hand_points_path, {"points": points})
        text = dump_yaml({"points": [{"name": t.name, "observations": {i: [round(x, 3), round(y, 3)]
                                                                      for i, (x, y) in t.observations.items()}}
                                     for t in tracks]}, sort_keys=False, default_flow_style=None)
        path = self.hand_points_path
        try:
            backup = _keep_backup(path)
            save_text(path, text)
        except OSError as e:
            where = f" at {e.filename}" if e.filename and Path(e.filename) != path else ""
            raise DatasetError(f"{path}: cannot save the hand points ({_reason(e)}{where})") from None
        self.__dict__.pop("hand_observations", None)  # the cached parse is stale now
        return backup

    def _parse_hand_points(self, path: Path, data) -> list[HandTrack]:
        points = data.get("points") if isinstance(data, dict) else None
        if not isinstance(points, list):
            raise DatasetError(f"{path}: expected a top-level 'points:' list")
        unknown = sorted(map(str, set(data) - {"points"}))
        if unknown:  # a `version:` or a misspelt section would otherwise be ignored without a word
            raise DatasetError(f"{path}: unknown top-level key {_REPR.repr(unknown[0])}; hand_points.yaml holds "
                               f"only 'points:'")
        given = {p["name"] for p in points if isinstance(p, dict) and isinstance(p.get("name"), str)}
        tracks = [self._hand_track(path, k, p, given) for k, p in enumerate(points)]
        _check_unique_names(path, tracks)
        return tracks

    def _hand_track(self, path: Path, k: int, point, given: set[str]) -> HandTrack:
        if not isinstance(point, dict) or not isinstance(point.get("observations"), dict):
            raise DatasetError(f"{path}: points[{k}] needs an 'observations' mapping")
        unknown = sorted(map(str, set(point) - _HAND_POINT_KEYS))
        if unknown:  # most likely a misspelt 'name', which would otherwise be ignored
            raise DatasetError(f"{path}: points[{k}] has unknown key(s) {unknown}; allowed: name, observations")
        name = _track_name(path, k, point, given)
        obs = {image: self._hand_pixel(path, name, image, xy) for image, xy in point["observations"].items()}
        if len(obs) < 2:  # one observation constrains nothing
            raise DatasetError(f"{path}: point {name!r} has {len(obs)} observation(s); a track needs at least 2")
        return HandTrack(name=name, observations=obs)

    def _hand_pixel(self, path: Path, name: str, image, xy) -> tuple[float, float]:
        if not isinstance(image, str) or image not in self.image_names:
            raise DatasetError(f"{path}: point {name!r} names unknown image {image!r}")
        pixel = _number_array(xy, (2,))
        if pixel is None or not np.isfinite(pixel).all():
            raise DatasetError(f"{path}: point {name!r} in {image}: expected [x, y] of two finite numbers, "
                               f"got {_REPR.repr(xy)}")
        w, h = self.image_sizes[image]
        x, y = float(pixel[0]), float(pixel[1])
        if not (0 <= x <= w and 0 <= y <= h):
            raise DatasetError(f"{path}: point {name!r} at ({x}, {y}) lies outside {image} ({w}x{h})")
        return x, y

    @cached_property
    def hand_observations(self) -> HandObservations:
        """Per image: (track indices (K,), pixels (K, 2)) of its hand observations, tracks in file order; its
        ``sha256`` is that of the bytes they were parsed from (one read: the fingerprint names what was used)."""
        sha, data = self._read_hand_points()
        tracks = [] if data is _ABSENT else self._parse_hand_points(self.hand_points_path, data)
        out = {name: ([], []) for name in self.image_names}
        for k, track in enumerate(tracks):
            for image, xy in track.observations.items():
                out[image][0].append(k)
                out[image][1].append(xy)
        return HandObservations({n: (np.array(t, np.int64), np.array(p, np.float64).reshape(-1, 2))
                                 for n, (t, p) in out.items()}, sha256=sha)

    def hand_pair_matches(self, num_sift: list[int], i: int, j: int) -> np.ndarray:
        """(K, 2) hand correspondences of images i, j in the extended feature index space (SIFT features first, then
        each image's hand observations; see `Workspace.load_observations`)."""
        tracks_i, _ = self.hand_observations[self.image_names[i]]
        tracks_j, _ = self.hand_observations[self.image_names[j]]
        _, ki, kj = np.intersect1d(tracks_i, tracks_j, assume_unique=True, return_indices=True)
        return np.column_stack([ki + num_sift[i], kj + num_sift[j]]).astype(np.int64)

    # ------------------------------------------------------------------------------------------ ground truth
    def has_ground_truth(self) -> bool:
        return (self.ground_truth_dir / "poses.yaml").exists()

    def ground_truth_poses(self) -> dict[str, GroundTruthPose]:
        """Ground-truth poses by image name, validated (known images, each once, proper finite rotations, finite
        and distinct centres)."""
        path = self.ground_truth_dir / "poses.yaml"
        data = _load_yaml(path)
        cameras = data.get("cameras") if isinstance(data, dict) else None
        if not isinstance(cameras, list):
            raise DatasetError(f"{path}: expected a top-level 'cameras:' list")
        out = {}
        for k, cam in enumerate(cameras):
            image, pose = self._ground_truth_pose(path, k, cam)
            if image in out:
                raise DatasetError(f"{path}: image {image!r} appears twice")
            out[image] = pose
        _check_distinct_centers(path, out)
        return out

    def _ground_truth_pose(self, path: Path, k: int, cam) -> tuple[str, GroundTruthPose]:
        if not isinstance(cam, dict):
            raise DatasetError(f"{path}: cameras[{k}] is invalid: expected a mapping, got {_REPR.repr(cam)}")
        missing = [key for key in _CAMERA_KEYS if key not in cam]
        if missing:
            raise DatasetError(f"{path}: cameras[{k}] is invalid: missing key {missing[0]!r}")
        image = cam["image"]
        if not isinstance(image, str) or image not in self.image_names:
            raise DatasetError(f"{path}: cameras[{k}] names unknown image {image!r}")
        # A flat list of 9 is accepted for R, as it always was (it used to be reshaped).
        R = _pose_array(path, k, image, cam, "R_world_from_cam", (3, 3), (9,))
        c = _pose_array(path, k, image, cam, "center", (3,))
        if not _is_rotation(R):
            raise DatasetError(f"{path}: R_world_from_cam of {image!r} is not a rotation matrix")
        return image, GroundTruthPose(R_world_from_cam=R, center=c)

    def ground_truth_depth(self, name: str) -> np.ndarray | None:
        """Ground-truth range map of image `name` (NaN = no depth), None when the dataset has none for it."""
        path = self.ground_truth_dir / "depth" / f"{Path(name).stem}.npy"
        if not path.exists():
            return None
        depth = _load_npy(path)
        _check_depth(path, depth)
        return depth

    def ground_truth_scene_size(self, centers: np.ndarray) -> float:
        """``scene_size`` from ground_truth/scene.npz (synthetic scenes), else the extent of the true camera
        centres (the length dense metrics' tolerance τ is relative to)."""
        path = self.ground_truth_dir / "scene.npz"
        if path.exists():
            try:
                with np.load(path, allow_pickle=False) as data:
                    if "scene_size" in data and np.isfinite(data["scene_size"]) and float(data["scene_size"]) > 0:
                        return float(data["scene_size"])
            except (OSError, ValueError, EOFError) as e:
                raise DatasetError(f"{path}: cannot read ({_reason(e)})") from None
            raise DatasetError(f"{path}: no positive finite 'scene_size'")
        return float(np.linalg.norm(centers.max(0) - centers.min(0)))


# ---------------------------------------------------------------------------------------------- file access
# ------------------------------------------------------------------------------------------- hand point backups
# Timestamped backups of hand_points.yaml kept (the newest): one per save, a few kB each, enough for a long picking
# session; the .orig.bak (the file before the viewer's first save) is never removed.
BACKUPS_KEPT = 50
_ORIGINAL_SUFFIX = ".orig.bak"


def _keep_backup(path: Path) -> Path | None:
    """Copy `path` (when it exists) to a backup no other save can overwrite: `<name>.<UTC time, microseconds>Z-<random
    hex>.bak`, each created exclusively. The very first save also writes `<name>.orig.bak`, exclusively, so it keeps
    the file as it was before any save, whatever saves race. Only the newest BACKUPS_KEPT timestamped backups stay."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    _write_new(path.with_name(path.name + _ORIGINAL_SUFFIX), data)  # False once it exists: kept as it is
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
    while not _write_new(backup := path.with_name(f"{path.name}.{stamp}-{uuid.uuid4().hex[:8]}.bak"), data):
        pass  # the same microsecond and the same 32 random bits: draw again
    pattern = re.compile(re.escape(path.name) + r"\.\d{8}T\d{6}\.\d{6}Z-[0-9a-f]{8}\.bak")
    stamped = sorted(p for p in path.parent.iterdir() if pattern.fullmatch(p.name))
    for old in stamped[:-BACKUPS_KEPT]:
        old.unlink(missing_ok=True)  # a concurrent save may have removed it already
    return backup


def _write_new(path: Path, data: bytes) -> bool:
    """Create `path` holding `data`, complete or not at all; False (and nothing changed) when `path` exists."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        apply_umask(Path(tmp))
        try:
            os.link(tmp, path)  # unlike a rename, a link never replaces a file that exists
        except FileExistsError:
            return False
        return True
    finally:
        os.unlink(tmp)


def _reason(e: Exception) -> str:
    """One line saying what went wrong: an OSError's strerror ('Permission denied'), else the message."""
    text = (e.strerror if isinstance(e, OSError) else None) or str(e) or type(e).__name__
    return " ".join(text.split())


def _read_bytes(path: Path, what: str) -> bytes:
    _check_regular_file(path)
    try:
        return path.read_bytes()
    except OSError as e:
        raise DatasetError(f"cannot read {what} {path}: {_reason(e)}") from None


def _signature(path: Path) -> tuple | None:
    """What changes when a file is replaced or rewritten (None when it cannot be stat'ed): its device and inode,
    size, modification time and change time (which no program sets at will)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def _check_regular_file(p: Path) -> None:
    """A file about to be read must be a regular file (or a symlink to one) when it exists: reading a folder fails
    obscurely and opening a FIFO blocks forever. A missing file is left to the read to report."""
    if p.is_symlink() and not p.exists():
        raise DatasetError(f"{p}: broken symbolic link (to {os.readlink(p)!r})")
    if p.exists() and not p.is_file():
        raise DatasetError(f"{p}: not a regular file (a folder, FIFO or device named like a data file)")


def _load_yaml(path: Path):
    _check_regular_file(path)
    try:
        return load_yaml(path, where=str(path))
    except YamlError as e:
        raise DatasetError(str(e)) from None


def _load_npy(path: Path) -> np.ndarray:
    _check_regular_file(path)
    try:
        # Memory-mapped first: a header claiming more data than the file holds fails here instead of allocating it.
        loaded = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise DatasetError(f"{path}: cannot read depth map ({_reason(e)})") from None
    if not isinstance(loaded, np.ndarray):  # an .npz archive named .npy
        loaded.close()
        raise DatasetError(f"{path}: not a .npy array (an .npz archive?)")
    return np.array(loaded)


def _check_depth(path: Path, depth: np.ndarray) -> None:
    # Depth maps may have any resolution (they are resampled to the estimate's), but must be 2:1 like the images.
    if depth.dtype.kind != "f" or depth.ndim != 2 or depth.shape[0] == 0 or depth.shape[1] != 2 * depth.shape[0]:
        raise DatasetError(f"{path}: depth map must be a 2-D float array twice as wide as high, "
                           f"got {depth.dtype} {depth.shape}")
    if np.isinf(depth).any() or (depth < 0).any():
        raise DatasetError(f"{path}: depth map has infinite or negative values (use NaN where there is no depth)")


# --------------------------------------------------------------------------------------------------- values
def _number_array(value, shape: tuple[int, ...]) -> np.ndarray | None:
    """Nested lists of real numbers (int or float, not bool) of exactly `shape` as float64 (possibly non-finite),
    None for anything else."""
    if not shape:
        return _real(value)
    if not isinstance(value, list) or len(value) != shape[0]:
        return None
    items = [_number_array(v, shape[1:]) for v in value]
    return None if any(item is None for item in items) else np.array(items, np.float64)


def _real(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        return float(v)
    except OverflowError:  # an integer beyond float range
        return math.inf


def _pose_array(path: Path, k: int, image: str, cam: dict, key: str, *shapes: tuple[int, ...]) -> np.ndarray:
    value = cam[key]
    array = next((a for a in (_number_array(value, s) for s in shapes) if a is not None), None)
    if array is None:
        raise DatasetError(f"{path}: cameras[{k}] is invalid: {key} of {image!r} must be a "
                           f"{'x'.join(map(str, shapes[0]))} (nested) list of numbers, got {_REPR.repr(value)}")
    if not np.isfinite(array).all():
        raise DatasetError(f"{path}: {key} of {image!r} has a non-finite entry (NaN or inf)")
    return array.reshape(shapes[0])


def _is_rotation(R: np.ndarray) -> bool:
    # Entries of a rotation lie in [-1, 1]: checking that first keeps R.T @ R from overflowing.
    return (np.abs(R).max() <= 1 + 1e-6 and np.abs(R.T @ R - np.eye(3)).max() <= 1e-6
            and np.linalg.det(R) > 0)


def _check_distinct_centers(path: Path, poses: dict[str, GroundTruthPose]) -> None:
    """Two cameras at one position make the baselines the metrics divide by zero."""
    if len(poses) < 2:
        return
    names = list(poses)
    c = np.stack([poses[n].center for n in names])
    c = c / (np.abs(c).max() or 1.0)  # scale-free test, and no overflow for huge coordinates
    extent = float(np.linalg.norm(c.max(0) - c.min(0)))
    pairs = cKDTree(c).query_pairs(_COINCIDENT * extent, output_type="ndarray")
    if len(pairs):
        a, b = sorted(pairs.tolist())[0]
        raise DatasetError(f"{path}: cameras {names[a]!r} and {names[b]!r} have coincident centres "
                           f"{poses[names[a]].center.tolist()}")


def _track_name(path: Path, k: int, point: dict, given: set[str]) -> str:
    """The point's name, or for an unnamed one point_<k>, made unique against the names the file gives (an unnamed
    point beside one named point_0 is not a duplicate)."""
    if "name" not in point:
        name, n = f"point_{k}", 1
        while name in given:
            n += 1
            name = f"point_{k}_{n}"
        return name
    name = point["name"]
    if not isinstance(name, str) or not name.strip():
        raise DatasetError(f"{path}: points[{k}] name must be a non-empty string, got {_REPR.repr(name)}")
    return name


def _check_unique_names(path: Path, tracks: list[HandTrack]) -> None:
    seen = set()
    for track in tracks:
        if track.name in seen:
            raise DatasetError(f"{path}: point name {track.name!r} is used twice")
        seen.add(track.name)


# --------------------------------------------------------------------------------------------------- images
_REDUCED_FLAGS = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}


def read_image(path: Path, reduction: int = 1) -> np.ndarray:
    """BGR uint8 image (decoded at 1/reduction size, EXIF orientation ignored); a clear error when unreadable or not
    2:1 equirectangular. Does not detect truncation: `image_size` (which `Dataset.load_image` runs first) does."""
    image = cv2.imread(str(path), _REDUCED_FLAGS[reduction] | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise DatasetError(f"cannot read image {path} (missing, corrupt or not an image)")
    _check_two_to_one(path, image.shape[1], image.shape[0])
    return image


_GPS_IFD = 0x8825  # EXIF GPSInfo; tags 1-6: LatitudeRef, Latitude, LongitudeRef, Longitude, AltitudeRef, Altitude


def exif_gps(path: Path) -> tuple[float, float, float] | None:
    """(latitude, longitude, altitude) from the image's EXIF GPS tags, or None (no tags, or unreadable ones: GPS
    only proposes pairs, so a broken tag is logged and ignored rather than an error)."""
    if not _png_may_hold_exif(path):
        return None
    try:
        with PIL.Image.open(path) as im:
            gps = im.getexif().get_ifd(_GPS_IFD)
        if 2 not in gps or 4 not in gps:
            return None
        lat = sum(float(v) / 60**k for k, v in enumerate(gps[2])) * (-1 if gps.get(1) == "S" else 1)
        lon = sum(float(v) / 60**k for k, v in enumerate(gps[4])) * (-1 if gps.get(3) == "W" else 1)
        alt = float(gps.get(6, 0.0)) * (-1 if gps.get(5) in (1, b"\x01") else 1)
    except Exception as e:  # noqa: BLE001 — PIL's EXIF parser raises many kinds; GPS is optional, never fatal
        log.warning("%s: EXIF GPS ignored (%s: %s)", path, type(e).__name__, e)
        return None
    return (lat, lon, alt) if np.isfinite([lat, lon, alt]).all() and abs(lat) <= 90 and abs(lon) <= 180 else None


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_EXIF_CHUNKS = {b"eXIf", b"tEXt", b"zTXt", b"iTXt"}  # where PIL finds a PNG's EXIF (text: "Raw profile type exif")


def _png_may_hold_exif(path: Path) -> bool:
    """False only for a PNG file none of whose chunks can hold EXIF, found by walking the chunk headers.

    Why: a PNG's eXIf chunk may follow the image data, so PIL decodes the whole image to look for it (8-10 ms a
    1024-px panorama: 0.5 s of the 50-view walk's matches stage, on one core, for images that have none). Anything
    else (a JPEG, such a chunk, a malformed file) goes to PIL as before."""
    try:
        with open(path, "rb") as f:
            if f.read(8) != PNG_SIGNATURE:
                return True
            while header := f.read(8):
                if len(header) < 8:
                    return True
                length, kind = struct.unpack(">I4s", header)
                if kind in PNG_EXIF_CHUNKS:
                    return True
                if kind == b"IEND":
                    return False
                f.seek(length + 4, os.SEEK_CUR)  # the data and its CRC
    except OSError:
        return True
    return True  # no IEND: let PIL judge the file


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, validated as a complete JPEG or PNG file, 2:1, within this machine's
    pixel budget, at least `MIN_IMAGE_HEIGHT` high, and holding the data its header claims."""
    data = _read_bytes(path, "image")
    w, h = checked_image_file(path, data, "image")
    _check_two_to_one(path, w, h)
    return w, h


def checked_image_file(path: Path, data: bytes, what: str) -> tuple[int, int]:
    """(width, height) of the JPEG or PNG file `data` (read from `path`) after checking, in this order and before
    anything decodes it: the size its header claims against the pixel budget (`io/limits.py`) and the minimum
    size; its structure and that its compressed data can hold that many pixels (`_check_complete`). Every
    failure is a DatasetError naming the file."""
    claimed = _header_size(data)
    if claimed is not None:
        _check_pixel_count(path, *claimed, what)
    try:
        with PIL.Image.open(io.BytesIO(data)) as im:
            w, h = im.size
            _check_pixel_count(path, w, h, what)
            _check_complete(path, im, data, what)  # first: PNG's verify() must come directly after open
            if im.format in _JPEG_FORMATS:  # (verify() leaves a PNG unusable, but its orientation is moot too)
                _log_orientation(path, im)
    except (OSError, PIL.Image.DecompressionBombError):  # UnidentifiedImageError is an OSError
        raise DatasetError(f"cannot read {what} {path}: not a JPEG or PNG image, or its header is corrupt") from None
    return w, h


MIN_IMAGE_HEIGHT = 3  # the features' noise estimate (sfm/features.noise_sigma) needs a pixel with a full 3x3 neighbourhood


def _check_pixel_count(path: Path, w: int, h: int, what: str) -> None:
    budget = limits.pixel_budget()
    if w * h > budget:
        raise DatasetError(f"{what} {path} is {w}x{h} ({w * h / 1e6:.1f} Mpx), more than this machine's budget "
                           f"of {budget / 1e6:.1f} Mpx per image ({limits.budget_text()})")
    if min(w, h) < MIN_IMAGE_HEIGHT:
        raise DatasetError(f"{what} {path} is {w}x{h}; an image must be at least {MIN_IMAGE_HEIGHT} pixels high "
                           f"(the features' noise estimate needs a 3x3 neighbourhood)")


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) a JPEG's first frame header or a PNG's IHDR claims, read without PIL (which warns about, or
    refuses, a large claim before it can be checked against the budget); None when not found."""
    if data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    frame = _jpeg_frame(data)
    return None if frame is None else (frame.width, frame.height)


def _check_complete(path: Path, im: PIL.Image.Image, data: bytes, what: str) -> None:
    """The file's structure is complete (JPEG markers up to the EOI, PNG chunks' CRCs up to IEND) and its compressed
    data holds the pixels its header claims (`_check_jpeg_data`, `_check_png_data`)."""
    if im.format in _JPEG_FORMATS:
        walk = _jpeg_walk(data)
        if walk is None:
            raise DatasetError(f"cannot read {what} {path}: truncated or corrupt JPEG (its data ends before the "
                               f"end-of-image marker)")
        _check_jpeg_data(path, walk, *im.size, what)
    elif im.format == "PNG":
        try:
            im.verify()  # CRC of every chunk up to IEND, without decompressing
        except (OSError, SyntaxError, ValueError, EOFError) as e:
            raise DatasetError(f"cannot read {what} {path}: truncated or corrupt PNG ({_reason(e)})") from None
        _check_png_data(path, data, *im.size, what)
    else:
        raise DatasetError(f"cannot read {what} {path}: a {im.format} file; expected JPEG or PNG")


def _check_two_to_one(path: Path, w: int, h: int) -> None:
    if w != 2 * h:
        raise DatasetError(f"image {path} is {w}x{h}; an equirectangular panorama must be twice as wide as high")


def _log_orientation(path: Path, im: PIL.Image.Image) -> None:
    try:
        orientation = im.getexif().get(0x0112)
    except Exception:  # noqa: BLE001 — a malformed EXIF block only loses this note; the pixels are read without it
        return
    if orientation not in (None, 1):
        log.warning("%s: EXIF orientation %s ignored; the stored pixels are used as the panorama", path, orientation)


# A marker ending entropy-coded data: 0xFF followed by anything but a stuffed 0x00, a restart marker or fill 0xFF.
_SCAN_END = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")
_STANDALONE_MARKERS = {0x01, *range(0xD0, 0xD8)}  # TEM and RSTn carry no length


@dataclass(kw_only=True)
class _JpegFrame:
    marker: int  # SOFn: 0xC0-0xC3, 0xC5-0xC7 Huffman coded, 0xC9-0xCB, 0xCD-0xCF arithmetic coded
    width: int
    height: int
    mcus: int  # minimum coded units of an interleaved scan (each holds one or more 8x8 blocks of every component)


_SOF_MARKERS = {*range(0xC0, 0xC4), *range(0xC5, 0xC8), *range(0xC9, 0xCC), *range(0xCD, 0xD0)}
_ARITHMETIC_SOF = {*range(0xC9, 0xCC), *range(0xCD, 0xD0)}


def _jpeg_end(data: bytes) -> int | None:
    """Offset just past the EOI marker ending the primary image of a JPEG file, None when the marker structure
    breaks off before it (truncated or corrupt file). Bytes after it (padding, trailers) are not looked at."""
    walk = _jpeg_walk(data)
    return None if walk is None else walk[0]


def _jpeg_frame(data: bytes) -> _JpegFrame | None:
    """The first frame header (SOFn) of a JPEG file, None when there is none before the structure breaks off."""
    walk = _jpeg_walk(data, stop_at_frame=True)
    return None if walk is None else walk[2]


def _jpeg_walk(data: bytes, stop_at_frame: bool = False) -> tuple[int, int, _JpegFrame | None] | None:
    """(offset past the EOI, bytes of entropy-coded data of all scans, the first frame header) of the primary image
    of a JPEG file, None when its marker structure breaks off before the EOI. With `stop_at_frame`, returns at the
    first frame header (offset and bytes 0)."""
    if data[:2] != b"\xff\xd8":
        return None
    pos, entropy, frame = 2, 0, None
    while pos + 1 < len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte before a marker
            pos += 1
        elif marker == 0xD9:
            return pos + 2, entropy, frame
        elif marker in _STANDALONE_MARKERS:
            pos += 2
        else:
            if marker in _SOF_MARKERS and frame is None:
                frame = _parse_frame(data, pos, marker)
                if stop_at_frame:
                    return (0, 0, frame) if frame is not None else None
            end = _skip_segment(data, pos, marker)
            if end is None:
                return None
            if marker == 0xDA:
                entropy += end - (pos + 2 + int.from_bytes(data[pos + 2:pos + 4], "big"))
            pos = end
    return None


def _parse_frame(data: bytes, pos: int, marker: int) -> _JpegFrame | None:
    """The frame header at `pos`: precision, height, width, components (id, sampling factors, table)."""
    if pos + 10 > len(data):
        return None
    height, width, count = struct.unpack(">HHB", data[pos + 5:pos + 10])
    sampling = data[pos + 10:pos + 10 + 3 * count]
    if count == 0 or len(sampling) < 3 * count:
        return None
    h_max = max(max(b >> 4 for b in sampling[1::3]), 1)
    v_max = max(max(b & 15 for b in sampling[1::3]), 1)
    mcus = math.ceil(width / (8 * h_max)) * math.ceil(height / (8 * v_max))
    return _JpegFrame(marker=marker, width=width, height=height, mcus=mcus)


def _skip_segment(data: bytes, pos: int, marker: int) -> int | None:
    """Offset after the segment at `pos` (and after the entropy-coded data following a start of scan)."""
    if pos + 4 > len(data):
        return None
    end = pos + 2 + int.from_bytes(data[pos + 2:pos + 4], "big")
    if end < pos + 4 or end > len(data):
        return None
    if marker != 0xDA:
        return end
    scan_end = _SCAN_END.search(data, end)
    return scan_end.start() if scan_end else None


# ------------------------------------------------------------------------------ compressed data vs header
# A file whose header claims more pixels than its data holds decodes "successfully": libjpeg fills the missing
# blocks with grey and only warns on stderr; libpng fails inside the features stage with its own message. The
# claim is checked against the data at validation instead.
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type -> samples per pixel
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
_INFLATE_STEP = 1 << 20  # bytes of PNG data inflated at a time: the check never holds the image


def _check_jpeg_data(path: Path, walk: tuple, w: int, h: int, what: str) -> None:
    _, entropy, frame = walk
    if frame is None:
        raise DatasetError(f"cannot read {what} {path}: corrupt JPEG (no frame header before its end)")
    # Huffman coding spends at least one bit on each 8x8 block of an interleaved scan (a DC difference code, and
    # a baseline block its end-of-block code too): fewer bytes than MCUs / 8 cannot hold the claimed image.
    # Arithmetic coding can go below a bit per block; such a file (no camera writes one) is decoded as it is.
    if frame.marker not in _ARITHMETIC_SOF and 8 * entropy < frame.mcus:
        raise DatasetError(f"cannot read {what} {path}: its header claims {w}x{h} pixels but it holds {entropy} "
                           f"bytes of image data, fewer than the {math.ceil(frame.mcus / 8)} that many pixels take "
                           f"at least (a forged or truncated JPEG)")


def _check_png_data(path: Path, data: bytes, w: int, h: int, what: str) -> None:
    """Inflate the PNG's image data (in steps, keeping none of it) and compare its length with what the IHDR's
    size, bit depth, colour type and interlacing need: rows of filter byte + packed samples."""
    depth, colour, interlace = data[24], data[25], data[28]
    bits = depth * _PNG_CHANNELS.get(colour, 4)
    passes = _ADAM7 if interlace == 1 else ((0, 0, 1, 1),)
    needed = 0
    for x0, y0, dx, dy in passes:
        cols, rows = max(0, math.ceil((w - x0) / dx)), max(0, math.ceil((h - y0) / dy))
        if cols and rows:
            needed += rows * (1 + math.ceil(cols * bits / 8))
    inflater, got = zlib.decompressobj(), 0
    try:
        for chunk in _png_chunks(data, b"IDAT"):
            while chunk and got < needed:
                got += len(inflater.decompress(chunk, _INFLATE_STEP))
                chunk = inflater.unconsumed_tail
            if got >= needed:
                return
    except zlib.error as e:
        raise DatasetError(f"cannot read {what} {path}: corrupt PNG image data ({_reason(e)})") from None
    raise DatasetError(f"cannot read {what} {path}: its header claims {w}x{h} pixels but its image data holds "
                       f"{got} of the {needed} bytes they take (a forged or truncated PNG)")


def _png_chunks(data: bytes, kind: bytes) -> Iterator[memoryview]:
    """The data of every chunk of type `kind` of a PNG file whose chunk structure is already verified."""
    view, pos = memoryview(data), 8
    while pos + 8 <= len(data):
        length, chunk_kind = struct.unpack(">I4s", data[pos:pos + 8])
        if chunk_kind == kind:
            yield view[pos + 8:pos + 8 + length]
        if chunk_kind == b"IEND":
            return
        pos += 12 + length


def _not_a_folder(root: Path) -> str:
    """What to do when DATASET is not a folder: an image given instead of its dataset, or a wrong path."""
    if root.is_file() and root.suffix.lower() in IMAGE_SUFFIXES:
        hint = root.parent.parent if root.parent.name == "images" else root.parent
        return (f"{root}: is an image, not a dataset; give the dataset folder (the one holding images/), "
                f"e.g. {hint}")
    return f"dataset folder not found: {root}"


def _no_images_folder(root: Path) -> str:
    """What to do when DATASET has no images/: it is images/ itself, or it holds loose panoramas."""
    if root.name == "images" and (root.parent / "images").is_dir():
        return f"{root}: no images/ folder inside; did you mean the dataset folder {root.parent}?"
    loose = [p for p in root.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if loose:
        return (f"{root}: no images/ folder, but {len(loose)} image(s) lie here; move them into {root / 'images'}/ "
                "(a dataset is a folder with images/ inside)")
    return f"{root}: no images/ folder (a dataset is a folder with the panoramas in images/)"
