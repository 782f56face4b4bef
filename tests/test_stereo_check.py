"""The stereo check of densify (``densify.stereo_check``): a range resting on one pair that another panorama sees
through is dropped; the partner's copy of the same disparity is no confirmation."""

from __future__ import annotations

import numpy as np
import pytest

from fullview.sfm import dense


@pytest.fixture(scope="module")
def room(small_room):
    ranges, R, t = small_room
    return [r.astype(np.float32) for r in ranges], R, t


def test_single_partner_names_the_only_pair_of_a_pixel():
    a = np.array([[1.0, np.nan, 2.0, np.nan]], np.float32)
    b = np.array([[np.nan, np.nan, 2.0, 3.0]], np.float32)
    assert dense.single_partner([a, b], [7, 9]).tolist() == [[7, -1, -1, 9]]


def _too_near_patch(room):
    """View 0 with a patch 10% too near resting on its pair with view 1, and view 1 holding the same wrong points
    (the same disparity, carried over), resting on its pair with view 0."""
    ranges, R, t = room
    maps = [r.copy() for r in ranges]
    singles = [np.full(r.shape, -1, np.int32) for r in ranges]
    patch = (slice(60, 80), slice(100, 140))
    maps[0][patch] *= 0.9
    singles[0][:] = 1  # every range of view 0 comes from its pair with view 1 alone
    center0 = -R[0].T @ t[0]
    rows, cols = np.mgrid[patch]
    from fullview.sfm.camera import bearings_to_pixels, pixels_to_bearings
    bearings = pixels_to_bearings(np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], 1), 256, 128)
    points = center0 + (bearings * maps[0][rows, cols].reshape(-1, 1)) @ R[0]
    x1 = points @ R[1].T + t[1]
    uv = bearings_to_pixels(x1, 256, 128).astype(np.intp)
    maps[1][uv[:, 1], uv[:, 0]] = np.linalg.norm(x1, axis=1)
    singles[1][uv[:, 1], uv[:, 0]] = 0
    return maps, singles, R, t, patch


def test_a_range_another_view_sees_through_is_dropped(room):
    maps, singles, R, t, patch = _too_near_patch(room)
    drop = dense.seen_through_single_estimates(maps, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02,
                                               views=[0])[0]
    assert drop[patch].mean() > 0.8  # views 2 and 3 see the wall behind the floating points
    outside = np.ones(drop.shape, bool)
    outside[patch] = False
    assert drop[outside].mean() < 0.02  # the exact ranges: confirmed or not judged


def test_the_partner_of_the_same_pair_is_no_confirmation(room):
    maps, singles, R, t, patch = _too_near_patch(room)  # (5%: view 1 holds the copies to a pixel)
    drop = dense.seen_through_single_estimates(maps, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.05,
                                               views=[0])[0]
    # the same maps with view 1's copies counted as independent (another pair): the patch is confirmed and stays
    other = [s.copy() for s in singles]
    other[1][other[1] == 0] = -1
    kept = dense.seen_through_single_estimates(maps, other, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.05,
                                               views=[0])[0]
    assert drop[patch].mean() > 0.8 > 0.2 > kept[patch].mean()


def test_a_range_resting_on_two_pairs_or_judged_by_no_view_is_kept(room):
    maps, singles, R, t, patch = _too_near_patch(room)
    singles[0][:] = -1  # two pairs agreed on every range
    assert not dense.seen_through_single_estimates(maps, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02,
                                                   views=[0])[0].any()
    maps, singles, R, t, patch = _too_near_patch(room)
    empty = [maps[0]] + [np.full_like(m, np.nan) for m in maps[1:]]
    assert not dense.seen_through_single_estimates(empty, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02,
                                                   views=[0])[0].any()


def test_conflicting_estimates_are_those_combine_drops():
    a = np.array([[1.0, 1.0, 1.0, np.nan]], np.float32)
    b = np.array([[1.0, 1.5, np.nan, 2.0]], np.float32)
    c = np.array([[np.nan, 2.5, np.nan, 2.0]], np.float32)
    pixels, candidates = dense.conflicting_estimates([a, b, c], 0.02)
    _, valid = dense.combine_range_estimates([a, b, c], 0.02)
    assert pixels.tolist() == [1] and not valid.ravel()[1] and valid.ravel()[[0, 2, 3]].all()
    assert candidates[:, 0].tolist() == [1.0, 1.5, 2.5]


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5])
def test_combine_with_conflicts_finds_the_conflicts_found_on_the_whole_map(n):
    # rows past several of combine's blocks; estimates that agree, conflict, or are missing, with and without errors
    rng = np.random.default_rng(n)
    shape = (2 * 64 + 37, 29)
    truth = rng.uniform(1.0, 5.0, shape).astype(np.float32)
    estimates, errors = [], []
    for _ in range(n):
        e = truth * rng.choice([1.0, 1.005, 1.3, 0.6], shape).astype(np.float32)
        e[rng.random(shape) < 0.3] = np.nan
        estimates.append(e)
        errors.append(rng.uniform(0.001, 0.1, shape).astype(np.float32))
    # the conflicts as found on the whole map at once (the stage's former second pass)
    raw = np.stack([e.ravel() for e in estimates])
    several = np.flatnonzero(np.isfinite(raw).sum(0) >= 2)
    conflict = dense.depth._agreement_with_median(raw[:, several], 0.02)[2].sum(0) < 2
    for errs in (None, errors):
        _, valid, pixels, candidates = dense.combine_with_conflicts(estimates, 0.02, errs)
        assert pixels.tolist() == several[conflict].tolist()
        assert candidates.shape == (n, len(pixels))
        assert candidates.tobytes() == raw[:, several[conflict]].tobytes()
        assert not valid.ravel()[pixels].any()
    if n >= 2:
        assert 0 < len(pixels) < len(several)


