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
from fullview.io.yamlio import YamlError, load_yaml
from fullview.sfm import two_view
from fullview.sfm.camera import bearings_to_lonlat, camera_up, pixels_to_bearings
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline
from fullview.viewer import tour

log = logging.getLogger(__name__)

NEIGHBOURS = 4  # hotspots per panorama: its nearest registered panoramas among those it shares verified pairs with
POINT_SEED = 0  # clouds are ordered once, so any prefix is a spatially uniform subsample (the page's point budget)
TOUR_FILE = "tour.yaml"  # in the dataset folder: {names: {image: room name}}; unnamed panoramas are numbered
WALKED = ("verified",)  # placement verdicts (registration.json placements) whose cameras are in the walk


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
        R_display = display_rotation(R[reg], centers[reg])
        geometry = _tour_geometry(self.ws.root, self.generation(), self, R_display.tobytes())
        labels, problem = self.tour_names()  # read on every request: tour.yaml is the user's, edited any time
        for cam, extra in zip(cams, geometry["cameras"]):
            cam.update(extra, label=labels.get(cam["name"], cam["name"]),
                       hotspots=[{**h, "label": labels.get(h["name"], h["name"])} for h in extra["hotspots"]],
                       left_out=[{**h, "label": labels.get(h["name"], h["name"])} for h in extra["left_out"]])
            for h in cam["left_out"]:  # the page names the nearer hotspot as it is drawn
                if "behind" in h:
                    h["reason"] = f"behind the hotspot {labels.get(h['behind'], h['behind'])} ({h['behind']})"
        return {"poses_from": source, "cameras": cams, "tour": {**geometry["model"], "names_problem": problem},
                "unregistered": [n for n, ok in zip(names, registered) if not ok],
                "unregistered_reasons": ((self.ws.read_manifest("registration") or {}).get("summary") or {})
                .get("unregistered_reasons", {}),
                "R_display_from_world": R_display.tolist(),
                "has_sparse": source == "triangulation",
                "has_dense": self.dense_matches_poses() and self.ws.path("dense_cloud").exists(),
                "has_mesh": self.dense_matches_poses() and self.ws.path("dense_mesh").exists(),
                "pairs": self._pairs(names)}

    def dense_matches_poses(self) -> bool:
        """Whether densify's output was made from the poses on disk (its upstream triangulation is the one there):
        then it is shown even when stale for another reason (a code or setting change; the page says results may
        be outdated), never when it belongs to other poses."""
        dense, tri = self.ws.read_manifest("densify"), self.ws.read_manifest("triangulation")
        return bool(dense and tri and dense.get("upstream", {}).get("triangulation") == tri.get("fingerprint"))

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

    # ---------------------------------------------------------------------------------------------- tour
    def tour_names(self) -> tuple[dict[str, str], str | None]:
        """Each image's name in the tour: the dataset's tour.yaml `names` (image -> text) where given, else its
        number in capture order ("1", "2", ...); and a one-line problem with tour.yaml (then numbers only)."""
        names = {n: str(k + 1) for k, n in enumerate(self.dataset.image_names)}
        path = self.dataset.root / TOUR_FILE
        if not path.is_file():
            return names, None
        try:
            doc = load_yaml(path, str(path))
        except YamlError as e:
            return names, str(e)
        given = doc.get("names", {}) if isinstance(doc, dict) else None
        if not isinstance(given, dict):
            return names, f"{path}: expected `names:` mapping image file names to room names"
        for image, label in given.items():
            if image not in names:
                return names, f"{path}: names: unknown image {str(image)[:80]!r}"
            if not isinstance(label, (str, int)) or isinstance(label, bool) or not str(label).strip():
                return names, f"{path}: names: {str(image)[:80]!r}: expected a non-empty text, got {label!r:.40}"
            names[image] = str(label).strip()[:80]
        return names, None

    def verdicts(self, names: list[str]) -> dict[str, str]:
        """Each image's placement verdict (registration.json `placements`; "verified" when a workspace predates
        them)."""
        report = self.ws.load_json("registration_report") or {}
        placements = report.get("placements") if isinstance(report.get("placements"), dict) else {}
        return {n: str((placements.get(n) or {}).get("verdict", "verified")) for n in names}

    def measure(self, name: str, a: tuple[float, float], b: tuple[float, float]) -> dict:
        """Distance between two pixels (full size) of a panorama, from its depth map, with its standard error; in
        metres when a scale is stated (its uncertainty included), else in model units. A RequestError names why it
        cannot be measured."""
        name = self.image(name)
        W, H = self.dataset.image_sizes[name]
        for label, (x, y) in (("A", a), ("B", b)):
            if not (0 <= x <= W and 0 <= y <= H):
                raise RequestError(f"point {label} ({x:g}, {y:g}) is outside the {W}x{H} panorama")
        with self.ws.reading():
            poses, _ = self.ws.load_poses()
            names = [str(n) for n in poses["image_names"]]
            k = names.index(name) if name in names else -1
            if k < 0 or not poses["registered"][k]:
                raise RequestError(f"cannot measure in {name}: it is not placed in the model", 409)
            depth = self.ws.load_depth(name) if self.dense_matches_poses() else None
        if depth is None:
            raise RequestError(f"cannot measure in {name}: it has no depth map made from these poses (run densify)",
                               409)
        R, c = poses["R_cam_from_world"][k], poses["centers"][k]
        rel = self.pipeline.config["densify"].consistency_tolerance
        points, rays, sigmas = [], [], []
        for label, px in (("A", a), ("B", b)):
            bearing = pixels_to_bearings(np.array([px], float), W, H)[0]
            found = tour.range_at(depth, bearing, rel)
            if found is None:
                raise RequestError(f"cannot measure: no depth at point {label} ({px[0]:.0f}, {px[1]:.0f}) of {name} "
                                   f"(the depth map has none within {tour.MEASURE_WINDOW_PX} pixels: plain or far)",
                                   409)
            ray = R.T @ bearing
            points.append(c + found[0] * ray)
            rays.append(ray)
            sigmas.append(found[1])
        d, sigma = tour.distance_between(np.array(points), np.array(rays), np.array(sigmas))
        ranges = [float(np.linalg.norm(p - c)) for p in points]
        model = int(poses["model_id"][k]) if "model_id" in poses else 0
        scale = self.metric_scale(model)
        if scale is None:
            return {"image": name, "distance": d, "sigma": sigma, "units": "model units",
                    "points": np.array(points).tolist(), "ranges": ranges, "range_sigmas": sigmas}
        f, rel = scale.metres_per_unit, (scale.rel_std if np.isfinite(scale.rel_std) else 0.0)
        # the depth's error and the scale's (stated camera height or distance) are independent: add in quadrature
        return {"image": name, "distance": d * f, "sigma": float(np.hypot(sigma * f, d * f * rel)), "units": "m",
                "scale": scale.describe(), "points": np.array(points).tolist(), "ranges": [r * f for r in ranges],
                "range_sigmas": [float(np.hypot(s_ * f, r * f * rel)) for r, s_ in zip(ranges, sigmas)]}

    def metric_scale(self, model: int):
        """The metric scale of `model` the user stated (`fullview export --camera-height` / `--known-distance`),
        or None: lengths are then in model units."""
        from fullview.commands.export import metric_scale
        return metric_scale(self.pipeline, model)

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
    order = _cloud_order(root, kind, generation, scene)[0]
    head = np.array([len(points)], "<u4").tobytes()
    return head + points[order].astype("<f4").tobytes() + colors[order].astype(np.uint8).tobytes()


