"""The trimmed Poisson mesh of the dense stage (`fullview.sfm.dense.mesh`): accurate on a box room, trimmed where the
views see through it, reproducible."""

import numpy as np
import pytest

from fullview.sfm.camera import pixel_grid_bearings
from fullview.sfm.dense.mesh import MeshParams, mesh_from_dense, view_support
from fullview.sfm.dense_metrics import backproject_range_map, voxel_downsample
from fullview.stages.protocol import forked

ROOM_MIN, ROOM_MAX = np.array([-3.0, -1.5, -2.5]), np.array([3.0, 1.5, 2.5])  # a box room, y down
CENTERS = np.array([[-1.2, 0.0, -0.8], [1.0, 0.1, -0.5], [0.2, -0.1, 1.1]])
WIDTH = 160
VOXEL = 0.1
BLOB_CENTER, BLOB_RADIUS = np.array([1.8, 0.2, -0.5]), 0.4  # a fake blob of points in front of camera 1


def box_range_map(center, width=WIDTH):
    """Range from `center` (inside the room) to its walls for every pixel of an identity-rotation panorama."""
    dirs = pixel_grid_bearings(width, width // 2).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.where(dirs > 0, (ROOM_MAX - center) / dirs, (ROOM_MIN - center) / dirs)
    return t.min(1).reshape(width // 2, width).astype(np.float32)


def box_normals(points):
    """Inward normals of the walls the points lie on (towards the cameras)."""
    gap = np.stack([points - ROOM_MIN, ROOM_MAX - points], 1)  # (N, 2, 3)
    side, axis = np.unravel_index(gap.reshape(len(points), -1).argmin(1), (2, 3))
    normals = np.zeros_like(points)
    normals[np.arange(len(points)), axis] = np.where(side == 0, 1.0, -1.0)
    return normals


def distance_to_box(points):
    inside = np.minimum(points - ROOM_MIN, ROOM_MAX - points)
    return np.abs(inside).min(1)


@pytest.fixture(scope="module")
def room():
    R = np.repeat(np.eye(3)[None], len(CENTERS), 0)
    t = -CENTERS
    maps = [box_range_map(c) for c in CENTERS]
    points = np.concatenate([backproject_range_map(m, R[k], t[k]) for k, m in enumerate(maps)])
    points = voxel_downsample(points, VOXEL)[0]
    colors = np.clip((points - ROOM_MIN) / (ROOM_MAX - ROOM_MIN) * 255, 0, 255).astype(np.uint8)
    return points, colors, box_normals(points), R, t, maps


def test_mesh_of_a_box_room_is_accurate_and_complete(room):
    points, colors, normals, R, t, maps = room
    mesh = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL)
    assert len(mesh.triangles) > 1000
    d = distance_to_box(mesh.vertices)
    assert np.percentile(d, 99) < VOXEL and d.max() < 3 * VOXEL
    # every wall sample has mesh nearby: the trims removed nothing the views support
    dist, _ = _nearest(mesh.vertices, points)
    assert np.mean(dist < 2 * VOXEL) > 0.99
    # colours come from the nearest dense points
    _, idx = _nearest(mesh.vertices, points, reverse=True)
    assert np.array_equal(mesh.vertex_colors, colors[idx])
    assert mesh.stats["triangles"] == len(mesh.triangles) and 0 <= mesh.stats["trimmed_share"] < 0.2


def test_normals_of_either_sign_give_the_same_mesh(room):
    points, colors, normals, R, t, maps = room
    flipped = normals * np.where(np.random.default_rng(2).random(len(normals)) < 0.5, -1.0, 1.0)[:, None]
    a = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL)
    b = mesh_from_dense(points, colors, flipped, R, t, maps, voxel_size=VOXEL)
    assert a.vertices.tobytes() == b.vertices.tobytes() and a.triangles.tobytes() == b.triangles.tobytes()


def test_a_blob_the_views_see_through_is_trimmed(room):
    points, colors, normals, R, t, maps = room
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    blob = BLOB_CENTER + BLOB_RADIUS * dirs  # dense points the range maps do not have: they see the walls behind
    all_points = np.concatenate([points, blob])
    all_normals = np.concatenate([normals, dirs])
    all_colors = np.concatenate([colors, np.full((len(blob), 3), 200, np.uint8)])
    mesh = mesh_from_dense(all_points, all_colors, all_normals, R, t, maps, voxel_size=VOXEL)
    near_blob = np.linalg.norm(mesh.vertices - BLOB_CENTER, axis=1) < 1.5 * BLOB_RADIUS
    assert not near_blob.any()
    assert mesh.stats["trimmed_by_visibility"] > 200  # Poisson did make the blob; the views removed it
    # ... and without the range maps nothing would have removed it
    kept = mesh_from_dense(all_points, all_colors, all_normals, R, t, [None] * 3, voxel_size=VOXEL)
    assert (np.linalg.norm(kept.vertices - BLOB_CENTER, axis=1) < 1.5 * BLOB_RADIUS).any()


