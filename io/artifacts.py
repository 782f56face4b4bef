"""Artifact formats: versioned npz, JSON, binary PLY; every write is atomic (temp file + os.replace)."""

from __future__ import annotations

import errno
import json
import os
import tempfile
import threading
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from fullview.io.errors import FullviewError

FORMAT_KEY = "format_version"


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


UMASK = _read_umask()  # read once: os.umask can only be read by setting it, which is not thread-safe


class ArtifactError(FullviewError, RuntimeError):
    """An artifact on disk is missing, of another version, or lacks a key."""


def apply_umask(path: Path, *, directory: bool = False) -> None:
    """Give a file or folder made by tempfile (0600 / 0700) the permissions open() and mkdir() would give it."""
    os.chmod(path, (0o777 if directory else 0o666) & ~UMASK)


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it replaces `path`, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        apply_umask(Path(tmp))
        yield Path(tmp)
        with open(tmp, "rb+") as f:  # flush to disk before the rename makes it visible
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            # A write's OSError names no file: name the artifact and the stage whose transaction folder holds it.
            stage = next((p.name.split(".")[1] for p in path.parents
                          if p.name.startswith(".") and ".running." in p.name), None)
            during = f" (writing the {stage} stage's output)" if stage else ""
            raise ArtifactError(f"{path}: {os.strerror(e.errno)}{during}; free some space and run "
                                f"again") from None
        raise


