"""The leave-one-out pose check (sfm/pose_check.py, `fullview eval`'s pose_check): a camera moved by a tenth of the
scene's size is flagged, and no other; an untouched model (noisy bearings, or a rendered room through the pipeline)
has nothing flagged; a camera whose points have no third view is unverifiable, not disagreeing."""

import json

import numpy as np
import pytest

from fullview.cli import main
from fullview.sfm import pose_check
from fullview.sfm.camera import normalize
from fullview.sfm.dense import scene_size

THETA = np.radians(0.5)  # the pipeline's default triangulation.max_reprojection_error_deg
OPTIONS = pose_check.PoseCheckOptions(threshold_rad=THETA, min_angle_rad=np.radians(1.5), min_points=15)
NOISE_DEG = 0.05  # bearing noise of the in-memory model: a quarter of a pixel at 2048 px (0.18° per pixel)


def _room_model(seed: int = 0, cameras: int = 8):
    """A 8 x 6 x 3 room's surfaces sampled with 3,000 points, seen by level cameras at eye height on a walk; each
    camera keeps 60% of the points it sees (features found in some views only), bearings with Gaussian noise."""
    rng = np.random.default_rng(seed)
    n = 3000
    lo, hi = np.array([-4.0, -1.5, -3.0]), np.array([4.0, 1.5, 3.0])
    points = rng.uniform(lo, hi, (n, 3))
    face = rng.integers(0, 6, n)  # push each point onto one face of the box
    axis, side = face % 3, face // 3
    points[np.arange(n), axis] = np.where(side == 0, lo[axis], hi[axis])
    centres = np.column_stack([np.linspace(-3, 3, cameras), np.zeros(cameras), rng.uniform(-1.5, 1.5, cameras)])
    yaw = rng.uniform(-np.pi, np.pi, cameras)
    R = np.stack([[[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]] for a in yaw])
    t = -np.einsum("nab,nb->na", R, centres)
    seen = rng.random((cameras, n)) < 0.6
    cam, pt = np.nonzero(seen)
    bearings_cam = np.einsum("kab,kb->ka", R[cam], points[pt]) + t[cam]
    noise = np.radians(NOISE_DEG) * rng.standard_normal(bearings_cam.shape) / np.sqrt(2)
    bearings_cam = normalize(normalize(bearings_cam) + noise)
    per_image, feature = [], np.empty(len(cam), np.int64)
    for c in range(cameras):  # feature ids: the observation's index within its image
        mine = cam == c
        feature[mine] = np.arange(mine.sum())
        per_image.append(bearings_cam[mine])
    return dict(points=points, centres=centres, R=R, t=t, track_ids=pt, image_ids=cam, feature_ids=feature,
                bearings=per_image)


def _check(model, t=None):
    return pose_check.check_poses(range(len(model["R"])), model["track_ids"], model["image_ids"],
                                  model["feature_ids"], model["bearings"], model["R"],
                                  model["t"] if t is None else t, OPTIONS)


def test_an_untouched_model_has_nothing_flagged():
    checks = _check(_room_model())
    assert all(c.status == "agrees" for c in checks.values()), {k: c.reason for k, c in checks.items()}
    # the re-estimate is far more precise than the bound: the check could see a difference well below θ
    assert max(c.shift_deg for c in checks.values()) < 0.2 * np.degrees(THETA)
    assert max(c.noise_deg for c in checks.values()) < np.degrees(THETA) / pose_check.NOISE_SIGMAS


@pytest.mark.parametrize("moved", [0, 3, 7])
def test_a_camera_moved_by_a_tenth_of_the_scene_is_flagged_and_no_other(moved):
    model = _room_model()
    size = scene_size(model["centres"], model["points"])
    rng = np.random.default_rng(moved)
    step = normalize(rng.standard_normal(3)) * 0.1 * size
    t = model["t"].copy()
    t[moved] -= model["R"][moved] @ step  # the centre moves by `step`, the rotation stays
    checks = _check(model, t)
    assert checks[moved].status == "disagrees", checks[moved].reason
    assert checks[moved].centre_distance == pytest.approx(0.1 * size, rel=0.02)  # it finds where the camera was
    others = {k: c.status for k, c in checks.items() if k != moved}
    assert set(others.values()) == {"agrees"}, others


