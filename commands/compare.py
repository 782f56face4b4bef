"""`fullview compare`: our reconstruction against pycolmap's panorama pipeline on the same images.

COLMAP's run (pycolmap.panorama.reconstruct, exhaustive matcher, CPU) is cached by the stage runner
(`run_cached`) in the workspace folder `colmap_<render type>/`: its fingerprint covers the image contents, the
options and the pycolmap version, so it reruns only when one of those changes. Our pipeline is brought up to date
until triangulation through the Pipeline. Results go to `compare_<render type>/`: `colmap.json`, `colmap.md` and
`top_view.png`.

A stored baseline (benchmarks/baseline.json) gates the result: see `check_against_baseline`.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from fullview.io.artifacts import atomic_path
from fullview.io.colmap import load_reconstruction, model_arrays, pycolmap_version, reconstruct_equirectangular
from fullview.io.config import ConfigError
from fullview.io.dataset import Dataset
from fullview.io.workspace import StageWriter, Workspace, folder_of
from fullview.sfm import compare as cmp
from fullview.sfm.metrics import pose_metrics
from fullview.stages import PIPELINE
from fullview.stages.runner import Pipeline, RunnerError, record_fingerprint, run_cached

log = logging.getLogger(__name__)

COLMAP_VERSION = 1  # format of the cached COLMAP run (bump to force a rerun)
RENDER_TYPES = ("spherical", "perspective_overlapping", "perspective_non_overlapping")
SPARSE_STAGES = PIPELINE[:PIPELINE.index("triangulation") + 1]
DEFAULT_BASELINE = Path(__file__).resolve().parents[1] / "benchmarks" / "baseline.json"


# --------------------------------------------------------------------------------------------- COLMAP, cached
def images_fingerprint(dataset: Dataset) -> str:
    """sha256 (short) over the dataset's image names and contents: which scene a baseline entry belongs to."""
    return record_fingerprint({n: dataset.image_hash(n) for n in dataset.image_names})


def colmap_record(dataset: Dataset, render_type: str, matcher: str = "exhaustive", seed: int = 0) -> dict:
    """What the cached COLMAP run depends on: images, options, pycolmap version."""
    return {"stage": f"colmap_{render_type}", "version": COLMAP_VERSION,
            "params": {"render_type": render_type, "matcher": matcher, "seed": seed, "use_gpu": False},
            "inputs": {"images": {n: dataset.image_hash(n) for n in dataset.image_names}},
            "pycolmap": pycolmap_version()}


def colmap_reference(dataset: Dataset, ws: Workspace, *, render_type: str = "spherical", matcher: str = "exhaustive",
                     seed: int = 0, force: bool = False) -> tuple[Path | None, dict]:
    """COLMAP's model folder (None when it reconstructed nothing) and its manifest; cached by the stage runner."""
    if render_type not in RENDER_TYPES:
        raise RunnerError(f"unknown render type {render_type!r} (expected one of {', '.join(RENDER_TYPES)})")

    def produce(out: StageWriter) -> dict:
        log.info("running pycolmap.panorama.reconstruct (%s, %s matcher, CPU)", render_type, matcher)
        # exactly the dataset's image list (no stray files such as README.md); not "images", which the
        # perspective render types fill with their rendered views
        images = out.path("colmap_reference_images", render_type=render_type)
        images.mkdir()
        for image_name in dataset.image_names:
            os.symlink(dataset.image_path(image_name).resolve(), images / image_name)
        result = reconstruct_equirectangular(images, out.dir, out.path("colmap_reference", render_type=render_type),
                                             render_type=render_type, matcher=matcher, seed=seed)
        summary = {"num_models": result["num_models"], "colmap_wall_time_s": result["wall_time_s"],
                   "model": result["model_dir"] is not None}
        if result["model_dir"] is not None:
            rec = load_reconstruction(result["model_dir"])
            summary.update(registered=int(rec.num_reg_images()), points=int(rec.num_points3D()))
        return summary

    folder = folder_of("colmap_reference", render_type=render_type)
    with ws.locked(command="fullview compare"):
        manifest = run_cached(ws, folder, colmap_record(dataset, render_type, matcher, seed), produce, force=force)
    model = ws.path("colmap_reference", render_type=render_type) if manifest["summary"].get("model") else None
    return model, manifest


