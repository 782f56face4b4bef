"""Stage 5 — global registration: absolute rotations and positions from the pairwise relative poses."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from fullview.io.errors import FullviewError
from fullview.sfm.options import RegistrationOptions
from fullview.sfm.registration import relative_from_absolute
from fullview.sfm.registration.models import ModelSet, PairLinks, build_models
from fullview.sfm.registration.diagnosis import pairs_toward_main, unregistered_reasons
from fullview.sfm.registration.evidence import placements, verdict_counts, verified_mask, weakest_links
from fullview.sfm.rotations import angle_between_deg, rotation_angle_deg
from fullview.sfm.tracks import build_tracks
from fullview.stages.protocol import StageContext

log = logging.getLogger(__name__)

VERSION = 2
UPSTREAM = ("epipoles",)
INPUTS: tuple[str, ...] = ()


class NothingToRegister(FullviewError):
    """No pair of images survived verification, so there is no model to build."""


def run(ctx: StageContext) -> dict:
    options: RegistrationOptions = ctx.options
    epi = ctx.ws.load_epipoles()
    verified = ctx.ws.load_inliers()
    usable = epi["valid"] & ((epi["num_inliers"] >= options.min_inliers) | _weak_verified(verified))
    if not usable.any():
        raise NothingToRegister(f"{ctx.dataset.root}: no image pair has a usable relative pose (verified pairs with "
                                f"a baseline and >= registration.min_inliers={options.min_inliers} inliers); "
                                "nothing to register")
    weights = np.where(usable, epi["num_inliers"], 0).astype(np.float64)  # 0: not used
    names = ctx.dataset.image_names
    obs = ctx.ws.load_observations(ctx.dataset)
    tracks, _ = build_tracks(track_matches(ctx.dataset, verified, obs, weights > 0), [len(o["bearings"]) for o in obs])
    links = PairLinks(pairs=epi["pairs"], R_j_from_i=epi["R_j_from_i"], t_j_from_i=epi["t_j_from_i"],
                      weights=weights, e_i=epi["e_i"], e_j=epi["e_j"])
    models = build_models(links=links, tracks=tracks, bearings=[o["bearings"] for o in obs], options=options,
                          descriptors=_descriptors(ctx, obs) if options.resection else None,
                          pair_matches=_raw_matches(ctx) if (options.min_weak_pair_inliers
                                                              or options.join_by_weak_pairs) else None,
                          gravity=verified.extra.get("gravity"), weak_join_threshold_rad=_filter_threshold(ctx),
                          wall_axes=verified.extra.get("manhattan_axis"))
    R, C, model_id = models.R_cam_from_world, models.centers, models.model_id
    t = -np.einsum("nab,nb->na", R, C)
    rot_res, dir_res, pair_ok = _judge_pairs(epi, weights, models, t, options)
    placed = model_id >= 0
    reasons = _reasons(ctx, obs, verified, epi, usable, placed)
    sizes = models.sizes()
    links_toward_main = _pairs_toward_main(verified, epi, model_id, names)
    toward_main = {m: ", ".join(f"{a} – {b} ({raw} raw matches, {n} inliers)" for a, b, raw, n in found)
                   for m, found in links_toward_main.items()}
    for k in np.flatnonzero(model_id > 0):  # outside the main model, but placed: say where
        reasons[names[k]] = (f"in model {model_id[k]} ({sizes[model_id[k]]} images), not joined to model 0 by "
                             "verified pairs or shared points")
    for k in models.scale_free:
        if model_id[k] != 0:
            reasons[names[k]] = (reasons.get(names[k], "") + "; " if k in reasons else "") + (
                "its part of the view graph meets model 0 where the pair directions fix no scale, and too few shared "
                "points fix it")
    for name, reason in reasons.items():
        log.warning("%s is not in model 0: %s", name, reason)
    if len(sizes) > 1:
        log.warning("%d separate models (sizes %s): no verified pairs or shared points join them; model 0 is the "
                    "main one (densify, viewer)", len(sizes), sizes)
        for m, text in toward_main.items():
            log.warning("model %d meets model 0 best at %s: too few to verify alone; 8 hand points across one of "
                        "them (hand_points.yaml) join the models", m, text)
    records = placements(names=names, model_id=model_id, own=models.own, join_records=models.join_records,
                         approximate=models.approximate, pairs=epi["pairs"], weights=weights, pair_ok=pair_ok)
    verdicts = verdict_counts(records, len(names))
    if verdicts["approximate"]:
        log.warning("%d camera(s) placed by joins nothing confirms (approximate: out of densify and the exports): %s",
                    verdicts["approximate"], [n for n, r in records.items() if r["verdict"] == "approximate"])
    summary = {"registered": int((model_id == 0).sum()), "images": len(names), "models": sizes,
               "verdicts": verdicts,
               "weak_pairs": len({(i, j) for i, _, j, _ in models.weak_pair_matches}),
               "in_models": int(placed.sum()), "unregistered": [n for n, ok in zip(names, placed) if not ok],
               "unregistered_reasons": reasons, "model_of_image": {n: int(k) for n, k in zip(names, model_id)},
               "attached_by_points": [names[k] for k in models.attached],
               "resected": [names[k] for k in models.resected],
               "merged": [{"images": [names[k] for k in m["images"]], "points": m["points"]} for m in models.merges],
               "joined_parts": [{"images": [names[k] for k in j["images"]], "tracks": j["tracks"],
                                 # every part joins by tracks agreeing on its scale (confirmed); kept_averaging: they
                                 # agree with averaging's own placement, which stays
                                 "scale": j["scale"], "confirmed": True, "kept_averaging": j.get("confirmed", False)}
                                for j in models.joins],
               "matched_2d3d": [names[k] for k in models.matched],
               "pairs_toward_model_0": {str(m): text for m, text in toward_main.items()},
               "model": options.model, "inlier_pairs": int(pair_ok.sum()), "epipole_cost": float(models.epipole_cost),
               "weakest_links": weakest_links(records, links_toward_main), "placements": records}
    ctx.out.save_registration(report=summary, image_names=names, registered=model_id == 0, model_id=model_id,
                              R_cam_from_world=R, t_cam_from_world=t, pair_inlier_mask=pair_ok,
                              rotation_residual_deg=rot_res, direction_residual_deg=dir_res,
                              verified=verified_mask(names, records),
                              matches_2d3d=np.array(models.matches_2d3d, np.int64).reshape(-1, 4),
                              weak_pair_matches=np.array(models.weak_pair_matches, np.int64).reshape(-1, 4))
    return summary


class NormalisedDescriptors(Sequence):
    """Per image, its SIFT descriptors L2-normalised (2D-3D matching compares them by Euclidean distance), read from
    the workspace when first indexed: registration matches descriptors only for images (or models) that the
    view graph left out, so usually none is read (at 24 views all of them held 85 MB). `counts` gives each image's
    number without reading it."""

    def __init__(self, ws, names: list[str], counts: list[int]):
        self.ws, self.names, self.counts = ws, names, counts
        self._loaded: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, k: int) -> np.ndarray:
        k = int(k)
        if k not in self._loaded:
            d = np.asarray(self.ws.load_descriptors(self.names[k]), np.float32)
            self._loaded[k] = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return self._loaded[k]


def _descriptors(ctx: StageContext, obs) -> NormalisedDescriptors:
    return NormalisedDescriptors(ctx.ws, list(ctx.dataset.image_names), [int(o["num_sift"]) for o in obs])


def _filter_threshold(ctx: StageContext) -> float | None:
    """The filter's inlier threshold (radians), from its manifest: weak pairs between models are fitted as it fits
    pairs. None when the manifest does not record it."""
    value = ((ctx.ws.read_manifest("filter") or {}).get("params") or {}).get("threshold_deg")
    return None if value is None else float(np.radians(value))


def _pairs_toward_main(verified, epi, model_id: np.ndarray, names: list[str]) -> dict[int, list]:
    """Per model beyond model 0: the pairs into model 0 with the most raw matches, (image of the model, image of
    model 0, raw matches, inliers) each, most first: where hand points would join the two."""
    num_raw = np.asarray(verified.extra.get("num_raw", np.zeros(len(verified.pairs))), np.int64)
    pairs = np.asarray(verified.pairs, np.int64).reshape(-1, 2)
    inliers = {(int(i), int(j)): int(n) for (i, j), n in zip(epi["pairs"], epi["num_inliers"])}
    out = {}
    for m in range(1, int(model_id.max(initial=0)) + 1):
        found = pairs_toward_main(pairs=pairs, num_raw=num_raw, model_id=model_id, model=m)
        if found:
            out[m] = [(names[a], names[b], raw, inliers.get((min(a, b), max(a, b)), 0)) for a, b, raw in found]
    return out


def _raw_matches(ctx: StageContext) -> dict[tuple[int, int], np.ndarray]:
    """Every matched pair's raw matches (before verification): the evidence of pairs too weak to verify alone."""
    raw = ctx.ws.load_matches()
    return {(int(i), int(j)): np.asarray(m, np.int64) for (i, j), m in zip(raw.pairs, raw.matches)}