@lru_cache(maxsize=4)
def _cloud_order(root, kind: str, generation: str, scene: SceneData) -> tuple[np.ndarray, int]:
    return tour.spatial_order(scene.load_cloud(kind)[0], POINT_SEED)


@lru_cache(maxsize=2)
def _tour_geometry(root, generation: str, scene: SceneData, R_display_bytes: bytes) -> dict:
    """Per camera (in pose order): its verdict, whether it is walked, its floor and ceiling (distance
    below / above the centre, with what gave them) and its hotspots (see `_hotspots`); for the model: the robust
    bounds of the cloud in the display frame, the floor and ceiling heights there and the readable point budget."""
    ws = scene.ws
    R_display = np.frombuffer(R_display_bytes).reshape(3, 3)
    with ws.reading():
        poses, _ = ws.load_poses()
        names = [str(n) for n in poses["image_names"]]
        registered = poses["registered"].astype(bool)
        R, centers = poses["R_cam_from_world"], poses["centers"]
        verdicts = scene.verdicts(names)
        dense_ok = scene.dense_matches_poses()  # depth and dense cloud of other poses are not used
        depths = {n: ws.load_depth(n) for n, ok in zip(names, registered) if ok and dense_ok}
    clouds = []
    for k in ("dense", "sparse") if dense_ok else ("sparse",):
        try:
            points = scene.load_cloud(k)[0].astype(np.float32)
        except ArtifactError:
            continue
        if len(points):
            clouds.append((k, points))
    kind = clouds[0][0] if clouds else "sparse"
    observed = _observed_points(ws, len(names))
    up = camera_up(R[registered]) if registered.any() else np.array([0.0, -1.0, 0.0])
    floor, ceiling = _vertical(names, R, centers, registered, depths, clouds, up)
    walked = registered & np.array([verdicts[n] in WALKED for n in names])
    tolerance = scene.pipeline.config["densify"].mesh_support_tolerance
    drops = [d for d, _ in floor if d is not None]
    radius = tour.HOTSPOT_RADIUS * float(np.median(drops)) if drops else None
    links = scene._links(len(names))
    seen = {}  # k -> j -> visibility of j from k
    for k in np.flatnonzero(walked):
        others = [j for j in np.flatnonzero(walked) if j != k]
        seen[k] = dict(zip(others, tour.visibility(centers[k], R[k], centers[others], depths.get(names[k]), clouds,
                                                   observed[k], tolerance)))
    cameras = []
    for k, name in enumerate(names):
        cam = {"verdict": verdicts[name] if registered[k] else None,
               "walked": bool(walked[k]), "floor_drop": floor[k][0], "floor_from": floor[k][1],
               "ceiling_rise": ceiling[k][0], "ceiling_from": ceiling[k][1], "hotspots": [], "left_out": []}
        if walked[k]:
            cam["hotspots"], cam["left_out"] = _hotspots(k, R, centers, walked, floor, up, seen, radius, links, names)
        cameras.append(cam)
    points = dict(clouds).get(kind, np.zeros((0, 3)))
    bounds = tour.robust_bounds(points @ R_display.T) if len(points) else None
    if bounds is None and registered.sum() > 1:
        bounds = (centers[registered] @ R_display.T).min(0), (centers[registered] @ R_display.T).max(0)
    heights = centers @ (R_display @ up)
    floors = [heights[k] - d for k, (d, _) in enumerate(floor) if d is not None and registered[k]]
    ceilings = [heights[k] + d for k, (d, _) in enumerate(ceiling) if d is not None and registered[k]]
    model = {"bounds": None if bounds is None else [bounds[0].tolist(), bounds[1].tolist()],
             "floor": float(np.median(floors)) if floors else None,
             "ceiling": float(np.median(ceilings)) if ceilings else None,
             "readable_points": _cloud_order(root, kind, generation, scene)[1] if len(points) else 0,
             "cloud": kind,
             "left_apart": [n for n, ok, w in zip(names, registered, walked) if ok and not w]}
    return {"cameras": cameras, "model": model}


