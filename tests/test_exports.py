"""Export writers: COLMAP (text and binary via pycolmap), nerfstudio transforms.json, PLY with normals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.io.artifacts import load_ply
from fullview.io.colmap import load_reconstruction, model_arrays, write_text_model
from fullview.io.exports import (SparseModel, nerfstudio_camera_to_world, point_errors_px, read_nerfstudio,
                                 sparse_point_normals, write_colmap_model, write_nerfstudio, write_point_cloud)
from fullview.sfm.camera import bearings_to_pixels, pixels_to_bearings

pycolmap = pytest.importorskip("pycolmap")

SIZES = [(512, 256), (512, 256), (400, 200), (512, 256), (400, 200)]  # image 3 unregistered
REGISTERED = np.array([True, True, True, False, True])


def make_model(seed: int = 0, sizes=SIZES, registered=REGISTERED, num_points: int = 30) -> SparseModel:
    """Random poses and points; each point seen by 2..N cameras (the unregistered one included), pixels by
    projecting through the equirectangular model, shuffled among extra unobserved features."""
    rng = np.random.default_rng(seed)
    n = len(sizes)
    R = Rotation.random(n, random_state=seed).as_matrix()
    centers = rng.normal(size=(n, 3))
    t = -np.einsum("nab,nb->na", R, centers)
    points = rng.normal(size=(num_points, 3)) * 5
    seen = rng.random((n, num_points)) < 0.6
    seen[np.flatnonzero(registered)[:2]] = True  # at least two registered observers per point
    pixels, obs = [], []
    for k, (w, h) in enumerate(sizes):
        idx = np.flatnonzero(seen[k])
        projected = bearings_to_pixels(points[idx] @ R[k].T + t[k], w, h)
        extra = rng.random((7, 2)) * [w, h]
        order = rng.permutation(len(idx) + len(extra))
        pixels.append(np.concatenate([projected, extra])[order])
        position = np.argsort(order)[:len(idx)]  # where each projected point landed
        obs.append(np.stack([idx, np.full(len(idx), k), position], axis=1))
    obs = np.concatenate(obs)
    return SparseModel(image_names=[f"pano_{k:03d}.jpg" for k in range(n)], image_sizes=list(sizes),
                       registered=np.asarray(registered), R_cam_from_world=R, t_cam_from_world=t, points=points,
                       colors=rng.integers(0, 256, (num_points, 3), dtype=np.uint8),
                       point_errors_rad=rng.random(num_points) * 0.01, track_point3d=obs[:, 0],
                       track_image=obs[:, 1], track_point2d=obs[:, 2], pixels=pixels)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_model_round_trips_through_pycolmap(tmp_path, binary):
    m = make_model()
    write_colmap_model(m, tmp_path, binary=binary)
    ext = ".bin" if binary else ".txt"
    assert all((tmp_path / f"{name}{ext}").exists() for name in ("cameras", "images", "points3D", "rigs", "frames"))
    rec = pycolmap.Reconstruction(tmp_path)
    reg = np.flatnonzero(m.registered)
    assert rec.num_reg_images() == len(reg) == rec.num_images() and rec.num_cameras() == 2
    for k in reg:
        image = rec.images[int(k) + 1]
        cam = rec.cameras[image.camera_id]
        assert image.name == m.image_names[k] and cam.model.name == "EQUIRECTANGULAR"
        assert (cam.width, cam.height) == m.image_sizes[k]
        pose = image.cam_from_world()
        assert np.allclose(pose.rotation.matrix(), m.R_cam_from_world[k], rtol=0, atol=1e-9)
        assert np.allclose(pose.translation, m.t_cam_from_world[k], rtol=0, atol=1e-9)
        assert np.allclose([p.xy for p in image.points2D], m.pixels[k], rtol=0, atol=1e-9)
    assert rec.num_points3D() == len(m.points)
    keep = m.registered[m.track_image]
    errors_px = point_errors_px(m)
    for p in range(len(m.points)):
        point = rec.points3D[p + 1]
        assert np.allclose(point.xyz, m.points[p], rtol=0, atol=1e-9)
        assert np.array_equal(point.color, m.colors[p])
        assert point.error == pytest.approx(errors_px[p], abs=1e-9)  # pixels, as COLMAP's ERROR
        sel = keep & (m.track_point3d == p)
        expected = set(zip((m.track_image[sel] + 1).tolist(), m.track_point2d[sel].tolist()))
        assert {(e.image_id, e.point2D_idx) for e in point.track.elements} == expected
        assert len(expected) >= 2
    # COLMAP's own camera model projects the points onto the stored pixels: same pixel convention
    for k in reg:
        image = rec.images[int(k) + 1]
        for el_idx in image.get_observation_point2D_idxs():
            p2d = image.points2D[int(el_idx)]
            proj = rec.cameras[image.camera_id].img_from_cam(image.cam_from_world() * rec.points3D[p2d.point3D_id].xyz)
            assert np.allclose(proj, p2d.xy, atol=1e-6)


def test_colmap_formats_replace_each_other(tmp_path):
    """A text export over a binary one removes the .bin files, which pycolmap would read first."""
    m = make_model(seed=1)
    write_colmap_model(m, tmp_path, binary=True)
    m.points = m.points + 1.0
    write_colmap_model(m, tmp_path, binary=False)
    assert not list(tmp_path.glob("*.bin")) and not list(tmp_path.glob(".colmap.*"))
    assert np.allclose(pycolmap.Reconstruction(tmp_path).points3D[1].xyz, m.points[0], atol=1e-9)


def test_write_text_model_keeps_its_signature_and_files(tmp_path):
    m = make_model(seed=2)
    out = write_text_model(tmp_path / "colmap", image_sizes=m.image_sizes, image_names=m.image_names,
                           registered=m.registered, R_cam_from_world=m.R_cam_from_world,
                           t_cam_from_world=m.t_cam_from_world, points=m.points, colors=m.colors,
                           errors_rad=m.point_errors_rad, track_image=m.track_image, track_point2d=m.track_point2d,
                           track_point3d=m.track_point3d, pixels=m.pixels)
    assert {"cameras.txt", "images.txt", "points3D.txt"} <= {p.name for p in out.iterdir()}
    arrays = model_arrays(load_reconstruction(out), m.image_names)
    assert arrays["registered"].tolist() == m.registered.tolist()
    assert np.allclose(arrays["centers"][m.registered], m.centers[m.registered], atol=1e-9)


def test_bad_tracks_are_named(tmp_path):
    m = make_model(seed=3)
    m.track_point2d = m.track_point2d.copy()
    m.track_point2d[0] = 10_000
    with pytest.raises(ValueError, match="track_point2d"):
        write_colmap_model(m, tmp_path, binary=False)
    m = make_model(seed=3)
    with pytest.raises(ValueError, match="image_paths"):
        write_nerfstudio(m, tmp_path, image_paths=["a.jpg"])


def test_nerfstudio_round_trip_and_convention(tmp_path):
    m = make_model(seed=4)
    paths = [f"images/{name}" for name in m.image_names]
    write_nerfstudio(m, tmp_path, image_paths=paths)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    reg = np.flatnonzero(m.registered)
    assert meta["camera_model"] == "EQUIRECTANGULAR" and "w" not in meta  # two sizes: per-frame intrinsics
    assert [f["file_path"] for f in meta["frames"]] == [paths[k] for k in reg]
    assert np.allclose(meta["applied_transform"], np.eye(4)[:3])
    for f, k in zip(meta["frames"], reg):
        w, h = m.image_sizes[k]
        assert (f["w"], f["h"], f["fl_x"], f["fl_y"], f["cx"], f["cy"]) == (w, h, w / 2, h, w / 2, h / 2)
        M = np.array(f["transform_matrix"])
        assert np.array_equal(M[3], [0, 0, 0, 1])
        assert np.allclose(M[:3, :3].T @ M[:3, :3], np.eye(3), atol=1e-12) and np.linalg.det(M[:3, :3]) > 0
        R_world_from_cam = m.R_cam_from_world[k].T
        assert np.allclose(-M[:3, 2], R_world_from_cam @ [0, 0, 1], atol=1e-12)  # looks along our +z
        assert np.allclose(M[:3, 1], R_world_from_cam @ [0, -1, 0], atol=1e-12)  # up = our −y
        # nerfstudio's EQUIRECTANGULAR ray (cameras.py) of every feature equals our world bearing
        x, y = m.pixels[k].T
        cx_, cy_ = (x - f["cx"]) / f["fl_x"], -(y - f["cy"]) / f["fl_y"]
        theta, phi = -np.pi * cx_, np.pi * (0.5 - cy_)
        d_gl = np.stack([-np.sin(theta) * np.sin(phi), np.cos(phi), -np.cos(theta) * np.sin(phi)], axis=1)
        assert np.allclose(d_gl @ M[:3, :3].T, pixels_to_bearings(m.pixels[k], w, h) @ R_world_from_cam.T,
                           atol=1e-12)
    names, R, centers = read_nerfstudio(tmp_path / "transforms.json")
    assert names == [paths[k] for k in reg]
    assert np.allclose(R, m.R_cam_from_world[reg], rtol=0, atol=1e-9)
    assert np.allclose(centers, m.centers[reg], rtol=0, atol=1e-9)
    forward = np.einsum("nba,b->na", R, [0, 0, 1])
    assert np.allclose(forward, np.einsum("nba,b->na", m.R_cam_from_world[reg], [0, 0, 1]), atol=1e-9)
    ply = load_ply(tmp_path / meta["ply_file_path"])
    assert np.allclose(np.stack([ply["x"], ply["y"], ply["z"]], 1), m.points, atol=1e-5)
    assert np.array_equal(np.stack([ply["red"], ply["green"], ply["blue"]], 1), m.colors)


def test_nerfstudio_shared_size_is_top_level_and_applied_transform_undone(tmp_path):
    m = make_model(seed=5, sizes=[(512, 256)] * 5)
    write_nerfstudio(m, tmp_path, image_paths=m.image_names)
    path = tmp_path / "transforms.json"
    meta = json.loads(path.read_text())
    assert (meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"]) == (512, 256, 256, 256, 256, 128)
    assert all("w" not in f and "fl_x" not in f for f in meta["frames"])
    # a file re-oriented the way ns-process-data does it (x, z, −y) reads back in the original world frame
    A = np.eye(4)[[0, 2, 1, 3]]
    A[2] *= -1
    for f in meta["frames"]:
        f["transform_matrix"] = (A @ np.array(f["transform_matrix"])).tolist()
    meta["applied_transform"] = A[:3].tolist()
    path.write_text(json.dumps(meta))
    _, R, centers = read_nerfstudio(path)
    reg = np.flatnonzero(m.registered)
    assert np.allclose(R, m.R_cam_from_world[reg], atol=1e-9) and np.allclose(centers, m.centers[reg], atol=1e-9)


def test_camera_to_world_inverts_pose():
    m = make_model(seed=6)
    M = nerfstudio_camera_to_world(m.R_cam_from_world, m.t_cam_from_world)
    x_world = np.array([0.3, -1.2, 2.0])
    x_cam = m.R_cam_from_world @ x_world + m.t_cam_from_world  # our axes
    x_gl = x_cam * [1, -1, -1]
    assert np.allclose(np.einsum("nab,nb->na", M[:, :3, :3], x_gl) + M[:, :3, 3], x_world, atol=1e-12)


def test_point_cloud_with_normals_facing_the_cameras(tmp_path):
    rng = np.random.default_rng(7)
    floor = np.c_[rng.uniform(-5, 5, (200, 2)), np.zeros(200)]  # plane z = 0
    wall = np.c_[rng.uniform(-5, 5, 200), np.full(200, 6.0), rng.uniform(0.5, 4, 200)]  # plane y = 6
    points = np.concatenate([floor, wall])
    centers = np.array([[0, 0, 1.5], [1, 1, 1.5], [np.nan] * 3])  # last camera unregistered
    normals = sparse_point_normals(points, centers)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)
    assert np.median(normals[:200, 2]) > 0.99 and np.median(-normals[200:, 1]) > 0.99
    # with tracks: every point seen by camera 1 only, normals face camera 1
    tracked = sparse_point_normals(points, centers, track_point3d=np.arange(400), track_image=np.ones(400, int))
    assert (np.einsum("pa,pa->p", tracked, centers[1] - points) > 0).all()
    colors = rng.integers(0, 256, (400, 3), dtype=np.uint8)
    write_point_cloud(tmp_path / "sparse.ply", points, colors, normals)
    ply = load_ply(tmp_path / "sparse.ply")
    assert b"binary_little_endian" in (tmp_path / "sparse.ply").read_bytes()[:100]
    assert np.allclose(np.stack([ply["nx"], ply["ny"], ply["nz"]], 1), normals, atol=1e-6)
    assert np.array_equal(np.stack([ply["red"], ply["green"], ply["blue"]], 1), colors)
    with pytest.raises(ValueError, match="normals"):
        write_point_cloud(tmp_path / "bad.ply", points, colors, normals[:3])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_direct_colmap_text_points_equal_pycolmap_files(tmp_path, seed):
    """The text model we format ourselves is byte for byte what pycolmap writes for the model."""
    from fullview.io.exports import _text_points_writable, build_reconstruction

    m = make_model(seed, num_points=200)
    rng = np.random.default_rng(seed)
    # values whose %.17g forms differ: negative zero, integers, tiny and huge coordinates
    m.points[:4] = [[-0.0, 1.0, 2.5], [1e-300, -3e12, 7.0], [0.1, 0.2, 0.3], [np.pi, -np.e, 1e-7]]
    m.point_errors_rad[:2] = [0.0, 1e-9]
    m.pixels[0][:2] = [[0.0, 0.5], [1023.999, 1e-5]]
    m.points[4:] += rng.normal(size=m.points[4:].shape)
    assert _text_points_writable(m)
    ours = write_colmap_model(m, tmp_path / "ours", binary=False)
    (tmp_path / "theirs").mkdir()
    build_reconstruction(m).write_text(tmp_path / "theirs")
    for name in ("cameras", "images", "points3D", "rigs", "frames"):
        assert (ours / f"{name}.txt").read_bytes() == (tmp_path / "theirs" / f"{name}.txt").read_bytes(), name


def test_colmap_text_falls_back_to_pycolmap_for_a_point_without_registered_observations(tmp_path):
    from fullview.io.exports import _text_points_writable, build_reconstruction

    m = make_model(3)
    unregistered = np.flatnonzero(~np.asarray(m.registered))
    assert len(unregistered)
    alone = m.track_point3d[0]
    m.track_image[m.track_point3d == alone] = unregistered[0]
    m.track_point2d[m.track_point3d == alone] = 0
    assert not _text_points_writable(m)
    ours = write_colmap_model(m, tmp_path / "ours", binary=False)
    (tmp_path / "theirs").mkdir()
    build_reconstruction(m).write_text(tmp_path / "theirs")
    for name in ("images", "points3D"):
        assert (ours / f"{name}.txt").read_bytes() == (tmp_path / "theirs" / f"{name}.txt").read_bytes(), name


def test_quaternions_are_bitwise_pycolmaps():
    """Poses are written from our own matrix-to-quaternion conversion: it must be pycolmap's to the last bit, on
    both branches (trace > 0 or not) and on matrices a little off orthonormal, as after bundle adjustment."""
    from fullview.io.exports import _quaternions_wxyz

    R = Rotation.random(3000, random_state=7).as_matrix()
    R[:1500] += np.random.default_rng(7).normal(scale=1e-12, size=(1500, 3, 3))
    R[0], R[1] = np.eye(3), np.diag([1.0, -1.0, -1.0])  # trace 3 and -1
    trace = np.trace(R, axis1=1, axis2=2)
    assert (trace > 0).any() and (trace <= 0).any()
    theirs = np.array([pycolmap.Rotation3d(m).quat for m in R])  # x, y, z, w
    assert np.array_equal(_quaternions_wxyz(R), theirs[:, [3, 0, 1, 2]])
