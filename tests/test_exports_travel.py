"""Outputs that travel: a nerfstudio export that holds its images, COLMAP point errors in pixels, a metric scale.

The reconstructions are real runs of the pipeline on rendered scenes: the tiny 3-view scene for the formats, an
8-view room with ground truth (camera heights 1.4-1.8 m: EYE_HEIGHT_JITTER) for the scale.
"""

from __future__ import annotations

import errno
import itertools
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import yaml

from fullview.cli import main
from fullview.io.artifacts import load_ply
from fullview.io.exports import SparseModel, point_errors_px, write_colmap_model
from fullview.sfm.camera import bearings_to_pixels
from fullview.synth import FLOOR_Y, write_synthetic_dataset
from fullview.synth.scene import _box_corners

UNTIL = ["--until", "triangulation"]


@pytest.fixture(scope="module")
def tiny_run(tiny_dataset, tmp_path_factory, tiny_set_args):
    """A private copy of the tiny dataset (the test removes it) reconstructed up to the sparse model."""
    root = tmp_path_factory.mktemp("travel")
    data = root / "data" / "tiny"
    shutil.copytree(tiny_dataset, data)
    ws = root / "ws"
    assert main(["run", str(data), "-w", str(ws), *tiny_set_args, *UNTIL]) == 0
    return data, ws, list(tiny_set_args)


@pytest.fixture(scope="module")
def room(tmp_path_factory, tiny_set_args):
    """An 8-view rendered room with ground truth, reconstructed up to the sparse model."""
    root = tmp_path_factory.mktemp("room")
    data = write_synthetic_dataset(root / "room8", views=8, width=512, seed=3)
    ws = root / "ws"
    assert main(["run", str(data), "-w", str(ws), *tiny_set_args, *UNTIL]) == 0
    return data, ws, list(tiny_set_args)


def _export(run, fmt, *extra) -> int:
    data, ws, settings = run
    return main(["export", str(data), "-w", str(ws), "--format", fmt, *settings, *extra])


# ------------------------------------------------------------------------------------------------------------------
# nerfstudio: the folder travels

@pytest.mark.parametrize("mode", ["--copy-images", "--link"])
def test_nerfstudio_export_moved_away_without_the_dataset_resolves_every_frame(tiny_run, tmp_path, mode):
    data, ws, settings = tiny_run
    out = tmp_path / "export"
    assert main(["export", str(data), "-w", str(ws), "--format", "nerfstudio", "--out", str(out), mode,
                 *settings]) == 0
    originals = {p.name: p.read_bytes() for p in (data / "images").iterdir()}
    inodes = {p.name: p.stat().st_ino for p in (data / "images").iterdir()}
    moved = tmp_path / "elsewhere" / "training"
    moved.parent.mkdir()
    shutil.move(str(out), str(moved))
    hidden = data.parent / "tiny.gone"
    data.rename(hidden)  # the dataset is gone from where it was
    try:
        meta = json.loads((moved / "0" / "transforms.json").read_text())
        assert meta["camera_model"] == "EQUIRECTANGULAR" and meta["frames"]
        for frame in meta["frames"]:
            path = Path(frame["file_path"])
            assert not path.is_absolute() and ".." not in path.parts and path.parts[0] == "images"
            image = moved / "0" / path  # nerfstudio resolves file_path against the folder of transforms.json
            assert image.is_file(), frame["file_path"]
            assert image.read_bytes() == originals[path.name]
            assert (image.stat().st_ino == inodes[path.name]) == (mode == "--link")
        manifest = json.loads((moved / "manifest.json").read_text())
        assert {f"0/{f['file_path']}" for f in meta["frames"]} <= set(manifest["outputs"])
    finally:
        hidden.rename(data)


