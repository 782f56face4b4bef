"""World planes (sfm/dense/world_planes.py): extents with gravity known, and planes the views disagree with.

The room scenes (plain box, doorway, a plane seen through) are in tests/test_planes.py; these check the properties
the gravity extents and the one-sided planes rely on, on exact synthetic points.
"""

from dataclasses import replace

import numpy as np
import pytest

from fullview.sfm.dense import planes, world_planes

UP = np.array([0.0, -1.0, 0.0])  # y down, as the pipeline's cameras
CELL = 0.1


def _line(a, b, step=0.02):
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
    return a + np.linspace(0, 1, n)[:, None] * (b - a)


def _wall_with_doorway():
    """Support of a plain wall z = 3, x in [-2, 2], floor y = 1.2, ceiling y = -1.3, with a doorway x in [-0.5, 0.5]
    up to y = -0.8: what stereo finds there (floor and ceiling lines, corners, the doorway's jambs and lintel)."""
    z = 3.0
    parts = [_line([-2, 1.2, z], [-0.5, 1.2, z]), _line([0.5, 1.2, z], [2, 1.2, z]),  # floor line, open at the door
             _line([-2, -1.3, z], [2, -1.3, z]),  # ceiling line
             _line([-2, -1.3, z], [-2, 1.2, z]), _line([2, -1.3, z], [2, 1.2, z]),  # corners
             _line([-0.5, 1.2, z], [-0.5, -0.8, z]), _line([0.5, 1.2, z], [0.5, -0.8, z]),  # jambs
             _line([-0.5, -0.8, z], [0.5, -0.8, z])]  # lintel
    return np.vstack(parts), np.array([0.0, 0.0, 1.0]), z


def _cells(origin, axes, extent, points):
    uv = (points - origin) @ axes.T / CELL
    return extent[np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)]


def test_gravity_extent_fills_a_wall_between_floor_and_ceiling_but_not_its_doorway():
    support, normal, z = _wall_with_doorway()
    origin, axes, extent, fallback = world_planes._extent(support, normal, z, CELL, 3, False, "gravity", UP)
    plain = np.array([[-1.3, 0.2, z], [1.3, -0.5, z], [1.5, 0.9, z], [-1.0, -1.0, z]])
    doorway = np.array([[0.0, 0.9, z], [0.0, 0.3, z], [-0.2, -0.3, z], [0.2, 0.6, z]])
    assert _cells(origin, axes, extent, plain).all()
    assert not _cells(origin, axes, extent, doorway).any()
    # the support's own extent (closed, holes filled) is kept as the fallback for carve_extents
    assert fallback is not None and not _cells(origin, axes, fallback, doorway).any()


def test_a_level_plane_spans_its_support_even_with_an_open_outline():
    # a ceiling supported along the walls of a room, its outline open above a doorway: the support mode encloses
    # nothing, the gravity mode spans the rectangle
    y = -1.3
    support = np.vstack([_line([-4, y, -2], [4, y, -2]), _line([-4, y, 2], [-0.5, y, 2]),
                         _line([0.5, y, 2], [4, y, 2]),  # open above a doorway in the z = 2 wall
                         _line([-4, y, -2], [-4, y, 2]), _line([4, y, -2], [4, y, 2])])
    normal = np.array([0.0, 1.0, 0.0])
    middle = np.array([[-2.0, y, 0.0], [2.0, y, 1.0], [3.0, y, -1.2]])
    o, a, gravity, _ = world_planes._extent(support, normal, y, CELL, 3, False, "gravity", UP)
    assert _cells(o, a, gravity, middle).all()
    o, a, closed, _ = world_planes._extent(support, normal, y, CELL, 3, False, "support", UP)
    assert not _cells(o, a, closed, middle).any()


def _thin_wall(gap: float):
    """Points on the two faces (x = 0 and x = gap) of a wall, each measured by a camera in its own room."""
    rng = np.random.default_rng(0)
    face = np.column_stack([np.zeros(800), rng.uniform(-1.3, 1.2, 800), rng.uniform(-2, 2, 800)])
    points = np.vstack([face, face + [gap, 0, 0]])
    observers = np.repeat([[-2.0, 0.0, 0.0], [2.0 + gap, 0.0, 0.0]], 800, axis=0)
    ranges = np.linalg.norm(points - observers, axis=1)
    return points, ranges, observers


def test_a_plane_through_both_faces_of_a_thin_wall_is_not_kept():
    # the faces are closer than the support tolerance: one plane explains both, but its points were seen from both
    # sides; a surface is seen from one side only, so with the observers known it is not kept
    points, ranges, observers = _thin_wall(0.02)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=100)
    blind = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP)
    assert any(abs(p.normal[0]) > 0.99 and p.front == 0 for p in blind)
    seen = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP,
                                            observers=observers)
    assert not any(abs(p.normal[0]) > 0.99 for p in seen)


def test_faces_of_a_thick_wall_are_one_sided_and_only_their_own_side_fills():
    # 10 cm apart: two planes, each seen from its own room; a camera behind a face does not get it
    points, ranges, observers = _thin_wall(0.1)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=100)
    found = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP,
                                             observers=observers)
    walls = sorted((p for p in found if abs(p.normal[0]) > 0.99), key=lambda p: p.offset * np.sign(p.normal[0]))
    assert len(walls) == 2
    for plane, x_room in zip(walls, (-2.0, 2.1)):
        assert plane.front == int(np.sign(plane.normal[0] * x_room - plane.offset))


