import dataclasses
import itertools
import shutil

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from fullview.io.artifacts import FORMAT_KEY, load_ply
from fullview.io.config import load_config
from fullview.io.dataset import Dataset
from fullview.io.render import colorize_range, render_mesh, render_point_cloud
from fullview.synth import write_synthetic_dataset
from fullview.io.workspace import DEPTH_VERSION, Workspace
from fullview.sfm import dense
from fullview.sfm.dense_metrics import (backproject_range_map, cloud_accuracy_completeness, dense_metrics,
                                        range_map_errors, voxel_downsample)
from fullview.sfm.metrics import Similarity, umeyama
from fullview.stages import densify
from fullview.commands.evaluate import evaluate
from fullview.stages.protocol import thread_map
from fullview.stages.runner import Pipeline

SMALL = [
    "features.working_width=512", "features.max_features_per_face=1500",
    "densify.working_width=512", "densify.rect_height=256", "densify.min_pair_inliers=30",
    "densify.max_range_error_per_px=0.2",  # pixels are 4x the default's angle: the same conditioning bound
]


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    """A tiny synthetic scene (3 views, 512 px) run through the pipeline up to densify."""
    root = tmp_path_factory.mktemp("densify")
    dataset = Dataset(write_synthetic_dataset(root / "scene", views=3, width=512, seed=1))
    ws = Workspace(root / "ws", dataset.name)
    pipeline = Pipeline(dataset, ws, load_config(None, SMALL))
    ran = pipeline.run(until="densify")
    assert ran[-1] == "densify"
    return dataset, ws, pipeline


def _gt_poses(dataset):
    gt = dataset.ground_truth_poses()
    R = np.stack([gt[n].R_world_from_cam.T for n in dataset.image_names])
    c = np.stack([gt[n].center for n in dataset.image_names])
    return R, c


# --------------------------------------------------------------------------------------------- end to end
def test_dense_ply_is_binary_with_sensible_points(reconstructed):
    dataset, ws, pipeline = reconstructed
    path = ws.path("dense_cloud")
    head = path.read_bytes()[:400]
    assert b"format binary_little_endian 1.0" in head and b"property float nx" in head
    cloud = load_ply(path)
    n = len(cloud["x"])
    summary = ws.read_manifest("densify")["summary"]
    assert summary["points"] == n
    assert 5_000 < n < 3 * 512 * 256  # far more than the sparse points, fewer than the pixels of all maps
    normals = np.column_stack([cloud["nx"], cloud["ny"], cloud["nz"]])
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)
    assert np.ptp(cloud["red"].astype(int)) > 50  # real colours, not a constant
    assert pipeline.status("densify").state == "fresh"


def test_depth_maps_are_saved_per_panorama(reconstructed):
    dataset, ws, _ = reconstructed
    for name in dataset.image_names:
        stem = name.rsplit(".", 1)[0]
        with np.load(ws.path("depth", stem=stem)) as data:
            assert int(data[FORMAT_KEY]) == DEPTH_VERSION
            rng, valid = data["range"], data["valid"]
        assert rng.shape == (256, 512) and rng.dtype == np.float32 and valid.dtype == bool
        assert np.all(np.isnan(rng[~valid])) and np.all(rng[valid] > 0)
        png = cv2.imread(str(ws.path("depth_image", stem=stem)))
        assert png.shape == (256, 512, 3) and png[valid].any(axis=-1).mean() > 0.99
    preview = cv2.imread(str(ws.path("dense_preview")))
    assert preview is not None and preview.std() > 10


def test_densify_reruns_are_byte_identical_on_one_thread(reconstructed, tmp_path, monkeypatch):
    """densify again on a copy of the workspace with every pool of the stage and OpenCV on one thread: the range
    maps, the cloud and the mesh are the same bytes (the threads over pairs and panoramas change only the time)."""
    dataset, ws, _ = reconstructed
    shutil.copytree(ws.root, tmp_path / dataset.name)
    copy = Workspace(tmp_path, dataset.name)
    monkeypatch.setattr(densify, "thread_map", lambda fn, items, threads=None: thread_map(fn, items, threads=1))
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        Pipeline(dataset, copy, load_config(None, SMALL)).run(start="densify", until="densify")
    finally:
        cv2.setNumThreads(opencv_threads)
    for name in dataset.image_names:
        stem = name.rsplit(".", 1)[0]
        with np.load(ws.path("depth", stem=stem)) as a, np.load(copy.path("depth", stem=stem)) as b:
            assert a["range"].tobytes() == b["range"].tobytes() and np.array_equal(a["valid"], b["valid"])
    for artifact in ("dense_cloud", "dense_mesh"):
        assert ws.path(artifact).read_bytes() == copy.path(artifact).read_bytes(), artifact


