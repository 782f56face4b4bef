"""The workspace of one dataset: the one owner of every file fullview reads or writes there.

Layout (``FILES`` is the single table of names; nothing else in fullview spells a workspace path)::

    <workspace>/<dataset name>/
        .fullview.lock, .fullview.commit.lock   run lock and commit lock (see Guarantees in the README)
        settings.yaml                        the settings every command on this workspace uses (io/settings.py)
        <folder>/manifest.json               fingerprint, params, inputs, outputs (size + sha256), summary; last
        features/<stem>.npz                  per-image features
        matches/matches.npz                  raw matches of every pair
        filter/inliers.npz                   F and epipolar inliers of every pair
        epipoles/epipoles.npz                relative poses of every pair
        registration/registration.npz, registration.json
        triangulation/sparse.npz, sparse.ply (model 0), summary.json, models/<k>/{cameras,images,points3D,...}.txt
                (.bin when an image name would not read back from COLMAP's text format)
        densify/dense.ply, dense_preview.png, summary.json (no timings: those are in the manifest's summary),
                depth/<stem>.npz, depth/<stem>.png,
                dense_mesh.ply, dense_mesh_preview.png   (the trimmed Poisson mesh, densify.mesh)
        eval/metrics.json                                    (fullview eval)
        colmap_<render type>/model/                          (fullview compare: cached COLMAP reference)
        compare_<render type>/colmap.json, colmap.md, top_view.png   (fullview compare)
        colmap_check/check.json, check.md, database.db, faces/       (fullview colmap-check)
        export_<format>/...                                  (fullview export)
        scale/statement.json                                 (export --camera-height / --known-distance: the
                                                             user's statement of the metric scale, kept)
        view_cache/<stem>_<width>_<image hash>.jpg           (fullview view: panoramas at display width)
        report/index.html, *.png                             (fullview report)

Reading goes through `Workspace` (``load_*``); writing only through a `StageWriter` (``save_*``), which exists only
inside `Workspace.transaction` and is bound to that run's temporary folder: no code path can write into a live
folder. A transaction commits by swapping its folder in, under the commit lock, once its manifest is written.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import logging
import os
import shutil
import stat
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from fullview.io.render import save_png
from fullview.io.artifacts import (ArtifactError, apply_umask, load_mesh_ply, load_npz, load_ply, save_bytes,
                                   save_json, save_mesh_ply, save_npz, save_ply, save_text)
from fullview.sfm.camera import pixels_to_bearings

log = logging.getLogger(__name__)

MANIFEST_NAME = "manifest.json"  # written last in every folder a transaction commits
RUN_LOCK = ".fullview.lock"  # held by the process that writes the workspace (holds its pid and command)
COMMIT_LOCK = ".fullview.commit.lock"  # exclusive while a folder is swapped in, shared while a command reads

# Every file of a workspace: artifact -> (folder, name pattern). Patterns take `stem`, `render_type`, `format`, ...
FILES: dict[str, tuple[str, str]] = {
    "manifest": ("{folder}", MANIFEST_NAME),
    "settings": ("", "settings.yaml"),
    "features": ("features", "{stem}.npz"),
    "matches": ("matches", "matches.npz"),
    "inliers": ("filter", "inliers.npz"),
    "epipoles": ("epipoles", "epipoles.npz"),
    "registration": ("registration", "registration.npz"),
    "registration_report": ("registration", "registration.json"),
    "sparse": ("triangulation", "sparse.npz"),
    "sparse_cloud": ("triangulation", "sparse.ply"),
    "sparse_summary": ("triangulation", "summary.json"),
    "sparse_model": ("triangulation", "models/{model}"),
    "depth": ("densify", "depth/{stem}.npz"),
    "depth_image": ("densify", "depth/{stem}.png"),
    "dense_cloud": ("densify", "dense.ply"),
    "dense_preview": ("densify", "dense_preview.png"),
    "dense_summary": ("densify", "summary.json"),
    "dense_mesh": ("densify", "dense_mesh.ply"),
    "dense_mesh_preview": ("densify", "dense_mesh_preview.png"),
    "eval_metrics": ("eval", "metrics.json"),
    "colmap_reference": ("colmap_{render_type}", "model"),
    "colmap_reference_images": ("colmap_{render_type}", "panoramas"),
    "compare_report": ("compare_{render_type}", "colmap.json"),
    "compare_markdown": ("compare_{render_type}", "colmap.md"),
    "compare_top_view": ("compare_{render_type}", "top_view.png"),
    "check_report": ("colmap_check", "check.json"),
    "check_markdown": ("colmap_check", "check.md"),
    "check_database": ("colmap_check", "database.db"),
    "check_face": ("colmap_check", "faces/{face}.png"),
    "export_dir": ("export_{format}", ""),
    "scale_statement": ("scale", "statement.json"),
    "view_cache": ("view_cache", "{stem}.jpg"),
    "report_page": ("report", "index.html"),
    "report_asset": ("report", "{file}"),
}

FEATURES_VERSION = 1
PAIRS_VERSION = 1
EPIPOLES_VERSION = 1
REGISTRATION_VERSION = 2  # 2: model_id (N,) (several models; `registered` = in model 0)
SPARSE_VERSION = 2  # 2: model_id (N,), point_model (P,)
DEPTH_VERSION = 1  # range (H, W) float32 (NaN invalid), valid (H, W) bool
FEATURE_KEYS = ("pixels", "bearings", "descriptors", "scales", "colors", "image_size")
# `registered`: the image is in model 0, the main model; `model_id`: its model (-1: none), poses in that model's frame
POSE_KEYS = ("image_names", "registered", "model_id", "R_cam_from_world", "t_cam_from_world", "centers")
HAND_COLOR = (255, 0, 0)  # hand points are drawn red in the sparse cloud
MANIFEST_KEYS = {"fingerprint": str, "upstream": dict, "outputs": dict}
# Without -w a dataset's workspace is this hidden folder inside it: found from any folder, moved with the dataset,
# never listed as input (images are read from images/ only).
DATASET_WORKSPACE = ".fullview"


# Descriptors of the locks this process holds (run, commit and shared reading locks). A forked child inherits
# them, and an flock lives as long as any descriptor of it: `close_inherited_locks` closes the child's copies, so
# a child that outlives its parent (kill -9) cannot keep the workspace locked.
_LOCK_FDS: set[int] = set()


def _open_lock(path: Path, flags: int = os.O_RDWR | os.O_CREAT) -> int:
    fd = os.open(path, flags | os.O_CLOEXEC, 0o666)  # O_CLOEXEC: no exec'd program inherits it either
    _LOCK_FDS.add(fd)
    return fd


def _close_lock(fd: int) -> None:
    _LOCK_FDS.discard(fd)
    os.close(fd)  # closing releases the lock (unless a forked child holds a copy)


def close_inherited_locks() -> None:
    """In a forked child only: close its copies of the parent's lock descriptors (closing, never unlocking: an
    unlock would release the parent's lock too)."""
    for fd in list(_LOCK_FDS):
        try:
            os.close(fd)
        except OSError:
            pass
    _LOCK_FDS.clear()


