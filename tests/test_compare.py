"""The COLMAP comparison on small synthetic models with known poses (no COLMAP run): agreement, alignment,
reprojection, top view, the baseline gate, and the feature mapping of colmap-check."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm import compare as cmp
from fullview.sfm.camera import bearings_to_pixels, normalize
from fullview.sfm.features import face_rotations
from fullview.sfm.metrics import Similarity


def _model(n=6, seed=0):
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    c = rng.normal(size=(n, 3)) * [3.0, 0.2, 3.0]
    return R, c, np.ones(n, bool)


def _similar_copy(R, c, seed=5, scale=0.37, shift=(4.0, -1.0, 2.0)):
    """The same cameras in another world frame: x' = s S x + shift."""
    S = Rotation.random(random_state=seed).as_matrix()
    return R @ S.T, scale * c @ S.T + np.array(shift), Similarity(scale=scale, R=S, t=np.array(shift))


def _rot(axis, deg):
    return Rotation.from_rotvec(np.radians(deg) * normalize(np.asarray(axis, float))).as_matrix()


# --------------------------------------------------------------------------------------------- agreement
def test_similarity_transformed_copy_agrees_exactly_and_aligns():
    R, c, reg = _model()
    R2, c2, sim_true = _similar_copy(R, c)
    a = cmp.relative_agreement(R, c, reg, R2, c2, reg)
    s = a.summary()
    assert s["pairs_compared"] == s["pairs_total"] == 15
    assert s["rotation_max_deg"] < 1e-5 and s["translation_max_deg"] < 1e-5
    sim = cmp.align_cameras(R, c, R2, c2, reg)
    assert np.isclose(sim.scale, sim_true.scale) and np.allclose(sim.R, sim_true.R) and np.allclose(sim.t, sim_true.t)
    d = cmp.aligned_differences(sim, R, c, R2, c2, reg)
    assert d["rotation_max_deg"] < 1e-5 and d["center_max_rel"] < 1e-9


def test_perturbed_rotation_gives_its_angle_on_the_pairs_it_touches():
    R, c, reg = _model()
    k, angle = 2, 0.3
    R2 = R.copy()
    R2[k] = _rot([0.2, 1.0, -0.4], angle) @ R[k]  # camera k turned by 0.3° about an axis of its own frame
    a = cmp.relative_agreement(R, c, reg, R2, c, reg)
    touches = (a.pairs == k).any(axis=1)
    assert np.allclose(a.rotation_deg[touches], angle, atol=1e-6)
    assert np.all(a.rotation_deg[~touches] < 1e-5)
    # t_j_from_i = R_j (c_i - c_j): unchanged where k is the first camera, turned by at most the angle otherwise
    assert np.all(a.translation_deg[a.pairs[:, 0] == k] < 1e-5)
    second = a.pairs[:, 1] == k
    assert np.all(a.translation_deg[second] <= angle + 1e-6) and np.any(a.translation_deg[second] > 0.5 * angle)
    assert np.isclose(a.summary()["rotation_max_deg"], angle, atol=1e-6)


def test_moved_centre_changes_translation_direction_by_the_expected_angle():
    R, c, reg = _model()
    c2 = c.copy()
    baseline = c[1] - c[0]
    side = normalize(np.cross(baseline, [0.0, 1.0, 0.0]))
    c2[1] = c[1] + np.tan(np.radians(2.0)) * np.linalg.norm(baseline) * side  # c1 seen from c0 turns by 2°
    a = cmp.relative_agreement(R, c, reg, R, c2, reg)
    row = np.flatnonzero((a.pairs[:, 0] == 0) & (a.pairs[:, 1] == 1))[0]
    assert np.isclose(a.translation_deg[row], 2.0, atol=1e-6)
    assert np.all(a.rotation_deg < 1e-5)


def test_unregistered_images_are_left_out_of_the_agreement():
    R, c, reg = _model(n=5)
    R2, c2, _ = _similar_copy(R, c)
    reg2 = reg.copy()
    reg2[3] = False
    R2[3], c2[3] = np.eye(3) * np.nan, np.nan  # whatever an unregistered image holds must not matter
    a = cmp.relative_agreement(R, c, reg, R2, c2, reg2)
    assert a.pairs_total == 10 and len(a.pairs) == 6 and not (a.pairs == 3).any()
    assert a.summary()["rotation_max_deg"] < 1e-5
    sim = cmp.align_cameras(R, c, R2, c2, reg & reg2)
    assert cmp.aligned_differences(sim, R, c, R2, c2, reg & reg2)["center_max_rel"] < 1e-9
    none = cmp.relative_agreement(R, c, np.zeros(5, bool), R2, c2, reg2)
    assert none.summary()["pairs_compared"] == 0 and none.summary()["rotation_median_deg"] is None
    with pytest.raises(ValueError, match="image count"):
        cmp.relative_agreement(R, c, reg, R2[:4], c2[:4], reg2[:4])