def test_dense_mesh_is_saved_with_its_summary_and_preview(reconstructed):
    dataset, ws, pipeline = reconstructed
    mesh = ws.load_dense_mesh()
    summary = ws.read_manifest("densify")["summary"]["mesh"]
    assert summary["triangles"] == len(mesh["triangles"]) > 1000 and summary["vertices"] == len(mesh["vertices"])
    assert 0.0 <= summary["trimmed_share"] < 1.0
    assert mesh["triangles"].max() < len(mesh["vertices"]) and np.ptp(mesh["colors"].astype(int)) > 50
    # every vertex lies near the fused cloud (the distance trim), whatever Poisson closed
    cloud = load_ply(ws.path("dense_cloud"))
    xyz = np.column_stack([cloud["x"], cloud["y"], cloud["z"]])
    dist, _ = cKDTree(xyz).query(mesh["vertices"])
    assert dist.max() <= 3.5 * ws.read_manifest("densify")["summary"]["voxel_size"]
    preview = cv2.imread(str(ws.path("dense_mesh_preview")))
    assert preview is not None and preview.std() > 10
    assert "dense_mesh.ply" in ws.read_manifest("densify")["outputs"]


def test_eval_reports_dense_metrics(reconstructed):
    dataset, ws, pipeline = reconstructed
    metrics = evaluate(pipeline)
    d = metrics["dense"]
    assert set(d["per_panorama"]) == set(dataset.image_names)
    for name, m in d["per_panorama"].items():
        assert m["median_rel_error"] < 0.03, name
        assert m["valid_share"] > 0.4, name
    assert d["cloud"]["accuracy"] > 0.85
    assert d["cloud"]["completeness"] > 0.5
    assert np.isclose(d["cloud"]["tau"], 0.01 * d["scene_size"])
    assert d["mesh"]["accuracy"] > 0.85 and d["mesh"]["completeness"] > 0.5
    assert d["mesh"]["triangles"] == len(ws.load_dense_mesh()["triangles"])
    # without ground truth: each panorama's ranges against what the others predict (accurate maps agree)
    agreement = metrics["dense_agreement"]
    assert set(agreement["per_image"]) == set(dataset.image_names) and agreement["median_agreement"] > 0.8
    for name, m in agreement["per_image"].items():
        assert m["valid_share"] == pytest.approx(d["per_panorama"][name]["valid_share"], abs=0.05), name


def test_fusion_drops_a_corrupted_panorama(reconstructed):
    """Stage-level consistency: a panorama whose ranges are 30 % off finds no support, so the cloud stays accurate;
    without the check its points pollute the cloud."""
    dataset, ws, _ = reconstructed
    names = dataset.image_names
    maps = {k: (d["range"], d["valid"]) for k, d in enumerate(ws.load_depth(n) for n in names)}
    maps[2] = (maps[2][0] * 1.3, maps[2][1])
    poses = np.load(ws.path("sparse"))
    R, t, centers = poses["R_cam_from_world"], poses["t_cam_from_world"], poses["centers"]
    sparse = {"points": poses["points"]}
    images = {k: dataset.load_image(n, width=512) for k, n in enumerate(names)}
    R_gt, c_gt = _gt_poses(dataset)
    sim = umeyama(centers, c_gt)
    gt = [dataset.ground_truth_depth(n) for n in names]
    t_gt = -np.einsum("nab,nb->na", R_gt, c_gt)
    scene = float(np.load(dataset.ground_truth_dir / "scene.npz")["scene_size"])
    config = load_config(None, SMALL)["densify"]
    acc = {}
    for min_consistent in (1, 0):
        options = dataclasses.replace(config, min_consistent=min_consistent)
        pts = densify._fuse(options, images, maps, R, t, centers, sparse)[0]
        m = dense_metrics(range_est=[None] * 3, valid_est=[None] * 3, range_gt=gt, R_gt_cam_from_world=R_gt,
                          t_gt_cam_from_world=t_gt, sim=sim, points=pts, scene_size=scene, names=names)
        acc[min_consistent] = m["cloud"]["accuracy"]
    assert acc[1] > 0.85 and acc[0] < acc[1] - 0.1


