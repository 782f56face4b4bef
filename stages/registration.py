"""Stage 5 — global registration: absolute rotations and positions from the pairwise relative poses."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from fullview.io.artifacts import load_npz, save_json
from fullview.io.dataset import Dataset
from fullview.io.store import EPIPOLES_VERSION, REGISTRATION_VERSION, save_poses
from fullview.io.workspace import Workspace
from fullview.sfm.registration import register

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("epipoles",)
INPUTS: tuple[str, ...] = ()


def run(*, config: dict, dataset: Dataset, ws: Workspace, out_dir: Path) -> dict:
    if config["model"] not in ("general", "planar"):
        raise ValueError(f"registration.model must be 'general' or 'planar', got {config['model']!r}")
    epi = load_npz(ws.epipoles_path(), EPIPOLES_VERSION, ("pairs", "R_j_from_i", "t_j_from_i", "valid"))
    weights = np.where(epi["valid"], epi["num_inliers"], 0).astype(np.float64)
    names = dataset.image_names
    reg = register(num_images=len(names), pairs=epi["pairs"], R_j_from_i=epi["R_j_from_i"],
                   t_j_from_i=epi["t_j_from_i"], weights=weights, model=config["model"], seed=config["seed"],
                   e_ij=epi["e_i"], e_ji=epi["e_j"], min_weight=config["min_inliers"],
                   max_rotation_residual_deg=config["max_rotation_residual_deg"],
                   max_direction_residual_deg=config["max_direction_residual_deg"])
    R = np.where(reg.registered[:, None, None], reg.R_cam_from_world, np.eye(3))
    t = np.where(reg.registered[:, None], reg.t_cam_from_world, 0.0)
    save_poses(ws.registration_path(out_dir), REGISTRATION_VERSION, image_names=names, registered=reg.registered,
               R_cam_from_world=R, t_cam_from_world=t, pair_inlier_mask=reg.pair_inlier_mask,
               rotation_residual_deg=reg.rotation_residual_deg, direction_residual_deg=reg.direction_residual_deg)
    unregistered = [n for n, ok in zip(names, reg.registered) if not ok]
    if unregistered:
        log.warning("could not register %d image(s): %s", len(unregistered), ", ".join(unregistered))
    summary = {"registered": int(reg.registered.sum()), "images": len(names), "unregistered": unregistered,
               "model": config["model"], "inlier_pairs": int(reg.pair_inlier_mask.sum()),
               "epipole_cost": float(reg.epipole_cost)}
    save_json(out_dir / "registration.json", summary)
    return summary
