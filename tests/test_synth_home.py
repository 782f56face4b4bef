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
from fullview.sfm.camera import pixel_grid_bearings
from fullview.synth import home as synth_home

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


def _layout(seed: int, views: int, rooms: int, closed_door: int | None = None) -> synth_home.HomeLayout:
    return synth_home.layout_home(np.random.default_rng(seed), views, rooms, closed_door)


def _sees(a: np.ndarray, b: np.ndarray, boxes: np.ndarray) -> bool:
    rel = b - a
    dist = float(np.linalg.norm(rel))
    t, _ = synth.cast_rays(a, (rel / dist)[None], boxes)
    return bool(t[0] >= dist - 1e-4)


def _inside(p: np.ndarray, box: np.ndarray) -> bool:
    return bool(np.all(p >= box[0]) and np.all(p <= box[1]))


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


@pytest.mark.parametrize("seed", range(4))
def test_closed_door_splits_the_home(seed):
    rooms, views, closed = 4, 7, 1
    lay = _layout(seed, views, rooms, closed)
    assert len(lay.plain_boxes) == 1 + 3 * 2 + 1  # shell, 2 open doorways of 3 slabs, 1 full slab (closed)
    left = lay.centers[lay.room_of_view <= closed]
    right = lay.centers[lay.room_of_view > closed]
    assert len(left) and len(right)
    for a, b in itertools.product(left, right):
        assert not _sees(a, b, lay.boxes)
    opened = _layout(seed, views, rooms)
    for k in range(views - 1):
        assert _sees(opened.centers[k], opened.centers[k + 1], opened.boxes)
    crossings = np.flatnonzero(np.diff(opened.room_of_view))
    assert len(crossings) == rooms - 1


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
    assert len(scene.views) == 4 and np.all((steps >= 1.0) & (steps <= 2.0))


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
    assert not (tmp_path / "bad").exists()
