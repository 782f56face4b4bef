"""`fullview colmap-check`: our SIFT stage against COLMAP's SIFT on the very same cube faces.

Everything but the detector/descriptor is held equal: the faces are rendered by `sfm.features.render_faces` from
the same grey image at the same working width, face size and margin (and written as PNG,
`colmap_check/faces/<stem>_<face>.png`, one PINHOLE camera per face size with the face focal length); COLMAP's
keypoints (continuous pixel coordinates, (0, 0) the top-left corner — measured: no half-pixel offset, unlike
OpenCV's) go back to bearings through the face rotation, the same owner-face dedup and latitude mask; COLMAP's
descriptors (uint8, L1-root) are turned into unit float vectors and matched with our `match_descriptors` (ratio
test, mutual check) over our pair list; verification is our unseeded `ransac_f` with the filter stage's threshold,
iterations, confidence, seeds and minimum inlier count. Ours come from the workspace's matches/filter artifacts
(hand correspondences excluded). A pair is flagged where ours fall below half of COLMAP's.

COLMAP's per-face feature cap defaults to ours (`features.max_features_per_face`); `max_features=0` gives COLMAP its
own default (8192 per face). The caps differ in kind: OpenCV's counts keypoints (a second orientation is a second
keypoint), COLMAP's counts locations (each may carry two orientations), so at the same number COLMAP keeps ~1.3x the
locations. Measured on 360_Flat: at a COLMAP cap of 1000 the feature counts match (ours/COLMAP 1.05) and so do the
raw and verified matches (median ratios 1.00 and 0.96).
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from fullview.io.colmap import extract_sift_on_images, pycolmap_version
from fullview.io.render import save_png
from fullview.io.dataset import Dataset
from fullview.io.workspace import StageWriter, Workspace, folder_of
from fullview.sfm import two_view
from fullview.sfm.camera import bearings_to_lonlat
from fullview.sfm.features import FACE_NAMES, face_keypoints_to_bearings, native_face_size, owned_by_face, render_faces
from fullview.sfm.matching import match_descriptors
from fullview.sfm.pairs import select_pairs
from fullview.sfm.options import FilterOptions
from fullview.stages.runner import Pipeline, RunnerError, record_fingerprint

log = logging.getLogger(__name__)

FLAG_RATIO = 0.5  # a pair is flagged where ours < FLAG_RATIO x COLMAP's


def colmap_features(bearing_parts: list[tuple[np.ndarray, int, np.ndarray]], face_size: int, focal: float,
                    min_lat_deg: float, max_lat_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bearings (N,3), unit float32 descriptors (N,128) and face ids of one panorama's COLMAP features.

    `bearing_parts` holds per face (keypoints (K,2) in COLMAP pixel coordinates, face index, uint8 descriptors).
    """
    bearings, descs, faces = [], [], []
    for xy, face, desc in bearing_parts:
        b = face_keypoints_to_bearings(xy, face, face_size, focal)
        keep = owned_by_face(b, face)
        bearings.append(b[keep])
        descs.append(desc[keep])
        faces.append(np.full(int(keep.sum()), face, np.uint8))
    bearings = np.concatenate(bearings) if bearings else np.zeros((0, 3))
    descs = np.concatenate(descs).astype(np.float32) if descs else np.zeros((0, 128), np.float32)
    faces = np.concatenate(faces) if faces else np.zeros(0, np.uint8)
    _, lat = bearings_to_lonlat(bearings)
    keep = (lat >= np.radians(min_lat_deg)) & (lat <= np.radians(max_lat_deg))
    descs = descs[keep]
    descs /= np.maximum(np.linalg.norm(descs, axis=1, keepdims=True), 1e-12)
    return bearings[keep], descs, faces[keep]


def verify(bear_i: np.ndarray, bear_j: np.ndarray, matches: np.ndarray, config: FilterOptions, seed: int) -> int:
    """Inlier count of the filter stage's unseeded verification (0 below its min_inliers)."""
    if len(matches) < 8:
        return 0
    opts = two_view.RansacOptions(threshold_rad=np.radians(config.threshold_deg),
                                  max_iterations=config.max_iterations, confidence=config.confidence, seed=seed)
    try:
        res = two_view.ransac_f(bear_i[matches[:, 0]], bear_j[matches[:, 1]], opts)
    except ValueError:
        return 0
    count = int(res.inliers.sum())
    return count if count >= config.min_inliers else 0


