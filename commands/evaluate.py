"""`fullview eval`: the current reconstruction against the dataset's ground_truth/ (poses, and dense results when
the dataset has ground-truth depth), and on any dataset the checks that need none: the leave-one-out pose check
(``sfm.pose_check``) and the dense leave-one-out agreement."""

from __future__ import annotations

import hashlib
import logging
import sys

import numpy as np

from fullview.io.dataset import Dataset, DatasetError
from fullview.io.artifacts import ArtifactError
from fullview.io.workspace import Workspace, WorkspaceBusy, folder_of, select_model
from fullview.sfm import pose_check as pose_check_module
from fullview.sfm.dense import scene_size
from fullview.sfm.dense_agreement import visible_agreement
from fullview.sfm.dense_metrics import dense_metrics, leave_one_out_agreement
from fullview.sfm.metrics import Similarity, pose_metrics, umeyama
from fullview.stages.runner import Pipeline, RunnerError, code_hashes, record_fingerprint

log = logging.getLogger(__name__)

AGREEMENT_TOLERANCE = 0.02  # leave-one-out agreement: relative range difference that counts as agreeing
AGREEMENT_STRIDE = 2  # ... other panoramas' pixels are splatted every this many pixels in both directions


def evaluate(pipeline: Pipeline) -> dict:
    """Pose metrics against ground truth (and dense metrics when available), and on any dataset the leave-one-out
    pose check (of the triangulation's models) and the dense leave-one-out agreement when densify is current; also
    written to eval/metrics.json when the workspace is not busy (eval is a read-only command: it never waits for a
    run)."""
    dataset, ws = pipeline.dataset, pipeline.ws
    with ws.reading():
        source = _current_model(pipeline)
        dense_current = source == "triangulation" and pipeline.status("densify", deep=True).state == "fresh"
        key = _cache_key(pipeline, source, dense_current)
        cached = _cached(ws, key)
        if cached is not None:
            log.info("eval: the results are unchanged since the last eval; its metrics are reused (%s)",
                     ws.path("eval_metrics"))
            _log_summary(cached)
            return cached
        est = ws.load_sparse() if source == "triangulation" else ws.load_registration()
        metrics = {"dataset": dataset.name, "poses_from": source}
        if dataset.has_ground_truth():
            metrics.update(_against_ground_truth(pipeline, est, source))
        if source == "triangulation":
            metrics["pose_check"] = pose_check(pipeline, est)
        if dense_current:
            metrics["dense_agreement"] = dense_agreement(dataset, ws, est)
        elif not dataset.has_ground_truth() and source != "triangulation":
            raise DatasetError(f"{dataset.root}: no ground_truth/poses.yaml and no triangulation results: nothing "
                               "to evaluate")
    _log_summary(metrics)
    _save(pipeline, metrics, key)
    return metrics


def _cache_key(pipeline: Pipeline, source: str, dense_current: bool) -> str:
    """What the metrics depend on, like a stage's fingerprint: the evaluated stages' fingerprints (settings, inputs,
    code), whether densify is current, eval's own code and the ground truth's bytes."""
    truth = pipeline.dataset.ground_truth_dir
    files = sorted(p for p in truth.rglob("*") if p.is_file()) if truth.is_dir() else []
    digest = hashlib.sha256()
    for path in files:
        digest.update(str(path.relative_to(truth)).encode() + b"\0" + path.read_bytes())
    return record_fingerprint({"poses_from": source, "dense_current": dense_current,
                               "upstream": {s: pipeline.fingerprint(s) for s in ("registration", "triangulation",
                                                                               "densify")},
                               "code": code_hashes(sys.modules[__name__]), "ground_truth": digest.hexdigest()})


def _cached(ws: Workspace, key: str) -> dict | None:
    """The metrics of the last eval when they were computed for `key` and their file is intact, else None."""
    manifest = ws.read_manifest(folder_of("eval_metrics"))
    if manifest is None or manifest.get("eval_key") != key or ws.verify(folder_of("eval_metrics"), manifest,
                                                                          deep=True):
        return None
    try:
        return ws.load_json("eval_metrics")
    except ArtifactError:
        return None