def _yawed_room_points(yaw_deg: float, seed: int = 0):
    """Stereo-like points of a plain box room turned by ``yaw_deg`` about the vertical, seen from the origin: each
    surface with 0.3% range noise, and the floor's band along one wall 3% too far (what the matching window does at
    the line where two plain surfaces meet), which tilts a least-squares floor."""
    rng = np.random.default_rng(seed)
    yaw = np.radians(yaw_deg)
    rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    n = 1500
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    faces = [np.column_stack([4 * u, np.full(n, 1.2), 3 * v]),  # floor (y down)
             np.column_stack([4 * u, np.full(n, -1.3), 3 * v]),  # ceiling
             np.column_stack([np.full(n, -4.0), 1.25 * v - 0.05, 3 * u]),  # walls
             np.column_stack([np.full(n, 4.0), 1.25 * v - 0.05, 3 * u]),
             np.column_stack([4 * u, 1.25 * v - 0.05, np.full(n, -3.0)]),
             np.column_stack([4 * u, 1.25 * v - 0.05, np.full(n, 3.0)])]
    band = np.column_stack([rng.uniform(3.0, 4.0, 1000), np.full(1000, 1.2), rng.uniform(-3, 3, 1000)]) * 1.03
    points = np.vstack(faces + [band])
    points *= 1 + 0.003 * rng.standard_normal(len(points))[:, None]
    points = points @ rot.T
    return points, np.linalg.norm(points, axis=1), np.zeros_like(points), rot


def test_with_gravity_planes_are_exactly_level_or_on_the_dominant_wall_directions():
    points, ranges, observers, rot = _yawed_room_points(20.0)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=300, max_planes=8)
    found = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP,
                                             observers=observers)
    level = [p for p in found if abs(p.normal @ UP) > 0.5]
    walls = [p for p in found if abs(p.normal @ UP) <= 0.5]
    assert len(level) >= 2 and len(walls) >= 4
    for plane in level:
        assert abs(abs(plane.normal @ UP) - 1) < 1e-12
    floor = max((p for p in level if p.offset * np.sign(p.normal[1]) > 0), key=lambda p: p.support)
    assert abs(floor.offset * np.sign(floor.normal[1]) - 1.2) < 0.01
    room_x = rot[:, 0]  # the room's own wall normals are rot's x and z columns
    for plane in walls:
        assert abs(plane.normal @ UP) < 1e-12
        assert min(abs(abs(plane.normal @ room_x) - 1), abs(plane.normal @ room_x)) < np.sin(np.radians(0.3))
    # the fit alone (no snapping) is tilted by the biased band: what the snapping removes
    plain = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0),
                                             world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=300,
                                                                            max_planes=8, snap_deg=0.0),
                                             up=UP, observers=observers)
    tilt = max(np.degrees(np.arccos(min(1.0, abs(p.normal @ UP)))) for p in plain if abs(p.normal @ UP) > 0.5)
    assert tilt > 0.1


def test_dominant_wall_azimuth_is_the_weighted_mode_modulo_a_right_angle():
    az = np.radians([20.0, 110.5, 199.5, 290.0, 47.0])  # four walls of one room and one odd wall
    normals = np.column_stack([np.cos(az), np.zeros(5), np.sin(az)])
    weights = np.array([5.0, 3.0, 3.0, 5.0, 6.0])
    found = world_planes.dominant_wall_azimuth(normals, weights, UP)
    e1, e2 = world_planes._horizontal_basis(UP)
    expected = np.arctan2(np.array([np.cos(np.radians(20)), 0, np.sin(np.radians(20))]) @ e2,
                          np.array([np.cos(np.radians(20)), 0, np.sin(np.radians(20))]) @ e1)
    diff = np.angle(np.exp(4j * (found - expected))) / 4
    assert abs(np.degrees(diff)) < 0.2


def test_a_ceilings_rectangle_follows_the_walls_not_the_stray_points_beyond_them():
    # the room turned by 20°: the ceiling's gravity rectangle is taken along the walls (a rectangle in other axes
    # has corners outside the room, where rays past a plain wall met it); a few ceiling points 0.4 m beyond a wall
    # (stereo too far at the line where the ceiling meets it) do not stretch it
    points, ranges, observers, rot = _yawed_room_points(20.0)
    rng = np.random.default_rng(1)
    stray = np.column_stack([rng.uniform(4.2, 4.4, 15), np.full(15, -1.3), rng.uniform(-3, 3, 15)]) @ rot.T
    points = np.vstack([points, stray])
    ranges = np.linalg.norm(points, axis=1)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=300, max_planes=8)
    found = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP,
                                             observers=np.zeros_like(points))
    ceiling = max((p for p in found if abs(p.normal @ UP) > 0.5 and p.offset * np.sign(p.normal[1]) < 0),
                  key=lambda p: p.support)
    inside = np.array([[3.6, -1.3, 2.6], [-3.6, -1.3, -2.6], [0.0, -1.3, 0.0], [3.6, -1.3, -2.6]]) @ rot.T
    beyond = np.array([[4.35, -1.3, 0.0], [4.35, -1.3, 2.0]]) @ rot.T
    corner = rot @ np.array([4.0, -1.3, 3.0])  # the corner of the room's axis-aligned bounding box in the world
    world_box_corner = np.array([[abs(corner[0]) * 0.97, -1.3, (rot @ np.array([-4.0, -1.3, 3.0]))[2] * 0.97]])
    assert ceiling.contains(inside).all()
    assert not ceiling.contains(beyond).any()
    assert not ceiling.contains(world_box_corner).any()