def _ours(dataset: Dataset, ws: Workspace) -> tuple[list, list, list, list, dict[str, int]]:
    """Pairs, raw and verified (SIFT-only) match counts from the matches/filter artifacts, whether the filter seeded
    each pair with hand points, features per image."""
    num_sift = {n: len(ws.load_features(n)["bearings"]) for n in dataset.image_names}
    sift = [num_sift[n] for n in dataset.image_names]
    raw_data, verified_data = ws.load_matches(), ws.load_inliers()
    pairs, raw = raw_data.pairs, raw_data.matches
    inliers, extra = verified_data.matches, verified_data.extra
    if pairs != verified_data.pairs:
        raise RunnerError(f"{ws.root}: matches and filter artifacts disagree on the pair list; rerun filter")
    verified = [int(((m[:, 0] < sift[i]) & (m[:, 1] < sift[j])).sum()) for (i, j), m in zip(pairs, inliers)]
    seeded = [bool(v) for v in extra.get("seeded", np.zeros(len(pairs), bool))]
    return pairs, [len(m) for m in raw], verified, seeded, num_sift


def colmap_check(dataset: Dataset, ws: Workspace, pipeline: Pipeline, *, max_features: int | None = None) -> dict:
    """Run the check; writes colmap_check/{check.json, check.md, faces/, database.db}; returns the report."""
    if max_features is not None and max_features < 0:
        raise RunnerError(f"--colmap-max-features must be >= 0 (0: COLMAP's default), got {max_features}")
    with ws.locked(command="fullview colmap-check"):
        ran = pipeline.run(until="filter")
        log.info("our pipeline until filter: %s", ", ".join(ran) if ran else "fresh")
        with ws.transaction(folder_of("check_report")) as out:
            report = _check(dataset, ws, pipeline, out, max_features)
            out.save_json("check_report", report)
            markdown = format_markdown(report)
            out.save_text("check_markdown", markdown)
            upstream = {s: pipeline.fingerprint(s) for s in ("features", "matches", "filter")}
            out.commit_manifest({"fingerprint": record_fingerprint({**upstream, "cap": report["settings"][
                "colmap_max_features_per_face"]}), "upstream": upstream, "summary": {"flagged": len(report["flagged"])}})
    report["markdown"] = markdown
    return report


def _check(dataset: Dataset, ws: Workspace, pipeline: Pipeline, out: StageWriter, max_features: int | None) -> dict:
    fcfg, mcfg, vcfg = (pipeline.config[s] for s in ("features", "matches", "filter"))
    cap = fcfg.max_features_per_face if max_features is None else max_features
    names = dataset.image_names
    pairs, ours_raw, ours_verified, ours_seeded, ours_features = _ours(dataset, ws)
    descriptors = [ws.load_features(n)["descriptors"] for n in names]
    config_pairs, _ = select_pairs(descriptors, mcfg, dataset.gps_positions())
    if not set(pairs) <= set(config_pairs):  # loop candidates whose round never came are not in the artifact
        raise RunnerError(f"{ws.root}: the matches artifact's pair list differs from the config's; rerun matches")
    geometry, groups = _write_faces(dataset, fcfg, out)
    log.info("COLMAP SIFT (CPU) on %d faces, max %s features per face", sum(map(len, groups.values())),
             cap if cap > 0 else "default")
    faces_dir = out.path("check_face", face="x").parent
    extracted = extract_sift_on_images(faces_dir, out.path("check_database"), groups, max_num_features=cap)
    bearings, descriptors, colmap_counts = [], [], {}
    for name in names:
        face_size, focal = geometry[name]
        empty = (np.zeros((0, 2)), np.zeros((0, 128)))
        faces = [extracted.get(_face_file(name, f), empty) for f in range(6)]
        parts = [(xy, f, desc) for f, (xy, desc) in enumerate(faces)]
        b, d, _ = colmap_features(parts, face_size, focal, fcfg.min_latitude_deg, fcfg.max_latitude_deg)
        bearings.append(b)
        descriptors.append(d)
        colmap_counts[name] = len(b)
    # as in the matches stage: threads over pairs, single-threaded BLAS
    with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        jobs = pool.map(lambda p: match_descriptors(descriptors[p[0]], descriptors[p[1]], mcfg), pairs)
        all_matches = list(tqdm(jobs, total=len(pairs), desc="colmap-check matches", unit="pair"))
        verified_counts = [verify(bearings[i], bearings[j], m, vcfg, seed=vcfg.seed + k)
                           for k, ((i, j), m) in enumerate(zip(pairs, all_matches))]
    rows = []
    for k, (i, j) in enumerate(pairs):
        row = {"pair": [names[i], names[j]], "ours_raw": ours_raw[k], "colmap_raw": int(len(all_matches[k])),
               "ours_verified": ours_verified[k], "colmap_verified": verified_counts[k],
               "ours_seeded": ours_seeded[k]}
        row["flag_raw"] = row["ours_raw"] < FLAG_RATIO * row["colmap_raw"]
        row["flag_verified"] = row["ours_verified"] < FLAG_RATIO * row["colmap_verified"]
        rows.append(row)
    return {"dataset": dataset.name, "pycolmap": pycolmap_version(),
            "settings": {"working_width": fcfg.working_width, "face_size": {n: g[0] for n, g in geometry.items()},
                         "margin_deg": fcfg.margin_deg, "colmap_max_features_per_face": cap,
                         "ours_max_features_per_face": fcfg.max_features_per_face,
                         "latitude_deg": [fcfg.min_latitude_deg, fcfg.max_latitude_deg],
                         "ratio": mcfg.ratio, "mutual": mcfg.mutual, "threshold_deg": vcfg.threshold_deg,
                         "min_inliers": vcfg.min_inliers, "flag_ratio": FLAG_RATIO},
            "features": {n: {"ours": ours_features[n], "colmap": colmap_counts[n]} for n in names},
            "pairs": rows, "flagged": [r["pair"] for r in rows if r["flag_raw"] or r["flag_verified"]]}


