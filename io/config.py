"""pipeline.yaml: one section per stage, validated against typed defaults (unknown keys and wrong types fail)."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

STAGE_ORDER = ("features", "matches", "filter", "epipoles", "registration", "triangulation", "densify")

# Defaults and types of every key; pipeline.yaml may override any subset.
DEFAULTS: dict[str, dict[str, Any]] = {
    "features": {
        "working_width": 2048,  # panoramas are resized to this width before detection (0 = native)
        "face_size": 0,  # cube face side in pixels (0 = as many pixels per degree as the working panorama)
        "margin_deg": 5.0,  # extra field of view per face side, keeps features at seams
        "max_features_per_face": 1500,  # SIFT nfeatures per face
        "contrast_threshold": 0.02,  # SIFT contrast threshold
        "min_latitude_deg": -90.0,  # mask out features below this latitude (tripod / hand)
        "max_latitude_deg": 90.0,  # mask out features above this latitude
        "root_sift": True,  # RootSIFT descriptors
    },
    "matches": {
        "pairs": "exhaustive",  # exhaustive | sequential
        "window": 3,  # sequential: partners after each image
        "ratio": 0.8,  # Lowe's ratio test
        "mutual": True,  # mutual nearest neighbour check
    },
    "filter": {
        "use_hand_points": True,  # seed F with hand points where a pair has >= min_hand_points
        "min_hand_points": 8,  # hand correspondences needed to seed a pair
        "threshold_deg": 0.35,  # angular distance to the epipolar great circle for inliers
        "max_iterations": 5000,  # RANSAC hypotheses cap
        "confidence": 0.9999,  # RANSAC adaptive stopping confidence
        "min_inliers": 30,  # pairs with fewer inliers are dropped
        "seed": 0,  # RANSAC random seed
    },
    "epipoles": {
        "min_cheiral_ratio": 0.9,  # share of inliers in front of both cameras for a valid pose
    },
    "registration": {
        "model": "general",  # general | planar
        "min_inliers": 30,  # pairs with fewer inliers are not used
        "max_rotation_residual_deg": 5.0,  # pairs whose relative rotation disagrees more are rejected
        "max_direction_residual_deg": 10.0,  # pairs whose baseline direction disagrees more are rejected
        "seed": 0,  # random seed for robust averaging
    },
    "triangulation": {
        "max_reprojection_error_deg": 0.5,  # angular reprojection error for a kept observation
        "min_triangulation_angle_deg": 1.5,  # tracks seen under a smaller angle are dropped
        "bundle_adjust": True,  # refine poses and points jointly
        "ba_loss_scale_deg": 0.2,  # soft-L1 loss scale of bundle adjustment residuals
        "ba_max_iterations": 100,  # function evaluations of bundle adjustment
    },
    "densify": {
        "neighbours": 2,  # stereo partners per camera (best by inlier count, discounted for short baselines)
        "min_triangulation_angle_deg": 5.0,  # partner baselines must subtend at least this at the scene's median depth
        "max_triangulation_angle_deg": 60.0,  # ... and at most this
        "min_pair_inliers": 50,  # epipolar inliers a stereo pair needs
        "working_width": 2048,  # panoramas are resized to this width; range maps have this size (0 = native)
        "rect_height": 1024,  # rectified grid height (angle from the epipole), width = 2x
        "min_depth_percentile": 1.0,  # nearest plausible depth: this percentile of a camera's sparse-point distances
        "min_depth_factor": 0.5,  # ... times this factor; bounds the disparity search (model units are arbitrary)
        "max_disparity_deg": 45.0,  # cap of the disparity search (wide baselines then lose their nearest points)
        "epipole_margin_deg": 8.0,  # pixels closer than this to an epipole are masked
        "max_range_error_per_px": 0.05,  # drop ranges whose relative error per pixel of disparity error exceeds this
        "block_size": 5,  # SGBM matching window side (odd)
        "min_texture_std": 2.0,  # grey-level std below which a pixel counts as untextured (not matched)
        "min_latitude_deg": -90.0,  # range maps are invalid below this latitude (tripod / hand)
        "combine_tolerance": 0.02,  # relative agreement of a panorama's pair estimates (conflicting ones are dropped)
        "min_consistent": 1,  # other depth maps that must agree for a fused point
        "consistency_tolerance": 0.02,  # relative range tolerance for agreement
        "fusion_views": 4,  # nearest other panoramas checking each panorama's points
        "fusion_stride": 2,  # fuse every n-th pixel of the range maps in both directions (the cloud is voxelised)
        "voxel_size": 0.0,  # voxel size of the fused cloud (0 = 0.2% of the scene's size)
        "outlier_neighbours": 20,  # statistical outlier removal: neighbours
        "outlier_std_ratio": 2.0,  # statistical outlier removal: std ratio
        "preview": True,  # render densify/dense_preview.png
    },
}


# Allowed values beyond the type: a set of choices, or (min, max) bounds (None = unbounded).
CONSTRAINTS: dict[str, object] = {
    "features.working_width": (0, None),
    "features.face_size": (0, None),
    "features.margin_deg": (0.0, 30.0),
    "features.max_features_per_face": (0, None),
    "features.min_latitude_deg": (-90.0, 90.0),
    "features.max_latitude_deg": (-90.0, 90.0),
    "matches.pairs": {"exhaustive", "sequential"},
    "matches.window": (1, None),
    "matches.ratio": (0.0, 1.0),
    "filter.min_hand_points": (8, None),  # the 8-point algorithm needs 8
    "filter.threshold_deg": (0.0, 90.0),
    "filter.max_iterations": (1, None),
    "filter.confidence": (0.0, 0.999999999),
    "filter.min_inliers": (8, None),
    "epipoles.min_cheiral_ratio": (0.0, 1.0),
    "registration.model": {"general", "planar"},
    "registration.min_inliers": (8, None),
    "registration.max_rotation_residual_deg": (0.0, 180.0),
    "registration.max_direction_residual_deg": (0.0, 180.0),
    "triangulation.max_reprojection_error_deg": (0.0, 90.0),
    "triangulation.min_triangulation_angle_deg": (0.0, 90.0),
    "triangulation.ba_loss_scale_deg": (0.0, 90.0),
    "triangulation.ba_max_iterations": (1, None),
}


class ConfigError(ValueError):
    """pipeline.yaml or a --set override is invalid."""


def load_config(path: Path | None, overrides: list[str] = ()) -> dict[str, dict[str, Any]]:
    """Defaults, updated by the YAML file at `path` (optional) and by `stage.key=value` overrides."""
    config = copy.deepcopy(DEFAULTS)
    if path is not None:
        path = Path(path)
        if not path.exists():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML: {e}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping of stage sections, got {type(data).__name__}")
        for section, values in data.items():
            _merge(config, section, values, where=str(path))
    for item in overrides:
        key, sep, raw = item.partition("=")
        section, dot, name = key.partition(".")
        if not sep or not dot:
            raise ConfigError(f"--set {item!r}: expected stage.key=value")
        _merge(config, section, {name: yaml.safe_load(raw)}, where=f"--set {item}")
    return config


def _merge(config: dict, section: str, values: Any, where: str) -> None:
    if section not in DEFAULTS:
        raise ConfigError(f"{where}: unknown section {section!r} (known: {', '.join(DEFAULTS)})")
    if values is None:
        return
    if not isinstance(values, dict):
        raise ConfigError(f"{where}: section {section!r} must be a mapping, got {type(values).__name__}")
    for key, value in values.items():
        if key not in DEFAULTS[section]:
            raise ConfigError(f"{where}: unknown key {section}.{key} (known: {', '.join(DEFAULTS[section])})")
        config[section][key] = _checked(value, DEFAULTS[section][key], f"{where}: {section}.{key}")
        _within(config[section][key], CONSTRAINTS.get(f"{section}.{key}"), f"{where}: {section}.{key}")


def _within(value: Any, constraint, name: str) -> None:
    if constraint is None:
        return
    if isinstance(constraint, set):
        if value not in constraint:
            raise ConfigError(f"{name} must be one of {sorted(constraint)}, got {value!r}")
        return
    low, high = constraint
    if (low is not None and value < low) or (high is not None and value > high):
        raise ConfigError(f"{name} must lie in [{low}, {'∞' if high is None else high}], got {value!r}")


def _checked(value: Any, default: Any, name: str) -> Any:
    expected = type(default)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if type(value) is not expected:
        raise ConfigError(f"{name} must be {expected.__name__}, got {value!r} ({type(value).__name__})")
    return value
