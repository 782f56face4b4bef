"""Stereo on the ground by a sweep of ground-parallel planes (sfm/dense/ground_sweep.py).

Two panoramas a baseline of two camera heights apart over a ground tilted 6° (a street's slope, or gravity known to a
few degrees), with a fine random texture fixed to the ground; nothing else (the sky above). Rectified SGBM fails on
it (the near ground lies beyond its disparity cap, and the foreshortened ground differs between the panoramas); the
sweep recovers it to a fraction of a percent.
"""

import numpy as np
import pytest

from fullview.sfm import dense
from fullview.sfm.camera import pixel_grid_bearings, pixel_latitude
from fullview.sfm.dense import ground_sweep

WIDTH = 512
UP = np.array([0.0, -1.0, 0.0])  # y down, as the pipeline's cameras
HEIGHT = 1.0  # the first camera's height above the ground
CENTERS = [np.zeros(3), np.array([2.0, 0.0, 0.3])]
TILT = np.radians(6.0)


def _ground() -> tuple[np.ndarray, float]:
    """The tilted ground plane n·X = d (n pointing down, into the ground)."""
    normal = np.array([-np.sin(TILT), np.cos(TILT), 0.3 * np.sin(TILT)])
    normal /= np.linalg.norm(normal)
    return normal, HEIGHT * normal[1]


def _value_noise(x: np.ndarray, z: np.ndarray, cell: float) -> np.ndarray:
    """Bilinear value noise in [-1, 1] fixed to the ground's x, z (a hash per lattice corner)."""
    u, v = x / cell, z / cell
    i, j = np.floor(u), np.floor(v)
    fu, fv = u - i, v - j

    def corner(a, b):
        return ((a.astype(np.int64) * 73856093 ^ b.astype(np.int64) * 19349663) % 1000) / 500.0 - 1.0

    return (corner(i, j) * (1 - fu) * (1 - fv) + corner(i + 1, j) * fu * (1 - fv)
            + corner(i, j + 1) * (1 - fu) * fv + corner(i + 1, j + 1) * fu * fv)


