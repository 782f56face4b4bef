"""Tests of the multi-room "home" synthetic scene (fullview.synth.home, render_scene(kind="home"))."""

from __future__ import annotations

import hashlib
import itertools

import cv2
import numpy as np
import pytest
import yaml

from fullview import synth
from fullview.cli import main
from fullview.sfm.camera import bearings_to_pixels, pixel_grid_bearings
from fullview.synth import home as synth_home
from fullview.synth.scene import crossing_hand_points

WIDTH = 384
# sha256 of render_scene(views=2, width=256, seed=3) images and depths, computed with the code before the home
# scene existed: the default room scene must stay bit-identical (tests and benchmarks depend on its images).
ROOM_IMAGE_SHA256 = ["b5fda948763453c4761439f6dc8a05a54c86bd11682c7acc9426add2f55cd187",
                     "a77e9cf77dafe1c7af9b830d829e5e07619c44190ced60d0fdb23b5ecc0b9a45"]
ROOM_DEPTH_SHA256 = ["de13794ab3d267ace0f0890540501afd43b5904c49ca4e844678a67a90d42c84",
                     "c3c0ecb3ffca727b805432aaa8d51dfee940866ccd8ca5cd3e01c759cba363a5"]


@pytest.fixture(scope="module")
def home() -> synth.SynthScene:
    return synth.render_scene(views=7, width=WIDTH, seed=1, kind="home", rooms=3)


@pytest.fixture(scope="module")
def closed_home() -> synth.SynthScene:
    """Doorway 1 of 3 closed; exact hand-point pixels (no noise)."""
    return synth.render_scene(views=7, width=512, seed=1, kind="home", rooms=4, closed_door=1, hand_point_noise_px=0.0)


def _layout(seed: int, views: int, rooms: int, closed_door: int | None = None) -> synth_home.HomeLayout:
    return synth_home.layout_home(np.random.default_rng(seed), views, rooms, closed_door)


def _sees(a: np.ndarray, b: np.ndarray, boxes: np.ndarray) -> bool:
    rel = b - a
    dist = float(np.linalg.norm(rel))
    t, _ = synth.cast_rays(a, (rel / dist)[None], boxes)
    return bool(t[0] >= dist - 1e-4)


def _inside(p: np.ndarray, box: np.ndarray) -> bool:
    return bool(np.all(p >= box[0]) and np.all(p <= box[1]))


def _through_window(a: np.ndarray, b: np.ndarray, window: np.ndarray) -> bool:
    """Whether the segment a-b crosses the closed door's plane inside its window."""
    s = (window[:, 0].mean() - a[0]) / (b[0] - a[0])
    p = a + s * (b - a)
    return bool(0 < s < 1 and np.all(p[1:] >= window[0, 1:]) and np.all(p[1:] <= window[1, 1:]))


def test_room_scene_is_unchanged():
    scene = synth.render_scene(views=2, width=256, seed=3)
    assert [hashlib.sha256(v.image.tobytes()).hexdigest() for v in scene.views] == ROOM_IMAGE_SHA256
    assert [hashlib.sha256(v.depth.tobytes()).hexdigest() for v in scene.views] == ROOM_DEPTH_SHA256


def test_views_and_camera_placement(home):
    assert [v.name for v in home.views] == [f"pano_{k:03d}.png" for k in range(7)]
    shell, others = home.boxes[0], home.boxes[1:]
    assert home.scene_size == pytest.approx(np.linalg.norm(shell[1] - shell[0]))
    for v in home.views:
        assert v.image.shape == (WIDTH // 2, WIDTH, 3) and v.depth.shape == (WIDTH // 2, WIDTH)
        assert np.all((v.center > shell[0]) & (v.center < shell[1]))
        assert not any(_inside(v.center, box) for box in others)
        assert shell[1, 1] - v.center[1] == pytest.approx(synth_home.HOME_EYE_HEIGHT, abs=0.1)  # floor at max y
        R = v.R_world_from_cam
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 1], [0.0, 1.0, 0.0], atol=1e-9)  # level: camera y = world down
    steps = np.linalg.norm(np.diff([v.center for v in home.views], axis=0), axis=1)
    assert np.all((steps >= 1.0) & (steps <= 2.0)), steps


