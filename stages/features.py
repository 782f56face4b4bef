"""Stage 1 — features: cube-map SIFT per panorama (`fullview.sfm.features`), one npz per image."""

from __future__ import annotations

import logging
from functools import partial

import numpy as np
from tqdm import tqdm

from fullview.io.dataset import Dataset
from fullview.io.workspace import FEATURES_VERSION, StageWriter
from fullview.sfm.features import FACE_NAMES, Features, detect_features
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = FEATURES_VERSION
UPSTREAM: tuple[str, ...] = ()
INPUTS = ("images", "masks")


def run(ctx: StageContext) -> dict:
    names = ctx.dataset.image_names
    ctx.dataset.image_sizes  # noqa: B018 — every header read once here, not in each task (the dataset travels)
    # One task per image. Locally OpenCV releases the GIL inside SIFT, so two images at a time use both cores (more
    # would only hold more full-size panoramas in memory).
    # The faces that kept too few SIFT keypoints in the last image, a hint shared by the tasks (on a cluster each task
    # has its own); at first the ceiling only, the face most often plain (360_Flat's in every image; the rooms' none).
    jobs = ctx.map(partial(extract_image, ctx.dataset, ctx.options, ctx.out, short_faces={FACE_NAMES.index("up")}),
                   names, threads=2)
    found = list(tqdm(jobs, total=len(names), desc="features", unit="image"))
    counts = {name: count for name, count, _ in found}
    noise = {name: round(sigma, 3) for name, _, sigma in found}
    log.info("features per image: min %d, median %d, max %d; sensor noise (grey levels) median %.2f, max %.2f",
             min(counts.values()), int(np.median(list(counts.values()))), max(counts.values()),
             np.median(list(noise.values())), max(noise.values()))
    return {"images": len(counts), "min_features": min(counts.values()), "per_image": counts, "noise": noise}


def extract_image(dataset: Dataset, options, out: StageWriter, name: str, *, short_faces: set[int] | None = None
                  ) -> tuple[str, int, float]:
    """Detect and save one image's features; returns (name, count, sensor noise). A task of its own: picklable
    arguments, and it writes only its own file into the transaction's folder (a retried task rewrites it whole)."""
    full_w, full_h = dataset.image_sizes[name]
    # Never upsample: a working width above the native width means "native".
    image = dataset.load_image(name, width=min(options.working_width or full_w, full_w))
    feats = detect_features(image, options, short_faces)
    scale = full_w / image.shape[1]
    feats = keep_unmasked(feats, dataset.load_mask(name), scale)
    colors = sample_colors(image, feats.pixels)  # detection pixels are working-image pixels
    out.save_features(name, pixels=feats.pixels * scale, bearings=feats.bearings, descriptors=feats.descriptors,
                      scales=feats.scales * scale, colors=colors, image_size=np.array([full_w, full_h]),
                      noise_sigma=np.float64(feats.noise))
    return name, len(feats.bearings), feats.noise


def keep_unmasked(feats: Features, keep: np.ndarray | None, scale: float) -> Features:
    """The features whose (full-size) pixel the image's mask keeps; all of them without a mask."""
    if keep is None:
        return feats
    h, w = keep.shape
    cols = np.clip(np.floor(feats.pixels[:, 0] * scale).astype(int), 0, w - 1)
    rows = np.clip(np.floor(feats.pixels[:, 1] * scale).astype(int), 0, h - 1)
    return feats.subset(keep[rows, cols])


def sample_colors(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """RGB uint8 colours at continuous pixel positions (nearest pixel)."""
    h, w = image.shape[:2]
    cols = np.clip(np.floor(pixels[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.floor(pixels[:, 1]).astype(int), 0, h - 1)
    return image[rows, cols][:, ::-1].copy()
