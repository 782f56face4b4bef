"""What the viewer page shows, read from the workspace through its owner: stage states, cameras and their
neighbours, point clouds for the 3-D scene, inlier matches of a pair, and downscaled panoramas from a cache."""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import stat
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from fullview.io.artifacts import ArtifactError
from fullview.io.errors import FullviewError
from fullview.io.workspace import image_stem
from fullview.sfm import two_view
from fullview.sfm.camera import bearings_to_lonlat, camera_up, pixels_to_bearings
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline

log = logging.getLogger(__name__)

NEIGHBOURS = 4  # hotspots per panorama: its nearest registered panoramas among those it shares verified pairs with
POINT_SEED = 0  # clouds are shuffled once, so any prefix is a uniform subsample (the page's point budget)


class RequestError(FullviewError):
    """A request the viewer refuses, with the HTTP status it answers (400 bad input, 403 refused, 404 absent)."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


class SceneData:
    """The page's data for one pipeline (dataset, workspace, config); reloads when the workspace changes."""

    def __init__(self, pipeline: Pipeline):
        self.pipeline = pipeline
        self.dataset, self.ws = pipeline.dataset, pipeline.ws

    # ---------------------------------------------------------------------------------------------- state
    def generation(self) -> str:
        """Changes whenever a stage is committed: the page polls it to notice a workspace that changed."""
        stamps = {s: _mtime(self.ws.path("manifest", folder=s)) for s in PIPELINE}  # a rerun commits a new one
        return hashlib.sha256(json.dumps(stamps, sort_keys=True).encode()).hexdigest()[:12]

    def state(self) -> dict:
        self.pipeline.refresh()  # images, hand points or masks may have changed since the page last asked
        with self.ws.reading():
            stages = {s: _status(self.pipeline, s) for s in PIPELINE}
            out = {"dataset": self.dataset.name, "generation": self.generation(), "stages": stages,
                   "images": [{"name": n, "size": self.dataset.image_sizes[n]} for n in self.dataset.image_names],
                   "model": None, "message": _message(stages)}
            if stages["registration"]["state"] != "missing":
                try:
                    out["model"] = self._model(stages)
                except ArtifactError as e:
                    out["message"] = f"cannot read the reconstruction: {e}"
        return out

    def _model(self, stages: dict) -> dict:
        poses, source = self.ws.load_poses()
        registered = poses["registered"].astype(bool)
        R, centers = poses["R_cam_from_world"], poses["centers"]
        names = [str(n) for n in poses["image_names"]]
        links = self._links(len(names))
        cams = []
        for k, name in enumerate(names):
            cams.append({"name": name, "registered": bool(registered[k]),
                         "R_cam_from_world": R[k].tolist() if registered[k] else None,
                         "center": centers[k].tolist() if registered[k] else None,
                         "neighbours": _neighbours(k, R, centers, registered, links, names)})
        reg = registered.nonzero()[0]
        return {"poses_from": source, "cameras": cams,
                "unregistered": [n for n, ok in zip(names, registered) if not ok],
                "unregistered_reasons": ((self.ws.read_manifest("registration") or {}).get("summary") or {})
                .get("unregistered_reasons", {}),
                "R_display_from_world": display_rotation(R[reg], centers[reg]).tolist(),
                "has_sparse": source == "triangulation", "has_dense": stages["densify"]["state"] == "fresh",
                "has_mesh": stages["densify"]["state"] == "fresh" and self.ws.path("dense_mesh").exists(),
                "pairs": self._pairs(names)}

    def _links(self, n: int) -> np.ndarray:
        """(N, N) verified inliers between images (0 = no verified pair)."""
        links = np.zeros((n, n))
        try:
            epi = self.ws.load_epipoles()
        except ArtifactError:
            return links
        ok = epi["valid"].astype(bool)
        i, j = epi["pairs"][ok].T
        links[i, j] = links[j, i] = epi["num_inliers"][ok]
        return links

    def _pairs(self, names: list[str]) -> list[dict]:
        try:
            verified = self.ws.load_inliers()
        except ArtifactError:
            return []
        return [{"a": names[i], "b": names[j], "inliers": int(len(m))}
                for (i, j), m in zip(verified.pairs, verified.matches) if len(m)]

    # ---------------------------------------------------------------------------------------------- points
    def points(self, kind: str) -> bytes:
        """A cloud as bytes: uint32 count, float32 xyz (world frame) and uint8 rgb, in a fixed random order."""
        return _cloud_bytes(self.ws.root, kind, self.generation(), self)

    def load_cloud(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        with self.ws.reading():
            if kind == "sparse":
                sparse = self.ws.load_sparse_model(0)
                return sparse["points"], sparse["colors"]
            cloud = self.ws.load_dense_cloud()
        if cloud is None:
            return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        return (np.column_stack([cloud["x"], cloud["y"], cloud["z"]]),
                np.column_stack([cloud["red"], cloud["green"], cloud["blue"]]))

    def mesh(self) -> bytes:
        """The dense mesh as bytes: uint32 vertex and triangle counts, float32 xyz (world frame), uint8 rgb, zero
        padding to a multiple of 4 bytes, uint32 vertex indices (three per triangle); empty counts when none."""
        return _mesh_bytes(self.ws.root, self.generation(), self)

    def load_mesh(self) -> dict[str, np.ndarray] | None:
        with self.ws.reading():
            return self.ws.load_dense_mesh()

    def matches(self, a: str, b: str) -> list[list[float]]:
        """Inlier matches of a verified pair as [x_a, y_a, x_b, y_b] pixels of the full-size panoramas."""
        names = self.dataset.image_names
        i, j = names.index(self.image(a)), names.index(self.image(b))
        flip = i > j
        if flip:
            i, j = j, i
        with self.ws.reading():
            verified = self.ws.load_inliers()
            obs = self.ws.load_observations(self.dataset)
        m = dict(zip(verified.pairs, verified.matches)).get((i, j), np.zeros((0, 2), int))
        px = np.column_stack([obs[i]["pixels"][m[:, 0]], obs[j]["pixels"][m[:, 1]]])
        return (px[:, [2, 3, 0, 1]] if flip else px).round(2).tolist()

    # ---------------------------------------------------------------------------------------------- hand points
    def hand_check(self, points: list, threshold_deg: float) -> list[dict]:
        """For every pair of images sharing >= 8 hand tracks: the F those tracks give (b_aᵀ F b_b = 0, bearings)
        and each track's angular distance to its epipolar circle; tracks beyond `threshold_deg` are flagged."""
        sizes = self.dataset.image_sizes
        names = self.dataset.image_names
        obs = _picks(points, sizes)
        out = []
        for a_idx, a in enumerate(names):
            for b in names[a_idx + 1:]:
                shared = sorted(set(obs.get(a, {})) & set(obs.get(b, {})))
                if len(shared) < 8:
                    continue
                b_a = pixels_to_bearings(np.array([obs[a][t] for t in shared]), *sizes[a])
                b_b = pixels_to_bearings(np.array([obs[b][t] for t in shared]), *sizes[b])
                F = _hand_f(b_a, b_b, np.radians(threshold_deg))
                errors = np.degrees(two_view.epipolar_angular_errors(F, b_a, b_b))
                out.append({"a": a, "b": b, "F": F.tolist(), "errors_deg": dict(zip(shared, errors.tolist())),
                            "flagged": [t for t, e in zip(shared, errors) if e > threshold_deg]})
        return out

    # ---------------------------------------------------------------------------------------------- images
    def panorama_jpeg(self, name: str, width: int) -> bytes:
        """The panorama at a display width (never above native), from the workspace's cache."""
        native = self.dataset.image_sizes[name][0]
        width = int(min(max(width, 256), native))
        key = self.dataset.image_hash(name)[:12]
        stem = f"{image_stem(name)}_{width}_{key}"
        if os.path.lexists(cached := self.ws.path("view_cache", stem=stem)):
            self.workspace_file(cached)  # the cache is read back as it is: only from inside the workspace

        def encode() -> bytes:
            ok, jpg = cv2.imencode(".jpg", self.dataset.load_image(name, width=width), [cv2.IMWRITE_JPEG_QUALITY, 88])
            if not ok:
                raise ArtifactError(f"cannot encode {name} for display")
            return jpg.tobytes()

        return self.ws.cached_bytes("view_cache", encode, stem=stem)

    def depth_png(self, name: str) -> bytes | None:
        path = self.ws.path("depth_image", stem=image_stem(self.image(name)))
        return self.workspace_file(path).read_bytes() if os.path.lexists(path) else None

    # ---------------------------------------------------------------------------------------------- what is served
    def image(self, name: str) -> str:
        """`name` when it is in the dataset's image list (the only images served), else a RequestError."""
        if name not in self.dataset.image_names:
            raise RequestError(f"unknown image {name!r}: not in {self.dataset.images_dir}", 404)
        return name

    def workspace_file(self, path: Path) -> Path:
        """The real path of a workspace file about to be served: a regular file whose real path lies inside this
        dataset's workspace folder, else a RequestError (a symbolic link planted there cannot serve /etc/passwd)."""
        real, root = os.path.realpath(path), os.path.realpath(self.ws.root)
        try:
            regular = stat.S_ISREG(os.stat(real).st_mode)
        except OSError:
            regular = False
        if os.path.commonpath([real, root]) != root or not regular:
            raise RequestError(f"{path}: not served (not a regular file inside the workspace {root})", 403)
        return Path(real)


@lru_cache(maxsize=4)
def _cloud_bytes(root, kind: str, generation: str, scene: SceneData) -> bytes:
    points, colors = scene.load_cloud(kind)
    order = np.random.default_rng(POINT_SEED).permutation(len(points))
    head = np.array([len(points)], "<u4").tobytes()
    return head + points[order].astype("<f4").tobytes() + colors[order].astype(np.uint8).tobytes()


@lru_cache(maxsize=2)
def _mesh_bytes(root, generation: str, scene: SceneData) -> bytes:
    mesh = scene.load_mesh()
    if mesh is None:
        return np.zeros(2, "<u4").tobytes()
    vertices, colors, triangles = mesh["vertices"], mesh["colors"], mesh["triangles"]
    head = np.array([len(vertices), len(triangles)], "<u4").tobytes()
    rgb = colors.astype(np.uint8).tobytes()
    pad = bytes(-len(rgb) % 4)  # the page views the indices as a Uint32Array, which needs 4-byte alignment
    return head + vertices.astype("<f4").tobytes() + rgb + pad + triangles.astype("<u4").tobytes()


def _picks(points, sizes: dict[str, tuple[int, int]]) -> dict[str, dict[str, tuple[float, float]]]:
    """The page's picks ({"points": [{"name", "observations": {image: [x, y]}}]}, tracks of any length) as
    image -> track name -> pixel; a RequestError naming the first thing that is not a finite pixel of a known image."""
    if not isinstance(points, list):
        raise RequestError('expected a JSON object {"points": [...]}')
    obs: dict[str, dict[str, tuple[float, float]]] = {}
    for k, point in enumerate(points):
        if not isinstance(point, dict):
            raise RequestError(f"points[{k}]: expected an object {{name, observations}}, got {type(point).__name__}")
        if not isinstance(point.get("observations", {}), dict):
            raise RequestError(f"points[{k}]: 'observations' must map image names to [x, y], got "
                               f"{type(point['observations']).__name__}")
        name = point.get("name", f"point_{k}")
        if not isinstance(name, str):
            raise RequestError(f"points[{k}]: the name must be a string")
        for image, xy in point.get("observations", {}).items():
            if image not in sizes:
                raise RequestError(f"points[{k}] ({name[:80]!r}): unknown image {image[:80]!r}")
            pixel = _pixel(xy)
            w, h = sizes[image]
            if pixel is None or not (0 <= pixel[0] <= w and 0 <= pixel[1] <= h):
                raise RequestError(f"points[{k}] ({name[:80]!r}) in {image[:80]!r}: expected [x, y], two finite "
                                   f"numbers inside {w}x{h}")
            obs.setdefault(image, {})[name] = pixel
    return obs


def _pixel(xy) -> tuple[float, float] | None:
    if not isinstance(xy, list) or len(xy) != 2 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in xy):
        return None
    try:
        x, y = float(xy[0]), float(xy[1])
    except OverflowError:  # an integer beyond float range
        return None
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