def test_layout_has_rooms_doorways_and_plain_walls():
    lay = _layout(1, 7, 3)
    assert len(lay.rooms) == 3 and len(lay.doors) == 2
    for door in lay.doors:
        size = door[1] - door[0]
        assert size[2] == pytest.approx(synth_home.DOOR_WIDTH) and size[1] == pytest.approx(synth_home.DOOR_HEIGHT)
    assert np.bincount(lay.room_of_view).tolist() == synth_home.views_per_room(7, 3) == [3, 2, 2]
    for c, r in zip(lay.centers, lay.room_of_view):
        assert _inside(c, lay.rooms[r])
    furniture = len(lay.boxes) - len(lay.plain_boxes)
    assert furniture >= 2 * 3 and lay.plain_boxes == tuple(range(1 + 3 * 2))  # shell + 3 slabs per doorway


def test_depth_is_exact(home):
    for v in home.views[:2]:
        h, w = v.depth.shape
        rng = np.random.default_rng(0)
        i, j = rng.integers(0, h, 500), rng.integers(0, w, 500)
        dirs = pixel_grid_bearings(w, h)[i, j] @ v.R_world_from_cam.T
        t, _ = synth.cast_rays(v.center, dirs, home.boxes)
        np.testing.assert_allclose(v.depth[i, j], t, rtol=1e-5, atol=1e-5)


def test_hand_points(home):
    assert len(home.hand_points) >= 10
    names = {p["name"] for p in home.hand_points}
    assert any("floor_marker" in n for n in names)
    assert all(len(p["observations"]) >= 2 for p in home.hand_points)


def _sift_count(image: np.ndarray) -> int:
    return len(cv2.SIFT_create().detect(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), None))


def test_walls_are_plain_but_objects_textured(home):
    room = synth.render_scene(views=2, width=WIDTH, seed=3)
    home_counts = [_sift_count(v.image) for v in home.views[:3]]
    room_counts = [_sift_count(v.image) for v in room.views]
    assert np.mean(home_counts) < np.mean(room_counts) / 3, (home_counts, room_counts)
    assert min(home_counts) >= 20, home_counts
    # the plain walls alone: a pixel band looking at the shell wall only has (almost) no keypoints
    lay = synth_home.layout_home(np.random.default_rng(0), 1, 1)
    plain = synth.build_geometry(lay.boxes[:1], texel=0.02, seed=0, plain_boxes=(0,))
    image, _ = synth.render_view(plain, R_world_from_cam=lay.R_world_from_cam[0], center=lay.centers[0], width=WIDTH)
    assert _sift_count(image) < 0.05 * np.mean(room_counts)