def test_link_falls_back_to_a_copy_across_file_systems(tiny_run, tmp_path, monkeypatch, caplog):
    data, ws, settings = tiny_run

    def no_link(src, dst, **kw):
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    monkeypatch.setattr(os, "link", no_link)
    out = tmp_path / "export"
    with caplog.at_level(logging.WARNING):
        assert main(["export", str(data), "-w", str(ws), "--format", "nerfstudio", "--out", str(out), "--link",
                     *settings]) == 0
    assert "copied, not linked" in caplog.text
    meta = json.loads((out / "0" / "transforms.json").read_text())
    for frame in meta["frames"]:
        copy = out / "0" / frame["file_path"]
        original = data / "images" / Path(frame["file_path"]).name
        assert copy.read_bytes() == original.read_bytes() and copy.stat().st_ino != original.stat().st_ino


# ------------------------------------------------------------------------------------------------------------------
# COLMAP: point errors in pixels, as pycolmap computes them

def _recomputed(rec) -> dict[int, float]:
    """pycolmap's own reprojection error of every point, recomputed from the poses, points and observations read
    back (`Reconstruction.update_point_3d_errors`; for an EQUIRECTANGULAR camera COLMAP 4.2.1 takes the angle
    between the observed ray and the ray to the point, times W / 2π)."""
    rec.update_point_3d_errors()
    return {pid: p.error for pid, p in rec.points3D.items()}


def _image_distance(rec) -> dict[int, float]:
    """Per point, the mean pixel distance on the image from each observation to pycolmap's projection
    (`Image.project_point`), the column difference the short way round the seam: what COLMAP's number means at
    the equator, larger towards the poles."""
    out = {}
    for pid, point in rec.points3D.items():
        d = []
        for el in point.track.elements:
            image = rec.images[el.image_id]
            w = rec.cameras[image.camera_id].width
            e = np.asarray(image.points2D[el.point2D_idx].xy) - np.asarray(image.project_point(point.xyz)).ravel()
            e[0] = (e[0] + w / 2) % w - w / 2
            d.append(np.hypot(*e))
        out[pid] = float(np.mean(d))
    return out


@pytest.mark.parametrize("fmt", ["colmap", "colmap-bin"])
def test_colmap_point_errors_agree_with_pycolmaps_reprojection_errors(tiny_run, fmt):
    _, ws, _ = tiny_run
    assert _export(tiny_run, fmt) == 0
    rec = pycolmap.Reconstruction(ws / "tiny" / f"export_{fmt}" / "0")
    stored = {pid: p.error for pid, p in rec.points3D.items()}
    assert len(stored) > 100
    near = _image_distance(rec)
    recomputed = _recomputed(rec)
    for pid, error in stored.items():
        assert error == pytest.approx(recomputed[pid], abs=1e-5), pid  # pycolmap's arccos: ~1e-6 px rounding
    errors, on_image = np.array(list(stored.values())), np.array([near[p] for p in stored])
    assert 0.05 < np.mean(errors) < 5  # pixels of a 512-px panorama (degrees would read 0.06 here)
    # the image-plane distance is the same figure up to the latitude's stretch (1 / cos lat across columns)
    assert np.median(on_image / errors) == pytest.approx(1.0, abs=0.1)
    assert np.all(on_image >= errors * (1 - 1e-3))


