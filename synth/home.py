"""Seeded layout of the multi-room "home" scene: a hard case for feature matching.

The flat is a row of rooms along world x inside one outer shell (box 0, seen from inside). Rooms are separated by
interior walls built from thin slab boxes: each wall has one doorway (``DOOR_WIDTH`` x ``DOOR_HEIGHT``), made of a
slab on either side of the opening and a lintel slab above it up to the ceiling; a closed doorway is one full
slab. The shell and the slabs are PLAIN (near-uniform colour, faint noise: SIFT finds little on them); each room
holds a few strongly textured furniture boxes. The cameras are level (no roll or pitch) at ``HOME_EYE_HEIGHT``
above the floor and walk through the rooms in order, 1-3 per room, passing each doorway, with a free line of
sight and ``HOME_STEP_RANGE`` metres between consecutive cameras. Same world frame as the room scene (y down,
floor at ``y = FLOOR_Y``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullview.synth.layout import FLOOR_Y, rect_gap, rot_y, sample_box
from fullview.synth.render import cast_rays


HOME_EYE_HEIGHT = 1.5  # camera height above the floor (m)
HOME_EYE_JITTER = 0.05  # camera height is uniform in HOME_EYE_HEIGHT +- this
WALL_THICKNESS = 0.1  # interior wall slabs (m)
DOOR_WIDTH = 0.9  # doorway opening (m)
DOOR_HEIGHT = 2.0  # doorway opening (m); the lintel slab fills the rest up to the ceiling
HOME_CLEARANCE = 0.4  # minimum horizontal distance from a camera to any wall or furniture box (m)
HOME_STEP_RANGE = (1.1, 1.9)  # distance between consecutive cameras (m), inside the promised 1-2 m
HOME_MIN_SEPARATION = 0.8  # minimum distance between any two cameras (m)
DOOR_REACH = 1.4  # the last camera of a room and the first of the next are this close to their doorway (m)
MAX_VIEWS_PER_ROOM = 3
# Room extent along x by its number of cameras (m): a one-camera room is a narrow hall, so that a walk through
# several of them keeps 1-2 m steps.
ROOM_WIDTH = {1: (1.7, 1.9), 2: (3.0, 3.6), 3: (3.8, 4.4)}
FLAT_DEPTH = (3.6, 4.6)  # extent of the flat along z (m)
FLAT_HEIGHT = (2.5, 2.8)  # floor to ceiling (m)
FLOOR_MARKERS_PER_ROOM = 3  # target markers on each room's floor (hand-point candidates)
FLOOR_FACE = 3  # face index of the shell's floor (box 0, y axis, max side)
_GRID = 0.05  # camera position grid (m)


@dataclass(kw_only=True)
class HomeLayout:
    boxes: np.ndarray  # (K, 2, 3): shell, wall slabs, furniture
    plain_boxes: tuple[int, ...]  # indices of the plain boxes (shell and wall slabs)
    rooms: np.ndarray  # (N, 2, 3) interior of every room (between its walls)
    doors: np.ndarray  # (N - 1, 2, 3) doorway openings (the empty box inside each interior wall)
    closed_door: int | None  # doorway k (between room k and k + 1) walled up, or None
    markers: np.ndarray  # (M, 3) floor marker centres
    marker_names: list[str]
    marker_faces: list[int]
    R_world_from_cam: np.ndarray  # (V, 3, 3) level rotations (about world y)
    centers: np.ndarray  # (V, 3)
    room_of_view: np.ndarray  # (V,) room index of every camera


def views_per_room(views: int, rooms: int) -> list[int]:
    """Cameras per room (1-3 each, earlier rooms get the extra ones); ValueError when impossible."""
    if not isinstance(rooms, (int, np.integer)) or rooms < 1:
        raise ValueError(f"rooms must be a positive integer, got {rooms!r}")
    if not rooms <= views <= MAX_VIEWS_PER_ROOM * rooms:
        raise ValueError(f"a home of {rooms} rooms needs between {rooms} and {MAX_VIEWS_PER_ROOM * rooms} views "
                         f"(1-{MAX_VIEWS_PER_ROOM} per room), got {views}")
    return [views // rooms + (r < views % rooms) for r in range(rooms)]


def check_closed_door(closed_door: int | None, rooms: int) -> None:
    if closed_door is not None and not (isinstance(closed_door, (int, np.integer)) and 0 <= closed_door < rooms - 1):
        raise ValueError(f"closed_door must be a doorway index 0..{rooms - 2} (between room k and k + 1), "
                         f"got {closed_door!r}")


def layout_home(rng: np.random.Generator, views: int, rooms: int, closed_door: int | None = None) -> HomeLayout:
    """Seeded home of ``rooms`` rooms and a walk of ``views`` cameras through it (see the module doc)."""
    counts = views_per_room(views, rooms)
    check_closed_door(closed_door, rooms)
    for _attempt in range(50):
        shell, rooms_b, doors, slabs = _walls(rng, counts, closed_door)
        furniture = _furniture(rng, rooms_b, doors)
        boxes = np.array([shell] + slabs + furniture)
        for _try in range(10):
            walk = _walk(rng, boxes, rooms_b, doors, counts, closed_door)
            if walk is not None:
                rots, centers, room_of = walk
                markers, names = _floor_markers(rng, rooms_b, furniture)
                return HomeLayout(boxes=boxes, plain_boxes=tuple(range(1 + len(slabs))), rooms=rooms_b, doors=doors,
                                  closed_door=closed_door, markers=markers, marker_names=names,
                                  marker_faces=[FLOOR_FACE] * len(names), R_world_from_cam=rots, centers=centers,
                                  room_of_view=room_of)
    raise RuntimeError("could not lay out a home with a camera walk through it")


def _walls(rng: np.random.Generator, counts: list[int], closed_door: int | None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """Shell, room interiors, doorway openings and wall slabs; the flat is centred on x = z = 0."""
    n = len(counts)
    widths = [rng.uniform(*ROOM_WIDTH[c]) for c in counts]
    depth, height = rng.uniform(*FLAT_DEPTH), rng.uniform(*FLAT_HEIGHT)
    length = sum(widths) + WALL_THICKNESS * (n - 1)
    ceil_y, z0, z1 = FLOOR_Y - height, -depth / 2, depth / 2
    shell = np.array([[-length / 2, ceil_y, z0], [length / 2, FLOOR_Y, z1]])
    door_lo, door_hi = z0 + 0.3, z1 - 0.3 - DOOR_WIDTH
    rooms, doors, slabs = [], [], []
    x, zd = -length / 2, None
    for r in range(n):
        rooms.append([[x, ceil_y, z0], [x + widths[r], FLOOR_Y, z1]])
        x += widths[r]
        if r == n - 1:
            break
        if zd is None or counts[r] > 1:
            zd = rng.uniform(door_lo, door_hi)
        else:  # a one-camera room: its two doorways nearly face each other, so the walk can pass it in 1-2 m steps
            zd = float(np.clip(zd + rng.uniform(-0.4, 0.4), door_lo, door_hi))
        xw = x + WALL_THICKNESS
        doors.append([[x, FLOOR_Y - DOOR_HEIGHT, zd], [xw, FLOOR_Y, zd + DOOR_WIDTH]])
        if r == closed_door:
            slabs.append(np.array([[x, ceil_y, z0], [xw, FLOOR_Y, z1]]))
        else:
            slabs += [np.array([[x, ceil_y, z0], [xw, FLOOR_Y, zd]]),
                      np.array([[x, ceil_y, zd + DOOR_WIDTH], [xw, FLOOR_Y, z1]]),
                      np.array([[x, ceil_y, zd], [xw, FLOOR_Y - DOOR_HEIGHT, zd + DOOR_WIDTH]])]
        x = xw
    return shell, np.array(rooms), np.array(doors).reshape(-1, 2, 3), slabs


def _furniture(rng: np.random.Generator, rooms: np.ndarray, doors: np.ndarray) -> list[np.ndarray]:
    """2-3 textured boxes per room (cupboards, tables, crates; 2 small ones in a narrow hall), clear of the
    doorways and of each other."""
    keep_clear = [np.array([d[0] - [1.0, 0, 0.2], d[1] + [1.0, 0, 0.2]]) for d in doors]
    out = []
    for room in rooms:
        if room[1, 0] - room[0, 0] < ROOM_WIDTH[2][0]:
            kinds = ["cupboard", "crate"]
        else:
            kinds = ["cupboard"] + list(rng.choice(["table", "cupboard", "crate"], size=int(rng.integers(1, 3))))
        placed: list[np.ndarray] = []
        for kind in kinds:
            for _try in range(50):
                try:
                    box = sample_box(rng, kind, room)
                except ValueError:  # drew a box wider than this room
                    continue
                if (np.all(box[0] >= room[0]) and np.all(box[1] <= room[1])
                        and all(rect_gap(box, other) >= 0.6 for other in placed)
                        and all(rect_gap(box, zone) > 0 for zone in keep_clear)):
                    placed.append(box)
                    break
        out += placed
    return out


def _room_cells(room: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(C, 2) x-z grid points of a room at least HOME_CLEARANCE from its walls and every box."""
    xs = np.arange(room[0, 0] + HOME_CLEARANCE, room[1, 0] - HOME_CLEARANCE + 1e-9, _GRID)
    zs = np.arange(room[0, 2] + HOME_CLEARANCE, room[1, 2] - HOME_CLEARANCE + 1e-9, _GRID)
    cells = np.stack(np.meshgrid(xs, zs, indexing="ij"), axis=-1).reshape(-1, 2)
    ok = np.ones(len(cells), bool)
    for box in boxes[1:]:
        dx = np.maximum(np.maximum(box[0, 0] - cells[:, 0], cells[:, 0] - box[1, 0]), 0.0)
        dz = np.maximum(np.maximum(box[0, 2] - cells[:, 1], cells[:, 1] - box[1, 2]), 0.0)
        ok &= np.hypot(dx, dz) >= HOME_CLEARANCE
    return cells[ok]