# --------------------------------------------------------------------------------------------- both models
def our_model(dataset: Dataset, ws: Workspace) -> dict:
    """Our bundle-adjusted poses, points and observations (bearings from the features + hand points)."""
    if ws.poses_source() != "triangulation":
        raise RunnerError(f"{ws.root}: triangulation is not current; run the pipeline until triangulation")
    sparse = ws.load_sparse_model(0)
    poses = sparse
    obs = ws.load_observations(dataset)
    offsets = np.cumsum([0] + [len(o["bearings"]) for o in obs])
    all_bearings = np.concatenate([o["bearings"] for o in obs])
    bearings = all_bearings[offsets[sparse["image_ids"]] + sparse["feature_ids"]]
    centers = poses["centers"].astype(np.float64).copy()
    centers[~poses["registered"]] = np.nan
    return {"R_cam_from_world": poses["R_cam_from_world"], "t_cam_from_world": poses["t_cam_from_world"],
            "centers": centers, "registered": poses["registered"].astype(bool), "points": sparse["points"],
            "obs_point": sparse["track_ids"], "obs_image": sparse["image_ids"], "obs_bearings": bearings}


def _side_stats(model: dict, wall_time_s: float | None) -> dict:
    ok = model["obs_image"] >= 0
    errors = cmp.angular_reprojection_errors(model["R_cam_from_world"], model["t_cam_from_world"], model["points"],
                                             model["obs_image"][ok], model["obs_point"][ok],
                                             model["obs_bearings"][ok])
    stats = cmp.model_statistics(registered=model["registered"], points=model["points"],
                                 obs_image=model["obs_image"], obs_point=model["obs_point"], errors_rad=errors)
    stats["wall_time_s"] = None if wall_time_s is None else round(float(wall_time_s), 2)
    return stats


def _empty_model(n: int) -> dict:
    return {"R_cam_from_world": np.tile(np.eye(3), (n, 1, 1)), "t_cam_from_world": np.zeros((n, 3)),
            "centers": np.full((n, 3), np.nan), "registered": np.zeros(n, bool), "points": np.zeros((0, 3)),
            "obs_point": np.zeros(0, np.int64), "obs_image": np.zeros(0, np.int64), "obs_bearings": np.zeros((0, 3))}


# --------------------------------------------------------------------------------------------- the comparison
def compare(dataset: Dataset, ws: Workspace, pipeline: Pipeline, *, render_type: str = "spherical",
            force_colmap: bool = False, baseline_path: Path | None = DEFAULT_BASELINE) -> dict:
    """Run what is stale, compare, write compare_<render type>/colmap.{json,md} and top_view.png; the result
    (with `gate`)."""
    if baseline_path is not None and Path(baseline_path).is_file():
        load_baseline(Path(baseline_path))  # a broken baseline fails now, not after the COLMAP run
    ran = pipeline.run(until="triangulation")
    log.info("our pipeline: %s", ", ".join(ran) if ran else "fresh")
    model_dir, colmap_manifest = colmap_reference(dataset, ws, render_type=render_type, force=force_colmap)
    names = dataset.image_names
    ours = our_model(dataset, ws)
    theirs = model_arrays(load_reconstruction(model_dir), names) if model_dir is not None else _empty_model(len(names))
    manifests = {s: ws.read_manifest(s) for s in SPARSE_STAGES}
    our_time = sum(m["wall_time_s"] for m in manifests.values() if m)

    result = {"dataset": dataset.name, "render_type": render_type, "pycolmap": colmap_manifest["pycolmap"],
              "images": names, "images_sha256": images_fingerprint(dataset),
              "ours": _side_stats(ours, our_time), "colmap": _side_stats(theirs, colmap_manifest["wall_time_s"])}
    result["ours"]["stage_time_s"] = {s: m["wall_time_s"] for s, m in manifests.items() if m}
    result["registered"] = {"ours": ours["registered"].tolist(), "colmap": theirs["registered"].tolist()}
    agreement = cmp.relative_agreement(ours["R_cam_from_world"], np.nan_to_num(ours["centers"]), ours["registered"],
                                       theirs["R_cam_from_world"], np.nan_to_num(theirs["centers"]),
                                       theirs["registered"])
    result["agreement"] = agreement.summary()
    result["agreement"]["per_pair"] = [
        {"pair": [names[i], names[j]], "rotation_deg": float(r), "translation_deg": float(t)}
        for (i, j), r, t in zip(agreement.pairs.tolist(), agreement.rotation_deg, agreement.translation_deg)]
    both = ours["registered"] & theirs["registered"]
    sim = None
    if both.any():
        sim = cmp.align_cameras(ours["R_cam_from_world"], ours["centers"], theirs["R_cam_from_world"],
                                theirs["centers"], both)
        result["alignment"] = cmp.aligned_differences(sim, ours["R_cam_from_world"], ours["centers"],
                                                      theirs["R_cam_from_world"], theirs["centers"], both)
    if dataset.has_ground_truth():
        gt = dataset.ground_truth_poses()
        R_gt = np.stack([gt[n].R_world_from_cam.T for n in names])
        c_gt = np.stack([gt[n].center for n in names])
        result["ground_truth"] = {
            side: pose_metrics(m["R_cam_from_world"], np.nan_to_num(m["centers"]), R_gt, c_gt, m["registered"])
            for side, m in (("ours", ours), ("colmap", theirs))}
    result["gate"] = check_against_baseline(result, baseline_path)

    markdown = format_markdown(result)
    with ws.locked(command="fullview compare"), ws.transaction(folder_of("compare_report", render_type=render_type)) as out:
        out.save_json("compare_report", result, render_type=render_type)
        out.save_text("compare_markdown", markdown, render_type=render_type)
        plot_top_view(out.path("compare_top_view", render_type=render_type), ours, theirs, sim, names,
                      title=f"{dataset.name}: cameras after alignment (ours → COLMAP {render_type})")
        upstream = {"triangulation": manifests["triangulation"]["fingerprint"],
                    folder_of("colmap_reference", render_type=render_type): colmap_manifest["fingerprint"]}
        out.commit_manifest({"fingerprint": record_fingerprint(upstream), "upstream": upstream,
                             "summary": {"gate": result["gate"]["status"]}})
    result["markdown"] = markdown
    return result


