"""Stage 5 — global registration: absolute rotations and positions from the pairwise relative poses."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fullview.io.artifacts import load_npz, save_json
from fullview.io.dataset import Dataset
from fullview.io.store import EPIPOLES_VERSION, REGISTRATION_VERSION, save_poses
from fullview.io.workspace import Workspace
from fullview.io.store import load_observations, load_pair_data
from fullview.sfm.attach import attach_cameras
from fullview.sfm.registration import register, relative_from_absolute
from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg
from fullview.sfm.tracks import build_tracks

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("epipoles",)
INPUTS: tuple[str, ...] = ()
ATTACH_MAX_ERROR_DEG = 1.0  # points used to attach cameras: angular error bound before bundle adjustment


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    if config["model"] not in ("general", "planar"):
        raise ValueError(f"registration.model must be 'general' or 'planar', got {config['model']!r}")
    epi = load_npz(ws.epipoles_path(), EPIPOLES_VERSION, ("pairs", "R_j_from_i", "t_j_from_i", "valid"))
    usable = epi["valid"] & (epi["num_inliers"] >= config["min_inliers"])
    weights = np.where(usable, epi["num_inliers"], 0).astype(np.float64)
    names = dataset.image_names
    reg = register(num_images=len(names), pairs=epi["pairs"], R_j_from_i=epi["R_j_from_i"],
                   t_j_from_i=epi["t_j_from_i"], weights=weights, model=config["model"], seed=config["seed"],
                   e_ij=epi["e_i"], e_ji=epi["e_j"], min_weight=config["min_inliers"],
                   max_rotation_residual_deg=config["max_rotation_residual_deg"],
                   max_direction_residual_deg=config["max_direction_residual_deg"])
    R = np.where(reg.registered[:, None, None], reg.R_cam_from_world, np.eye(3))
    C = np.where(reg.registered[:, None], reg.centers, 0.0)
    registered, attached = reg.registered, []
    if not registered.all() and (weights > 0).any():
        result = _attach(dataset, ws, epi, weights, R, C, registered)
        R, C, registered, attached = result.R_cam_from_world, result.centers, result.registered, result.attached
    t = -np.einsum("nab,nb->na", R, C)
    rot_res, dir_res = _pair_residuals(epi, R, t)
    # Averaging judged its own pairs (the planar model by yaw only); pairs of attached cameras are judged here.
    pair_ok = reg.pair_inlier_mask.copy()
    touched = (registered & ~reg.registered)[epi["pairs"]].any(axis=1)
    pair_ok[touched] = ((weights > 0) & registered[epi["pairs"][:, 0]] & registered[epi["pairs"][:, 1]]
                        & (rot_res <= config["max_rotation_residual_deg"])
                        & (dir_res <= config["max_direction_residual_deg"]))[touched]
    save_poses(ws.registration_path(out_dir), REGISTRATION_VERSION, image_names=names, registered=registered,
               R_cam_from_world=R, t_cam_from_world=t, pair_inlier_mask=pair_ok,
               rotation_residual_deg=rot_res, direction_residual_deg=dir_res)
    unregistered = [n for n, ok in zip(names, registered) if not ok]
    if unregistered:
        log.warning("could not register %d image(s): %s", len(unregistered), ", ".join(unregistered))
    summary = {"registered": int(registered.sum()), "images": len(names), "unregistered": unregistered,
               "attached_by_points": [names[k] for k in attached], "model": config["model"],
               "inlier_pairs": int(pair_ok.sum()), "epipole_cost": float(reg.epipole_cost)}
    save_json(out_dir / "registration.json", summary)
    return summary


def _attach(dataset, ws, epi, weights, R, C, registered):
    """Place the cameras averaging left out (single-pair links) from their pair and the model's points."""
    obs = load_observations(ws, dataset)
    pairs, inliers, _ = load_pair_data(ws.inliers_path())
    tracks, _ = build_tracks({p: m for p, m, w in zip(pairs, inliers, weights) if w > 0 and len(m)},
                             [len(o["bearings"]) for o in obs])
    return attach_cameras(R_cam_from_world=R, centers=C, registered=registered, pairs=epi["pairs"],
                          R_j_from_i=epi["R_j_from_i"], t_j_from_i=epi["t_j_from_i"], weights=weights,
                          tracks=tracks, bearings_per_image=[o["bearings"] for o in obs],
                          max_error_rad=np.radians(ATTACH_MAX_ERROR_DEG), min_angle_rad=np.radians(1.0))


def _pair_residuals(epi, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: angle between measured and model relative rotation, and between translation directions."""
    i, j = epi["pairs"][:, 0], epi["pairs"][:, 1]
    R_rel, t_rel = relative_from_absolute(R, t, i, j)
    return rotation_angle_deg(epi["R_j_from_i"], R_rel), angle_between_deg(epi["t_j_from_i"], t_rel)
