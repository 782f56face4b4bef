import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fullview.sfm import dense
from fullview.sfm.camera import normalize, pixel_grid_bearings

# --------------------------------------------------------------------------------------------- synthetic renderer
ROOM_MIN = np.array([-3.0, -1.5, -2.5])  # box-shaped room (world units: metres), y down like the cameras
ROOM_MAX = np.array([4.0, 1.5, 3.0])
PILLAR_MIN = np.array([1.2, -1.5, 0.8])  # a free-standing box inside the room (occlusions, depth edges)
PILLAR_MAX = np.array([1.8, 0.6, 1.5])


def _noise_layers(seed, cells, extent=12.0):
    """Per-surface random grids for multi-scale value noise (one list of (cell, grid) per surface id)."""
    rng = np.random.default_rng(seed)
    return [[(c, rng.random((int(extent / c) + 4,) * 2).astype(np.float32)) for c in cells] for _ in range(12)]


def _bicubic(grid, x, y):
    """cv2.remap bicubic sampling of ``grid`` at flat coordinate arrays (folded into rows of 4096)."""
    n = len(x)
    pad = -n % 4096
    fold = lambda a: np.concatenate([a, np.zeros(pad)]).astype(np.float32).reshape(-1, 4096)
    return cv2.remap(grid, fold(x), fold(y), cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT).ravel()[:n]


def _texture(u, v, surface, layers):
    """Smooth multi-scale noise at wall coordinates (u, v) (metres), per surface id, values in [0, 255]."""
    out = np.zeros(u.shape, np.float32)
    for s in np.unique(surface):
        m = surface == s
        acc = np.zeros(m.sum(), np.float32)
        for k, (cell, grid) in enumerate(layers[s]):
            gx, gy = (u[m] + 6.0) / cell + 1.0, (v[m] + 6.0) / cell + 1.0
            acc += _bicubic(grid, gx, gy) / (1.0 + 0.3 * k)
        out[m] = acc
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / (hi - lo) * 230 + 12, 0, 255)