def test_view_support_free_space_and_occlusion():
    maps = [box_range_map(c) for c in CENTERS[:1]]
    R, t = np.eye(3)[None], -CENTERS[:1]
    wall = np.array([[3.0, 0.0, 0.0]])  # on the wall: observed
    free = np.array([[2.0, 0.0, -0.3]])  # between the camera and the wall: seen through
    ok = view_support(np.concatenate([wall, free]), R, t, maps, tolerance=0.03, window_px=3)
    assert ok.tolist() == [True, False]


def test_mesh_is_reproducible(room):
    points, colors, normals, R, t, maps = room
    a = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6))
    b = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6))
    assert a.vertices.tobytes() == b.vertices.tobytes() and a.triangles.tobytes() == b.triangles.tobytes()
    assert a.vertex_colors.tobytes() == b.vertex_colors.tobytes()


def test_poisson_in_a_child_process_gives_the_same_mesh(room):
    """The stage runs Poisson in a forked child (open3d holds the GIL): the same vertices, triangles and colours."""
    points, colors, normals, R, t, maps = room
    here = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6))
    child = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6),
                            poisson=forked)
    for a, b in ((here.vertices, child.vertices), (here.triangles, child.triangles),
                 (here.vertex_colors, child.vertex_colors)):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    assert here.stats == child.stats


def test_observing_cameras_found_beforehand_give_the_same_mesh(room):
    """The stage finds each point's observing camera while the cloud is cleaned and hands them over."""
    from fullview.sfm.dense.mesh import nearest_observing_cameras

    points, colors, normals, R, t, maps = room
    observers = nearest_observing_cameras(points, R, t, maps, tolerance=0.03, window_px=3)
    assert (observers >= 0).mean() > 0.95
    here = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6))
    given = mesh_from_dense(points, colors, normals, R, t, maps, voxel_size=VOXEL, params=MeshParams(depth=6),
                            observers=observers)
    assert here.vertices.tobytes() == given.vertices.tobytes() and here.triangles.tobytes() == given.triangles.tobytes()
    # they are what turns the normals: a camera outside the room (no map), named for every point, turns the wall
    # facing it outwards
    from fullview.sfm.dense.mesh import orient_normals_to_views

    R4, t4 = np.concatenate([R, R[:1]]), np.concatenate([t, [[0.0, 0.0, -10.0]]])
    inward = orient_normals_to_views(points, normals, R4, t4, list(maps) + [None], tolerance=0.03, window_px=3)
    outward = orient_normals_to_views(points, normals, R4, t4, list(maps) + [None], tolerance=0.03, window_px=3,
                                      observers=np.full(len(points), 3))
    assert np.mean(np.einsum("na,na->n", inward, outward) < 0) > 0.05  # the wall between them and it


def _nearest(a, b, reverse=False):
    from scipy.spatial import cKDTree
    return cKDTree(a).query(b) if not reverse else cKDTree(b).query(a)


def test_mesh_ply_round_trip_and_corruption(tmp_path):
    from fullview.io.artifacts import ArtifactError, load_mesh_ply, save_mesh_ply
    rng = np.random.default_rng(1)
    vertices, colors = rng.random((7, 3)), rng.integers(0, 256, (7, 3)).astype(np.uint8)
    triangles = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6]])
    path = save_mesh_ply(tmp_path / "m.ply", vertices, triangles, colors)
    mesh = load_mesh_ply(path)
    assert np.array_equal(mesh["triangles"], triangles) and np.array_equal(mesh["colors"], colors)
    assert np.allclose(mesh["vertices"], vertices, atol=1e-7)
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(ArtifactError, match="m.ply: corrupt mesh PLY"):
        load_mesh_ply(path)


def test_mesh_samples_are_uniform_on_the_surface():
    from fullview.sfm.dense_metrics import sample_mesh_surface
    # a 2 x 1 rectangle in z = 0 made of one large and two small triangles: samples follow area, not triangles
    vertices = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0], [1, 1, 0]], float)
    triangles = np.array([[0, 1, 2], [0, 2, 4], [0, 4, 3]])
    samples = sample_mesh_surface(vertices, triangles, 0.02)
    assert len(samples) == 5000 and np.all(samples[:, 2] == 0)
    assert samples[:, 0].min() >= 0 and samples[:, 0].max() <= 2 and samples[:, 1].min() >= 0
    hist = np.histogram2d(samples[:, 0], samples[:, 1], bins=(4, 2), range=((0, 2), (0, 1)))[0]
    assert hist.min() > 0.8 * hist.mean()
    assert np.array_equal(samples, sample_mesh_surface(vertices, triangles, 0.02))


