import cv2
import numpy as np

from fullview.sfm.options import FeaturesOptions
import pytest

from fullview.sfm import features as ft
from fullview.sfm.camera import bearings_to_pixels, normalize, pixels_to_bearings, pixel_grid_bearings


def test_pixel_bearing_round_trip_and_convention():
    W, H = 2048, 1024
    assert np.allclose(pixels_to_bearings(np.array([[W / 2, H / 2]]), W, H), [[0, 0, 1]])  # image centre: +z
    assert np.allclose(pixels_to_bearings(np.array([[3 * W / 4, H / 2]]), W, H), [[1, 0, 0]])  # lon 90°: +x
    assert np.allclose(pixels_to_bearings(np.array([[W / 2, 0.0]]), W, H), [[0, -1, 0]])  # top: -y (up)
    rng = np.random.default_rng(0)
    px = rng.uniform([0, 1], [W, H - 1], (1000, 2))
    assert np.allclose(bearings_to_pixels(pixels_to_bearings(px, W, H), W, H), px, atol=1e-8)
    grid = pixel_grid_bearings(8, 4)
    assert grid.shape == (4, 8, 3) and np.allclose(np.linalg.norm(grid, axis=-1), 1)


def test_face_rotations_are_proper_and_cover_the_sphere():
    R = ft.face_rotations()
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3)) and np.allclose(np.linalg.det(R), 1)
    rng = np.random.default_rng(1)
    b = normalize(rng.normal(size=(5000, 3)))
    owners = np.stack([ft.owned_by_face(b, f) for f in range(6)])
    # every bearing belongs to at least one face; only the measure-zero seams to two
    assert owners.any(axis=0).all() and owners.sum(axis=0).max() <= 2 and (owners.sum(axis=0) == 1).mean() > 0.999


def test_face_maps_sample_the_right_directions():
    W, H = 512, 256
    size, margin = 64, 5.0
    map_x, map_y, focal = ft.face_maps(size, margin, W, H)
    # the centre pixel of the front face looks along +z (image centre)
    c = size // 2
    assert abs(map_x[0, c, c] + 0.5 - W / 2) < 2 and abs(map_y[0, c, c] + 0.5 - H / 2) < 2
    assert np.isclose(focal, 0.5 * size / np.tan(np.radians(45 + margin)))


def _blob_panorama(width, rng, n=300):
    """Gaussian blobs at random bearings: a panorama with known feature positions."""
    H = width // 2
    grid = pixel_grid_bearings(width, H)
    centres = normalize(rng.normal(size=(n, 3)))
    centres = centres[np.abs(centres[:, 1]) < 0.8]
    img = np.zeros((H, width))
    sigma = np.radians(0.6)
    for c in centres:  # test-only loop over a few hundred blobs
        ang = np.arccos(np.clip(grid @ c, -1, 1))
        img += np.exp(-(ang / sigma) ** 2 / 2)
    return (np.clip(img, 0, 1) * 220 + 20).astype(np.uint8), centres


def test_detected_bearings_are_unbiased_and_unique():
    rng = np.random.default_rng(2)
    img, centres = _blob_panorama(1024, rng)
    feats = ft.detect_features(img, FeaturesOptions(contrast_threshold=0.01))
    assert len(feats.bearings) > 0.8 * len(centres)
    ang = np.degrees(np.arccos(np.clip(feats.bearings @ centres.T, -1, 1)))
    nearest = ang.min(axis=1)
    good = nearest < 0.3
    assert good.sum() > 0.6 * len(centres)
    # sub-pixel accuracy: median error well under one panorama pixel (0.35° at 1024 px)
    assert np.median(nearest[good]) < 0.05
    # margins overlap, yet no blob is reported by two faces (one face may give several orientations of it)
    close = np.degrees(np.arccos(np.clip(feats.bearings @ feats.bearings.T, -1, 1))) < 0.1
    i, j = np.nonzero(np.triu(close, 1))
    assert len(i) and (feats.faces[i] == feats.faces[j]).all()
    assert len(np.unique(feats.faces)) == 6
    assert np.allclose(np.linalg.norm(feats.bearings, axis=1), 1)
    assert np.allclose(pixels_to_bearings(feats.pixels, 1024, 512), feats.bearings, atol=1e-9)


def test_latitude_mask():
    rng = np.random.default_rng(3)
    img, _ = _blob_panorama(512, rng)
    feats = ft.detect_features(img, FeaturesOptions(min_latitude_deg=-10, max_latitude_deg=20))
    lat = 90 - 180 * feats.pixels[:, 1] / 256
    assert len(lat) and lat.min() >= -10 - 1e-9 and lat.max() <= 20 + 1e-9