def test_a_third_view_settles_conflicting_estimates(room):
    ranges, R, t = room
    maps = [r.copy() for r in ranges]
    singles = [np.full(r.shape, -1, np.int32) for r in ranges]
    pixels = np.arange(60 * 256 + 100, 60 * 256 + 140)  # a row of view 0 whose two pairs (with 1 and 2) conflict
    truth = ranges[0].ravel()[pixels]
    maps[0].ravel()[pixels] = np.nan
    candidates = np.stack([1.1 * truth, truth])  # the pair with view 1 is 10% too far there
    got, values = dense.resolve_conflicts(maps, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02, 0, pixels,
                                          candidates, [1, 2])
    assert len(got) > 0.5 * len(pixels)  # (the rest: nearest pixels of 1.4° at oblique views, neither confirmed)
    np.testing.assert_allclose(values, ranges[0].ravel()[got], rtol=1e-6)  # always the right one
    # no view can judge: nothing is settled
    blind = [maps[0]] + [np.full_like(m, np.nan) for m in maps[1:]]
    assert len(dense.resolve_conflicts(blind, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02, 0, pixels,
                                       candidates, [1, 2])[0]) == 0
    # the right estimate held by its own partner alone (the same pair's disparity): no confirmation, a tie
    only_partner = [maps[0], np.full_like(maps[1], np.nan), maps[2], np.full_like(maps[3], np.nan)]
    partner_singles = [s.copy() for s in singles]
    partner_singles[2][:] = 0
    assert len(dense.resolve_conflicts(only_partner, partner_singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02, 0,
                                       pixels, candidates, [1, 2])[0]) == 0


def test_a_range_behind_another_views_surface_is_dropped_with_its_points(room):
    ranges, R, t = room
    maps = [r.copy() for r in ranges]
    singles = [np.full(r.shape, -1, np.int32) for r in ranges]
    patch = (slice(60, 80), slice(100, 140))
    maps[0][patch] *= 1.1  # too far: behind the wall, where no view can see through it
    singles[0][:] = 1
    from fullview.sfm.dense_metrics import backproject_range_map
    points = [backproject_range_map(m, R[k], t[k]) for k, m in enumerate(maps)]
    args = (maps, singles, [0, 1, 2, 3], R, t, [[1, 2, 3]] * 4, 0.02)
    without = dense.seen_through_single_estimates(*args, views=[0])[0]
    with_points = dense.seen_through_single_estimates(*args, views=[0], points=points)[0]
    assert with_points[patch].mean() > 0.8 > 0.2 > without[patch].mean()
    outside = np.ones(with_points.shape, bool)
    outside[patch] = False
    assert with_points[outside].mean() < 0.02


def test_pixel_indices_and_nearest_range_where_equal_the_full_splat():
    """The stereo check's projections (``fusion.pixel_rows_cols``, ``fusion.nearest_range_where``) give the
    pixels ``bearings_to_pixels`` gives and, at every wanted pixel, the value ``splat_nearest`` gives, to the
    last bit: points across the seam and the poles, several on one pixel, one at the camera centre."""
    from fullview.sfm.camera import bearings_to_pixels
    from fullview.sfm.dense.fusion import nearest_range_where, pixel_rows_cols
    from fullview.sfm.dense_metrics import splat_nearest
    rng = np.random.default_rng(3)
    height, width = 64, 128
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    t = rng.normal(size=3)
    center = -R.T @ t
    points = center + rng.normal(size=(20000, 3)) * rng.uniform(0.1, 5.0, size=(20000, 1))
    points[:50] = points[50:100]  # duplicates: ties on one pixel
    points[100] = center  # no direction: skipped by both
    pole = R.T @ np.array([0.0, -1.0, 0.0])
    points[101:110] = center + np.outer(np.linspace(1, 2, 9), pole)
    seam = R.T @ np.array([-1e-12, 0.0, -1.0])
    points[110:120] = center + np.outer(np.linspace(1, 2, 10), seam)
    x_cam = points @ R.T + t
    norm = np.linalg.norm(x_cam, axis=1)
    seen = norm > 0
    pix = bearings_to_pixels(x_cam[seen], width, height)
    rows, cols = pixel_rows_cols(x_cam[seen], norm[seen], width, height)
    assert np.array_equal(rows, np.clip(pix[:, 1].astype(np.intp), 0, height - 1))
    assert np.array_equal(cols, np.clip(pix[:, 0].astype(np.intp), 0, width - 1))
    full = splat_nearest(points, R, t, (height, width))
    wanted = rng.random((height, width)) < 0.3
    wanted.ravel()[rows * width + cols] |= rng.random(len(rows)) < 0.5  # many wanted pixels that points hit
    near = nearest_range_where(points, R, t, wanted)
    assert np.array_equal(near[wanted.ravel()], full[wanted.ravel()])
    assert np.isinf(near[~wanted.ravel()]).all()
    assert np.isfinite(near[wanted.ravel()]).sum() > 1000