def _hand_f(b_a: np.ndarray, b_b: np.ndarray, threshold_rad: float) -> np.ndarray:
    """F of a pair's hand correspondences: exact through 8; beyond, robust, so one wrong click cannot bend it."""
    if len(b_a) > 8:
        try:
            return two_view.ransac_f(b_a, b_b, two_view.RansacOptions(threshold_rad=threshold_rad, seed=0)).F
        except ValueError:
            pass
    return two_view.estimate_f_linear(b_a, b_b)


def _mtime(path) -> int | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def _status(pipeline: Pipeline, stage: str) -> dict:
    st = pipeline.status(stage)
    return {"state": st.state, "reasons": st.reasons}


def _message(stages: dict) -> str | None:
    """What the page says above everything when the model is missing or stale."""
    if stages["registration"]["state"] == "missing":
        return "this dataset has not been reconstructed yet: run `fullview run` first"
    stale = [s for s, st in stages.items() if st["state"] != "fresh"]
    if stale:
        return "stale or missing stages (shown results may be outdated): " + ", ".join(
            f"{s} ({stages[s]['state']}: {'; '.join(stages[s]['reasons'][:1])})" for s in stale)
    return None


def _neighbours(k: int, R, centers, registered, links, names) -> list[dict]:
    """Hotspots of camera k: its nearest registered cameras among those with a verified pair to it (any registered
    camera when it has none), with the direction to each in camera k's frame as yaw/pitch (PSV: yaw = longitude)."""
    if not registered[k]:
        return []
    others = [j for j in np.flatnonzero(registered) if j != k]
    linked = [j for j in others if links[k, j] > 0] or others
    dist = {j: float(np.linalg.norm(centers[j] - centers[k])) for j in linked}
    out = []
    for j in sorted(linked, key=dist.get)[:NEIGHBOURS]:
        d = R[k] @ (centers[j] - centers[k])
        lon, lat = bearings_to_lonlat(d / max(np.linalg.norm(d), 1e-12))
        out.append({"name": names[j], "yaw": float(lon), "pitch": float(lat), "distance": dist[j]})
    return out


def display_rotation(R_cam_from_world: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """R_display_from_world: the cameras' mean up becomes +y (three.js' up), the main horizontal direction of the
    camera track +x."""
    up = camera_up(R_cam_from_world) if len(R_cam_from_world) else np.array([0.0, -1.0, 0.0])
    spread = centers - centers.mean(0) if len(centers) > 1 else np.eye(3)
    flat = spread - np.outer(spread @ up, up)
    x = np.linalg.svd(flat, full_matrices=False)[2][0] if np.abs(flat).sum() > 1e-12 else _any_perpendicular(up)
    x -= (x @ up) * up
    x /= np.linalg.norm(x)
    return np.stack([x, up, np.cross(x, up)])


def _any_perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.eye(3)[np.argmin(np.abs(v))]
    return np.cross(v, a)
