"""Seeded layout of a synthetic room: its size, the furniture boxes, the target markers and the camera walk.

The world frame has y pointing DOWN like the camera frame (floor at ``y = +FLOOR_Y``, eye height at ``y ≈ 0``);
cameras are level up to a small tilt, keep clear of walls and boxes and follow a compact random walk.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from fullview.synth.geometry import face_frame


FLOOR_Y = 1.6  # world y of the floor (m); eye height 1.6 m is at y = 0
EYE_HEIGHT_JITTER = 0.2  # cameras' y is uniform in [-this, +this]
CLEARANCE = 0.6  # minimum horizontal distance from a camera centre to any wall or box (m)
MAX_TILT_DEG = 5.0  # maximum |roll| and |pitch| of a camera
STEP_RANGE = (0.6, 1.6)  # distance from a camera to the previous one in the random walk (m)
MIN_CAMERA_SEPARATION = 0.5  # minimum distance between any two cameras (m)
MAX_SPREAD = 1.8  # preferred maximum distance of a new camera from the centroid of the previous ones (m)
MARKERS_PER_ROOM_FACE = 4  # target markers drawn on each room face (hand-point candidates)


def _room(rng: np.random.Generator) -> np.ndarray:
    lx, lz, h = rng.uniform(7.0, 9.0), rng.uniform(5.0, 7.0), rng.uniform(2.7, 3.1)
    return np.array([[-lx / 2, FLOOR_Y - h, -lz / 2], [lx / 2, FLOOR_Y, lz / 2]])


def rect_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal (x-z) gap between two boxes' footprints (0 if they overlap)."""
    dx = max(a[0, 0] - b[1, 0], b[0, 0] - a[1, 0], 0.0)
    dz = max(a[0, 2] - b[1, 2], b[0, 2] - a[1, 2], 0.0)
    return math.hypot(dx, dz)


def sample_box(rng: np.random.Generator, kind: str, room: np.ndarray) -> np.ndarray:
    (x0, ceil_y, z0), (x1, floor_y, z1) = room
    if kind == "cupboard":
        w, dep, h = rng.uniform(0.8, 1.6), rng.uniform(0.4, 0.6), rng.uniform(1.8, 2.2)
        wall = rng.integers(4)
        gap = 0.02
        if wall < 2:  # against an x wall: extent along z
            z = rng.uniform(z0 + 0.1, z1 - 0.1 - w)
            x = x0 + gap if wall == 0 else x1 - gap - dep
            lo, hi = [x, floor_y - h, z], [x + dep, floor_y, z + w]
        else:
            x = rng.uniform(x0 + 0.1, x1 - 0.1 - w)
            z = z0 + gap if wall == 2 else z1 - gap - dep
            lo, hi = [x, floor_y - h, z], [x + w, floor_y, z + dep]
        return np.array([lo, hi])
    if kind == "column":
        s = rng.uniform(0.3, 0.5)
        x, z = rng.uniform(x0 + 0.8, x1 - 0.8 - s), rng.uniform(z0 + 0.8, z1 - 0.8 - s)
        return np.array([[x, ceil_y, z], [x + s, floor_y, z + s]])
    if kind == "table":
        w, dep, h = rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0), rng.uniform(0.7, 0.8)
    else:  # low crate / bench
        w, dep, h = rng.uniform(0.4, 1.0), rng.uniform(0.4, 0.7), rng.uniform(0.35, 0.6)
    if rng.random() < 0.5:
        w, dep = dep, w
    x, z = rng.uniform(x0 + 0.3, x1 - 0.3 - w), rng.uniform(z0 + 0.3, z1 - 0.3 - dep)
    return np.array([[x, floor_y - h, z], [x + w, floor_y, z + dep]])