def track_matches(dataset, verified, obs, use: np.ndarray, matches_2d3d: np.ndarray | None = None
                  ) -> dict[tuple[int, int], np.ndarray]:
    """Matches tracks are built from: the inliers of the pairs in `use`, plus the hand correspondences of every
    matched pair that has some (the filter records them only with filter.use_hand_points), plus the matches
    registration added (`matches_2d3d` rows (image, feature, image, feature): its 2D-3D matches and the inliers of
    the weak pairs it checked). Hand points are the
    user's own correspondences: a hand point seen on both sides of a closed door joins the two models even where
    no pair across it verifies."""
    num_sift = [int(o["num_sift"]) for o in obs]
    num_hand = verified.extra.get("num_hand", np.zeros(len(verified.pairs), np.int64))
    out = {}
    for k, (pair, m) in enumerate(zip(verified.pairs, verified.matches)):
        parts = [m] if use[k] and len(m) else []
        if num_hand[k] > 0:
            parts.append(dataset.hand_pair_matches(num_sift, *pair))
        if parts:
            out[pair] = np.concatenate(parts)
    rows = np.zeros((0, 4), np.int64) if matches_2d3d is None else np.asarray(matches_2d3d, np.int64)
    rows = np.where((rows[:, 0] > rows[:, 2])[:, None], rows[:, [2, 3, 0, 1]], rows)  # lower image first
    pair_of = rows[:, [0, 2]]
    for i, j in np.unique(pair_of, axis=0):
        found = rows[(pair_of == (i, j)).all(axis=1)][:, [1, 3]]
        key = (int(i), int(j))
        out[key] = np.concatenate([out.get(key, np.zeros((0, 2), np.int64)), found]).astype(np.int64)
    return out


