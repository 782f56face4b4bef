"""Bad input gives a clear error naming the file, key or value, and leaves nothing half-written."""

import shutil

import cv2
import numpy as np
import pytest

from fullview.cli import main
from fullview.io.config import ConfigError, load_config
from fullview.io.dataset import Dataset, DatasetError


def _run_cli(capsys, *args):
    code = main(list(map(str, args)))
    return code, capsys.readouterr().err


def test_missing_dataset_folder(tmp_path, capsys):
    code, err = _run_cli(capsys, "run", tmp_path / "nope", "-w", tmp_path / "ws")
    assert code == 2 and "dataset folder not found" in err and "nope" in err


def test_fewer_than_two_images(dataset_copy):
    for p in sorted((dataset_copy / "images").iterdir())[1:]:
        p.unlink()
    with pytest.raises(DatasetError, match="at least two images, found 1"):
        Dataset(dataset_copy)


def test_unreadable_image(dataset_copy, make_pipeline, tmp_path):
    bad = sorted((dataset_copy / "images").iterdir())[0]
    bad.write_bytes(b"not an image at all")
    with pytest.raises(DatasetError, match=f"cannot read image .*{bad.name}"):
        make_pipeline(dataset_copy).run(until="features")
    assert not (tmp_path / "ws" / "tiny" / "features").exists()
    assert not list((tmp_path / "ws" / "tiny").glob(".features.*"))


def test_image_not_two_to_one(dataset_copy, make_pipeline):
    path = sorted((dataset_copy / "images").iterdir())[0]
    cv2.imwrite(str(path), np.zeros((256, 300, 3), np.uint8))
    with pytest.raises(DatasetError, match=f"{path.name} is 300x256"):
        make_pipeline(dataset_copy).run(until="features")


def test_hand_point_unknown_image(dataset_copy):
    (dataset_copy / "hand_points.yaml").write_text(
        "points:\n  - name: corner\n    observations: {pano_000.png: [10, 20], ghost.jpg: [1, 2]}\n")
    with pytest.raises(DatasetError, match="'corner' names unknown image 'ghost.jpg'"):
        Dataset(dataset_copy).hand_tracks()


def test_hand_point_outside_image(dataset_copy):
    (dataset_copy / "hand_points.yaml").write_text(
        "points:\n  - observations: {pano_000.png: [600, 20], pano_001.png: [1, 2]}\n")
    with pytest.raises(DatasetError, match=r"\(600.0, 20.0\) lies outside pano_000.png \(512x256\)"):
        Dataset(dataset_copy).hand_tracks()


def test_hand_point_malformed(dataset_copy):
    (dataset_copy / "hand_points.yaml").write_text("points:\n  - observations: {pano_000.png: [1]}\n")
    with pytest.raises(DatasetError, match=r"expected \[x, y\]"):
        Dataset(dataset_copy).hand_tracks()


def test_config_unknown_key(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text("filter:\n  treshold_deg: 0.3\n")
    with pytest.raises(ConfigError, match=r"pipeline.yaml: unknown key filter.treshold_deg"):
        load_config(path)


def test_config_unknown_section(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text("matcher:\n  ratio: 0.7\n")
    with pytest.raises(ConfigError, match="unknown section 'matcher'"):
        load_config(path)


def test_config_wrong_type(tmp_path):
    path = tmp_path / "pipeline.yaml"
    path.write_text("matches:\n  ratio: high\n")
    with pytest.raises(ConfigError, match=r"matches.ratio must be float, got 'high'"):
        load_config(path)


def test_set_override_wrong_type_via_cli(tiny_dataset, tmp_path, capsys):
    code, err = _run_cli(capsys, "run", tiny_dataset, "-w", tmp_path / "ws", "--set", "features.working_width=wide")
    assert code == 2 and "features.working_width must be int" in err


def test_int_accepted_for_float():
    assert load_config(None, ["filter.threshold_deg=1"])["filter"].threshold_deg == 1.0


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "absent.yaml")


@pytest.mark.parametrize("item,message", [
    ("matches.pairs=seq", "matches.pairs must be one of"),
    ("registration.model=Planar", "registration.model must be one of"),
    ("densify.ground_sweep=off", r"densify.ground_sweep must be one of \['never', 'no_ceiling', 'always'\], got 'off'"),  # YAML 1.2: a string
    ("features.working_width=-5", r"features.working_width must be >= 128 or 0 \(native width\)"),
    ("matches.window=0", r"matches.window must be >= 1"),
    ("filter.min_hand_points=5", r"filter.min_hand_points must be >= 8"),
])
def test_config_values_are_checked(item, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [item])


def test_images_sharing_a_stem(dataset_copy):
    src = sorted((dataset_copy / "images").iterdir())[0]
    shutil.copy(src, src.with_suffix(".jpg"))
    with pytest.raises(DatasetError, match="share a file stem"):
        Dataset(dataset_copy)


@pytest.mark.parametrize("text,message", [
    ("cameras: [\n", "not valid YAML"),
    ("", "top-level 'cameras:' list"),
    ("cameras: 5\n", "top-level 'cameras:' list"),
    ("cameras:\n  - {image: ghost.png, R_world_from_cam: [[1,0,0],[0,1,0],[0,0,1]], center: [0,0,0]}\n",
     "unknown image 'ghost.png'"),
    ("cameras:\n  - {image: pano_000.png, R_world_from_cam: [[2,0,0],[0,1,0],[0,0,1]], center: [0,0,0]}\n",
     "not a rotation matrix"),
    ("cameras:\n  - {image: pano_000.png, center: [0,0,0]}\n", r"cameras\[0\] is invalid"),
])
def test_bad_ground_truth_poses(dataset_copy, text, message):
    (dataset_copy / "ground_truth" / "poses.yaml").write_text(text)
    with pytest.raises(DatasetError, match=message):
        Dataset(dataset_copy).ground_truth_poses()


def test_corrupt_artifact_is_a_clear_error(tiny_dataset, tmp_path, capsys, tiny_set_args):
    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features", *tiny_set_args]) == 0
    path = ws / "tiny" / "features" / "pano_001.npz"
    path.write_bytes(path.read_bytes()[:100])
    capsys.readouterr()
    code, err = _run_cli(capsys, "run", tiny_dataset, "-w", ws, "--only", "matches", *tiny_set_args)
    assert code == 2 and "upstream stage features is stale" in err and "pano_001.npz" in err
    # a normal run rebuilds the damaged stage before anything consumes it
    code, err = _run_cli(capsys, "run", tiny_dataset, "-w", ws, "--until", "matches", *tiny_set_args)
    assert code == 0, err