def _vertical(names, R, centers, registered, depths, clouds, up) -> tuple[list, list]:
    """Each camera's floor (distance below its centre along -up) and ceiling (above, along up) with their source:
    its depth map's nadir (zenith) cone, else the points there (dense, then sparse); the floor of a camera with
    neither is the median of the others' (a tripod keeps its height: the camera-height prior), its ceiling too."""
    floor, ceiling = [], []
    for k in range(len(centers)):
        out = []
        for sign in (-1.0, 1.0):
            value, source = None, None
            if registered[k]:
                d = depths.get(names[k])
                if d is not None:
                    value = tour.cone_extent(d["range"], d["valid"], R[k] @ (sign * up))
                    source = "depth" if value is not None else None
                for kind, points in clouds:
                    if value is None:
                        value = tour.points_cone_extent(points, centers[k], sign * up)
                        source = kind if value is not None else None
            out.append((value, source))
        floor.append(out[0])
        ceiling.append(out[1])
    for side in (floor, ceiling):
        known = [v for (v, _), ok in zip(side, registered) if v is not None and ok]
        for k, (v, _) in enumerate(side):
            if v is None and registered[k] and known:
                side[k] = (float(np.median(known)), "prior")
    return floor, ceiling


def _observed_points(ws, n: int) -> list[np.ndarray]:
    """Per image, the sparse points (world) it observed (empty without a triangulation)."""
    try:
        with ws.reading():
            sparse = ws.load_sparse_model(0)
    except ArtifactError:
        return [np.zeros((0, 3))] * n
    points, tracks, images = sparse["points"], sparse["track_ids"], sparse["image_ids"]
    return [points[np.unique(tracks[images == k])] for k in range(n)]


def _hotspots(k, R, centers, walked, floor, up, seen, radius, links, names):
    """Camera k's hotspots: every walked camera the geometry shows visible (`tour.visibility` of the segment
    between the centres from both ends, `tour.mutual`; where nothing says, a verified pair between them counts),
    placed on the floor below it
    (at its floor drop; at its centre without one), laid out by `tour.place_hotspots`. Left out: the ones behind a
    wall (with the evidence) and the ones behind a nearer hotspot."""
    candidates, left = [], []
    for j in [j for j in np.flatnonzero(walked) if j != k]:
        visible, evidence, beyond = tour.mutual(seen[k][j], seen[j][k])
        if visible is None and links[k, j] > 0:
            visible, evidence = True, "no geometry along the way; a verified pair"
        if not visible:
            left.append({"name": names[j],
                         "reason": f"not seen: {evidence}" if visible is False else
                         "not seen: no depth, point or verified pair says it is"})
            continue
        spot = centers[j] - (floor[j][0] or 0.0) * up
        rel = R[k] @ (spot - centers[k])
        candidates.append({"name": names[j], "bearing": rel / np.linalg.norm(rel),
                           "distance": float(np.linalg.norm(rel)), "evidence": evidence,
                           "walk_distance": float(np.linalg.norm(centers[j] - centers[k])),
                           "walk_bearing": (R[k] @ (centers[j] - centers[k]) / np.linalg.norm(centers[j] - centers[k]))
                           .tolist(), "beyond": beyond})
    r = radius if radius else 0.1 * min([c["walk_distance"] for c in candidates] or [1.0])
    placed, behind = tour.place_hotspots(candidates, r)
    for b in behind:
        left.append({"name": b["name"], "behind": b["behind"], "reason": f"behind the hotspot of {b['behind']}"})
    return [{key: v for key, v in p.items() if key != "bearing"} for p in placed], left


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