def _weak_verified(verified) -> np.ndarray:
    """(P,) pairs the filter kept below its min_inliers (hand points or the upright model verified them)."""
    return verified.extra.get("weak_verified", np.zeros(len(verified.pairs), bool)).astype(bool)


def _judge_pairs(epi, weights, models: ModelSet, t, options: RegistrationOptions):
    """Per pair: rotation and direction residuals, and whether it is a consistent pair inside one model.

    Averaging judged the pairs between the images it placed (the planar model by yaw only); every other pair inside
    a model (attached, resected or merged images) is judged by its residuals here."""
    pairs = epi["pairs"]
    i, j = pairs[:, 0], pairs[:, 1]
    rot_res, dir_res = _pair_residuals(epi, models.R_cam_from_world, t)
    same = (models.model_id[i] == models.model_id[j]) & (models.model_id[i] >= 0)
    rot_res, dir_res = np.where(same, rot_res, np.nan), np.where(same, dir_res, np.nan)
    by_averaging = (models.averaged_in[i] == models.averaged_in[j]) & (models.averaged_in[i] >= 0)
    by_residuals = ((weights > 0) & (rot_res <= options.max_rotation_residual_deg)
                    & (dir_res <= options.max_direction_residual_deg))
    return rot_res, dir_res, same & np.where(by_averaging, models.averaging_verdict, by_residuals)


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


def _pair_residuals(epi, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: angle between measured and model relative rotation, and between translation directions."""
    i, j = epi["pairs"][:, 0], epi["pairs"][:, 1]
    R_rel, t_rel = relative_from_absolute(R, t, i, j)
    return rotation_angle_deg(epi["R_j_from_i"], R_rel), angle_between_deg(epi["t_j_from_i"], t_rel)
