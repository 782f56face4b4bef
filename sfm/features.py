"""SIFT features on the six faces of a cube map, returned as equirectangular pixels and unit bearings.

SIFT on the raw panorama suffers from the equirectangular stretch (the report's failure); on cube faces the local
geometry is nearly perspective. Each face covers 90° plus a margin so that blobs straddling a seam are detected
with full support; a keypoint is then kept only by the face whose own 90° square contains its bearing, which removes
the duplicates the overlapping margins create.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from functools import lru_cache, wraps

import cv2
import numpy as np

from fullview.sfm.camera import bearings_to_lonlat, bearings_to_pixels, normalize, rays_to_remap_coords
from fullview.sfm.options import FeaturesOptions

log = logging.getLogger(__name__)

# Rotation face_from_cam... stored as cam_from_face: columns are the face's x (right), y (down), z (forward) axes.
_FACE_AXES = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "right": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
    "back": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
    "left": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),
    "up": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "down": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
}
FACE_NAMES = tuple(_FACE_AXES)

# OpenCV pixel centres sit at integer coordinates, so continuous = pt + 0.5; but OpenCV SIFT also reports points
# found on its 2x-upsampled base image as (upsampled index) / 2, ignoring that resize puts upsampled pixel c at
# source position c/2 - 0.25 (cv2.resize's pixel-centre convention; a blob of known centre confirms it: +0.23/+0.25
# px). Left uncorrected, this bias rotates differently with each cube face and costs ~0.03° of relative rotation.
OPENCV_SIFT_TO_CONTINUOUS = 0.5 - 0.25


def face_rotations() -> np.ndarray:
    """(6, 3, 3) R_cam_from_face for the faces in FACE_NAMES order."""
    return np.stack([np.array(_FACE_AXES[n], dtype=np.float64).T for n in FACE_NAMES])


@dataclass(kw_only=True)
class Features:
    pixels: np.ndarray  # (N, 2) float64 equirectangular pixel coordinates in the input image
    bearings: np.ndarray  # (N, 3) float64 unit bearings, camera frame
    descriptors: np.ndarray  # (N, 128) float32 descriptors
    scales: np.ndarray  # (N,) float32 keypoint size in face pixels
    faces: np.ndarray  # (N,) uint8 index into FACE_NAMES of the detecting face
    noise: float = 0.0  # the working panorama's sensor noise, grey levels (`noise_sigma`): the matches' ratio test

    def subset(self, keep: np.ndarray) -> "Features":
        """The features where `keep` (N,) bool is True."""
        return Features(pixels=self.pixels[keep], bearings=self.bearings[keep], descriptors=self.descriptors[keep],
                        scales=self.scales[keep], faces=self.faces[keep], noise=self.noise)


def computed_once(func):
    """`lru_cache(maxsize=4)` of `func` whose misses compute once: a caller that misses while another computes the
    same value waits for it. (functools' cache lets both compute: the features stage's two image threads start
    together, and each built the faces' remap maps and keep masks, 65 ms of CPU at 1024 px, 0.2 s at 2048.)"""
    cached, lock = lru_cache(maxsize=4)(func), threading.Lock()

    @wraps(func)
    def once(*args):
        with lock:  # held for a hit too: a dictionary look-up
            return cached(*args)
    once.cache_clear, once.cache_info = cached.cache_clear, cached.cache_info
    return once


@computed_once
def face_maps(face_size: int, margin_deg: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """cv2.remap maps of every face (6, S, S) and the face focal length in pixels (cached: same for every image)."""
    half_fov = np.radians(45.0 + margin_deg)
    focal = 0.5 * face_size / np.tan(half_fov)
    uv = ((np.arange(face_size) + 0.5 - 0.5 * face_size) / focal).astype(np.float32)
    u, v = np.meshgrid(uv, uv)
    rays_face = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rays_cam = (rays_face @ face_rotations().astype(np.float32).transpose(0, 2, 1)).reshape(6, face_size, face_size, 3)
    map_x, map_y = rays_to_remap_coords(rays_cam, width, height)
    return map_x.astype(np.float32), map_y.astype(np.float32), focal


def native_face_size(width: int, margin_deg: float) -> int:
    """Face side giving the face as many pixels per degree, across its field of view, as the panorama's equator.

    (A face matched to the panorama at its centre would oversample its corners ~2x: SIFT time, no accuracy gain.)
    """
    return int(round(width * (90.0 + 2.0 * margin_deg) / 360.0))


def render_faces(image: np.ndarray, face_size: int, margin_deg: float) -> tuple[list[np.ndarray], float]:
    """The six perspective faces of a panorama (wrap-around in longitude) and their focal length."""
    height, width = image.shape[:2]
    map_x, map_y, focal = face_maps(face_size, margin_deg, width, height)
    faces = [cv2.remap(image, map_x[f], map_y[f], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_WRAP) for f in range(6)]
    return faces, focal


def face_keypoints_to_bearings(points: np.ndarray, face: int, face_size: int, focal: float) -> np.ndarray:
    rays = np.column_stack([(points - 0.5 * face_size) / focal, np.ones(len(points))])
    return normalize(rays @ face_rotations()[face].T)


def owned_by_face(bearings: np.ndarray, face: int) -> np.ndarray:
    """True where the face's own 90° square contains the bearing (its axis dominates)."""
    local = bearings @ face_rotations()[face]
    return (local[:, 2] > 0) & (np.abs(local[:, 0]) <= local[:, 2]) & (np.abs(local[:, 1]) <= local[:, 2])


# The 3x3 kernel of Immerkær's noise estimate: zero on any linear ramp, 6 sigma on white noise.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SIGMA = 0.6745


def noise_sigma(grey: np.ndarray) -> float:
    """Standard deviation of a grey image's white sensor noise, in grey levels: the median absolute response of
    `_NOISE_KERNEL` (edges and texture are a minority of a room's pixels; the median ignores them). The responses of
    a uint8 image are integers, so the median is interpolated within its unit bin (a plain median jumps by 0.25).
    The image needs a pixel with a full 3x3 neighbourhood (the dataset refuses smaller ones: io/dataset.py)."""
    if min(grey.shape[:2]) < _NOISE_KERNEL.shape[0]:
        raise ValueError(f"noise_sigma: a {grey.shape[1]}x{grey.shape[0]} image has no pixel with a full 3x3 "
                         "neighbourhood")
    response = np.abs(cv2.filter2D(grey.astype(np.float32), -1, _NOISE_KERNEL)[1:-1, 1:-1])
    levels = np.rint(response).astype(np.int64).ravel()
    counts = np.bincount(levels)
    below = np.cumsum(counts) - counts
    half = 0.5 * levels.size
    level = int(np.searchsorted(below + counts, half))
    low, width = (0.0, 0.5) if level == 0 else (level - 0.5, 1.0)
    median = low + (half - below[level]) / counts[level] * width
    return float(median / (_MAD_TO_SIGMA * 6.0))


def denoised(grey: np.ndarray, options: FeaturesOptions, noise: float | None = None) -> np.ndarray:
    """The grey panorama SIFT sees. With more sensor noise than `denoise_min_noise`, non-local means of strength
    1.5 sigma (5 px patches, 11 px search): a room's faint texture repeats over many pixels, the noise does not, so
    the texture survives while the noise's own DoG blobs go, which would otherwise fill the plain faces (detected at
    lowered thresholds) with keypoints and drown their real ones. Clean renders measure ~0.1, the real Theta
    panoramas at 2048 px 0.59-0.73 (360_school, 360_Flat). Off by default: nothing shows it helps (on rendered noisy
    homes it removed the noise keypoints but brought back none of the true matches the noise costs: README, "Sensor
    noise in the features stage"; not measured on the real captures)."""
    if not options.denoise_min_noise:
        return grey
    noise = noise_sigma(grey) if noise is None else noise
    if noise <= options.denoise_min_noise:
        return grey
    return cv2.fastNlMeansDenoising(grey, None, h=1.5 * noise, templateWindowSize=5, searchWindowSize=11)


def detect_on_face(face: np.ndarray, options: FeaturesOptions, keep_mask: np.ndarray, *,
                   expect_short: bool = False) -> tuple[list, np.ndarray | None, bool]:
    """SIFT keypoints and descriptors of one face, and whether it kept fewer than `min_features_per_face` at the
    first threshold. A face with fewer keypoints than that (a plain wall) is detected again with the contrast
    threshold halved, down to `min_contrast_threshold`: low-contrast texture is all a bare room offers, while
    textured faces keep the stricter threshold.

    `keep_mask` (uint8, the face's size: `face_keep_masks`) marks where a keypoint may be kept. A face expected to
    keep enough (`expect_short`, a performance hint, is False) is detected with it as OpenCV's mask: applied after
    the `max_features_per_face` strongest keypoints of the whole face are chosen and before their descriptors (three
    quarters of SIFT's time), from the same pyramid, so the keypoints on the mask and their descriptors are exactly
    those of an unmasked run; only when it keeps too few is the face detected again without it, for the unmasked
    count that decides the threshold. A face expected to keep too few (plain, or with most of its keypoints in the
    margins) is detected without the mask at each threshold, as that costs it least; the caller drops what lies
    off the mask either way."""
    threshold, floor, wanted = options.contrast_threshold, options.min_contrast_threshold, options.min_features_per_face
    if not expect_short:
        sift = cv2.SIFT_create(nfeatures=options.max_features_per_face, contrastThreshold=threshold)
        keypoints, desc = sift.detectAndCompute(face, keep_mask)
        if len(keypoints) >= wanted:
            return keypoints, desc, False
        if threshold / 2 < floor or len(sift.detect(face, None)) >= wanted:
            return keypoints, desc, True
        threshold /= 2
    while True:
        sift = cv2.SIFT_create(nfeatures=options.max_features_per_face, contrastThreshold=threshold)
        keypoints, desc = sift.detectAndCompute(face, None)
        if len(keypoints) >= wanted or threshold / 2 < floor:
            break
        threshold /= 2
    short = threshold < options.contrast_threshold or _on_mask(keypoints, keep_mask).sum() < wanted
    return keypoints, desc, short


def _on_mask(keypoints: list, mask: np.ndarray) -> np.ndarray:
    """Which keypoints OpenCV's `mask` would keep: it tests pixel (int(y + 0.5), int(x + 0.5)) in float32."""
    xy = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2) + np.float32(0.5)
    return mask[xy[:, 1].astype(int), xy[:, 0].astype(int)] > 0


@computed_once
def face_keep_masks(face_size: int, margin_deg: float, min_latitude_deg: float, max_latitude_deg: float
                    ) -> np.ndarray:
    """(6, S, S) uint8: 255 on the face pixels where a keypoint may be kept (its own 90° square, within the
    latitudes), widened by 2 pixels so that the exact test on each keypoint's bearing (`detect_features`) decides
    at the edges. OpenCV tests keypoint (x, y) on pixel (int(y + 0.5), int(x + 0.5)); that pixel's keypoints lie
    within a pixel of its centre's bearing, tested here."""
    focal = 0.5 * face_size / np.tan(np.radians(45.0 + margin_deg))
    centres = np.arange(face_size, dtype=np.float64) + OPENCV_SIFT_TO_CONTINUOUS
    xx, yy = np.meshgrid(centres, centres)
    points = np.column_stack([xx.ravel(), yy.ravel()])
    masks = np.zeros((6, face_size, face_size), np.uint8)
    for f in range(6):
        bearings = face_keypoints_to_bearings(points, f, face_size, focal)
        keep = owned_by_face(bearings, f) & _within_latitudes(bearings, min_latitude_deg, max_latitude_deg)
        masks[f] = cv2.dilate(keep.reshape(face_size, face_size).astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    return masks


def _within_latitudes(bearings: np.ndarray, min_latitude_deg: float, max_latitude_deg: float) -> np.ndarray:
    _, lat = bearings_to_lonlat(bearings)
    return (lat >= np.radians(min_latitude_deg)) & (lat <= np.radians(max_latitude_deg))


def detect_features(image: np.ndarray, options: FeaturesOptions, short_faces: set[int] | None = None) -> Features:
    """SIFT on the cube faces of an equirectangular image (grey or BGR uint8).

    `short_faces`, when given, is a hint carried from image to image (it never changes the features): the indices
    of the faces that kept fewer than `min_features_per_face` keypoints at the first threshold in the last image,
    updated here; they are detected the way that suits such a face (`detect_on_face`). Ceilings and bare walls tend
    to stay plain across a tour."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    noise = noise_sigma(grey)
    grey = denoised(grey, options, noise)
    height, width = grey.shape
    face_size = options.face_size or native_face_size(width, options.margin_deg)
    faces, focal = render_faces(grey, face_size, options.margin_deg)
    keep_masks = face_keep_masks(face_size, options.margin_deg, options.min_latitude_deg, options.max_latitude_deg)
    parts = []
    for f, face in enumerate(faces):
        keypoints, desc, short = detect_on_face(face, options, keep_masks[f],
                                                expect_short=short_faces is not None and f in short_faces)
        if short_faces is not None:
            (short_faces.add if short else short_faces.discard)(f)
        if not keypoints:
            continue
        pts = np.array([k.pt for k in keypoints], dtype=np.float64)
        bearings = face_keypoints_to_bearings(pts + OPENCV_SIFT_TO_CONTINUOUS, f, face_size, focal)
        keep = owned_by_face(bearings, f)
        sizes = np.array([k.size for k in keypoints], dtype=np.float32)
        parts.append((bearings[keep], desc[keep], sizes[keep], np.full(keep.sum(), f, np.uint8)))
    bearings = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
    desc = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 128), np.float32)
    sizes = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0, np.float32)
    face_ids = np.concatenate([p[3] for p in parts]) if parts else np.zeros(0, np.uint8)
    keep = _within_latitudes(bearings, options.min_latitude_deg, options.max_latitude_deg)
    desc = desc[keep]
    if options.root_sift and len(desc):
        desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)
    return Features(pixels=bearings_to_pixels(bearings[keep], width, height), bearings=bearings[keep],
                    descriptors=desc, scales=sizes[keep], faces=face_ids[keep], noise=noise)