@pytest.mark.parametrize("seed", range(6))
def test_closed_door_splits_the_home(seed):
    rooms, views, closed = 4, 7, 1
    lay = _layout(seed, views, rooms, closed)
    # shell, 3 slabs per doorway (the closed one's wall too), and the closed door's leaf: 4 boards around the window
    assert len(lay.plain_boxes) == 1 + 3 * 3 + 4
    door, window = lay.doors[closed], lay.window
    np.testing.assert_allclose(window[1] - window[0], [synth_home.DOOR_LEAF_THICKNESS, synth_home.WINDOW_HEIGHT,
                                                       synth_home.WINDOW_WIDTH])
    assert door[1, 1] - window[1, 1] == pytest.approx(synth_home.WINDOW_SILL)
    leaf = [b for b in lay.boxes[list(lay.plain_boxes)] if b[0, 0] > door[0, 0] and b[1, 0] < door[1, 0]]
    assert len(leaf) == 4 and all(np.all(b[:, 1:] >= door[0, 1:] - 1e-9) and np.all(b[:, 1:] <= door[1, 1:] + 1e-9)
                                  for b in leaf)
    # the leaf fills the doorway but for the window: boards and window tile the opening (y-z) without overlap
    area = lambda b: (b[1, 1] - b[0, 1]) * (b[1, 2] - b[0, 2])  # noqa: E731
    assert sum(area(b) for b in leaf) + area(window) == pytest.approx(area(door))
    for a, b in itertools.combinations([*leaf, window], 2):
        assert np.any(np.minimum(a[1, 1:], b[1, 1:]) - np.maximum(a[0, 1:], b[0, 1:]) <= 1e-9)

    side_a = lay.room_of_view <= closed
    left, right = lay.centers[side_a], lay.centers[~side_a]
    assert len(left) and len(right)
    for a, b in itertools.product(left, right):  # across the closed door, cameras see each other only through it
        assert not _sees(a, b, lay.boxes) or _through_window(a, b, window)
    # the leaf blocks every ray through the doorway but those through the window (the nearest two cameras per side)
    xd = window[:, 0].mean()
    ys = np.linspace(door[0, 1], door[1, 1], 41)[1:-1]
    zs = np.linspace(door[0, 2], door[1, 2], 19)[1:-1]
    grid = np.array([[xd, y, z] for y in ys for z in zs])
    in_window = np.all((grid[:, 1:] > window[0, 1:] + 0.03) & (grid[:, 1:] < window[1, 1:] - 0.03), axis=1)
    on_leaf = np.any((grid[:, 1:] < window[0, 1:] - 0.01) | (grid[:, 1:] > window[1, 1:] + 0.01), axis=1)
    near = np.concatenate([np.flatnonzero(side_a)[-2:], np.flatnonzero(~side_a)[:2]])
    for c in lay.centers[near]:
        rel = grid - c
        dirs = rel / np.linalg.norm(rel, axis=1)[:, None]
        t, _ = synth.cast_rays(c, dirs, lay.boxes)
        crossed = np.sign(c[0] + t * dirs[:, 0] - xd) != np.sign(c[0] - xd)
        assert crossed[in_window].all() and not crossed[on_leaf].any()
    # nobody stands close to the window; 1-2 m steps but across the door
    near_rooms = np.isin(lay.room_of_view, [closed, closed + 1])
    assert np.all(np.abs(lay.centers[near_rooms, 0] - xd) >= synth_home.WINDOW_MIN_DISTANCE)
    steps = np.linalg.norm(np.diff(lay.centers, axis=0), axis=1)[np.diff(side_a.astype(int)) == 0]
    assert np.all((steps >= 1.0) & (steps <= 2.0)), steps
    # the crossing markers: on plain surfaces, each in sight of >= 2 cameras per side (of the far side's through
    # the window)
    cross = [k for k, n in enumerate(lay.marker_names) if n.startswith(f"home_door{closed}_marker")]
    assert len(cross) == synth_home.CROSSING_MARKERS
    for k in cross:
        p = lay.markers[k]
        assert lay.marker_faces[k] // 6 in lay.plain_boxes
        seers = [v for v, c in enumerate(lay.centers) if _sees(c, p, lay.boxes)]
        assert sum(side_a[seers]) >= 2 and sum(~side_a[seers]) >= 2
        for v in seers:
            if side_a[v] != (p[0] < xd):
                assert _through_window(lay.centers[v], p, window)

    opened = _layout(seed, views, rooms)
    assert opened.window is None and not any(n.startswith("home_door") for n in opened.marker_names)
    for k in range(views - 1):
        assert _sees(opened.centers[k], opened.centers[k + 1], opened.boxes)
    crossings = np.flatnonzero(np.diff(opened.room_of_view))
    assert len(crossings) == rooms - 1


def test_closed_door_is_deterministic():
    a, b = _layout(5, 4, 2, 0), _layout(5, 4, 2, 0)
    assert a.marker_names == b.marker_names and a.marker_faces == b.marker_faces
    for key in ("boxes", "window", "markers", "centers", "R_world_from_cam"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))


def test_crossing_hand_points(closed_home, home):
    scene, closed = closed_home, 1
    window = scene.home.window
    names = [v.name for v in scene.views]
    side_a = scene.home.room_of_view <= closed
    row = {p["name"]: k for k, p in enumerate(scene.hand_points)}
    tracks = crossing_hand_points(scene, closed)
    assert len(tracks) == 8 and len({t["name"] for t in tracks}) == 8
    assert crossing_hand_points(scene) == tracks  # the scene's closed door by default
    for t in tracks:
        assert t["name"].startswith(f"home_door{closed}_marker")  # targets first, and there are enough
        views = [names.index(n) for n in t["observations"]]
        assert sum(side_a[views]) >= 2 and sum(~side_a[views]) >= 2
        xyz = scene.hand_point_xyz[row[t["name"]]]
        for v in views:
            view = scene.views[v]
            h, w = view.depth.shape
            true = bearings_to_pixels(((xyz - view.center) @ view.R_world_from_cam)[None], w, h)[0]
            np.testing.assert_allclose(t["observations"][view.name], true, atol=1e-6)
            if side_a[v] != (xyz[0] < window[:, 0].mean()):  # seen from the other side: through the window
                assert _through_window(view.center, xyz, window)
    seen = [len(t["observations"]) for t in tracks]
    assert seen == sorted(seen, reverse=True)
    with pytest.raises(ValueError, match="only .* tracks"):
        crossing_hand_points(scene, count=len(scene.hand_points) + 1)
    for bad in ((home, None), (scene, 0)):
        with pytest.raises(ValueError, match="closed_door"):
            crossing_hand_points(*bad)