def save_npz(path: Path, version: int, **arrays: np.ndarray) -> Path:
    """Write arrays plus a format version key; never pickles objects."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **{FORMAT_KEY: np.int64(version)}, **{k: np.asarray(v) for k, v in arrays.items()})
    return Path(path)


# numpy parses every .npy header with ast.literal_eval, and CPython 3.11 keeps the AST constructor's recursion depth
# per interpreter, not per thread: two threads parsing at once can fail with "SystemError: AST constructor recursion
# depth mismatch" (python/cpython#106905). Stages load features on several threads at once, so npz reads take turns.
_NPZ_READ_LOCK = threading.Lock()


def load_npz(path: Path, version: int, keys: tuple[str, ...] = (), *, only: bool = False) -> dict[str, np.ndarray]:
    """Load an npz written by `save_npz`, checking its version and required keys; with `only`, just those keys are
    read (an npz member is read when asked for: the features' descriptors are 90% of their file). One thread reads
    at a time (`_NPZ_READ_LOCK`)."""
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"missing artifact {path}")
    try:
        with _NPZ_READ_LOCK, np.load(path, allow_pickle=False) as data:
            found = int(data[FORMAT_KEY]) if FORMAT_KEY in data else None
            if found != version:
                raise ArtifactError(f"{path}: format version {found}, expected {version}; rerun its stage")
            missing = [k for k in keys if k not in data]
            if missing:
                raise ArtifactError(f"{path}: missing keys {missing}")
            return {k: data[k] for k in (keys if only else data.files) if k != FORMAT_KEY}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
        raise ArtifactError(f"{path}: corrupt artifact ({type(e).__name__}: {e}); rerun its stage with --from") from None


def save_json(path: Path, obj) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")
    return Path(path)


def save_text(path: Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def save_bytes(path: Path, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _write_ply(path: Path, header: list[str], *blocks: np.ndarray) -> Path:
    """Atomically write a binary PLY: its header lines (without the ``ply`` / ``end_header`` frame) then the blocks."""
    lines = ["ply", "format binary_little_endian 1.0", *header, "end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(lines) + "\n").encode("ascii"))
            for block in blocks:
                f.write(block.tobytes())
    return Path(path)


def _read_ply_header(f) -> list[str]:
    """The header lines of an open PLY, up to ``end_header`` (a ValueError when there is none)."""
    lines: list[str] = []
    while not lines or lines[-1] != "end_header":
        line = f.readline()
        if not line or len(lines) > 64:
            raise ValueError("no end_header")
        lines.append(line.decode("ascii").strip())
    return lines


def save_ply(path: Path, points: np.ndarray, colors: np.ndarray | None = None,
             normals: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY with float32 xyz, optional float32 normals and uint8 rgb."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(points), dtype=fields)
    rec["x"], rec["y"], rec["z"] = points.T
    if normals is not None:
        rec["nx"], rec["ny"], rec["nz"] = np.asarray(normals, np.float32).reshape(-1, 3).T
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = np.asarray(colors, np.uint8).reshape(-1, 3).T
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = [f"element vertex {len(points)}"] + [f"property {ply_type[t]} {n}" for n, t in fields]
    return _write_ply(path, header, rec)


def load_ply(path: Path) -> dict[str, np.ndarray]:
    """Read a binary PLY written by `save_ply` into named columns."""
    try:
        with open(path, "rb") as f:
            lines = _read_ply_header(f)
            count = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
            props = [l.split() for l in lines if l.startswith("property")]
            dtype = [(p[2], {"float": "<f4", "uchar": "u1"}[p[1]]) for p in props]
            rec = np.frombuffer(f.read(), dtype=dtype, count=count)
    except (ValueError, KeyError, IndexError, StopIteration, UnicodeDecodeError) as e:
        raise ArtifactError(f"{path}: corrupt PLY ({type(e).__name__}); rerun its stage") from None
    return {name: rec[name] for name, _ in dtype}


def save_mesh_ply(path: Path, vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> Path:
    """Binary little-endian PLY of a triangle mesh: float32 xyz and uint8 rgb per vertex, int32 vertex triples."""
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    vert = np.empty(len(vertices), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1")])
    vert["x"], vert["y"], vert["z"] = vertices.T
    vert["red"], vert["green"], vert["blue"] = np.asarray(colors, np.uint8).reshape(-1, 3).T
    faces = np.empty(len(triangles), [("n", "u1"), ("v", "<i4", (3,))])
    faces["n"], faces["v"] = 3, np.asarray(triangles, np.int32).reshape(-1, 3)
    header = [f"element vertex {len(vert)}", "property float x", "property float y", "property float z",
              "property uchar red", "property uchar green", "property uchar blue", f"element face {len(faces)}",
              "property list uchar int vertex_indices"]
    return _write_ply(path, header, vert, faces)


def load_mesh_ply(path: Path) -> dict[str, np.ndarray]:
    """A mesh written by `save_mesh_ply`: ``vertices`` (V, 3) float32, ``colors`` (V, 3) uint8, ``triangles``
    (T, 3) int32 (indices checked)."""
    vert_dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    face_dtype = [("n", "u1"), ("v", "<i4", (3,))]
    try:
        with open(path, "rb") as f:
            lines = _read_ply_header(f)
            counts = {l.split()[1]: int(l.split()[2]) for l in lines if l.startswith("element")}
            data = f.read()
        size = counts["vertex"] * 15 + counts["face"] * 13
        if len(data) != size:
            raise ValueError(f"{len(data)} bytes of data, expected {size}")
        vert = np.frombuffer(data, vert_dtype, counts["vertex"])
        faces = np.frombuffer(data, face_dtype, counts["face"], offset=counts["vertex"] * 15)
        if (faces["n"] != 3).any() or (faces["v"] < 0).any() or (faces["v"] >= len(vert)).any():
            raise ValueError("bad faces")
    except (ValueError, KeyError, IndexError, UnicodeDecodeError) as e:
        raise ArtifactError(f"{path}: corrupt mesh PLY ({type(e).__name__}: {e}); rerun its stage") from None
    return {"vertices": np.column_stack([vert["x"], vert["y"], vert["z"]]),
            "colors": np.column_stack([vert["red"], vert["green"], vert["blue"]]),
            "triangles": np.ascontiguousarray(faces["v"])}
