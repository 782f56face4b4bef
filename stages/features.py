"""Stage 1 — SIFT features on cube-map faces of every panorama (pixels, bearings, descriptors, colours)."""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fullview.io.store import FEATURES_VERSION, save_features
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.features import FeatureOptions, detect_features

log = logging.getLogger(__name__)

VERSION = FEATURES_VERSION
UPSTREAM: tuple[str, ...] = ()
INPUTS = ("images",)


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    options = FeatureOptions(**{k: v for k, v in config.items() if k != "working_width"})
    # OpenCV releases the GIL inside SIFT, so two images at a time use both cores.
    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
        jobs = pool.map(lambda name: _extract(dataset, name, config["working_width"], options, ws, out_dir),
                        dataset.image_names)
        counts = dict(tqdm(jobs, total=len(dataset.image_names), desc="features", unit="image"))
    log.info("features per image: min %d, median %d, max %d", min(counts.values()),
             int(np.median(list(counts.values()))), max(counts.values()))
    return {"images": len(counts), "min_features": min(counts.values()), "per_image": counts}


def _extract(dataset: Dataset, name: str, working_width: int, options: FeatureOptions, ws: Workspace,
             out_dir: Path) -> tuple[str, int]:
    """Detect and save one image's features; returns (name, count)."""
    full_w, full_h = dataset.image_sizes[name]
    # Never upsample: a working width above the native width means "native".
    image = dataset.load_image(name, width=min(working_width or full_w, full_w))
    feats = detect_features(image, options)
    scale = full_w / image.shape[1]
    colors = sample_colors(image, feats.pixels)  # detection pixels are working-image pixels
    save_features(ws.features_path(name, out_dir), pixels=feats.pixels * scale, bearings=feats.bearings,
                  descriptors=feats.descriptors, scales=feats.scales * scale, colors=colors,
                  image_size=np.array([full_w, full_h]))
    return name, len(feats.bearings)


def sample_colors(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """RGB uint8 colours at continuous pixel positions (nearest pixel)."""
    h, w = image.shape[:2]
    cols = np.clip(np.floor(pixels[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.floor(pixels[:, 1]).astype(int), 0, h - 1)
    return image[rows, cols][:, ::-1].copy()