def _render(center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(true range, NaN above the ground's horizon; BGR image) of an identity-oriented panorama at ``center``."""
    b = pixel_grid_bearings(WIDTH, WIDTH // 2)
    normal, offset = _ground()
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offset - normal @ center) / (b @ normal)
    t = np.where(t > 0, t, np.nan)
    p = center + b * np.nan_to_num(t)[..., None]
    grey = 128 + 50 * _value_noise(p[..., 0], p[..., 2], 0.06) + 40 * _value_noise(p[..., 0], p[..., 2], 0.2)
    grey = np.where(np.isfinite(t), grey, 230.0)
    return t.astype(np.float32), np.repeat(grey[..., None], 3, axis=2).clip(0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def scene():
    return [_render(c) for c in CENTERS]


def _band(shape) -> np.ndarray:
    lat = np.degrees(pixel_latitude(np.arange(shape[0]) + 0.5, shape[0]))
    return np.broadcast_to(((lat > -65) & (lat < 0))[:, None], shape)


def _recovered(estimate: np.ndarray, truth: np.ndarray, tolerance: float = 0.01) -> float:
    """Share of the ground band (latitudes −65° to 0°, where the ground is) estimated within ``tolerance``."""
    band = _band(truth.shape) & np.isfinite(truth)
    with np.errstate(invalid="ignore"):
        good = np.abs(estimate - truth) <= tolerance * truth
    return float(good[band].mean())


def _sweep(scene, **kw):
    (_, image_i), (_, image_j) = scene
    options = ground_sweep.GroundSweepOptions(min_latitude_deg=-65.0, **kw)
    return ground_sweep.ground_sweep_pair(image_i, image_j, np.eye(3), -CENTERS[0], np.eye(3), -CENTERS[1], UP,
                                          np.nan, np.nan, options)


def test_the_sweep_recovers_a_slanted_ground(scene):
    ranges = _sweep(scene)
    for estimate, (truth, _) in zip(ranges, scene):
        band = _band(truth.shape) & np.isfinite(estimate)
        error = np.nan_to_num(np.abs(estimate - truth)[band] / truth[band], nan=1.0)  # a range on the sky: wrong
        assert band.sum() > 0.3 * _band(truth.shape).sum()  # a third of the ground band at least (measured 0.5)
        assert np.median(error) < 0.005 and np.mean(error < 0.02) > 0.98
        assert _recovered(estimate, truth) > 0.3


def test_rectified_sgbm_misses_the_slanted_ground(scene):
    """Without the sweep: the pipeline's pair stereo on the same panoramas gets almost none of it right."""
    (truth_i, image_i), (truth_j, image_j) = scene
    ratio = dense.pair_min_depth_ratio(0.5 * HEIGHT, 0.5 * HEIGHT, float(np.linalg.norm(CENTERS[1])), 0.5, 45.0)
    pair = dense.densify_pair(image_i, image_j, np.eye(3), -CENTERS[0], np.eye(3), -CENTERS[1],
                              rect_height=WIDTH // 2, out_width=WIDTH, min_depth_ratio=ratio)
    assert _recovered(pair.range_i, truth_i) < 0.05 and _recovered(pair.range_j, truth_j) < 0.05


def test_the_coarse_sweep_finds_the_camera_height(scene):
    (_, image_i), (_, image_j) = scene
    grey = [ground_sweep._grey(image) for image in (image_i, image_j)]
    options = ground_sweep.GroundSweepOptions(min_latitude_deg=-65.0)
    heights = ground_sweep.swept_ground_heights(*grey, np.eye(3), CENTERS[0], np.eye(3), CENTERS[1], UP, options)
    # the ground is tilted 6°: within the near ground's reach (about 2 heights) its height below a camera spreads
    # by ±0.2; the estimate only centres the fine sweep's span (half to twice it)
    truth = [(_ground()[1] - _ground()[0] @ c) / (_ground()[0] @ -UP) for c in CENTERS]
    assert np.allclose(heights, truth, rtol=0.15)


def test_without_a_unique_peak_nothing_is_kept(scene):
    """A textureless ground (all grey) gets no range: the windows have no texture and no peak."""
    flat = [(truth, np.full_like(image, 128)) for truth, image in scene]
    assert all(not np.isfinite(r).any() for r in _sweep(flat))


def _room_points(rng) -> np.ndarray:
    """Sparse points of a 6 x 4 room, 2.5 high, cameras at height 1.5: floor, walls, a ceiling (lamps, edges)."""
    floor = np.column_stack([rng.uniform(-3, 3, 400), np.full(400, 1.5), rng.uniform(-2, 2, 400)])
    ceiling = np.column_stack([rng.uniform(-3, 3, 60), np.full(60, -1.0), rng.uniform(-2, 2, 60)])
    wall = np.column_stack([np.full(200, 3.0), rng.uniform(-1.0, 1.5, 200), rng.uniform(-2, 2, 200)])
    return np.vstack([floor, ceiling, wall])


def _street_points(rng) -> np.ndarray:
    """Sparse points of a courtyard: a few on a plain ground, facades and tree tops at many heights overhead."""
    ground = np.column_stack([rng.uniform(-6, 6, 30), np.full(30, 1.0), rng.uniform(-6, 6, 30)])
    trees = np.column_stack([rng.uniform(-4, 4, 200), rng.uniform(-12, -2, 200), rng.uniform(-4, 4, 200)])
    facade = np.column_stack([rng.uniform(-8, 8, 200), rng.uniform(-8, 1, 200), np.full(200, 8.0)])
    return np.vstack([ground, trees, facade])


def test_a_room_has_a_ceiling_a_courtyard_has_not():
    rng = np.random.default_rng(0)
    cameras = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [-1.0, 0.0, -0.5]])
    assert ground_sweep.has_ceiling(cameras, _room_points(rng), UP)
    # a plain floor (no points below) under a ceiling with lamps: still a room, by the ceiling's level band
    room = _room_points(rng)
    assert ground_sweep.has_ceiling(cameras, room[room[:, 1] < 1.4], UP)
    assert not ground_sweep.has_ceiling(cameras, _street_points(rng), UP)


def test_the_stage_sweeps_only_where_no_ceiling_spans_over_the_cameras():
    from fullview.sfm.options import DensifyOptions
    from fullview.stages import densify

    rng = np.random.default_rng(1)
    cameras = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [-1.0, 0.0, -0.5]])
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    room, street = _room_points(rng), _street_points(rng)

    def setup(points, mode):
        return densify._ground_sweep_setup(DensifyOptions(ground_sweep=mode), R, cameras, [0, 1, 2], points)

    assert setup(room, "no_ceiling") is None and setup(street, "no_ceiling") is not None
    assert setup(room, "always") is not None and setup(street, "never") is None
    up, heights, _, _ = setup(room, "always")
    assert np.allclose(up, UP) and np.allclose(list(heights.values()), 1.5)  # the floor 1.5 below every camera
