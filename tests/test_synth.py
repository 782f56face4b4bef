"""Tests of the synthetic equirectangular scene renderer (fullview.synth)."""

from __future__ import annotations

import itertools
import time

import cv2
import numpy as np
import pytest

from fullview import synth
from fullview.sfm.camera import bearings_to_pixels, pixel_grid_bearings

WIDTH = 512


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.render_scene(views=3, width=WIDTH, seed=3, hand_point_noise_px=1.0)


@pytest.fixture(scope="module")
def exact_scene() -> synth.SynthScene:
    return synth.render_scene(views=3, width=256, seed=5, hand_point_noise_px=0.0)


def _surface_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest face of any box (room faces from inside)."""
    best = np.full(len(points), np.inf)
    for box in boxes:
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            inside = np.all((points[:, others] >= box[0, others] - 1e-6) & (points[:, others] <= box[1, others] + 1e-6), 1)
            for plane in box[:, axis]:
                best = np.where(inside, np.minimum(best, np.abs(points[:, axis] - plane)), best)
    return best


def test_shapes_and_types(scene):
    assert len(scene.views) == 3
    assert [v.name for v in scene.views] == ["pano_000.png", "pano_001.png", "pano_002.png"]
    for v in scene.views:
        assert v.image.shape == (WIDTH // 2, WIDTH, 3) and v.image.dtype == np.uint8
        assert v.depth.shape == (WIDTH // 2, WIDTH) and v.depth.dtype == np.float32
        assert np.all(np.isfinite(v.depth)) and v.depth.min() > 0.3
    assert scene.boxes.shape[1:] == (2, 3) and 4 <= len(scene.boxes) <= 7
    room = scene.boxes[0]
    assert scene.scene_size == pytest.approx(np.linalg.norm(room[1] - room[0]))
    assert 7 <= room[1, 0] - room[0, 0] <= 9 and 2.5 <= room[1, 1] - room[0, 1] <= 3.2


def test_small_scene_is_fast():
    t0 = time.perf_counter()
    synth.render_scene(views=3, width=256, seed=11)
    assert time.perf_counter() - t0 < 5.0  # generous: shared CI machines are noisy


def test_poses_are_proper_rotations_and_cameras_well_placed(scene):
    room = scene.boxes[0]
    centers = np.array([v.center for v in scene.views])
    for v in scene.views:
        R = v.R_world_from_cam
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        tilt = np.degrees(np.arccos(np.clip(R[1, 1], -1, 1)))  # camera y vs world y (both down)
        assert tilt <= synth.MAX_TILT_DEG * np.sqrt(2) + 1e-9
        c = v.center
        assert abs(c[1]) <= synth.EYE_HEIGHT_JITTER + 1e-9
        assert min(c[0] - room[0, 0], room[1, 0] - c[0], c[2] - room[0, 2], room[1, 2] - c[2]) >= synth.CLEARANCE
        for box in scene.boxes[1:]:
            dx = max(box[0, 0] - c[0], c[0] - box[1, 0], 0)
            dz = max(box[0, 2] - c[2], c[2] - box[1, 2], 0)
            assert np.hypot(dx, dz) >= synth.CLEARANCE
    gaps = [np.linalg.norm(a - b) for a, b in itertools.combinations(centers, 2)]
    assert min(gaps) >= synth.MIN_CAMERA_SEPARATION
    steps = np.linalg.norm(np.diff(centers, axis=0), axis=1)
    assert np.all(steps <= 2.5)


def test_depth_follows_pixel_centre_bearings(scene):
    """pixel_grid_bearings * depth lands exactly on a scene surface."""
    v = scene.views[0]
    h, w = v.depth.shape
    b = pixel_grid_bearings(w, h)
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, h, 2000), rng.integers(0, w, 2000)
    X = v.center + (b[i, j] @ v.R_world_from_cam.T) * v.depth[i, j, None].astype(np.float64)
    assert np.max(_surface_distance(X, scene.boxes)) < 2e-5 * scene.scene_size


def test_depth_consistency_between_views(scene):
    a, b = scene.views[0], scene.views[1]
    h, w = a.depth.shape
    bear = pixel_grid_bearings(w, h).reshape(-1, 3)
    X = a.center + (bear @ a.R_world_from_cam.T) * a.depth.reshape(-1, 1).astype(np.float64)
    rel = X - b.center
    rng_b = np.linalg.norm(rel, axis=1)
    pix = bearings_to_pixels(rel @ b.R_world_from_cam, w, h)
    ib = np.clip(pix[:, 1].astype(int), 0, h - 1)
    jb = np.clip(pix[:, 0].astype(int), 0, w - 1)
    # the pixel in B whose centre bearing is closest: compare its depth with the range of X (bearing
    # mismatch up to half a pixel, so the tolerance covers oblique surfaces)
    depth_b = b.depth[ib, jb].astype(np.float64)
    tol = 0.01 + rng_b * 0.03
    visible = np.abs(depth_b - rng_b) < tol
    occluded = depth_b < rng_b - tol
    impossible = depth_b > rng_b + tol  # B sees through the surface point X
    assert visible.mean() > 0.75
    assert impossible.mean() < 0.01
    assert occluded.mean() + visible.mean() + impossible.mean() == pytest.approx(1.0)
    # the exact ray from B towards the surface point X stops at X or at an occluder before it, and
    # exact visibility agrees with the depth-map test except at a few silhouette pixels
    t, _ = synth.cast_rays(b.center, rel / rng_b[:, None], scene.boxes)
    assert np.all(t <= rng_b + 1e-4 * scene.scene_size)
    exact_visible = t >= rng_b - 1e-4 * scene.scene_size
    assert np.mean(exact_visible == visible) > 0.98


def test_hand_points_reproject_within_noise(scene, exact_scene):
    for sc, noise in ((scene, 1.0), (exact_scene, 0.0)):
        assert len(sc.hand_points) == len(sc.hand_point_xyz) >= 8
        names = [p["name"] for p in sc.hand_points]
        assert len(set(names)) == len(names)
        views = {v.name: v for v in sc.views}
        errors = []
        for track, X in zip(sc.hand_points, sc.hand_point_xyz):
            assert set(track) == {"name", "observations"}
            assert len(track["observations"]) >= 2
            assert _surface_distance(X[None], sc.boxes)[0] < 1e-9
            for name, (x, y) in track["observations"].items():
                v = views[name]
                h, w = v.depth.shape
                proj = bearings_to_pixels(((X - v.center) @ v.R_world_from_cam)[None], w, h)[0]
                dx = (x - proj[0] + w / 2) % w - w / 2
                errors.append(np.hypot(dx, y - proj[1]))
                # visible: the true point is not behind the rendered surface
                rng_ = np.linalg.norm(X - v.center)
                assert v.depth[int(proj[1]), int(proj[0]) % w] > rng_ - 0.1 * rng_
        errors = np.array(errors)
        if noise == 0:
            assert errors.max() < 1e-6
        else:
            assert 0.5 * noise < np.sqrt(np.mean(errors ** 2)) < 2.0 * noise and errors.max() < 6 * noise


def test_hand_points_cover_every_pair(scene):
    for a, b in itertools.combinations([v.name for v in scene.views], 2):
        shared = sum(a in p["observations"] and b in p["observations"] for p in scene.hand_points)
        assert shared >= 8, (a, b, shared)


def test_occluded_corner_is_not_observed(scene):
    """A point hidden behind a box in one view must not be reported there."""
    v = scene.views[0]
    centre = scene.boxes[1].mean(axis=0)
    dist = np.linalg.norm(centre - v.center)
    direction = (centre - v.center) / dist
    t, _ = synth.cast_rays(v.center, direction[None], scene.boxes)
    behind = v.center + direction * (dist + 1.0)  # straight behind the box centre
    _, vis = synth.visible_observations(np.array([behind, v.center + direction * t[0]]), [v])
    assert t[0] < dist  # the box is hit first
    assert not vis[0, 0]
    assert vis[1, 0] or not (0.05 < bearings_to_pixels(((centre - v.center) @ v.R_world_from_cam)[None],
                                                        512, 256)[0, 1] / 256 < 0.95)


def test_images_are_textured_and_views_differ(scene):
    for v in scene.views:
        grey = cv2.cvtColor(v.image, cv2.COLOR_BGR2GRAY)
        assert grey.std() > 25
        assert np.abs(cv2.Laplacian(grey, cv2.CV_32F)).mean() > 8  # fine detail everywhere
        assert len(cv2.SIFT_create().detect(grey, None)) > 800
    assert np.mean(scene.views[0].image != scene.views[1].image) > 0.5


def test_determinism_and_seed_dependence(exact_scene):
    again = synth.render_scene(views=3, width=256, seed=5, hand_point_noise_px=0.0)
    for v, u in zip(exact_scene.views, again.views):
        assert np.array_equal(v.image, u.image) and np.array_equal(v.depth, u.depth)
        assert np.array_equal(v.R_world_from_cam, u.R_world_from_cam) and np.array_equal(v.center, u.center)
    assert again.hand_points == exact_scene.hand_points
    assert np.array_equal(again.boxes, exact_scene.boxes)
    other = synth.render_scene(views=3, width=256, seed=6, hand_point_noise_px=0.0)
    assert not np.array_equal(other.boxes, exact_scene.boxes)
    assert not np.array_equal(other.views[0].image, exact_scene.views[0].image)
    assert not np.allclose(other.views[0].center, exact_scene.views[0].center)


def test_prefix_stability_in_views(exact_scene):
    """Camera k and the room do not depend on how many views are rendered."""
    two = synth.render_scene(views=2, width=256, seed=5, hand_point_noise_px=0.0)
    assert np.array_equal(two.boxes, exact_scene.boxes)
    for v, u in zip(two.views, exact_scene.views):
        assert np.array_equal(v.image, u.image) and np.array_equal(v.center, u.center)


def test_sample_surface_points(scene):
    spacing = 0.1
    pts = synth.sample_surface_points(scene, spacing=spacing, seed=0)
    assert pts.ndim == 2 and pts.shape[1] == 3
    assert np.max(_surface_distance(pts, scene.boxes)) < 1e-9
    room = scene.boxes[0]
    size = room[1] - room[0]
    room_area = 2 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    assert 0.7 * room_area / spacing ** 2 < len(pts) < 1.6 * room_area / spacing ** 2
    for box in scene.boxes[1:]:  # nothing strictly inside furniture (e.g. floor under a table)
        assert not np.any(np.all((pts > box[0] + 1e-6) & (pts < box[1] - 1e-6), axis=1))
        below = np.all((pts[:, [0, 2]] > box[0, [0, 2]] + 0.01) & (pts[:, [0, 2]] < box[1, [0, 2]] - 0.01), axis=1)
        assert not np.any(below & (pts[:, 1] > synth.FLOOR_Y - 1e-9))  # floor covered by the box
    # roughly uniform: points per 1 m^2 patch of the ceiling
    ceiling = pts[np.abs(pts[:, 1] - room[0, 1]) < 1e-9]
    counts, _, _ = np.histogram2d(ceiling[:, 0], ceiling[:, 2], bins=[np.arange(room[0, 0], room[1, 0] - 1, 1.0),
                                                                      np.arange(room[0, 2], room[1, 2] - 1, 1.0)])
    assert counts.min() > 0.6 / spacing ** 2 and counts.max() < 1.4 / spacing ** 2
    np.testing.assert_array_equal(pts, synth.sample_surface_points(scene, spacing=spacing, seed=0))
    seen = synth.sample_surface_points(scene, spacing=spacing, seed=0, min_views=1)
    assert 0.3 * len(pts) < len(seen) < len(pts)


def test_bad_arguments():
    with pytest.raises(ValueError, match="width"):
        synth.render_scene(views=2, width=255)
    with pytest.raises(ValueError, match="seed"):
        synth.render_scene(views=2, width=256, seed=-1)
    with pytest.raises(ValueError, match="views"):
        synth.render_scene(views=0, width=256)