def test_a_wall_seen_only_along_its_floor_and_ceiling_lines_is_found_by_the_sweep():
    # the +z wall is plain: its stereo is its floor and ceiling lines, which the floor and the ceiling explain first,
    # so RANSAC (scoring unexplained points) never takes it; the sweep along the dominant directions does
    yaw = np.radians(20.0)
    rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    rng = np.random.default_rng(0)
    n = 2000
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    points = np.vstack([np.column_stack([4 * u, np.full(n, 1.2), 3 * v]),
                        np.column_stack([4 * u, np.full(n, -1.3), 3 * v]),
                        np.column_stack([np.full(n, -4.0), 1.25 * v - 0.05, 3 * u]),
                        np.column_stack([np.full(n, 4.0), 1.25 * v - 0.05, 3 * u]),
                        np.column_stack([4 * u, 1.25 * v - 0.05, np.full(n, -3.0)]),
                        _line([-4, 1.2, 3], [4, 1.2, 3]), _line([-4, -1.3, 3], [4, -1.3, 3])]) @ rot.T
    ranges, observers = np.linalg.norm(points, axis=1), np.zeros_like(points)
    wall_normal = rot @ np.array([0.0, 0.0, 1.0])

    def has_the_wall(planes):
        return any(abs(p.normal @ wall_normal) > 0.999 and abs((p.normal * p.offset) @ wall_normal - 3.0) < 0.03
                   for p in planes)

    for sweep in (True, False):
        options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=300, sweep_walls=sweep)
        found = world_planes.detect_world_planes(points, ranges, np.random.default_rng(0), options, up=UP,
                                                 observers=observers)
        assert has_the_wall(found) == sweep
        assert all(p.front != 0 for p in found)


def _level(y, support, normal_sign=1.0, front=0):
    normal = np.array([0.0, normal_sign, 0.0])
    points = np.stack(np.meshgrid(np.linspace(-2, 2, 21), [y], np.linspace(-2, 2, 21)), -1).reshape(-1, 3)
    origin, axes, extent, _ = world_planes._extent(points, normal, normal_sign * y, CELL, 3, False)
    return world_planes.WorldPlane(normal=normal, offset=normal_sign * y, origin=origin, axes=axes, cell=CELL,
                                   extent=extent, support=support, level=True, front=front)


def _flat_points(seed=0):
    """Stereo-like points of a flat: a floor y = 1.2 with 6 mm noise, the bottom strips of its four walls (they
    trail above the floor), a ceiling y = -1.3 and a table top y = 0.45, seen from three cameras at y = 0:
    (points, ranges from the nearest camera, that camera's centre)."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(np.arange(-3, 3, 0.05), [0.0], np.arange(-3, 3, 0.05)), -1).reshape(-1, 3)
    floor = grid + [0, 1.2, 0] + rng.normal(scale=[0, 0.006, 0], size=grid.shape)
    ceiling = grid + [0, -1.3, 0] + rng.normal(scale=[0, 0.006, 0], size=grid.shape)
    table = grid[np.all(np.abs(grid[:, [0, 2]] - [1.5, 1.5]) < 0.4, axis=1)] + [0, 0.45, 0]
    side = np.arange(-3, 3, 0.05)
    strips = [np.stack(np.meshgrid(side, np.arange(1.0, 1.2, 0.02), [s]), -1).reshape(-1, 3) for s in (-3, 3)]
    strips += [p[:, [2, 1, 0]] for p in strips]
    points = np.vstack([floor, ceiling, table] + strips)
    cameras = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [1.0, 0.0, -1.0]])
    distances = np.linalg.norm(points[:, None] - cameras[None], axis=2)
    return points, distances.min(axis=1), cameras[np.argmin(distances, axis=1)]


def _heights_of_level(planes, low, high):
    out = []
    for p in planes:
        height = p.offset * np.sign(p.normal @ UP)
        if p.level and low < height < high:
            out.append(height)
    return out


def test_the_pieces_of_a_floor_become_one_level_plane_at_the_height_of_its_points():
    # the floor (height -1.2 along UP) found as six pieces 1-3 cm apart with both signs of the normal and supports
    # within 2% of each other, as on the home of seed 17; the best supported piece 3 cm above the floor
    points, ranges, observers = _flat_points()
    tolerance = 0.015 * ranges
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)
    floor_ys = [1.17, 1.185, 1.195, 1.205, 1.215, 1.18]
    ceiling, table = _level(-1.3, 900, 1.0, 1), _level(0.45, 150, -1.0, 1)
    wall = world_planes.WorldPlane(normal=np.array([0.0, 0.0, 1.0]), offset=3.0, origin=np.zeros(3),
                                   axes=np.eye(3)[:2], cell=CELL, extent=np.ones((2, 2), bool), support=100)

    def merged(supports, pts=points):
        pieces = [_level(y, s, sign, -int(sign)) for y, s, sign in zip(floor_ys, supports, [1, -1, 1, -1, 1, -1])]
        planes = pieces[:3] + [wall, ceiling] + pieces[3:] + [table]
        out = world_planes._one_level_plane_per_band(planes, pts, tolerance, UP, observers, options)
        assert any(p is wall for p in out)
        return out

    out = merged([1000, 990, 985, 980, 995, 992])
    floors = _heights_of_level(out, -1.3, -1.1)
    assert len(floors) == 1  # one plane for both signs of the normal (the old rule kept one of each)
    assert abs(floors[0] + 1.2) < 0.002  # the points' mode, not the best piece's 3 cm off
    assert len(_heights_of_level(out, 1.2, 1.4)) == 1 and len(_heights_of_level(out, -0.5, -0.4)) == 1
    # which piece is the best supported, or a tiny change of the points, does not move it
    for supports in ([980, 990, 1000, 985, 995, 992], [980, 990, 985, 1000, 995, 992]):
        assert _heights_of_level(merged(supports), -1.3, -1.1) == floors
    shaken = points + np.random.default_rng(1).normal(scale=1e-6, size=points.shape)
    assert abs(_heights_of_level(merged([1000, 990, 985, 980, 995, 992], shaken), -1.3, -1.1)[0] - floors[0]) < 1e-4
    # pieces farther apart than the bands are separate surfaces (a table top above the floor)
    apart = [_level(1.2, 900, -1.0, 1), _level(0.9, 300, -1.0, 1)]
    assert len(world_planes._one_level_plane_per_band(apart, points, tolerance, UP, observers, options)) == 2


def _ceiling_views(height: float, too_far: float):
    """Two panoramas at y = 0 whose stereo sees only a ceiling ``height`` above them, ``too_far`` (relative) too far
    as a plain ceiling's stereo often is."""
    views = []
    for center in ([0.0, 0.0, 0.0], [1.0, 0.0, 0.5]):
        bearings = world_planes.reduced_bearings_world(np.eye(3), 256, 128).astype(np.float64)
        cos = bearings @ UP
        with np.errstate(divide="ignore", invalid="ignore"):
            ranges = np.where(cos > 0.1, (1 + too_far) * height / cos, np.nan).astype(np.float32)
        views.append(world_planes.View(R_cam_from_world=np.eye(3), t_cam_from_world=-np.asarray(center),
                                       range_map=ranges, observable=np.ones(ranges.shape, bool),
                                       color=np.zeros((*ranges.shape, 3), np.float32)))
    return views


