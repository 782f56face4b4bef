"""Stage 7 — dense reconstruction by rectified spherical disparity: one range map per panorama and a fused cloud.

1. Stereo pairs: each camera's best partners (inlier count, triangulation angle at its median sparse depth).
2. Per pair (``fullview.sfm.dense.densify_pair``): rectify, SGBM with a left-right check, law-of-sines ranges,
   back to both panoramas. The disparity search covers depths down to the nearest plausible one, taken from the
   sparse points (a low percentile of the camera-to-point distances), since the model's scale is arbitrary.
2a. Ground sweep (``densify.ground_sweep``, ``fullview.sfm.dense.ground_sweep``): where no ceiling spans over the
   cameras (outdoors: ``ground_sweep.indoor_or_outdoor``, the highest points around the cameras taller than a room;
   the decision and its evidence are logged and kept in the summary's ``scene``), each pair's pixels below the
   horizon are matched again under hypotheses of ground-parallel planes (plane-induced warps, NCC, a unique peak, a
   left-right check), so the near and slanted ground is matched as if fronto-parallel and without a disparity cap;
   its range is taken where SGBM has none or one it disagrees with, and goes through the same conditioning and
   checks as SGBM's.
3. Per panorama: the pair estimates are combined (median of the agreeing ones; pixels whose estimates conflict are
   dropped).
3a. Stereo check (``densify.stereo_check``): where a panorama's pair estimates conflict, the one its neighbours'
   stereo confirms is taken where the fills leave the pixel empty (``densify.resolve_conflicts``); a range resting
   on one pair that a neighbouring panorama's stereo sees clearly beyond (or puts a surface in front of), with no
   neighbour confirming it, is dropped from the saved map after the fills (which still see it: it bounds their
   image regions).
3b. Textureless regions (``densify.fill_planes``, ``fullview.sfm.dense.planes``): each edge-bounded region whose
   border depths lie on planes gets them where the views do not contradict it (a nearly level plane made
   exactly so, ``densify.region_plane_snap_deg``), and a filled pixel is kept only where another panorama's own
   result (stereo, else its own fill) agrees; a region whose fill a kept level world plane (3c) matches takes it
   (``densify.region_planes_from_world``).
3c. World planes (``densify.world_planes``, ``fullview.sfm.dense.world_planes``): the dominant level and upright planes
   of the whole model (RANSAC on every panorama's stereo points and the sparse points; level ones made exactly level,
   walls turned onto the dominant wall direction, ``densify.world_plane_snap_deg``; the ground refitted with a tilt
   where it slopes, ``densify.ground_max_tilt_deg``), each within the extent its
   points support (a wall's columns carried to the floor and the ceiling, ``densify.walls_floor_to_ceiling``) minus
   what the views' confirmed stereo sees through (``densify.free_space_confirmed``); a pixel still empty gets the
   nearest such plane its ray meets, among those its image region's stereo depths support (a ceiling that spans over
   the camera needs none, ``densify.free_ceiling``, ``densify.ceiling_over_camera``; a wall may instead be
   bracketed by the ranges next to the pixel in its image column or row, ``densify.wall_brackets``; in a room, a
   pixel still empty may take the floor under the camera where that is the first plane its ray meets,
   ``densify.free_floor``, or the first plane its ray meets where that is a wall, ``densify.free_walls``), kept under
   the same view checks (by confirmed stereo) and confirmation as 3b.
   The maps are saved as ``depth/<stem>.npz``
   (``range``, ``valid``) and a colour-mapped ``depth/<stem>.png``.
4. Fusion: every panorama's points are kept where the nearest other panoramas agree, voxel down-sampled per
   panorama (bounded memory), then merged, cleaned (statistical outliers), given normals and written to
   ``dense.ply``; ``dense_preview.png`` renders it.

Panoramas are never upsampled: the working width is at most the native width.

Threads: pairs run two at a time, the per-panorama steps (region fill, world fill, confirmation, fusion) on a pool
of local threads, the world planes are found in a forked child process while the stereo check and the region fill
run (their pools leave the child a core while it works, ``protocol.thread_map``), open3d is imported on a side thread while the fusion checks the points, the cloud is cleaned in a child
process while the maps are saved on the side thread and each point's observing camera (the mesh's normals) is found,
the cloud's preview is drawn on the side thread while the mesh's Poisson runs in a child process, and BLAS keeps one
thread; every result is gathered in a fixed order, so
the outputs are the same bytes on any number of threads (``tests/test_densify_stage.py``). ``phases_s`` in the
manifest's summary (not in ``summary.json``: a hashed output holds no timings) gives each phase's wall and CPU seconds (the process's and its reaped children's: a side thread's or a
child's count in the phase it ends in).
"""

from __future__ import annotations

import ctypes
import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import nullcontext
from functools import partial
from typing import Callable