def test_point_errors_at_the_seam_and_the_poles_are_colmaps():
    """A point behind the camera (longitude ±180°, the seam) observed 0.3 px across it, and one near the pole: the
    stored error is what pycolmap recomputes, 0.3 px at the seam rather than an image width."""
    from fullview.io.exports import build_reconstruction

    w, h = 512, 256
    R = np.tile(np.eye(3), (2, 1, 1))
    t = np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    X = np.array([[0.001, 0.0, -3.0], [0.2, -3.0, 0.3]])  # the seam; 80° up
    pixels = [bearings_to_pixels(X @ R[k].T + t[k], w, h) for k in range(2)]
    assert pixels[0][0, 0] > w - 1
    pixels[0] = pixels[0] + [[0.3 - w, 0.0], [2.0, 0.0]]  # across the seam; 2 columns off near the pole
    assert 0 <= pixels[0][0, 0] < 1
    m = SparseModel(image_names=["a.png", "b.png"], image_sizes=[(w, h)] * 2, registered=np.array([True, True]),
                    R_cam_from_world=R, t_cam_from_world=t, points=X, colors=np.zeros((2, 3), np.uint8),
                    point_errors_rad=np.zeros(2), track_point3d=np.array([0, 0, 1, 1]),
                    track_image=np.array([0, 1, 0, 1]), track_point2d=np.array([0, 0, 1, 1]), pixels=pixels)
    ours = point_errors_px(m)
    assert ours[0] == pytest.approx(0.15, abs=1e-6)  # (0.3 + 0) / 2 observations
    assert ours[1] < 0.5 * 2.0 / 2  # 2 columns near the pole: a small angle
    rec = build_reconstruction(m)
    rec.update_point_3d_errors()
    # pycolmap takes the angle as arccos(cos): √ε ≈ 1.5e-8 rad, 1e-6 px, of rounding near zero
    assert [rec.points3D[k].error for k in (1, 2)] == pytest.approx(ours.tolist(), abs=1e-5)


def test_colmap_text_writer_stores_the_errors_pycolmap_recomputes(tmp_path):
    """The direct text writer (the triangulation stage's models, every colmap export) stores each point's error as
    pycolmap recomputes it from the file's own poses, points and pixels."""
    from tests.test_exports import make_model

    m = make_model(seed=7)
    m.pixels = [px + np.random.default_rng(k).normal(0, 0.5, px.shape) for k, px in enumerate(m.pixels)]
    write_colmap_model(m, tmp_path, binary=False)
    rec = pycolmap.Reconstruction(tmp_path)
    stored = {pid: p.error for pid, p in rec.points3D.items()}
    recomputed = _recomputed(rec)
    assert all(stored[pid] == pytest.approx(recomputed[pid], abs=1e-5) for pid in stored)
    assert 0.2 < np.mean(list(stored.values())) < 1.5  # ~ 0.5·√(π/2) px of noise, less where it stretches


# ------------------------------------------------------------------------------------------------------------------
# metric scale

def _truth(data: Path) -> dict[str, np.ndarray]:
    gt = yaml.safe_load((data / "ground_truth" / "poses.yaml").read_text())
    return {c["image"]: np.asarray(c["center"], np.float64) for c in gt["cameras"]}


def _distance_ratio(rec, truth) -> float:
    """Median over camera pairs of exported distance / true distance (1: metric)."""
    centers = {im.name: im.projection_center() for im in rec.images.values()}
    names = sorted(centers)
    return float(np.median([np.linalg.norm(centers[a] - centers[b]) / np.linalg.norm(truth[a] - truth[b])
                            for a, b in itertools.combinations(names, 2)]))


def _summary_scale(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())["summary"]["models"][0]