def test_normals_turn_to_the_nearest_observing_camera_as_a_pass_over_every_view_finds(room):
    """Each point asks its cameras nearest first and stops at the first that observes it: the same normals as the
    pass over every view written out here (the nearest observing camera, ties to the lower index; none observing:
    the nearest camera), with a blob no map observes, a camera twice (a tie) and a view without a map."""
    from scipy.spatial import cKDTree

    from fullview.sfm.dense.mesh import (_pixel_index, _window_ranges, nearest_observing_cameras,
                                         orient_normals_to_views)

    points, _, normals, R, t, maps = room
    rng = np.random.default_rng(1)
    blob = BLOB_CENTER + BLOB_RADIUS * rng.normal(size=(500, 3)) / 2
    points = np.concatenate([points, blob])
    normals = np.concatenate([normals, rng.normal(size=(500, 3))]) * rng.choice([-1.0, 1.0], (len(points), 1))
    R4, t4 = np.concatenate([R, R[:1], R[:1]]), np.concatenate([t, t[:1], t[:1] + 0.3])
    maps4 = list(maps) + [maps[0], None]  # camera 3 is camera 0 again; camera 4 has no map
    got = orient_normals_to_views(points, normals, R4, t4, maps4, tolerance=0.03, window_px=3)
    chosen = nearest_observing_cameras(points, R4, t4, maps4, tolerance=0.03, window_px=3)
    centers = -np.einsum("kba,kb->ka", R4, t4)
    best, towards = np.full(len(points), np.inf), np.zeros_like(points)
    camera = np.full(len(points), -1)
    for k, rmap in enumerate(maps4):
        if rmap is None:
            continue
        near, far, _ = _window_ranges(rmap, 3)
        dist = np.linalg.norm(centers[k] - points, axis=1)
        idx = _pixel_index(points @ R4[k].T + t4[k], rmap.shape)
        seen = (near.ravel()[idx] <= dist * 1.03) & (far.ravel()[idx] >= dist * 0.97)
        better = seen & (dist < best)
        best[better], towards[better], camera[better] = dist[better], centers[k] - points[better], k
    assert np.array_equal(chosen, camera) and np.sum(camera == 3) == 0 and np.sum(camera == 0) > 100
    assert len(np.unique(camera)) == 4  # -1 and the three room cameras
    unseen = ~np.isfinite(best)
    assert 100 < unseen.sum() < len(blob) + 0.05 * len(points)  # the blob, and a few points on the room's edges
    towards[unseen] = centers[cKDTree(centers).query(points[unseen])[1]] - points[unseen]
    expected = np.where((np.einsum("na,na->n", normals, towards) < 0)[:, None], -normals, normals)
    assert np.array_equal(got, expected)


@pytest.mark.parametrize("cell_voxels", [2.0, 4.0, 5.5])
def test_automatic_poisson_depth_gives_cells_of_about_the_asked_width(cell_voxels):
    from fullview.sfm.dense.mesh import POISSON_SCALE, auto_poisson_depth

    points = np.random.default_rng(0).uniform(-3.0, 3.0, (1000, 3))
    extent = float(np.max(points.max(0) - points.min(0))) * POISSON_SCALE
    for voxel in (0.005, 0.01, 0.013, 0.02):
        cell = extent / 2 ** auto_poisson_depth(points, voxel, cell_voxels)
        assert cell_voxels / 2 < cell / voxel <= cell_voxels


@pytest.mark.parametrize("window", [1, 3, 5])
def test_window_extremes_at_pixels_are_the_filtered_maps_values(window):
    """The nearest / farthest valid range of a pixel's window read off its pixels equals the filtered maps' value
    there, at the seam (columns wrap), at the poles (rows clamp) and next to invalid pixels (NaN, 0, negative)."""
    from fullview.sfm.dense.mesh import _window_extremes_at, _window_ranges

    rng = np.random.default_rng(window)
    rmap = rng.uniform(1.0, 5.0, (40, 80)).astype(np.float32)
    rmap[rng.random(rmap.shape) < 0.2] = np.nan
    rmap[rng.random(rmap.shape) < 0.05] = 0.0
    rmap[rng.random(rmap.shape) < 0.05] = -1.0
    rmap[8:17, 18:27] = np.nan  # a window with no valid range
    idx = np.concatenate([rng.integers(0, rmap.size, 500), [0, 79, 80 * 39, rmap.size - 1, 12 * 80 + 22]])
    near, far, _ = _window_ranges(rmap, window)
    got_near, got_far = _window_extremes_at(rmap, idx, window)
    assert np.array_equal(got_near, near.ravel()[idx]) and np.array_equal(got_far, far.ravel()[idx])
    assert np.isinf(got_near[-1]) and got_near.dtype == np.float32
