"""The world fill looks only at the stereo pixels that can change its answer (sfm/dense/world_planes.py,
sfm/dense/planes.py): the regions with pixels to fill, the ranges next to the pixels the brackets judge. Each must
give exactly what the straightforward computation over every pixel gives (written out here as it was)."""

from types import SimpleNamespace

import numpy as np
import pytest

from fullview.sfm.dense import planes, world_planes
from fullview.sfm.dense.planes import RING_OFFSETS, reduced_bearings_world


def _reference_evidence_pixels(labels, range_map):
    rows, cols = np.nonzero(np.isfinite(range_map))
    height, width = labels.shape
    near = [labels[rows, cols]] + [labels[np.clip(rows + dy, 0, height - 1), (cols + dx) % width]
                                   for dy, dx in RING_OFFSETS]
    pixel = np.tile(np.arange(len(rows)), len(near))
    region = np.concatenate(near)
    keep = region > 0
    pair = np.unique(region[keep].astype(np.int64) * max(len(rows), 1) + pixel[keep])
    return pair // max(len(rows), 1), pair % max(len(rows), 1), rows, cols


def _reference_wall_brackets(ref, planes_, pix, tolerance):
    h, w = ref.range_map.shape
    rows, cols = np.nonzero(np.isfinite(ref.range_map))
    index = np.full((h, w), len(rows), np.intp)
    index[rows, cols] = np.arange(len(rows))
    bearings = reduced_bearings_world(ref.R_cam_from_world, w, h)[rows, cols].astype(np.float64)
    observed = ref.range_map[rows, cols].astype(np.float64)
    center = -ref.R_cam_from_world.T @ ref.t_cam_from_world
    upright = np.array([not p.level for p in planes_])
    normals = np.array([p.normal for p in planes_])
    distances = np.array([p.offset for p in planes_]) - normals @ center
    width = (len(planes_) + 7) // 8
    on, beyond = [np.zeros((0, width), np.uint8)], [np.zeros((0, width), np.uint8)]
    for start in range(0, len(rows), world_planes.EVIDENCE_BLOCK):
        block = slice(start, start + world_planes.EVIDENCE_BLOCK)
        with np.errstate(divide="ignore", invalid="ignore"):
            predicted = distances[None] / world_planes._rows_times(bearings[block], normals.T)
            o = observed[block, None]
            on.append(np.packbits((np.abs(predicted - o) <= tolerance * o) & upright, axis=1))
            beyond.append(np.packbits((o > (1 + tolerance) * predicted) & upright, axis=1))
    none = np.zeros((1, width), np.uint8)
    on, beyond = np.concatenate(on + [none]), np.concatenate(beyond + [none])
    finite = index < len(rows)
    row, col = np.divmod(pix, w)
    grid = np.broadcast_to(np.arange(h)[:, None], (h, w))
    above = np.maximum.accumulate(np.where(finite, grid, -1), axis=0)
    below = np.minimum.accumulate(np.where(finite, grid, h)[::-1], axis=0)[::-1]
    up = above[np.maximum(row - 1, 0), col]
    down = below[np.minimum(row + 1, h - 1), col]
    twice = np.concatenate([finite, finite], axis=1)
    grid = np.broadcast_to(np.arange(2 * w)[None], (h, 2 * w))
    left = np.maximum.accumulate(np.where(twice, grid, -1), axis=1)[row, col + w - 1]
    right = np.minimum.accumulate(np.where(twice, grid, 2 * w)[:, ::-1], axis=1)[:, ::-1][row, col + 1]

    def at(r, c, ok):
        return np.where(ok, index[np.clip(r, 0, h - 1), np.clip(c, 0, 2 * w - 1) % w], len(rows))

    u, d = at(up, col, (row > 0) & (up >= 0)), at(down, col, (row < h - 1) & (down < h))
    lt, rt = at(row, left, left > col), at(row, right, right < col + w)
    return (on[u] & on[d]) | (on[lt] & on[rt] & ~beyond[u] & ~beyond[d])