import cv2
import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from fullview.io.config import ConfigError
from fullview.io.render import colorize_range, render_point_cloud
from fullview.sfm import dense
from fullview.sfm.camera import camera_center, camera_up
from fullview.sfm.dense import ground_sweep, planes, world_planes
from fullview.sfm.dense import (apply_mask, camera_depths, fusion_neighbours,
                                mask_below_latitude, pair_min_depth_ratio, range_error_per_pixel, scene_size)
from fullview.sfm.dense_metrics import backproject_range_map, voxel_downsample
from fullview.sfm.open3d_module import open3d
from fullview.sfm.options import DensifyOptions
from fullview.stages import mesh_step
from fullview.stages.protocol import StageContext, cpu_seconds, forked, thread_map

log = logging.getLogger(__name__)

VERSION = 2
UPSTREAM = ("triangulation",)
INPUTS = ("images", "masks")
WORLD_PLANE_CELL_SHARE = 0.04  # extent cells of the world planes: this share of the scene's median depth
DEFAULT_VOXEL_SHARE = 0.002  # voxel size = this share of the scene size when densify.voxel_size is 0
PAIR_THREADS = 2  # stereo pairs densified at once (each holds ~0.2 GB of 2048-px temporaries)


def run(ctx: StageContext) -> dict:
    # the stage runs its own threads over pairs and panoramas; BLAS's threads on top only spin (on 360_Flat they
    # doubled the CPU time of the world planes' RANSAC for the same numbers: each product's rows are split, not
    # summed differently)
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(ctx)


def _run(ctx: StageContext) -> dict:
    t_start = time.perf_counter()
    clock = _Clock()
    config: DensifyOptions = ctx.options
    sparse = ctx.ws.load_sparse_model(0)
    names = ctx.dataset.image_names
    R, t, centers = sparse["R_cam_from_world"], sparse["t_cam_from_world"], sparse["centers"]
    registered = sparse["registered"].astype(bool)
    near, median_depth = camera_depths(centers, sparse, config.min_depth_percentile)
    pairs = _stereo_pairs(ctx.ws.load_epipoles(), centers, registered, median_depth, config)
    if not len(pairs):
        raise ConfigError(f"densify: no stereo pair satisfies the selection ({len(names)} images, "
                          f"{int(registered.sum())} registered); lower densify.min_triangulation_angle_deg "
                          "or densify.min_pair_inliers")
    cams = sorted(set(pairs.ravel().tolist()))
    native = min(ctx.dataset.image_sizes[names[k]][0] for k in cams)
    width = min(config.working_width or native, native)  # never upsample
    log.info("densify: %d stereo pairs over %d panoramas at %dx%d: %s", len(pairs), len(cams), width, width // 2,
             ", ".join(f"{i}-{j}" for i, j in pairs))
    images = dict(zip(cams, thread_map(lambda k: ctx.dataset.load_image(names[k], width=width), cams)))
    clock.lap("load")
    scene = scene_kind(sparse, cams)
    log.info("scene %s", scene.reason)
    sweep = _ground_sweep_setup(config, R, centers, cams, sparse["points"], scene)
    maps, singles, conflicts, pair_log = _range_maps(ctx, images, R, t, near, pairs, sweep)
    clock.lap("stereo")
    # the world planes come from the combined stereo alone (not from the stereo check's settlements and drops,
    # applied after the fills): found in a child process forked now (no other thread at work) while the stereo
    # check and the region fill run here; in a thread, its Python held the GIL against theirs
    fill = _FillInputs(ctx, images, maps, R, t, centers) if config.fill_planes or config.world_planes else None
    # (the options are read here: the child's reads would not be seen by tests/test_settings.py)
    with forked(_world_planes, _world_plane_options(config, fill.options, float(np.nanmedian(median_depth))),
                config.seed, fill.views, sparse["points"]) \
            if fill is not None and config.world_planes else nullcontext() as world:
        settled = _resolve_conflicts(config, maps, singles, conflicts, R, t, centers) \
            if config.stereo_check and config.resolve_conflicts else {}
        unconfirmed = _seen_through_stereo(config, maps, singles, R, t, centers) if config.stereo_check else {}
        del singles, conflicts
        clock.lap("stereo_check")
        filled = _fill_textureless(ctx, fill, maps, world) if fill is not None else {}
    for k, drop in unconfirmed.items():  # the fills have seen them: they bounded the image regions (module doc, 3a)
        maps[k] = (np.where(drop, np.nan, maps[k][0]).astype(np.float32), maps[k][1] & ~drop)
    for k, (pixels, values) in settled.items():  # where the fills left the pixel empty
        rng, valid = maps[k]
        empty = ~valid.ravel()[pixels]
        rng.ravel()[pixels[empty]], valid.ravel()[pixels[empty]] = values[empty], True
    clock.lap("fill")
    _release_freed_memory()
    checkers = min(config.fusion_views, len(maps) - 1)
    if config.min_consistent > checkers:
        raise ConfigError(f"densify.min_consistent={config.min_consistent}: a point can be checked by at most "
                          f"{checkers} other panorama(s) here (densify.fusion_views={config.fusion_views}, "
                          f"{len(maps)} range maps); no point could be kept")
    with ThreadPoolExecutor(max_workers=1) as side:
        # open3d (the cloud's cleaning at the fusion's end, the mesh) takes 0.3 CPU s to import without its plotly
        # drawing (``sfm.open3d_module``; 0.65 with it): imported on the side thread while the panoramas' points are
        # checked, not on the serial cleaning (not earlier either: its memory would come on top of the stereo's
        # peak); a failed import fails again where open3d is used
        imported = side.submit(open3d)
        saved = []

        def while_cleaning(merged: np.ndarray) -> np.ndarray | None:
            # the maps are saved on the side thread and each point's observing camera (the mesh's normals) found
            # here while the cloud is cleaned in a child process (open3d holds the GIL throughout)
            saved.append(side.submit(lambda: [ctx.out.save_depth(names[k], *maps[k], colorize_range(*maps[k]))
                                              for k in sorted(maps)]))
            return mesh_step.observing_cameras(ctx, merged, R, t, maps)

        points, colors, normals, voxel, observers = _fuse(config, images, maps, R, t, centers, sparse, imported,
                                                          while_cleaning)
        clock.lap("fusion_and_saving")
        _release_freed_memory()
        # the mesh's Poisson runs on one thread (reproducible), in a child process: meanwhile the side thread draws
        # the cloud's preview (both only read the cloud)
        preview = side.submit(render_point_cloud, ctx.out.path("dense_preview"), points, colors, normals=normals,
                              up=camera_up(R[cams]), cameras=centers[cams],
                              title=f"{ctx.dataset.name}: {len(points)} points") \
            if config.preview and len(points) >= 3 else None
        mesh = mesh_step.write_dense_mesh(ctx, points, colors, normals, R, t, maps, voxel, observers)
        for job in (preview, *saved):
            if job is not None:
                job.result()
    clock.lap("mesh_and_previews")
    log.debug("densify phases (wall / CPU s): %s", ", ".join(f"{k} {v['wall']} / {v['cpu']}" for k, v in clock.phases.items()))
    summary = {
        "pairs": int(len(pairs)), "panoramas": len(maps), "points": int(len(points)), "voxel_size": voxel,
        "width": int(width), "median_pair_time_s": float(np.median([p["time_s"] for p in pair_log])),
        "valid_share": {names[k]: float(np.mean(m[1])) for k, m in maps.items()},
        "filled_share": filled,
        "stereo_dropped_share": {names[k]: float(np.mean(drop)) for k, drop in unconfirmed.items()},
        "scene": {**scene.as_dict(), "ground_sweep": sweep is not None,
                  "cameras": dict(zip((names[k] for k in cams), scene.cameras))},
        "pair_log": pair_log,
        "mesh": mesh,
        "phases_s": clock.phases,
    }
    summary["wall_time_s"] = round(time.perf_counter() - t_start, 2)  # mesh included
    # summary.json is a hashed output, the same bytes on every run of the same inputs: its figures without the
    # times and memory (which the manifest's summary keeps, beside the stage's own wall time)
    ctx.out.save_dense(points=points, colors=colors, normals=normals, summary=_without_timings(summary))
    return summary