def test_views_spread_over_rooms_and_bad_arguments():
    assert synth_home.views_per_room(4, 4) == [1, 1, 1, 1]
    assert synth_home.views_per_room(12, 4) == [3, 3, 3, 3]
    assert synth_home.views_per_room(6, 4) == [2, 2, 1, 1]
    for views, rooms in ((3, 4), (13, 4), (2, 0)):
        with pytest.raises(ValueError, match="rooms"):
            synth.render_scene(views=views, width=64, kind="home", rooms=rooms)
    with pytest.raises(ValueError, match="closed_door"):
        synth.render_scene(views=4, width=64, kind="home", rooms=4, closed_door=3)
    with pytest.raises(ValueError, match="kind"):
        synth.render_scene(views=4, width=64, kind="flat")


def test_one_camera_per_room_and_closed_door_render():
    scene = synth.render_scene(views=4, width=128, seed=2, kind="home", rooms=4, closed_door=2)
    steps = np.linalg.norm(np.diff([v.center for v in scene.views], axis=0), axis=1)
    assert len(scene.views) == 4 and np.all((steps[:2] >= 1.0) & (steps[:2] <= 2.0))  # steps[2] crosses the door


def test_cli(tmp_path, capsys):
    out = tmp_path / "home"
    assert main(["synth", str(out), "--scene", "home", "--rooms", "2", "--views", "3", "--width", "128",
                 "--closed-door", "0"]) == 0
    poses = yaml.safe_load((out / "ground_truth" / "poses.yaml").read_text())["cameras"]
    assert len(poses) == 3 and len(list((out / "ground_truth" / "depth").glob("*.npy"))) == 3
    with np.load(out / "ground_truth" / "scene.npz") as data:
        assert str(data["kind"]) == "home" and int(data["rooms"]) == 2 and int(data["closed_door"]) == 0
    capsys.readouterr()
    for bad in (["--views", "7"], ["--views", "2", "--rooms", "3"], ["--views", "4", "--closed-door", "1"]):
        assert main(["synth", str(tmp_path / "bad"), "--scene", "home", "--rooms", "2", "--width", "128", *bad]) == 2
        assert "synth" in capsys.readouterr().err
    assert main(["synth", str(tmp_path / "bad"), "--closed-door", "0", "--width", "128"]) == 2
    assert main(["synth", str(tmp_path / "bad"), "--scene", "home", "--rooms", "2", "--views", "4", "--width", "128",
                 "--hand-points", "crossing"]) == 2  # no closed door to cross
    assert "closed door" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_cli_hand_points(tmp_path):
    home = ["--scene", "home", "--rooms", "2", "--views", "4", "--width", "256", "--closed-door", "0"]
    assert main(["synth", str(tmp_path / "crossing"), *home, "--hand-points", "crossing"]) == 0
    points = yaml.safe_load((tmp_path / "crossing" / "hand_points.yaml").read_text())["points"]
    assert len(points) == 8 and all(p["name"].startswith("home_door0_marker") for p in points)
    assert main(["synth", str(tmp_path / "none"), *home, "--hand-points", "none"]) == 0
    assert not (tmp_path / "none" / "hand_points.yaml").exists()
    assert main(["synth", str(tmp_path / "all"), *home]) == 0
    every = yaml.safe_load((tmp_path / "all" / "hand_points.yaml").read_text())["points"]
    assert len(every) > len(points) and {p["name"] for p in points} <= {p["name"] for p in every}