def _against_ground_truth(pipeline: Pipeline, est: dict, source: str) -> dict:
    dataset, ws = pipeline.dataset, pipeline.ws
    gt = dataset.ground_truth_poses()
    missing = [n for n in dataset.image_names if n not in gt]
    if missing:
        raise DatasetError(f"{dataset.ground_truth_dir / 'poses.yaml'}: no pose for {missing}")
    R_gt = np.stack([gt[n].R_world_from_cam.T for n in dataset.image_names])
    c_gt = np.stack([gt[n].center for n in dataset.image_names])
    metrics = pose_metrics(est["R_cam_from_world"], est["centers"], R_gt, c_gt, est["registered"])
    metrics["models"] = _model_metrics(est, R_gt, c_gt)
    metrics["in_models"] = int((est["model_id"] >= 0).sum())
    if source == "triangulation" and pipeline.status("densify", deep=True).state == "fresh":
        dense = evaluate_dense(dataset, ws, est, R_gt, c_gt)
        if dense is not None:
            metrics["dense"] = dense
    return metrics


def dense_agreement(dataset: Dataset, ws: Workspace, est: dict) -> dict:
    """Leave-one-out agreement of the densify range maps (no ground truth needed): per panorama of model 0 its valid
    share and the share of its ranged pixels within 2% of what the other panoramas predict, splatted
    (``agreement``) and with visibility (``visible_agreement``: ``sfm.dense_agreement.visible_agreement``); with the
    medians."""
    names = [n for n, ok in zip(dataset.image_names, est["registered"]) if ok]
    keep = np.asarray(est["registered"], bool)
    maps = [(d["range"] if d is not None else None) for d in (ws.load_depth(n) for n in names)]
    per_image = leave_one_out_agreement(maps, est["R_cam_from_world"][keep], est["t_cam_from_world"][keep],
                                        tolerance=AGREEMENT_TOLERANCE, stride=AGREEMENT_STRIDE)
    visible = visible_agreement(maps, est["R_cam_from_world"][keep], est["t_cam_from_world"][keep],
                                tolerance=AGREEMENT_TOLERANCE, stride=AGREEMENT_STRIDE)
    for entry, seen in zip(per_image, visible):
        entry["visible_agreement"], entry["visible_checked_share"] = seen["agreement"], seen["checked_share"]
    values = [p["agreement"] for p in per_image if p["agreement"] is not None]
    seen_values = [p["agreement"] for p in visible if p["agreement"] is not None]
    return {"tolerance": AGREEMENT_TOLERANCE,
            "median_agreement": float(np.median(values)) if values else None,
            "median_visible_agreement": float(np.median(seen_values)) if seen_values else None,
            "median_valid_share": float(np.median([p["valid_share"] for p in per_image])) if per_image else None,
            "per_image": dict(zip(names, per_image))}


def pose_check(pipeline: Pipeline, sparse: dict) -> dict:
    """The leave-one-out pose check (``sfm.pose_check``) of every camera of every model of the triangulation, with
    the stages' own thresholds: θ = triangulation.max_reprojection_error_deg (the model's inlier threshold), its
    minimum triangulation angle, and registration.min_resection_points. Per image also its model; centres relative
    to that model's size (``sfm.dense.scene_size``)."""
    dataset, ws, config = pipeline.dataset, pipeline.ws, pipeline.config
    tri, reg = config["triangulation"], config["registration"]
    options = pose_check_module.PoseCheckOptions(threshold_rad=np.radians(tri.max_reprojection_error_deg),
                                                 min_angle_rad=np.radians(tri.min_triangulation_angle_deg),
                                                 min_points=reg.min_resection_points, seed=reg.seed)
    bearings = [o["bearings"] for o in ws.load_observations(dataset)]
    names = list(sparse["image_names"])
    checks = {}
    for model in range(int(sparse["model_id"].max(initial=-1)) + 1):
        part = select_model(sparse, model)
        cams = np.flatnonzero(part["registered"])
        size = scene_size(sparse["centers"][cams], part["points"])
        found = pose_check_module.check_poses(cams, part["track_ids"], part["image_ids"], part["feature_ids"],
                                              bearings, sparse["R_cam_from_world"], sparse["t_cam_from_world"],
                                              options)
        for c in cams:
            checks[str(names[c])] = {"model": model, **found[c].as_dict(size)}
    out = pose_check_module.summarise(checks)
    out["threshold_deg"] = float(tri.max_reprojection_error_deg)
    return out


def _log_summary(metrics: dict) -> None:
    """One line per check, in plain words (the per-image figures are in the JSON and eval/metrics.json)."""
    check = metrics.get("pose_check")
    if check is not None:
        count = len(check["per_image"])
        log.info("pose check (leave-one-out): %d of %d cameras agree with the other cameras' points; disagree: %s; "
                 "unverifiable: %s; median rotation %s°, centre %s of the model's size",
                 count - len(check["flagged"]), count, ", ".join(check["disagrees"]) or "none",
                 ", ".join(check["unverifiable"]) or "none", _fmt(check["median_rot_deg"]),
                 _fmt(check["median_centre_rel"]))
    dense = metrics.get("dense_agreement")
    if dense is not None:
        log.info("dense leave-one-out agreement: median %s (visible %s), median valid share %s",
                 _fmt(dense["median_agreement"]), _fmt(dense["median_visible_agreement"]),
                 _fmt(dense["median_valid_share"]))


