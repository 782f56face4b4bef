"""The stereo check of densify (``densify.stereo_check``): a range resting on one pair that another panorama sees
through is dropped; the partner's copy of the same disparity is no confirmation."""

from __future__ import annotations

import numpy as np
import pytest

from fullview import synth
from fullview.sfm import dense


@pytest.fixture(scope="module")
def room():
    scene = synth.render_scene(views=4, width=256, seed=2, supersample=1)
    R = np.stack([v.R_world_from_cam.T for v in scene.views])
    t = -np.einsum("nab,nb->na", R, np.stack([v.center for v in scene.views]))
    return [v.depth.astype(np.float32) for v in scene.views], R, t


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