# --------------------------------------------------------------------------------------------- pure parts
def test_combine_range_estimates():
    a = np.array([[2.0, 2.0, np.nan, 5.0, np.nan]], np.float32)
    b = np.array([[2.02, 3.0, 4.0, np.nan, np.nan]], np.float32)
    c = np.array([[1.98, 2.0, np.nan, np.nan, np.nan]], np.float32)
    rng, valid = dense.combine_range_estimates([a, b, c], rel_tol=0.02)
    # px0: three agree -> mean; px1: two of three agree; px2 / px3: single estimates kept; px4: none
    assert np.allclose(rng[0, :4], [2.0, 2.0, 4.0, 5.0], atol=1e-5) and valid.tolist() == [[True] * 4 + [False]]
    rng, valid = dense.combine_range_estimates([a, b], rel_tol=0.02)
    assert valid[0].tolist() == [True, False, True, True, False]  # 2 vs 3: a conflict is dropped
    assert np.isnan(rng[0, 1])
    single, ok = dense.combine_range_estimates([b], rel_tol=0.02)
    assert ok[0].tolist() == [True, True, True, False, False]
    # with confidences: the better-conditioned estimate dominates the agreeing ones (weights 1 / error²)
    err_a, err_c = np.full(a.shape, 0.001, np.float32), np.full(a.shape, 0.01, np.float32)
    rng, valid = dense.combine_range_estimates([a, c], rel_tol=0.02, errors=[err_a, err_c])
    assert abs(rng[0, 0] - (2.0 * 100 + 1.98) / 101) < 1e-5 and valid[0, 0]


def test_combined_estimates_use_the_order_statistics_np_sort_gives():
    """The few-estimate sorting network (invalid ones as +inf) holds at every position below a pixel's count of
    finite estimates what np.sort (NaN last) holds there: every pattern of NaN, ties and order of 2-4 estimates."""
    from fullview.sfm.dense.depth import _sorted_finite_first

    for n in (2, 3, 4):
        raw = np.array(list(itertools.product([np.nan, 1.0, 2.0, 2.0, 3.0], repeat=n)), np.float32).T
        reference, network = np.sort(raw, axis=0), _sorted_finite_first(raw)
        count = np.isfinite(raw).sum(0)
        for position in range(n):
            used = count > position
            assert np.array_equal(network[position, used], reference[position, used]), (n, position)


def test_mask_below_latitude():
    rng = np.ones((8, 16), np.float32)
    out, valid = dense.mask_below_latitude(rng, np.ones((8, 16), bool), -45.0)
    assert valid[:6].all() and not valid[6:].any() and np.isnan(out[6:]).all()  # rows 6, 7 centre below -45°


def test_pair_min_depth_ratio_is_capped():
    assert np.isclose(dense.pair_min_depth_ratio(4.0, 3.0, 1.0, 0.5, 45.0), 1.5)
    assert np.isclose(dense.pair_min_depth_ratio(1.0, 1.0, 1.0, 0.5, 45.0), np.sqrt(2))  # capped at 45°
    assert np.isclose(dense.pair_min_depth_ratio(np.nan, 2.0, 1.0, 1.0, 90.0), 2.0)