def _free_mask(boxes: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid of camera positions (x-z cell centres) at least CLEARANCE (+ half a cell) from walls and boxes."""
    room = boxes[0]
    xs = np.arange(room[0, 0] + res / 2, room[1, 0], res)
    zs = np.arange(room[0, 2] + res / 2, room[1, 2], res)
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    margin = CLEARANCE + res
    free = ((gx - room[0, 0] >= margin) & (room[1, 0] - gx >= margin)
            & (gz - room[0, 2] >= margin) & (room[1, 2] - gz >= margin))
    for box in boxes[1:]:
        dx = np.maximum(np.maximum(box[0, 0] - gx, gx - box[1, 0]), 0.0)
        dz = np.maximum(np.maximum(box[0, 2] - gz, gz - box[1, 2]), 0.0)
        free &= np.hypot(dx, dz) >= margin
    return free, gx, gz


def layout_boxes(rng: np.random.Generator) -> np.ndarray:
    """Room + 3-6 non-overlapping furniture boxes leaving a connected free area for the cameras."""
    for _attempt in range(100):
        room = _room(rng)
        n = int(rng.integers(3, 7))
        kinds = ["cupboard", "table"] + list(rng.choice(["table", "cupboard", "column", "crate"], size=n - 2))
        boxes = [room]
        for kind in kinds:
            for _try in range(50):
                box = sample_box(rng, kind, room)
                if all(rect_gap(box, other) >= 0.4 for other in boxes[1:]):
                    boxes.append(box)
                    break
        boxes = np.array(boxes)
        if len(boxes) < 4:
            continue
        free, _, _ = _free_mask(boxes, 0.1)
        labels, count = ndimage.label(free)
        if count and np.bincount(labels.ravel())[1:].max() * 0.01 >= 6.0:
            return boxes
    raise RuntimeError("could not lay out a room with enough free space")


def place_cameras(rng: np.random.Generator, boxes: np.ndarray, views: int) -> tuple[np.ndarray, np.ndarray]:
    """Random walk of camera centres in the largest free region; returns (R_world_from_cam (V,3,3), centers (V,3))."""
    res = 0.05
    free, gx, gz = _free_mask(boxes, res)
    labels, _ = ndimage.label(free)
    largest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    cells = np.stack([gx[labels == largest], gz[labels == largest]], axis=1)
    pos: list[np.ndarray] = []
    centers, rots = [], []
    for k in range(views):  # camera k depends only on cameras < k (prefix-stable in ``views``)
        if k == 0:
            cand = cells
        else:
            d_prev = np.linalg.norm(cells - pos[-1], axis=1)
            d_all = np.min(np.linalg.norm(cells[:, None] - np.array(pos)[None], axis=2), axis=1)
            d_mean = np.linalg.norm(cells - np.mean(pos, axis=0), axis=1)
            ok = d_all >= MIN_CAMERA_SEPARATION + res  # + res: the jitter below moves up to res / sqrt(2)
            step = ok & (d_prev >= STEP_RANGE[0]) & (d_prev <= STEP_RANGE[1])
            cand = cells[step & (d_mean <= MAX_SPREAD)]  # keep the cluster compact
            if len(cand) == 0:
                cand = cells[step]
            if len(cand) == 0:  # walk stuck: attach to any camera
                cand = cells[ok & (d_all <= 2.0)]
            if len(cand) == 0:
                cand = cells[ok] if ok.any() else cells
        pos.append(cand[rng.integers(len(cand))] + rng.uniform(-res / 2, res / 2, 2))
        y = rng.uniform(-EYE_HEIGHT_JITTER, EYE_HEIGHT_JITTER)
        yaw = rng.uniform(0.0, 2 * np.pi)
        pitch, roll = np.deg2rad(rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG, 2))
        centers.append([pos[-1][0], y, pos[-1][1]])
        rots.append(rot_y(yaw) @ _rot_x(pitch) @ _rot_z(roll))
    return np.array(rots), np.array(centers)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def room_markers(rng: np.random.Generator, boxes: np.ndarray) -> tuple[np.ndarray, list[str], list[int]]:
    """Target marker centres on the six room faces: (M, 3), names, face index of each."""
    pts, names, faces = [], [], []
    for face in range(6):
        axis, uax, vax, plane, uv0, size = face_frame(boxes, face)
        for m in range(MARKERS_PER_ROOM_FACE):
            uv = uv0 + rng.uniform(0.3, size - 0.3)
            p = np.zeros(3)
            p[axis], p[uax], p[vax] = plane, uv[0], uv[1]
            pts.append(p)
            names.append(f"room_face{face}_marker{m}")
            faces.append(face)
    return np.array(pts), names, faces
