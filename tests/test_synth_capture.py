"""Tests of the real-capture traits of the synthetic scenes (fullview.synth.capture, `fullview synth --tilt-deg ...`)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from fullview import synth
from fullview.cli import main
from fullview.sfm.camera import pixel_grid_bearings
from fullview.synth.capture import CaptureTraits

WIDTH = 256
HOME = dict(views=5, width=WIDTH, seed=2, kind="home", rooms=3)


@pytest.fixture(scope="module")
def clean() -> synth.SynthScene:
    return synth.render_scene(**HOME)


def test_traits_off_leave_the_render_bit_identical(clean):
    off = synth.render_scene(**HOME, capture=CaptureTraits())
    for a, b in zip(clean.views, off.views):
        assert a.name == b.name and np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)
        assert np.array_equal(a.R_world_from_cam, b.R_world_from_cam)


def test_tilt_is_within_the_bound_and_the_ground_truth_is_the_tilted_pose(clean):
    tilt = 2.0
    scene = synth.render_scene(**HOME, capture=CaptureTraits(tilt_deg=tilt))
    up = np.array([0.0, -1.0, 0.0])  # world y points down
    angles = []
    for a, b in zip(clean.views, scene.views):
        assert np.allclose(a.center, b.center)
        # the tilt is a rotation about a horizontal axis applied to the level pose
        R_tilt = b.R_world_from_cam @ a.R_world_from_cam.T
        assert np.allclose(R_tilt @ R_tilt.T, np.eye(3), atol=1e-12)
        axis = np.array([R_tilt[2, 1] - R_tilt[1, 2], R_tilt[0, 2] - R_tilt[2, 0], R_tilt[1, 0] - R_tilt[0, 1]])
        assert abs(axis[1]) < 1e-12
        angles.append(np.degrees(np.arccos(np.clip((R_tilt @ up) @ up, -1, 1))))
        # the depth map is the exact range along the tilted pose's pixel rays
        h, w = b.depth.shape
        dirs = pixel_grid_bearings(w, h).reshape(-1, 3) @ b.R_world_from_cam.T
        t, _ = synth.cast_rays(b.center, dirs, scene.boxes)
        assert np.allclose(t.reshape(h, w), b.depth, rtol=1e-5, atol=1e-5)
    assert 0.0 < min(angles) and max(angles) <= tilt + 1e-9 and max(angles) > tilt / 4


def test_exposure_and_noise_change_the_intensities_only(clean):
    scene = synth.render_scene(**HOME, capture=CaptureTraits(exposure_stops=1.0))
    ratios = []
    for a, b in zip(clean.views, scene.views):
        assert np.array_equal(a.depth, b.depth)
        lit = (a.image > 20) & (a.image < 100)  # far from clipping at up to 2x
        ratios.append(np.median(b.image[lit].astype(float) / a.image[lit]))
    ratios = np.array(ratios)
    assert np.all((ratios >= 0.48) & (ratios <= 2.05)) and np.ptp(np.log2(ratios)) > 0.3
    noisy = synth.render_scene(**HOME, capture=CaptureTraits(noise=3.0))
    diff = np.concatenate([(b.image.astype(float) - a.image).ravel() for a, b in zip(clean.views, noisy.views)])
    assert abs(diff.mean()) < 0.1 and 2.8 < diff.std() < 3.2


def test_shuffle_renames_the_walk_and_keeps_each_pose(clean):
    scene = synth.render_scene(**HOME, capture=CaptureTraits(shuffle=True))
    names = [v.name for v in scene.views]
    assert sorted(names) == [v.name for v in clean.views] and names != sorted(names)
    for a, b in zip(clean.views, scene.views):  # view k of the walk is the same view under another name
        assert np.array_equal(a.image, b.image) and np.array_equal(a.R_world_from_cam, b.R_world_from_cam)


def test_cli_records_the_traits_and_rejects_bad_values(tmp_path, capsys):
    home = ["--scene", "home", "--rooms", "2", "--views", "3", "--width", "128", "--hand-points", "none"]
    assert main(["synth", str(tmp_path / "real"), *home, "--tilt-deg", "1.5", "--exposure-stops", "0.5",
                 "--noise", "2", "--shuffle"]) == 0
    with np.load(tmp_path / "real" / "ground_truth" / "scene.npz") as data:
        assert float(data["tilt_deg"]) == 1.5 and float(data["exposure_stops"]) == 0.5
        assert float(data["noise"]) == 2.0 and bool(data["shuffle"])
    poses = yaml.safe_load((tmp_path / "real" / "ground_truth" / "poses.yaml").read_text())["cameras"]
    assert sorted(p["image"] for p in poses) == [f"pano_{k:03d}.png" for k in range(3)]
    assert main(["synth", str(tmp_path / "clean"), *home]) == 0
    with np.load(tmp_path / "clean" / "ground_truth" / "scene.npz") as data:
        assert "tilt_deg" not in data.files and "shuffle" not in data.files
    capsys.readouterr()
    for bad in (["--tilt-deg", "-1"], ["--exposure-stops", "9"], ["--noise", "100"]):
        assert main(["synth", str(tmp_path / "bad"), *home, *bad]) == 2
        err = capsys.readouterr().err
        assert bad[0] in err and bad[1] in err
    assert not (tmp_path / "bad").exists()