def test_a_level_plane_of_a_band_is_dropped_only_when_the_views_see_well_beyond_it():
    views = _ceiling_views(1.3, 0.04)  # the stereo 4% (5 cm) beyond the ceiling, 1.3 above the cameras
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)

    def kept(height: float, drop_tolerance: float) -> bool:
        grid = np.stack(np.meshgrid(np.arange(-3, 3, 0.05), [-height], np.arange(-3, 3, 0.05)), -1).reshape(-1, 3)
        origin, axes, extent, _ = world_planes._extent(grid, UP, height, CELL, 3, False)
        plane = world_planes.WorldPlane(normal=UP, offset=height, origin=origin, axes=axes, cell=CELL,
                                        extent=extent, support=len(grid), level=True, front=-1,
                                        drop_tolerance=drop_tolerance)
        return world_planes._carve(plane, views, options)

    assert not kept(1.3, 0.0)  # judged by view_tolerance (3%): seen through on every judged cell
    margin = world_planes.LEVEL_DROP_TOLERANCES * options.view_tolerance
    assert kept(1.3, margin)  # the band's plane: a ceiling whose stereo is 4% too far
    assert not kept(1.0, margin)  # a plane 30 cm below the ceiling is still seen through
    # the pieces of a band become a plane judged that way
    points, ranges, observers = _flat_points()
    merged = world_planes._one_level_plane_per_band([_level(-1.3, 900, 1.0, 1)], points, 0.015 * ranges, UP,
                                                    observers, options)
    assert merged[0].drop_tolerance == margin


def _turned(points, degrees):
    """Points turned about the vertical (UP) by ``degrees``."""
    a = np.radians(degrees)
    rot = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return points @ rot.T


def _long_room(turn_deg, seed=0, step_at=None):
    """Stereo-like points of the walls of a long room, x in [-6, 6], z in [-2, 2], floor y = 1.2, ceiling y = -1.3,
    each wall a grid with 5 mm noise, seen from cameras along z = 0; turned about the vertical by ``turn_deg``.
    ``step_at``: the z = 2 wall steps 10 cm back (to z = 2.1) for x > step_at, an alcove a wall's thickness deep.
    Returns (points, ranges from the nearest camera, that camera's centre, cameras)."""
    rng = np.random.default_rng(seed)
    along, height = np.arange(-6, 6, 0.04), np.arange(-1.3, 1.2, 0.04)
    u, h = (a.ravel() for a in np.meshgrid(along, height))
    far = np.where(u > step_at, 2.1, 2.0) if step_at is not None else np.full(len(u), 2.0)
    across, hh = (a.ravel() for a in np.meshgrid(np.arange(-2, 2, 0.04), height))
    walls = [np.column_stack([u, h, far]), np.column_stack([u, h, np.full(len(u), -2.0)]),
             np.column_stack([np.full(len(across), 6.0), hh, across]),
             np.column_stack([np.full(len(across), -6.0), hh, across])]
    points = np.vstack(walls)
    points = points + rng.normal(scale=0.005, size=points.shape)
    cameras = np.column_stack([np.arange(-5, 5.5, 1.0), np.zeros(11), np.zeros(11)])
    points, cameras = _turned(points, turn_deg), _turned(cameras, turn_deg)
    distances = np.linalg.norm(points[:, None] - cameras[None], axis=2)
    nearest = np.argmin(distances, axis=1)
    return points, distances.min(axis=1), cameras[nearest], cameras


def _wall_piece(normal_deg, offset, support, cell=CELL):
    """A snapped wall piece seen from the side of its normal, (1, 0, 0) turned by ``normal_deg`` about the vertical
    (90: -z, -90: +z)."""
    normal = _turned(np.array([[1.0, 0.0, 0.0]]), normal_deg)[0]
    return world_planes.WorldPlane(normal=normal, offset=offset, origin=np.zeros(3), axes=np.eye(3)[:2], cell=cell,
                                   extent=np.ones((2, 2), bool), support=support, front=1)


def _pieces_of_the_room(mode_deg, far_offsets, supports):
    """The room's walls as RANSAC and the sweep find them, snapped to a dominant direction ``mode_deg`` off the
    truth: the z = 2 wall (seen from -z) in pieces at ``far_offsets`` (along its outward normal), the other three
    walls one piece each."""
    pieces = [_wall_piece(mode_deg + 90.0, o, s) for o, s in zip(far_offsets, supports)]  # outward normal -z
    pieces += [_wall_piece(mode_deg - 90.0, -2.0, 900), _wall_piece(mode_deg + 180.0, -6.0, 500),
               _wall_piece(mode_deg, -6.0, 500)]
    return pieces