def test_camera_height_makes_every_export_metric_within_its_stated_uncertainty(room):
    """The camera heights of the rendered room vary by ±0.2 m about FLOOR_Y; the user states their median. The
    exported camera distances then agree with the true ones within 3 stated standard errors: the stated error is
    the spread of the per-camera heights over √n (`sfm.scale`), so it must cover the real height differences."""
    data, ws, _ = room
    truth = _truth(data)
    height = float(np.median([FLOOR_Y - c[1] for c in truth.values()]))
    assert _export(room, "colmap", "--camera-height", f"{height:.4f}") == 0
    folder = ws / "room8" / "export_colmap"
    scale = _summary_scale(folder)
    assert scale["unit"] == "metre" and scale["method"] == "camera_height" and scale["measurements"] >= 4
    assert 0 < scale["rel_std"] < 0.15
    ratio = _distance_ratio(pycolmap.Reconstruction(folder / "0"), truth)
    assert abs(ratio - 1) <= 3 * scale["rel_std"], (ratio, scale)
    assert "unit: metres (1 model unit = " in (folder / "README.txt").read_text()

    # the statement is kept: a plain export of another format is metric too, with the same factor
    assert _export(room, "ply", "--sparse-only") == 0
    ply = ws / "room8" / "export_ply"
    assert _summary_scale(ply)["metres_per_unit"] == pytest.approx(scale["metres_per_unit"], rel=1e-12)
    sparse = np.load(ws / "room8" / "triangulation" / "sparse.npz")
    cloud = load_ply(ply / "0" / "sparse.ply")
    xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
    assert np.allclose(xyz, sparse["points"][sparse["point_model"] == 0] * scale["metres_per_unit"], atol=1e-4)
    assert _export(room, "nerfstudio") == 0
    meta = json.loads((ws / "room8" / "export_nerfstudio" / "0" / "transforms.json").read_text())
    centers = {Path(f["file_path"]).name: np.array(f["transform_matrix"])[:3, 3] for f in meta["frames"]}
    a, b = sorted(centers)[:2]
    assert np.linalg.norm(centers[a] - centers[b]) / np.linalg.norm(truth[a] - truth[b]) == pytest.approx(
        ratio, rel=1e-3)

    # --model-units forgets it
    assert _export(room, "colmap", "--model-units") == 0
    assert _summary_scale(folder)["unit"] == "model unit"
    assert _export(room, "colmap") == 0
    assert _summary_scale(folder)["unit"] == "model unit"


def test_known_distance_makes_the_export_metric_within_its_stated_uncertainty(room):
    """Two triangulated hand points (box corners, whose true positions the scene file gives) and their true
    distance: the exported camera distances agree with the true ones within 3 stated standard errors."""
    from fullview.commands.export import _hand_point, sparse_models
    from fullview.io.config import load_config
    from fullview.io.dataset import Dataset
    from fullview.io.workspace import Workspace
    from fullview.stages.runner import Pipeline

    data, ws, settings = room
    boxes = np.load(data / "ground_truth" / "scene.npz")["boxes"]
    corners = {f"room_corner{c}" if k == 0 else f"box{k}_corner{c}": p
               for k, box in enumerate(boxes) for c, p in enumerate(_box_corners(box))}
    ds = Dataset(data)
    pipeline = Pipeline(ds, Workspace(ws, ds.name), load_config(None, [s for s in settings if s != "--set"]))
    model = sparse_models(pipeline)[0]
    seen = [n for n in corners if _hand_point(pipeline, model, n) is not None]
    assert len(seen) >= 2
    a, b = max(itertools.combinations(seen, 2), key=lambda p: np.linalg.norm(corners[p[0]] - corners[p[1]]))
    distance = float(np.linalg.norm(corners[a] - corners[b]))
    assert _export(room, "colmap", "--known-distance", a, b, f"{distance:.6f}") == 0
    folder = ws / "room8" / "export_colmap"
    scale = _summary_scale(folder)
    assert scale["method"] == "known_distance" and 0 < scale["rel_std"] < 0.1
    ratio = _distance_ratio(pycolmap.Reconstruction(folder / "0"), _truth(data))
    assert abs(ratio - 1) <= 3 * scale["rel_std"], (ratio, scale)
    assert _export(room, "colmap", "--model-units") == 0


def test_a_scale_that_cannot_be_measured_is_a_one_line_error(room, capsys):
    data, ws, _ = room
    assert _export(room, "colmap", "--known-distance", "no_such_point", "room_corner0", "2") == 2
    err = capsys.readouterr().err
    assert "no_such_point not in" in err and "hand_points.yaml" in err and "Traceback" not in err
    assert _export(room, "colmap", "--camera-height", "-1") == 2
    assert "--camera-height -1.0: expected a positive height" in capsys.readouterr().err
    assert not (ws / "room8" / "scale" / "statement.json").exists() or \
        json.loads((ws / "room8" / "scale" / "statement.json").read_text()) == {}
