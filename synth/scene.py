"""A whole synthetic scene: seeded room, rendered views with exact poses and depth, hand-point tracks.

``render_scene`` is the entry point (pure: no file access; ``dataset.write_synthetic_dataset`` writes one to disk);
``visible_observations`` and ``sample_surface_points`` give ground truth for tests and metrics;
``crossing_hand_points`` picks the hand-point tracks that join the two sides of a home's closed door.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np
from tqdm import tqdm

from fullview.sfm.camera import bearings_to_pixels
from fullview.synth.capture import CaptureTraits, exposed, gains, name_order, tilted
from fullview.synth.geometry import SceneGeometry, face_frame, face_normal
from fullview.synth.corridor import layout_corridor
from fullview.synth.home import HomeLayout, layout_home
from fullview.synth.layout import layout_boxes, place_cameras, room_markers
from fullview.synth.render import CHUNK_RAYS, SUPERSAMPLE, cast_rays, render_view
from fullview.synth.textures import build_geometry, texel_for_width

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class SynthView:
    name: str  # image file name, e.g. "pano_000.png"
    image: np.ndarray  # (H, W, 3) uint8, BGR (OpenCV order)
    depth: np.ndarray  # (H, W) float32, range (m) from the camera centre along the pixel-centre bearing
    R_world_from_cam: np.ndarray  # (3, 3) rotation, x_world = R_world_from_cam @ x_cam + center
    center: np.ndarray  # (3,) camera centre in world


@dataclass(kw_only=True)
class SynthScene:
    views: list[SynthView]  # rendered panoramas with their true poses
    hand_points: list[dict]  # [{"name": str, "observations": {image_name: [x, y]}}], each track in >= 2 views
    boxes: np.ndarray  # (K, 2, 3) axis-aligned boxes (min corner, max corner), room included as box 0
    scene_size: float  # diagonal of the room (the home's shell) (m), used to normalise errors
    hand_point_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) true point of hand_points[p]
    geometry: SceneGeometry | None = None  # textured geometry, to render further views with render_view
    home: HomeLayout | None = None  # home scene: its layout (rooms, doorways, closed door, window, room of each view)


def _box_corners(box: np.ndarray) -> np.ndarray:
    idx = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return np.where(idx == 1, box[1], box[0])


def _hand_candidates(geometry: SceneGeometry) -> tuple[np.ndarray, list[str]]:
    pts, names = [], []
    for k, box in enumerate(geometry.boxes):
        for c, p in enumerate(_box_corners(box)):
            pts.append(p)
            names.append(f"room_corner{c}" if k == 0 else f"box{k}_corner{c}")
    pts.extend(geometry.markers)
    names.extend(geometry.marker_names)
    return np.array(pts), names


def visible_observations(points: np.ndarray, views: list[SynthView], *,
                         border_frac: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Exact projections (P, V, 2) of world points and a (P, V) visibility mask (depth test vs the depth maps)."""
    points = np.asarray(points, dtype=np.float64)
    pix = np.zeros((len(points), len(views), 2))
    vis = np.zeros((len(points), len(views)), bool)
    for v, view in enumerate(views):
        h, w = view.depth.shape
        rel = points - view.center
        pix[:, v] = bearings_to_pixels(rel @ view.R_world_from_cam, w, h)
        rng_ = np.linalg.norm(rel, axis=1)
        x, y = pix[:, v, 0], pix[:, v, 1]
        margin = max(2.0, border_frac * h)
        inside = (y >= margin) & (y <= h - margin) & (x >= margin) & (x <= w - margin)
        # the (up to) 4 pixel centres around the projection must not be in front of the point
        j0 = np.floor(x - 0.5).astype(int)
        i0 = np.clip(np.floor(y - 0.5).astype(int), 0, h - 2)
        near = np.min([view.depth[i0 + di, (j0 + dj) % w] for di in (0, 1) for dj in (0, 1)], axis=0)
        tol = 0.02 + rng_ * max(0.02, 2.0 * 2.0 * np.pi / w)
        vis[:, v] = inside & (near >= rng_ - tol)
    return pix, vis


def _hand_points(geometry: SceneGeometry, views: list[SynthView], rng: np.random.Generator,
                 noise_px: float) -> tuple[list[dict], np.ndarray]:
    pts, names = _hand_candidates(geometry)
    pix, vis = visible_observations(pts, views)
    noise = rng.normal(0.0, 1.0, pix.shape) * noise_px
    tracks, xyz = [], []
    for p in np.flatnonzero(vis.sum(axis=1) >= 2):
        obs = {}
        for v in np.flatnonzero(vis[p]):
            h, w = views[v].depth.shape
            x, y = pix[p, v] + noise[p, v]
            obs[views[v].name] = [float(np.mod(x, w)), float(np.clip(y, 0.0, h))]
        tracks.append({"name": names[p], "observations": obs})
        xyz.append(pts[p])
    return tracks, np.array(xyz).reshape(-1, 3)