def _walls_facing(planes, outward, turn_deg):
    """(offset, normal) of the planes whose outward normal is within 2° of ``outward`` turned by ``turn_deg``."""
    direction = _turned(np.asarray(outward, float)[None], turn_deg)[0]
    return [(p.offset * p.front, p.front * p.normal) for p in planes
            if p.front and (p.front * p.normal) @ direction > np.cos(np.radians(2.0))]


def test_the_pieces_of_a_wall_become_one_plane_along_the_direction_of_all_walls_points():
    # the room is turned 0.4° about the vertical; the pieces were snapped to a dominant direction 0.9° off it (the
    # mode of short pieces' fitted normals, as on home 3), the long z = 2 wall found as six pieces 1-3 cm apart
    turn = 0.4
    points, ranges, observers, _ = _long_room(turn)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)
    offsets = [-2.03, -2.01, -1.99, -1.98, -2.02, -2.0]

    def merged(supports, pts=points):
        pieces = _pieces_of_the_room(turn + 0.9, offsets, supports)
        return world_planes._one_wall_plane_per_offset(pieces, pts, 0.015 * ranges, UP, observers, options)

    out = merged([1000, 990, 985, 980, 995, 992])
    far = _walls_facing(out, [0.0, 0.0, -1.0], turn)
    assert len(far) == 1  # one plane for the six pieces
    offset, normal = far[0]
    true_normal = _turned(np.array([[0.0, 0.0, -1.0]]), turn)[0]
    assert np.degrees(np.arccos(min(1.0, normal @ true_normal))) < 0.05  # the walls' points, not the pieces' 0.9°
    assert abs(offset + 2.0) < 0.003
    assert out[[p.front * p.normal @ true_normal > 0.99 for p in out].index(True)].drop_tolerance > 0
    for outward in ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]):  # the other walls turned with it
        assert len(_walls_facing(out, outward, turn)) == 1
    # which piece is the best supported, or a tiny change of the points, does not move it
    for supports in ([980, 990, 1000, 985, 995, 992], [980, 990, 985, 1000, 995, 992]):
        assert _walls_facing(merged(supports), [0.0, 0.0, -1.0], turn)[0][0] == offset
    shaken = points + np.random.default_rng(1).normal(scale=1e-6, size=points.shape)
    offset2, normal2 = _walls_facing(merged([1000, 990, 985, 980, 995, 992], shaken), [0.0, 0.0, -1.0], turn)[0]
    assert abs(offset2 - offset) < 1e-4 and np.degrees(np.arccos(min(1.0, normal2 @ normal))) < 1e-3


def test_two_parallel_walls_a_wall_thickness_apart_are_not_merged():
    # the z = 2 wall steps back 10 cm for x > 0 (3 median tolerances at these ranges): two surfaces seen from the
    # same side; and the two faces of one thin wall are seen from opposite sides
    points, ranges, observers, _ = _long_room(0.0, step_at=0.0)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)
    tolerance = 0.015 * ranges
    assert 0.1 > 3 * np.median(tolerance)
    out = world_planes._one_wall_plane_per_offset(_pieces_of_the_room(0.0, [-2.0, -2.01, -2.1, -2.09],
                                                                      [900, 800, 700, 600]),
                                                  points, tolerance, UP, observers, options)
    far = sorted(o for o, _ in _walls_facing(out, [0.0, 0.0, -1.0], 0.0))
    assert len(far) == 2 and abs(far[0] + 2.1) < 0.005 and abs(far[1] + 2.0) < 0.005
    # the other face of the z = -2 wall (seen from z < -2) is a wall of its own
    back = points[:, 2] < -1.9
    behind = observers.copy()
    behind[back] = observers[back] * [1, 1, 0] + [0, 0, -4.0]
    pieces = _pieces_of_the_room(0.0, [-2.0], [900])
    pieces.append(world_planes.WorldPlane(normal=np.array([0.0, 0.0, 1.0]), offset=-2.0, origin=np.zeros(3),
                                          axes=np.eye(3)[:2], cell=CELL, extent=np.ones((2, 2), bool), support=400,
                                          front=-1))
    out = world_planes._one_wall_plane_per_offset(pieces, np.vstack([points, points[back] + [0, 0, -0.1]]),
                                                  np.concatenate([tolerance, tolerance[back]]), UP,
                                                  np.vstack([observers, behind[back]]), options)
    assert len(_walls_facing(out, [0.0, 0.0, 1.0], 0.0)) == 1 and len(_walls_facing(out, [0.0, 0.0, -1.0], 0.0)) == 2


def _wall_beside_an_opening(opening_columns: int) -> tuple[world_planes.WorldPlane, list]:
    """A wall z = 3 (x in [-2, 2], y from 1.2 up to -1.3: 40 x 25 cells) whose generous extent is its whole grid and
    whose support's extent (``fallback``) its left 20 columns, and one view at the origin. The view's ranges: on the
    wall along its floor and ceiling rows and its two corner columns (a plain wall's stereo); beyond the wall (the
    room behind) in the ``opening_columns`` columns right of the support (an opening the generous extent bridged);
    none elsewhere (plain)."""
    rows, cols = 25, 40
    plane = world_planes.WorldPlane(normal=np.array([0.0, 0.0, 1.0]), offset=3.0, origin=np.array([-2.0, 1.2, 3.0]),
                                    axes=np.array([[1.0, 0, 0], [0, -1.0, 0]]), cell=CELL,
                                    extent=np.ones((rows, cols), bool), support=1000, front=-1)
    plane.fallback = np.zeros((rows, cols), bool)
    plane.fallback[:, :20] = True
    h, w = 512, 1024
    bearings = planes.reduced_bearings_world(np.eye(3), w, h).reshape(-1, 3).astype(np.float64)
    with np.errstate(divide="ignore"):
        r = np.where(bearings[:, 2] > 0.1, 3.0 / bearings[:, 2], np.nan)
    row, col, inside = plane.cells_of(np.nan_to_num(bearings * r[:, None]))
    on = inside & ((row == 0) | (row == rows - 1) | (col == 0) | (col == cols - 1))
    opening = inside & (col >= 20) & (col < 20 + opening_columns)
    ranges = np.where(opening, 1.3 * r, np.where(on, r, np.nan)).astype(np.float32).reshape(h, w)
    view = planes.View(R_cam_from_world=np.eye(3), t_cam_from_world=np.zeros(3), range_map=ranges,
                       observable=np.ones((h, w), bool), color=np.zeros((h, w, 3), np.float32))
    return plane, [view]