def test_fuse_depth_maps_views_subset_matches_full():
    rng = np.random.default_rng(0)
    Rs = np.stack([np.eye(3)] * 3)
    ts = -np.array([[0, 0, 0], [0.3, 0, 0], [0, 0, 0.3]], float)
    maps = [np.full((32, 64), 3.0, np.float32) + rng.normal(0, 0.001, (32, 64)).astype(np.float32) for _ in range(3)]
    imgs = [np.zeros((32, 64, 3), np.uint8)] * 3
    full, _, src = dense.fuse_depth_maps(maps, imgs, Rs, ts, min_consistent=0, return_sources=True)
    one, _ = dense.fuse_depth_maps(maps, imgs, Rs, ts, min_consistent=0, views=[1])
    assert np.array_equal(one, full[src == 1])


def test_voxel_downsample_means():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.51, 0.0, 0.0]])
    cols = np.array([[0, 0, 0], [100, 200, 50], [9, 9, 9]], np.uint8)
    out, c = voxel_downsample(pts, 0.1, cols)
    order = np.argsort(out[:, 0])
    assert np.allclose(out[order], [[0.02, 0.02, 0.02], [0.51, 0, 0]])
    assert c.dtype == np.uint8 and c[order].tolist() == [[50, 100, 25], [9, 9, 9]]