def _slab(center, dirs, bmin, bmax):
    """Ray/box slab intersection: (t_enter, t_exit, axis of entry, axis of exit)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (bmin - center) / dirs
        t2 = (bmax - center) / dirs
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    return tmin.max(-1), tmax.min(-1), tmin.argmax(-1), tmax.argmin(-1)


def cast(center, dirs):
    """Ranges, hit points and surface ids of world rays (unit dirs) from ``center`` in the room with a pillar."""
    _, t_wall, _, axis = _slab(center, dirs, ROOM_MIN, ROOM_MAX)
    surface = 2 * axis + (np.take_along_axis(dirs, axis[..., None], -1)[..., 0] > 0)
    t_in, t_out, axis_in, _ = _slab(center, dirs, PILLAR_MIN, PILLAR_MAX)
    hit = (t_in <= t_out) & (t_in > 0) & (t_in < t_wall)
    t = np.where(hit, t_in, t_wall)
    surface = np.where(hit, 6 + 2 * axis_in + (np.take_along_axis(dirs, axis_in[..., None], -1)[..., 0] > 0), surface)
    return t, center + t[..., None] * dirs, surface, np.where(hit, axis_in, axis)


def render(R_cam_from_world, center, width, layers, supersample=2, flat=()):
    """(grey uint8 panorama, ground-truth range map) of the textured room seen from ``center``; surfaces listed in
    ``flat`` are a uniform grey."""
    def shade(w):
        dirs = pixel_grid_bearings(w, w // 2) @ R_cam_from_world  # world directions: R_camᵀ b (row-vector form)
        t, p, surface, axis = cast(center, dirs)
        u = np.where(axis == 0, p[..., 2], p[..., 0])
        v = np.where(axis == 1, p[..., 2], p[..., 1])
        tex = _texture(u, v, surface, layers)
        tex[np.isin(surface, flat)] = 128.0
        return tex, t

    img, _ = shade(width * supersample)
    img = cv2.resize(img, (width, width // 2), interpolation=cv2.INTER_AREA)
    _, rng = shade(width)
    return img.round().astype(np.uint8), rng


def make_pair(width, seed=0, baseline=(0.45, 0.08, 0.25), cells=(0.6, 0.25, 0.1, 0.04), flat=()):
    """Two rendered panoramas with random orientations and known poses (R_cam_from_world, t_cam_from_world)."""
    rng = np.random.default_rng(seed)
    layers = _noise_layers(seed, cells)
    c_i = np.array([-0.3, 0.1, -0.2])
    c_j = c_i + np.asarray(baseline)
    out = []
    for c in (c_i, c_j):
        R = Rotation.from_rotvec(rng.normal(size=3) * 0.6).as_matrix()
        img, gt = render(R, c, width, layers, flat=flat)
        out.append((img, gt, R, -R @ c))
    return out


# --------------------------------------------------------------------------------------------- tests
def _random_poses(seed):
    rng = np.random.default_rng(seed)
    Rs = Rotation.random(2, random_state=seed).as_matrix()
    cs = rng.normal(size=(2, 3))
    return Rs, np.einsum("nab,nb->na", -Rs, cs), cs


def test_rectifying_rotation_aligns_baseline_with_pole():
    Rs, ts, cs = _random_poses(1)
    R = dense.rectifying_rotation(cs[0], cs[1], Rs[0])
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R @ normalize(cs[1] - cs[0]), [0, -1, 0], atol=1e-12)


def test_epipolar_circles_are_rows_and_theta_grows():
    Rs, ts, cs = _random_poses(2)
    n_phi, n_theta = 1024, 512
    img = np.zeros((n_theta, n_phi), np.uint8)
    pair = dense.rectify_pair(img, img, Rs[0], ts[0], Rs[1], ts[1], height=n_theta, width=n_phi)
    P = np.random.default_rng(3).normal(size=(500, 3)) * 5
    b_i = (P - cs[0]) @ Rs[0].T  # bearings in camera frames
    b_j = (P - cs[1]) @ Rs[1].T
    uv_i = dense.bearings_to_rectified(b_i, pair.R_rect_from_cam_i, n_phi, n_theta)
    uv_j = dense.bearings_to_rectified(b_j, pair.R_rect_from_cam_j, n_phi, n_theta)
    drow = np.abs(uv_i[:, 1] - uv_j[:, 1])
    drow = np.minimum(drow, n_phi - drow)  # rows wrap around
    pole = np.minimum(uv_i[:, 0], n_theta - uv_i[:, 0]) < 1  # the plane is undefined on the epipole itself
    assert drow[~pole].max() < 1e-6
    assert np.all(uv_j[:, 0] >= uv_i[:, 0] - 1e-9)  # θ_j = θ_i + d with d ≥ 0
    # exact law of sines on the same points
    theta_i, theta_j = uv_i[:, 0] * np.pi / n_theta, uv_j[:, 0] * np.pi / n_theta
    r = dense.depth_from_disparity(theta_i, theta_j - theta_i, pair.baseline)
    assert np.allclose(r, np.linalg.norm(P - cs[0], axis=1), rtol=1e-7)


def test_rectified_image_matches_rendering_in_rectified_frame():
    (img_i, _, R_i, t_i), (img_j, _, R_j, t_j) = make_pair(512, seed=4, cells=(0.6, 0.25, 0.1))
    pair = dense.rectify_pair(img_i, np.dstack([img_j] * 3), R_i, t_i, R_j, t_j)  # grey and 3-channel inputs
    assert pair.rect_i.shape == (512, 256) and pair.rect_j.shape == (512, 256, 3)
    pair.rect_j = pair.rect_j[..., 1]
    layers = _noise_layers(4, (0.6, 0.25, 0.1))
    for rect, c in ((pair.rect_i, pair.center_i), (pair.rect_j, pair.center_j)):
        # the rectified image is the equirectangular view of the rectified camera, transposed
        direct, _ = render(pair.R_rect_from_world, c, 512, layers)
        err = np.abs(rect.astype(float) - direct.T.astype(float))
        assert np.median(err) < 3.0 and np.percentile(err, 90) < 12.0


def test_depth_from_disparity_known_triangle():
    T = 2.0
    # right triangle: P straight "above" O_j at height h -> θ_i = atan2(h, T), θ_j = π/2, |O_i P| = hypot(T, h)
    h = np.array([0.5, 1.0, 3.0, 10.0])
    theta_i = np.arctan2(h, T)
    d = np.pi / 2 - theta_i
    assert np.allclose(dense.depth_from_disparity(theta_i, d, T), np.hypot(T, h), rtol=1e-12)
    # isoceles: P on the bisector plane at distance s from both centres: θ_i = acos(T/2s), θ_j = π − θ_i
    s = 3.0
    th = np.arccos(T / 2 / s)
    assert np.isclose(dense.depth_from_disparity(th, np.pi - 2 * th, T), s, rtol=1e-12)
    assert np.isnan(dense.depth_from_disparity(0.3, 0.0, T))


def test_rectified_range_maps_equal_the_law_of_sines_bit_for_bit():
    """The in-place law of sines of ``rectified_range_maps`` equals ``depth_from_disparity`` cast to float32 on
    both grids: NaN, zero and negative disparities, ranges that come out negative (θ + d > π), SGBM's 1/16-pixel
    steps."""
    from fullview.sfm.dense.disparity import DisparityResult
    from fullview.sfm.dense.rectify import theta_of_columns
    rng = np.random.default_rng(5)
    n_phi, n_theta = 64, 256
    pixel_angle = np.pi / n_theta
    maps = []
    for _ in range(2):
        d = (rng.integers(-16, 16 * 80, size=(n_phi, n_theta)) / 16).astype(np.float32) * np.float32(pixel_angle)
        d[rng.random(d.shape) < 0.2] = np.nan
        d[:, -20:] = np.float32(1.2)  # near the anti-epipole: sin(θ + d) < 0
        maps.append(d)
    disp = DisparityResult(disparity_i=maps[0], disparity_j=maps[1], valid_i=np.isfinite(maps[0]),
                           valid_j=np.isfinite(maps[1]), num_disparities=80, pixel_angle=pixel_angle)
    theta = theta_of_columns(n_theta)[None, :]
    range_i, range_j = dense.rectified_range_maps(disp, 1.7)
    want_i = dense.depth_from_disparity(theta, maps[0], 1.7).astype(np.float32)
    want_j = dense.depth_from_disparity(np.pi - theta, maps[1], 1.7).astype(np.float32)
    assert range_i.dtype == range_j.dtype == np.float32
    assert range_i.tobytes() == want_i.tobytes() and range_j.tobytes() == want_j.tobytes()
    assert np.isnan(range_i[:, -20:]).any() and np.isfinite(range_i).mean() > 0.5


def test_pad_theta_is_spherically_continuous():
    n_phi, n_theta = 64, 32
    grid = dense.rectified_grid_bearings(n_phi, n_theta)
    padded = dense.pad_theta(grid, 5, 7)
    theta = (np.arange(-5, n_theta + 7) + 0.5) * np.pi / n_theta
    phi = 2 * np.pi * ((np.arange(n_phi) + 0.5) / n_phi - 0.5)
    th, ph = np.meshgrid(theta, phi)
    expected = np.stack([np.sin(th) * np.sin(ph), -np.cos(th), np.sin(th) * np.cos(ph)], -1)
    assert np.allclose(padded, expected, atol=1e-12)


def test_search_range():
    assert dense.disparity_search_range(1024, 2.0) == 176  # asin(0.5) = 30° = 170.7 px -> 176
    assert dense.disparity_search_range(256, 1000.0) == 16
    with pytest.raises(ValueError, match="min_depth_ratio"):
        dense.disparity_search_range(256, 0.0)


@pytest.fixture(scope="module")
def rendered_pair():
    return make_pair(512, seed=0, cells=(0.6, 0.25, 0.1))


def test_end_to_end_depth_accuracy(rendered_pair):
    (img_i, gt_i, R_i, t_i), (img_j, gt_j, R_j, t_j) = rendered_pair
    res = dense.densify_pair(img_i, img_j, R_i, t_i, R_j, t_j, min_depth_ratio=1.5)
    for rng, valid, gt in ((res.range_i, res.valid_i, gt_i), (res.range_j, res.valid_j, gt_j)):
        rel = np.abs(rng[valid] - gt[valid]) / gt[valid]
        assert valid.mean() > 0.5
        assert np.median(rel) < 0.03
        assert np.mean(rel < 0.1) > 0.9


def test_disparity_direction_and_invalid_near_epipoles(rendered_pair):
    (img_i, _, R_i, t_i), (img_j, _, R_j, t_j) = rendered_pair
    pair = dense.rectify_pair(img_i, img_j, R_i, t_i, R_j, t_j)
    disp = dense.compute_disparity(pair.rect_i, pair.rect_j, min_depth_ratio=1.5, min_epipole_angle_deg=10)
    cols = int(np.ceil(10 / 180 * pair.n_theta))
    assert not disp.valid_i[:, : cols - 1].any() and not disp.valid_i[:, -cols + 1 :].any()
    assert np.all(disp.disparity_i[disp.valid_i] > 0)
    # swapping the roles (wrong direction) must not give a comparably consistent result
    swapped = dense.compute_disparity(pair.rect_j, pair.rect_i, min_depth_ratio=1.5, min_epipole_angle_deg=10)
    assert swapped.valid_i.mean() < 0.5 * disp.valid_i.mean()


def test_untextured_surfaces_are_rejected():
    (img_i, gt_i, R_i, t_i), (img_j, _, R_j, t_j) = make_pair(512, seed=6, cells=(0.6, 0.25, 0.1), flat=(2, 3))
    res = dense.densify_pair(img_i, img_j, R_i, t_i, R_j, t_j, min_depth_ratio=1.5)
    _, _, surface, _ = cast(-R_i.T @ t_i, pixel_grid_bearings(512, 256) @ R_i)
    flat = np.isin(surface, (2, 3))  # floor and ceiling (without the texture test ~1/3 of them pass, mostly wrong)
    assert 0.2 < flat.mean() < 0.9
    assert res.valid_i[flat].mean() < 0.15 and res.valid_i[~flat].mean() > 0.8
    rel = np.abs(res.range_i - gt_i) / gt_i
    assert np.median(rel[res.valid_i & ~flat]) < 0.03


def test_range_map_to_panorama_roundtrip():
    Rs, ts, cs = _random_poses(5)
    img = np.zeros((128, 256), np.uint8)
    pair = dense.rectify_pair(img, img, Rs[0], ts[0], Rs[1], ts[1])
    # smooth analytic range on the rectified grid, with a step edge
    grid = dense.rectified_grid_bearings(pair.n_phi, pair.n_theta)
    b_cam = grid @ pair.R_rect_from_cam_i  # camera-frame bearings of rectified pixels
    truth = lambda b: 2.0 + b[..., 0] + 3.0 * (b[..., 2] > 0.3)
    for mode in ("nearest", "edge_aware"):
        pano, valid = dense.range_map_to_panorama(truth(b_cam), pair.R_rect_from_cam_i, width=256, interpolation=mode)
        expected = truth(pixel_grid_bearings(256, 128))
        assert valid.all()
        err = np.abs(pano - expected)
        assert np.median(err) < 0.02
        assert np.mean(err > 0.5) < 0.02  # only pixels on the step itself may take the other side
        assert np.all((err < 0.1) | (np.abs(err - 3.0) < 0.1))  # never a blend across the step


def test_range_map_to_panorama_on_the_rows_within_the_latitude_caps_only():
    # the rows a latitude cap masks are left invalid; every other row has the values of the whole map, bit for bit
    Rs, ts, _ = _random_poses(5)
    img = np.zeros((512, 1024), np.uint8)
    pair = dense.rectify_pair(img, img, Rs[0], ts[0], Rs[1], ts[1])
    grid = dense.rectified_grid_bearings(pair.n_phi, pair.n_theta)
    ranges = (2.0 + (grid @ pair.R_rect_from_cam_i)[..., 0]).astype(np.float32)
    ranges[::7] = np.nan
    whole, whole_valid = dense.range_map_to_panorama(ranges, pair.R_rect_from_cam_i, width=1024)
    rows = dense.depth.latitude_rows(512, -65.0, 80.0)
    part, part_valid = dense.range_map_to_panorama(ranges, pair.R_rect_from_cam_i, width=1024, rows=rows)
    masked, masked_valid = dense.mask_below_latitude(whole, whole_valid, -65.0, 80.0)
    assert 0 < rows.start and rows.stop < 512 and (rows.stop - rows.start) % dense.depth.BACKMAP_ROWS
    assert part.tobytes() == masked.tobytes() and np.array_equal(part_valid, masked_valid)
    assert not part_valid[:rows.start].any() and part_valid[rows].mean() > 0.5


def _fusion_scene():
    """Three cameras in the room with exact range maps (256x128)."""
    layers = _noise_layers(0, (0.6,))
    Rs = Rotation.from_rotvec(np.random.default_rng(0).normal(size=(3, 3)) * 0.4).as_matrix()
    cs = np.array([[0.0, 0.0, 0.0], [0.5, 0.1, 0.0], [-0.4, 0.0, 0.5]])
    imgs, ranges = zip(*[render(R, c, 256, layers, supersample=1) for R, c in zip(Rs, cs)])
    return list(imgs), [r.astype(np.float32) for r in ranges], Rs, np.einsum("nab,nb->na", -Rs, cs)


def test_fusion_keeps_consistent_and_rejects_inconsistent():
    imgs, ranges, Rs, ts = _fusion_scene()
    pts, cols = dense.fuse_depth_maps(ranges, imgs, Rs, ts, min_consistent=2, rel_tol=0.02)
    n = sum(r.size for r in ranges)
    assert len(pts) > 0.8 * n and cols.shape == (len(pts), 3) and cols.dtype == np.uint8
    # fused points lie on the room surfaces: ray-cast from camera 0 towards them recovers their distance
    d = pts - (-Rs[0].T @ ts[0])
    t, _, _, _ = cast(-Rs[0].T @ ts[0], normalize(d))
    assert np.median(np.abs(t - np.linalg.norm(d, axis=1))) < 1e-3
    # corrupt view 2 (scaled by 1.3): its points are rejected, the other two views still support each other
    bad = [ranges[0], ranges[1], ranges[2] * 1.3]
    pts2, _, src = dense.fuse_depth_maps(bad, imgs, Rs, ts, min_consistent=1, rel_tol=0.02, return_sources=True)
    assert np.sum(src == 2) < 0.02 * ranges[2].size
    assert np.sum(src == 0) > 0.8 * ranges[0].size
    pts3, _ = dense.fuse_depth_maps(bad, imgs, Rs, ts, min_consistent=2, rel_tol=0.02)
    assert len(pts3) < 0.05 * n


def test_clean_point_cloud_removes_outliers_and_gives_normals():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (4000, 2)), np.zeros(4000)]
    outliers = rng.uniform(-1, 1, (40, 3)) + [0, 0, 3]
    pts = np.vstack([plane, outliers])
    cols = rng.integers(0, 255, (len(pts), 3), dtype=np.uint8)
    p, c, n = dense.clean_point_cloud(pts, cols, voxel_size=0.02, nb_neighbors=20, std_ratio=2.0)
    assert len(p) == len(c) == len(n) and c.dtype == np.uint8
    assert np.abs(p[:, 2]).max() < 1e-9  # every outlier gone
    assert np.allclose(np.abs(n[:, 2]), 1.0, atol=1e-6)


def test_select_stereo_pairs():
    centers = np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0], [1.02, 0, 0], [5.0, 0, 0]], float)
    inl = np.array(
        [
            [0, 300, 200, 210, 10],
            [300, 0, 400, 380, 20],
            [200, 400, 0, 900, 5],
            [210, 380, 900, 0, 5],
            [10, 20, 5, 5, 0],
        ]
    )
    pairs = dense.select_stereo_pairs(centers, inl, k=1, min_triangulation_angle_deg=3.0, scene_depths=np.full(5, 3.0))
    # (2, 3) has most inliers but a 2 cm baseline (0.4° at 3 m): excluded; camera 4 has too few inliers
    assert {tuple(p) for p in pairs} == {(0, 1), (1, 2), (1, 3)}
    assert np.all(pairs[:, 0] < pairs[:, 1])
    with pytest.raises(ValueError, match="inlier_counts"):
        dense.select_stereo_pairs(centers, inl[:4], k=1, min_triangulation_angle_deg=3.0)


def test_stereo_partners_spread_over_baseline_directions():
    # camera 0 with three strong partners on one line (their epipoles coincide) and a weaker one across: with
    # separation, the second partner is the one across, so every pixel has a partner whose epipole is elsewhere
    from fullview.sfm.dense.pairs import _diverse_partners
    centers = np.array([[0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [2.0, 0, 0], [0, 0, 1.0]], float)
    score = np.full((5, 5), -np.inf)
    score[0, 1:] = [900, 800, 700, 100]
    assert list(_diverse_partners(centers, score, 2, 0.0)[0]) == [1, 2]
    assert list(_diverse_partners(centers, score, 2, 30.0)[0]) == [1, 4]
    assert list(_diverse_partners(centers, score, 3, 30.0)[0]) == [1, 4, 2]  # then the best remaining
    assert list(_diverse_partners(centers, score, 2, 30.0)[1]) == [-1, -1]  # no candidates
    # through select_stereo_pairs
    inl = np.zeros((5, 5), int)
    inl[0, 1:] = inl[1:, 0] = [900, 800, 700, 100]
    pairs = dense.select_stereo_pairs(centers, inl, k=2, min_triangulation_angle_deg=3.0, min_inliers=50,
                                      scene_depths=np.full(5, 3.0), min_epipole_separation_deg=30.0)
    assert {tuple(p) for p in pairs} == {(0, 1), (0, 2), (0, 3), (0, 4)}  # each other camera's only partner is 0


def test_partner_in_another_direction_removes_the_epipole_stripe():
    # one partner leaves the pixels around its epipoles without depth (a stripe along the line of cameras); a second
    # partner in another direction fills them, and the confidence-weighted combination keeps them accurate
    layers = _noise_layers(0, (0.6, 0.25, 0.1))
    centers = np.array([[-0.3, 0.1, -0.2], [0.15, 0.1, -0.2], [-0.3, 0.1, 0.25]])  # partners along x and along z
    views = [render(np.eye(3), c, 384, layers) + (np.eye(3), -c) for c in centers]
    (img0, gt0, R0, t0) = views[0]
    estimates, errors = [], []
    for img, _, R, t in views[1:]:
        res = dense.densify_pair(img0, img, R0, t0, R, t, min_depth_ratio=1.5)
        err = dense.range_error_per_pixel(res.range_i, R0, -t0, -t, np.pi / 192)
        rng = np.where(err <= 0.2, res.range_i, np.nan)  # 384 px: a pixel of disparity is a coarse step
        estimates.append(rng)
        errors.append(err)
    lon, lat = np.meshgrid(np.linspace(-np.pi, np.pi, 384, endpoint=False) + np.pi / 384,
                           np.pi / 2 - (np.arange(192) + 0.5) * np.pi / 192)
    bearing = np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], -1)
    near_x_epipole = np.abs(bearing[..., 0]) > np.cos(np.radians(12))  # within 12° of the x partner's epipoles
    single, _ = dense.combine_range_estimates(estimates[:1], 0.02)
    both, ok = dense.combine_range_estimates(estimates, 0.02, errors)
    assert np.isfinite(single[near_x_epipole]).mean() < 0.05  # the stripe
    assert ok[near_x_epipole].mean() > 0.5  # filled by the other partner
    rel = np.abs(both[ok] - gt0[ok]) / gt0[ok]
    assert np.median(rel) < 0.02 and np.mean(rel < 0.1) > 0.9


@pytest.mark.parametrize("min_consistent", [1, 2])
def test_fusion_stops_checking_a_point_once_kept_with_the_kept_set_of_counting_every_view(min_consistent):
    """A point is checked by the next view only while short of min_consistent supports: the kept points are the ones
    counting every view's support gives (the reference written out here), whatever the views' disagreements."""
    from fullview.sfm.camera import pixels_to_bearings
    from fullview.sfm.dense.fusion import _pixel_centers, _support, _valid_range

    imgs, ranges, Rs, ts = _fusion_scene()
    rng = np.random.default_rng(3)
    noisy = [r * np.where(rng.random(r.shape) < 0.3, 1.05, 1.0).astype(np.float32) for r in ranges]
    noisy += [ranges[0] * np.float32(1.3)]
    R4, t4 = np.concatenate([Rs, Rs[:1]]), np.concatenate([ts, ts[:1] + 0.05])
    imgs4 = list(imgs) + [imgs[0]]
    got, _, src = dense.fuse_depth_maps(noisy, imgs4, R4, t4, min_consistent=min_consistent, rel_tol=0.02,
                                        return_sources=True)
    kept = total = 0
    for i, rmap in enumerate(noisy):
        rows, cols = _pixel_centers(*rmap.shape, 1)
        keep = _valid_range(rmap[rows, cols])
        rows, cols = rows[keep], cols[keep]
        x_cam = pixels_to_bearings(np.stack([cols + 0.5, rows + 0.5], 1), rmap.shape[1], rmap.shape[0]) \
            * rmap[rows, cols][:, None]
        pts = (x_cam - t4[i]) @ R4[i]
        count = sum(_support(pts, noisy[k], R4[k], t4[k], 0.02).astype(int) for k in range(len(noisy)) if k != i)
        expected = pts[count >= min_consistent]
        assert np.array_equal(got[src == i], expected)
        kept, total = kept + len(expected), total + len(pts)
    assert 0.05 * total < kept < 0.95 * total  # the checks decided: neither all kept nor all dropped


def test_clean_point_cloud_names_the_rows_it_keeps():
    """Without down-sampling the cleaned points are input rows, in order (the stage finds each point's observing
    camera on the merged cloud while it is cleaned and keeps these rows of it)."""
    rng = np.random.default_rng(1)
    pts = np.vstack([np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)], rng.uniform(-1, 1, (30, 3)) + [0, 0, 3]])
    pts = pts[rng.permutation(len(pts))]
    cols = rng.integers(0, 255, (len(pts), 3), dtype=np.uint8)
    p, c, n, kept = dense.clean_point_cloud(pts, cols, voxel_size=0.0, nb_neighbors=20, std_ratio=2.0,
                                            normal_radius=0.1, return_index=True)
    assert np.array_equal(p, pts[kept]) and np.array_equal(c, cols[kept]) and np.all(np.diff(kept) > 0)
    assert len(kept) == 3000 and np.abs(p[:, 2]).max() < 1e-9
    with pytest.raises(ValueError, match="voxel_size 0"):
        dense.clean_point_cloud(pts, cols, voxel_size=0.02, return_index=True)


def test_forward_warp_equals_the_row_column_version():
    """``disparity._forward_warp`` (flat indices) equals the straightforward version with (row, column) indices
    written out here, bit for bit: collisions (the largest disparity wins), targets past the last column, NaN,
    halves rounded to even."""
    from fullview.sfm.dense.disparity import _forward_warp
    rng = np.random.default_rng(11)
    disp = (rng.integers(0, 16 * 40, size=(32, 96)) / 16).astype(np.float32)
    disp[rng.random(disp.shape) < 0.3] = np.nan
    disp[:, -8:] = 30.5  # beyond the grid
    rows, cols = np.nonzero(np.isfinite(disp))
    d = disp[rows, cols]
    target = np.rint(cols + d).astype(np.intp)
    inside = (target >= 0) & (target < disp.shape[1])
    want = np.full(disp.size, -np.inf, np.float32)
    np.maximum.at(want, rows[inside] * disp.shape[1] + target[inside], d[inside])
    want = np.where(np.isfinite(want), want, np.nan).reshape(disp.shape)
    got = _forward_warp(disp)
    assert got.tobytes() == want.tobytes()
    assert np.isfinite(got).mean() > 0.3