def test_a_wall_beside_an_opening_keeps_about_the_same_extent_when_one_more_column_is_seen_through():
    # 4 and 5 columns of the opening seen through: 46% and 52% of the judged cells of the generous extent, either
    # side of max_seen_through. Judged as a whole, the wall kept its plain right part in the one and fell back to
    # its support in the other (the 360_Flat cliff); judged column by column with the votes around, one more
    # column seen through moves about one column, and no cell of the opening is kept either way
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)
    kept = {}
    for n in (4, 5):
        for local in (True, False):
            plane, views = _wall_beside_an_opening(n)
            assert world_planes.carve_extents([plane], views, replace(options, local_extent=local)) == [plane]
            kept[n, local] = plane.extent.copy()
    assert abs(int(kept[4, False].sum()) - int(kept[5, False].sum())) >= 10 * 25  # the old rule's cliff
    assert abs(int(kept[4, True].sum()) - int(kept[5, True].sum())) <= 2 * 25
    for n in (4, 5):
        assert not kept[n, True][:, 20:20 + n].any()  # the opening
        assert kept[n, True][:, :20].all() and kept[n, True][:, 32:].all()  # the support, the plain wall further on


def test_a_wall_narrower_than_the_window_of_votes_is_judged_by_all_its_columns():
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL)
    seen_on, carved = np.zeros((10, 5), bool), np.zeros((10, 5), bool)
    seen_on[0, 0] = True
    assert world_planes._evidenced(seen_on, carved, options).all()
    carved[:, 4] = True
    assert not world_planes._evidenced(seen_on, carved, options).any()
    wide_on, wide_carved = np.zeros((10, 40), bool), np.zeros((10, 40), bool)
    wide_on[0, 0] = True
    wide_carved[:, 39] = True  # seen through 30 columns away: outside the window of the first columns
    evidenced = world_planes._evidenced(wide_on, wide_carved, options)
    assert evidenced[:, :9].all() and not evidenced[:, 9:].any()


def _reference_mode(values, band):
    """The wall and level fits' mode as first written: medians of masked windows (np.median each time)."""
    mode = float(np.median(values))
    for window in world_planes.LEVEL_MODE_WINDOWS:
        for _ in range(world_planes.LEVEL_MODE_ROUNDS):
            near = values[np.abs(values - mode) <= window * band]
            if len(near) < 3:
                break
            previous, mode = mode, float(np.median(near))
            if previous == mode:
                break
    return mode


def _mode_samples(rng):
    """Offsets as the fits see them (a peak on a spread), on a grid of a quarter band (values exactly at the windows'
    edges, many ties), with exact duplicates, and tiny sets."""
    band = 0.04
    yield rng.normal(0.3, 0.02, 400).tolist() + rng.uniform(-1, 1, 600).tolist(), band
    yield (np.round(rng.normal(0.0, 0.05, 300) / (band / 4)) * (band / 4)).tolist(), band
    yield np.repeat(rng.uniform(-0.1, 0.1, 40), rng.integers(1, 6, 40)).tolist(), band
    yield [0.5], band
    yield [0.5, 0.52], band
    yield [0.1, 0.1 + 2 * band, 0.1 + 4 * band], band
    yield (rng.normal(0, 1e-3, 50) + 1e6).tolist(), 1e-4  # rounding where the values are large


def test_the_mode_read_off_sorted_values_is_the_masked_medians_mode():
    rng = np.random.default_rng(3)
    for _ in range(40):
        for values, band in _mode_samples(rng):
            values = np.array(values)
            expected = _reference_mode(values, band)
            assert world_planes._mode_of(rng.permutation(values), band) == expected
            assert world_planes._mode_of(np.sort(values), band, presorted=True) == expected


class _ReferenceWallSide:
    """The wall side as first written: every point seen from the side sorted by offset (stable), slabs bisected."""

    def __init__(self, flat, seen_from, tolerance, azimuth):
        normal = np.array([np.cos(azimuth), np.sin(azimuth)])
        d = flat @ normal
        front = np.flatnonzero(seen_from @ normal > d)
        self.index = front[np.argsort(d[front], kind="stable")]
        self.d, self.tolerance = d[self.index], tolerance[self.index]
        self.widest = float(self.tolerance.max()) if len(self.index) else 0.0

    def offset(self, low, high, band):
        values = self.d[np.searchsorted(self.d, low, "left"):np.searchsorted(self.d, high, "right")]
        return _reference_mode(values, band) if len(values) >= 3 else 0.5 * (low + high)

    def near(self, offset, shrink):
        lo = np.searchsorted(self.d, offset - shrink * self.widest, "left")
        hi = np.searchsorted(self.d, offset + shrink * self.widest, "right")
        ok = np.abs(self.d[lo:hi] - offset) <= shrink * self.tolerance[lo:hi]
        return self.index[lo:hi][ok]