def test_collinear_centres_align_through_the_orientations():
    R, _, reg = _model(n=4)
    c = np.outer(np.arange(4.0), [1.0, 0.0, 0.5])  # on a line: Umeyama cannot fix the roll about it
    R2, c2, sim_true = _similar_copy(R, c)
    sim = cmp.align_cameras(R, c, R2, c2, reg)
    assert np.allclose(sim.R, sim_true.R) and np.isclose(sim.scale, sim_true.scale)
    assert np.allclose(sim.apply(c), c2)
    two = np.array([True, True, False, False])  # two cameras only
    assert np.allclose(cmp.align_cameras(R, c, R2, c2, two).R, sim_true.R)


def test_rotation_difference_after_alignment_ignores_a_loose_centre_fit():
    R, _, reg = _model(n=4)
    c = np.outer(np.arange(4.0), [1.0, 0.0, 0.0]) + [[0, 0.01, 0], [0, 0, 0], [0, -0.01, 0], [0, 0, 0.01]]
    R2, c2, _ = _similar_copy(R, c)
    c2 = c2 + np.random.default_rng(1).normal(scale=2e-3, size=c2.shape)  # noise tilts the roll of Umeyama's fit
    sim = cmp.align_cameras(R, c, R2, c2, reg)
    d = cmp.aligned_differences(sim, R, c, R2, c2, reg)
    assert d["rotation_max_deg"] < 1e-5 and d["similarity_vs_orientation_rotation_deg"] > 0.01


# --------------------------------------------------------------------------------------------- model statistics
def test_angular_reprojection_errors():
    R, c, _ = _model(n=3)
    t = -np.einsum("nab,nb->na", R, c)
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4, 3)) * 5
    obs_image = np.array([0, 1, 2, 0, 1])
    obs_point = np.array([0, 0, 1, 2, 3])
    x = np.einsum("nab,nb->na", R[obs_image], points[obs_point]) + t[obs_image]
    bearings = normalize(x)
    assert np.all(cmp.angular_reprojection_errors(R, t, points, obs_image, obs_point, bearings) < 1e-7)
    turned = bearings.copy()
    axis = normalize(np.cross(bearings[2], [0.3, 1.0, 0.1]))
    turned[2] = _rot(axis, 0.25) @ bearings[2]
    err = np.degrees(cmp.angular_reprojection_errors(R, t, points, obs_image, obs_point, 3.0 * turned))
    assert np.isclose(err[2], 0.25, atol=1e-6) and np.all(np.delete(err, 2) < 1e-5)
    stats = cmp.model_statistics(registered=np.array([True, True, False]), points=points, obs_image=obs_image,
                                 obs_point=obs_point, errors_rad=np.radians(err))
    assert stats["registered"] == 2 and stats["points"] == 4 and np.isclose(stats["mean_track_length"], 1.25)


def test_top_view_basis_looks_down_the_vertical_in_any_gauge():
    rng = np.random.default_rng(4)
    c = np.column_stack([rng.normal(size=8) * 3, rng.normal(size=8) * 0.05, rng.normal(size=8) * 2])
    R = np.stack([_rot([0, 1, 0], a) for a in rng.uniform(0, 360, 8)])  # level cameras: up is world −y
    S = Rotation.random(random_state=7).as_matrix()  # another gauge
    for RR, cc in ((R, c), (R @ S.T, c @ S.T)):
        up = cmp.camera_up(RR)
        basis = cmp.top_view_basis(cc, up)
        assert np.allclose(basis @ basis.T, np.eye(2), atol=1e-9)
        assert np.cross(basis[0], basis[1]) @ up > 0.99  # seen from above
    walk = np.column_stack([np.arange(6.0), [0, 0.1, -0.1, 0.1, -0.1, 0], [0, 0.01, 0, -0.01, 0, 0.01]])
    basis = cmp.top_view_basis(walk, np.array([0.0, -1.0, 0.0]))  # bobbing up and down more than sideways
    assert np.allclose(np.cross(basis[0], basis[1]), [0, -1, 0]) and abs(basis[0] @ [1, 0, 0]) > 0.99
    line = np.outer(np.arange(3.0), [1.0, 0.0, 0.0])  # collinear: plane orthogonal to up
    basis = cmp.top_view_basis(line, np.array([0.0, -1.0, 0.0]))
    assert np.allclose(np.cross(basis[0], basis[1]), [0, -1, 0]) and np.isclose(abs(basis[0] @ [1, 0, 0]), 1.0)
    assert cmp.top_view_basis(line[:1], None).shape == (2, 3)