def render_scene(*, views: int = 6, width: int = 2048, seed: int = 0, hand_point_noise_px: float = 1.0,
                 supersample: int = SUPERSAMPLE, kind: str = "room", rooms: int = 4,
                 closed_door: int | None = None, capture: CaptureTraits | None = None) -> SynthScene:
    """Render a seeded synthetic scene seen by ``views`` panoramas of ``width`` x ``width // 2``.

    ``kind="room"`` (default): one textured room; the room, furniture and textures depend only on ``seed`` (the
    texture resolution on ``width``) and camera k does not depend on ``views`` > k. ``kind="home"``: a flat of
    ``rooms`` rooms with plain walls and doorways, 1-3 level cameras per room (``views`` in [rooms, 3 * rooms]);
    ``closed_door=k`` closes the doorway between room k and k + 1 with a door that has a window (impassable for
    the walk and for matching, see ``fullview.synth.home``; ``crossing_hand_points`` picks tracks across it).
    ``kind="corridor"``: a long textured corridor divided into bays, walked by ``views`` level cameras in order
    (sparse view graph, see ``fullview.synth.corridor``). ``capture``: traits of a real capture (tilt, exposure,
    noise, file order; ``fullview.synth.capture``), none by default. The same arguments give bit-identical output.
    """
    if kind not in ("room", "home", "corridor"):
        raise ValueError(f"kind must be 'room', 'home' or 'corridor', got {kind!r}")
    if not isinstance(views, (int, np.integer)) or views < 1:
        raise ValueError(f"views must be a positive integer, got {views!r}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if hand_point_noise_px < 0:
        raise ValueError(f"hand_point_noise_px must be >= 0, got {hand_point_noise_px}")
    if width < 16 or width % 2:
        raise ValueError(f"width must be an even integer >= 16, got {width}")
    t0 = time.perf_counter()
    s_layout, s_cam, s_tex, s_noise = np.random.SeedSequence(int(seed)).spawn(4)
    layout_rng = np.random.default_rng(s_layout)
    home = None
    if kind == "home":
        home = layout_home(layout_rng, views, rooms, closed_door)
        boxes, rots, centers = home.boxes, home.R_world_from_cam, home.centers
        geometry = build_geometry(boxes, texel=texel_for_width(width), seed=s_tex, markers=home.markers,
                                  marker_names=home.marker_names, marker_faces=home.marker_faces,
                                  plain_boxes=home.plain_boxes)
        t1 = time.perf_counter()
    elif kind == "corridor":
        corridor = layout_corridor(layout_rng, views)
        boxes, rots, centers = corridor.boxes, corridor.R_world_from_cam, corridor.centers
        geometry = build_geometry(boxes, texel=texel_for_width(width), seed=s_tex)
        t1 = time.perf_counter()
    else:
        boxes = layout_boxes(layout_rng)
        markers, marker_names, marker_faces = room_markers(layout_rng, boxes)
        geometry = build_geometry(boxes, texel=texel_for_width(width), seed=s_tex, markers=markers,
                                  marker_names=marker_names, marker_faces=marker_faces)
        t1 = time.perf_counter()
        rots, centers = place_cameras(np.random.default_rng(s_cam), boxes, views)
    capture = capture or CaptureTraits()
    if capture.tilt_deg > 0:
        rots = tilted(rots, capture.tilt_deg, seed)
        home = replace(home, R_world_from_cam=rots) if home is not None else None
    order = name_order(views, capture.shuffle, seed)
    out = []
    for k in tqdm(range(views), desc="render", disable=None, leave=False):
        image, depth = render_view(geometry, R_world_from_cam=rots[k], center=centers[k], width=width,
                                   supersample=supersample)
        out.append(SynthView(name=f"pano_{order[k]:03d}.png", image=image, depth=depth,
                             R_world_from_cam=rots[k], center=centers[k]))
    images = exposed([v.image for v in out], gains(views, capture.exposure_stops, seed), capture.noise, seed)
    for view, image in zip(out, images):
        view.image = image
    t2 = time.perf_counter()
    hand, hand_xyz = _hand_points(geometry, out, np.random.default_rng(s_noise), hand_point_noise_px)
    log.info("synthetic %s seed=%d: %d boxes, textures %.2fs, %d views %dx%d %.2fs, %d hand tracks",
             kind, seed, len(boxes) - 1, t1 - t0, views, width, width // 2, t2 - t1, len(hand))
    return SynthScene(views=out, hand_points=hand, boxes=boxes,
                      scene_size=float(np.linalg.norm(boxes[0, 1] - boxes[0, 0])), hand_point_xyz=hand_xyz,
                      geometry=geometry, home=home)


def crossing_hand_points(scene: SynthScene, closed_door: int | None = None, count: int = 8) -> list[dict]:
    """The ``count`` hand-point tracks of a home scene that join the two sides of its closed door.

    A track qualifies when >= 2 views on EACH side of doorway ``closed_door`` (default: the scene's closed door)
    observe it; a view's side is its room (``scene.home.room_of_view``) <= ``closed_door`` or > ``closed_door``.
    Target markers come first (the closed door's crossing markers are made for this), then other points (box
    corners); within each, tracks seen by more views, then by more views on their weaker side; ties keep the order
    of ``scene.hand_points``. The tracks are returned as they are (same dicts, every observation). ValueError when
    the scene is not a home with that doorway closed, or when fewer than ``count`` tracks qualify.
    """
    home = scene.home
    closed = home.closed_door if home is not None else None
    closed_door = closed if closed_door is None else closed_door
    if home is None or closed_door is None or closed_door != closed:
        raise ValueError(f"crossing hand points need a home scene rendered with closed_door={closed_door!r} "
                         f"(this scene: {'no home' if home is None else f'closed_door={closed!r}'})")
    if not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    side_a = {v.name: bool(r <= closed_door) for v, r in zip(scene.views, home.room_of_view)}
    ranked = []
    for i, track in enumerate(scene.hand_points):
        n_a = sum(side_a[name] for name in track["observations"])
        n_b = len(track["observations"]) - n_a
        if n_a >= 2 and n_b >= 2:
            ranked.append(("marker" not in track["name"], -(n_a + n_b), -min(n_a, n_b), i))
    if len(ranked) < count:
        raise ValueError(f"only {len(ranked)} hand-point tracks are seen by >= 2 views on each side of doorway "
                         f"{closed_door}, {count} wanted")
    return [scene.hand_points[key[-1]] for key in sorted(ranked)[:count]]


def sample_surface_points(scene: SynthScene, *, spacing: float, seed: int = 0, min_views: int = 0) -> np.ndarray:
    """(N, 3) roughly uniform (jittered grid, ``spacing`` m) points on every surface that can be seen.

    Covers the room's walls, floor and ceiling and the furniture faces, minus surfaces hidden in
    contact or in crevices narrower than 5 cm (box bottoms, floor under boxes, cupboard backs).
    With ``min_views`` > 0 only points with a free line of sight to at least that many of the
    scene's camera centres are kept.
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    boxes = np.asarray(scene.boxes, dtype=np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for face in range(6 * len(boxes)):
        axis, uax, vax, plane, uv0, size = face_frame(boxes, face)
        nu, nv = (max(1, int(round(s / spacing))) for s in size)
        u = (np.arange(nu)[None, :] + rng.uniform(0, 1, (nv, nu))) * (size[0] / nu) + uv0[0]
        v = (np.arange(nv)[:, None] + rng.uniform(0, 1, (nv, nu))) * (size[1] / nv) + uv0[1]
        p = np.empty((nu * nv, 3))
        p[:, axis], p[:, uax], p[:, vax] = plane, u.ravel(), v.ravel()
        n = face_normal(face, room=face < 6)
        out.append(p[_open_surface(p, n, boxes)])
    pts = np.concatenate(out)
    if min_views > 0:
        seen = np.zeros(len(pts), int)
        for view in scene.views:
            rel = pts - view.center
            dist = np.linalg.norm(rel, axis=1)
            for s in range(0, len(pts), CHUNK_RAYS):
                t, _ = cast_rays(view.center, rel[s:s + CHUNK_RAYS] / dist[s:s + CHUNK_RAYS, None], boxes)
                seen[s:s + CHUNK_RAYS] += t >= dist[s:s + CHUNK_RAYS] - 1e-3 * np.maximum(dist[s:s + CHUNK_RAYS], 1.0)
        pts = pts[seen >= min_views]
    return pts


def _open_surface(p: np.ndarray, n: np.ndarray, boxes: np.ndarray, gap: float = 0.05) -> np.ndarray:
    """Mask of surface points whose outward side is inside the room, outside every box, with >= gap free space."""
    q = p + 1e-4 * n
    room = boxes[0]
    ok = np.all((q > room[0]) & (q < room[1]), axis=1)
    for box in boxes[1:]:
        ok &= ~np.all((q > box[0]) & (q < box[1]), axis=1)
    if ok.any():
        t, _ = cast_rays(q[ok], np.broadcast_to(n, (int(ok.sum()), 3)), boxes)
        ok[np.flatnonzero(ok)] = t >= gap
    return ok