def test_a_wall_sides_slabs_are_those_of_all_its_points_sorted():
    """The same points, in the same order (ties in row order), and the same modes as sorting every point of the side
    by its offset, on points with repeated offsets (duplicated points, a grid), a few far ones with wide tolerances,
    and slab bounds on points' offsets."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        n = 3000
        flat = np.round(rng.uniform(-3, 3, (n, 2)), 2 if trial % 2 else 6)  # coarse grid: many equal offsets
        flat = np.vstack([flat, flat[:200]])  # exact duplicates
        seen_from = flat + rng.normal(0, 1, flat.shape)
        tolerance = np.where(rng.random(len(flat)) < 0.02, 0.5, 0.03) * rng.uniform(0.5, 1.5, len(flat))
        azimuth = 0.0 if trial < 2 else rng.uniform(-np.pi, np.pi)
        fast = world_planes._WallSide(flat, seen_from, tolerance, azimuth)
        slow = _ReferenceWallSide(flat, seen_from, tolerance, azimuth)
        offsets = np.concatenate([rng.uniform(-3, 3, 20), slow.d[rng.integers(0, len(slow.d), 20)]])
        for offset in offsets:
            for shrink in (3.0, 1.0):
                np.testing.assert_array_equal(fast.near(offset, shrink), slow.near(offset, shrink))
            for low, high in ((offset - 0.1, offset + 0.1), (offset, offset), (offset + 0.1, offset - 0.1)):
                assert fast.offset(low, high, 0.04) == slow.offset(low, high, 0.04)


@pytest.mark.parametrize("index_after", [0, 10**9])
def test_a_wall_sides_slabs_read_from_its_offset_buckets_are_those_of_a_pass_over_all_its_points(
        monkeypatch, index_after):
    """Indexed from the first slab (0) or never: the same points in the same order and the same modes as sorting
    every point of the side, with offsets crowded into few buckets (a coarse grid, duplicates, a far outlier that
    stretches the buckets), slab bounds on points' offsets and beyond all of them."""
    monkeypatch.setattr(world_planes, "INDEX_AFTER_SLABS", index_after)
    rng = np.random.default_rng(11)
    for trial in range(4):
        flat = np.round(rng.uniform(-3, 3, (2000, 2)), 3 if trial % 2 else 7)
        flat = np.vstack([flat, flat[:100], [[400.0, -300.0]]])  # duplicates; one point far away
        seen_from = flat + rng.normal(0, 1, flat.shape)
        tolerance = np.where(rng.random(len(flat)) < 0.02, 0.5, 0.03) * rng.uniform(0.5, 1.5, len(flat))
        azimuth = rng.uniform(-np.pi, np.pi)
        fast = world_planes._WallSide(flat, seen_from, tolerance, azimuth)
        slow = _ReferenceWallSide(flat, seen_from, tolerance, azimuth)
        offsets = np.concatenate([rng.uniform(-4, 4, 15), slow.d[rng.integers(0, len(slow.d), 15)],
                                  [slow.d.min(), slow.d.max(), slow.d.max() + 1]])
        for offset in offsets:
            for shrink in (3.0, 1.0):
                np.testing.assert_array_equal(fast.near(offset, shrink), slow.near(offset, shrink))
            for low, high in ((offset - 0.1, offset + 0.1), (offset, offset), (offset - 1e3, offset + 1e3)):
                assert fast.offset(low, high, 0.04) == slow.offset(low, high, 0.04)
        assert (fast._index is not None) == (index_after == 0)