# --------------------------------------------------------------------------------------------- baseline
def check_against_baseline(result: dict, baseline_path: Path | None) -> dict:
    """Gate the result with the stored baseline of its dataset (same render type); not gated when absent."""
    current = cmp.gated_metrics(result)
    if baseline_path is None:
        return {"status": "not gated", "reason": "no baseline given", "metrics": current, "failures": []}
    if not Path(baseline_path).exists():
        return {"status": "not gated", "reason": f"{baseline_path} not found", "metrics": current, "failures": []}
    baseline = load_baseline(Path(baseline_path))
    entry = baseline.get("datasets", {}).get(result["dataset"])
    if entry is None:
        return {"status": "not gated", "reason": f"{result['dataset']} not in {baseline_path}", "metrics": current,
                "failures": []}
    if entry.get("render_type", baseline.get("render_type", "spherical")) != result["render_type"]:
        return {"status": "not gated", "reason": "baseline recorded with another render type", "metrics": current,
                "failures": []}
    if entry.get("images_sha256") and result.get("images_sha256") != entry["images_sha256"]:
        return {"status": "not gated", "reason": f"baseline {result['dataset']!r} was recorded on other images",
                "metrics": current, "failures": []}
    tolerances = {**baseline.get("tolerances", {}), **entry.get("tolerances", {})}
    failures = cmp.gate(current, entry["metrics"], tolerances)
    return {"status": "fail" if failures else "pass", "baseline": entry["metrics"], "tolerances": tolerances,
            "metrics": current, "failures": failures}


def load_baseline(path: Path) -> dict:
    """A baseline file, checked for the shape the gate reads; ConfigError naming the file otherwise."""
    try:
        baseline = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(f"{path}: not a readable baseline ({type(e).__name__}: {e})") from None
    entries = baseline.get("datasets") if isinstance(baseline, dict) else None
    if not isinstance(entries, dict) or not all(isinstance(e, dict) and isinstance(e.get("metrics"), dict)
                                                for e in entries.values()):
        raise ConfigError(f"{path}: a baseline needs a 'datasets' mapping of entries with 'metrics'")
    if not isinstance(baseline.get("tolerances", {}), dict):
        raise ConfigError(f"{path}: 'tolerances' must be a mapping")
    return baseline


