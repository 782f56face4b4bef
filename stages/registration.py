"""Stage 5 — global registration: absolute rotations and positions from the pairwise relative poses."""

from __future__ import annotations

import logging

import numpy as np

from fullview.io.errors import FullviewError
from fullview.sfm.attach import attach_cameras
from fullview.sfm.options import RegistrationOptions
from fullview.sfm.registration import register, relative_from_absolute
from fullview.sfm.registration.diagnosis import unregistered_reasons
from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg
from fullview.sfm.tracks import build_tracks
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 1
UPSTREAM = ("epipoles",)
INPUTS: tuple[str, ...] = ()
ATTACH_MAX_ERROR_DEG = 1.0  # points used to attach cameras: angular error bound before bundle adjustment


class NothingToRegister(FullviewError):
    """No pair of images survived verification, so there is no model to build."""


def run(ctx: StageContext) -> dict:
    options: RegistrationOptions = ctx.options
    epi = ctx.ws.load_epipoles()
    usable = epi["valid"] & (epi["num_inliers"] >= options.min_inliers)
    if not usable.any():
        raise NothingToRegister(f"{ctx.dataset.root}: no image pair has a usable relative pose (verified pairs with "
                                f"a baseline and >= registration.min_inliers={options.min_inliers} inliers); "
                                "nothing to register")
    weights = np.where(usable, epi["num_inliers"], 0).astype(np.float64)
    names = ctx.dataset.image_names
    reg = register(num_images=len(names), pairs=epi["pairs"], R_j_from_i=epi["R_j_from_i"],
                   t_j_from_i=epi["t_j_from_i"], weights=weights, model=options.model,
                   e_ij=epi["e_i"], e_ji=epi["e_j"], min_weight=options.min_inliers,
                   max_rotation_residual_deg=options.max_rotation_residual_deg,
                   max_direction_residual_deg=options.max_direction_residual_deg)
    R = np.where(reg.registered[:, None, None], reg.R_cam_from_world, np.eye(3))
    C = np.where(reg.registered[:, None], reg.centers, 0.0)
    registered, attached = reg.registered, []
    # Both attaching cameras and explaining the ones left out need the observations and inliers: read them once.
    obs = ctx.ws.load_observations(ctx.dataset) if not registered.all() else None
    verified = ctx.ws.load_inliers() if not registered.all() else None
    if not registered.all():
        result = _attach(obs, verified, epi, weights, R, C, registered)
        R, C, registered, attached = result.R_cam_from_world, result.centers, result.registered, result.attached
    t = -np.einsum("nab,nb->na", R, C)
    rot_res, dir_res = _pair_residuals(epi, R, t)
    # Averaging judged its own pairs (the planar model by yaw only); pairs of attached cameras are judged here.
    pair_ok = reg.pair_inlier_mask.copy()
    touched = (registered & ~reg.registered)[epi["pairs"]].any(axis=1)
    pair_ok[touched] = ((weights > 0) & registered[epi["pairs"][:, 0]] & registered[epi["pairs"][:, 1]]
                        & (rot_res <= options.max_rotation_residual_deg)
                        & (dir_res <= options.max_direction_residual_deg))[touched]
    unregistered = [n for n, ok in zip(names, registered) if not ok]
    reasons = _reasons(ctx, obs, verified, epi, usable, registered)
    for name, reason in reasons.items():
        log.warning("%s is not registered: %s", name, reason)
    summary = {"registered": int(registered.sum()), "images": len(names), "unregistered": unregistered,
               "unregistered_reasons": reasons,
               "attached_by_points": [names[k] for k in attached], "model": options.model,
               "inlier_pairs": int(pair_ok.sum()), "epipole_cost": float(reg.epipole_cost)}
    ctx.out.save_registration(report=summary, image_names=names, registered=registered, R_cam_from_world=R,
                              t_cam_from_world=t, pair_inlier_mask=pair_ok, rotation_residual_deg=rot_res,
                              direction_residual_deg=dir_res)
    return summary


def _reasons(ctx: StageContext, obs, verified, epi, usable, registered) -> dict[str, str]:
    """Why each unregistered image is out of the model (features, pairs, groups of the view graph)."""
    if registered.all():
        return {}
    names = ctx.dataset.image_names
    num_features = np.array([int(o["num_sift"]) for o in obs])
    no_baseline = verified.extra.get("no_baseline", np.zeros(len(verified.pairs), bool)).astype(bool)
    return unregistered_reasons(names=names, registered=registered, num_features=num_features, pairs=epi["pairs"],
                                num_inliers=epi["num_inliers"], usable=usable, no_baseline=no_baseline,
                                min_features=8, min_inliers=ctx.options.min_inliers)


def _attach(obs, verified, epi, weights, R, C, registered):
    """Place the cameras averaging left out (single-pair links) from their pair and the model's points."""
    tracks, _ = build_tracks({p: m for p, m, w in zip(verified.pairs, verified.matches, weights) if w > 0 and len(m)},
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
