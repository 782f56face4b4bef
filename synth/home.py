"""Seeded layout of the multi-room "home" scene: a hard case for feature matching.

The flat is a row of rooms along world x inside one outer shell (box 0, seen from inside). Rooms are separated by
interior walls built from thin slab boxes: each wall has one doorway (``DOOR_WIDTH`` x ``DOOR_HEIGHT``), made of a
slab on either side of the opening and a lintel slab above it up to the ceiling. The shell and the slabs are PLAIN
(near-uniform colour, faint noise: SIFT finds little on them); each room holds a few strongly textured furniture
boxes. The cameras are level (no roll or pitch) at ``HOME_EYE_HEIGHT`` above the floor and walk through the rooms
in order, 1-3 per room, passing each doorway, with a free line of sight and ``HOME_STEP_RANGE`` metres between
consecutive cameras. Same world frame as the room scene (y down, floor at ``y = FLOOR_Y``).

A closed doorway (``closed_door=k``, between room k and k + 1) keeps its wall and gets a closed door: a plain leaf
(``DOOR_LEAF_THICKNESS``, centred in the wall) filling the opening, with a small window in it (an open hole,
``WINDOW_WIDTH`` x ``WINDOW_HEIGHT`` at ``WINDOW_SILL`` above the floor, centred across the leaf): think of a
glazed door. The leaf is four plain boxes around the window (below, above and beside it). The walk does not pass
it (the cameras either side of it need not see each other nor be 1-2 m apart) and automatic matching does not join
the two sides, yet a person can pick common points across it:

- the cameras of its two rooms keep ``WINDOW_MIN_DISTANCE`` from it and see no furniture through the window
  (``WINDOW_MAX_CLUTTER``), the nearest ones hardly anything beyond the next room (``WINDOW_MAX_BEYOND``), so only
  a small, mostly plain patch of the other side shows through it;
- the ``WINDOW_VIEW_CAMERAS`` cameras nearest it on each side look through the window (``WINDOW_VIEW_MAX_ANGLE_DEG``
  from its normal, ``WINDOW_PAIR_MAX_ANGLE_DEG`` from each other), and ``CROSSING_MARKERS`` extra target markers
  ("home_door<k>_marker<m>") are placed, spread out, on plain walls, floor or ceiling of the two rooms where
  ``CROSSING_MIN_VIEWS`` cameras on EACH side see them whole (from one side through the window).

When the two rooms have fewer cameras than that, the markers that fit are placed (maybe none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fullview.sfm.camera import bearings_to_lonlat
from fullview.synth.geometry import face_frame, face_normal
from fullview.synth.layout import FLOOR_Y, rect_gap, rot_y, sample_box
from fullview.synth.render import cast_rays
from fullview.synth.textures import MARKER_RADIUS


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
# The closed doorway's door (see the module doc). Tuned with `fullview synth --scene home --rooms 4 --views 12
# --closed-door 1` at --width 1024 (seeds 0-11) and 2048 (seeds 0-2), then `fullview run --until epipoles` with
# filter.use_hand_points false. With a 0.5 m window and the cameras >= 1.2 m away, the filter keeps no cross-door
# pair at 1024 (at most 7 of a pair's raw matches are true; with the filter's minimums lowered to 8, no pair gets
# beyond the 8-11 inliers random matches give the 3-point upright solver); at 2048 one pair of seed 0 reached 15
# (filter.min_inliers_upright). Cameras 0.8 m away let pairs reach 16-24 (a 0.6 m window once 40), mostly through
# the plain walls' faint texture and the crossing markers seen through the window.
DOOR_LEAF_THICKNESS = 0.04  # door leaf (m), centred in the wall's thickness
WINDOW_WIDTH = 0.5  # window opening along the wall (m), centred in the leaf
WINDOW_HEIGHT = 0.5  # window opening (m)
WINDOW_SILL = 1.2  # window bottom above the floor (m): the window (1.2-1.7 m) spans the eye height
WINDOW_MIN_DISTANCE = 1.2  # no camera of the closed door's two rooms is nearer its plane (m)
WINDOW_MAX_CLUTTER = 0.0  # ... nor sees furniture through more than this share of the window (6 x 6 rays)
WINDOW_MAX_BEYOND = 0.25  # ... and the nearest ones see past the next room (its far doorway) through <= this share
CLOSED_DOOR_REACH = 2.0  # DOOR_REACH of the closed door (m)
WINDOW_VIEW_CAMERAS = 2  # cameras nearest the closed door on each side (in its two rooms) that see through it
WINDOW_VIEW_MAX_ANGLE_DEG = 45.0  # ... from within this horizontal angle of the door's normal
WINDOW_PAIR_MAX_ANGLE_DEG = 10.0  # ... and within this horizontal angle of each other's direction from the window
CROSSING_MARKERS = 8  # target markers seen through the window by cameras on both sides of the closed door
CROSSING_MIN_VIEWS = 2  # cameras on EACH side that see every crossing marker whole
CROSSING_MARKER_GAP = 0.35  # minimum distance between a crossing marker and any other marker (m)
_CROSSING_RAYS = 120  # rays per camera cast through the window to find crossing-marker candidates
# A view of a crossing marker counts only where scene.visible_observations (depth maps) agrees at widths >= 384:
_MIN_FACING = 0.5  # not steeper than 60° from the face's normal (depth varies too much across a pixel)
_BORDER_ANGLE = np.deg2rad(6.0)  # not this near the panorama's left/right seam or its poles (the image border)
_CLEAR_ANGLE = np.deg2rad(1.0)  # no occluding edge this near the marker's centre (the 4 pixels around it)
_GRID = 0.05  # camera position grid (m)


@dataclass(kw_only=True)
class HomeLayout:
    boxes: np.ndarray  # (K, 2, 3): shell, wall slabs, furniture
    plain_boxes: tuple[int, ...]  # indices of the plain boxes (shell, wall slabs, the closed door's leaf)
    rooms: np.ndarray  # (N, 2, 3) interior of every room (between its walls)
    doors: np.ndarray  # (N - 1, 2, 3) doorway openings (the empty box inside each interior wall)
    closed_door: int | None  # doorway k (between room k and k + 1) closed by a door with a window, or None
    window: np.ndarray | None  # (2, 3) the closed door's window opening (through the leaf), or None
    markers: np.ndarray  # (M, 3) marker centres: floor markers, then the closed door's crossing markers
    marker_names: list[str]
    marker_faces: list[int]  # face index (fullview.synth.geometry) each marker is drawn on
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
    """Seeded home of ``rooms`` rooms and a walk of ``views`` cameras through it (see the module doc).

    With a closed door whose two rooms have >= CROSSING_MIN_VIEWS cameras each, walks are drawn until
    ``CROSSING_MARKERS`` crossing markers fit (failing that, the walk with the most is kept); otherwise the
    first walk is kept with the crossing markers that fit (maybe none)."""
    counts = views_per_room(views, rooms)
    check_closed_door(closed_door, rooms)
    want_crossing = closed_door is not None and min(counts[closed_door], counts[closed_door + 1]) >= CROSSING_MIN_VIEWS
    best = None
    for _attempt in range(50):
        shell, rooms_b, doors, slabs, window, leaf = _walls(rng, counts, closed_door)
        furniture = _furniture(rng, rooms_b, doors)
        boxes = np.array([shell] + slabs + furniture)
        plain = tuple(range(1 + len(slabs)))
        cells = [_room_cells(room, boxes) for room in rooms_b]
        for _try in range(10):
            walk = _walk(rng, boxes, rooms_b, doors, counts, closed_door, window, len(plain), cells)
            if walk is None:
                continue
            rots, centers, room_of = walk
            markers, names = _floor_markers(rng, rooms_b, furniture)
            faces = [FLOOR_FACE] * len(names)
            if closed_door is not None:
                span = (rooms_b[closed_door][0, 0], rooms_b[closed_door + 1][1, 0])
                cross, cross_faces = _crossing_markers(rng, boxes, [k for k in plain if k not in leaf], window, span,
                                                       centers, rots, room_of <= closed_door, markers)
                markers = np.concatenate([markers, cross])
                names += [f"home_door{closed_door}_marker{m}" for m in range(len(cross))]
                faces += cross_faces
            layout = HomeLayout(boxes=boxes, plain_boxes=plain, rooms=rooms_b, doors=doors,
                                closed_door=closed_door, window=window, markers=markers, marker_names=names,
                                marker_faces=faces, R_world_from_cam=rots, centers=centers, room_of_view=room_of)
            if not want_crossing or _crossing_count(layout) >= CROSSING_MARKERS:
                return layout
            if best is None or _crossing_count(layout) > _crossing_count(best):
                best = layout
    if best is not None:
        return best
    raise RuntimeError("could not lay out a home with a camera walk through it")


def _crossing_count(layout: HomeLayout) -> int:
    return sum(n.startswith("home_door") for n in layout.marker_names)


def _walls(rng: np.random.Generator, counts: list[int], closed_door: int | None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray], np.ndarray | None, list[int]]:
    """Shell, room interiors, doorway openings, wall slabs (with the closed door's leaf), the closed door's window
    and the box indices of its leaf; the flat is centred on x = z = 0."""
    n = len(counts)
    widths = [rng.uniform(*ROOM_WIDTH[c]) for c in counts]
    depth, height = rng.uniform(*FLAT_DEPTH), rng.uniform(*FLAT_HEIGHT)
    length = sum(widths) + WALL_THICKNESS * (n - 1)
    ceil_y, z0, z1 = FLOOR_Y - height, -depth / 2, depth / 2
    shell = np.array([[-length / 2, ceil_y, z0], [length / 2, FLOOR_Y, z1]])
    door_lo, door_hi = z0 + 0.3, z1 - 0.3 - DOOR_WIDTH
    rooms, doors, slabs = [], [], []
    window, leaf = None, []
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
        slabs += [np.array([[x, ceil_y, z0], [xw, FLOOR_Y, zd]]),
                  np.array([[x, ceil_y, zd + DOOR_WIDTH], [xw, FLOOR_Y, z1]]),
                  np.array([[x, ceil_y, zd], [xw, FLOOR_Y - DOOR_HEIGHT, zd + DOOR_WIDTH]])]
        if r == closed_door:
            window, boards = _door_leaf(np.array(doors[-1]))
            leaf = list(range(1 + len(slabs), 1 + len(slabs) + len(boards)))
            slabs += boards
        x = xw
    return shell, np.array(rooms), np.array(doors).reshape(-1, 2, 3), slabs, window, leaf


def _door_leaf(door: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The window opening (2, 3) of a closed door filling the doorway ``door`` and the leaf's four boxes around it
    (below, above, left, right of the window)."""
    xc = door[:, 0].mean()
    x0, x1 = xc - DOOR_LEAF_THICKNESS / 2, xc + DOOR_LEAF_THICKNESS / 2
    (_, top, dz0), (_, floor, dz1) = door
    wz0 = (dz0 + dz1 - WINDOW_WIDTH) / 2
    wz1 = wz0 + WINDOW_WIDTH
    sill, head = floor - WINDOW_SILL, floor - WINDOW_SILL - WINDOW_HEIGHT
    window = np.array([[x0, head, wz0], [x1, sill, wz1]])
    boards = [np.array([[x0, sill, dz0], [x1, floor, dz1]]),  # below the window, down to the floor
              np.array([[x0, top, dz0], [x1, head, dz1]]),  # above it, up to the lintel
              np.array([[x0, head, dz0], [x1, sill, wz0]]),  # beside it
              np.array([[x0, head, wz1], [x1, sill, dz1]])]
    return window, boards


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
          counts: list[int], closed_door: int | None, window: np.ndarray | None = None, furniture_from: int = 0,
          room_cells: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Cameras room by room (None if the random walk gets stuck): consecutive ones 1-2 m apart and in sight, but
    across the closed doorway. Its nearest ``WINDOW_VIEW_CAMERAS`` cameras on each side see through its window, and
    no camera of its two rooms is nearer than ``WINDOW_MIN_DISTANCE`` to it or sees furniture (boxes from index
    ``furniture_from`` on) through it (see the module doc)."""
    door_xz = doors.mean(axis=1)[:, [0, 2]]
    room_cells = room_cells or [_room_cells(room, boxes) for room in rooms]
    centers: list[np.ndarray] = []
    rots, room_of = [], []
    for r, count in enumerate(counts):
        cells = room_cells[r]
        for j in range(count):
            y = FLOOR_Y - HOME_EYE_HEIGHT + rng.uniform(-HOME_EYE_JITTER, HOME_EYE_JITTER)
            ok = np.ones(len(cells), bool)
            if j == 0 and r > 0:
                reach = CLOSED_DOOR_REACH if r - 1 == closed_door else DOOR_REACH
                ok &= np.linalg.norm(cells - door_xz[r - 1], axis=1) <= reach
            if j == count - 1 and r < len(counts) - 1:
                reach = CLOSED_DOOR_REACH if r == closed_door else DOOR_REACH
                ok &= np.linalg.norm(cells - door_xz[r], axis=1) <= reach
            by_window = closed_door is not None and r in (closed_door, closed_door + 1)
            if by_window:
                off = np.abs(cells[:, 0] - window[:, 0].mean())
                ok &= off >= WINDOW_MIN_DISTANCE
                if r == closed_door and j == count - 1:  # the nearest one before the door: not much farther
                    ok &= off <= WINDOW_MIN_DISTANCE + 0.3
                elif r == closed_door and j == count - WINDOW_VIEW_CAMERAS:  # so that the last one is in step from here
                    ok &= (off >= WINDOW_MIN_DISTANCE + HOME_STEP_RANGE[0])
                    ok &= off <= WINDOW_MIN_DISTANCE + 0.3 + HOME_STEP_RANGE[1]
            looks = by_window and (j >= count - WINDOW_VIEW_CAMERAS if r == closed_door else j < WINDOW_VIEW_CAMERAS)
            if looks and j > 0 and (r == closed_door + 1 or j > count - WINDOW_VIEW_CAMERAS):
                # the second one looks through from about the direction of the first (the previous camera), so
                # that the two see much the same part of the far side (where the crossing markers go)
                w = window.mean(axis=0)[[0, 2]]
                u = (centers[-1][[0, 2]] - w) / np.linalg.norm(centers[-1][[0, 2]] - w)
                rel = cells - w
                ok &= rel @ u >= np.cos(np.deg2rad(WINDOW_PAIR_MAX_ANGLE_DEG)) * np.linalg.norm(rel, axis=1)
            if centers:
                prev = np.array(centers)[:, [0, 2]]
                d_all = np.linalg.norm(cells[:, None] - prev[None], axis=2)
                ok &= d_all.min(axis=1) >= HOME_MIN_SEPARATION
                if not (j == 0 and r - 1 == closed_door):  # no step across the closed door (nobody walks through)
                    ok &= (d_all[:, -1] >= HOME_STEP_RANGE[0]) & (d_all[:, -1] <= HOME_STEP_RANGE[1])
                    ok[ok] = _in_sight(centers[-1], np.column_stack([cells[ok, 0], np.full(int(ok.sum()), y),
                                                                    cells[ok, 1]]), boxes)
            if looks:
                ok[ok] = _sees_window(cells[ok], y, window, boxes)
            if by_window:
                far_room = rooms[closed_door + 1 if r == closed_door else closed_door] if looks else None
                ok[ok] = _window_clutter(cells[ok], y, window, boxes, furniture_from, far_room) <= WINDOW_MAX_CLUTTER
            if not ok.any():
                return None
            x, z = cells[np.flatnonzero(ok)[rng.integers(int(ok.sum()))]]
            centers.append(np.array([x, y, z]))
            rots.append(rot_y(rng.uniform(0.0, 2 * np.pi)))
            room_of.append(r)
    return np.array(rots), np.array(centers), np.array(room_of)


def _sees_window(cells: np.ndarray, y: float, window: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(C,) whether cameras at x-z ``cells`` and height ``y`` look at the window within WINDOW_VIEW_MAX_ANGLE_DEG
    of its normal, with a free line of sight to its centre and to its four corners (5 cm inside)."""
    centre = window.mean(axis=0)
    rel = centre[[0, 2]] - cells
    ok = np.abs(rel[:, 0]) >= np.cos(np.deg2rad(WINDOW_VIEW_MAX_ANGLE_DEG)) * np.linalg.norm(rel, axis=1)
    (_, y0, z0), (_, y1, z1) = window
    targets = [centre] + [np.array([centre[0], yy, zz])
                          for yy in (y0 + 0.05, y1 - 0.05) for zz in (z0 + 0.05, z1 - 0.05)]
    for target in targets:
        idx = np.flatnonzero(ok)
        origins = np.column_stack([cells[idx, 0], np.full(len(idx), y), cells[idx, 1]])
        rel3 = target - origins
        dist = np.linalg.norm(rel3, axis=1)
        if len(idx):
            t, _ = cast_rays(origins, rel3 / dist[:, None], boxes)
            ok[idx] = t >= dist - 1e-4
    return ok


def _window_clutter(cells: np.ndarray, y: float, window: np.ndarray, boxes: np.ndarray, furniture_from: int,
                    far_room: np.ndarray | None = None) -> np.ndarray:
    """(C,) share of the rays from cameras at x-z ``cells`` and height ``y`` through a grid of points of the window
    that pass it and land on furniture (boxes from index ``furniture_from`` on) or, given ``far_room`` (the room on
    the other side of the door), beyond it (through its far doorway)."""
    (_, y0, z0), (_, y1, z1) = window
    g = np.linspace(0.03, 0.97, 6)
    grid = np.array([[window[:, 0].mean(), y0 + a * (y1 - y0), z0 + b * (z1 - z0)] for a in g for b in g])
    origins = np.repeat(np.column_stack([cells[:, 0], np.full(len(cells), y), cells[:, 1]]), len(grid), axis=0)
    rel = np.tile(grid, (len(cells), 1)) - origins
    dist = np.linalg.norm(rel, axis=1)
    dirs = rel / dist[:, None]
    t, face = cast_rays(origins, dirs, boxes)
    x = origins[:, 0] + t * dirs[:, 0]
    beyond = np.zeros(len(x), bool) if far_room is None else (x < far_room[0, 0] - 1e-4) | (x > far_room[1, 0] + 1e-4)
    through = (t > dist).reshape(len(cells), len(grid))
    furniture = through & (face // 6 >= furniture_from).reshape(through.shape)
    far = through & beyond.reshape(through.shape)
    return np.maximum(furniture.mean(axis=1), far.mean(axis=1) - WINDOW_MAX_BEYOND)


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


def _crossing_markers(rng: np.random.Generator, boxes: np.ndarray, surfaces: list[int], window: np.ndarray,
                      span: tuple[float, float], centers: np.ndarray, rots: np.ndarray, side_a: np.ndarray,
                      markers: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Up to CROSSING_MARKERS marker centres (and their faces) on the faces of boxes ``surfaces`` between x =
    ``span`` (the closed door's two rooms), each seen whole
    by >= CROSSING_MIN_VIEWS cameras on either side of the closed door (``side_a``: cameras on its first side),
    spread out (farthest point sampling, at least CROSSING_MARKER_GAP from each other and from ``markers``).

    Candidates are where rays cast from every camera through the window land, so they lie behind it."""
    (wx0, wy0, wz0), (wx1, wy1, wz1) = window
    pts, faces = [], []
    for c in centers:
        m = _CROSSING_RAYS
        target = np.column_stack([np.full(m, (wx0 + wx1) / 2), rng.uniform(wy0 + 0.02, wy1 - 0.02, m),
                                  rng.uniform(wz0 + 0.02, wz1 - 0.02, m)])
        rel = target - c
        dist = np.linalg.norm(rel, axis=1)
        dirs = rel / dist[:, None]
        t, face = cast_rays(c, dirs, boxes)
        through = t > dist + 0.3  # passed the window (not stopped by furniture on the way) and landed beyond it
        pts.append(c + t[through, None].astype(np.float64) * dirs[through])
        faces.append(face[through])
    pts, faces = np.concatenate(pts), np.concatenate(faces).astype(int)
    keep = np.isin(faces // 6, surfaces) & (pts[:, 0] >= span[0] - 1e-6) & (pts[:, 0] <= span[1] + 1e-6)
    pts, faces = pts[keep], faces[keep]
    # the marker (radius and black ring) must lie on its face: check its rim, 4 points on the face plane
    rim_r = 1.3 * MARKER_RADIUS
    ok = np.ones(len(pts), bool)
    rims = np.zeros((len(pts), 5, 3))
    for i, (p, f) in enumerate(zip(pts, faces)):
        axis, uax, vax, plane, uv0, size = face_frame(boxes, int(f))
        uv = p[[uax, vax]]
        ok[i] = np.all(uv - rim_r - 0.02 >= uv0) and np.all(uv + rim_r + 0.02 <= uv0 + size)
        p = p.copy()
        p[axis] = plane  # exactly on the face
        rims[i] = p
        for k, (du, dv) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1)), start=1):
            rims[i, k, uax] += du * rim_r
            rims[i, k, vax] += dv * rim_r
    pts, faces, rims = rims[ok, 0], faces[ok], rims[ok]
    if not len(pts):
        return np.zeros((0, 3)), []
    normals = np.array([face_normal(int(f), room=f < 6) for f in faces])
    seen = np.zeros((len(pts), len(centers)), bool)
    flat = rims.reshape(-1, 3)
    for v, (c, R) in enumerate(zip(centers, rots)):
        rel = flat - c
        dist = np.linalg.norm(rel, axis=1)
        t, _ = cast_rays(c, rel / dist[:, None], boxes)
        whole = (t >= dist - 2e-3 * np.maximum(dist, 1.0)).reshape(-1, 5).all(axis=1)
        facing = np.einsum("ij,ij->i", normals, c - pts) >= _MIN_FACING * np.linalg.norm(c - pts, axis=1)
        lon, lat = bearings_to_lonlat((pts - c) @ R)
        inside = (np.abs(lon) <= np.pi - _BORDER_ANGLE) & (np.abs(lat) <= np.pi / 2 - _BORDER_ANGLE)
        seen[:, v] = whole & facing & inside & _clear_around(c, pts, faces, boxes)
    n_a, n_b = seen[:, side_a].sum(axis=1), seen[:, ~side_a].sum(axis=1)
    cand = np.flatnonzero((n_a >= CROSSING_MIN_VIEWS) & (n_b >= CROSSING_MIN_VIEWS))
    cand = cand[rng.permutation(len(cand))]
    # spread them (farthest point first, from the one seen by most cameras): clustered targets make large blobs
    # that SIFT matches through the window
    chosen: list[int] = []
    gap = np.full(len(cand), np.inf)
    for m in np.asarray(markers, dtype=np.float64).reshape(-1, 3):
        gap = np.minimum(gap, np.linalg.norm(pts[cand] - m, axis=1))
    while len(chosen) < CROSSING_MARKERS and len(cand):
        if not chosen:
            views = np.where(gap >= CROSSING_MARKER_GAP, (n_a + n_b)[cand], -1)
            k = int(np.argmax(views))
        else:
            k = int(np.argmax(gap))
        if gap[k] < CROSSING_MARKER_GAP:
            break
        chosen.append(int(cand[k]))
        gap = np.minimum(gap, np.linalg.norm(pts[cand] - pts[cand[k]], axis=1))
    return pts[chosen].reshape(-1, 3), [int(faces[i]) for i in chosen]



def _clear_around(c: np.ndarray, pts: np.ndarray, faces: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) whether the rays from ``c`` _CLEAR_ANGLE up, down, left and right of each point land on its face."""
    d = pts - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e1 = np.cross(d, [0.0, 1.0, 0.0])
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-9)
    e2 = np.cross(d, e1)
    ok = np.ones(len(pts), bool)
    for e in (e1, -e1, e2, -e2):
        ray = d + np.tan(_CLEAR_ANGLE) * e
        _, face = cast_rays(c, ray / np.linalg.norm(ray, axis=1, keepdims=True), boxes)
        ok &= face == faces
    return ok