# --------------------------------------------------------------------------------------------- reports
def _f(x, spec: str) -> str:
    return "—" if x is None else format(x, spec)


def format_markdown(result: dict) -> str:
    o, c = result["ours"], result["colmap"]
    lines = [f"## {result['dataset']}: fullview vs COLMAP ({result['render_type']}, pycolmap {result['pycolmap']})",
             "", "| | fullview | COLMAP |", "|---|---|---|",
             f"| registered images | {o['registered']}/{o['images']} | {c['registered']}/{c['images']} |",
             f"| 3-D points | {o['points']} | {c['points']} |",
             f"| mean track length | {o['mean_track_length']:.2f} | {c['mean_track_length']:.2f} |",
             f"| median reprojection error (°) | {_f(o['median_reprojection_error_deg'], '.4f')} | "
             f"{_f(c['median_reprojection_error_deg'], '.4f')} |",
             f"| wall time (s) | {_f(o['wall_time_s'], '.1f')} | {_f(c['wall_time_s'], '.1f')} |"]
    gt = result.get("ground_truth")
    if gt:
        for key, label in (("auc@0.5", "AUC@0.5°"), ("auc@1", "AUC@1°"), ("auc@5", "AUC@5°"),
                           ("median_relative_rotation_error_deg", "GT median rel. rotation error (°)"),
                           ("median_translation_direction_error_deg", "GT median transl. direction error (°)")):
            lines.append(f"| {label} | {_f(gt['ours'].get(key), '.4f')} | {_f(gt['colmap'].get(key), '.4f')} |")
    a = result["agreement"]
    lines += ["", f"Agreement over {a['pairs_compared']}/{a['pairs_total']} pairs registered by both:", "",
              "| | median | max |", "|---|---|---|",
              f"| relative rotation (°) | {_f(a['rotation_median_deg'], '.4f')} | {_f(a['rotation_max_deg'], '.4f')} |",
              f"| translation direction (°) | {_f(a['translation_median_deg'], '.4f')} | "
              f"{_f(a['translation_max_deg'], '.4f')} |"]
    al = result.get("alignment")
    if al:
        lines.append(f"| absolute rotation after rotation alignment (°) | {al['rotation_median_deg']:.4f} | "
                     f"{al['rotation_max_deg']:.4f} |")
        lines.append(f"| centre after similarity alignment (× scene size) | {al['center_median_rel']:.2e} | "
                     f"{al['center_max_rel']:.2e} |")
    g = result["gate"]
    lines += ["", f"Baseline gate: **{g['status']}**" + (f" ({g['reason']})" if g.get("reason") else "")]
    lines += [f"- {f}" for f in g.get("failures", [])]
    return "\n".join(lines) + "\n"


def plot_top_view(path: Path, ours: dict, theirs: dict, sim, names: list[str], *, title: str) -> Path:
    """Camera centres of both models in COLMAP's frame (ours aligned), seen from above."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c_theirs = theirs["centers"][theirs["registered"]]
    c_ours = sim.apply(ours["centers"][ours["registered"]]) if sim is not None else ours["centers"][ours["registered"]]
    R_ours = ours["R_cam_from_world"][ours["registered"]] @ sim.R.T if sim is not None else \
        ours["R_cam_from_world"][ours["registered"]]
    R_all = np.concatenate([theirs["R_cam_from_world"][theirs["registered"]], R_ours])
    ref = c_theirs if len(c_theirs) else c_ours
    basis = cmp.top_view_basis(ref, cmp.camera_up(R_all)) if len(R_all) else np.eye(3)[:2]
    fig, ax = plt.subplots(figsize=(6, 6))
    if len(c_theirs):
        p = (c_theirs - ref.mean(0)) @ basis.T
        ax.plot(p[:, 0], p[:, 1], "s", ms=9, mfc="none", mec="tab:blue", label="COLMAP")
        for k, xy in zip(np.flatnonzero(theirs["registered"]), p):
            ax.annotate(Path(names[k]).stem, xy, textcoords="offset points", xytext=(6, 6), fontsize=7)
    if len(c_ours):
        q = (c_ours - ref.mean(0)) @ basis.T
        ax.plot(q[:, 0], q[:, 1], "o", ms=4, color="tab:red", label="fullview (aligned)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("first principal axis")
    ax.set_ylabel("second principal axis")
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path