def _walk(rng: np.random.Generator, boxes: np.ndarray, rooms: np.ndarray, doors: np.ndarray,
          counts: list[int], closed_door: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Cameras room by room (None if the random walk gets stuck): consecutive ones 1-2 m apart and in sight
    (except across the closed doorway)."""
    door_xz = doors.mean(axis=1)[:, [0, 2]]
    centers: list[np.ndarray] = []
    rots, room_of = [], []
    for r, count in enumerate(counts):
        cells = _room_cells(rooms[r], boxes)
        for j in range(count):
            y = FLOOR_Y - HOME_EYE_HEIGHT + rng.uniform(-HOME_EYE_JITTER, HOME_EYE_JITTER)
            ok = np.ones(len(cells), bool)
            if j == 0 and r > 0:
                ok &= np.linalg.norm(cells - door_xz[r - 1], axis=1) <= DOOR_REACH
            if j == count - 1 and r < len(counts) - 1:
                ok &= np.linalg.norm(cells - door_xz[r], axis=1) <= DOOR_REACH
            if centers:
                prev = np.array(centers)[:, [0, 2]]
                d_all = np.linalg.norm(cells[:, None] - prev[None], axis=2)
                ok &= d_all.min(axis=1) >= HOME_MIN_SEPARATION
                ok &= (d_all[:, -1] >= HOME_STEP_RANGE[0]) & (d_all[:, -1] <= HOME_STEP_RANGE[1])
                if not (j == 0 and r - 1 == closed_door):
                    ok[ok] = _in_sight(centers[-1], np.column_stack([cells[ok, 0], np.full(int(ok.sum()), y),
                                                                    cells[ok, 1]]), boxes)
            if not ok.any():
                return None
            x, z = cells[np.flatnonzero(ok)[rng.integers(int(ok.sum()))]]
            centers.append(np.array([x, y, z]))
            rots.append(rot_y(rng.uniform(0.0, 2 * np.pi)))
            room_of.append(r)
    return np.array(rots), np.array(centers), np.array(room_of)


def _in_sight(origin: np.ndarray, targets: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) whether the straight segment from ``origin`` to each target is free (cast_rays)."""
    rel = targets - origin
    dist = np.linalg.norm(rel, axis=1)
    if len(dist) == 0:
        return np.zeros(0, bool)
    t, _ = cast_rays(origin, rel / dist[:, None], boxes)
    return t >= dist - 1e-4


def _floor_markers(rng: np.random.Generator, rooms: np.ndarray, furniture: list[np.ndarray]
                   ) -> tuple[np.ndarray, list[str]]:
    """Target markers on the floor of every room, off the furniture footprints."""
    pts, names = [], []
    for r, room in enumerate(rooms):
        for m in range(FLOOR_MARKERS_PER_ROOM):
            for _try in range(50):
                x, z = rng.uniform(room[0, [0, 2]] + 0.3, room[1, [0, 2]] - 0.3)
                p = np.array([[x - 0.15, FLOOR_Y, z - 0.15], [x + 0.15, FLOOR_Y, z + 0.15]])
                if all(rect_gap(p, box) > 0 for box in furniture):
                    pts.append([x, FLOOR_Y, z])
                    names.append(f"home_room{r}_floor_marker{m}")
                    break
    return np.array(pts).reshape(-1, 3), names