TIMING_KEYS = frozenset({"time_s", "timings_s", "cpu_time_s", "wall_time_s", "phases_s", "median_pair_time_s",
                         "process_peak_rss_mb"})  # what varies from run to run of the same inputs


def _without_timings(summary):
    """`summary` with every TIMING_KEYS entry left out, at any depth."""
    if isinstance(summary, dict):
        return {k: _without_timings(v) for k, v in summary.items() if k not in TIMING_KEYS}
    if isinstance(summary, list):
        return [_without_timings(v) for v in summary]
    return summary


def _release_freed_memory() -> None:
    """Hand the memory the stage's threads have freed back to the system: glibc keeps a heap per thread and returns
    its free blocks only when asked, and the mesh's peak would come on top of them."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to do
        pass


class _Clock:
    """Wall and process CPU seconds of each phase of the stage (summary ``phases_s``; with the child processes'
    the phase reaped, the mesh's Poisson): the CPU seconds do not depend on the machine's load, and CPU / wall tells
    how busy the phase kept the cores."""

    def __init__(self):
        self.phases: dict[str, dict[str, float]] = {}
        self._last = (time.perf_counter(), cpu_seconds())

    def lap(self, phase: str) -> None:
        now = (time.perf_counter(), cpu_seconds())
        self.phases[phase] = {"wall": round(now[0] - self._last[0], 2), "cpu": round(now[1] - self._last[1], 2)}
        self._last = now


# ------------------------------------------------------------------------------------------------ pairs and depth
def _stereo_pairs(epi: dict, centers, registered, median_depth, config: DensifyOptions) -> np.ndarray:
    """(M, 2) global camera indices (i < j) of the stereo pairs among the registered cameras."""
    n = len(centers)
    inliers = np.zeros((n, n))
    ok = epi["valid"].astype(bool)
    i, j = epi["pairs"][ok].T
    inliers[i, j] = inliers[j, i] = epi["num_inliers"][ok]
    idx = np.flatnonzero(registered)
    depths = median_depth[idx]
    if np.isfinite(depths).any():
        depths = np.where(np.isfinite(depths), depths, np.nanmedian(depths))
    pairs = dense.select_stereo_pairs(
        centers[idx], inliers[np.ix_(idx, idx)], k=config.neighbours,
        min_triangulation_angle_deg=config.min_triangulation_angle_deg,
        max_triangulation_angle_deg=config.max_triangulation_angle_deg, min_inliers=config.min_pair_inliers,
        min_epipole_separation_deg=config.min_epipole_separation_deg,
        scene_depths=depths if np.isfinite(depths).all() else None)
    return idx[pairs] if len(pairs) else np.zeros((0, 2), np.intp)


def _range_maps(ctx: StageContext, images, R, t, near, pairs, sweep=None):
    """Densify every pair (two at a time on local threads: rectification, SGBM and the back-mapping run in OpenCV
    and numpy without the GIL); combine each panorama's estimates, in pair order, as soon as its last pair is done
    (the same maps as one pair after the other).

    Returns ({camera: (range float32 NaN-invalid, valid bool)}, {camera: ``dense.single_partner`` map}, {camera:
    (its observable pixels whose pair estimates conflict, their estimates, the partners)} (both with
    ``densify.stereo_check``), per-pair log)."""
    config: DensifyOptions = ctx.options
    names = ctx.dataset.image_names
    remaining = {k: int(np.sum(pairs == k)) for k in np.unique(pairs)}
    estimates: dict[int, list[np.ndarray]] = {k: [] for k in remaining}
    errors: dict[int, list[np.ndarray]] = {k: [] for k in remaining}
    partners: dict[int, list[int]] = {k: [] for k in remaining}
    maps, singles, conflicts, pair_log = {}, {}, {}, []
    # never upsample: the rectified grid spans 180° in at most as many rows as the panoramas have
    rect_height = min(config.rect_height, min(image.shape[0] for image in images.values()))
    work = partial(_densify_pair, config, images, R, t, near, rect_height, sweep)
    for (i, j), (res, pair_errors, kept, ratio, baseline, elapsed, swept) in tqdm(zip(
            pairs, thread_map(work, [tuple(p) for p in pairs], threads=PAIR_THREADS)), total=len(pairs),
            desc="densify", unit="pair"):
        pair_log.append({"pair": [names[i], names[j]], "baseline": baseline, "min_depth_ratio": ratio,
                         "num_disparities": dense.disparity_search_range(rect_height, ratio),
                         "valid_i": float(res.valid_i.mean()), "valid_j": float(res.valid_j.mean()),
                         "well_conditioned_i": kept[0], "well_conditioned_j": kept[1],
                         "ground_sweep_i": swept[0], "ground_sweep_j": swept[1],
                         "time_s": round(elapsed, 3), "timings_s": {k: round(v, 3) for k, v in res.timings.items()}})
        log.debug("pair %s-%s: baseline %.3f, depth ratio %.2f, valid %.0f%% / %.0f%% (well conditioned %.0f%% / "
                  "%.0f%%), %.1f s", names[i], names[j], baseline, ratio, 100 * res.valid_i.mean(),
                  100 * res.valid_j.mean(), 100 * kept[0], 100 * kept[1], elapsed)
        for cam, other, rng, err in ((i, j, res.range_i, pair_errors[0]), (j, i, res.range_j, pair_errors[1])):
            estimates[cam].append(rng)
            errors[cam].append(err)
            partners[cam].append(int(other))
            remaining[cam] -= 1
            if remaining[cam] == 0:
                keep = _observable(config, ctx.dataset.load_mask(names[cam]), rng.shape)
                if config.stereo_check:
                    singles[cam] = dense.single_partner(estimates[cam], partners[cam])
                combined, valid, pixels, candidates = dense.combine_with_conflicts(
                    estimates.pop(cam), config.combine_tolerance, errors.pop(cam))
                if config.stereo_check:
                    inside = keep.ravel()[pixels]
                    conflicts[cam] = (pixels[inside], candidates[:, inside], partners[cam])
                maps[cam] = (np.where(keep, combined, np.nan).astype(np.float32), valid & keep)
    return maps, singles, conflicts, pair_log


def _resolve_conflicts(config: DensifyOptions, maps, singles, conflicts, R, t, centers
                       ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per panorama, the conflicting pair estimates its neighbours settle (``fusion.resolve_conflicts``; module doc,
    step 3a): (flat pixel indices, ranges), all judged by the maps as combined (one panorama per local thread)."""
    cams = sorted(maps)
    ranges = [maps[k][0] for k in cams]
    neighbours = fusion_neighbours(centers[cams], config.fusion_views)
    settled = dict(zip(cams, thread_map(lambda a: dense.resolve_conflicts(
        ranges, [singles[k] for k in cams], cams, R[cams], t[cams], neighbours, config.consistency_tolerance, a,
        *conflicts[cams[a]]), range(len(cams)))))
    log.debug("conflicting pair estimates settled: %s", ", ".join(
        f"{k} {100 * len(p) / maps[k][0].size:.1f}%" for k, (p, _) in settled.items()))
    return settled


def _seen_through_stereo(config: DensifyOptions, maps, singles, R, t, centers) -> dict[int, np.ndarray]:
    """Per panorama, the stereo ranges resting on one pair that a neighbouring panorama's stereo sees through (or
    puts a surface in front of) and none confirms (``fusion.seen_through_single_estimates``; module doc, step 3a),
    one panorama per local thread."""
    cams = sorted(maps)
    ranges = [maps[k][0] for k in cams]
    neighbours = fusion_neighbours(centers[cams], config.fusion_views)
    points = list(thread_map(lambda k: backproject_range_map(maps[k][0], R[k], t[k], stride=2), cams))
    drops = thread_map(lambda a: dense.seen_through_single_estimates(
        ranges, [singles[k] for k in cams], cams, R[cams], t[cams], neighbours, config.consistency_tolerance,
        views=[a], points=points)[0], range(len(cams)))
    drops = dict(zip(cams, drops))
    log.debug("stereo check: %s", ", ".join(f"{k} {100 * d.mean():.1f}%" for k, d in drops.items()))
    return drops


def _densify_pair(config: DensifyOptions, images, R, t, near, rect_height: int, sweep, pair: tuple[int, int]):
    """One stereo pair (``_range_maps``): its ``PairDepth`` (with the ground sweep's ranges, ``_add_ground_sweep``,
    when ``sweep`` is set) with the ill-conditioned ranges dropped, the expected relative range error per pixel of
    both maps, their well-conditioned shares, the depth ratio, the baseline and the time taken."""
    i, j = pair
    baseline = float(np.linalg.norm(camera_center(R[i], t[i]) - camera_center(R[j], t[j])))
    ratio = pair_min_depth_ratio(near[i], near[j], baseline, config.min_depth_factor, config.max_disparity_deg)
    params = dense.SgbmParams(block_size=config.block_size, min_texture_std=config.min_texture_std)
    t0 = time.perf_counter()
    res = dense.densify_pair(images[i], images[j], R[i], t[i], R[j], t[j], rect_height=rect_height,
                             out_width=images[i].shape[1], min_depth_ratio=ratio,
                             min_epipole_angle_deg=config.epipole_margin_deg, params=params,
                             latitudes_deg=(config.min_latitude_deg, config.max_latitude_deg))
    swept = _add_ground_sweep(images, R, t, sweep, pair, res) if sweep is not None else (0.0, 0.0)
    elapsed = time.perf_counter() - t0
    pair_errors, kept = [], []
    for cam, other, rng in ((i, j, res.range_i), (j, i, res.range_j)):
        err = range_error_per_pixel(rng, R[cam], camera_center(R[cam], t[cam]), camera_center(R[other], t[other]),
                                    np.pi / rect_height)
        with np.errstate(invalid="ignore"):
            rng[~(err <= config.max_range_error_per_px)] = np.nan
        kept.append(float(np.isfinite(rng).mean()))
        pair_errors.append(err)
    return res, pair_errors, kept, ratio, baseline, elapsed, swept


def scene_kind(sparse: dict, cams: list[int]) -> ground_sweep.SceneKind:
    """Indoors or outdoors (``ground_sweep.indoor_or_outdoor``) from the points each of ``cams`` sees."""
    return ground_sweep.indoor_or_outdoor(sparse["centers"][cams], sparse["points"],
                                          camera_up(sparse["R_cam_from_world"][cams]), *_observations_of(sparse, cams))


def _observations_of(sparse: dict, cams: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(camera row in ``cams``, point) of every sparse observation by one of ``cams``."""
    row = np.full(len(sparse["registered"]), -1, np.intp)
    row[cams] = np.arange(len(cams))
    mine = row[sparse["image_ids"]] >= 0
    return row[sparse["image_ids"][mine]], np.asarray(sparse["track_ids"][mine], np.intp)


def _ground_sweep_setup(config: DensifyOptions, R, centers, cams, sparse_points, scene=None):
    """(up, {camera: height above its ground, NaN where the sparse points do not tell}, the sweep's options, its
    width) for the ground sweep, or None where it does not run (never, or indoors with ``no_ceiling``: there the
    fills own the floor). ``scene``: ``ground_sweep.indoor_or_outdoor`` of the cameras (from ``sparse_points``
    alone, every camera seeing every point, when None)."""
    if config.ground_sweep == "never":
        return None
    options = ground_sweep.GroundSweepOptions(window=config.ground_sweep_window, min_ncc=config.ground_sweep_min_ncc,
                                              min_texture_std=config.min_texture_std,
                                              lr_tolerance=config.combine_tolerance,
                                              min_latitude_deg=config.min_latitude_deg)
    width = config.ground_sweep_width  # read here: the settings are the stage's whether the sweep runs or not
    up = camera_up(R[cams])
    points = np.asarray(sparse_points, np.float64).reshape(-1, 3)
    if scene is None:
        scene = ground_sweep.indoor_or_outdoor(centers[cams], points, up)
    if config.ground_sweep == "no_ceiling" and scene.indoors:
        log.info("ground sweep: off (indoors: a ceiling over the cameras)")
        return None
    heights = ground_sweep.ground_heights(centers[cams], points, up)  # NaN: a coarse sweep of each pair finds it
    log.info("ground sweep: on, camera heights from the sparse points %s", ", ".join(f"{h:.3g}" for h in heights))
    return up, dict(zip(cams, heights.tolist())), options, width


def _add_ground_sweep(images, R, t, sweep, pair: tuple[int, int], res) -> tuple[float, float]:
    """Fill the pair's maps with the ground sweep's ranges (``sfm.dense.ground_sweep``) where SGBM found none or one
    the sweep disagrees with (checked against the other panoramas, the sweep was right 4 times as often), in
    place; the sweep runs at ``ground_sweep_width`` at most and its ranges are resized to the maps (nearest).
    Returns the share of each map it set."""
    i, j = pair
    up, heights, options, width = sweep
    shape = res.range_i.shape
    width = min(width, images[i].shape[1])
    small = [cv2.resize(images[k], (width, width // 2), interpolation=cv2.INTER_AREA)
             if images[k].shape[1] != width else images[k] for k in pair]
    t0 = time.perf_counter()
    swept = ground_sweep.ground_sweep_pair(*small, R[i], t[i], R[j], t[j], up, heights[i], heights[j], options)
    shares = []
    for (rng, valid), ground in zip(((res.range_i, res.valid_i), (res.range_j, res.valid_j)), swept):
        if ground.shape != shape:
            ground = cv2.resize(ground, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
        with np.errstate(invalid="ignore"):  # where SGBM disagrees with the sweep, the sweep is taken (README)
            new = np.isfinite(ground) & (~valid | (np.abs(rng - ground) > options.lr_tolerance * ground))
        rng[new], valid[new] = ground[new], True
        shares.append(float(new.mean()))
    res.timings["ground_sweep"] = time.perf_counter() - t0
    return shares[0], shares[1]


# ------------------------------------------------------------------------------------------------ textureless
class _FillInputs:
    """What the fills of a stage's panoramas share (``cams``: the cameras with a range map, in order): each one's
    observable area and reduced view (stereo ranges as combined), the views checking it, the plane options."""

    def __init__(self, ctx: StageContext, images, maps, R, t, centers):
        config: DensifyOptions = ctx.options
        self.cams = sorted(maps)
        self.neighbours = fusion_neighbours(centers[self.cams], config.fusion_views)
        self.options = planes.PlaneOptions(fit_tolerance=config.plane_tolerance, snap_deg=config.region_plane_snap_deg)
        self.observable = [_observable(config, ctx.dataset.load_mask(ctx.dataset.image_names[k]), maps[k][0].shape)
                           for k in self.cams]
        self.views = [planes.view_of(R[k], t[k], maps[k][0], self.observable[a], images[k],
                                     min(config.fill_width, maps[k][0].shape[1])) for a, k in enumerate(self.cams)]


def _fill_textureless(ctx: StageContext, inputs: _FillInputs, maps, world) -> dict[str, float]:
    """Fill each range map's textureless regions in place (module doc, step 3b), then the world planes'
    (``world``: the job of ``_world_planes``, or None); returns the filled share per panorama. Only where a
    stereo range could be: inside the latitude caps and the image mask. Every per-panorama step runs on local
    threads (numpy and OpenCV release the GIL); each result depends on its panorama alone."""
    config: DensifyOptions = ctx.options
    names = ctx.dataset.image_names
    cams, views, neighbours, options = inputs.cams, inputs.views, inputs.neighbours, inputs.options
    fills = [(np.full(v.range_map.shape, np.nan, np.float32), np.zeros(v.range_map.shape, np.int32)) for v in views]
    if config.fill_planes:
        fills = list(tqdm(thread_map(lambda a: planes.fill_plane_ranges(
            views[a], [views[b] for b in neighbours[a]], options, config.seed + cams[a]), range(len(cams))),
            total=len(cams), desc="planes", unit="pano"))
    if world is not None:
        # the views judging the planes with their confirmed stereo need no plane: made while the planes are found
        judges = world_planes.confirmed_views(views, neighbours, options.view_tolerance) \
            if config.free_space_confirmed else views
        fills = _fill_world_planes(views, fills, neighbours, options,
                                   *_carved_world_planes(config, views, judges, *world.result()))
    confirmed = list(thread_map(lambda a: planes.confirmed_by_views(
        views[a], *fills[a], [views[b] for b in neighbours[a]], [fills[b][0] for b in neighbours[a]], options),
        range(len(cams))))
    shares = {}
    for a, k in enumerate(cams):
        fill, kept = fills[a][0], confirmed[a]
        rng, valid = maps[k]
        fill = cv2.resize(np.where(kept, fill, np.nan), (rng.shape[1], rng.shape[0]),
                          interpolation=cv2.INTER_NEAREST)
        new = ~valid & np.isfinite(fill) & inputs.observable[a]
        maps[k] = (np.where(new, fill, rng).astype(np.float32), valid | new)
        shares[names[k]] = float(new.mean())
        log.debug("planes: %s %.0f%% filled, %.0f%% valid", names[k], 100 * new.mean(), 100 * np.mean(maps[k][1]))
    return shares


def _world_plane_options(config: DensifyOptions, options: planes.PlaneOptions, median_depth: float
                         ) -> world_planes.WorldPlaneOptions:
    """The world planes' options from the stage's (``median_depth``: the scene's, for the extent cells)."""
    return world_planes.WorldPlaneOptions(distance=config.world_plane_distance,
                                          cell=WORLD_PLANE_CELL_SHARE * median_depth,
                                          view_tolerance=options.view_tolerance, extent=config.world_plane_extent,
                                          snap_deg=config.world_plane_snap_deg, free_ceiling=config.free_ceiling,
                                          sweep_walls=config.sweep_walls,
                                          one_level_per_band=config.one_level_plane_per_band,
                                          one_wall_per_offset=config.one_wall_plane_per_offset,
                                          walls_floor_to_ceiling=config.walls_floor_to_ceiling,
                                          wall_brackets=config.wall_brackets,
                                          ceiling_over_camera=config.ceiling_over_camera,
                                          free_floor=config.free_floor, free_walls=config.free_walls,
                                          occluders_on_walls=config.occlusion_aware_wall_vote,
                                          local_extent=config.wall_extent_by_votes,
                                          adopt_in_regions=config.region_planes_from_world,
                                          room_window_cells=config.room_window_cells,
                                          ground_max_tilt_deg=config.ground_max_tilt_deg)


def _world_planes(wopt: world_planes.WorldPlaneOptions, seed: int, views, sparse_points):
    """The world planes of the model (``sfm.dense.world_planes``) as found: (their options, the planes, how many
    points they were found in, the seconds taken); ``_carved_world_planes`` keeps them."""
    t0 = time.perf_counter()
    points, ranges, observers = _model_points(views, sparse_points)
    up = camera_up(np.array([v.R_cam_from_world for v in views]))
    found = world_planes.detect_world_planes(points, ranges, np.random.default_rng(seed), wopt, up=up,
                                             observers=observers)
    tilted = world_planes.tilt_ground(  # the same list when ground_max_tilt_deg is 0
        found, points, ranges, np.array([camera_center(v.R_cam_from_world, v.t_cam_from_world) for v in views]),
        up, np.random.default_rng(seed), wopt)
    for plane in (p for p in tilted if not any(p is q for q in found)):
        log.debug("world planes: the ground refitted %.2f° from level (%d points; %d level pieces of it dropped)",
                  np.degrees(np.arccos(min(1.0, abs(plane.normal @ up)))), plane.support, len(found) - len(tilted))
    found = tilted
    return wopt, found, len(points), time.perf_counter() - t0


def _carved_world_planes(config: DensifyOptions, views, judges, wopt, found, points: int, seconds: float):
    """The world planes found (``_world_planes``) kept after the free-space check by the ``judges`` (the views with
    their confirmed stereo): (options, planes, the judges, each view's nearest plane per ray or None)."""
    kept = world_planes.carve_extents(found, judges, wopt, map=thread_map)  # each plane on its own
    log.info("world planes: %d found in %d points (%.1f s), %d kept after the free-space check", len(found), points,
             seconds, len(kept))
    occluders = list(thread_map(lambda v: world_planes.nearest_plane_ranges(v, kept, wopt), views)) \
        if config.occlusion_aware_vote else None
    return wopt, kept, judges, occluders


def _fill_world_planes(views, fills, neighbours, options, wopt, kept, judges, occluders):
    """Pixels the region fill left empty get the world plane their ray meets (``sfm.dense.world_planes``); the
    labels of the two fills are kept apart (world plane labels are offset past the region labels). With
    `occluders` (each view's nearest world plane per ray) a view's colour the model says is hidden is no vote."""

    def fill(a: int) -> tuple[np.ndarray, np.ndarray]:
        view, (fill, labels) = views[a], fills[a]
        if wopt.adopt_in_regions:  # a region's own plane gives way to the world plane of the same surface
            fill = world_planes.adopt_world_planes(view, fill, labels, kept, wopt)
        empty = planes.View(R_cam_from_world=view.R_cam_from_world, t_cam_from_world=view.t_cam_from_world,
                            range_map=np.where(np.isfinite(fill), fill, view.range_map), observable=view.observable,
                            color=view.color)
        wfill, wlabels = world_planes.fill_from_world_planes(
            empty, kept, [judges[b] for b in neighbours[a]], wopt, options,
            [occluders[b] for b in neighbours[a]] if occluders is not None else None)
        new = np.isfinite(wfill) & ~np.isfinite(fill)
        return (np.where(new, wfill, fill).astype(np.float32),
                np.where(new, wlabels + labels.max() + 1, labels).astype(np.int32))

    return list(tqdm(thread_map(fill, range(len(views))), total=len(views), desc="world planes", unit="pano"))


def _model_points(views: list[planes.View], sparse_points: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stereo points of all views (every other pixel of the reduced grid) and the sparse points, voxel
    down-sampled at 0.5% of the median range: (points (N, 3), range (N,) from the camera that measured each, that
    camera's centre (N, 3); for a sparse point its nearest camera; both averaged over a voxel)."""
    stereo, stereo_ranges, stereo_observers = planes.stereo_points(views, step=2)
    centers = np.array([camera_center(v.R_cam_from_world, v.t_cam_from_world) for v in views])
    points, ranges, observers = [stereo], [stereo_ranges], [stereo_observers]
    sparse = np.asarray(sparse_points, np.float64).reshape(-1, 3)
    points.append(sparse)
    distances = np.linalg.norm(sparse[:, None] - centers[None], axis=2)
    ranges.append(distances.min(axis=1) if len(sparse) else np.zeros(0))
    observers.append(centers[np.argmin(distances, axis=1)] if len(sparse) else np.zeros((0, 3)))
    points, ranges = np.concatenate(points), np.concatenate(ranges).astype(np.float64)
    voxel = 0.005 * float(np.median(ranges))
    points, attrs = voxel_downsample(points, voxel, np.column_stack([ranges, np.concatenate(observers)]))
    return points, attrs[:, 0], attrs[:, 1:]


def _observable(config: DensifyOptions, mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Where a range map may hold a range: inside the latitude caps and the image mask (True = keep)."""
    anywhere = np.ones(shape, bool)
    inside = mask_below_latitude(np.zeros(shape, np.float32), anywhere, config.min_latitude_deg,
                                 config.max_latitude_deg)[1]
    return apply_mask(np.zeros(shape, np.float32), inside, mask)[1]


# ------------------------------------------------------------------------------------------------ fusion
def _fuse(config: DensifyOptions, images, maps, R, t, centers, sparse, imported: Future | None = None,
          while_cleaning: Callable[[np.ndarray], np.ndarray | None] | None = None):
    """Consistency-checked, voxel-merged, cleaned cloud: (points, RGB colours, normals, voxel size, what
    ``while_cleaning`` gave for the merged points, at the kept ones). Each panorama's points are checked and
    down-sampled on local threads, then merged in panorama order; the cleaning (open3d, ``imported`` on the side
    thread) runs in a child process forked once no other thread is at work, ``while_cleaning`` here meanwhile."""
    cams = sorted(maps)
    voxel = config.voxel_size or DEFAULT_VOXEL_SHARE * scene_size(centers[cams], sparse["points"])
    ranges = [maps[k][0] for k in cams]
    rgb = [images[k][..., ::-1] for k in cams]
    neighbours = fusion_neighbours(centers[cams], config.fusion_views)

    def fuse(v: int) -> tuple[np.ndarray, np.ndarray, int]:
        pts, cols = dense.fuse_depth_maps(ranges, rgb, R[cams], t[cams], min_consistent=config.min_consistent,
                                          rel_tol=config.consistency_tolerance, stride=config.fusion_stride,
                                          neighbors=neighbours, views=[v])
        return *voxel_downsample(pts, voxel, cols), len(pts)

    parts = list(tqdm(thread_map(fuse, range(len(cams))), total=len(cams), desc="fusion", unit="pano"))
    raw = sum(part[2] for part in parts)
    points, colors = voxel_downsample(np.concatenate([part[0] for part in parts]), voxel,
                                      np.concatenate([part[1] for part in parts]))
    log.info("fusion: %d consistent points, %d after voxel merging (voxel %.4g)", raw, len(points), voxel)
    clean = partial(dense.clean_point_cloud, voxel_size=0.0, nb_neighbors=config.outlier_neighbours,
                    std_ratio=config.outlier_std_ratio, normal_radius=3.0 * voxel, viewpoint=centers[cams].mean(0),
                    return_index=True)
    if imported is not None:
        wait([imported])  # no thread at work when forking (a failed import fails again in the cleaning)
    with forked(clean, points, colors) as cleaned:
        found = while_cleaning(points) if while_cleaning is not None else None
        points, colors, normals, kept = cleaned.result()
    return points, colors, normals, float(voxel), (found[kept] if found is not None else None)