def eval_summary(metrics: dict) -> dict:
    """``metrics`` without its per-image and per-model lists (eval/metrics.json keeps them): what a terminal needs."""
    out = {}
    for key, value in metrics.items():
        if isinstance(value, dict):
            out[key] = {k: v for k, v in value.items() if k != "per_image"}
        elif key != "models":
            out[key] = value
    return out


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def _model_metrics(est: dict, R_gt: np.ndarray, c_gt: np.ndarray) -> list[dict]:
    """Pose metrics of every model on its own (model 0's are also the top-level figures); pairs of images in
    different models count as failures, so a model's AUC says how much of the whole scene it covers well."""
    model_id = est["model_id"]
    return [pose_metrics(est["R_cam_from_world"], est["centers"], R_gt, c_gt, model_id == k)
            for k in range(int(model_id.max(initial=-1)) + 1)]


def _current_model(pipeline: Pipeline) -> str:
    """The stage whose poses are evaluated: triangulation when fresh, else registration when fresh; an error
    naming the reason otherwise (metrics of a stale model would describe other settings or images)."""
    for stage in ("triangulation", "registration"):
        status = pipeline.chain_status(stage)
        if status.state == "fresh":
            if stage == "registration":
                log.warning("triangulation is not current: evaluating the registration's poses (before bundle "
                            "adjustment)")
            return stage
    raise RunnerError(f"{pipeline.ws.root}: the reconstruction is {status.state} ({'; '.join(status.reasons)}); "
                      "run the pipeline first")


def _save(pipeline: Pipeline, metrics: dict, key: str) -> None:
    ws = pipeline.ws
    try:
        with ws.locked(command="fullview eval"), ws.transaction(folder_of("eval_metrics")) as out:
            out.save_json("eval_metrics", metrics)
            upstream = {s: pipeline.fingerprint(s) for s in ("registration", "triangulation", "densify")}
            out.commit_manifest({"fingerprint": pipeline.fingerprint(metrics["poses_from"]), "upstream": upstream,
                                 "eval_key": key,
                                 "summary": {"poses_from": metrics["poses_from"]}})
    except (WorkspaceBusy, OSError) as e:  # eval reads; a busy or read-only workspace only loses the copy on disk
        log.warning("metrics not written to %s: %s", ws.path("eval_metrics"), e)


def evaluate_dense(dataset: Dataset, ws: Workspace, est: dict, R_gt_cam_from_world: np.ndarray,
                   c_gt: np.ndarray) -> dict | None:
    """Dense metrics of the workspace's densify results against the dataset's ground-truth depth (None when either
    is missing or fewer than 3 cameras are registered). The reconstruction is aligned by the similarity of its
    camera centres onto the true ones (as for the pose metrics)."""
    names = dataset.image_names
    gt = [dataset.ground_truth_depth(n) for n in names]
    registered = est["registered"].astype(bool)
    manifest = ws.read_manifest("densify")
    if manifest is None or any(g is None for g in gt) or registered.sum() < 3:
        return None
    sim: Similarity = umeyama(est["centers"][registered], c_gt[registered])
    depth = [ws.load_depth(n) if registered[k] else None for k, n in enumerate(names)]
    missing = {"range": np.full((1, 2), np.nan, np.float32), "valid": np.zeros((1, 2), bool)}
    depth = [d if d is not None else missing for d in depth]  # no range map: nothing of it is valid
    cloud = ws.load_dense_cloud()
    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]) if cloud is not None else None
    mesh = ws.load_dense_mesh()
    t_gt = -np.einsum("nab,nb->na", R_gt_cam_from_world, c_gt)
    out = dense_metrics(range_est=[d["range"] for d in depth], valid_est=[d["valid"] for d in depth], range_gt=gt,
                        R_gt_cam_from_world=R_gt_cam_from_world, t_gt_cam_from_world=t_gt, sim=sim, points=points,
                        scene_size=dataset.ground_truth_scene_size(c_gt), names=names,
                        mesh=(mesh["vertices"], mesh["triangles"]) if mesh is not None else None)
    out["median_pair_time_s"] = manifest.get("summary", {}).get("median_pair_time_s")
    out["stage_wall_time_s"] = manifest.get("wall_time_s")
    return out
