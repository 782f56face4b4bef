"""End to end on a tiny synthetic scene: every sparse stage, eval, and the COLMAP export."""

import json
import shutil

import numpy as np
import pycolmap
import pytest

from fullview.cli import main
from fullview.commands.evaluate import eval_summary
from fullview.io.artifacts import load_ply

SPARSE_UNTIL = "triangulation"


@pytest.fixture(scope="module")
def reconstructed(tiny_dataset, tmp_path_factory, tiny_set_args):
    ws = tmp_path_factory.mktemp("e2e") / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", SPARSE_UNTIL, *tiny_set_args]) == 0
    return tiny_dataset, ws


def test_eval_metrics(reconstructed, capsys, tiny_set_args):
    dataset, ws = reconstructed
    capsys.readouterr()
    assert main(["eval", str(dataset), "-w", str(ws), *tiny_set_args]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["registered"] == 3
    assert metrics["auc@5"] > 95
    assert metrics["median_relative_rotation_error_deg"] < 0.1
    stored = json.loads((ws / "tiny" / "eval" / "metrics.json").read_text())
    assert eval_summary(stored) == metrics  # the terminal gets the summary, the file every per-image figure
    assert "per_image" in stored["pose_check"] and "per_image" not in metrics["pose_check"]


def test_a_second_eval_reuses_the_first_until_an_input_changes(reconstructed, caplog, tiny_set_args, tmp_path):
    """eval is cached like a stage: unchanged results give the stored metrics at once; a changed ground truth (an
    input of the metrics) computes them again."""
    dataset, ws = reconstructed
    assert main(["eval", str(dataset), "-w", str(ws), *tiny_set_args]) == 0
    caplog.clear()
    with caplog.at_level("INFO"):
        assert main(["eval", str(dataset), "-w", str(ws), *tiny_set_args]) == 0
    assert "reused" in caplog.text
    moved = tmp_path / "tiny"
    shutil.copytree(dataset, moved)
    poses = moved / "ground_truth" / "poses.yaml"
    poses.write_text(poses.read_text() + "\n# edited\n")
    caplog.clear()
    with caplog.at_level("INFO"):
        assert main(["eval", str(moved), "-w", str(ws), *tiny_set_args]) == 0
    assert "reused" not in caplog.text


def test_colmap_model_is_readable(reconstructed):
    _, ws = reconstructed
    rec = pycolmap.Reconstruction(str(ws / "tiny" / "triangulation" / "models" / "0"))
    assert rec.num_reg_images() == 3 and rec.num_points3D() > 100
    cam = next(iter(rec.cameras.values()))
    assert cam.model.name == "EQUIRECTANGULAR" and (cam.width, cam.height) == (512, 256)
    errors = [p.error for p in rec.points3D.values()]
    assert np.median(errors) < 1.5  # degrees (our angular error)
    sparse = np.load(ws / "tiny" / "triangulation" / "sparse.npz")
    ours = sparse["points"][0]
    assert np.allclose(rec.points3D[1].xyz, ours, atol=1e-5)


def test_colmap_model_reprojects_with_colmap_camera(reconstructed):
    """COLMAP's own EQUIRECTANGULAR projection of our points lands on our stored 2-D observations."""
    _, ws = reconstructed
    rec = pycolmap.Reconstruction(str(ws / "tiny" / "triangulation" / "models" / "0"))
    residuals = []
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        for p2d in image.points2D:
            if p2d.has_point3D():
                x_cam = image.cam_from_world() * rec.points3D[p2d.point3D_id].xyz
                proj = cam.img_from_cam(x_cam)
                d = proj - p2d.xy
                d[0] = (d[0] + 256) % 512 - 256
                residuals.append(np.linalg.norm(d))
    assert np.median(residuals) < 1.0


def test_sparse_ply_is_binary_with_colours(reconstructed):
    _, ws = reconstructed
    path = ws / "tiny" / "triangulation" / "sparse.ply"
    assert b"format binary_little_endian" in path.read_bytes()[:200]
    ply = load_ply(path)
    assert len(ply["x"]) > 100 and ply["red"].dtype == np.uint8


def test_without_hand_points_too(tiny_dataset, tmp_path, capsys, tiny_set_args):
    ws = tmp_path / "ws"
    settings = [*tiny_set_args, "--set", "filter.use_hand_points=false"]
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", SPARSE_UNTIL, *settings]) == 0
    capsys.readouterr()
    assert main(["eval", str(tiny_dataset), "-w", str(ws), *settings]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["registered"] == 3 and metrics["auc@5"] > 95
    summary = json.loads((ws / "tiny" / "filter" / "manifest.json").read_text())["summary"]
    assert summary["seeded_pairs"] == 0


def test_planar_model_runs(reconstructed, tmp_path, capsys, tiny_set_args):
    dataset, _ = reconstructed
    ws = tmp_path / "ws"
    settings = [*tiny_set_args, "--set", "registration.model=planar", "--set",
                "registration.max_rotation_residual_deg=20", "--set", "registration.max_direction_residual_deg=20"]
    assert main(["run", str(dataset), "-w", str(ws), "--until", "registration", *settings]) == 0
    capsys.readouterr()
    assert main(["eval", str(dataset), "-w", str(ws), *settings]) == 0
    metrics = json.loads(capsys.readouterr().out)
    # The synthetic cameras tilt by up to 5°, which the level-camera model cannot represent.
    assert metrics["registered"] == 3 and metrics["auc@10"] > 20


def test_unrelated_image_is_reported_not_fatal(dataset_copy, tmp_path, capsys, tiny_set_args):
    import cv2
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.integers(0, 255, (256, 512, 3), dtype=np.uint8), (5, 5), 0)
    cv2.imwrite(str(dataset_copy / "images" / "zz_unrelated.png"), noise)
    ws = tmp_path / "ws"
    assert main(["run", str(dataset_copy), "-w", str(ws), "--until", SPARSE_UNTIL, *tiny_set_args]) == 0
    summary = json.loads((ws / "tiny" / "registration" / "manifest.json").read_text())["summary"]
    assert summary["registered"] == 3 and summary["unregistered"] == ["zz_unrelated.png"]
    assert summary["unregistered_reasons"]["zz_unrelated.png"].startswith("no verified pair with >= 15 inliers")
    rec = pycolmap.Reconstruction(str(ws / "tiny" / "triangulation" / "models" / "0"))
    assert rec.num_reg_images() == 3


def test_sequential_chain_registers_every_image(tiny_dataset, tmp_path, capsys, tiny_set_args):
    """Pairs (0,1), (1,2) only: averaging cannot scale the chain; attaching by points does."""
    ws = tmp_path / "ws"
    settings = [*tiny_set_args, "--set", "matches.pairs=sequential", "--set", "matches.window=1"]
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", SPARSE_UNTIL, *settings]) == 0
    capsys.readouterr()
    assert main(["eval", str(tiny_dataset), "-w", str(ws), *settings]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["registered"] == 3 and metrics["auc@5"] > 95


def test_colours_at_reduced_working_width(tiny_dataset, tmp_path):
    """Features found at half the native width keep the colour of their own pixel."""
    import cv2

    from fullview.io.dataset import Dataset
    from fullview.io.workspace import Workspace

    ws = tmp_path / "ws"
    assert main(["run", str(tiny_dataset), "-w", str(ws), "--until", "features",
                 "--set", "features.working_width=256"]) == 0
    ds = Dataset(tiny_dataset)
    name = ds.image_names[0]
    feats = Workspace(ws, ds.name).load_features(name)
    image = cv2.imread(str(ds.image_path(name)))  # native 512 px: stored pixels are native coordinates
    cols = np.clip(feats["pixels"][:, 0].astype(int), 0, 511)
    rows = np.clip(feats["pixels"][:, 1].astype(int), 0, 255)
    native = image[rows, cols][:, ::-1].astype(float)
    assert np.abs(native - feats["colors"]).mean() < 20  # blurred by the downscale, but the same place