# --------------------------------------------------------------------------------------------- baseline gate
TOL = {"registered_max_drop": 0, "auc@1_max_drop_points": 1.0,
       "agreement_rotation_median_max_increase_deg": 0.05, "agreement_translation_median_max_increase_deg": 0.25}
BASE = {"ours_registered": 11, "ours_auc@1": 95.0, "agreement_rotation_median_deg": 0.04,
        "agreement_translation_median_deg": 0.2}


def test_gate_passes_within_tolerance_and_fails_beyond():
    within = {"ours_registered": 11, "ours_auc@1": 94.2, "agreement_rotation_median_deg": 0.089,
              "agreement_translation_median_deg": 0.44}
    assert cmp.gate(within, BASE, TOL) == []
    better = {"ours_registered": 12, "ours_auc@1": 99.0, "agreement_rotation_median_deg": 0.0,
              "agreement_translation_median_deg": 0.0}
    assert cmp.gate(better, BASE, TOL) == []
    for key, bad in (("ours_registered", 10), ("ours_auc@1", 93.9), ("agreement_rotation_median_deg", 0.091),
                     ("agreement_translation_median_deg", 0.46), ("agreement_rotation_median_deg", None)):
        failures = cmp.gate({**within, key: bad}, BASE, TOL)
        assert len(failures) == 1 and failures[0].startswith(key)
    # a metric the baseline does not record (real data: no AUC) is not gated
    assert cmp.gate({**within, "ours_auc@1": None}, {**BASE, "ours_auc@1": None}, TOL) == []
    with pytest.raises(ValueError, match="auc@1_max_drop_points"):
        cmp.gate(within, BASE, {k: v for k, v in TOL.items() if k != "auc@1_max_drop_points"})


def _result(dataset="scene", **over):
    result = {"dataset": dataset, "render_type": "spherical", "ours": {"registered": 11},
              "agreement": {"rotation_median_deg": 0.04, "translation_median_deg": 0.2},
              "ground_truth": {"ours": {"auc@1": 95.0}}}
    result.update(over)
    return result


def test_baseline_file_gates_listed_datasets_only(tmp_path):
    from fullview.commands.compare import check_against_baseline

    path = tmp_path / "baseline.json"
    path.write_text(json.dumps({"render_type": "spherical", "tolerances": TOL,
                                "datasets": {"scene": {"metrics": BASE,
                                                       "tolerances": {"auc@1_max_drop_points": 0.1}}}}))
    assert check_against_baseline(_result(), path)["status"] == "pass"
    worse = _result(ground_truth={"ours": {"auc@1": 94.5}})  # within the global 1.0, beyond the scene's 0.1
    g = check_against_baseline(worse, path)
    assert g["status"] == "fail" and "ours_auc@1" in g["failures"][0]
    assert check_against_baseline(_result("other"), path)["status"] == "not gated"
    assert check_against_baseline(_result(render_type="perspective_overlapping"), path)["status"] == "not gated"
    assert check_against_baseline(_result(), tmp_path / "absent.json")["status"] == "not gated"
    # an entry recorded on other images (same folder name, another scene) is not applied
    path.write_text(json.dumps({"tolerances": TOL, "datasets": {"scene": {"metrics": BASE, "images_sha256": "abc"}}}))
    assert check_against_baseline(_result(images_sha256="abc"), path)["status"] == "pass"
    g = check_against_baseline(_result(images_sha256="def", ours={"registered": 1}), path)
    assert g["status"] == "not gated" and "other images" in g["reason"]