def _face_file(name: str, face: int) -> str:
    return f"{Path(name).stem}_{FACE_NAMES[face]}.png"


def _write_faces(dataset: Dataset, fcfg, out: StageWriter) -> tuple[dict, dict]:
    """Render every panorama's cube faces as PNG; returns per image (face size, focal) and the faces grouped by
    camera parameters (one COLMAP PINHOLE camera per group)."""
    geometry, groups = {}, {}
    for name in tqdm(dataset.image_names, desc="faces", unit="image"):
        full_w, _ = dataset.image_sizes[name]
        image = dataset.load_image(name, width=min(fcfg.working_width or full_w, full_w))
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        face_size = fcfg.face_size or native_face_size(grey.shape[1], fcfg.margin_deg)
        faces, focal = render_faces(grey, face_size, fcfg.margin_deg)
        geometry[name] = (face_size, focal)
        params = f"{focal:.17g},{focal:.17g},{face_size / 2:.17g},{face_size / 2:.17g}"
        for f, face in enumerate(faces):
            face_name = _face_file(name, f)
            save_png(out.path("check_face", face=Path(face_name).stem), face)
            groups.setdefault(params, []).append(face_name)
    return geometry, groups


def format_markdown(report: dict) -> str:
    s = report["settings"]
    cap = s["colmap_max_features_per_face"]
    lines = [f"## {report['dataset']}: our SIFT vs COLMAP SIFT (pycolmap {report['pycolmap']}) on the same cube faces",
             "", f"Working width {s['working_width']}, margin {s['margin_deg']}°, features per face: ours ≤ "
             f"{s['ours_max_features_per_face']}, COLMAP ≤ {cap if cap > 0 else 'default (8192)'}; ratio "
             f"{s['ratio']}, mutual {s['mutual']}; F-RANSAC {s['threshold_deg']}°, min {s['min_inliers']} inliers. "
             f"⚠ = ours < {s['flag_ratio']:g} × COLMAP's. (OpenCV's cap counts keypoints, COLMAP's counts "
             f"locations, each with up to two orientations.)", "",
             "| pair | ours raw | COLMAP raw | ours verified | COLMAP verified | verified ratio | flag |",
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in report["pairs"]:
        ratio = r["ours_verified"] / r["colmap_verified"] if r["colmap_verified"] else None
        flag = " ".join(x for x, on in (("⚠ raw", r["flag_raw"]), ("⚠ verified", r["flag_verified"])) if on)
        a, b = (Path(p).stem for p in r["pair"])
        b += "*" if r.get("ours_seeded") else ""
        lines.append(f"| {a}–{b} | {r['ours_raw']} | {r['colmap_raw']} | {r['ours_verified']} | "
                     f"{r['colmap_verified']} | {'—' if ratio is None else f'{ratio:.2f}'} | {flag} |")
    if any(r.get("ours_seeded") for r in report["pairs"]):
        lines += ["", "\\* our filter seeded this pair with hand points (COLMAP's side: unseeded LO-MSAC)."]
    lines += ["", "| image | ours features | COLMAP features |", "|---|---:|---:|"]
    for name, c in report["features"].items():
        lines.append(f"| {Path(name).stem} | {c['ours']} | {c['colmap']} |")
    lines += ["", f"Flagged pairs: {len(report['flagged'])} of {len(report['pairs'])}"]
    return "\n".join(lines) + "\n"