def test_a_run_within_reach_is_what_the_mask_keeps_at_the_last_bit():
    """``abs(v - c) <= r`` as rounded and ``c - r <= v <= c + r`` disagree for values within a few ulps of the
    bounds; the run found by bisection must still be exactly the mask's values."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        centre, reach = rng.uniform(-10, 10), rng.uniform(0, 1)
        edges = [centre - reach, centre + reach]
        near_edges = [np.nextafter(e, np.inf * s) for e in edges for s in (-1, 1)]
        near_edges += [np.nextafter(np.nextafter(e, np.inf * s), np.inf * s) for e in edges for s in (-1, 1)]
        values = np.sort(np.concatenate([edges, near_edges, edges, rng.uniform(centre - 2, centre + 2, 20)]))
        lo, hi = world_planes._run_within(values, centre, reach)
        np.testing.assert_array_equal(values[lo:hi], values[np.abs(values - centre) <= reach])


def test_the_modes_of_many_slabs_at_once_are_each_slabs_own_mode():
    """``_WallSide.offsets`` (every slab's mode in one vectorised pass) gives, slab for slab, the mode of the
    sorted reference side: slabs on points' offsets, empty and reversed ones, a grid of quarter bands with ties and
    duplicates, a far point with a wide tolerance, tiny slabs (fewer than three points: the middle)."""
    rng = np.random.default_rng(13)
    for trial in range(6):
        flat = np.round(rng.uniform(-3, 3, (2500, 2)), 2 if trial % 2 else 6)
        flat = np.vstack([flat, flat[:150], [[300.0, 200.0]]])
        seen_from = flat + rng.normal(0, 1, flat.shape)
        tolerance = np.where(rng.random(len(flat)) < 0.02, 0.5, 0.03) * rng.uniform(0.5, 1.5, len(flat))
        azimuth = rng.uniform(-np.pi, np.pi)
        fast = world_planes._WallSide(flat, seen_from, tolerance, azimuth)
        slow = _ReferenceWallSide(flat, seen_from, tolerance, azimuth)
        centres = np.concatenate([rng.uniform(-4, 4, 30), slow.d[rng.integers(0, len(slow.d), 30)]])
        widths = rng.choice([0.0, 1e-4, 0.03, 0.12, 0.5, -0.05], len(centres))
        lows, highs = centres - widths, centres + widths
        expected = [slow.offset(low, high, 0.04) for low, high in zip(lows, highs)]
        assert fast.offsets(lows, highs, 0.04).tolist() == expected
        # and the offsets the wall fit asks a side for, at once, are those of one slab after the other
        for band, values in ((0.04, slow.d), (1e-4, np.sort(rng.normal(0, 1e-3, 60) + 1e6))):
            starts = rng.integers(0, len(values) - 3, 25)
            stops = np.minimum(starts + rng.integers(3, 400, 25), len(values))
            got = world_planes._modes_of_runs(values, starts, stops, band)
            assert got.tolist() == [_reference_mode(values[a:b], band) for a, b in zip(starts, stops)]


def test_runs_within_reach_at_once_are_what_the_masks_keep_at_the_last_bit():
    """``_runs_within`` on many runs at once: each run's values within reach as the mask keeps them, with values
    a few ulps from both bounds and runs that end inside the reach."""
    rng = np.random.default_rng(17)
    for _ in range(100):
        centre, reach = rng.uniform(-10, 10), rng.uniform(0, 1)
        edges = [centre - reach, centre + reach]
        near_edges = [np.nextafter(e, np.inf * s) for e in edges for s in (-1, 1)]
        near_edges += [np.nextafter(np.nextafter(e, np.inf * s), np.inf * s) for e in edges for s in (-1, 1)]
        values = np.sort(np.concatenate([edges, near_edges, edges, rng.uniform(centre - 2, centre + 2, 20)]))
        starts = np.array([0, 0, 3, len(values) // 2, 5])
        stops = np.array([len(values), len(values) // 2, len(values) - 3, len(values), 6])
        lo, hi = world_planes._runs_within(values, starts, stops, np.full(5, centre), reach)
        for a, b, low, high in zip(starts, stops, lo, hi):
            run = values[a:b]
            np.testing.assert_array_equal(values[low:high], run[np.abs(run - centre) <= reach])


def _reference_sweep_walls(planes_, points, tolerance, up, observers, options):
    """``_sweep_walls`` as first written: every candidate judged by passes over all the side's points."""
    up = up / np.linalg.norm(up)
    upright = [p for p in planes_ if abs(p.normal @ up) < 1e-9]
    azimuth = world_planes.dominant_wall_azimuth(np.array([p.normal for p in upright]).reshape(-1, 3),
                                                 np.array([p.support for p in upright], np.float64), up)
    if azimuth is None:
        return []
    e1, e2 = world_planes._horizontal_basis(up)
    band = float(np.median(tolerance))
    found, kept = [], []
    for quarter in range(4):
        a = azimuth + quarter * np.pi / 2
        normal = np.cos(a) * e1 + np.sin(a) * e2
        offsets = points @ normal
        front = observers @ normal > offsets
        values = offsets[front]
        need = world_planes.SWEEP_SUPPORT_FACTOR * options.min_support
        if len(values) < need:
            continue
        taken = [(p.offset if p.normal @ normal > 0 else -p.offset) for p in planes_ + found
                 if abs(p.normal @ normal) > 0.999 and (p.front == 0 or p.front * np.sign(p.normal @ normal) > 0)]
        edges = np.arange(values.min(), values.max() + 2 * band, band)
        counts = np.histogram(values, edges)[0]
        pairs = counts[:-1] + counts[1:]
        for i in np.argsort(-pairs, kind="stable"):
            if pairs[i] < need:
                break
            offset = float(edges[i + 1])
            if any(abs(offset - o) < 2 * band for o in taken):
                continue
            with np.errstate(invalid="ignore"):
                for shrink in world_planes.SNAP_SHRINK:
                    near = np.abs(values - offset) <= shrink * 2 * band
                    offset = float(np.median(values[near])) if near.any() else float("nan")
            inliers = front & (np.abs(offsets - offset) <= tolerance)
            if inliers.sum() < need:
                continue
            taken.append(offset)
            found.append(replace(planes_[0], normal=normal, offset=offset, front=1, level=False))
            kept.append((offset, np.flatnonzero(inliers)))
    return kept


def test_swept_walls_read_off_sorted_offsets_are_those_of_passes_over_all_points(monkeypatch):
    """The sweep's walls (offset, support, extent from the same points in the same order) equal the straightforward
    version's, on a yawed box room with walls RANSAC was not given, points on a coarse grid (ties), duplicates and
    far points with wide tolerances."""
    for seed, yaw in ((0, 20.0), (1, 0.0), (2, -35.0)):
        points, ranges, observers, rot = _yawed_room_points(yaw, seed)
        rng = np.random.default_rng(seed)
        if seed == 1:
            points = np.round(points, 2)
        points = np.vstack([points, points[:300], rng.uniform(-30, 30, (20, 3))])
        observers = np.zeros_like(points)
        tolerance = 0.015 * np.linalg.norm(points, axis=1)
        options = world_planes.WorldPlaneOptions(distance=0.015, cell=CELL, min_support=60, max_planes=8)
        floor = world_planes.WorldPlane(normal=UP.astype(float), offset=1.2, origin=np.zeros(3),
                                        axes=np.eye(3)[[0, 2]], cell=CELL, extent=np.ones((2, 2), bool), support=1,
                                        level=True)
        walls = [replace(floor, normal=rot[:, 0].copy(), offset=4.0, level=False, front=-1)]
        seen = []
        monkeypatch.setattr(world_planes, "_extent", lambda support, *a, **k: (seen.append(support.copy()),
                                                                              (np.zeros(3), np.eye(3)[:2],
                                                                               np.ones((1, 1), bool), None))[1])
        found = world_planes._sweep_walls([floor] + walls, points, tolerance, UP.astype(float), observers, options)
        expected = _reference_sweep_walls([floor] + walls, points, tolerance, UP.astype(float), observers, options)
        assert len(found) == len(expected) >= 2
        for plane, support, (offset, rows) in zip(found, seen, expected):
            assert plane.offset == offset and plane.support == len(rows)
            np.testing.assert_array_equal(support, points[rows])
