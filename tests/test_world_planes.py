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