def test_markdown_report_renders_every_section():
    from fullview.commands.compare import format_markdown

    side = {"registered": 3, "images": 3, "points": 10, "mean_track_length": 2.5,
            "median_reprojection_error_deg": 0.03, "wall_time_s": 1.0}
    result = {"dataset": "scene", "render_type": "spherical", "pycolmap": "x", "ours": side, "colmap": side,
              "agreement": cmp.Agreement(pairs=np.zeros((0, 2), int), rotation_deg=np.zeros(0),
                                         translation_deg=np.zeros(0), pairs_total=3).summary(),
              "ground_truth": {"ours": {"auc@1": 99.0}, "colmap": {"auc@1": 98.0}},
              "gate": {"status": "fail", "failures": ["ours_auc@1: worse"]}}
    md = format_markdown(result)
    assert "0/3 pairs" in md and "| AUC@1° | 99.0000 | 98.0000 |" in md and "- ours_auc@1: worse" in md


# --------------------------------------------------------------------------------------------- colmap-check mapping
def test_colmap_face_keypoints_map_back_to_their_bearings():
    from fullview.commands.colmap_check import colmap_features

    face_size, margin = 200, 5.0
    focal = 0.5 * face_size / np.tan(np.radians(45.0 + margin))
    rng = np.random.default_rng(6)
    parts, truth = [], []
    for f, R_cam_from_face in enumerate(face_rotations()):
        xy = rng.uniform(0, face_size, size=(40, 2))  # COLMAP pixels: (0, 0) is the corner, no half-pixel shift
        rays = normalize(np.column_stack([(xy - face_size / 2) / focal, np.ones(len(xy))]) @ R_cam_from_face.T)
        parts.append((xy, f, rng.integers(0, 255, size=(40, 128)).astype(np.uint8)))
        truth.append(rays)
    b, d, faces = colmap_features(parts, face_size, focal, -60.0, 90.0)
    truth = np.concatenate(truth)
    local = np.einsum("nab,na->nb", face_rotations()[np.repeat(np.arange(6), 40)], truth)
    owned = (np.abs(local[:, 0]) <= local[:, 2]) & (np.abs(local[:, 1]) <= local[:, 2])
    lat = np.degrees(np.arcsin(-truth[:, 1]))
    expected = truth[owned & (lat >= -60.0)]
    assert len(b) == len(expected) and 0 < len(b) < len(truth)
    assert np.allclose(b, expected, atol=1e-12)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6) and d.dtype == np.float32
    # the owner face of every kept feature is the one that found it
    owner = np.argmax(np.einsum("nb,fba->nfa", b, face_rotations())[..., 2], axis=1)
    assert np.array_equal(owner, faces)


def test_colmap_model_reader_matches_known_poses(tmp_path):
    """A model written by write_text_model and read back through pycolmap: poses, bearings, zero error."""
    pytest.importorskip("pycolmap")
    from fullview.io.colmap import load_reconstruction, model_arrays, write_text_model

    R, c, reg = _model(n=3, seed=2)
    t = -np.einsum("nab,nb->na", R, c)
    points = np.random.default_rng(8).normal(size=(5, 3)) * 10
    w, h = 2048, 1024
    x = np.einsum("nab,pb->npa", R, points) + t[:, None]  # (image, point, 3)
    pixels = [bearings_to_pixels(x[k], w, h) for k in range(3)]
    obs_image = np.repeat(np.arange(3), 5)
    obs_point = np.tile(np.arange(5), 3)
    names = ["a.jpg", "b.jpg", "c.jpg"]
    write_text_model(tmp_path, image_sizes=[(w, h)] * len(names), image_names=names, registered=reg, R_cam_from_world=R,
                     t_cam_from_world=t, points=points, colors=np.zeros((5, 3), np.uint8), errors_rad=np.zeros(5),
                     track_image=obs_image, track_point2d=obs_point, track_point3d=obs_point, pixels=pixels)
    m = model_arrays(load_reconstruction(tmp_path), ["c.jpg", "a.jpg", "b.jpg", "missing.jpg"])
    assert m["registered"].tolist() == [True, True, True, False]
    assert np.allclose(m["R_cam_from_world"][:3], R[[2, 0, 1]], atol=1e-12)
    assert np.allclose(m["centers"][:3], c[[2, 0, 1]], atol=1e-9) and np.isnan(m["centers"][3]).all()
    err = cmp.angular_reprojection_errors(m["R_cam_from_world"], m["t_cam_from_world"], m["points"],
                                          m["obs_image"], m["obs_point"], m["obs_bearings"])
    assert len(err) == 15 and np.degrees(err.max()) < 1e-3  # pixels are stored with 3 decimals