class WorkspaceBusy(ArtifactError):
    """Another process holds the workspace's run lock."""


@dataclass(kw_only=True)
class PairData:
    pairs: list[tuple[int, int]]  # image index pairs (i < j)
    matches: list[np.ndarray]  # per pair (M, 2) feature indices (extended index space, see load_observations)
    extra: dict[str, np.ndarray]  # further per-pair arrays (P, ...)


def folder_of(artifact: str, **fields) -> str:
    return FILES[artifact][0].format(**fields)


def _relative(artifact: str, **fields) -> str:
    return FILES[artifact][1].format(**fields)


def image_stem(name: str) -> str:
    """The name an image's per-image artifacts are filed under (its file name without the suffix)."""
    return Path(name).stem


# ---------------------------------------------------------------------------------------------------- reading
class Workspace:
    """Read access to one dataset's artifacts, the locks, and the transactions that write them."""

    def __init__(self, root: Path, dataset_name: str):
        self.root = Path(root) / dataset_name
        self._lock_depth = 0
        self._lock_fd: int | None = None

    @classmethod
    def of_dataset(cls, dataset_root: Path) -> "Workspace":
        """The default workspace of a dataset (no -w): <dataset>/.fullview/, whatever the current folder."""
        return cls(Path(dataset_root).resolve(), DATASET_WORKSPACE)

    def workspace_option(self, dataset_root: Path) -> str:
        """What a command line needs to find this workspace: "" for the dataset's default one, else " -w ROOT"."""
        return "" if self.root == Path(dataset_root).resolve() / DATASET_WORKSPACE else f" -w {self.root.parent}"

    def check_root(self) -> None:
        """An error when the workspace path cannot be a folder (it or a parent is a file)."""
        for p in [self.root, *self.root.parents]:
            if p.exists():
                if not p.is_dir():
                    raise ArtifactError(f"{p}: exists and is not a folder")
                return

    def folder(self, name: str) -> Path:
        return self.root / name

    def path(self, artifact: str, **fields) -> Path:
        """The live path of an artifact (for reading; writers get theirs from a StageWriter)."""
        return self.root / folder_of(artifact, **fields) / _relative(artifact, **fields)

    # ---- manifests and verification
    def manifest(self, folder: str) -> tuple[dict | None, str | None]:
        """(manifest, problem): (None, None) when never run; (None, reason) when unreadable or malformed."""
        return parse_manifest(self.path("manifest", folder=folder))

    def read_manifest(self, folder: str) -> dict | None:
        """The folder's manifest, or None when it is missing or malformed."""
        return self.manifest(folder)[0]

    def verify(self, folder: str, manifest: dict, *, deep: bool) -> str | None:
        """None when every output the manifest lists is on disk with its size (and, if `deep`, its sha256);
        otherwise the first problem, naming the file."""
        base = self.folder(folder)
        for rel, expected in manifest["outputs"].items():
            path = base / rel
            try:
                info = path.stat()
            except OSError:
                return f"{path} is missing"
            size = info.st_size
            if not stat.S_ISREG(info.st_mode):  # a FIFO would block the hash, a device never end it
                return f"{path} is not a regular file"
            if size != expected["size"]:
                return f"{path} has {size} bytes, its stage wrote {expected['size']}"
            if deep and file_sha256(path) != expected["sha256"]:
                return f"{path} was modified after its stage wrote it"
        return None

    # ---- typed readers, one per artifact
    def load_features(self, image_name: str, keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """An image's features; only `keys` of them when given (the others are not read)."""
        path = self.path("features", stem=image_stem(image_name))
        if keys is None:
            return load_npz(path, FEATURES_VERSION, FEATURE_KEYS)
        return load_npz(path, FEATURES_VERSION, keys, only=True)

    def load_descriptors(self, image_name: str) -> np.ndarray:
        return self.load_features(image_name, ("descriptors",))["descriptors"]

    def load_matches(self) -> PairData:
        return _load_pair_data(self.path("matches"))

    def load_inliers(self) -> PairData:
        return _load_pair_data(self.path("inliers"))

    def load_epipoles(self) -> dict[str, np.ndarray]:
        return load_npz(self.path("epipoles"), EPIPOLES_VERSION,
                        ("pairs", "R_j_from_i", "t_j_from_i", "e_i", "e_j", "num_inliers", "valid"))

    def load_registration(self) -> dict[str, np.ndarray]:
        return load_npz(self.path("registration"), REGISTRATION_VERSION, POSE_KEYS + ("pair_inlier_mask",))

    def verified_mask(self) -> np.ndarray:
        """(N,) images registration placed on evidence (verdict verified or own_model): approximate cameras, placed
        by a join nothing confirms, are False (densify and the exports leave them out; docs/trust.md). A
        registration written before verdicts existed: every placed image."""
        reg = load_npz(self.path("registration"), REGISTRATION_VERSION, ("model_id",))
        return reg["verified"].astype(bool) if "verified" in reg else reg["model_id"] >= 0

    def load_sparse(self) -> dict[str, np.ndarray]:
        return load_npz(self.path("sparse"), SPARSE_VERSION,
                        POSE_KEYS + ("points", "colors", "point_model", "track_ids", "image_ids", "feature_ids",
                                     "obs_error_rad"))

    def load_sparse_model(self, model: int = 0) -> dict[str, np.ndarray]:
        """The sparse arrays of one model, in its own frame: its points and their observations (point rows
        renumbered), the poses of every image with ``registered`` marking the model's images."""
        sparse = self.load_sparse()
        return select_model(sparse, model)

    def load_depth(self, image_name: str) -> dict[str, np.ndarray] | None:
        """A panorama's range map (``range``, ``valid``), or None if densify gave it none."""
        path = self.path("depth", stem=image_stem(image_name))
        return load_npz(path, DEPTH_VERSION, ("range", "valid")) if path.exists() else None

    def load_dense_cloud(self) -> dict[str, np.ndarray] | None:
        """Columns of the fused cloud (x, y, z, nx, ny, nz, red, green, blue), or None when there is none."""
        path = self.path("dense_cloud")
        return load_ply(path) if path.exists() else None

    def load_dense_mesh(self) -> dict[str, np.ndarray] | None:
        """The trimmed mesh of the dense cloud (``vertices``, ``colors``, ``triangles``), or None when there is none."""
        path = self.path("dense_mesh")
        return load_mesh_ply(path) if path.exists() else None

    def load_json(self, artifact: str, **fields) -> dict | None:
        path = self.path(artifact, **fields)
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ArtifactError(f"{path}: corrupt ({type(e).__name__}); rerun its stage") from None

    def load_observations(self, dataset) -> list[dict[str, np.ndarray]]:
        """Per image: SIFT features followed by the image's hand observations (the extended feature index space).

        Feature index k < num_sift refers to SIFT feature k; k >= num_sift to hand observation k - num_sift.
        """
        hand = dataset.hand_observations
        out = []
        for name in dataset.image_names:
            feats = self.load_features(name, ("pixels", "bearings", "colors", "image_size"))
            w, h = (int(v) for v in feats["image_size"])
            _, hand_px = hand[name]
            out.append({
                "pixels": np.concatenate([feats["pixels"], hand_px]),
                "bearings": np.concatenate([feats["bearings"], pixels_to_bearings(hand_px, w, h).reshape(-1, 3)]),
                "colors": np.concatenate([feats["colors"], np.tile(np.uint8(HAND_COLOR), (len(hand_px), 1))]),
                "num_sift": np.int64(len(feats["pixels"])),
                "image_size": feats["image_size"],
            })
        return out

    def poses_source(self) -> str | None:
        """Which stage holds the most refined poses: triangulation if it ran on the registration on disk, else
        registration, else None."""
        tri, reg = self.read_manifest("triangulation"), self.read_manifest("registration")
        if tri and reg and tri["upstream"].get("registration") == reg["fingerprint"]:
            return "triangulation"
        return "registration" if reg else None

    def load_poses(self) -> tuple[dict[str, np.ndarray], str]:
        """The most refined poses (see `poses_source`) and the stage they come from."""
        source = self.poses_source()
        if source == "triangulation":
            return load_npz(self.path("sparse"), SPARSE_VERSION, POSE_KEYS), source
        if source == "registration":
            return load_npz(self.path("registration"), REGISTRATION_VERSION, POSE_KEYS), source
        raise ArtifactError(f"{self.root}: no registration or triangulation results; run the pipeline first")

    def cached_bytes(self, artifact: str, produce, **fields) -> bytes:
        """A cache file (not a stage artifact: its name carries what it depends on, so it is never stale): read when
        present, else produced, and written atomically when the workspace is writable."""
        path = self.path(artifact, **fields)
        if path.exists():
            return path.read_bytes()
        data = produce()
        try:
            make_dirs(path.parent)
            save_bytes(path, data)
        except OSError as e:
            log.warning("cache not written to %s: %s", path, e)
        return data

    # ---- locks
    @contextmanager
    def locked(self, *, wait: bool = False, command: str = "fullview") -> Iterator[None]:
        """The run lock (an OS file lock, released when the process dies); re-entrant within one process.

        Raises WorkspaceBusy naming the holder unless `wait`."""
        if self._lock_depth:
            self._lock_depth += 1
            try:
                yield
            finally:
                self._lock_depth -= 1
            return
        make_dirs(self.root)
        fd = _open_lock(self.root / RUN_LOCK)
        try:
            _acquire(fd, self.root, wait)
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps({"pid": os.getpid(), "command": command,
                                      "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode(), 0)
            self._lock_fd, self._lock_depth = fd, 1
            self._clean_leftovers()
            yield
        finally:
            self._lock_depth, self._lock_fd = 0, None
            _close_lock(fd)

    @property
    def is_locked(self) -> bool:
        return self._lock_depth > 0

    @contextmanager
    def reading(self) -> Iterator[None]:
        """Shared commit lock: no stage is swapped in while a read-only command reads the workspace."""
        fd = _open_for_shared_lock(self.root / COMMIT_LOCK)
        if fd is None:
            yield
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_SH)
            yield
        finally:
            _close_lock(fd)

    # ---- writing
    @contextmanager
    def transaction(self, folder: str) -> Iterator["StageWriter"]:
        """A writer bound to a fresh temporary folder; swapped in for `folder` only when the body finishes and the
        writer's manifest is written. Requires the run lock."""
        if not self.is_locked:
            raise RuntimeError(f"{self.root}: writing {folder} needs the workspace lock")
        with folder_transaction(self.folder(folder), commit_lock=self._commit_lock) as writer:
            yield writer

    @contextmanager
    def _commit_lock(self) -> Iterator[None]:
        fd = _open_lock(self.root / COMMIT_LOCK)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            _close_lock(fd)

    def _clean_leftovers(self) -> None:
        """Under the lock only: remove temp folders of killed runs; restore a folder whose swap was cut short."""
        for p in self.root.glob(".*.old.*"):
            for saved in p.iterdir():
                if not self.folder(saved.name).exists():
                    saved.rename(self.folder(saved.name))
            shutil.rmtree(p, ignore_errors=True)
        for p in self.root.glob(".*.running.*"):
            shutil.rmtree(p, ignore_errors=True)


# ---------------------------------------------------------------------------------------------------- writing
class StageWriter:
    """Writes the artifacts of one folder (stage or command output) into its transaction's temporary folder."""

    def __init__(self, folder: str, directory: Path):
        self.folder, self.dir, self.committed = folder, Path(directory), False
        self._hashes: dict[Path, tuple[int, int, str]] = {}  # (size, mtime_ns, sha256) taken by writing tasks

    def _hashed(self, path: Path) -> Path:
        """Take `path`'s sha256 now, on the task that wrote it (in the page cache, and the tasks run in parallel):
        `commit_manifest` uses it instead of reading the file again while its size and mtime are unchanged."""
        st = path.stat()
        self._hashes[path] = (st.st_size, st.st_mtime_ns, file_sha256(path))
        return path

    def _sha256(self, path: Path) -> str:
        st, known = path.stat(), self._hashes.get(path)
        return known[2] if known is not None and known[:2] == (st.st_size, st.st_mtime_ns) else file_sha256(path)

    def path(self, artifact: str, **fields) -> Path:
        """Where `artifact` goes in this transaction; an artifact of another folder is refused."""
        owner = folder_of(artifact, **fields)
        if owner != self.folder:
            raise RuntimeError(f"a {self.folder} transaction cannot write {artifact} (it belongs to {owner})")
        return self.dir / _relative(artifact, **fields)

    def save_features(self, image_name: str, **arrays: np.ndarray) -> Path:
        missing = [k for k in FEATURE_KEYS if k not in arrays]
        if missing:
            raise ValueError(f"features of {image_name} lack {missing}")
        return self._hashed(save_npz(self.path("features", stem=image_stem(image_name)), FEATURES_VERSION, **arrays))

    def save_matches(self, pairs, matches, **per_pair: np.ndarray) -> Path:
        return _save_pair_data(self.path("matches"), pairs, matches, **per_pair)

    def save_inliers(self, pairs, matches, **per_pair: np.ndarray) -> Path:
        return _save_pair_data(self.path("inliers"), pairs, matches, **per_pair)

    def save_epipoles(self, **arrays: np.ndarray) -> Path:
        return save_npz(self.path("epipoles"), EPIPOLES_VERSION, **arrays)

    def save_registration(self, *, report: dict, **poses) -> None:
        _save_poses(self.path("registration"), REGISTRATION_VERSION, **poses)
        save_json(self.path("registration_report"), report)

    def save_sparse(self, *, points, colors, point_model, summary: dict, **poses_and_tracks) -> None:
        """The sparse arrays of every model, and the PLY cloud of model 0 (the main model)."""
        _save_poses(self.path("sparse"), SPARSE_VERSION, points=points, colors=colors, point_model=point_model,
                    **poses_and_tracks)
        main = np.asarray(point_model) == 0
        save_ply(self.path("sparse_cloud"), points[main], colors[main])
        save_json(self.path("sparse_summary"), summary)

    def save_depth(self, image_name: str, rng: np.ndarray, valid: np.ndarray, picture: np.ndarray) -> None:
        """A panorama's range map and its colour-mapped picture (BGR uint8)."""
        save_npz(self.path("depth", stem=image_stem(image_name)), DEPTH_VERSION, range=rng, valid=valid)
        save_png(self.path("depth_image", stem=image_stem(image_name)), picture)

    def save_dense(self, *, points, colors, normals, summary: dict) -> None:
        save_ply(self.path("dense_cloud"), points, colors, normals)
        save_json(self.path("dense_summary"), summary)

    def save_dense_mesh(self, *, vertices, triangles, colors) -> Path:
        return save_mesh_ply(self.path("dense_mesh"), vertices, triangles, colors)

    def save_json(self, artifact: str, obj, **fields) -> Path:
        return save_json(self.path(artifact, **fields), obj)

    def save_text(self, artifact: str, text: str, **fields) -> Path:
        return save_text(self.path(artifact, **fields), text)

    def save_bytes(self, artifact: str, data: bytes, **fields) -> Path:
        return save_bytes(self.path(artifact, **fields), data)

    def commit_manifest(self, record: dict) -> dict:
        """Write manifest.json (the record plus size and sha256 of every output); the transaction may commit."""
        for p in self.dir.rglob(".*.tmp"):  # an atomic write cut short (a fan-out task killed on another worker)
            p.unlink()
        outputs = {}
        for p in sorted(self.dir.rglob("*")):
            if p.is_file() and not p.is_symlink() and p.name != MANIFEST_NAME:
                outputs[str(p.relative_to(self.dir))] = {"size": p.stat().st_size, "sha256": self._sha256(p)}
        manifest = {**record, "outputs": outputs}
        save_json(self.dir / MANIFEST_NAME, manifest)
        self.committed = True
        return manifest


# ---------------------------------------------------------------------------------------------------- helpers
MANIFEST_MAX_BYTES = 64 << 20  # ~200 bytes an output: far above the largest manifest (a densify of 10k panoramas, 4 MB)


def parse_manifest(path: Path) -> tuple[dict | None, str | None]:
    """(manifest, problem) of a manifest file: (None, None) when absent, (None, reason) when malformed. Only a
    regular file of at most MANIFEST_MAX_BYTES is read: a link to /dev/zero would fill the memory, a FIFO block."""
    try:
        # O_NONBLOCK: opening a FIFO returns at once (a regular file ignores the flag)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except (FileNotFoundError, NotADirectoryError):
        return (None, f"{path}: broken symbolic link") if os.path.islink(path) else (None, None)
    except OSError as e:
        return None, f"{path}: unreadable manifest ({e.strerror or type(e).__name__})"
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            return None, f"{path}: not a regular file (a FIFO, device or folder named like a manifest)"
        if info.st_size > MANIFEST_MAX_BYTES:
            return None, f"{path}: {info.st_size} bytes, more than a manifest can hold ({MANIFEST_MAX_BYTES})"
        with os.fdopen(os.dup(fd), "rb") as f:
            raw = f.read(MANIFEST_MAX_BYTES + 1)
        if len(raw) > MANIFEST_MAX_BYTES:
            return None, f"{path}: more than a manifest can hold ({MANIFEST_MAX_BYTES} bytes)"
        data = json.loads(raw.decode("utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        return None, f"{path}: unreadable manifest ({type(e).__name__})"
    finally:
        os.close(fd)
    if not isinstance(data, dict):
        return None, f"{path}: malformed manifest (not a mapping)"
    for key, kind in MANIFEST_KEYS.items():
        if not isinstance(data.get(key), kind):
            return None, f"{path}: malformed manifest (no valid {key!r})"
    if not all(isinstance(v, dict) and isinstance(v.get("size"), int) and isinstance(v.get("sha256"), str)
               for v in data["outputs"].values()):
        return None, f"{path}: malformed manifest (bad 'outputs' entry)"
    if not all(_inside_folder(rel) for rel in data["outputs"]):
        return None, f"{path}: malformed manifest (an output outside its folder)"
    return data, None


def _inside_folder(rel: str) -> bool:
    """An output path a manifest may list: relative, without '..' (verification must not read elsewhere)."""
    parts = Path(rel).parts
    return bool(parts) and not Path(rel).is_absolute() and ".." not in parts


def read_manifest_file(folder: Path) -> dict | None:
    """The manifest of any folder a transaction wrote, or None when it has none or a malformed one."""
    return parse_manifest(Path(folder) / MANIFEST_NAME)[0]


@contextmanager
def folder_transaction(final: Path, commit_lock=None, commit=None) -> Iterator[StageWriter]:
    """Write a folder's new content beside it and swap it in only when complete (manifest written); used for
    workspace folders (under the run lock). `commit(tmp, final)` instead of the swap: `folder_update`."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.running.", dir=final.parent))
    apply_umask(tmp, directory=True)
    writer = StageWriter(final.name, tmp)
    try:
        yield writer
        if not writer.committed:
            raise RuntimeError(f"{final}: the transaction ended without a manifest")
        if commit_lock is None:
            (commit or swap_in)(tmp, final)
        else:
            with commit_lock():
                (commit or swap_in)(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if commit is not None:
        shutil.rmtree(tmp, ignore_errors=True)  # what the commit left of the temporary folder


PENDING_KEY = "pending"  # in the manifest of a folder being updated: the outputs being moved in, and those of
# earlier updates cut short (`folder_update`)


@contextmanager
def folder_update(final: Path) -> Iterator[StageWriter]:
    """Write a folder's new content beside it, then move it into `final` file by file: for a folder the user owns
    (``export --out``), where other files may lie that must stay. Only the files the folder's manifest lists, with
    the content it records, are replaced or removed; any other file is left as it is, and the update is refused
    (ArtifactError, nothing moved) when one stands where a new file goes, or a listed file changed since (it is the
    user's now), or a folder on the way is a symbolic link or a file. Each file is replaced atomically; until the new
    manifest is written, last, the old one lists the incoming files as ``pending`` (still ours if the update is cut
    short: the next one finishes it). Two updates of one folder take turns (an exclusive lock on the folder)."""
    existed = final.exists()
    make_dirs(final)
    fd = os.open(final, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ArtifactError(f"{final}: another command is writing this folder; wait for it to finish") from None
        for left in final.parent.glob(f".{final.name}.running.*"):  # of an update killed before it finished
            shutil.rmtree(left, ignore_errors=True)
        with folder_transaction(final, commit_lock=None, commit=_merge_into) as writer:
            yield writer
    except BaseException:
        if not existed:
            try:
                final.rmdir()  # the folder made for it, when still empty
            except OSError:
                pass
        raise
    finally:
        os.close(fd)


def _merge_into(tmp: Path, final: Path) -> None:
    """Move the files of `tmp` (a complete folder with its manifest) into `final` (`folder_update`)."""
    new = read_manifest_file(tmp)
    old, problem = parse_manifest(final / MANIFEST_NAME)
    if problem:  # someone else's file of that name: never overwritten
        raise ArtifactError(f"{problem}; {final} is not a folder a previous export wrote")
    old = old or {"outputs": {}}
    pending = old.get(PENDING_KEY) if isinstance(old.get(PENDING_KEY), list) else []  # of updates cut short
    recorded: dict[str, set[str]] = {}  # file -> the contents (sha256) an update of ours wrote there
    for listing in (old["outputs"], *pending):
        for rel, entry in (listing.items() if isinstance(listing, dict) else ()):
            if isinstance(entry, dict) and isinstance(entry.get("sha256"), str) and _inside_folder(rel):
                recorded.setdefault(rel, set()).add(entry["sha256"])
    incoming = new["outputs"]
    for rel in sorted(set(incoming) | set(recorded)):
        problem = _not_ours(final, rel, recorded.get(rel, set()))
        if problem:
            raise ArtifactError(f"{final / rel}: {problem}; move it out of {final} (or choose another folder), then "
                                "export again")
    save_json(final / MANIFEST_NAME, {**new, "outputs": old["outputs"], PENDING_KEY: [incoming, *pending]})
    for rel in sorted(incoming):
        make_dirs((final / rel).parent)
        os.replace(tmp / rel, final / rel)
    for rel in sorted(set(recorded) - set(incoming)):
        path = final / rel
        if path.is_file():
            path.unlink()
        for parent in path.parents:  # folders the removal left empty (rmdir: never one holding anything)
            if parent == final:
                break
            try:
                parent.rmdir()
            except OSError:
                break
    os.replace(tmp / MANIFEST_NAME, final / MANIFEST_NAME)


def _not_ours(final: Path, rel: str, contents: set[str]) -> str | None:
    """Why `final/rel` may not be replaced or removed by an update whose earlier writes there had `contents`; None
    when it may (absent, or a regular file holding one of them)."""
    path = final
    for part in Path(rel).parts[:-1]:
        path = path / part
        if path.is_symlink() or (path.exists() and not path.is_dir()):
            return f"{path.name} on the way is not a folder of this export"
    path = final / rel
    if not os.path.lexists(path):
        return None
    if path.is_symlink() or not path.is_file():
        return "not a regular file written by a previous export"
    if not contents:
        return "not written by a previous export"
    if file_sha256(path) not in contents:
        return "changed since a previous export wrote it"
    return None


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def make_dirs(path: Path) -> None:
    """mkdir -p honouring the umask; a clear error when a part of the path is a file."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ArtifactError(f"{path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        for part in (path, *path.parents):
            if part.is_symlink() and not part.exists():
                raise ArtifactError(f"{part}: a dangling symbolic link (to {os.readlink(part)!r})") from None
        raise ArtifactError(f"{path}: a part of this path is a file, not a folder") from None


def swap_in(tmp: Path, final: Path) -> None:
    """Replace `final` by `tmp` (both folders on one filesystem); an interruption leaves the old folder in place
    or in a `.<name>.old.*` folder that the next locked run restores."""
    old = None
    try:
        if final.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old.", dir=final.parent))
            final.rename(old / final.name)
        tmp.rename(final)
    except BaseException:
        if old is not None and not final.exists():
            (old / final.name).rename(final)  # put the previous good folder back
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _acquire(fd: int, root: Path, wait: bool) -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    except OSError as e:
        if e.errno not in (errno.EAGAIN, errno.EACCES):
            raise
    holder = _lock_holder(root)
    if not wait:
        raise WorkspaceBusy(f"{root} is in use by {holder}; wait for it to finish or pass --wait")
    log.info("waiting for %s to release %s", holder, root)
    fcntl.flock(fd, fcntl.LOCK_EX)


def _lock_holder(root: Path) -> str:
    try:
        info = json.loads((root / RUN_LOCK).read_text())
        return f"pid {info['pid']} ({info['command']}, since {info['since']})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


def _open_for_shared_lock(path: Path) -> int | None:
    """A descriptor to take a shared lock on; None when the workspace does not exist or cannot hold the file
    (a read-only workspace has no writer to wait for)."""
    if not path.parent.is_dir():
        return None
    try:
        return _open_lock(path)
    except OSError:
        try:
            return _open_lock(path, os.O_RDONLY)
        except OSError:
            return None


def _save_pair_data(path: Path, pairs, matches, **per_pair: np.ndarray) -> Path:
    """Per-pair match lists stored flat (CSR): `pairs` (P,2), `offsets` (P+1,), `matches` (M,2), plus (P,...) arrays."""
    offsets = np.concatenate([[0], np.cumsum([len(m) for m in matches])]).astype(np.int64)
    flat = np.concatenate(matches).astype(np.int64) if len(matches) else np.zeros((0, 2), np.int64)
    return save_npz(path, PAIRS_VERSION, pairs=np.asarray(pairs, np.int64).reshape(-1, 2), offsets=offsets,
                    matches=flat.reshape(-1, 2), **per_pair)


def _load_pair_data(path: Path) -> PairData:
    data = load_npz(path, PAIRS_VERSION, ("pairs", "offsets", "matches"))
    pairs = [tuple(int(v) for v in p) for p in data.pop("pairs")]
    offsets, flat = data.pop("offsets"), data.pop("matches")
    if len(offsets) != len(pairs) + 1 or (len(offsets) and offsets[-1] != len(flat)):
        raise ArtifactError(f"{path}: inconsistent pair offsets; rerun its stage")
    return PairData(pairs=pairs, matches=[flat[offsets[k]:offsets[k + 1]] for k in range(len(pairs))], extra=data)


def select_model(sparse: dict[str, np.ndarray], model: int) -> dict[str, np.ndarray]:
    """`sparse` (as `Workspace.load_sparse` returns it) restricted to one model's points and observations."""
    keep = sparse["point_model"] == model
    row = np.cumsum(keep) - 1
    obs = keep[sparse["track_ids"]]
    out = dict(sparse)
    for key in ("points", "colors", "point_error_rad", "point_model"):
        if key in sparse:
            out[key] = sparse[key][keep]
    out["track_ids"] = row[sparse["track_ids"][obs]]
    for key in ("image_ids", "feature_ids", "obs_error_rad"):
        out[key] = sparse[key][obs]
    out["registered"] = sparse["model_id"] == model
    return out


def _save_poses(path: Path, version: int, *, image_names: list[str], registered: np.ndarray,
                R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, **extra: np.ndarray) -> Path:
    """Camera poses with centres for convenience."""
    centers = -np.einsum("nba,nb->na", R_cam_from_world, t_cam_from_world)
    return save_npz(path, version, image_names=np.array(image_names), registered=registered,
                    R_cam_from_world=R_cam_from_world, t_cam_from_world=t_cam_from_world, centers=centers, **extra)