def _scene(seed: int, holes: float):
    """A view of a box room (ranges of its six faces, noisy, with holes: blobs and scattered pixels) from an
    off-centre camera, turned about the vertical; image regions of blocks; the room's planes (walls upright) and a
    few others, some through the room."""
    rng = np.random.default_rng(seed)
    h, w = 64, 128
    a = rng.uniform(-np.pi, np.pi)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    center = rng.uniform(-0.5, 0.5, 3)
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    offsets = np.array([2.0, 2.5, 1.2, 1.4, 3.0, 2.2])  # n . x = offset, x inside: n . x < offset
    bearings = reduced_bearings_world(R, w, h).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        r = (offsets - normals @ center)[None] / (bearings @ normals.T)
    r = np.where(r > 0, r, np.inf).min(axis=1).reshape(h, w)
    r = (r * rng.normal(1, 0.01, r.shape)).astype(np.float32)
    blobs = np.kron(rng.random((h // 8, w // 8)) < holes, np.ones((8, 8), bool))
    r[blobs | (rng.random(r.shape) < holes / 2)] = np.nan
    view = planes.View(R_cam_from_world=R, t_cam_from_world=-R @ center, range_map=r,
                       observable=np.ones((h, w), bool), color=np.zeros((h, w, 3), np.float32))
    labels = np.kron(rng.integers(0, 40, (h // 4, w // 8)), np.ones((4, 8), np.int32)).astype(np.int32)
    extra_normals = rng.normal(size=(5, 3))
    extra_normals /= np.linalg.norm(extra_normals, axis=1, keepdims=True)
    model = [SimpleNamespace(normal=n, offset=float(o), level=abs(n[1]) > 0.9)
             for n, o in zip(np.vstack([normals, extra_normals]), np.concatenate([offsets, rng.uniform(-1, 1, 5)]))]
    return view, labels, model


@pytest.mark.parametrize("seed, holes", [(0, 0.1), (1, 0.3), (2, 0.6), (3, 0.0)])
def test_evidence_pixels_of_the_wanted_regions_are_those_of_all_regions_kept_for_them(seed, holes):
    view, labels, _ = _scene(seed, holes)
    expected = _reference_evidence_pixels(labels, view.range_map)
    for got, want in zip(planes.region_evidence_pixels(labels, view.range_map), expected):
        np.testing.assert_array_equal(got, want)
    wanted = np.random.default_rng(seed).random(labels.max() + 1) < 0.3
    region, pixel, rows, cols = planes.region_evidence_pixels(labels, view.range_map, wanted)
    kept = wanted[expected[0]]
    np.testing.assert_array_equal(region, expected[0][kept])
    np.testing.assert_array_equal(pixel, expected[1][kept])
    np.testing.assert_array_equal(rows, expected[2])
    np.testing.assert_array_equal(cols, expected[3])


@pytest.mark.parametrize("shape", [(64, 128), (7, 9), (3, 4), (1, 2), (13, 1)])
def test_evidence_pixels_clip_rows_and_wrap_columns_as_the_reference(shape):
    """The padded labels (edge rows repeated, columns wrapped) give the clipped and wrapped labels of every offset,
    even on grids narrower or lower than the ring's reach (the columns then wrap more than once)."""
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    labels = rng.integers(0, 6, shape).astype(np.int32)  # every pixel its own label: a wrong neighbour shows
    range_map = np.where(rng.random(shape) < 0.8, 1.0, np.nan).astype(np.float32)
    for got, want in zip(planes.region_evidence_pixels(labels, range_map),
                         _reference_evidence_pixels(labels, range_map)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed, holes", [(0, 0.1), (1, 0.3), (2, 0.6)])
def test_region_candidates_of_the_wanted_regions_are_those_judged_on_every_pixel(seed, holes):
    view, labels, model = _scene(seed, holes)
    options = world_planes.WorldPlaneOptions(distance=0.015, cell=0.1, free_ceiling=False, min_region_support=3)
    every = world_planes.region_candidates(view, model, labels, options)
    assert every.any() and not every.all()
    wanted = np.random.default_rng(seed).random(labels.max() + 1) < 0.4
    some = world_planes.region_candidates(view, model, labels, options, wanted)
    np.testing.assert_array_equal(some[wanted], every[wanted])
    assert not some[~wanted].any()


@pytest.mark.parametrize("seed, holes", [(0, 0.1), (1, 0.3), (2, 0.6), (4, 0.02)])
def test_wall_brackets_judged_on_the_ranges_next_to_the_pixels_are_those_judged_on_every_range(
        seed, holes, monkeypatch):
    view, _, model = _scene(seed, holes)
    pix = np.flatnonzero(~np.isfinite(view.range_map).ravel())
    assert len(pix)
    for block in (world_planes.EVIDENCE_BLOCK, 7):  # blocks of many ranges; of a few, with a lone range at the end
        monkeypatch.setattr(world_planes, "EVIDENCE_BLOCK", block)
        expected = _reference_wall_brackets(view, model, pix, 0.03)
        assert expected.any()
        np.testing.assert_array_equal(world_planes._wall_brackets(view, model, pix, 0.03), expected)
        np.testing.assert_array_equal(world_planes._wall_brackets(view, model, pix[:0], 0.03), expected[:0])
