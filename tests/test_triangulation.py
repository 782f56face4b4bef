"""Tests of fullview.sfm.triangulation: two-view midpoint, multi-view least squares, filtering."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm.camera import normalize
from fullview.sfm.tracks import Tracks, build_tracks
from fullview.sfm.triangulation import (
    _max_pair_angle,
    _pairs_within_tracks,
    angular_errors,
    filter_tracks,
    gather_bearings,
    reprojection_errors,
    triangulate_multiview,
    triangulate_two_view_midpoint,
)

NOISE_RAD = 0.0015  # ≈ 0.5 px at 2048 px width


def _scene(rng, num_cameras=6, num_points=300):
    """Cameras on a ring (random orientations) and points around them, at least 1 away from any centre."""
    ang = np.linspace(0, 2 * np.pi, num_cameras, endpoint=False)
    centers = np.stack([2 * np.cos(ang), 0.2 * rng.normal(size=num_cameras), 2 * np.sin(ang)], 1)
    R = Rotation.random(num_cameras, random_state=rng).as_matrix()
    t = -np.einsum("nij,nj->ni", R, centers)
    points = rng.uniform(-6, 6, size=(3 * num_points, 3))
    far = (np.linalg.norm(points[:, None] - centers[None], axis=2) > 1.0).all(1)
    return R, t, centers, points[far][:num_points]


def _project(R, t, points):
    """(N, P, 3) unit bearings of every point in every camera."""
    return normalize(np.einsum("nij,pj->npi", R, points) + t[:, None, :])


def _full_tracks(num_cameras, num_points) -> Tracks:
    """Every point seen by every camera, feature index = point index."""
    ident = np.stack([np.arange(num_points)] * 2, 1)
    matches = {(0, j): ident for j in range(1, num_cameras)}
    tracks, _ = build_tracks(matches, [num_points] * num_cameras)
    return tracks


def _track_points(tracks: Tracks) -> np.ndarray:
    """(T,) point index of each track (its feature index in any image)."""
    return tracks.feature_ids[tracks.offsets[:-1]]


def _noisy(bearings, rng, sigma=NOISE_RAD):
    return normalize(bearings + rng.normal(scale=sigma, size=bearings.shape))


def test_two_view_midpoint_exact_without_noise():
    rng = np.random.default_rng(0)
    R, t, _, X = _scene(rng, num_cameras=2)
    R21 = R[1] @ R[0].T
    t21 = t[1] - R21 @ t[0]
    x1 = X @ R[0].T + t[0]
    b = _project(R, t, X)
    res = triangulate_two_view_midpoint(b[0] * 3.0, b[1], R21, t21)  # any bearing norm
    np.testing.assert_allclose(res.points, x1, atol=1e-9)
    np.testing.assert_allclose(res.depth1, np.linalg.norm(x1, axis=1), rtol=1e-9)
    np.testing.assert_allclose(res.depth2, np.linalg.norm(X @ R[1].T + t[1], axis=1), rtol=1e-9)
    assert (res.parallax_rad > 0).all()


def test_two_view_depths_flag_points_behind():
    rng = np.random.default_rng(1)
    R, t, _, X = _scene(rng, num_cameras=2, num_points=50)
    R21, t21 = R[1] @ R[0].T, t[1] - R[1] @ R[0].T @ t[0]
    b = _project(R, t, X)
    res = triangulate_two_view_midpoint(-b[0], -b[1], R21, t21)  # both rays flipped: same lines
    assert (res.depth1 < 0).all() and (res.depth2 < 0).all()
    np.testing.assert_allclose(res.points, X @ R[0].T + t[0], atol=1e-9)


def test_two_view_parallel_rays_give_nan():
    b = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    res = triangulate_two_view_midpoint(b, b, np.eye(3), np.array([1.0, 0.0, 0.0]))
    assert np.isnan(res.points).all() and np.isnan(res.depth1).all()
    np.testing.assert_allclose(res.parallax_rad, 0.0, atol=1e-12)


def test_two_view_matches_multiview_for_two_cameras_with_noise():
    rng = np.random.default_rng(2)
    R, t, _, X = _scene(rng, num_cameras=2, num_points=200)
    b = _noisy(_project(R, t, X), rng, sigma=5 * NOISE_RAD)
    R21, t21 = R[1] @ R[0].T, t[1] - R[1] @ R[0].T @ t[0]
    two = triangulate_two_view_midpoint(b[0], b[1], R21, t21)
    tracks = _full_tracks(2, len(X))
    multi = triangulate_multiview(tracks, [b[0], b[1]], R, t)
    pts = _track_points(tracks)
    np.testing.assert_allclose(multi.points @ R[0].T + t[0], two.points[pts], atol=1e-9)
    assert np.abs(multi.points - X[pts]).max() > 1e-3  # the noise did change the points


def test_multiview_exact_without_noise_and_everything_kept():
    rng = np.random.default_rng(4)
    R, t, _, X = _scene(rng)
    b = _project(R, t, X)
    tracks = _full_tracks(len(R), len(X))
    res = triangulate_multiview(tracks, list(b), R, t)
    np.testing.assert_allclose(res.points, X[_track_points(tracks)], atol=1e-9)
    assert res.max_error_rad.max() < 1e-9 and res.positive_depth.all()
    keep = filter_tracks(res, max_error_rad=1e-6, min_angle_rad=np.deg2rad(1.0))
    assert keep.all()


def test_multiview_max_angle_is_the_largest_pairwise_ray_angle():
    rng = np.random.default_rng(5)
    R, t, centers, X = _scene(rng, num_cameras=5, num_points=40)
    tracks = _full_tracks(5, len(X))
    res = triangulate_multiview(tracks, list(_project(R, t, X)), R, t)
    for k, p in enumerate(_track_points(tracks)):
        rays = normalize(X[p] - centers)
        expected = max(np.arccos(np.clip(rays[i] @ rays[j], -1, 1)) for i, j in itertools.combinations(range(5), 2))
        assert res.max_angle_rad[k] == pytest.approx(expected, abs=1e-7)


def test_filter_removes_injected_outliers_and_keeps_noisy_inliers():
    rng = np.random.default_rng(6)
    R, t, _, X = _scene(rng, num_cameras=8, num_points=400)
    b = _noisy(_project(R, t, X), rng)
    outlier_points = rng.choice(len(X), size=40, replace=False)
    cams = rng.integers(0, len(R), size=len(outlier_points))
    b[cams, outlier_points] = normalize(rng.normal(size=(len(outlier_points), 3)))
    tracks = _full_tracks(len(R), len(X))
    res = triangulate_multiview(tracks, list(b), R, t)
    keep = filter_tracks(res, max_error_rad=0.01, min_angle_rad=np.deg2rad(1.0))
    is_outlier = np.isin(_track_points(tracks), outlier_points)
    assert not keep[is_outlier].any()
    assert keep[~is_outlier].all()
    err = np.linalg.norm(res.points[keep] - X[_track_points(tracks)[keep]], axis=1)
    assert np.median(err) < 0.01


def test_filter_removes_small_angle_and_behind_camera_tracks():
    rng = np.random.default_rng(7)
    R, t, centers, X = _scene(rng, num_cameras=4, num_points=100)
    X[:10] = 1e4 * normalize(rng.normal(size=(10, 3)))  # far away: tiny triangulation angle
    b = _noisy(_project(R, t, X), rng, sigma=1e-6)
    b[:, 10:20] *= -1.0  # every ray flipped: same lines, point behind every camera
    tracks = _full_tracks(4, len(X))
    res = triangulate_multiview(tracks, list(b), R, t)
    pts = _track_points(tracks)
    far, behind = pts < 10, (pts >= 10) & (pts < 20)
    assert (res.max_angle_rad[far] < np.deg2rad(0.1)).all()
    assert not res.positive_depth[behind].any() and res.positive_depth[~behind].all()
    keep = filter_tracks(res, max_error_rad=0.01, min_angle_rad=np.deg2rad(1.0))
    assert np.array_equal(keep, ~far & ~behind)
    assert filter_tracks(res, max_error_rad=4.0, min_angle_rad=np.deg2rad(1.0), require_positive_depth=False)[
        behind
    ].all()


def test_partial_tracks_and_gather_bearings():
    rng = np.random.default_rng(8)
    R, t, _, X = _scene(rng, num_cameras=5, num_points=60)
    b = _project(R, t, X)
    # Each image keeps its own shuffled feature order; tracks of varying length 2..5.
    perms = [rng.permutation(len(X)) for _ in range(5)]
    feats = [np.argsort(p) for p in perms]  # feats[i][point] = feature index of the point in image i
    bearings = [b[i][perms[i]] for i in range(5)]
    seen = rng.random((5, len(X))) < 0.6
    seen[:2] = True
    matches = {}
    for i, j in itertools.combinations(range(5), 2):
        both = np.flatnonzero(seen[i] & seen[j])
        matches[(i, j)] = np.stack([feats[i][both], feats[j][both]], 1)
    tracks, _ = build_tracks(matches, [len(X)] * 5)
    assert set(tracks.lengths.tolist()) >= {2, 5}
    got = gather_bearings(bearings, tracks.image_ids, tracks.feature_ids)
    point_of_obs = perms[0][tracks.feature_ids[tracks.offsets[:-1]]]  # image 0 is always in the track
    np.testing.assert_allclose(got, b[tracks.image_ids, np.repeat(point_of_obs, tracks.lengths)])
    res = triangulate_multiview(tracks, bearings, R, t)
    np.testing.assert_allclose(res.points, X[point_of_obs], atol=1e-9)
    with pytest.raises(ValueError, match="no bearing"):
        gather_bearings(bearings[:3], tracks.image_ids, tracks.feature_ids)


def test_pairs_within_tracks_lists_every_pair_once():
    lengths = np.array([2, 5, 3, 1, 4])
    offsets = np.r_[0, np.cumsum(lengths)]
    first, second = _pairs_within_tracks(offsets)
    expected = sorted(
        (int(o + i), int(o + j)) for o, n in zip(offsets[:-1], lengths) for i, j in itertools.combinations(range(n), 2)
    )
    assert sorted(zip(first.tolist(), second.tolist())) == expected
    first, second = _pairs_within_tracks(offsets[2:])  # a slice of the tracks keeps global indices
    assert sorted(zip(first.tolist(), second.tolist())) == [p for p in expected if p[0] >= offsets[2]]


@pytest.mark.parametrize("chunk_pairs", [1, 7, 10_000])
def test_max_pair_angle_in_chunks_matches_brute_force(chunk_pairs):
    rng = np.random.default_rng(9)
    lengths = rng.integers(1, 9, size=30)
    offsets = np.r_[0, np.cumsum(lengths)]
    rays = normalize(rng.normal(size=(offsets[-1], 3)) + [0, 0, 2])
    got = _max_pair_angle(rays, offsets, chunk_pairs=chunk_pairs)
    for k, (o, n) in enumerate(zip(offsets[:-1], lengths)):
        angles = [np.arccos(np.clip(rays[o + i] @ rays[o + j], -1, 1)) for i, j in itertools.combinations(range(n), 2)]
        assert got[k] == pytest.approx(max(angles, default=0.0), abs=1e-7)


def test_angular_and_reprojection_errors():
    assert angular_errors(np.array([[0, 0, 1.0]]), np.array([[0, 0, -5.0]]))[0] == pytest.approx(np.pi)
    assert angular_errors(np.array([[0, 0, 1.0]]), np.array([[0, 2.0, 2.0]]))[0] == pytest.approx(np.pi / 4)
    R = np.stack([np.eye(3), Rotation.from_euler("y", 90, degrees=True).as_matrix()])
    t = np.array([[0.0, 0, 0], [0, 0, 1.0]])
    pts = np.array([[0.0, 0, 2.0]])
    b = np.array([[0.0, 0, 1.0], [1.0, 0, 0]])
    err = reprojection_errors(R, t, pts, np.array([0, 1]), np.array([0, 0]), b)
    x1 = R[1] @ pts[0] + t[1]
    np.testing.assert_allclose(err, [0.0, np.arccos(x1[0] / np.linalg.norm(x1))], atol=1e-12)


def test_bad_pose_shapes_are_rejected():
    tracks = _full_tracks(3, 4)
    with pytest.raises(ValueError, match="poses"):
        triangulate_multiview(tracks, [np.eye(3)[[2, 2, 2, 2]]] * 3, np.stack([np.eye(3)] * 2), np.zeros((2, 3)))


def test_no_tracks_gives_empty_results():
    tracks, _ = build_tracks({}, [3, 3])
    res = triangulate_multiview(tracks, [np.eye(3)] * 2, np.stack([np.eye(3)] * 2), np.zeros((2, 3)))
    assert res.points.shape == (0, 3) and res.max_angle_rad.shape == (0,)
    assert filter_tracks(res, max_error_rad=0.01, min_angle_rad=0.01).shape == (0,)


def test_longest_tracks_per_image_keeps_each_images_longest():
    from fullview.sfm.tracks import build_tracks
    from fullview.sfm.triangulation import longest_tracks_per_image
    rng = np.random.default_rng(0)
    num_images, num_features = 5, 40
    matches = {}
    for i in range(num_images):
        for j in range(i + 1, num_images):
            f = rng.choice(num_features, size=25, replace=False)
            matches[(i, j)] = np.stack([f, f], 1)  # feature k of every image is one scene point
    tracks, _ = build_tracks(matches, [num_features] * num_images)
    per_image = 7
    keep = longest_tracks_per_image(tracks, per_image)
    lengths = tracks.lengths
    for image in range(num_images):
        mine = np.unique(tracks.track_ids[tracks.image_ids == image])
        kept = mine[keep[mine]]
        assert len(kept) >= min(per_image, len(mine))
        # no track of this image left out is longer than the shortest of its per_image longest
        best = np.sort(lengths[mine])[::-1][:per_image]
        assert lengths[mine[~keep[mine]]].max(initial=0) <= best.min()
    assert longest_tracks_per_image(tracks, 10**6).all()