def test_opencv_sift_offset_is_corrected():
    """Blobs at known sub-pixel positions on a flat image: OpenCV's keypoints + our offset hit them."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:256, 0:256] + 0.5  # continuous coordinates of pixel centres
    img = np.zeros((256, 256))
    pts = rng.uniform(30, 226, (30, 2))
    for x, y in pts:
        img += np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 3.0**2))
    kp = cv2.SIFT_create(contrastThreshold=0.01).detect((img / img.max() * 200 + 20).astype(np.uint8))
    found = np.array([k.pt for k in kp]) + ft.OPENCV_SIFT_TO_CONTINUOUS
    d = np.linalg.norm(found[:, None] - pts[None], axis=2)
    ok = d.min(axis=1) < 1
    offset = (found[ok] - pts[d[ok].argmin(axis=1)]).mean(axis=0)
    assert np.abs(offset).max() < 0.08


@pytest.mark.parametrize("mode,expected", [("exhaustive", 10), ("sequential", 7)])
def test_pair_list(mode, expected):
    from fullview.sfm.pairs import pair_list
    pairs = pair_list(5, mode, window=2)
    assert len(pairs) == expected and all(i < j for i, j in pairs)


def test_plain_faces_are_detected_again_with_a_lower_contrast_threshold():
    """A low-contrast panorama: the default threshold finds little; asking for a minimum per face lowers it there."""
    rng = np.random.default_rng(3)
    img = (128 + 6 * cv2.GaussianBlur(rng.standard_normal((256, 512)), (0, 0), 2.0)).clip(0, 255).astype(np.uint8)
    plain = ft.detect_features(img, FeaturesOptions(contrast_threshold=0.04, min_features_per_face=0))
    adaptive = ft.detect_features(img, FeaturesOptions(contrast_threshold=0.04, min_features_per_face=200))
    assert len(adaptive.bearings) > 2 * max(len(plain.bearings), 1)
    # a face that already has enough keeps the stricter threshold: a textured image is unchanged
    busy = (rng.random((256, 512)) * 255).astype(np.uint8)
    a = ft.detect_features(busy, FeaturesOptions(min_features_per_face=10))
    b = ft.detect_features(busy, FeaturesOptions(min_features_per_face=0))
    assert np.array_equal(a.bearings, b.bearings)


def test_two_threads_that_need_the_same_face_masks_build_them_once(monkeypatch):
    # The features stage's two image threads start together and both need the faces' keep masks (and remap maps):
    # the second waits for the first's instead of building its own (functools' cache let both build them).
    import threading
    import time

    built = []
    inner = ft.face_keypoints_to_bearings

    def slow(points, face, *args):  # called once per face while the masks are built
        built.append(face)
        time.sleep(0.02)
        return inner(points, face, *args)

    monkeypatch.setattr(ft, "face_keypoints_to_bearings", slow)
    args = (40, 5.0, -61.25, 90.0)  # a size and latitude no other test caches
    start = threading.Barrier(2)
    results = []

    def worker():
        start.wait()
        results.append(ft.face_keep_masks(*args))

    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(built) == list(range(6))  # six faces, built by one of the threads
    assert results[0] is results[1]
    ft.face_keep_masks.cache_clear()


def _spotted_panorama(noise: float, seed: int = 4) -> np.ndarray:
    """A plain panorama with 150 dark spots (its only real features), with white sensor noise of `noise` levels."""
    rng = np.random.default_rng(seed)
    image = np.full((512, 1024), 128.0)
    for x, y, r in zip(rng.integers(0, 1024, 150), rng.integers(60, 452, 150), rng.integers(3, 8, 150)):
        cv2.circle(image, (int(x), int(y)), int(r), 80.0, -1)
    image = cv2.GaussianBlur(image, (0, 0), 1.0) + rng.normal(0.0, noise, image.shape) * (noise > 0)
    return image.clip(0, 255).round().astype(np.uint8)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0])
def test_noise_sigma_recovers_a_known_sensor_noise(sigma):
    assert ft.noise_sigma(_spotted_panorama(0.0)) < 0.15  # plain, spotted, rounded to uint8: next to no noise
    assert ft.noise_sigma(_spotted_panorama(sigma)) == pytest.approx(sigma, rel=0.05)


def test_sensor_noise_does_not_fill_a_plain_panorama_with_keypoints():
    """Noise of 2 levels on a plain panorama: undenoised, the lowered thresholds of its plain faces find several
    times its real keypoints, most of them noise; denoised, about as many as the clean panorama's, at its places."""
    clean = ft.detect_features(_spotted_panorama(0.0), FeaturesOptions())
    noisy = _spotted_panorama(2.0)
    raw = ft.detect_features(noisy, FeaturesOptions())  # the default: never denoised
    handled = ft.detect_features(noisy, FeaturesOptions(denoise_min_noise=1.0))
    assert len(raw.bearings) > 3 * len(clean.bearings)
    assert 0.7 * len(clean.bearings) < len(handled.bearings) < 1.5 * len(clean.bearings)
    near_clean = (handled.bearings @ clean.bearings.T).max(axis=1) > np.cos(np.radians(0.5))
    assert near_clean.mean() > 0.8
    # below the noise level that calls for it, the panorama is left exactly as it is
    assert ft.denoised(noisy, FeaturesOptions(denoise_min_noise=2.5)) is noisy


def test_features_carry_the_working_panoramas_noise():
    assert ft.detect_features(_spotted_panorama(2.0), FeaturesOptions()).noise == pytest.approx(2.0, rel=0.05)
    clean = ft.detect_features(_spotted_panorama(0.0), FeaturesOptions())
    assert clean.noise < 0.15 and clean.subset(np.arange(len(clean.bearings)) < 5).noise == clean.noise
