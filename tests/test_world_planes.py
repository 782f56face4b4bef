"""World planes (sfm/dense/world_planes.py): extents with gravity known, and planes the views disagree with.

The room scenes (plain box, doorway, a plane seen through) are in tests/test_planes.py; these check the properties
the gravity extents and the one-sided planes rely on, on exact synthetic points.
"""

import numpy as np

from fullview.sfm.dense import world_planes

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


def _level(y, support, normal_sign=1.0):
    normal = np.array([0.0, normal_sign, 0.0])
    points = np.stack(np.meshgrid(np.linspace(-2, 2, 21), [y], np.linspace(-2, 2, 21)), -1).reshape(-1, 3)
    origin, axes, extent, _ = world_planes._extent(points, normal, normal_sign * y, CELL, 3, False)
    return world_planes.WorldPlane(normal=normal, offset=normal_sign * y, origin=origin, axes=axes, cell=CELL,
                                   extent=extent, support=support, level=True)


def test_one_level_plane_per_band_keeps_the_best_supported_piece_of_a_ceiling():
    # three pieces of one ceiling 2-4 cm apart (the nearest piece would win every ray), the floor and a table top
    ceiling = [_level(-1.30, 900), _level(-1.27, 300), _level(-1.33, 200)]
    floor, table = _level(1.2, 800, -1.0), _level(0.45, 150, -1.0)
    wall = world_planes.WorldPlane(normal=np.array([0.0, 0.0, 1.0]), offset=3.0, origin=np.zeros(3),
                                   axes=np.eye(3)[:2], cell=CELL, extent=np.ones((2, 2), bool), support=100)
    planes = [ceiling[1], floor, ceiling[0], wall, table, ceiling[2]]
    kept = world_planes._one_level_plane_per_band(planes, band=0.02)
    assert [p.support for p in kept] == [800, 900, 100, 150]  # input order, the 300 and 200 pieces dropped
    # pieces farther apart than the bands are separate surfaces (a shelf under the ceiling)
    assert len(world_planes._one_level_plane_per_band([ceiling[0], _level(-1.0, 300)], band=0.02)) == 2
