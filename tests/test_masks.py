"""Per-image masks (masks/<image name>.png, white = keep) and the nadir/zenith caps: applied to features and densify,
part of the fingerprint, validated before any stage."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fullview.cli import main
from fullview.io.dataset import Dataset, DatasetError
from fullview.sfm.dense import apply_mask, mask_below_latitude

DENSE = ["--set", "densify.working_width=512", "--set", "densify.rect_height=256", "--set",
         "densify.min_pair_inliers=30"]


def _mask_left_half(dataset_dir, name: str) -> np.ndarray:
    w, h = Dataset(dataset_dir).image_sizes[name]
    keep = np.full((h, w), 255, np.uint8)
    keep[:, : w // 2] = 0
    (dataset_dir / "masks").mkdir(exist_ok=True)
    cv2.imwrite(str(dataset_dir / "masks" / f"{name}.png"), keep)
    return keep > 127


def test_a_mask_of_the_wrong_size_is_refused_before_any_stage(dataset_copy, tmp_path, capsys):
    name = Dataset(dataset_copy).image_names[0]
    (dataset_copy / "masks").mkdir()
    cv2.imwrite(str(dataset_copy / "masks" / f"{name}.png"), np.zeros((10, 20), np.uint8))
    assert main(["run", str(dataset_copy), "-w", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err
    assert f"{name}.png: mask is 20x10" in err and err.count("fullview: error") == 1
    assert not (tmp_path / "ws" / "tiny" / "features").exists()


def test_a_mask_of_no_image_is_refused(dataset_copy):
    (dataset_copy / "masks").mkdir()
    cv2.imwrite(str(dataset_copy / "masks" / "ghost.jpg.png"), np.zeros((10, 20), np.uint8))
    with pytest.raises(DatasetError, match="ghost.jpg.png names no image"):
        Dataset(dataset_copy).check_masks()


def test_features_keep_only_unmasked_pixels_and_a_mask_change_reruns(dataset_copy, tmp_path, tiny_set_args,
                                                                     make_pipeline):
    ws = tmp_path / "ws"
    assert main(["run", str(dataset_copy), "-w", str(ws), "--until", "matches", *tiny_set_args]) == 0
    name = Dataset(dataset_copy).image_names[0]
    before = np.load(ws / "tiny" / "features" / f"{name.rsplit('.', 1)[0]}.npz")["pixels"]
    keep = _mask_left_half(dataset_copy, name)
    assert make_pipeline(dataset_copy, workspace=ws).status("features").state == "stale"
    assert main(["run", str(dataset_copy), "-w", str(ws), "--until", "matches", *tiny_set_args]) == 0
    after = np.load(ws / "tiny" / "features" / f"{name.rsplit('.', 1)[0]}.npz")["pixels"]
    rows, cols = np.floor(after[:, 1]).astype(int), np.floor(after[:, 0]).astype(int)
    assert keep[rows, cols].all()
    # exactly the unmasked ones of the unmasked run survive
    assert len(after) == int(keep[np.floor(before[:, 1]).astype(int), np.floor(before[:, 0]).astype(int)].sum())


def test_densify_leaves_masked_pixels_without_depth(dataset_copy, tmp_path, tiny_set_args):
    name = Dataset(dataset_copy).image_names[1]
    keep = _mask_left_half(dataset_copy, name)
    ws = tmp_path / "ws"
    assert main(["run", str(dataset_copy), "-w", str(ws), *tiny_set_args, *DENSE]) == 0
    depth = np.load(ws / "tiny" / "densify" / "depth" / f"{name.rsplit('.', 1)[0]}.npz")
    valid = depth["valid"]
    small = cv2.resize(keep.astype(np.float32), valid.shape[::-1], interpolation=cv2.INTER_AREA) >= 1.0 - 1e-6
    assert not valid[~small].any() and np.isnan(depth["range"][~small]).all()
    assert valid[small].mean() > 0.3  # the kept half still has depth


def test_zenith_and_nadir_caps_of_range_maps():
    rng = np.ones((90, 180), np.float32)
    out, valid = mask_below_latitude(rng, np.ones_like(rng, bool), -45.0, 60.0)
    lat = 90.0 - (np.arange(90) + 0.5) * 2.0
    assert not valid[lat > 60].any() and not valid[lat < -45].any() and valid[(lat > -45) & (lat < 60)].all()
    keep = np.ones((900, 1800), bool)
    keep[:, :10] = False  # a sliver narrower than one map pixel still removes the map pixels it touches
    _, masked = apply_mask(rng, np.ones_like(rng, bool), keep)
    assert not masked[:, 0].any() and masked[:, 1:].all()
