"""Typed readers and writers of the pipeline's npz artifacts (one place knows every key and version)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fullview.io.artifacts import ArtifactError, load_npz, save_npz
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.camera import pixels_to_bearings

FEATURES_VERSION = 1
PAIRS_VERSION = 1
EPIPOLES_VERSION = 1
REGISTRATION_VERSION = 1
SPARSE_VERSION = 1
FEATURE_KEYS = ("pixels", "bearings", "descriptors", "scales", "colors", "image_size")


def save_features(path: Path, **arrays: np.ndarray) -> Path:
    missing = [k for k in FEATURE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"features for {path} lack {missing}")
    return save_npz(path, FEATURES_VERSION, **arrays)


def load_features(ws: Workspace, image_name: str) -> dict[str, np.ndarray]:
    return load_npz(ws.features_path(image_name), FEATURES_VERSION, FEATURE_KEYS)


HAND_COLOR = (255, 0, 0)  # hand points are drawn red in the sparse cloud


def load_observations(ws: Workspace, dataset: Dataset) -> list[dict[str, np.ndarray]]:
    """Per image: SIFT features followed by the image's hand observations (the extended feature index space).

    Feature index k < num_sift refers to SIFT feature k; k >= num_sift to hand observation k - num_sift.
    """
    hand = dataset.hand_observations
    out = []
    for name in dataset.image_names:
        feats = load_features(ws, name)
        w, h = (int(v) for v in feats["image_size"])
        _, hand_px = hand[name]
        out.append({
            "pixels": np.concatenate([feats["pixels"], hand_px]),
            "bearings": np.concatenate([feats["bearings"], pixels_to_bearings(hand_px, w, h).reshape(-1, 3)]),
            "colors": np.concatenate([feats["colors"], np.tile(np.uint8(HAND_COLOR), (len(hand_px), 1))]),
            "num_sift": np.int64(len(feats["pixels"])),
            "image_size": feats["image_size"],
        })
    return out


def hand_pair_matches(dataset: Dataset, num_sift: list[int], i: int, j: int) -> np.ndarray:
    """(K, 2) hand correspondences of images i, j in the extended feature index space."""
    hand = dataset.hand_observations
    tracks_i, _ = hand[dataset.image_names[i]]
    tracks_j, _ = hand[dataset.image_names[j]]
    _, ki, kj = np.intersect1d(tracks_i, tracks_j, assume_unique=True, return_indices=True)
    return np.column_stack([ki + num_sift[i], kj + num_sift[j]]).astype(np.int64)


def save_pair_data(path: Path, pairs: list[tuple[int, int]], matches: list[np.ndarray],
                   **per_pair: np.ndarray) -> Path:
    """Per-pair match lists stored flat (CSR): `pairs` (P,2), `offsets` (P+1,), `matches` (M,2), plus (P,...) arrays."""
    offsets = np.concatenate([[0], np.cumsum([len(m) for m in matches])]).astype(np.int64)
    flat = np.concatenate(matches).astype(np.int64) if matches else np.zeros((0, 2), np.int64)
    return save_npz(path, PAIRS_VERSION, pairs=np.asarray(pairs, np.int64).reshape(-1, 2), offsets=offsets,
                    matches=flat.reshape(-1, 2), **per_pair)


def load_pair_data(path: Path) -> tuple[list[tuple[int, int]], list[np.ndarray], dict[str, np.ndarray]]:
    """Inverse of `save_pair_data`: pair list, per-pair (M,2) matches and the remaining per-pair arrays."""
    data = load_npz(path, PAIRS_VERSION, ("pairs", "offsets", "matches"))
    pairs = [tuple(int(v) for v in p) for p in data.pop("pairs")]
    offsets, flat = data.pop("offsets"), data.pop("matches")
    matches = [flat[offsets[k]:offsets[k + 1]] for k in range(len(pairs))]
    return pairs, matches, data


def save_poses(path: Path, version: int, *, image_names: list[str], registered: np.ndarray,
               R_cam_from_world: np.ndarray, t_cam_from_world: np.ndarray, **extra: np.ndarray) -> Path:
    """Camera poses (registration or bundle-adjusted), with centres for convenience."""
    centers = -np.einsum("nba,nb->na", R_cam_from_world, t_cam_from_world)
    return save_npz(path, version, image_names=np.array(image_names), registered=registered,
                    R_cam_from_world=R_cam_from_world, t_cam_from_world=t_cam_from_world, centers=centers, **extra)


def load_poses(ws: Workspace) -> tuple[dict[str, np.ndarray], str]:
    """The most refined poses in the workspace: bundle-adjusted if triangulation ran on the current registration."""
    keys = ("image_names", "registered", "R_cam_from_world", "t_cam_from_world", "centers")
    tri, reg = ws.read_manifest("triangulation"), ws.read_manifest("registration")
    if ws.sparse_path().exists() and tri and reg and tri["upstream"].get("registration") == reg["fingerprint"]:
        return load_npz(ws.sparse_path(), SPARSE_VERSION, keys), "triangulation"
    if ws.registration_path().exists():
        return load_npz(ws.registration_path(), REGISTRATION_VERSION, keys), "registration"
    raise ArtifactError(f"{ws.root}: no registration or triangulation results; run the pipeline first")