def test_range_map_errors_and_cloud_metrics():
    gt = np.full((16, 32), 2.0, np.float32)
    est = np.full((8, 16), 1.0, np.float32)  # half size, half scale
    valid = np.ones((8, 16), bool)
    valid[:4] = False
    m = range_map_errors(est, valid, gt, scale=2.0 * 1.01)
    assert np.isclose(m["median_rel_error"], 0.01, atol=1e-5) and np.isclose(m["valid_share"], 0.5)
    surface = backproject_range_map(gt, np.eye(3), np.zeros(3))
    assert np.allclose(np.linalg.norm(surface, axis=1), 2.0)
    shifted = surface[: len(surface) // 2] * 1.2  # half the sphere, 0.4 off
    c = cloud_accuracy_completeness(np.vstack([surface[: len(surface) // 2], shifted]), surface, tau=0.1)
    assert np.isclose(c["accuracy"], 0.5) and 0.4 < c["completeness"] < 0.6
    sim = Similarity(scale=2.0, R=np.eye(3), t=np.zeros(3))
    m = dense_metrics(range_est=[est], valid_est=[valid], range_gt=[gt], R_gt_cam_from_world=np.eye(3)[None],
                      t_gt_cam_from_world=np.zeros((1, 3)), sim=sim, points=surface / 2, scene_size=10.0,
                      names=["a"])
    assert m["cloud"]["accuracy"] == 1.0 and m["cloud"]["completeness"] > 0.95
    assert np.isclose(m["per_panorama"]["a"]["median_rel_error"], 0.0)


def test_render_point_cloud_and_colorize(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (5000, 3)) * [3, 1, 2]
    cols = rng.integers(0, 255, (5000, 3), dtype=np.uint8)
    path = render_point_cloud(tmp_path / "p.png", pts, cols, up=np.array([0, 1.0, 0]), panel_px=200,
                              cameras=np.zeros((2, 3)), title="t")
    img = cv2.imread(str(path))
    assert img.shape == (250, 600, 3) and img.std() > 5
    rmap = np.linspace(1, 5, 64 * 32, dtype=np.float32).reshape(32, 64)
    rmap[0, 0] = np.nan
    pic = colorize_range(rmap)
    assert pic.shape == (32, 64, 3) and not pic[0, 0].any() and pic[5:].any(axis=-1).all()


def _two_layers(upper_normal_z: float):
    """A blue 2 x 2 square at height 0 under a red 1 x 1 square at height 1 (dense grids), the red one listed
    last and first, with normals +z for the blue one and ``upper_normal_z`` for the red one."""
    g = np.linspace(-1, 1, 81)
    lower = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    upper = lower[(np.abs(lower) <= 0.5).all(1)]
    pts = np.vstack([np.c_[lower, np.zeros(len(lower))], np.c_[upper, np.ones(len(upper))]])
    cols = np.vstack([np.tile([0, 0, 255], (len(lower), 1)), np.tile([255, 0, 0], (len(upper), 1))]).astype(np.uint8)
    normals = np.vstack([np.tile([0, 0, 1.0], (len(lower), 1)), np.tile([0, 0, upper_normal_z], (len(upper), 1))])
    return pts, cols, normals


@pytest.mark.parametrize("reverse", [False, True])
def test_render_point_cloud_near_hides_far_and_culls_back_faces(tmp_path, reverse):
    """Seen from the top, the red square above hides the blue one below at the panel's centre, whatever the order
    of the points; once it faces down (normals -z) it is culled and the blue one shows there. The blue ring
    around shows in both, and the PNG has one panel_px square per view under the title band."""
    for upper_normal_z, centre_bgr in ((1.0, (0, 0, 255)), (-1.0, (255, 0, 0))):
        pts, cols, normals = _two_layers(upper_normal_z)
        order = slice(None, None, -1 if reverse else 1)
        path = render_point_cloud(tmp_path / "p.png", pts[order], cols[order], normals=normals[order],
                                  up=np.array([0, 0, 1.0]), views=(("top", 0.0, 90.0),), panel_px=120)
        img = cv2.imread(str(path))
        assert img.shape == (120 + 50, 120, 3)
        panel = img[50:]
        assert (panel[55:65, 55:65] == centre_bgr).all()
        assert (panel[60, 8:20] == (255, 0, 0)).all() and (panel[60, -20:-8] == (255, 0, 0)).all()


def test_render_mesh_culls_faces_turned_away(tmp_path):
    """A mesh of two stacked 2 x 2 grids seen from the top: the upper red one hides the lower blue one when its
    triangles face up (counter-clockwise from above) and is culled when they face down."""
    g = np.linspace(-1, 1, 21)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    i = (np.arange(20)[:, None] * 21 + np.arange(20)).ravel()  # lower-left corner of each quad
    up_tris = np.vstack([np.c_[i, i + 1, i + 22], np.c_[i, i + 22, i + 21]])  # counter-clockwise from above
    for turned, centre_bgr in ((False, (0, 0, 255)), (True, (255, 0, 0))):
        verts = np.vstack([np.c_[xy, np.zeros(len(xy))], np.c_[xy, np.ones(len(xy))]])
        tris = np.vstack([up_tris, (up_tris[:, ::-1] if turned else up_tris) + len(xy)])
        cols = np.vstack([np.tile([0, 0, 255], (len(xy), 1)), np.tile([255, 0, 0], (len(xy), 1))]).astype(np.uint8)
        path = render_mesh(tmp_path / "m.png", verts, tris, cols, up=np.array([0, 0, 1.0]),
                           views=(("top", 0.0, 90.0),), panel_px=100)
        img = cv2.imread(str(path)).astype(int)
        assert img.shape == (150, 100, 3)
        centre = img[50:][45:55, 45:55].reshape(-1, 3)
        drawn = centre.max(1) > 100  # triangle centres splatted: a few background pixels between them
        assert drawn.mean() > 0.5 and (np.argmax(centre[drawn], 1) == np.argmax(centre_bgr)).all(), turned


def test_range_error_per_pixel_matches_law_of_sines_derivative():
    from scipy.spatial.transform import Rotation
    from fullview.sfm.camera import pixel_grid_bearings
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    c_i, c_j = np.array([0.2, 0.1, -0.3]), np.array([1.0, 0.3, 0.1])
    rng_map = np.linspace(1.0, 6.0, 32 * 64, dtype=np.float32).reshape(32, 64)
    pixel_angle = np.pi / 512
    err = dense.range_error_per_pixel(rng_map, R, c_i, c_j, pixel_angle)
    w = pixel_grid_bearings(64, 32) @ R  # world directions of the pixel rays
    T = np.linalg.norm(c_j - c_i)
    theta = np.arccos(np.clip(w @ (c_j - c_i) / T, -1, 1))
    P = c_i + rng_map[..., None] * w
    a, b = c_i - P, c_j - P
    d = np.arccos(np.einsum("...k,...k", a, b) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1))
    r_of = lambda dd: T * np.sin(theta + dd) / np.sin(dd)
    assert np.allclose(r_of(d), rng_map, rtol=1e-4)  # the triangle is the law of sines' one
    h = 1e-6
    numeric = np.abs(r_of(d + h) - r_of(d - h)) / (2 * h) * pixel_angle / rng_map
    assert np.allclose(err, numeric, rtol=1e-3)