def test_a_camera_turned_by_twice_the_threshold_is_flagged():
    model = _room_model()
    turn = 2 * THETA
    Rz = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    R, t = model["R"].copy(), model["t"].copy()
    c = -R[2].T @ t[2]
    R[2] = Rz @ R[2]
    t[2] = -R[2] @ c
    checks = pose_check.check_poses(range(len(R)), model["track_ids"], model["image_ids"], model["feature_ids"],
                                    model["bearings"], R, t, OPTIONS)
    assert checks[2].status == "disagrees"
    assert checks[2].rotation_deg == pytest.approx(np.degrees(turn), rel=0.05)
    assert all(c.status == "agrees" for k, c in checks.items() if k != 2)


def test_two_cameras_are_unverifiable_not_disagreeing():
    model = _room_model(cameras=2)
    checks = _check(model)
    assert [c.status for c in checks.values()] == ["unverifiable"] * 2
    assert all(c.points == 0 and c.rotation_deg is None for c in checks.values())


def test_leave_one_out_points_owe_nothing_to_the_left_out_camera():
    # moving camera 0 changes none of the points its own check rests on (they are triangulated without it)
    model = _room_model()
    args = (model["track_ids"], model["image_ids"], model["feature_ids"], model["bearings"], model["R"])
    img, fid, points = pose_check.leave_one_out_points(*args, model["t"], OPTIONS)
    t = model["t"].copy()
    t[0] += 0.5
    img2, fid2, points2 = pose_check.leave_one_out_points(*args, t, OPTIONS)
    mine, mine2 = img == 0, img2 == 0
    assert mine.sum() > 100
    np.testing.assert_array_equal(fid[mine], fid2[mine2])
    np.testing.assert_allclose(points[mine], points2[mine2])


def test_eval_reports_the_pose_check_of_a_rendered_room(tmp_path, capsys, tiny_set_args, make_pipeline):
    # a rendered room (5 views at 512 px with sensor noise) through the pipeline: eval's pose_check flags nothing;
    # with one camera's centre moved by a tenth of the scene's size in the model, that camera and no other is
    from fullview.commands.evaluate import eval_summary, pose_check as eval_pose_check
    from fullview.synth import write_synthetic_dataset
    from fullview.synth.capture import CaptureTraits

    dataset = write_synthetic_dataset(tmp_path / "room", views=5, width=512, seed=3,
                                      capture=CaptureTraits(noise=2.0))
    ws = tmp_path / "ws"
    assert main(["run", str(dataset), "-w", str(ws), "--until", "triangulation", *tiny_set_args]) == 0
    capsys.readouterr()
    assert main(["eval", str(dataset), "-w", str(ws), *tiny_set_args]) == 0
    short = json.loads(capsys.readouterr().out)["pose_check"]  # the terminal's summary: no per-image entries
    metrics = json.loads((ws / "room" / "eval" / "metrics.json").read_text())
    check = metrics["pose_check"]
    assert len(check["per_image"]) == 5
    assert short == eval_summary(metrics)["pose_check"] and "per_image" not in short
    assert short["flagged"] == check["flagged"]
    assert check["flagged"] == [], check["per_image"]
    assert check["threshold_deg"] == 1.5  # the tiny settings' triangulation threshold

    pipeline = make_pipeline(dataset, workspace=ws)
    sparse = pipeline.ws.load_sparse()
    registered = np.flatnonzero(sparse["model_id"] == 0)
    moved = int(registered[1])
    size = scene_size(sparse["centers"][registered], sparse["points"][sparse["point_model"] == 0])
    step = np.array([0.1 * size, 0.0, 0.0])
    sparse["t_cam_from_world"][moved] -= sparse["R_cam_from_world"][moved] @ step
    sparse["centers"][moved] += step
    check = eval_pose_check(pipeline, sparse)
    name = str(sparse["image_names"][moved])
    assert check["flagged"] == [name], check["per_image"]
    assert check["per_image"][name]["status"] == "disagrees"
    assert check["per_image"][name]["centre_rel"] == pytest.approx(0.1, rel=0.1)
